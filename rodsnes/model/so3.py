"""Batched rotations and unit quaternions (pure math, no PETSc).

Quaternions are arrays (..., 4) = (q0, qv), Hamilton product, R(q) rotates material
vectors into space: R = d_i (x) e_i, i.e. column i of R is the director d_i.
exp of a spatial rotation vector theta:  exp(theta^x) = R(qexp(theta)),
qexp(theta) = (cos|theta|/2, sin(|theta|/2) theta/|theta|).
``rotated`` (exp(theta) q at every node of a rod) has a compiled kernel (so3_compiled).
"""
import numpy as np

from rodsnes.model import so3_compiled


def hat(w):
    """Skew matrix w^x with w^x a = w x a, batched over leading axes."""
    w = np.asarray(w, dtype=float)
    H = np.zeros(w.shape[:-1] + (3, 3))
    H[..., 0, 1] = -w[..., 2]
    H[..., 0, 2] = w[..., 1]
    H[..., 1, 0] = w[..., 2]
    H[..., 1, 2] = -w[..., 0]
    H[..., 2, 0] = -w[..., 1]
    H[..., 2, 1] = w[..., 0]
    return H


def qmul(a, b):
    """Hamilton product a * b = (a0 b0 - av.bv, a0 bv + b0 av + av x bv), batched (leading axes
    broadcast), written out by components (np.cross and concatenate cost 4 x as much)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    b0, b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    out[..., 0] = a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3
    out[..., 1] = a0 * b1 + b0 * a1 + (a2 * b3 - a3 * b2)
    out[..., 2] = a0 * b2 + b0 * a2 + (a3 * b1 - a1 * b3)
    out[..., 3] = a0 * b3 + b0 * a3 + (a1 * b2 - a2 * b1)
    return out


def qconj(q):
    out = np.array(q, dtype=float, copy=True)
    out[..., 1:] *= -1.0
    return out


def qexp(theta):
    """Unit quaternion of the rotation vector theta (any size, no singularity)."""
    theta = np.asarray(theta, dtype=float)
    t1, t2, t3 = theta[..., 0], theta[..., 1], theta[..., 2]
    ang = np.sqrt(t1 * t1 + t2 * t2 + t3 * t3)
    half = 0.5 * ang
    # sin(half)/ang, with its series near zero
    small = ang < 1e-8
    s_over = np.where(small, 0.5 - ang**2 / 48.0, np.sin(half) / np.where(small, 1.0, ang))
    out = np.empty(theta.shape[:-1] + (4,))
    out[..., 0] = np.cos(half)
    out[..., 1:] = s_over[..., None] * theta
    return out


def rotated(theta, q, normalize=False):
    """exp(theta_i) q_i per node (qmul(qexp(theta), q)), divided by its norm with
    ``normalize``: by the compiled kernel (so3_compiled; theta read in place) when it is built,
    else by numpy."""
    out = so3_compiled.rotate(theta, q, normalize)
    if out is None:
        out = qmul(qexp(theta), q)
        if normalize:
            out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return out


def qlog(q):
    """Rotation vector of a unit quaternion, angle in [0, pi] (q and -q agree)."""
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., :1] < 0, -q, q)
    vn = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(vn, q[..., :1])
    small = vn < 1e-12
    fac = np.where(small, 2.0 / np.maximum(q[..., :1], 1e-300), ang / np.where(small, 1.0, vn))
    return fac * q[..., 1:]


def twisted(q, phi):
    """q exp(phi e3^x): the rotations q turned about their own third director by the angles
    phi (material twist), batched over the leading axis."""
    e3 = np.zeros((len(phi), 3))
    e3[:, 2] = phi
    return qmul(q, qexp(e3))


def log_relative(qa, qb):
    """psi = log(R_a R_b^T) as a rotation vector (spatial: R_a = exp(psi^x) R_b), batched over
    the leading axes of the unit quaternions qa, qb."""
    return qlog(qmul(qa, qconj(qb)))


def rot(q):
    """Rotation matrix of a (not necessarily unit) quaternion: Rq(q)/|q|^2 with
    Rq(q) = (q0^2 - |qv|^2) I + 2 qv qv^T + 2 q0 qv^x."""
    q = np.asarray(q, dtype=float)
    q0 = q[..., 0]
    qv = q[..., 1:]
    n2 = np.sum(q * q, axis=-1)
    R = (q0**2 - np.sum(qv * qv, axis=-1))[..., None, None] * np.eye(3)
    R = R + 2.0 * qv[..., :, None] * qv[..., None, :] + 2.0 * q0[..., None, None] * hat(qv)
    return R / n2[..., None, None]


def quat_from_rot(R):
    """Unit quaternion of a rotation matrix (Shepperd's method, batched), q0 >= 0."""
    R = np.asarray(R, dtype=float)
    shp = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    q = np.empty((R.shape[0], 4))
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    choice = np.argmax(np.concatenate([tr[:, None], diag], axis=1), axis=1)
    for k in range(4):
        m = choice == k
        if not np.any(m):
            continue
        Rm = R[m]
        if k == 0:
            t = np.sqrt(1.0 + tr[m]) * 2.0
            q[m, 0] = 0.25 * t
            q[m, 1] = (Rm[:, 2, 1] - Rm[:, 1, 2]) / t
            q[m, 2] = (Rm[:, 0, 2] - Rm[:, 2, 0]) / t
            q[m, 3] = (Rm[:, 1, 0] - Rm[:, 0, 1]) / t
        else:
            i = k - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            t = np.sqrt(1.0 + Rm[:, i, i] - Rm[:, j, j] - Rm[:, l, l]) * 2.0
            q[m, 0] = (Rm[:, l, j] - Rm[:, j, l]) / t
            q[m, 1 + i] = 0.25 * t
            q[m, 1 + j] = (Rm[:, j, i] + Rm[:, i, j]) / t
            q[m, 1 + l] = (Rm[:, l, i] + Rm[:, i, l]) / t
    q = np.where(q[:, :1] < 0, -q, q)
    return q.reshape(shp + (4,))


def rotvec_rotate(theta, R):
    """exp(theta^x) R, batched."""
    return rot(qexp(theta)) @ R


def frame_from_tangent(t, d1_hint=None):
    """A rotation whose third column is the unit tangent t and whose first column
    d1 lies in the plane spanned by t and d1_hint (default: in the x-y plane)."""
    t = np.asarray(t, dtype=float)
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    if d1_hint is None:
        # d1 in the x-y plane, perpendicular to t: e_z x t, or e_x for t along z
        d1 = np.cross(np.array([0.0, 0.0, 1.0]), t)
        bad = np.linalg.norm(d1, axis=-1) < 1e-12
        d1 = np.where(bad[..., None], np.array([1.0, 0.0, 0.0]), d1)
    else:
        d1 = np.broadcast_to(np.asarray(d1_hint, float), t.shape).copy()
        d1 = d1 - np.sum(d1 * t, axis=-1, keepdims=True) * t
    d1 = d1 / np.linalg.norm(d1, axis=-1, keepdims=True)
    d2 = np.cross(t, d1)
    return np.stack([d1, d2, t], axis=-1)
