"""The fast elastic kernels against the reference one, and the stability count read from
Newton's own LDL^T factorisation against a factorisation of its own."""
import json
import os

import numpy as np
import pytest

from rodsnes import elastic, so3
from conftest import run_case

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
    if bound:       # active at about half of the points, none of them at the kink
        kappa = np.sort(np.linalg.norm(rod.strains(qe, xe)[..., 3:5], axis=-1).ravel())
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


def test_every_kernel_gives_the_same_cantilever(tmp_path):
    """Mattiasson's cantilever with each kernel: the same tip to solver tolerance."""
    tips = {}
    for kernel in ("numpy", "reference") + (("compiled",) if elastic.compiled_available() else ()):
        run = run_case("mattiasson", outdir=tmp_path / kernel, rod_kernel=kernel)
        assert run.ok
        tips[kernel] = np.array(json.load(open(os.path.join(tmp_path / kernel, "summary.json")))["tip_position"])
    for kernel, tip in tips.items():
        assert np.abs(tip - tips["reference"]).max() < 1e-9, kernel


def test_stability_count_comes_from_newtons_factorisation(tmp_path):
    """-stability: Newton factors the symmetric Hessian (SBAIJ, MUMPS LDL^T); a stable step's
    count is read from that factorisation, an unstable one is confirmed by a factorisation of
    its own.  A perfect Euler
    column at 1.2 P_cr held on the straight branch (no switch) has the two buckling modes
    (y and z) negative; the buckled branch (imperfection) has none."""
    from rodsnes import stability
    counts = []
    for imperfection, want in ((0.0, 2), (1e-3, 0)):
        run = run_case("euler", outdir=tmp_path / str(imperfection), stability=True,
                       stability_switch=0, rod_imperfection=imperfection,
                       load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4), load_steps=4)
        p = run.problem
        assert p.symmetric and "sbaij" in p.J.getType()
        assert run.solver.snes.getKSP().getPC().getType() == "cholesky"
        counted = run.solver.inertia_counts
        if want == 0:      # every accepted (stable) step counted from Newton's factorisation
            assert counted["newton"] >= len(run.solver.results) >= 4
        else:              # the unstable ones confirmed by a factorisation of their own
            assert counted["separate"] >= 1
        last = run.solver.results[-1]
        assert last.negative_eigenvalues == want
        assert stability.negative_eigenvalues(p) == want          # a factorisation of its own
        counts.append(last.negative_eigenvalues)
        summary = json.load(open(os.path.join(tmp_path / str(imperfection), "summary.json")))
        assert summary["inertia_counts"]["newton"] == run.solver.inertia_counts["newton"]
    assert counts == [2, 0]


def test_newton_on_the_symmetric_hessian_takes_the_steps_of_the_consistent_tangent(tmp_path):
    """The symmetric Hessian differs from the consistent tangent by -1/2 g_theta^x = O(|F|), so
    Newton keeps its rate: Mattiasson's cantilever takes the same iterations per step with
    either (the residual histories agree to the level the dropped term reaches) and ends at
    the same tip."""
    runs = [run_case("mattiasson", outdir=tmp_path / str(flag), stability=flag)
            for flag in (False, True)]
    assert not runs[0].problem.symmetric and runs[1].problem.symmetric
    for a, b in zip(runs[0].solver.results, runs[1].solver.results, strict=True):
        assert a.its == b.its
        big = a.history > 1e-4
        assert np.allclose(a.history[big], b.history[big], rtol=1e-4)
    tips = [np.array(json.load(open(os.path.join(tmp_path / str(flag), "summary.json")))["tip_position"])
            for flag in (False, True)]
    assert np.abs(tips[0] - tips[1]).max() < 1e-9
