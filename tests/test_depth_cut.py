"""The minimiser's line search after a trial that pressed the strands deeper than the step's
allowance (minimize._depth_cut): the next trial is where the depth, linear in the step from
the iterate's, has gone 0.9 of the way to the allowance, within [0.01, 0.5] of the last one."""
import numpy as np
import pytest

from rodsnes.solve.minimize import _depth_cut


@pytest.mark.parametrize("depth0", [2e-4, 0.0, -3e-3])
def test_the_cut_lands_the_linear_depth_nine_tenths_of_the_way_to_the_allowance(depth0):
    """depth(alpha) = base + c alpha (base = depth0, or 0 where nothing touches): after a
    trial at alpha = 1 that reached depth(1) > allow, the factor f puts depth(f) 0.9 of the
    way from base to allow when that is within [0.01, 0.5]; a trial just past the allowance is halved; one far past
    it is cut a hundredfold at most."""
    allow = 1e-3
    base = max(depth0, 0.0)
    for c in (0.01, 0.02, 0.1):
        f = _depth_cut(depth0, base + c, allow)
        assert base + c * f == pytest.approx(base + 0.9 * (allow - base), rel=1e-12) or f in (0.01, 0.5)
        assert 0.01 <= f <= 0.5 and (f == 0.01 or base + c * f <= allow)   # 0.01: cut again
    assert _depth_cut(depth0, base + 1.01 * (allow - base), allow) == 0.5
    assert _depth_cut(depth0, base + 1e3 * allow, allow) == 0.01


def test_without_a_rise_the_step_is_halved():
    """A trial deeper than allowed without being deeper than the iterate (an allowance below
    the iterate's own depth, or a depth that is not finite) halves the step as before."""
    assert _depth_cut(2e-3, 2e-3, 1e-3) == 0.5
    assert _depth_cut(np.nan, 5e-3, 1e-3) == pytest.approx(0.9 * 1e-3 / 5e-3)
    assert _depth_cut(None, 5e-3, 1e-3) == pytest.approx(0.18)
