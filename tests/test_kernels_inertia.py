"""The fast elastic kernels against the reference one, and the stability count read from
Newton's own LDL^T factorisation against a factorisation of its own."""
import json
import os

import numpy as np
import pytest
from petsc4py import PETSc

from rodsnes.model import elastic, so3
from conftest import gathered_positions, inertia_solve, place, run_case

STIFF = [3.0, 4.0, 50.0, 1.0, 2.0, 1.5]


def deformed_elements(rng, p, ne, h):
    """Random deformed elements; every other element's second node quaternion flipped (q and
    -q are one rotation: the kernels must align signs)."""
    qe = so3.qexp(rng.normal(size=(ne, p + 1, 3)) * 0.6)
    qe[::2, 1] *= -1.0
    xe = np.cumsum(rng.normal(size=(ne, p + 1, 3)) * 0.1 + [h / p, 0, 0], axis=1)
    return qe, xe


def relative_errors(a, b):
    return [float(np.abs(x - y).max() / np.abs(x).max()) for x, y in zip(a, b) if x is not None]


@pytest.mark.parametrize("p", [1, 2, 3, 4])
@pytest.mark.parametrize("nq_extra", [0, 1])
@pytest.mark.parametrize("bound", [False, True])
def test_numpy_kernel_equals_the_reference(p, nq_extra, bound):
    rng = np.random.default_rng(10 * p + nq_extra)
    ne, h, nq = 7, 0.3, p + nq_extra
    rod = elastic.ElasticRod(p, nq, h, STIFF, kernel="numpy")
    qe, xe = deformed_elements(rng, p, ne, h)
    rod.set_reference(rng.normal(size=(ne, nq, 6)) * 0.1 + [0, 0, 1, 0, 0, 0])
    if bound:       # active at about half of the points, none of them at the kink (linear
        # elements have one flexure per element: equal values at its points)
        kappa = np.unique(np.round(np.linalg.norm(rod.strains(qe, xe)[..., 3:5], axis=-1), 9))
        mid = len(kappa) // 2
        rod.set_curvature_limit(0.5 * (kappa[mid - 1] + kappa[mid]), 30.0)
    for symmetric in (False, True):
        ref = rod.element_terms_reference(qe, xe, symmetric=symmetric)
        assert max(relative_errors(ref, rod.element_terms_numpy(qe, xe, symmetric=symmetric))) < 1e-12
    ref = rod.element_terms_reference(qe, xe, tangent=False)
    fast = rod.element_terms_numpy(qe, xe, tangent=False)
    assert fast[2] is None and max(relative_errors(ref, fast)) < 1e-12
    e_ref = elastic.strain_measures(rod.N @ elastic.align_signs(qe), rod.dN @ elastic.align_signs(qe),
                                    rod.dN @ xe)
    assert np.abs(rod.strains(qe, xe) - e_ref).max() < 1e-12 * np.abs(e_ref).max()


def test_kernel_choice():
    rod = elastic.ElasticRod(3, 3, 0.1, STIFF, kernel="auto")
    assert rod.kernel == ("compiled" if elastic.compiled_available() else "numpy")
    assert elastic.ElasticRod(3, 3, 0.1, STIFF, kernel="reference").kernel == "reference"
    with pytest.raises(ValueError):
        elastic.ElasticRod(3, 3, 0.1, STIFF, kernel="fortran")


@pytest.mark.mpi
def test_every_kernel_gives_the_same_cantilever():
    """Mattiasson's cantilever with each kernel: the same tip to solver tolerance."""
    tips = {}
    for kernel in ("numpy", "reference") + (("compiled",) if elastic.compiled_available() else ()):
        run = run_case("mattiasson", rod_kernel=kernel)
        assert run.ok
        tips[kernel] = gathered_positions(run)[-1]
    for kernel, tip in tips.items():
        assert np.abs(tip - tips["reference"]).max() < 1e-9, kernel


@pytest.mark.mpi
def test_stability_count_by_the_kept_ldlt_equals_a_fresh_factorisation():
    """-stability counts the Hessian's negative eigenvalues by the kept SBAIJ LDL^T
    (stability.Inertia: one matrix and symbolic analysis for the whole path); the count equals
    a fresh, Jacobi-scaled AIJ factorisation's.  A perfect Euler column at 1.2 P_cr held on the
    straight branch (no switch) has its two buckling modes (y and z) negative; the buckled
    branch (imperfection) none.  In 3-D (-rod_planar off): a planar run counts by its two
    blocks (tests/test_planar.py)."""
    from rodsnes.solve import stability
    for imperfection, want in ((0.0, 2), (1e-3, 0)):
        run = run_case("euler", stability=True, rod_imperfection=imperfection,
                       load_path="newton", rod_planar="off",
                       load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4), load_steps=4)
        p = run.problem
        assert run.solver.results[-1].negative_eigenvalues == want
        assert stability.negative_eigenvalues(p) == want
        assert stability.negative_eigenvalues_scaled(p) == want
        inertia = p.inertia
        if PETSc.COMM_WORLD.getSize() == 1:     # one rank: the chain LDL^T, every count
            assert inertia.H.getType() == "seqbaij" and inertia.chain_counts == inertia.counts
        else:
            assert "sbaij" in inertia.H.getType() and inertia.chain_counts == 0
        assert inertia.builds == 1 and inertia.counts >= len(run.solver.results) + 1


@pytest.mark.mpi
@pytest.mark.slow
def test_the_kept_ldlt_follows_a_new_contact_pattern():
    """With contact the Hessian's pattern follows the candidate pairs: the same state keeps
    the matrix; a state without contact (the rod put back straight) makes a new one; every
    count equals the fresh factorisation's.  (40 load steps reach the same equilibrium as 5 in
    40 % of the time: fewer cut-backs and long Newton solves at the first touch.)  In 3-D:
    a planar run counts by its in-plane and out-of-plane blocks (tests/test_planar.py)."""
    from rodsnes.solve import stability
    run = run_case("rollup_contact", rod_nelem=16, load_steps=40, stability=True,
                   rod_planar="off")
    assert run.ok and run.contact.summary()["active_points"] > 0
    p = run.problem
    builds = p.inertia.builds
    assert stability.negative_eigenvalues(p) == stability.negative_eigenvalues_scaled(p)
    assert p.inertia.builds == builds                   # same state, same pattern: kept
    n = run.mesh.n_nodes
    s_nodes = np.linspace(0.0, run.mesh.length, n)
    place(run, np.c_[s_nodes, np.zeros(n), np.zeros(n)], np.tile([1.0, 0.0, 0.0], (n, 1)))
    assert stability.negative_eigenvalues(p) == stability.negative_eigenvalues_scaled(p)
    assert p.inertia.builds == builds + 1            # other pairs: a new matrix


@pytest.mark.mpi
def test_a_small_hessian_is_factored_whole_on_every_rank(monkeypatch):
    """(MUMPS's paths: on one rank the chain LDL^T would count.)  On several ranks a Hessian of
    at most Inertia.REDUNDANT_MAX unknowns is factored whole
    on every rank (sequential MUMPS LDL^T of the gathered matrix: reproducible bit for bit,
    where MUMPS over the ranks is not); its count and solve equal those of MUMPS over the ranks
    (REDUNDANT_MAX 0) on the Euler column at 1.2 P_cr held straight (two negative modes): both
    solve (H + tau) x = b with a backward error at round-off (conftest.inertia_solve), and
    agree as far as H's conditioning allows (1e-8 relative measured on 2 ranks)."""
    from rodsnes.solve.stability import Inertia
    run = run_case("euler", stability=True, rod_imperfection=0.0, load_path="newton",
                   rod_planar="off", load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4),
                   load_steps=4)
    p = run.problem
    size = p.layout.comm.getSize()
    monkeypatch.setattr(Inertia, "_chain_applies", lambda self: False)
    whole, spread = Inertia(p), Inertia(p)
    spread.REDUNDANT_MAX = 0
    xs = []
    for inertia in (whole, spread):
        inertia.assemble()
        assert inertia.factor() == 2
        b, x = inertia_solve(inertia, 1e-12)     # backward error at round-off
        xs.append(x)
    assert (whole.pc.getComm().getSize(), whole.whole is not None) == (1, size > 1)
    assert spread.pc.getComm().getSize() == size and spread.whole is None
    d = xs[0].copy()
    d.axpy(-1.0, xs[1])
    assert d.norm() <= 1e-6 * xs[1].norm()
    x2 = xs[0].duplicate()
    whole.solve(b, x2)
    assert np.array_equal(x2.getArray(), xs[0].getArray())
    for obj in xs + [b, x, d, x2]:
        obj.destroy()
    whole.destroy()
    spread.destroy()


@pytest.mark.parametrize("user", [None, "4"])
def test_the_stability_ldlt_is_ordered_as_the_newton_steps_mumps(user):
    """The stability count's MUMPS LDL^T takes the Newton step's ordering rule
    (linear.mumps_ordering): minimum degree (ICNTL(7) = 0) where it fills the node graph no
    more than nested dissection (a rod's chain), PORD only when asked (-stability_mat_mumps_
    icntl_7 4: the user's choice stays)."""
    from petsc4py import PETSc
    from conftest import build_run
    from rodsnes.solve.stability import Inertia
    # MUMPS asked for (on one rank the chain LDL^T counts otherwise)
    kw = {"stability_pc_factor_mat_solver_type": "mumps"} if user is None else \
        {"stability_mat_mumps_icntl_7": user}
    p = build_run("mattiasson", rod_nelem=40, rod_planar="off", **kw).problem
    p.set_load(0.5)
    inertia = Inertia(p)
    inertia.assemble()
    assert inertia.factor() == 0
    want = 0 if user is None else int(user)
    assert inertia.pc.getFactorMatrix().getMumpsIcntl(7) == want
    inertia.destroy()
    PETSc.Options().delValue("stability_mat_mumps_icntl_7")
    PETSc.Options().delValue("stability_pc_factor_mat_solver_type")


@pytest.mark.mpi
def test_the_chain_ldlt_counts_and_hands_an_unstable_factorisation_to_mumps(monkeypatch):
    """An open rod without contact has its Hessian counted by the chain LDL^T (chain.py: the
    pivot blocks' inertias; on several ranks schur.RankSchur with each stretch's and the
    separator's Schur complement's, Haynsworth; Inertia.chain_counts), the count taken where
    its factors solve at round-off (Inertia.backward), and its factors serve solve(); with the
    backward error bound at 0 every count goes to MUMPS on an AIJ copy, the same counts and a
    solve as accurate.  The Euler column at 1.2 P_cr held straight: two negative modes."""
    from rodsnes.solve import schur, stability
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)     # condensed however short
    p = run_case("euler", rod_imperfection=0.0, load_path="newton", rod_planar="off",
                 load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4), load_steps=4).problem
    counts = {}
    for bound in (stability.Inertia.CHAIN_BACKWARD, 0.0):
        monkeypatch.setattr(stability.Inertia, "CHAIN_BACKWARD", bound)
        inertia = stability.Inertia(p)
        inertia.assemble()
        counts[bound] = inertia.factor()
        assert "baij" in inertia.H.getType() and "sbaij" not in inertia.H.getType()
        assert inertia.chain is not None
        assert inertia.chain_counts == (1 if bound else 0)
        assert (inertia.backward <= 1e-14) and inertia.by_chain == bool(bound)
        inertia_solve(inertia, 1e-12)
        inertia.destroy()
    assert list(counts.values()) == [2, 2]
    assert stability.negative_eigenvalues_scaled(p) == 2


def test_a_closed_turn_hands_its_count_to_mumps_and_the_chain_stays(monkeypatch):
    """A roll-up's closed turn (8 cubic elements) counted under the round-off shift alone
    (NEUTRAL 0: the neutral band's shift, 1e-4 there, keeps its pivots apart) has a pivot
    block carrying growth: the chain factors' backward error (8e-14 |H| |x|) exceeds a tenth
    of the round-off scale, MUMPS counts (the same count as the fresh factorisation's).  The
    MUMPS options rodsnes set for that count are its own defaults, not the user's: a later
    count still takes the chain where it is backward stable (the Euler column)."""
    from rodsnes.solve import stability
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("one rank (the rods are shorter than a condensation)")
    p = run_case("rollup", rod_nelem=8).problem
    monkeypatch.setattr(stability, "NEUTRAL", 0.0)
    inertia = stability.Inertia(p)
    n = inertia.count()
    assert inertia.chain is not None and not inertia.by_chain and inertia.chain_counts == 0
    assert inertia.backward > 1e-14 and n == stability.negative_eigenvalues_scaled(p) == 2
    inertia_solve(inertia, 1e-12)
    inertia.destroy()
    monkeypatch.undo()
    q = run_case("euler", stability=True, rod_imperfection=1e-3, load_path="newton",
                 rod_planar="off", load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4),
                 load_steps=4).problem
    again = stability.Inertia(q)
    assert again.count() == 0 and again.by_chain and again.chain_counts == 1
    again.destroy()


@pytest.mark.mpi
def test_a_ring_on_several_ranks_is_counted_by_the_kept_mumps_ldlt(monkeypatch):
    """Michell's ring on several ranks, condensed however short: its stretches are cut at both
    ends and the separator's neighbours lie deep (CHAIN_TAIL_MAX 0), so the condensation
    cannot count (RankSchur.structural); the first count goes to MUMPS, and from the next
    assembly on the kept SBAIJ LDL^T counts - the fresh factorisation's count each time."""
    from rodsnes.solve import schur, stability
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    monkeypatch.setattr(schur, "CHAIN_TAIL_MAX", 0)
    p = run_case("michell", rod_nelem=24).problem
    inertia = stability.Inertia(p)
    want = stability.negative_eigenvalues_scaled(p)
    assert inertia.count() == want and not inertia.by_chain and inertia.chain_structural
    assert inertia.count() == want and inertia.chain is None
    assert "sbaij" in inertia.H.getType()
    inertia.destroy()


@pytest.mark.mpi
def test_an_aij_hessian_is_counted_by_mumps():
    """-mat_type aij: the Hessian is not BAIJ, the chain LDL^T does not apply (no block value
    array), MUMPS counts as before - the fresh factorisation's count, after every change of
    the Hessian."""
    from rodsnes.solve import stability
    try:
        p = run_case("euler", rod_imperfection=0.0, load_path="newton", rod_planar="off",
                     load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4), load_steps=4,
                     mat_type="aij").problem
        inertia = stability.Inertia(p)
        assert inertia.count() == 2 == stability.negative_eigenvalues_scaled(p)
        assert inertia.chain is None and inertia.chain_counts == 0
        # refactored at every change of H: shifted positive definite, then H again (on
        # several ranks the gathered AIJ kept its first factor: 2, 2, 2)
        shift = inertia.diagonal.duplicate()
        shift.set(2.0 * inertia.diagonal.norm(PETSc.NormType.INFINITY))
        assert inertia.factor(shift) == 0
        assert inertia.count() == 2
        shift.destroy()
        inertia.destroy()
    finally:
        PETSc.Options().delValue("mat_type")


@pytest.mark.mpi
@pytest.mark.parametrize("mat_type", ["baij", "aij"])
def test_a_mat_type_keeps_the_twisted_ring_s_path(mat_type):
    """-mat_type baij (the Jacobian's own type, asked for by name): the Hessian stays SBAIJ, its
    upper triangle, which MUMPS's LDL^T takes (as BAIJ every factorisation of the minimiser's
    shifted Hessian failed: "no positive definite shift" at the first step).  -mat_type aij:
    on several ranks the gathered Hessian is refactored at every shift (it kept its first
    factor, and the ring stopped at its bifurcation, load 0.78).  The twisted ring then ends
    as without the option, on any number of ranks."""
    kw = dict(rod_nelem=12, load_twist_turns=2.2)
    ref = run_case("michell", **kw)
    try:
        run = run_case("michell", mat_type=mat_type, **kw)
        H = run.layout.create_matrix(symmetric=True)
        assert ("sbaij" in H.getType()) == (mat_type == "baij")
        H.destroy()
    finally:
        PETSc.Options().delValue("mat_type")
    assert ref.ok and run.ok
    assert abs(run.problem.energy() - ref.problem.energy()) <= 1e-10 * abs(ref.problem.energy())


@pytest.mark.parametrize("nelem, EA", [(16, None), (400, None), (1500, None), (16, 1e8)])
def test_a_column_past_buckling_counts_unstable_on_any_mesh(nelem, EA):
    """The perfect Euler column in 3-D at 1.44 P_cr: straight on the Newton path, its two
    buckling directions counted at every mesh (H v = lambda M v's lowest pair, -6.17 EI / L^4,
    is mesh-independent; H's own shrinks as h, below a shift of eps |H|, which grows as 1 / h,
    from a few hundred elements on: such a count certified the straight column stable at 400
    and 1500 elements); and the minimiser, whose convergence asks the same count, buckles it
    (energy 3.19185, the straight column's 3.55305) on every mesh.  Also for a rod 100 x as
    slender in EA/EI (EA = GA = 1e8 EI/L^2), whose rotation rows' H_ii/M_ii (GA EA/EI, on any
    mesh) once set the round-off term to 19 EI/L^4 and hid the pair."""
    kw = dict(rod_nelem=nelem, rod_imperfection=0.0, rod_planar="off", load_steps=4,
              load_end_force="-3.5530575843921685,0,0", rod_error_estimate="off")
    if EA is not None:
        kw.update(rod_EA=EA, rod_GA=EA)
    straight = run_case("euler", load_path="newton", stability=True, load_max_cutbacks=0, **kw)
    # loads 0.36, 0.72, 1.08, 1.44 P_cr
    assert [h["negative_eigenvalues"] for h in straight.history] == [0, 0, 2, 2]
    assert abs(straight.problem.energy() - 3.553051) < 1e-5
    assert straight.problem.stats["neutral_band"] < 0.2
    buckled = run_case("euler", **kw)
    assert buckled.ok and buckled.history[-1]["negative_eigenvalues"] == 0
    assert abs(buckled.problem.energy() - 3.191845) < 1e-5


def test_the_count_is_of_the_metric_eigenvalues_below_the_neutral_band(monkeypatch):
    """The count is Sylvester's on H + tau M: the eigenvalues of H v = lambda M v (M the rod's
    lumped mass metric, stability_metric) below -tau, by dense LAPACK.  The imperfect twisted
    ring at 1.5 turns has one, -1.0e-6 (-2e-3 EI / L^4, a near-symmetry the imperfection
    breaks), inside the neutral band at the default NEUTRAL (tau = 1e-2 EI / L^4): stable;
    narrower bands count it."""
    import scipy.linalg as sl
    from rodsnes.solve import stability
    from rodsnes.solve.stability import gather_csr
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("one rank (dense eigenvalues of the gathered Hessian)")
    p = run_case("michell", load_twist_turns=1.5, load_steps=4, rod_nelem=16,
                 load_path="newton", rod_imperfection=1e-4).problem
    inertia = stability.Inertia(p)
    H = inertia.assemble()
    A = gather_csr(H, p.layout).toarray()
    A = np.triu(A) + np.triu(A, 1).T
    lam = sl.eigh(A, np.diag(stability.stability_metric(p).ravel()), eigvals_only=True)
    assert -2e-6 < lam[0] < -5e-7 < 1e-2 < lam[1]
    counts = {}
    for neutral in (1e-2, 1e-3, 1e-4, 1e-6):
        monkeypatch.setattr(stability, "NEUTRAL", neutral)
        counts[neutral] = inertia.factor()
        assert counts[neutral] == int(np.sum(lam < -inertia.tau)), neutral
    assert counts == {1e-2: 0, 1e-3: 1, 1e-4: 1, 1e-6: 1}
    inertia.destroy()
