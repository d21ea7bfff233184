"""Rod meshes: nodes, elements and the reference (stress-free) and initial shapes.

Natural numbering: node k sits at arclength s_k = k h / p (h = L / nelem, p = order);
element e holds nodes e p + a, a = 0..p (modulo n for closed rods, whose last element
wraps to node 0).  Frames: column k of R is the director d_{k+1}; d3 is the unit tangent.

Shapes (all start at the origin):
  straight  r(s) = (s, 0, 0),  d1 = e_y (in the x-y plane), d2 = e_z
  arc       r(s) = rho (sin(s/rho), 1 - cos(s/rho), 0): tangent to +x, bending toward +y;
            d1 = e_z x d3 (the principal normal, toward the centre), d2 = e_z
  circle    the arc with rho = L/(2 pi), closed
  helix     axis +x, radius a, pitch c (rise per turn), b = c/(2 pi), w = sqrt(a^2 + b^2):
            r(s) = (b phi, a sin phi, a (1 - cos phi)), phi = s / w; Frenet frame
            (d1 = principal normal, toward the axis; d2 = binormal), so u = (0, kappa, tau)
            with kappa = a/w^2, tau = b/w^2.
Imperfection A: the first buckling mode of the supports, along d1 for open rods:
A (1 - cos(pi s/2L)) for a clamped-free rod (cantilever column), A (1 - cos(2 pi s/L))/2 for
clamped-clamped or clamped-sliding, A sin(pi s/L) otherwise; closed rods r += A sin(4 pi s/L) d2 (the out-of-plane
two-wave mode in which a twisted ring writhes).  Frames follow the perturbed tangent by the
smallest rotation.
Initial twist T turns: R_init(s) = R_ref(s) Rot_d3(2 pi T s / L) (right-handed about d3).
"""
from dataclasses import dataclass

import numpy as np

from rodsnes.model import fe, so3
from rodsnes.model.partition import NDOF


@dataclass
class RodMesh:
    nelem: int
    order: int
    closed: bool
    length: float
    n_nodes: int
    conn: np.ndarray        # (nelem, p+1) natural node ids
    s_nodes: np.ndarray     # (n,) arclength of the nodes
    x_ref: np.ndarray       # (n,3) stress-free centreline
    q_ref: np.ndarray       # (n,4) stress-free frames (unit quaternions)
    x_init: np.ndarray      # (n,3) initial configuration
    q_init: np.ndarray      # (n,4)
    x_perfect: np.ndarray   # (n,3) reference shape without the imperfection
    q_perfect: np.ndarray   # (n,4)

    @property
    def h(self):
        return self.length / self.nelem

    def element_nodes_s(self):
        """(nelem, p+1) arclength of each element's nodes (unwrapped for closed rods)."""
        e = np.arange(self.nelem)[:, None]
        a = np.arange(self.order + 1)[None, :]
        return (e * self.order + a) * self.h / self.order


def _shape(rod, s):
    """Centreline r(s), tangent r'(s) and the base frame (before imperfection)."""
    L = rod.length
    z = np.zeros_like(s)
    if rod.shape == "straight":
        r = np.stack([s, z, z], axis=1)
        t = np.tile([1.0, 0.0, 0.0], (len(s), 1))
        R = so3.frame_from_tangent(t)
    elif rod.shape in ("arc", "circle"):
        rho = rod.arc_radius if rod.shape == "arc" else (rod.arc_radius or L / (2 * np.pi))
        if rod.shape == "circle" and not rod.arc_radius:
            rho = L / (2 * np.pi)
        ph = s / rho
        r = np.stack([rho * np.sin(ph), rho * (1 - np.cos(ph)), z], axis=1)
        t = np.stack([np.cos(ph), np.sin(ph), z], axis=1)
        R = so3.frame_from_tangent(t)
    elif rod.shape == "helix":
        a = rod.helix_radius
        b = rod.helix_pitch / (2 * np.pi)
        w = np.hypot(a, b)
        ph = s / w
        r = np.stack([b * ph, a * np.sin(ph), a * (1 - np.cos(ph))], axis=1)
        t = np.stack([b * np.ones_like(ph), a * np.cos(ph), a * np.sin(ph)], axis=1) / w
        nrm = np.stack([z, -np.sin(ph), np.cos(ph)], axis=1)  # toward the axis
        R = np.stack([nrm, np.cross(t, nrm), t], axis=-1)
    else:
        raise ValueError(f"unknown shape {rod.shape}")
    return r, t, R


def _imperfection_mode(rod, bc, s):
    """Shape f(s) and slope f'(s) of the imperfection (see the module docstring)."""
    L = rod.length
    ends = (getattr(bc, "start", None), getattr(bc, "end", None))
    if ends == ("clamped", "free") or ends == ("free", "clamped"):
        k = np.pi / (2 * L)
        f, df = 1 - np.cos(k * s), k * np.sin(k * s)
        if ends[0] == "free":
            f, df = 1 - np.cos(k * (L - s)), -k * np.sin(k * (L - s))
        return f, df
    if ends in (("clamped", "clamped"), ("clamped", "sliding")):
        k = 2 * np.pi / L
        return (1 - np.cos(k * s)) / 2, k * np.sin(k * s) / 2
    k = np.pi / L
    return np.sin(k * s), k * np.cos(k * s)


def _imperfect(rod, s, r, t, R, bc=None):
    A = getattr(rod, "imperfection", 0.0) or 0.0
    if A == 0.0:
        return r, R
    L = rod.length
    if rod.closed:
        k = 4 * np.pi / L
        d = R[:, :, 1]
        f, df = np.sin(k * s), k * np.cos(k * s)
    else:
        d = R[:, :, 0]
        f, df = _imperfection_mode(rod, bc, s)
    # derivative of the director along s is neglected only in the tangent used to
    # orient the frame (exact tangent not needed: the frame only has to be admissible)
    r = r + A * f[:, None] * d
    tn = t + A * df[:, None] * d
    tn /= np.linalg.norm(tn, axis=1, keepdims=True)
    # smallest rotation taking t to tn, applied to the frame
    ax = np.cross(t, tn)
    sn = np.linalg.norm(ax, axis=1)
    c = np.sum(t * tn, axis=1)
    ang = np.arctan2(sn, c)
    rv = np.where(sn[:, None] > 1e-15, ax / np.maximum(sn, 1e-300)[:, None] * ang[:, None], 0.0)
    R = so3.rot(so3.qexp(rv)) @ R
    return r, R


def _frames(rod, s, bc=None):
    """(r, R, r0, R0, q_init) at arclengths s: the stress-free centreline and frames with the
    imperfection, without it, and the initial frames' unit quaternions (-rod_twist_turns
    turning them about the tangent)."""
    r0, t, R0 = _shape(rod, s)
    r, R = _imperfect(rod, s, r0, t, R0, bc)
    q = so3.quat_from_rot(R)
    turns = getattr(rod, "twist_turns", 0.0) or 0.0
    phi = 2 * np.pi * turns * s / rod.length
    q_init = so3.qmul(q, so3.qexp(np.stack([0 * phi, 0 * phi, phi], axis=1)))
    return r, q, r0, R0, q_init


def build_mesh(rod, bc=None):
    """Nodes, elements, stress-free and initial shapes of ``rod`` (a scene.Rod); ``bc`` (a
    scene.BC) selects the imperfection mode of open rods."""
    p, ne, L = rod.order, rod.nelem, rod.length
    n = ne * p if rod.closed else ne * p + 1
    s = np.arange(n) * (L / (ne * p))
    conn = (np.arange(ne)[:, None] * p + np.arange(p + 1)[None, :]) % n
    r, q, r0, R0, q_init = _frames(rod, s, bc)
    return RodMesh(nelem=ne, order=p, closed=rod.closed, length=L, n_nodes=n, conn=conn,
                   s_nodes=s, x_ref=r, q_ref=q, x_init=r.copy(), q_init=q_init,
                   x_perfect=r0, q_perfect=so3.quat_from_rot(R0))


def frame_rate_bound(rod, bc=None):
    """An upper bound of the rate |R^T R'| (rad per length) at which the initial frames turn
    along the rod: the shape's (an arc's or ring's 1/rho, a helix's Darboux vector 1/sqrt(a^2 +
    b^2)), the imperfection's tilt of the tangent (A f'' and A f' times the shape's, twice over)
    and -rod_twist_turns' 2 pi T / L."""
    L = rod.length
    if rod.shape in ("arc", "circle"):
        rho = rod.arc_radius or L / (2 * np.pi)
        shape = 1.0 / rho
    elif rod.shape == "helix":
        shape = 1.0 / np.hypot(rod.helix_radius, rod.helix_pitch / (2 * np.pi))
    else:
        shape = 0.0
    A = abs(getattr(rod, "imperfection", 0.0) or 0.0)
    k = 4 * np.pi / L       # the largest wavenumber of the imperfection modes
    tilt = 2.0 * A * k * (k + shape)
    return shape + tilt + 2 * np.pi * abs(getattr(rod, "twist_turns", 0.0) or 0.0) / L


# samples of the initial frames per node interval at most, in element_turns; beyond either
# bound the rate bound itself stands for the turn; frames sampled SAMPLE_CHUNK at a time
MAX_TURN_SAMPLES = 1024
MAX_TOTAL_SAMPLES = 2 ** 24
SAMPLE_CHUNK = 2 ** 18


def element_turns(mesh, rod=None, bc=None):
    """(nelem,) angle (rad) by which the initial frames turn across each element: the sum of
    the rotation angles 2 arccos |q_a . q_b| between consecutive frames along it (a ring's last
    element ends on node 0 after a full turn, so the ends alone would not show it).  The
    rotation interpolation works with rotations relative to a node of the element, unique only
    below half a turn: an element that turns by pi or more (a ring of two elements) cannot be
    represented.  An angle between two frames is seen only modulo a whole turn: with ``rod``
    (and ``bc``, the mesh's), the frames are sampled between the nodes so that no two
    consecutive samples can turn by a quarter turn (frame_rate_bound; the nodes alone when
    they cannot), where the nodes alone took a ring twisted by 73 turns on 24 elements for one
    twisted by 1 turn: a node interval whose sampled path stays below half a turn takes its
    node-to-node angle, one beyond takes the path (which the angle may have wrapped).  Beyond
    MAX_TURN_SAMPLES samples a node interval, or MAX_TOTAL_SAMPLES in all, the bound itself
    (rate x element length: frames turning by millions of turns)."""
    q = mesh.q_init[mesh.conn]                                  # (nelem, p+1, 4)
    dots = np.abs(np.sum(q[:, 1:] * q[:, :-1], axis=2))         # (nelem, p)
    node = 2.0 * np.arccos(np.minimum(dots, 1.0))               # (nelem, p): node to node
    nodal = node.sum(axis=1)
    if rod is None:
        return nodal
    h = mesh.length / (mesh.nelem * mesh.order)                 # a node interval
    rate = frame_rate_bound(rod, bc)
    m = int(np.ceil(rate * h / (0.5 * np.pi))) if np.isfinite(rate) else MAX_TURN_SAMPLES + 1
    if m <= 1:
        return nodal
    p = mesh.order
    if m > MAX_TURN_SAMPLES or mesh.nelem * p * (m + 1) > MAX_TOTAL_SAMPLES:
        return np.full(mesh.nelem, rate * h * p)
    e = mesh.element_nodes_s()                                  # (nelem, p+1), unwrapped
    t = np.arange(m + 1) / m
    out = np.empty(mesh.nelem)
    step = max(1, SAMPLE_CHUNK // (p * (m + 1)))                # elements a chunk
    for lo in range(0, mesh.nelem, step):
        ec = e[lo:lo + step]
        s = (ec[:, :-1, None] + (ec[:, 1:, None] - ec[:, :-1, None]) * t).ravel()
        qs = _frames(rod, s, bc)[4].reshape(len(ec), p, m + 1, 4)
        d = np.abs(np.sum(qs[..., 1:, :] * qs[..., :-1, :], axis=-1))
        path = (2.0 * np.arccos(np.minimum(d, 1.0))).sum(axis=-1)    # (chunk, p)
        # a node interval whose frames travel less than half a turn: its node-to-node angle
        # is the rotation itself (what the interpolation needs); beyond, it may have wrapped
        # and the path stands for it (at least half a turn: refused either way)
        out[lo:lo + step] = np.where(path < np.pi, node[lo:lo + step], path).sum(axis=1)
    return out


def reference_length(rod, bc=None, samples=4096):
    """Arclength of the stress-free centreline with its imperfection (-rod_imperfection),
    measured along a polyline of ``samples`` segments: L for a perfect rod; an imperfection
    lengthens it (by about (A f')^2 / 2 per unit length)."""
    L = rod.length
    s = np.linspace(0.0, L, samples + 1)
    r0, t, R0 = _shape(rod, s)
    r, _ = _imperfect(rod, s, r0, t, R0, bc)
    return float(np.linalg.norm(np.diff(r, axis=0), axis=1).sum())


def lumped_weights(mesh, layout):
    """M_i = int N_i ds for the owned nodes of ``layout`` (partition.Layout): the row-sum
    lumping of the consistent mass matrix of a unit line density, positive for the equispaced
    Lagrange elements of order 1..4 (the minimiser's metric).  Collective."""
    xi, w = fe.gauss_legendre(mesh.order + 1)
    N, _, _ = fe.lagrange(mesh.order, xi)
    we = (w * mesh.h / 2.0) @ N                       # (p+1,) per element node
    loc = np.zeros((len(layout.local_nodes), NDOF))
    # the sums in the elements' order, as np.add.at's (12 ms at 10^4 elements, numpy's
    # unbuffered loop) but by one bincount of the column that is read
    conn = np.asarray(layout.lconn)
    loc[:, 0] = np.bincount(conn.ravel(), weights=np.broadcast_to(we, conn.shape).ravel(),
                            minlength=len(loc))
    V = layout.create_vec()
    layout.add_to_global(loc, V)
    M = V.getArray(readonly=True).reshape(-1, NDOF)[:, 0].copy()
    V.destroy()
    return M
