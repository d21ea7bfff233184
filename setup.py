from setuptools import Extension, setup, find_packages


def kernel(module, exact=False, headers=()):
    """A compiled kernel: plain C99, no Python API, loaded with ctypes by its Python module;
    pip install -e . builds it in place next to the package.  ``exact``: no fused multiply-adds,
    so that its arithmetic is the numpy path's bit for bit.  ``headers``: the files it
    includes (next to it), which rebuild it when they change."""
    folder = module.rsplit(".", 1)[0].replace(".", "/")
    return Extension(module, sources=[module.replace(".", "/") + ".c"],
                     depends=[f"{folder}/{h}" for h in headers],
                     extra_compile_args=["-O3", "-std=c99"]
                     + (["-ffp-contract=off"] if exact else []),
                     libraries=["m"])


KERNELS = [
    # the fused elastic element kernel (rodsnes/model/elastic_compiled.py): the 3-D element
    # (_elastic_lanes.h) and the in-plane tangent (_elastic_plane.h) on 1, 2 or 4 elements at once
    kernel("rodsnes.model._elastic_kernel",
           headers=["_elastic_lanes.h", "_elastic_plane.h", "_element_blocks.h"]),
    # the pair-potential contact kernel (rodsnes/contact/potential_compiled.py)
    kernel("rodsnes.contact._potential_kernel", exact=True),
    # the Gauss double integral of writhe and link (rodsnes/model/topology.py): O(N^2) segment
    # pairs, the link check of every load step and the writhe of every summary
    kernel("rodsnes.model._topology_kernel"),
    # the nodes' rotations exp(theta) q (rodsnes/model/so3_compiled.py): at every iterate of a
    # large rod the quaternion arithmetic of numpy cost 4 x the sines and cosines
    kernel("rodsnes.model._rotation_kernel", exact=True),
    # element tangents added straight into a block matrix's values (rodsnes/model/assembly.py):
    # the places of the blocks found once per pattern, no search per insertion
    kernel("rodsnes.model._assembly_kernel", headers=["_element_blocks.h"]),
    # the contact search's element bounds and segment distances (search_compiled.py)
    kernel("rodsnes.contact._search_kernel", exact=True),
    # a rank's stretch of a rod factored without fill, its inverse's trailing block without a
    # whole substitution, the pivot blocks' inertia (rodsnes/solve/chain.py)
    kernel("rodsnes.solve._chain_kernel"),
]

setup(
    name="rodsnes",
    version="0.1.0",
    description="Parallel Newton solver for Cosserat rods with frictionless self-contact (PETSc)",
    packages=find_packages(include=["rodsnes", "rodsnes.*"]),
    python_requires=">=3.9",
    # petsc4py, mpi4py, h5py (MPI), meshio, scipy, matplotlib come from Debian packages
    # (see tools/install_system.sh); only what Debian lacks is pulled from PyPI.
    install_requires=["numpy", "pymetis", "typing_extensions"],
    entry_points={"console_scripts": ["rodsnes = rodsnes.cli:main"]},
    ext_modules=KERNELS,
)
