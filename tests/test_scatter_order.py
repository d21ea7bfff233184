"""scatter.add_in_order against np.add.at, bit for bit (the plectoneme's path is chaotic, so the
contact's speed-ups are held to the same bits, not to a tolerance): random rows and values with
signed zeros, and the edge cases the contact code meets (one row many times, 2-D rows with
blocks of values, empty, non-contiguous targets, non-finite values)."""
import numpy as np
import pytest

from rodsnes.contact.scatter import add_in_order, in_order_rows


def _bits(a):
    return np.ascontiguousarray(a).view(np.int64)


@pytest.mark.parametrize("seed", range(10))
def test_one_row_many_times_and_2d_rows(seed):
    rng = np.random.default_rng(seed)
    n, k, n1 = 7, int(rng.integers(1, 60)), 4
    rows = rng.integers(0, n, (k, n1))
    rows[: k // 2] = 3                               # one row takes most additions
    values = rng.standard_normal((k, n1, 3)) * 10.0 ** rng.integers(-10, 10, (k, 1, 1))
    base = rng.standard_normal((n, 6))
    want, got = base.copy(), base.copy()
    np.add.at(want[:, 0:3], rows, values)             # a strided view, as Floc[:, 0:3]
    add_in_order(got[:, 0:3], in_order_rows(rows), values)
    assert np.array_equal(_bits(want), _bits(got))


def test_blocks_of_values_into_flattened_rows():
    """potential.add_report: f (no, nqp, 3) reshaped to (no, nqp*3), values (k, nqp, 3)."""
    rng = np.random.default_rng(1)
    no, nqp, k = 5, 4, 40
    oi = rng.integers(0, no, k)
    v = rng.standard_normal((k, nqp, 3))
    want = rng.standard_normal((no, nqp, 3))
    got = want.copy()
    np.add.at(want, oi, v)
    add_in_order(got.reshape(no, -1), in_order_rows(oi), v)
    assert np.array_equal(_bits(want), _bits(got))


def test_empty_and_non_finite():
    base = np.array([[1.0, -0.0], [np.inf, 2.0]])
    got = base.copy()
    add_in_order(got, in_order_rows(np.zeros(0, dtype=np.int64)), np.zeros((0, 2)))
    assert np.array_equal(_bits(base), _bits(got))
    rows = np.array([0, 1, 0, 1])
    v = np.array([[np.nan, 1.0], [-np.inf, 0.0], [1e308, 1e308], [1.0, -0.0]])
    want, got = base.copy(), base.copy()
    with np.errstate(invalid="ignore"):        # inf - inf: NaN on both paths, as intended
        np.add.at(want, rows, v)
        add_in_order(got, in_order_rows(rows), v)
    assert np.array_equal(np.isnan(want), np.isnan(got))
    assert np.array_equal(_bits(np.nan_to_num(want)), _bits(np.nan_to_num(got)))


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
