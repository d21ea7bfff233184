"""The elastic tangents added into a block matrix's values as the compiled kernel makes them
(elastic_compiled.tangents_into, ElasticRod.tangents_into): bit for bit the matrix that the
tangents made first (element_terms, plane_tangents) and then added at the same places
(ElementBlocks.add) give, for every element count around the kernel's chunk of elements, the
3-D tangent (block size 6, cut to components, split into position and rotation blocks,
symmetric into SBAIJ) and the in-plane one; the groups it does not add (touching a
constrained node) are left to the caller."""
import ctypes

import numpy as np
import pytest
from petsc4py import PETSc

from rodsnes.model import assembly, elastic_compiled, partition
import test_elastic_compiled as compiled_test
import test_planar_kernel as planar_test

ADD = PETSc.InsertMode.ADD


class Touched:
    def __init__(self, n, hit=()):
        self.touched = np.zeros(n, dtype=bool)
        self.touched[list(hit)] = True


def chain(ne, nn):
    """The elements' nodes of a chain: element e holds nodes e (nn - 1) ... e (nn - 1) + nn - 1."""
    return (np.arange(ne)[:, None] * (nn - 1) + np.arange(nn)[None, :]).astype(np.int64)


def chain_matrix(conn, bs, symmetric, split):
    """A sequential (S)BAIJ matrix of block size bs holding every block of the node groups
    conn (node blocks of bs unknowns, or with ``split`` two blocks of 3 a node)."""
    n = int(conn.max()) + 1
    groups = partition.split_index(conn) if split else conn
    nb = 2 * n if split else n
    cols = [set() for _ in range(nb)]
    for g in groups:
        for i in g:
            cols[i].update(j for j in g if not symmetric or j >= i)
    ai = np.concatenate([[0], np.cumsum([len(c) for c in cols])]).astype(PETSc.IntType)
    aj = np.concatenate([sorted(c) for c in cols]).astype(PETSc.IntType)
    M = PETSc.Mat().create(comm=PETSc.COMM_SELF)
    M.setSizes((nb * bs, nb * bs), bsize=bs)
    M.setType(PETSc.Mat.Type.SEQSBAIJ if symmetric else PETSc.Mat.Type.SEQBAIJ)
    M.setPreallocationCSR((ai, aj))
    if symmetric:
        M.setOption(PETSc.Mat.Option.IGNORE_LOWER_TRIANGULAR, True)
    if split:
        M.setAttr(partition.SPLIT_ATTR, True)
    M.zeroEntries()
    M.assemble()
    return M


def node_arrays(qe, xe, conn):
    """Node arrays whose gathered elements are qe, xe but at the shared nodes, which take the
    later element's values (any state does: the two ways are compared at the same one)."""
    n = int(conn.max()) + 1
    qn, xn = np.empty((n, 4)), np.empty((n, 3))
    qn[conn.ravel()] = qe.reshape(-1, 4)
    xn[conn.ravel()] = xe.reshape(-1, 3)
    return qn, xn


CASES = {   # name: (block size, symmetric, split, comps, planar)
    "3d": (6, False, False, None, False),
    "3d_hessian_sbaij": (6, True, False, None, False),
    "3d_cut": (3, False, False, [0, 2, 4], False),
    "3d_split": (3, False, True, None, False),
    "plane": (3, False, False, None, True),
    "plane_sbaij": (3, True, False, None, True),
}


@pytest.mark.parametrize("ne", [1, 7, 8, 9, 17, 30])
@pytest.mark.parametrize("case", sorted(CASES))
def test_tangents_into_equal_the_tangents_added_after(case, ne):
    check_case(case, ne, 3, 4)


@pytest.mark.parametrize("p,nq", [(1, 1), (2, 3), (4, 5), (3, 17)])
@pytest.mark.parametrize("case", ["3d", "3d_split", "plane"])
def test_tangents_into_other_orders_and_points(case, p, nq):
    """Orders 1, 2, 4 and more points than the lane kernels take (17 > MAXQ: the 3-D tangent
    one element at a time), the reference strains given explicitly."""
    check_case(case, 9, p, nq, explicit_e0=True)


def check_case(case, ne, p, nq, explicit_e0=False):
    bs, symmetric, split, comps, planar = CASES[case]
    axis = 2
    rng = np.random.default_rng(ne + 31 * len(case) + 7 * p + nq)
    if planar:
        rod, qe, xe = planar_test.make_rod(p, nq, ne, axis, rng, bound=True)
    else:
        rod, qe, xe = compiled_test.make_rod(p, nq, ne, rng, bound=True)
    nn = p + 1
    conn = chain(ne, nn)
    qn, xn = node_arrays(qe, xe, conn)
    qe, xe = qn[conn], xn[conn]
    nc = 3 if planar else 6 if comps is None else len(comps)
    touched = Touched(int(conn.max()) + 1, hit=[0])         # element 0 is handed back
    A, B = (chain_matrix(conn, bs, symmetric, split) for _ in range(2))
    # the tangents made first, then added (the rest by the matrix's insertion)
    if planar:
        H = elastic_compiled.plane_tangents(rod, qe, xe, axis)
    else:
        H = elastic_compiled.element_terms(rod, qe, xe, symmetric=symmetric, comps=comps)[2]
    G = (partition.split_index(conn) if split else conn).astype(PETSc.IntType)
    rest = []
    for M in (A, B):
        M.zeroEntries()
    first = assembly.element_blocks(B, touched, conn, nc)
    assert first is not None and list(first.rest) == [0]
    first.add(0, ne, H, lambda i: rest.append(i))
    # made and added at once
    blocks = assembly.element_blocks(A, touched, conn, nc)
    with blocks.values() as ptr:
        elastic_compiled.tangents_into(rod, qn, xn, conn, rod.e0 if explicit_e0 else None,
                                       blocks.pos, ptr, blocks.k,
                                       blocks.bs, axis=axis if planar else -1, comps=comps,
                                       symmetric=symmetric)
    # and stored at each block's first addition into a matrix of garbage, zeroed only where no
    # direct element adds (ElementBlocks.zero_rest)
    C = chain_matrix(conn, bs, symmetric, split)
    stored = assembly.element_blocks(C, touched, conn, nc)
    with stored.values() as ptr:
        garbage = np.ctypeslib.as_array((ctypes.c_double * (stored.nblocks * bs * bs))
                                        .from_address(ptr))
        garbage[:] = rng.normal(size=garbage.shape)
    assert stored.zero_rest(C)
    with stored.values() as ptr:
        elastic_compiled.tangents_into(rod, qn, xn, conn, rod.e0 if explicit_e0 else None,
                                       stored.pos, ptr, stored.k, stored.bs,
                                       axis=axis if planar else -1, comps=comps,
                                       symmetric=symmetric, first=stored.first)
    for M in (A, B, C):
        M.setValuesBlockedRCV(G[:1], G[:1], H[:1], addv=ADD)
        M.assemble()
    a, b, c = (M.convert(PETSc.Mat.Type.AIJ, PETSc.Mat()).getValuesCSR() for M in (A, B, C))
    assert np.count_nonzero(b[2]) > 3 * len(b[0])             # something is compared
    for x, y, z in zip(a, b, c):
        assert np.array_equal(x, y) and np.array_equal(z, y), case
    # bit for bit, a zero's sign included
    assert np.array_equal(c[2].view(np.int64), b[2].view(np.int64)), case


def test_tangents_into_refuses_places_of_another_shape():
    """Places that do not fit the elements (their count, the blocks an element), components
    outside 0..5 and an axis beyond 2 are refused before the C call."""
    rng = np.random.default_rng(3)
    rod, qe, xe = compiled_test.make_rod(3, 4, 4, rng, bound=False)
    conn = chain(4, 4)
    qn, xn = node_arrays(qe, xe, conn)
    values = np.zeros(10)
    for pos, k, bs in ((np.zeros((3, 4, 4), dtype=np.int32), 4, 6),
                       (np.zeros((4, 4, 4), dtype=np.int32), 4, 3)):
        with pytest.raises(ValueError):
            elastic_compiled.tangents_into(rod, qn, xn, conn, None, pos,
                                           values.ctypes.data, k, bs)
    pos = np.zeros((4, 4, 4), dtype=np.int32)
    for kw in ({"comps": [-7, 0, 1]}, {"comps": [0, 1, 6]}, {"axis": 3}):
        with pytest.raises(ValueError):
            elastic_compiled.tangents_into(rod, qn, xn, conn, None, pos, values.ctypes.data,
                                           4, 3, **kw)
