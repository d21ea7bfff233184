"""The contact glue kept between evaluations (term._verlet_plan, _residual_rows,
potential._pair_rows, master_weights' table) against evaluations with every kept thing
dropped, through the changes a run makes: small moves (the Verlet list kept), a large move (a
new search), a return to an earlier state, a penalty change, the Verlet list dropped and
rebuilt equal, a closed ring; on any number of ranks, bit for bit."""
import numpy as np
import pytest

from conftest import build_run


def _coil(run, turns=40.0, radius=0.03, pitch=0.2):
    """Local node positions of a tight coil, a function of the natural node id (the same
    ghost values on every rank)."""
    lay, m = run.layout, run.mesh
    s = lay.local_nodes / max(m.n_nodes - 1, 1)
    return np.stack([pitch * s, radius * np.cos(turns * s), radius * np.sin(turns * s)], axis=1)


def _drop(c, search=False):
    c._plan, c._rows_kept, c.kept_evaluation = None, None, None
    c.leaf_nodes = None                 # the SF rebuilt (every rank: collective)
    if hasattr(c.kernel, "_rows"):
        c.kernel._rows = {}
    if hasattr(c.kernel, "_wm"):
        c.kernel._wm = (None, None)
    if search:
        c.verlet_list = None


def _eval(c, r, q):
    out = c.evaluate(r, tangent=True)
    F = np.zeros((len(r), 6))
    c.add_residual(0.0, r, q, F)
    deep = c.deepest(r, report=True)
    return [np.atleast_1d(out["energy"]), np.atleast_1d(out["depth"]), out["vec"].copy(),
            out["mat"].copy(), F, np.atleast_1d(deep)]


@pytest.mark.mpi
@pytest.mark.parametrize("case,model", [("plectoneme", "potential"),
                                        ("plectoneme", "projection"),
                                        ("michell_contact", None)])
def test_kept_glue_equals_fresh_through_a_runs_changes(case, model):
    # the coils overlap deeper than the pair potential's wall (-contact_wall): the law alone
    run = build_run(case, **({"rod_nelem": 24, "contact_model": model, "contact_wall": 0}
                             if model else {}))
    assert run.mesh.closed == (case == "michell_contact")
    p = run.problem
    c = next(t for t in p.terms if hasattr(t, "kept_evaluation"))
    r0, q = p.state.local_config()
    r0 = _coil(run)
    rng = np.random.default_rng(5)
    nat = rng.standard_normal((run.mesh.n_nodes, 3))[run.layout.local_nodes]
    r1 = r0 + 1e-6 * nat                           # within the skin: the list kept
    r2 = _coil(run, turns=38.0)                    # a large move: a new search
    mu = c.mu
    script = [("r0", r0, mu, False), ("r1", r1, mu, False), ("r2", r2, mu, False),
              ("back", r0, mu, False), ("mu", r0, 3.0 * mu, False), ("relist", r1, 3.0 * mu, True),
              ("r1b", r1, mu, False)]
    kept, fresh = [], []
    for label, r, m, relist in script:
        if m != c.mu:
            c.set_penalty(m)
        if relist:
            c.verlet_list = None                   # rebuilt as an equal, new object
        kept.append(_eval(c, r, q))
    _drop(c, search=True)
    c.set_penalty(mu)
    for label, r, m, relist in script:
        if m != c.mu:
            c.set_penalty(m)
        _drop(c, search=relist)
        fresh.append(_eval(c, r, q))
    assert any(len(k[2]) for k in kept)
    for (label, *_), a, b in zip(script, kept, fresh):
        for x, y in zip(a, b):
            assert x.shape == y.shape and np.array_equal(
                np.ascontiguousarray(x).view(np.int64), np.ascontiguousarray(y).view(np.int64)), label


def test_kept_rows_give_a_fresh_evaluations_bits():
    """An evaluation through the kept Verlet plan, pair rows and residual rows equals one made
    with every kept thing dropped, bit for bit (energy, residual, tangent, depth)."""
    run = build_run("plectoneme", rod_nelem=24, load_stop=0.05, contact_wall=0)  # deep coil
    p = run.problem
    c = next(t for t in p.terms if hasattr(t, "kept_evaluation"))
    r, q = p.state.local_config()
    rng = np.random.default_rng(0)
    # a tight coil: every element near others
    s = np.linspace(0.0, 1.0, len(r))
    r = np.stack([0.2 * s, 0.03 * np.cos(40 * s), 0.03 * np.sin(40 * s)], axis=1)
    results = []
    for fresh in (False, True):
        outs = []
        for i in range(4):
            ri = r + 1e-7 * rng.standard_normal(r.shape) if i else r
            if fresh:
                c._plan, c._rows_kept, c.kernel._rows = None, None, {}
            c.kept_evaluation = None
            out = c.evaluate(ri, tangent=True)
            F = np.zeros((len(r), 6))
            c.add_residual(0.0, ri, q, F)
            outs.append((out["energy"], out["depth"], out["vec"].copy(), out["mat"].copy(), F))
        rng = np.random.default_rng(0)
        results.append(outs)
    assert len(results[0][0][2])            # pairs in contact
    for a, b in zip(*results):
        for x, y in zip(a, b):
            assert np.array_equal(np.atleast_1d(x).view(np.int64), np.atleast_1d(y).view(np.int64))
