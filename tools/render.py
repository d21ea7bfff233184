#!/usr/bin/env python3
"""Pictures of a rodsnes result: ``tools/render.py DIR [options]`` reads DIR/result.h5.

The rod is drawn as a tube of its true radius (a circle swept along the centreline in the plane of
the directors d1, d2, Lambert + specular shading, one darker stripe along the material line d1 so
that twist is visible) or, when the tube would be thinner than ~2.5 pixels or has too many faces,
as a thick line with depth cueing (far parts lighter). Between nodes the centreline, the directors
and the field are evaluated with the elements' Lagrange shape functions (uniform mesh, equispaced
nodes: node i at s_i = i L/(n-1), or i L/n on a ring), so a coarse high-order mesh is drawn as the
finite element solution it is, not as a polygon through its nodes.

Colour fields (``--field``):
    curvature       bending curvature sqrt(u1^2 + u2^2) from ``strain_u`` [1/length]; without
                    ``strain_u``: the centreline's discrete curvature (circle through 3 nodes)
    twist           u3 from ``strain_u`` [rad/length]; without it: from the relative rotation
                    of consecutive director frames
    contact_force   contact line-force magnitude [force/length], nearest quadrature point
    none            one colour

Views: iso (elevation 25, azimuth -60), top (look down -z: x right, y up), front (look along +y:
x right, z up), side (look along -x: y right, z up); all orthographic, equal scale on every axis.

Outputs (default folder DIR/pictures): ``step_KKKKK.png`` (all views in one figure) or, with
``--separate``, ``step_KKKKK_VIEW.png``; ``--movie`` writes ``frames/frame_IIIII.png`` (one per
complete step, the same axis limits and colour scale in every frame) and, if ffmpeg is on the PATH,
``movie.mp4``.
"""
import argparse
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    from rodsnes.io import results as output
    from rodsnes.model import so3
    from rodsnes.model.fe import lagrange
except ImportError:  # run from a checkout without pip install -e
    sys.path.insert(0, str(ROOT))
    from rodsnes.io import results as output
    from rodsnes.model import so3
    from rodsnes.model.fe import lagrange

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import cm, colors  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

VIEWS = {  # name: (elevation, azimuth) in degrees, matplotlib convention
    "iso": (25.0, -60.0),
    "top": (90.0, -90.0),
    "front": (0.0, -90.0),
    "side": (0.0, 0.0),
}
HIDDEN_AXIS = {"top": "z", "front": "y", "side": "x"}  # the axis pointing at the viewer
FIELDS = ("curvature", "twist", "contact_force", "none")
CMAPS = {"curvature": "viridis", "twist": "coolwarm", "contact_force": "plasma"}
ROD_COLOUR = "#4f7fbf"


# --------------------------------------------------------------------------- fields at nodes
def _ds_nodes(meta):
    n = int(meta["n_nodes"])
    return float(meta["length"]) / (n if meta["closed"] else max(n - 1, 1))


def centreline_curvature(P, closed):
    """Discrete curvature at nodes: 1/radius of the circle through (P[i-1], P[i], P[i+1]);
    exact on circular arcs. Open rods copy the neighbour's value to the end nodes."""
    if len(P) < 3:
        return np.zeros(len(P))
    a, b, c = (np.roll(P, 1, 0), P, np.roll(P, -1, 0))
    ab, bc, ca = b - a, c - b, a - c
    area2 = np.linalg.norm(np.cross(ab, bc), axis=1)          # twice the triangle area
    den = np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) * np.linalg.norm(ca, axis=1)
    k = np.where(den > 0, 2.0 * area2 / np.where(den > 0, den, 1.0), 0.0)
    if not closed:
        k[0], k[-1] = k[1], k[-2]
    return k


def frame_twist(R, ds, closed):
    """u3 at nodes from consecutive frames: vee(log(R_i^T R_(i+1)))_3 / ds, averaged onto nodes."""
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    if closed:
        rel = np.concatenate([rel, (R[-1].T @ R[0])[None]], axis=0)
    u3 = so3.qlog(so3.quat_from_rot(rel))[:, 2] / ds
    if closed:
        return 0.5 * (u3 + np.roll(u3, 1))
    out = np.empty(len(R))
    out[1:-1] = 0.5 * (u3[1:] + u3[:-1])
    out[0], out[-1] = u3[0], u3[-1]
    return out


def field_values(step, field):
    """(values at nodes or None for qp-only fields, label, colormap name, symmetric?)."""
    meta = step["meta"]
    closed = bool(meta["closed"])
    if field == "curvature":
        if "strain_u" in step:
            u = np.asarray(step["strain_u"])
            return np.hypot(u[:, 0], u[:, 1]), "bending curvature $\\sqrt{u_1^2+u_2^2}$ [1/length]", False
        return centreline_curvature(step["positions"], closed), "centreline curvature [1/length]", False
    if field == "twist":
        if "strain_u" in step:
            return np.asarray(step["strain_u"])[:, 2], "twist $u_3$ [rad/length]", True
        return (frame_twist(step["directors"], _ds_nodes(meta), closed),
                "twist $u_3$ from the frames [rad/length]", True)
    if field == "contact_force":
        return None, "contact line force [force/length]", False
    if field == "none":
        return None, None, False
    raise ValueError(f"unknown field {field!r}: one of {FIELDS}")


# --------------------------------------------------------------------------- display curve
class Curve:
    """Display points along the rod: centreline P (m,3), orthonormal frames D (m,3,3) (columns d1, d2,
    d3), reference arclength s (m,), and field values c (m,) or None."""

    def __init__(self, P, D, s, c, closed):
        self.P, self.D, self.s, self.c, self.closed = P, D, s, c, closed


def _orthonormal(d1, d3):
    d3 = d3 / np.linalg.norm(d3, axis=1, keepdims=True)
    d1 = d1 - np.sum(d1 * d3, axis=1, keepdims=True) * d3
    d1 = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
    return np.stack([d1, np.cross(d3, d1), d3], axis=-1)


def display_curve(step, field, target_points=600):
    """Sample the finite element solution at sub-points of every element (see the module docstring)."""
    meta = step["meta"]
    n, closed = int(meta["n_nodes"]), bool(meta["closed"])
    p, ne = int(meta.get("order", 1)), int(meta.get("nelem", 0))
    L = float(meta["length"])
    P, R = np.asarray(step["positions"], float), np.asarray(step["directors"], float)
    vals, _, _ = field_values(step, field)
    if ne > 0 and p >= 1 and n == ne * p + (0 if closed else 1):
        m = p * max(1, min(16, math.ceil(target_points / (ne * p))))    # samples per element
        xi = -1.0 + 2.0 * np.arange(m) / m
        N = lagrange(p, xi)[0]                                          # (m, p+1)
        conn = (np.arange(ne)[:, None] * p + np.arange(p + 1)[None, :]) % n   # (ne, p+1)

        def interp(a):  # nodal (n, ...) -> (ne*m, ...)
            return np.einsum("ja,ea...->ej...", N, a[conn]).reshape((ne * m,) + a.shape[1:])

        Pd = interp(P)
        D = _orthonormal(interp(R[:, :, 0]), interp(R[:, :, 2]))
        s = ((np.arange(ne)[:, None] + (xi[None, :] + 1) / 2) * (L / ne)).ravel()
        c = interp(vals) if vals is not None else None
        if not closed:  # the last node
            Pd, D = np.vstack([Pd, P[-1:]]), np.concatenate([D, _orthonormal(R[-1:, :, 0], R[-1:, :, 2])])
            s = np.append(s, L)
            c = np.append(c, vals[-1]) if c is not None else None
    else:  # unknown layout: straight segments between nodes
        Pd, D, s, c = P, _orthonormal(R[:, :, 0], R[:, :, 2]), output.node_arclength(meta), vals
    if field == "contact_force":
        if "contact_force" in step and "qp_s" in step:
            c = output.qp_to_nodes(step["qp_s"], step["contact_force"], s, L if closed else None).astype(float)
        else:
            c = np.zeros(len(Pd))
    return Curve(Pd, D, s, c, closed)


# --------------------------------------------------------------------------- geometry for drawing
def view_vectors(elev, azim):
    """Unit vectors in data space: towards the viewer, screen-up, screen-right."""
    e, a = np.radians(elev), np.radians(azim)
    toward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    up = np.array([-np.sin(e) * np.cos(a), -np.sin(e) * np.sin(a), np.cos(e)])
    right = np.cross(up, toward)
    return toward, up, right


def tube_faces(curve, radius, K):
    """Quads of the swept circle: vertices (F,4,3), outward normals (F,3), segment index (F,),
    angular sector index (F,), plus end-cap polygons (list of (K,3) arrays and normals)."""
    P, D = curve.P, curve.D
    m = len(P)
    phi = 2 * np.pi * np.arange(K) / K
    radial = np.cos(phi)[None, :, None] * D[:, None, :, 0] + np.sin(phi)[None, :, None] * D[:, None, :, 1]
    ring = P[:, None, :] + radius * radial                       # (m, K, 3)
    i0 = np.arange(m if curve.closed else m - 1)
    i1 = (i0 + 1) % m
    k0 = np.arange(K)
    k1 = (k0 + 1) % K
    quads = np.stack([ring[i0][:, k0], ring[i0][:, k1], ring[i1][:, k1], ring[i1][:, k0]], axis=2)
    normals = (radial[i0][:, k0] + radial[i0][:, k1] + radial[i1][:, k1] + radial[i1][:, k0])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    seg = np.repeat(i0, K)
    sector = np.tile(k0, len(i0))
    caps = []
    if not curve.closed:
        caps = [(ring[0], -D[0, :, 2], 0), (ring[-1], D[-1, :, 2], m - 2)]
    return quads.reshape(-1, 4, 3), normals.reshape(-1, 3), seg, sector, caps


def shade(base_rgb, normals, toward, up, right, ambient=0.32):
    """Lambert + Blinn specular with a light above-left of the camera; colours (F,3) in [0,1]."""
    light = toward + 0.55 * up - 0.35 * right
    light /= np.linalg.norm(light)
    half = light + toward
    half /= np.linalg.norm(half)
    lam = np.clip(normals @ light, 0.0, 1.0)
    spec = np.clip(normals @ half, 0.0, 1.0) ** 24
    rgb = base_rgb * (ambient + (1 - ambient) * lam)[:, None] + 0.30 * spec[:, None]
    return np.clip(rgb, 0.0, 1.0)


def seg_colours(curve, norm, cmap):
    """Base colour of every segment (field averaged over its two end points)."""
    m = len(curve.P)
    i0 = np.arange(m if curve.closed else m - 1)
    if curve.c is None or norm is None:
        return np.tile(colors.to_rgb(ROD_COLOUR), (len(i0), 1))
    cs = 0.5 * (curve.c[i0] + curve.c[(i0 + 1) % m])
    return np.asarray(cmap(norm(cs)))[:, :3]


def draw_tube(ax, curve, radius, view, norm, cmap, K, stripe=True):
    toward, up, right = view_vectors(*VIEWS[view])
    quads, normals, seg, sector, caps = tube_faces(curve, radius, K)
    base = seg_colours(curve, norm, cmap)
    rgb = base[seg]
    if stripe:  # material line along d1: one darker sector shows twist
        rgb = np.where((sector == 0)[:, None], rgb * 0.55, rgb)
    front = normals @ toward > -0.05          # back faces are hidden by the front ones: cull
    fc = shade(rgb[front], normals[front], toward, up, right)
    polys = list(quads[front])
    for ring, nrm, si in caps:
        if nrm @ toward > 0:
            polys.append(ring)
            fc = np.vstack([fc, shade(base[si][None], nrm[None], toward, up, right)])
    coll = Poly3DCollection(polys, facecolors=fc, edgecolors=fc, linewidths=0.25)
    ax.add_collection3d(coll)


def draw_line(ax, curve, view, norm, cmap, width_pt):
    toward = view_vectors(*VIEWS[view])[0]
    m = len(curve.P)
    i0 = np.arange(m if curve.closed else m - 1)
    segs = np.stack([curve.P[i0], curve.P[(i0 + 1) % m]], axis=1)
    depth = segs.mean(axis=1) @ toward
    order = np.argsort(depth)                      # far first (painter)
    rgb = seg_colours(curve, norm, cmap)
    span = max(depth.max() - depth.min(), 1e-300)
    fade = 0.45 * (depth.max() - depth) / span    # far: blended towards white
    rgb = rgb * (1 - fade[:, None]) + fade[:, None]
    for idx in np.array_split(order, max(1, len(order) // 2000)):  # keep depth order across chunks
        ax.add_collection3d(Line3DCollection(segs[idx], colors=rgb[idx], linewidths=width_pt,
                                             capstyle="round", joinstyle="round"))


# --------------------------------------------------------------------------- figure
def bounds(curves, radius):
    lo = np.min([c.P.min(axis=0) for c in curves], axis=0) - radius
    hi = np.max([c.P.max(axis=0) for c in curves], axis=0) + radius
    return lo, hi


def field_limits(curves, symmetric, min_span=1e-12):
    vals = np.concatenate([c.c for c in curves if c.c is not None]) if any(c.c is not None for c in curves) else None
    if vals is None or len(vals) == 0:
        return None
    lo, hi = float(np.min(vals)), float(np.max(vals))
    if symmetric:
        a = max(abs(lo), abs(hi))
        lo, hi = -a, a
    # a colour range of at least 1% of the largest |value| (and min_span): round-off-level variation
    # of a (nearly) constant or zero field is not blown up to the whole colour map
    span = max(0.01 * max(abs(lo), abs(hi)), min_span)
    if hi - lo < span:
        mid = 0.0 if symmetric else 0.5 * (lo + hi)
        lo, hi = mid - 0.5 * span, mid + 0.5 * span
    return lo, hi


def visible_views(lo, hi, views=("iso", "top", "front", "side"), min_ratio=0.05):
    """The views in which the rod's bounding box is not edge-on (a planar rod seen from the side
    is a strip with nothing to see); iso is always kept."""
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    keep = []
    for v in views:
        _, up, right = view_vectors(*VIEWS[v])
        ex, ey = np.ptp(corners @ right), np.ptp(corners @ up)
        if v == "iso" or min(ex, ey) >= min_ratio * max(ex, ey, 1e-300):
            keep.append(v)
    return keep


def min_span(meta, field):
    """Smallest colour range: 1e-6 / L for curvature and twist (below that a rod is straight or
    untwisted to round-off), 1e-12 otherwise."""
    return 1e-6 / float(meta["length"]) if field in ("curvature", "twist") else 1e-12


def _layout(nviews):
    return {1: (1, 1), 2: (1, 2), 3: (1, 3)}.get(nviews, (2, math.ceil(nviews / 2)))


def render(steps_curves, meta, views, field, out_paths, size=None, dpi=110, style="auto",
           limits=None, clim=None, stripe=True, title_extra=None):
    """Draw one step. steps_curves = (step dict, Curve); out_paths: one path (all views in one
    figure) or a dict view -> path. limits=(lo, hi) and clim=(vmin, vmax) fix the scales (movies)."""
    step, curve = steps_curves
    radius = float(meta["radius"])
    lo, hi = limits if limits is not None else bounds([curve], radius)
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    half = np.maximum(half, max(half.max() * 0.02, radius, 1e-12))
    _, label, symmetric = field_values(step, field)
    if clim is None:
        clim = field_limits([curve], symmetric, min_span(meta, field))
    cmap = plt.get_cmap(CMAPS.get(field, "viridis"))
    norm = colors.Normalize(*clim) if (clim is not None and field != "none") else None

    groups = [(views, out_paths)] if not isinstance(out_paths, dict) else [([v], out_paths[v]) for v in views]
    for vlist, path in groups:
        rows, cols = _layout(len(vlist))
        if size is None:
            w_px, h_px = 80 + 620 * cols, 90 + 560 * rows
        else:
            w_px, h_px = size
        fig = plt.figure(figsize=(w_px / dpi, h_px / dpi), dpi=dpi)
        ax_px = min(w_px / cols, h_px / rows) * 0.75
        r_px = radius / (2 * half.max()) * ax_px
        use_tube = style == "tube" or (style == "auto" and r_px >= 2.5 and len(curve.P) <= 4000)
        K = int(np.clip(60000 // max(len(curve.P), 1), 8, 24))
        axes = []
        for i, view in enumerate(vlist):
            ax = fig.add_subplot(rows, cols, i + 1, projection="3d")
            ax.set_proj_type("ortho")
            ax.view_init(*VIEWS[view])
            if use_tube:
                draw_tube(ax, curve, radius, view, norm, cmap, K, stripe)
            else:
                draw_line(ax, curve, view, norm, cmap, float(np.clip(2 * r_px * 72 / dpi, 1.5, 12.0)))
            ax.set_xlim(centre[0] - half[0], centre[0] + half[0])
            ax.set_ylim(centre[1] - half[1], centre[1] + half[1])
            ax.set_zlim(centre[2] - half[2], centre[2] + half[2])
            ax.set_box_aspect(tuple(half / half.max()), zoom=1.0 if view == "iso" else 1.1)
            for j, a in enumerate("xyz"):
                getattr(ax, f"set_{a}label")(a, labelpad=0)
                if half[j] < 0.1 * half.max():   # a thin direction: no tick clutter
                    getattr(ax, f"set_{a}ticks")([])
            ax.locator_params(nbins=5)
            ax.tick_params(labelsize=7, pad=0)
            for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
                axis.pane.set_facecolor((0.96, 0.96, 0.97, 1.0))
                axis.pane.set_edgecolor((0.85, 0.85, 0.88, 1.0))
                axis._axinfo["grid"]["color"] = (0.88, 0.88, 0.9, 1.0)
            if view in HIDDEN_AXIS:
                a = HIDDEN_AXIS[view]
                getattr(ax, f"set_{a}ticks")([])
                getattr(ax, f"set_{a}label")("")
            ax.set_title(view, fontsize=9, pad=0, y=1.03)
            axes.append(ax)
        at = step["attrs"]
        fig.suptitle(f"{meta.get('case_name', '')}   step {step['step']}   load {float(at['load']):.6g}",
                     fontsize=12, y=0.985)
        sub = (f"{int(meta['nelem'])} elements, p = {int(meta['order'])}, {int(meta['n_nodes'])} nodes; "
               + (f"tube of true radius {radius:g}" if use_tube else
                  f"line, width not to scale (radius {radius:g}" + (" too thin to draw)" if style == "auto" else ")"))
               + (f"; energy {float(at['energy']):.6g}" if "energy" in at else "")
               + (f"; {title_extra}" if title_extra else ""))
        fig.text(0.5, 0.935 if rows == 1 else 0.955, sub, ha="center", fontsize=8, color="0.3")
        right = (0.78 if cols == 1 else 0.86) if norm is not None else 0.98
        fig.subplots_adjust(left=0.02, right=right, bottom=0.03, top=0.90 if rows == 1 else 0.93,
                            wspace=0.08, hspace=0.12)
        if norm is not None:
            cax = fig.add_axes([right + (0.07 if cols == 1 else 0.05), 0.15, 0.018, 0.65])
            cb = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax)
            cb.set_label(label, fontsize=8)
            cb.ax.tick_params(labelsize=7)
            if field == "contact_force" and curve.c is not None and not np.any(curve.c):
                fig.text(0.5, 0.02, "no contact force in this step", ha="center", fontsize=8, color="0.4")
        fig.savefig(path, dpi=dpi, facecolor="white")
        plt.close(fig)


def _paths(out, stem, views, separate):
    if separate:
        return {v: os.path.join(out, f"{stem}_{v}.png") for v in views}
    return os.path.join(out, f"{stem}.png")


def still(outdir, out, step=-1, field="curvature", views=None, size=None,
          dpi=110, style="auto", separate=False, stripe=True):
    st = output.read_step(outdir, step)
    curve = display_curve(st, field)
    if views is None:
        views = visible_views(*bounds([curve], 0.0))
    paths = _paths(out, f"step_{st['step']:05d}", views, separate)
    render((st, curve), st["meta"], views, field, paths, size, dpi, style, stripe=stripe)
    return list(paths.values()) if isinstance(paths, dict) else [paths]


def movie(outdir, out, field="curvature", views=("iso",), size=None, dpi=110, style="auto", stripe=True):
    """One frame per complete step with fixed axis limits and colour scale; movie.mp4 if ffmpeg exists."""
    steps = output.read_steps(outdir)
    if not steps:
        raise SystemExit(f"{outdir}: no complete step")
    lo = hi = None
    vmin, vmax = math.inf, -math.inf
    symmetric = False
    for k in steps:  # pass 1: common scales (one step in memory at a time)
        st = output.read_step(outdir, k)
        c = display_curve(st, field)
        l, h = bounds([c], float(st["meta"]["radius"]))
        lo = l if lo is None else np.minimum(lo, l)
        hi = h if hi is None else np.maximum(hi, h)
        symmetric = field_values(st, field)[2]
        lim = field_limits([c], symmetric, min_span(st["meta"], field))
        if lim is not None:
            vmin, vmax = min(vmin, lim[0]), max(vmax, lim[1])
    clim = (vmin, vmax) if math.isfinite(vmin) else None
    frames = os.path.join(out, "frames")
    os.makedirs(frames, exist_ok=True)
    written = []
    for i, k in enumerate(steps):
        st = output.read_step(outdir, k)
        path = os.path.join(frames, f"frame_{i:05d}.png")
        render((st, display_curve(st, field)), st["meta"], views, field, path, size, dpi, style,
               limits=(lo, hi), clim=clim, stripe=stripe, title_extra=f"frame {i + 1}/{len(steps)}")
        written.append(path)
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg:
        mp4 = os.path.join(out, "movie.mp4")
        cmd = [ffmpeg, "-y", "-loglevel", "error", "-framerate", "10", "-i",
               os.path.join(frames, "frame_%05d.png"), "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",
               "-pix_fmt", "yuv420p", mp4]
        if subprocess.run(cmd).returncode == 0:
            written.append(mp4)
        else:
            print("ffmpeg failed; the frames are in", frames, file=sys.stderr)
    return written


def _size(text):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        assert w > 0 and h > 0
        return w, h
    except Exception as exc:  # noqa: BLE001
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT in pixels, got {text!r}") from exc


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("dir", help="run directory holding result.h5")
    ap.add_argument("--out", help="output folder (default DIR/pictures)")
    ap.add_argument("--step", type=int, default=-1, help="step index, negative counts from the last (default -1)")
    ap.add_argument("--field", choices=FIELDS, default="curvature")
    ap.add_argument("--views", default=None,
                    help="comma list of iso,top,front,side (default: those of the four in which the rod "
                         "is not seen edge-on; iso only with --movie)")
    ap.add_argument("--movie", action="store_true", help="one frame per load step (+ movie.mp4 if ffmpeg exists)")
    ap.add_argument("--separate", action="store_true", help="one file per view instead of one figure")
    ap.add_argument("--size", type=_size, default=None, help="figure size in pixels, e.g. 1200x900")
    ap.add_argument("--dpi", type=int, default=110)
    ap.add_argument("--style", choices=("auto", "tube", "line"), default="auto")
    ap.add_argument("--no-stripe", action="store_true", help="no dark stripe along the director d1")
    args = ap.parse_args(argv)

    if args.views:
        views = [v.strip() for v in args.views.split(",") if v.strip()]
        bad = [v for v in views if v not in VIEWS]
        if bad:
            ap.error(f"unknown view(s) {bad}: use {','.join(VIEWS)}")
    else:
        views = ["iso"] if args.movie else None   # None: the four views minus edge-on ones
    out = args.out or os.path.join(args.dir, "pictures")
    os.makedirs(out, exist_ok=True)
    kw = dict(field=args.field, views=views, size=args.size, dpi=args.dpi, style=args.style,
              stripe=not args.no_stripe)
    if args.movie:
        written = movie(args.dir, out, **kw)
    else:
        written = still(args.dir, out, args.step, separate=args.separate, **kw)
    for p in written:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
