"""Link, twist and writhe of a discrete rod (Calugareanu-White-Fuller: Lk = Tw + Wr).

Pure numpy, no PETSc.  A rod is given by its centreline nodes ``x`` (n, 3), in order, and
the first director ``d1`` (n, 3) at the same nodes; ``closed`` says whether the last node is
joined to the first by an edge (do not repeat the first node at the end; a repeated node is
dropped).  The rod may shear, so ``d1`` is never assumed to be exactly normal to the tangent:
it is projected onto the plane normal to the local discrete tangent wherever that matters.

Conventions
-----------
* Gauss kernel: for two oriented curves a, b,
      G(a, b) = (1/4pi) oint oint (da x db) . (a - b) / |a - b|^3 .
  With it a right-handed (positive) crossing counts +1: Lk of a right-handed double helix,
  Wr of a right-handed toroidal supercoil and Tw of a director turning right-handedly about
  the tangent (d1 -> t x d1) are all positive.
* Writhe  Wr = G(x, x) (principal value; for a polygon: the sum over pairs of distinct,
  non-adjacent edges, adjacent edges contributing exactly 0).
* Link    Lk = G(x, x + w d1) for a small ribbon width w.
* Twist   Tw = (1/2pi) * total signed rotation of d1 about the tangent, measured relative
  to parallel transport along the polygon (see `twist`).

For a closed framed polygon, Lk is an integer up to round-off and the discrete
Calugareanu-White-Fuller identity Lk = Tw + Wr holds to round-off: the discrete parallel
transport across a vertex is the limit of parallel transport along an infinitesimal
circular fillet of that corner, and the polygon writhe is the limit of the filleted curve's
writhe, so Fuller's holonomy argument applies exactly (no discretisation error in the
identity, only in how well the polygon represents a smooth rod).

Methods and references
----------------------
* Writhe and link: the Gauss double integral over a pair of straight segments is computed
  exactly as the signed solid angle subtended at the origin by the parallelogram
  {a(s) - b(t)} (Levitt, J. Mol. Biol. 170, 723 (1983); Klenin & Langowski, Biopolymers 54,
  307 (2000)).  Instead of Klenin & Langowski's four arcsines of face normals we split the
  (convex, spherical) quadrilateral along a diagonal and evaluate the two triangles with
  the Van Oosterom-Strackee formula (IEEE Trans. Biomed. Eng. 30, 125 (1983)),
      tan(Omega/2) = a.(b x c) / (1 + a.b + b.c + c.a)   (a, b, c unit vectors),
  which uses atan2 and therefore keeps full accuracy near +-2pi (nearly touching or
  nearly parallel segments), where arcsin loses half the digits.  O(N^2) over segment pairs:
  by the compiled kernel (_topology_kernel.c, built by setup.py, the same formula in one pass)
  where it is built, else vectorised numpy in row chunks to bound memory (the reference;
  KERNEL = "numpy" forces it).  The 60-element plectoneme's link check took 8 ms a load step
  in numpy.
* Twist: discrete parallel transport (minimal rotation taking edge tangent t_i to t_{i+1},
  the "space-parallel transport" of Bergou et al., Discrete Elastic Rods, ACM TOG 27 (2008)).
* Open rods: closure at infinity along the clamping axis (see `close_open_rod`), as used
  for magnetic-tweezers / plectoneme experiments (e.g. Vologodskii & Marko, Biophys. J. 73,
  123 (1997); Rossetto & Maggs, J. Chem. Phys. 118, 9864 (2003); Starostin, "On the
  writhing number of a non-closed curve" (2005)).
"""
import ctypes

import numpy as np

from rodsnes import compiled

__all__ = ["writhe", "twist", "link", "close_open_rod", "topology"]

KERNEL = "auto"     # the Gauss sums: "auto" (compiled where built, else numpy) or "numpy"

FOUR_PI = 4.0 * np.pi
TWO_PI = 2.0 * np.pi
_PAIRS_PER_CHUNK = 200_000   # segment pairs evaluated at once (memory ~ 100 bytes x 30 / pair)


# ----------------------------------------------------------------------------- helpers
def _dot(a, b):
    return np.einsum("...k,...k->...", a, b)


def _cross(a, b):
    # explicit components: faster than np.cross on large stacked arrays
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _unit(v):
    """v / |v|, zero vectors left at zero."""
    n = np.sqrt(_dot(v, v))
    return v / np.where(n > 0.0, n, 1.0)[..., None]


def _as_curve(x, d1=None, closed=True):
    """Float copies, shape checks; for closed curves drop a repeated last node."""
    x = np.array(x, dtype=float, copy=True)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError("x must have shape (n, 3)")
    if d1 is not None:
        d1 = np.array(d1, dtype=float, copy=True)
        if d1.shape != x.shape:
            raise ValueError("d1 must have the same shape as x")
    if closed and len(x) > 1:
        scale = np.max(np.abs(x - x[0])) if len(x) > 1 else 0.0
        if np.linalg.norm(x[-1] - x[0]) <= 1e-14 * max(scale, 1e-300):
            x = x[:-1]
            d1 = None if d1 is None else d1[:-1]
    nmin = 3 if closed else 2
    if len(x) < nmin:
        raise ValueError("need at least %d nodes" % nmin)
    if np.any(~np.isfinite(x)) or (d1 is not None and np.any(~np.isfinite(d1))):
        raise ValueError("non-finite input")
    return x, d1


def _vertices(x, closed):
    """Polygon vertex list with segment k = V[k] -> V[k+1] (first node appended if closed)."""
    return np.vstack([x, x[:1]]) if closed else x


def _edge_tangents(x, closed):
    V = _vertices(x, closed)
    e = np.diff(V, axis=0)
    le = np.linalg.norm(e, axis=1)
    if np.any(le <= 0.0):
        raise ValueError("zero-length edge in the polygon")
    return e / le[:, None], le


def _node_directors(x, d1, closed):
    """d1 projected on the plane normal to the node tangent (mean of the adjacent unit edge
    tangents; the single edge tangent at the ends of an open rod), normalised."""
    t, _ = _edge_tangents(x, closed)
    if closed:
        tn = t + np.roll(t, 1, axis=0)           # node i: edges i-1 and i
    else:
        tn = np.vstack([t[:1], t[:-1] + t[1:], t[-1:]])
    tn = _unit(tn)
    u = d1 - _dot(d1, tn)[:, None] * tn
    nu = np.linalg.norm(u, axis=1)
    if np.any(nu <= 1e-12 * np.maximum(np.linalg.norm(d1, axis=1), 1e-300)):
        raise ValueError("d1 is parallel to the tangent at some node (or a hairpin vertex)")
    return u / nu[:, None]


def _edge_directors(x, d1, closed):
    """Unit edge tangents t_k and edge directors u_k: the average of d1 at the two end
    nodes of edge k, projected on the plane normal to t_k, normalised."""
    t, _ = _edge_tangents(x, closed)
    n = len(x)
    i0 = np.arange(len(t))
    i1 = (i0 + 1) % n
    dn = _unit(d1)
    u = dn[i0] + dn[i1]
    u -= _dot(u, t)[:, None] * t
    nu = np.linalg.norm(u, axis=1)
    if np.any(nu <= 1e-12):
        raise ValueError("d1 turns by ~pi over one edge (or lies along the edge): refine the rod")
    return t, u / nu[:, None]


def _transport(a, b, v):
    """Minimal rotation taking unit a to unit b (about a x b), applied to v (batched)."""
    c = _cross(a, b)
    cb = _dot(a, b)
    if np.any(cb <= -1.0 + 1e-12):
        raise ValueError("hairpin vertex (tangent reverses): parallel transport undefined")
    cv = _cross(c, v)
    return v + cv + _cross(c, cv) / (1.0 + cb)[..., None]


# ------------------------------------------------------------- Gauss integral, segments
def _gauss_block(P, Q, a0, a1, b0, b1):
    """Exact Gauss integrals 4pi*G over segment pairs (P_a P_{a+1}, Q_b Q_{b+1}) for
    a in [a0, a1), b in [b0, b1): array (a1-a0, b1-b0).

    The map (s, t) -> a(s) - b(t) sends the unit square onto a parallelogram lying in a
    plane that avoids the origin (unless the segments meet), so the integral equals minus
    the signed solid angle of that parallelogram (oriented by d/ds x d/dt = -(t_a x t_b)),
    computed as two Van Oosterom-Strackee triangles."""
    U = _unit(P[a0:a1 + 1, None, :] - Q[None, b0:b1 + 1, :])
    v00, v10 = U[:-1, :-1], U[1:, :-1]    # p1 - q1, p2 - q1
    v11, v01 = U[1:, 1:], U[:-1, 1:]      # p2 - q2, p1 - q2
    d0010 = _dot(v00, v10)
    d1011 = _dot(v10, v11)
    d0011 = _dot(v00, v11)
    d1101 = _dot(v11, v01)
    d0100 = _dot(v01, v00)
    c = _cross(v10, v11)
    n1 = _dot(v00, c)
    c = _cross(v11, v01)
    n2 = _dot(v00, c)
    om = np.arctan2(n1, 1.0 + d0010 + d1011 + d0011)
    om += np.arctan2(n2, 1.0 + d0011 + d1101 + d0100)
    return -2.0 * om


def _rows_per_chunk(ncols):
    return max(1, _PAIRS_PER_CHUNK // max(ncols, 1))


def _declare(lib):
    f64 = compiled.F64
    return compiled.Foreign(lib.rodsnes_gauss_sum,
                            [f64, ctypes.c_int64, f64, ctypes.c_int64, ctypes.c_int,
                             ctypes.c_int], ctypes.c_double)


# the compiled Gauss sum, or False when the library is not built or does not load.
_load = compiled.loader("rodsnes.model._topology_kernel", _declare)


def _kernel():
    return _load() if KERNEL != "numpy" else False


def _gauss_cross(P, Q):
    """sum over all segment pairs of 4pi*G: polygons P, Q given as vertex lists."""
    fn = _kernel()
    if fn:
        P, Q = (np.ascontiguousarray(v, dtype=float) for v in (P, Q))
        return float(fn(P, len(P), Q, len(Q), 0, 0))
    na, nb = len(P) - 1, len(Q) - 1
    step = _rows_per_chunk(nb)
    parts = []
    for a0 in range(0, na, step):
        a1 = min(na, a0 + step)
        parts.append(np.sum(_gauss_block(P, Q, a0, a1, 0, nb)))
    return float(np.sum(parts))


def _gauss_self(V, closed):
    """sum over unordered pairs {a, b} of distinct non-adjacent segments of 4pi*G."""
    fn = _kernel()
    if fn:
        V = np.ascontiguousarray(V, dtype=float)
        return float(fn(V, len(V), V, len(V), 1, int(bool(closed))))
    m = len(V) - 1
    total = []
    a0 = 0
    while a0 < m:
        step = _rows_per_chunk(m - a0)
        a1 = min(m, a0 + step)
        G = _gauss_block(V, V, a0, a1, a0, m)
        a = np.arange(a0, a1)[:, None]
        b = np.arange(a0, m)[None, :]
        keep = b > a + 1
        if closed:
            keep &= ~((a == 0) & (b == m - 1))
        total.append(np.sum(np.where(keep, G, 0.0)))
        a0 = a1
    return float(np.sum(total))


# ----------------------------------------------------------------------------- public API
def writhe(x, closed=True):
    """Writhe of the polygon through the nodes ``x`` (n, 3).

    Wr = (1/4pi) sum_{i != j} Omega_ij, the Gauss double integral
    (1/4pi) oint oint (dr1 x dr2).(r1 - r2)/|r1 - r2|^3 evaluated *exactly* for the
    polygon: each pair of straight edges contributes the signed solid angle Omega_ij of the
    parallelogram {r1(s) - r2(t)} (Levitt 1983; Klenin & Langowski 2000), computed as two
    spherical triangles with the Van Oosterom-Strackee atan2 formula.  Adjacent and
    identical edges contribute exactly 0.  No quadrature error: the only discretisation
    error is that of the polygon itself (O(h^2) for a smooth curve sampled at spacing h).

    ``closed=False`` gives the open-curve double integral (not a topological quantity; use
    `close_open_rod` / `topology` for clamped open rods).  Cost O(n^2), chunked memory.
    Sign: right-handed crossings positive (a right-handed toroidal supercoil has Wr > 0).
    """
    x, _ = _as_curve(x, None, closed)
    _edge_tangents(x, closed)                  # checks for zero-length edges
    V = _vertices(x, closed)
    return 2.0 * _gauss_self(V, closed) / FOUR_PI


def twist(x, d1, closed=True):
    """Twist Tw = (1/2pi) x total rotation of d1 about the tangent, relative to parallel
    transport along the polygon.

    Where d1 lives: d1 is given at the nodes; the director of edge k (nodes k, k+1) is
    u_k = normalise(P_k (d1_k/|d1_k| + d1_{k+1}/|d1_{k+1}|)), P_k the projector on the plane
    normal to the unit edge tangent t_k (this absorbs shear: d1 need not be normal to t).
    Across the vertex between edges k and k+1, u_k is parallel-transported by the minimal
    rotation R_k taking t_k to t_{k+1} (rotation about t_k x t_{k+1}), and the signed angle
        phi_k = atan2( t_{k+1} . (R_k u_k x u_{k+1}),  R_k u_k . u_{k+1} )  in (-pi, pi]
    is the twist increment (positive = right-handed about the tangent).  Tw = sum phi_k / 2pi
    over all vertices of a closed polygon.  For an open rod (``closed=False``) the sum runs
    over the interior vertices plus the two end half-edges (the angle from d1 at the first
    node to u_0 about t_0, and from u_last to d1 at the last node), so that Tw is the
    rotation of d1 from the first node to the last (exactly n for a straight rod whose end
    director is turned n turns).
    Requires d1 to turn by less than pi per edge (otherwise the count is ambiguous).
    """
    x, d1 = _as_curve(x, d1, closed)
    t, u = _edge_directors(x, d1, closed)
    if closed:
        k1 = np.roll(np.arange(len(t)), -1)
        a, b, ua, ub = t, t[k1], u, u[k1]
    else:
        a, b, ua, ub = t[:-1], t[1:], u[:-1], u[1:]
    Pu = _transport(a, b, ua)
    phi = np.arctan2(_dot(b, _cross(Pu, ub)), _dot(Pu, ub))
    tot = np.sum(phi)
    if not closed:
        # the two end half-edges: from d1 at the first node to u_0 about t_0, and from
        # u_last to d1 at the last node about t_last (each d1 projected normal to its edge)
        for tk, v0, v1 in ((t[0], d1[0], u[0]), (t[-1], u[-1], d1[-1])):
            v0 = v0 - np.dot(v0, tk) * tk
            v1 = v1 - np.dot(v1, tk) * tk
            tot += np.arctan2(np.dot(tk, np.cross(v0, v1)), np.dot(v0, v1))
    return float(tot / TWO_PI)


def default_ribbon_width(x, closed=True):
    """1e-3 of the shortest edge: the ribbon x + w d1 then stays within a thin tube in
    which no other part of the centreline (at distance >~ one edge, or the contact
    distance of a physical rod) can pass, so the linking number is that of the w -> 0
    limit, i.e. exactly the framing integer Tw + Wr."""
    x, _ = _as_curve(x, None, closed)
    _, le = _edge_tangents(x, closed)
    return 1e-3 * float(np.min(le))


def link(x, d1, closed=True, ribbon_width=None):
    """Gauss linking number of the centreline polygon x with the ribbon-edge polygon
    x + w d1 (d1 projected on the plane normal to the node tangent and normalised).

    Computed with the exact polygon-polygon Gauss integral (sum over all edge pairs of the
    exact segment-segment solid angles, as in `writhe`), not a quadrature, so for a closed
    rod the result is an integer up to round-off (~1e-12).  ``ribbon_width`` w defaults to
    `default_ribbon_width` (1e-3 x shortest edge); any w small enough that the ribbon does
    not pass through the centreline gives the same integer.  With ``closed=False`` this is
    the (non-integer, non-topological) open-curve Gauss integral; use `topology` instead.
    """
    x, d1 = _as_curve(x, d1, closed)
    u = _node_directors(x, d1, closed)
    w = default_ribbon_width(x, closed) if ribbon_width is None else float(ribbon_width)
    if not w > 0.0:
        raise ValueError("ribbon_width must be positive")
    P = _vertices(x, closed)
    Q = _vertices(x + w * u, closed)
    return _gauss_cross(P, Q) / FOUR_PI


def close_open_rod(x, d1, axis=None, far=None, n_twist_nodes=8, return_phi=False):
    """Close an open rod whose ends are clamped along a common axis.

    Standard closure at infinity used for magnetic-tweezers / plectoneme experiments (e.g.
    Vologodskii & Marko 1997; Rossetto & Maggs 2003): both ends are extended far along the
    axis, x[-1] -> B = x[-1] + far e and x[0] <- A = x[0] - far e, and B is joined back to A
    by a large planar rectangle B -> B + H f -> A + H f -> A (H = far), lying in the plane
    through the axis spanned by e and f = g x e, where g is d1 at the end x[-1] projected
    normal to e.  Along the whole closure d1 = g, which is normal to the closure plane, so
    it is parallel-transported exactly: the closure adds no twist.  Hence Lk, Tw, Wr of the
    closed curve are the open rod's topology: Tw is the rod's twist (including the transport
    from the end tangents onto the axis), Wr the writhe of the rod closed along its axis,
    and Lk the number of turns imposed between the two clamps (an integer when the end
    directors agree modulo full turns).  When the two ends lie on one line along the axis,
    the result does not depend on ``far`` at all (beyond round-off) as long as the closure
    stays clear of the rod: growing ``far`` deforms the closed curve without crossings, so
    Lk is fixed, Tw is fixed (the closure carries no twist), hence Wr = Lk - Tw is fixed.

    If d1 at the two ends differ (projected normal to e) by a fraction of a turn phi, the
    closure carries that rotation, spread over ``n_twist_nodes`` nodes on the extension
    before x[0] (it then belongs to Tw; Lk is the turn count rounded accordingly).  If the
    ends are not on one line along the axis the closure is still a valid closed curve but
    no longer exactly planar (extra Wr/Tw of order offset/far, hence the large default far).

    axis: clamping direction; default the end-to-end vector x[-1] - x[0] (or the mean end
    tangent if the ends nearly coincide); it is oriented from x[0] to x[-1].
    far:  extension length and rectangle height; default 1e4 x rod size (the largest
          distance of a node from the mid-point of the ends, or the end-to-end distance).
    Returns the closed curve (xc, d1c); pass it with closed=True.  The rod's nodes come
    first (xc[:n] = x, d1c[:n] = d1).
    """
    x, d1 = _as_curve(x, d1, closed=False)
    t, _ = _edge_tangents(x, closed=False)
    chord = x[-1] - x[0]
    size = max(np.max(np.linalg.norm(x - 0.5 * (x[0] + x[-1]), axis=1)),
               np.linalg.norm(chord), 1e-300)
    tend = t[0] + t[-1]
    if axis is None:
        e = chord if np.linalg.norm(chord) > 1e-8 * size else tend
    else:
        e = np.asarray(axis, dtype=float).reshape(3)
    ne = np.linalg.norm(e)
    if not ne > 0.0:
        raise ValueError("cannot determine the closure axis; pass axis=")
    e = e / ne
    ref = chord if np.linalg.norm(chord) > 1e-8 * size else tend
    if np.dot(e, ref) < 0.0:
        e = -e
    far = 1e4 * size if far is None else float(far)
    if not far > size:
        raise ValueError("far must exceed the rod size")

    def perp(v):
        vp = v - np.dot(v, e) * e
        nv = np.linalg.norm(vp)
        if not nv > 1e-12 * np.linalg.norm(v):
            raise ValueError("d1 at an end is parallel to the closure axis")
        return vp / nv

    g1, g0 = perp(d1[-1]), perp(d1[0])
    f = np.cross(g1, e)
    B = x[-1] + far * e
    A = x[0] - far * e
    H = far
    corners = np.array([B, B + H * f, A + H * f, A])
    # fractional mismatch carried on the last extension (A -> x[0])
    phi = np.arctan2(np.dot(e, np.cross(g1, g0)), np.dot(g1, g0))
    k = np.arange(1, n_twist_nodes + 1) / (n_twist_nodes + 1.0)
    ext = A + k[:, None] * (x[0] - A)
    ang = phi * k
    # Rodrigues rotation of g1 about e (g1 normal to e)
    gk = (np.cos(ang)[:, None] * g1 + np.sin(ang)[:, None] * np.cross(e, g1))
    xc = np.vstack([x, corners, ext])
    d1c = np.vstack([d1, np.tile(g1, (4, 1)), gk])
    if return_phi:
        return xc, d1c, phi
    return xc, d1c


def topology(x, d1, closed, axis=None, ribbon_width=None):
    """Link, twist and writhe of a rod: dict(link=Lk, twist=Tw, writhe=Wr).

    Closed rods are used as given: Lk is the exact Gauss linking number (an integer up to
    round-off) and Lk = Tw + Wr holds to round-off for the framed polygon.  Open rods are
    first closed with `close_open_rod` (ends clamped along ``axis``); when the end directors
    differ by a fraction phi / 2 pi of a turn the closure carries that rotation, and it is
    taken back out of Tw and Lk: Tw is the rod's own twist, Wr the writhe of the closed curve,
    and Lk = Tw + Wr the turns put in between the clamps (2.42 after 2.42 imposed turns, not
    the nearest whole number), still an integer for whole turns.
    """
    phi = 0.0
    if not closed:
        x, d1, phi = close_open_rod(x, d1, axis=axis, return_phi=True)
    closure = phi / (2 * np.pi)
    return dict(link=link(x, d1, True, ribbon_width=ribbon_width) - closure,
                twist=twist(x, d1, True) - closure,
                writhe=writhe(x, True))
