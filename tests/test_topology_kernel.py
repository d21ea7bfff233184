"""The compiled Gauss sums of writhe and link (model/_topology_kernel.c) against the numpy
reference (topology.KERNEL = "numpy"): closed and open polygons, a framed ribbon's link, a
right-handed supercoil and a knot, to round-off (the same formula summed in another order)."""
import numpy as np
import pytest

from rodsnes.model import topology


def _trefoil(n):
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.c_[np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)]


def _supercoil(n, turns=5, R=1.0, r=0.2):
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.c_[(R + r * np.cos(turns * t)) * np.cos(t), (R + r * np.cos(turns * t)) * np.sin(t),
                 r * np.sin(turns * t)]


def _both(fun):
    old = topology.KERNEL
    try:
        topology.KERNEL = "numpy"
        ref = fun()
        topology.KERNEL = "auto"
        fast = fun()
    finally:
        topology.KERNEL = old
    return ref, fast


needs_kernel = pytest.mark.skipif(not topology._load(), reason="compiled topology kernel not built")


@needs_kernel
@pytest.mark.parametrize("curve", [_trefoil(301), _supercoil(400), _supercoil(97, turns=3)])
@pytest.mark.parametrize("closed", [True, False])
def test_compiled_writhe_equals_numpy(curve, closed):
    ref, fast = _both(lambda: topology.writhe(curve, closed=closed))
    assert fast == pytest.approx(ref, rel=1e-12, abs=1e-12)


@needs_kernel
def test_compiled_link_and_topology_equal_numpy():
    x = _supercoil(300)
    t = np.gradient(x, axis=0)
    d1 = np.cross(t, [0.0, 0.0, 1.0])
    d1 /= np.linalg.norm(d1, axis=1)[:, None]
    ref, fast = _both(lambda: topology.link(x, d1, closed=True))
    assert fast == pytest.approx(ref, rel=1e-12, abs=1e-12)
    assert abs(fast - round(fast)) < 1e-8                 # an integer for a closed ribbon
    ref, fast = _both(lambda: topology.topology(x, d1, closed=True))
    for k in ("link", "twist", "writhe"):
        assert fast[k] == pytest.approx(ref[k], rel=1e-12, abs=1e-12), k


def test_numpy_is_the_fallback():
    old = topology.KERNEL
    try:
        topology.KERNEL = "numpy"
        assert topology._kernel() is False
    finally:
        topology.KERNEL = old
