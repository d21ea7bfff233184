"""The contact evaluation's bookkeeping kept between calls, and scatter.add_in_order, change no
bit of the results (issue 27: the plectoneme's path is chaotic, so the speed-ups are held to
the same bits, not to a tolerance)."""
import numpy as np
import pytest

from rodsnes.contact.scatter import add_in_order, in_order_rows


@pytest.mark.parametrize("seed", range(20))
def test_add_in_order_is_np_add_at_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    n, k, c = rng.integers(1, 40), rng.integers(0, 300), rng.integers(1, 10)
    rows = rng.integers(0, n, k)
    values = rng.standard_normal((k, c)) * 10.0 ** rng.integers(-8, 8, (k, 1))
    values[rng.random((k, c)) < 0.1] = 0.0
    base = rng.standard_normal((n, c + 3)) * 10.0 ** rng.integers(-8, 8, (n, 1))
    base[rng.random(base.shape) < 0.1] = -0.0           # the sign of zero counts too
    want, got = base.copy(), base.copy()
    np.add.at(want[:, :c], rows, values)
    add_in_order(got[:, :c], in_order_rows(rows), values)
    assert np.array_equal(want.view(np.int64), got.view(np.int64))


def test_kept_rows_give_a_fresh_evaluations_bits():
    """An evaluation through the kept Verlet plan, pair rows and residual rows equals one made
    with every kept thing dropped, bit for bit (energy, residual, tangent, depth)."""
    from conftest import build_run, perturb_state
    run = build_run("plectoneme", rod_nelem=24, load_stop=0.05)
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
