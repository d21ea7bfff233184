"""The Jacobian assembled in chunks of elements (RodProblem.jacobian, TANGENT_CHUNK): bit for
bit the one-call Jacobian (orders 1-4, a closed ring with per-element reference strains e0 that
vary and are twisted with the load, symmetric, the planar ComponentView, a chunk size that
leaves a short last chunk), the numpy kernel's to round-off; the residual and the Jacobian
sharing the kernel's workspace in any order; the same on several ranks (make test-mpi)."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, perturb_state
from rodsnes.model.problem import RodProblem


# -- helpers ---------------------------------------------------------------------------------
def _csr(M):
    """The matrix's local rows as (ai, aj, av) copies (BAIJ, AIJ)."""
    ai, aj, av = M.getValuesCSR()
    return ai.copy(), aj.copy(), av.copy()


def _assemble(p, chunk, symmetric=False):
    p.TANGENT_CHUNK = chunk
    try:
        p.jacobian(None, p.state.X, p.J, p.J, symmetric=symmetric)
    finally:
        del p.TANGENT_CHUNK
    return _csr(p.J)


def _same(a, b):
    return all(np.array_equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize("case,kw", [
    ("michell", dict(rod_nelem=600)),                       # closed, e0 per element, twisted
    ("mattiasson", dict(rod_nelem=530, rod_order=1, rod_planar="off")),
    ("mattiasson", dict(rod_nelem=300, rod_order=2, rod_planar="off")),
    ("mattiasson", dict(rod_nelem=257, rod_order=4, rod_planar="off")),
    ("euler", dict(rod_nelem=520)),                         # imperfect: e0 varies along the rod
])
@pytest.mark.parametrize("symmetric", [False, True])
def test_the_chunked_jacobian_is_the_one_call_jacobian(case, kw, symmetric):
    """Chunks of 256 and of 7 (a short last chunk) give the one-call tangent bit for bit; the
    numpy kernel (one call, e0 whole) the same to round-off: a chunk given another chunk's
    reference strains would differ at O(1) where e0 varies (the ring's imperfection and the
    load's twist, euler's imperfection; the straight cantilever's given a varying one)."""
    run = build_run(case, **kw)
    p = run.problem
    assert p.elastic.kernel == "compiled"
    p.set_load(0.4)                      # michell: e0 twisted by the load
    perturb_state(p)
    ne = len(p.layout.row_gconn)
    assert ne > RodProblem.TANGENT_CHUNK
    e0 = p.elastic.e0
    assert e0.ndim == 3 and len(e0) == ne
    if case == "mattiasson":            # straight: give every element its own e0
        k = np.arange(ne)[:, None, None] / ne
        p.elastic.set_reference(e0 + 0.05 * np.sin(7 * k + np.arange(6)))
    assert np.ptp(p.elastic.e0, axis=0).max() > 1e-6
    whole = _assemble(p, 10 ** 9, symmetric)
    assert _same(_assemble(p, RodProblem.TANGENT_CHUNK, symmetric), whole)
    assert _same(_assemble(p, 7, symmetric), whole)
    p.elastic.kernel = "numpy"
    try:
        ref = _assemble(p, RodProblem.TANGENT_CHUNK, symmetric)
    finally:
        p.elastic.kernel = "compiled"
    assert np.array_equal(ref[0], whole[0]) and np.array_equal(ref[1], whole[1])
    scale = np.abs(ref[2]).max()
    assert np.abs(ref[2] - whole[2]).max() <= 1e-10 * scale


def test_the_planar_view_of_the_chunked_jacobian_is_the_one_call_view():
    """The planar cantilever's in-plane block (PlanarSystem.assemble_tangent: the plane
    kernel's tangents, chunks of 4 x 256 and 4 x 7 elements, the same bytes as 256 and 7 of
    the 3-D tangents) gives the one-call block bit for bit."""
    run = build_run("mattiasson", rod_nelem=1100)
    p = run.problem
    pl = p.planar
    assert pl is not None
    p.set_load(0.4)
    perturb_state(p)
    out = []
    for chunk in (10 ** 9, RodProblem.TANGENT_CHUNK, 7):
        p.TANGENT_CHUNK = chunk
        try:
            pl.assemble_tangent()
        finally:
            del p.TANGENT_CHUNK
        out.append(_csr(pl.J))
    assert out[0][2].size and _same(out[1], out[0]) and _same(out[2], out[0])


def test_the_symmetric_planar_block_of_the_chunked_hessian_is_the_one_call_block():
    """The in-plane block of the energy Hessian (symmetric=True through ComponentView into an
    SBAIJ matrix of block size 3, as planar.BlockInertia assembles it, the 3-D tangents cut):
    chunks of 4 x 256 and 4 x 7 give the one-call block bit for bit."""
    from rodsnes.solve.planar import ComponentView, create_block_matrix
    run = build_run("mattiasson", rod_nelem=1100)
    p = run.problem
    p.set_load(0.4)
    perturb_state(p)
    H = create_block_matrix(p, p.patterns, symmetric=True)
    out = []
    for chunk in (10 ** 9, RodProblem.TANGENT_CHUNK, 7):
        p.TANGENT_CHUNK = chunk
        try:
            p.jacobian(None, p.state.X, H, H, symmetric=True,
                       view=ComponentView(H, p.planar.plane.inplane, p.constraints))
        finally:
            del p.TANGENT_CHUNK
        out.append(_csr(H.convert(PETSc.Mat.Type.AIJ, PETSc.Mat())))
    assert out[0][2].size and _same(out[1], out[0]) and _same(out[2], out[0])


@pytest.mark.parametrize("nelem", [100, 256, 257, 700])
def test_the_residual_and_the_jacobian_share_the_workspace_in_any_order(nelem):
    """The kernel's workspace grows and is handed out as leading slices: the residual (all the
    elements) and the Jacobian (a chunk at a time) interleaved in any order, at two states,
    give what a fresh problem gives (a slice overwritten while in use would not)."""
    runs = [build_run("michell", rod_nelem=nelem) for _ in range(2)]
    for run in runs:
        run.problem.set_load(0.4)
    a, b = (r.problem for r in runs)

    def F(p):
        p.residual(None, p.state.X, p.F)
        return p.F.getArray().copy()

    def J(p):
        p.jacobian(None, p.state.X, p.J, p.J)
        return _csr(p.J)

    # reference: a fresh problem, the Jacobian first (its workspace sized by a chunk)
    perturb_state(b, seed=5)
    J_ref, F_ref = J(b), F(b)
    perturb_state(b, seed=6)
    F_ref2, J_ref2 = F(b), J(b)
    # the other order on the other problem: residual first (workspace of all elements)
    perturb_state(a, seed=5)
    f1 = F(a)
    j1 = J(a)
    f1b = F(a)
    perturb_state(a, seed=6)
    j2 = J(a)
    f2 = F(a)
    j2b = J(a)
    assert np.array_equal(f1, F_ref) and np.array_equal(f1b, F_ref)
    assert _same(j1, J_ref)
    assert np.array_equal(f2, F_ref2) and _same(j2, J_ref2) and _same(j2b, J_ref2)


@pytest.mark.mpi
def test_the_chunked_jacobian_on_several_ranks():
    """On several ranks (off-process blocks stashed in the elements' order) the chunks give the
    one-call tangent bit for bit, for the ring too (its closing element spans the last rank
    and rank 0)."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    for case, kw in (("michell", dict(rod_nelem=900)),
                     ("mattiasson", dict(rod_nelem=900, rod_planar="off"))):
        p = build_run(case, **kw).problem
        p.set_load(0.4)
        perturb_state(p)
        whole = _assemble(p, 10 ** 9)
        assert _same(_assemble(p, RodProblem.TANGENT_CHUNK), whole)
        assert _same(_assemble(p, 7), whole)
