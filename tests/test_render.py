"""tools/render.py on synthetic results (a helix, a closed twisted ring) and the rate fitting and
CSV of tools/work_precision.py with a fake runner (no solver needed)."""
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import load_tool

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the package may not be pip-installed yet
    sys.path.insert(0, str(ROOT))

from rodsnes.io import results as output  # noqa: E402




render = load_tool("render")
wp = load_tool("work_precision")


def _frames(t, d1):
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    d1 = d1 - np.sum(d1 * t, axis=1, keepdims=True) * t
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    return np.stack([d1, np.cross(t, d1), t], axis=-1)


def helix_step(s, k, turns=3.0, a=1.0, pitch=0.6):
    """A helix of turns*k/2 turns about z (k = 0: straight along z); d3 = tangent, d1 = principal normal."""
    if k == 0:
        P = np.stack([0 * s, 0 * s, s], axis=1)
        return P, _frames(np.tile([0.0, 0, 1], (len(s), 1)), np.tile([1.0, 0, 0], (len(s), 1)))
    c = pitch / (2 * np.pi)
    th = 2 * np.pi * turns * (k / 2) * s / s[-1]
    P = np.stack([a * np.cos(th), a * np.sin(th), c * th], axis=1)
    t = np.stack([-a * np.sin(th), a * np.cos(th), c + 0 * th], axis=1)
    nrm = np.stack([-np.cos(th), -np.sin(th), 0 * th], axis=1)
    return P, _frames(t, nrm)


def write_helix(d, steps=3, nelem=24, order=2):
    n = nelem * order + 1
    L = 3 * 2 * np.pi * math.hypot(1.0, 0.6 / (2 * np.pi))
    s = np.linspace(0, L, n)
    w = output.ResultWriter(d, None, n, dict(case_name="helix", closed=False, length=L, radius=0.08,
                                             nelem=nelem, order=order), xdmf=False)
    for k in range(steps):
        P, R = helix_step(s, k)
        u = np.tile([0.0, 0.3 * k, 0.1 * k], (n, 1))
        w.write_step(k, dict(load=k / (steps - 1), energy=float(k), newton_iterations=3, residual_norm=1e-10),
                     np.arange(n), dict(positions=P, directors=R, strain_u=u + 0.01 * s[:, None]))
    return L


def write_ring(d, steps=3, nelem=16, order=3, twist_turns=2.0, with_contact=True):
    """Closed ring (node n-1 joins node 0) whose d1 turns `twist_turns` times about the tangent, with
    a growing out-of-plane buckle; no strain_u, so render falls back to centreline/frames."""
    n = nelem * order
    L = 2 * np.pi
    s = np.arange(n) * L / n
    nq = nelem * order
    qs = (np.arange(nq) + 0.5) * L / nq
    w = output.ResultWriter(d, None, n, dict(case_name="twisted ring", closed=True, length=L, radius=0.06,
                                             nelem=nelem, order=order), xdmf=False)
    for k in range(steps):
        amp = 0.25 * k
        P = np.stack([np.cos(s), np.sin(s), amp * np.sin(2 * s)], axis=1)
        t = np.stack([-np.sin(s), np.cos(s), 2 * amp * np.cos(2 * s)], axis=1)
        radial = np.stack([np.cos(s), np.sin(s), 0 * s], axis=1)
        b = np.cross(t, radial)
        ang = twist_turns * s
        d1 = np.cos(ang)[:, None] * radial + np.sin(ang)[:, None] * b
        qp = dict(qp_s=qs, gap=np.cos(2 * qs) + 0.1, contact_force=np.maximum(0.0, np.cos(2 * qs) * k))
        w.write_step(k, dict(load=float(k), energy=0.0, newton_iterations=2, residual_norm=0.0),
                     np.arange(n), dict(positions=P, directors=_frames(t, d1)),
                     np.arange(nq) if with_contact else None, qp if with_contact else None)
    return n


def _png(path):
    import matplotlib.image as mpimg
    img = mpimg.imread(path)
    assert img.ndim == 3
    return img


def _nontrivial(img):
    rgb = img[..., :3].reshape(-1, 3)
    assert len(np.unique(rgb, axis=0)) > 50, "image is (nearly) a single colour"
    # not mostly blank: enough pixels differ from the background (white)
    assert np.mean(np.any(rgb < 0.9, axis=1)) > 0.01


def test_helix_still_size_and_content(tmp_path):
    write_helix(tmp_path)
    out = tmp_path / "pics"
    assert render.main([str(tmp_path), "--out", str(out), "--size", "640x480", "--dpi", "80"]) == 0
    img = _png(out / "step_00002.png")
    assert img.shape[:2] == (480, 640)
    _nontrivial(img)


@pytest.mark.slow
def test_ring_views_fields_separate(tmp_path):
    write_ring(tmp_path)
    out = tmp_path / "pics"
    for field in ("twist", "contact_force", "curvature", "none"):
        render.main([str(tmp_path), "--out", str(out), "--field", field, "--views", "iso,top",
                     "--separate", "--size", "320x300", "--dpi", "60", "--step", "1"])
        for v in ("iso", "top"):
            img = _png(out / f"step_00001_{v}.png")
            assert img.shape[:2] == (300, 320)
            _nontrivial(img)


def test_line_style_for_thin_rods(tmp_path):
    write_ring(tmp_path, with_contact=False)
    out = tmp_path / "pics"
    render.main([str(tmp_path), "--out", str(out), "--style", "line", "--views", "front",
                 "--size", "300x300", "--dpi", "60"])
    _nontrivial(_png(out / "step_00002.png"))


def test_movie_one_frame_per_step(tmp_path):
    write_ring(tmp_path, steps=4)
    out = tmp_path / "pics"
    render.main([str(tmp_path), "--out", str(out), "--movie", "--size", "240x200", "--dpi", "50"])
    frames = sorted((out / "frames").glob("frame_*.png"))
    assert [f.name for f in frames] == [f"frame_{i:05d}.png" for i in range(4)]
    for f in frames:
        assert _png(f).shape[:2] == (200, 240)


def test_field_fallbacks_are_right():
    """Without strain_u: curvature of a circle of radius 2 is 1/2; twist of a uniformly twisted ring."""
    n = 64
    s = np.arange(n) * 2 * np.pi / n
    P = 2 * np.stack([np.cos(s), np.sin(s), 0 * s], axis=1)
    np.testing.assert_allclose(render.centreline_curvature(P, True), 0.5, rtol=1e-12)
    t = np.stack([-np.sin(s), np.cos(s), 0 * s], axis=1)
    radial = np.stack([np.cos(s), np.sin(s), 0 * s], axis=1)
    ang = 3.0 * s   # 3 turns of d1 about the tangent over arclength 4 pi: u3 = 3 / 2
    d1 = np.cos(ang)[:, None] * radial + np.sin(ang)[:, None] * np.cross(t, radial)
    R = _frames(t, d1)
    np.testing.assert_allclose(render.frame_twist(R, 4 * np.pi / n, True), 1.5, rtol=1e-3)


# --------------------------------------------------------------------------- work_precision
def test_rates_and_csv_with_fake_runner(tmp_path):
    """A fake solver whose errors are C h^(p+1): the fitted rates are p+1, the CSV has every run."""
    L = 10.0

    def fake_runner(case, order, nelem, np_, outdir, extra):
        h = L / nelem
        err = 0.3 * h ** (order + 1)
        if order == 4 and nelem == 32:   # a failed run is recorded, not a crash
            return dict(converged=False, wall_time_s=1.0, dofs=6 * (nelem * order + 1),
                        newton_iterations=50, error="diverged")
        return dict(converged=True, wall_time_s=1e-3 * nelem * order, dofs=6 * (nelem * order + 1),
                    newton_iterations=4, err_tip=err, err_l2=2 * err, err_energy=err**2)

    rows = wp.study("rollup", [1, 2, 3, 4], [2, 4, 8, 16, 32], 1, str(tmp_path), "", runner=fake_runner)
    rates = wp.rates(rows, "err_tip")
    for p in (1, 2, 3):
        assert rates[p] == pytest.approx(p + 1, abs=1e-9)
    assert rates[4] == pytest.approx(5, abs=1e-9)   # from 8 -> 16 because 32 failed
    assert wp.rates(rows, "err_energy")[2] == pytest.approx(6, abs=1e-9)
    wp.write_csv(rows, tmp_path / "work_precision.csv")
    with open(tmp_path / "work_precision.csv") as fh:
        got = list(csv.DictReader(fh))
    assert len(got) == 20
    assert set(wp.CSV_COLUMNS) <= set(got[0])
    bad = [r for r in got if r["converged"] != "True"]
    assert len(bad) == 1 and bad[0]["order"] == "4" and bad[0]["nelem"] == "32" and bad[0]["err_tip"] == "nan"
    wp.plot(rows, tmp_path / "work_precision.png", "rollup")
    _nontrivial(_png(tmp_path / "work_precision.png"))


def test_exact_rollup_errors_are_zero_for_the_exact_circle(tmp_path):
    """The error measures of the roll-up vanish on the exact solution and see a perturbation."""
    L, f = 10.0, 1.0
    k = 2 * np.pi * f / L
    nelem, order = 4, 3
    n = nelem * order + 1
    s = np.linspace(0, L, n)
    P = np.stack([np.sin(k * s) / k, (1 - np.cos(k * s)) / k, 0 * s], axis=1)
    EI = 100.0
    M = f * 2 * np.pi * EI / L
    exact = wp.RollupExact(L=L, EI=EI, M=M)
    e = exact.errors(P, energy=M**2 * L / (2 * EI), order=order, nelem=nelem)
    assert e["err_tip"] < 1e-12 and e["err_energy"] < 1e-12
    assert e["err_l2"] < 5e-4      # interpolation error of the cubic elements between the nodes
    e2 = exact.errors(P + [0.01, 0, 0], energy=M**2 * L / (2 * EI), order=order, nelem=nelem)
    assert e2["err_tip"] == pytest.approx(0.001, rel=1e-9)
    assert e2["err_l2"] == pytest.approx(0.001, rel=0.5)
    assert json.dumps(e2)   # plain floats
