"""The compiled node rotations (rodsnes/model/so3_compiled.py) against their numpy reference."""
import numpy as np

from rodsnes.model import so3, so3_compiled


def test_compiled_rotations_equal_the_numpy_path():
    """exp(theta_i) q_i, read in place from the rotation columns of an (n, 6) dof array, with
    and without normalisation: equal to so3.qmul(so3.qexp(theta), q) to 1e-15 (the sines and
    cosines of libm and numpy may differ in the last bit; at zero angle q itself), at zero,
    tiny (the series branch),
    moderate and large angles; the numpy fallback when theta is not a row-contiguous view.
    `make install` builds the kernel: a missing library is a failure."""
    assert so3_compiled.available(), "rodsnes.model._rotation_kernel is not built: make install"
    rng = np.random.default_rng(3)
    n = 1000
    X = rng.standard_normal((n, 6))
    X[:, 3:6] *= np.repeat([0.0, 1e-12, 1e-9, 0.3, 3.0], n // 5)[:, None]
    q = so3.qexp(rng.standard_normal((n, 3)))
    th = X[:, 3:6]
    for normalize in (False, True):
        ref = so3.qmul(so3.qexp(th), q)
        if normalize:
            ref /= np.linalg.norm(ref, axis=1, keepdims=True)
        got = so3_compiled.rotate(th, q, normalize)
        assert got is not None and np.abs(got - ref).max() <= 1e-15
        q0 = q[:n // 5]
        assert np.abs(got[:n // 5] - (q0 / np.linalg.norm(q0, axis=1, keepdims=True)
                                      if normalize else q0)).max() <= 1e-16
        assert np.allclose(so3.rotated(th, q, normalize), ref, rtol=0, atol=1e-15)
    assert so3_compiled.rotate(np.asfortranarray(th), q, False) is None
    assert np.allclose(so3.rotated(np.asfortranarray(th), q), so3.qmul(so3.qexp(th), q),
                       rtol=0, atol=1e-15)
