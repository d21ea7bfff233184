"""The term interface (rodsnes.model.term.Term): the problem sums any term it is given, one it
has never heard of included, through the declared methods alone."""
import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from conftest import build_run, tangent_against_finite_differences
from rodsnes.model.partition import NDOF
from rodsnes.model.problem import RodProblem
from rodsnes.model.term import Term


class EndSpring(Term):
    """E = (k/2) |r_N - a|^2: the free end tied to the anchor a (a term the problem does not
    know by name); its owner adds it."""

    name = "spring"

    def __init__(self, layout, node, anchor, k):
        self.k, self.anchor = float(k), np.asarray(anchor, dtype=float)
        li = layout.nat2local[node]
        self.local = int(li) if 0 <= li < layout.n_owned else -1
        self.row = int(layout.nat2petsc[node])
        self.comm = layout.comm.tompi4py()

    def energy_local(self, lam, r, q):
        if self.local < 0:
            return 0.0
        d = r[self.local] - self.anchor
        return 0.5 * self.k * float(d @ d)

    def add_residual(self, lam, r, q, Floc):
        if self.local >= 0:
            Floc[self.local, 0:3] += self.k * (r[self.local] - self.anchor)

    def add_jacobian(self, lam, r, q, P, symmetric=False):
        if self.local >= 0:
            B = np.zeros((1, NDOF, NDOF))
            B[0, 0:3, 0:3] = self.k * np.eye(3)
            idx = np.array([[self.row]], dtype=PETSc.IntType)
            P.setValuesBlockedRCV(idx, idx, B, addv=PETSc.InsertMode.ADD)

    def report(self, r):
        stretch = np.linalg.norm(r[self.local] - self.anchor) if self.local >= 0 else 0.0
        return {"stretch": float(self.comm.allreduce(stretch, op=MPI.MAX))}


@pytest.mark.mpi
def test_the_problem_sums_a_term_it_does_not_know():
    run = build_run("mattiasson", rod_nelem=6)
    base = run.problem
    n = run.mesh.n_nodes
    anchor, k = np.array([1.1, 0.3, -0.2]), 2e5
    spring = EndSpring(run.layout, n - 1, anchor, k)
    p = RodProblem(run.scene, run.mesh, run.layout, base.terms + [spring])
    for prob in (base, p):
        prob.set_load(0.4)
    # a bent state, the same in both problems
    rng = np.random.default_rng(7 + PETSc.COMM_WORLD.getRank())
    with p.state.X as a:
        a[:] += 1e-2 * rng.normal(size=a.shape)
        a[p.constraints.rows_local] = base.state.X.getArray(readonly=True)[p.constraints.rows_local]
    p.state.recentre()                     # the tangent is the chart's at theta = 0
    p.state.X.copy(base.state.X)
    base.state.q_ref[:] = p.state.q_ref
    # energy: the rod's and the loads' plus the spring's
    r, _ = p.state.local_config()
    end = PETSc.COMM_WORLD.tompi4py().allreduce(
        r[spring.local] if spring.local >= 0 else np.zeros(3))
    e_spring = 0.5 * k * float((end - anchor) @ (end - anchor))
    assert e_spring > 1.0
    assert p.energy() == pytest.approx(base.energy() + e_spring, rel=1e-12)
    # residual: the spring's force on the end node's position row, nothing elsewhere
    F, F0 = p.F.duplicate(), p.F.duplicate()
    p.residual(None, p.state.X, F)
    base.residual(None, base.state.X, F0)
    diff = (F - F0).getArray(readonly=True).reshape(-1, NDOF)
    want = np.zeros_like(diff)
    if spring.local >= 0:
        want[spring.local, 0:3] = k * (end - anchor)
    assert np.abs(diff - want).max() <= 1e-9 * k
    # tangent: against differences of the summed residual, and the spring's block is in it
    p.jacobian(None, p.state.X, p.J, p.J)
    fd, Jv, v = tangent_against_finite_differences(p, p.J, seed=2)
    assert (fd - Jv).norm() / Jv.norm() < 1e-6
    base.jacobian(None, base.state.X, base.J, base.J)
    Jv0 = v.duplicate()
    base.J.mult(v, Jv0)
    dJ = (Jv - Jv0).getArray(readonly=True).reshape(-1, NDOF)
    va = v.getArray(readonly=True).reshape(-1, NDOF)
    want = np.zeros_like(dJ)
    if spring.local >= 0:
        want[spring.local, 0:3] = k * va[spring.local, 0:3]
    assert np.abs(dJ - want).max() <= 1e-9 * k
    # its report, under its name; no step limit, no pattern, no promise: the defaults
    assert p.report()["spring"]["stretch"] == pytest.approx(np.linalg.norm(end - anchor))
    assert p.step_limit == base.step_limit == 0.0 and p.deepest() is None
    assert not p.moving_pattern and p.adaptive_terms() == []
