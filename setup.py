from setuptools import Extension, setup, find_packages

# The fused elastic element kernel: plain C, no Python API, loaded with ctypes
# (rodsnes/model/elastic_compiled.py); pip install -e . builds it in place next to the package.
elastic_kernel = Extension(
    "rodsnes.model._elastic_kernel",
    sources=["rodsnes/model/_elastic_kernel.c"],
    extra_compile_args=["-O3", "-std=c99"],
    libraries=["m"],
)

# The pair-potential contact kernel (rodsnes/contact/potential_compiled.py), the same way; no fused
# multiply-adds, so that its distances are the numpy path's bit for bit.
potential_kernel = Extension(
    "rodsnes.contact._potential_kernel",
    sources=["rodsnes/contact/_potential_kernel.c"],
    extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off"],
    libraries=["m"],
)

# The Gauss double integral of writhe and link (rodsnes/model/topology.py), the same way: O(N^2)
# segment pairs, the link check of every load step and the writhe of every summary.
topology_kernel = Extension(
    "rodsnes.model._topology_kernel",
    sources=["rodsnes/model/_topology_kernel.c"],
    extra_compile_args=["-O3", "-std=c99"],
    libraries=["m"],
)

# The nodes' rotations exp(theta) q (rodsnes/model/so3_compiled.py), the same way: at every
# iterate of a large rod the quaternion arithmetic of numpy cost 4 x the sines and cosines.
rotation_kernel = Extension(
    "rodsnes.model._rotation_kernel",
    sources=["rodsnes/model/_rotation_kernel.c"],
    extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off"],
    libraries=["m"],
)

# Element tangents added straight into a block matrix's values (rodsnes/model/assembly.py),
# the same way: the places of the blocks found once per pattern, no search per insertion.
assembly_kernel = Extension(
    "rodsnes.model._assembly_kernel",
    sources=["rodsnes/model/_assembly_kernel.c"],
    extra_compile_args=["-O3", "-std=c99"],
)

# The contact search's element bounds and segment distances (rodsnes/contact/search_compiled.py),
# the same way, without fused multiply-adds, as numpy computes them.
search_kernel = Extension(
    "rodsnes.contact._search_kernel",
    sources=["rodsnes/contact/_search_kernel.c"],
    extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off"],
    libraries=["m"],
)

# The rank's stretch of a rod factored without fill, its inverse's trailing block without a
# whole substitution (rodsnes/solve/chain.py, schur.RankSchur on several ranks).
chain_kernel = Extension(
    "rodsnes.solve._chain_kernel",
    sources=["rodsnes/solve/_chain_kernel.c"],
    extra_compile_args=["-O3", "-std=c99"],
    libraries=["m"],
)

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
    ext_modules=[elastic_kernel, potential_kernel, topology_kernel, rotation_kernel,
                 assembly_kernel, search_kernel, chain_kernel],
)
