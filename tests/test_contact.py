"""Self-contact in the parallel problem, at a constructed penetrating state (no solve needed):
the assembled tangent against finite differences of the assembled residual, one rank against
two (contact pairs across ranks: the SF halo exchange and the reaction sent back), and the KKT
report.  The converged contact scenes are run by tools/contact_study.py (slow: minutes)."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import run_case
from rodsnes import so3
from rodsnes.partition import NDOF

SETUP = dict(rod_nelem=12, load_steps=1, load_end_moment="0,0,0")


def coiled(comm=None, outdir=None):
    """The rollup_contact rod with no load, then put on a circle of 1.05 turns whose free end
    overlaps the clamped start by a fraction of the contact diameter."""
    run = run_case("rollup_contact", comm=comm, outdir=outdir, **SETUP)
    p, lay, m = run.problem, run.layout, run.mesh
    R = m.length / (2 * np.pi * 1.05)
    ph = m.s_nodes / R
    x = np.stack([R * np.sin(ph), R * (1 - np.cos(ph)) - 0.12 * m.s_nodes / m.length, 0 * ph], 1)
    t = np.stack([np.cos(ph), np.sin(ph), 0 * ph], 1)
    q = so3.quat_from_rot(so3.frame_from_tangent(t))
    p.state.q_ref[:] = q[lay.local_nodes]
    with p.state.X as a:
        a = a.reshape(-1, NDOF)
        a[:, 0:3] = x[lay.owned_nodes]
        a[:, 3:6] = 0.0
    return run


@pytest.mark.mpi
def test_assembled_tangent_matches_finite_differences_in_contact():
    run = coiled()
    p = run.problem
    X = p.state.X
    F = X.duplicate()
    p.residual(None, X, F)
    assert run.contact.summary()["active_points"] > 0
    J = p.layout.create_matrix(p.contact.extra_pattern(p.state.local_config()[0]))
    p.jacobian(None, X, J, J)
    rng = np.random.default_rng(3 + PETSc.COMM_WORLD.getRank())
    v = X.duplicate()
    with v as a:
        a[:] = rng.normal(size=a.shape)
        a[p.constraints.rows_local] = 0.0
    h = 1e-7
    Fp, Fm, Jv = X.duplicate(), X.duplicate(), X.duplicate()
    Xp, Xm = X.copy(), X.copy()
    Xp.axpy(h, v)
    Xm.axpy(-h, v)
    p.residual(None, Xp, Fp)
    p.residual(None, Xm, Fm)
    J.mult(v, Jv)
    fd = Fp - Fm
    fd.scale(1 / (2 * h))
    assert (fd - Jv).norm() / Jv.norm() < 1e-6


@pytest.mark.mpi
def test_two_ranks_give_the_serial_residual_energy_and_contact_forces():
    par = coiled()
    ser = coiled(comm=PETSc.COMM_SELF, outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}")
    F1, F2 = par.problem.F.duplicate(), ser.problem.F.duplicate()
    par.problem.residual(None, par.problem.state.X, F1)
    ser.problem.residual(None, ser.problem.state.X, F2)
    nat1 = par.layout.allgather_nodes(F1.getArray(readonly=True).reshape(-1, NDOF))
    nat2 = ser.layout.allgather_nodes(F2.getArray(readonly=True).reshape(-1, NDOF))
    assert np.abs(nat1 - nat2).max() < 1e-9 * np.abs(nat2).max()
    assert par.problem.energy() == pytest.approx(ser.problem.energy(), rel=1e-12)
    c1, c2 = par.contact.summary(), ser.contact.summary()
    assert c1["total_force"] == pytest.approx(c2["total_force"], rel=1e-12)
    assert c1["active_points"] == c2["active_points"] > 0
    if PETSc.COMM_WORLD.getSize() > 1:     # the contact really crosses ranks: clamp end and tip
        owners = par.layout.elem_owner
        assert owners[0] != owners[-1]


def test_kkt_report_and_action_reaction():
    run = coiled()
    p = run.problem
    F = p.F.duplicate()
    r, _ = p.state.local_config()
    Floc = np.zeros((len(r), NDOF))
    run.contact.add_residual(r, Floc)
    c = run.contact.summary()
    assert c["active_points"] > 0 and c["total_force"] > 0
    assert c["min_gap"] < 0 and c["max_penetration"] == pytest.approx(-c["min_gap"] / (2 * run.contact.eps))
    assert c["complementarity"] > 0
    # contact forces are internal: they sum to zero force and zero moment
    assert np.abs(Floc[:, 0:3].sum(axis=0)).max() < 1e-9 * np.abs(Floc).max()
    assert np.abs(np.cross(r, Floc[:, 0:3]).sum(axis=0)).max() < 1e-9 * np.abs(Floc).max() * 10
    del F
