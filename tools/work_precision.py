#!/usr/bin/env python3
"""Work-precision study: error against wall time and dofs for element orders 1..4 on refined meshes.

    tools/work_precision.py --case rollup [--orders 1,2,3,4] [--nelem 2,4,8,16,32] [--np 1]
                            [--out DIR] [--extra "-opt val ..."]
    tools/work_precision.py --case rollup_contact --orders 2,3 --nelem 8,16,32,64 --penalties 1,10,100,1000

Every (order, nelem[, penalty]) is one run of the solver's command line,

    rodsnes -options_file cases/CASE.opts -rod_nelem N -rod_order p -output_dir D -quiet EXTRA
            [-contact_penalty f mu0]

(under ``mpirun -n NP`` when NP > 1), read back from D/summary.json and D/result.h5. A run that fails,
times out, or stops short of the full load is recorded with converged = False and NaN errors.

Error measures (all dimensionless; h = L / nelem; x_h(s) = the Lagrange interpolant of the nodal
positions of the last step, x(s) = the reference centreline):
    err_tip     |x_h(L) - x(L)| / L
    err_l2      sqrt( (1/L) int_0^L |x_h(s) - x(s)|^2 ds ) / L    (RMS centreline error over L; Gauss
                quadrature with p+3 points per element)
    err_energy  |E_h - E| / |E|                                     (E = the energy in summary.json)
    err_max     max_s |x_h(s) - x(s)| / L over 8 equispaced points per element (the sampling of the
                solver's error estimate)
The solver's own a-posteriori estimate of the same run (summary.json error_estimate, written by
default at the last step: order p+1 on the same elements, docs/error_estimate.md), beside them:
    est_tip, est_centreline   the estimates of |x_h(L) - x(L)| and max_s |x_h(s) - x(s)|, / L;
                est_converged False where its order p+1 solve did not converge (not plotted)
References:
    rollup      exact (cases/rollup.opts: clamped rod, end moment M about an axis normal to the rod):
                a circular arc of curvature k = |M|/EI in the plane normal to M,
                x(s) = x0 + sin(ks)/k t0 + (1 - cos ks)/k (m x t0) (x0, t0: clamped end and its tangent
                d3 at step 0, m = M/|M|); E = M^2 L / (2 EI) (the strain energy; pure bending has n = 0,
                so this holds for any EA, GA).
    mattiasson  an overkill run (order 4, --ref-nelem elements) for all three errors, and the
                published 6-digit elastica tip (shared/REFERENCES.md) as err_tip_published =
                |(u_h, v_h) - (u, v)| / L (u = shortening along t0, v = deflection along the load),
                whose floor is ~1e-6.
    rollup_contact  exact in the hard-contact limit (tools/planar_contact_reference.py, numpy/scipy
                shooting of the planar Reissner rod, no rodsnes code): the free end is stopped by the
                clamped end, cap against cap, |r(L) - r(0)| = 2 eps, and the rod is one elastica under
                the contact force F.  Errors against it (penalty + finite-element error):
                    err_tip, err_l2, err_energy (E = the strain energy of the hard contact) as above,
                    err_force  |f_h - f| / f   (f_h = the run's contact total_force, the force each end
                               exerts on the other; f = |F|).
                No contact-location error: the reference's contact pair is the two rod ends
                (s = 0, s = L) for every mu.  A run whose tip lies more than 1e-2 L from the
                reference (a coarse mesh can let the tip slide onto the first turn: another
                equilibrium) keeps its errors in the CSV with a note and is left out of the rates,
                slopes and plots.
                Against the same reference solved with the run's penalty law (ends overlapping by
                d0 = sqrt(2 f / (mu (1/c1 + 1/c2)))): err_tip_law, err_force_law, the finite-element
                error alone down to floors that scale with d0 ~ mu^(-1/2) (measured, cubic elements,
                mu0..1000 mu0, 16-64 elements): err_tip_law 2e-4 d0/L; err_force_law 0.63 % of the
                law's force deficit (f - f_law)/f, because total_force, the integral of the line
                force over the zones, falls short of the internal force |F| by that much (|F| from
                the moment field matches f_law to 5e-5 of the deficit).
                --penalties f1,f2,...: every run at the fixed mu = f mu0 (-contact_penalty, so no
                -contact_penalty_adapt), mu0 = the solver's default (rodsnes.contact.default_penalty
                for the case's EI, radius and -contact_penetration, or the case's -contact_penalty).
                The references (hard, and the penalty law at each mu) are shot once and cached in
                DIR/reference_rollup_contact.json (reused when the rod is the same and the cached
                solution still meets its contact condition).  The hard-contact errors level off at
                the penalty error O(mu^(-1/2)); observed penalty slope: least-squares slope of
                log(error) against log(mu) over the penalties of each (order, mesh).
Observed rates: slope of log(error) against log(h) between the two finest converged meshes of each
order whose error is above the round-off floor (1e-13).

Cost columns (from summary.json): wall_time_s, newton_iterations and load_steps of the accepted steps,
step_time_s = the seconds of the accepted steps' solves (wall_time_s - step_time_s is set-up, output
and the rejected attempts, whose iterations newton_iterations does not count).

Outputs in DIR (default out/work_precision_CASE): work_precision.csv, work_precision.png (error against
wall time and against dofs, one line per order, log-log, the estimate dashed beside err_tip and
err_max; rollup_contact: tip and force error against
wall time, one line per (order, penalty), against the mesh (the tip estimate dashed beside
err_tip_law: it estimates the finite-element error of the penalty problem), the force error and the Newton
iterations against mu), rates.json, runs/pP_nN/ or runs/pP_nN_muF/ (each run's output directory).
The CSV is rewritten after every run, so an interrupted study keeps what it measured;
--from-csv FILE redoes the plot and the report from a CSV without running anything.
"""
import argparse
import csv
import importlib.util
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    from rodsnes.io import results as output
    from rodsnes.model.fe import gauss_legendre, lagrange
except ImportError:  # run from a checkout without pip install -e
    sys.path.insert(0, str(ROOT))
    from rodsnes.io import results as output
    from rodsnes.model.fe import gauss_legendre, lagrange

CSV_COLUMNS = ["case", "order", "nelem", "penalty_factor", "penalty", "dofs", "wall_time_s", "step_time_s",
               "newton_iterations", "load_steps", "err_tip", "err_l2", "err_energy", "err_max",
               "est_tip", "est_centreline", "est_converged", "err_force", "err_tip_law", "err_force_law",
               "err_tip_published", "converged", "load", "process_time_s", "ranks", "outdir", "note"]
ERRORS = ("err_tip", "err_l2", "err_energy", "err_max")
ESTIMATES = ("est_tip", "est_centreline")
ESTIMATE_OF = {"err_tip": "est_tip", "err_max": "est_centreline", "err_tip_law": "est_tip"}
SAMPLES_PER_ELEMENT = 8  # err_max's sampling, the estimator's (rodsnes.model.refine.sample_points)
CONTACT_ERRORS = ("err_force", "err_tip_law", "err_force_law")     # rollup_contact only
OTHER_BRANCH = 1e-2   # err_tip_law above this: the run found another equilibrium, not the end contact
ROUNDOFF = 1e-13

# shared/REFERENCES.md, Mattiasson (1981): lambda -> (u/L, v/L)
MATTIASSON = {1: (0.056433, 0.301721), 2: (0.160642, 0.493457), 5: (0.387628, 0.713792),
              10: (0.554996, 0.810609), 20: (0.683886, 0.868696), 100: (0.858579, 0.941421)}


# --------------------------------------------------------------------------- finite element helpers
def fe_eval(nodal, order, nelem, length, s):
    """The Lagrange interpolant of nodal values (uniform open mesh, node i at i h/p) at arclengths s."""
    s = np.asarray(s, float)
    h = length / nelem
    e = np.clip(np.floor(s / h).astype(int), 0, nelem - 1)
    xi = 2.0 * (s - e * h) / h - 1.0
    N = lagrange(order, xi)[0]                                   # (m, p+1)
    conn = e[:, None] * order + np.arange(order + 1)[None, :]    # (m, p+1)
    return np.einsum("ma,ma...->m...", N, np.asarray(nodal)[conn])


def quad_points(order, nelem, length, extra=3):
    """Gauss points and weights of the uniform mesh (order + extra points per element)."""
    xi, w = gauss_legendre(order + extra)
    h = length / nelem
    s = (np.arange(nelem)[:, None] + (xi[None, :] + 1) / 2) * h
    return s.ravel(), np.tile(w * h / 2, nelem)


def max_error(nodal, order, nelem, length, exact_fn):
    """max_s |x_h(s) - x(s)| / L over SAMPLES_PER_ELEMENT equispaced points per element, both
    ends included."""
    s = np.linspace(0.0, length, SAMPLES_PER_ELEMENT * nelem + 1)
    d = fe_eval(nodal, order, nelem, length, s) - exact_fn(s)
    return float(np.sqrt(np.sum(d * d, axis=1)).max() / length)


def l2_error(nodal, order, nelem, length, exact_fn):
    """sqrt((1/L) int |x_h - x|^2 ds) / L."""
    s, w = quad_points(order, nelem, length)
    d = fe_eval(nodal, order, nelem, length, s) - exact_fn(s)
    return float(math.sqrt(np.sum(w * np.sum(d * d, axis=1)) / length) / length)


# --------------------------------------------------------------------------- references
class RollupExact:
    """Pure bending of a clamped rod by an end moment M: circle of curvature |M|/EI (see module doc)."""

    def __init__(self, L, EI, M, x0=(0.0, 0.0, 0.0), t0=(1.0, 0.0, 0.0)):
        M = np.atleast_1d(np.asarray(M, float))
        self.L, self.EI = float(L), float(EI)
        self.M = float(np.linalg.norm(M)) if M.size == 3 else abs(float(M[0]))
        m = M / np.linalg.norm(M) if M.size == 3 else np.array([0.0, 0.0, 1.0])
        self.x0 = np.asarray(x0, float)
        self.t0 = np.asarray(t0, float) / np.linalg.norm(t0)
        if abs(m @ self.t0) > 1e-8:
            raise ValueError("roll-up reference: the end moment must be normal to the rod's tangent")
        self.n0 = np.cross(m, self.t0)
        self.k = self.M / self.EI
        self.energy = self.M**2 * self.L / (2 * self.EI)

    def centreline(self, s):
        s = np.asarray(s, float)
        k = self.k
        if k == 0:
            return self.x0 + s[:, None] * self.t0
        return self.x0 + (np.sin(k * s) / k)[:, None] * self.t0 + ((1 - np.cos(k * s)) / k)[:, None] * self.n0

    def errors(self, positions, energy, order, nelem):
        tip = self.centreline([self.L])[0]
        return {"err_tip": float(np.linalg.norm(positions[-1] - tip) / self.L),
                "err_l2": l2_error(positions, order, nelem, self.L, self.centreline),
                "err_max": max_error(positions, order, nelem, self.L, self.centreline),
                "err_energy": float(abs(energy - self.energy) / abs(self.energy))}


class FEReference:
    """A (fine) finite element solution used as the reference (overkill)."""

    def __init__(self, positions, energy, order, nelem, L):
        self.P, self.energy, self.order, self.nelem, self.L = positions, energy, order, nelem, L

    def centreline(self, s):
        return fe_eval(self.P, self.order, self.nelem, self.L, s)

    def errors(self, positions, energy, order, nelem):
        return {"err_tip": float(np.linalg.norm(positions[-1] - self.P[-1]) / self.L),
                "err_l2": l2_error(positions, order, nelem, self.L, self.centreline),
                "err_max": max_error(positions, order, nelem, self.L, self.centreline),
                "err_energy": float(abs(energy - self.energy) / max(abs(self.energy), 1e-300))}


def mattiasson_published_error(positions, directors0, x0, force, EI, L, load):
    """|(u_h, v_h) - (u, v)|/L against the published table, NaN if lambda is not in it."""
    F = np.asarray(force, float) * load
    lam = float(np.linalg.norm(F)) * L**2 / EI
    key = [k for k in MATTIASSON if abs(k - lam) <= 1e-9 * k]
    if not key:
        return float("nan"), lam
    u_ref, v_ref = MATTIASSON[key[0]]
    t0 = directors0[:, 2]
    d = positions[-1] - x0
    u = (L - d @ t0) / L
    v = (d @ (F / np.linalg.norm(F))) / L
    return float(math.hypot(u - u_ref, v - v_ref)), lam


def planar_reference_module():
    """tools/planar_contact_reference.py (numpy/scipy only), imported by its path so that tools/ need
    not be on sys.path (the tests load this file by path)."""
    name = "planar_contact_reference"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


def planar_rod(scene):
    """The reference's PlanarRod for the solver's scene (its derived stiffnesses, radius, end moment);
    refuses what the planar reference does not describe."""
    ref = planar_reference_module()
    rod, c, M = scene.rod, scene.contact, np.asarray(scene.loads.end_moment, float)
    if abs(M[0]) + abs(M[1]) > 1e-12 * abs(M[2]) or rod.closed or rod.shape != "straight":
        raise ValueError("planar contact reference: a straight open rod with an end moment along z only")
    if abs(rod.EI1 - rod.EI2) > 1e-12 * rod.EI1 or abs(rod.GA1 - rod.GA2) > 1e-12 * rod.GA1:
        raise ValueError("planar contact reference: EI1 = EI2 and GA1 = GA2 only")
    if c.standoff:
        # the study measures the law's error against hard contact at the tube
        raise ValueError("planar contact reference: the law at the tube only (-contact_standoff 0)")
    eps = float(c.radius if c.radius is not None else rod.radius)
    return ref.PlanarRod(L=float(rod.length), EI=float(rod.EI1), EA=float(rod.EA), GA=float(rod.GA1),
                         M=float(M[2]), eps=eps, exclusion=None if c.exclusion is None else float(c.exclusion))


class RollupContactReference:
    """The end-to-end contact of cases/rollup_contact.opts (module doc): the hard contact (mu -> inf)
    and the continuum penalty law at each mu, shot by tools/planar_contact_reference.py, each solved
    once and cached in a JSON file as its shooting unknowns (m(0), F, d0); a cached solution is
    re-integrated and used only if its rod is this rod and it still meets its contact condition
    |r(L) - r(0)| = 2 eps - d0 and m(L) = M."""

    def __init__(self, rod, cache_path=None):
        self.ref = planar_reference_module()
        self.rod, self.cache_path = rod, cache_path
        self.rod_key = {k: float(v) for k, v in vars(rod).items()}
        self._sol = {}              # "hard" or repr(mu) -> Solution
        self._energy = {}           # same keys -> strain energy
        self._cache = {"rod": self.rod_key, "solutions": {}}
        if cache_path and os.path.exists(cache_path):
            try:
                cached = json.loads(Path(cache_path).read_text())
            except (OSError, ValueError):
                cached = None
            if cached and cached.get("rod") == self.rod_key:
                self._cache = cached

    def hard(self):
        return self._solution("hard", None)

    def penalty(self, mu):
        return self._solution(repr(float(mu)), float(mu))

    def strain_energy(self, key):
        if key not in self._energy:
            self._energy[key] = self._sol[key].strain_energy()
        return self._energy[key]

    def _solution(self, key, mu):
        if key not in self._sol:
            sol = self._from_cache(key, mu)
            if sol is None:
                sol = (self.ref.solve_end_contact(self.rod) if mu is None else
                       self.ref.solve_end_contact_penalty(self.rod, mu, guess=self._guess()))
                self._store(key, sol)
            self._sol[key] = sol
        return self._sol[key]

    def _guess(self):
        h = self.hard()
        return [h.m0, h.f, math.atan2(h.F[1], h.F[0])]

    def _from_cache(self, key, mu):
        c = self._cache["solutions"].get(key)
        if c is None:
            return None
        rod, F = self.rod, np.asarray(c["F"], float)
        try:
            segs, yL, _ = self.ref.integrate(rod, [(0.0, rod.L)], [F], c["m0"], dense=True)
        except FloatingPointError:
            return None
        d0 = float(c.get("d0", 0.0))
        if (abs(math.hypot(yL[0], yL[1]) - (2 * rod.eps - d0)) > 1e-9 * rod.L
                or abs(yL[3] - rod.M) > 1e-9 * abs(rod.M)):
            return None
        kind = "end" if mu is None else f"end, penalty mu={mu:g}"
        sol = self.ref.Solution(rod, kind, [(0.0, rod.L)], F[None, :], float(c["m0"]), segs)
        if mu is not None:
            sol.d0, sol.penalty_energy = d0, float(c["penalty_energy"])
        return sol

    def _store(self, key, sol):
        self._cache["solutions"][key] = {"m0": float(sol.m0), "F": [float(v) for v in sol.F],
                                         "d0": float(getattr(sol, "d0", 0.0)),
                                         "penalty_energy": float(getattr(sol, "penalty_energy", 0.0))}
        if self.cache_path:
            tmp = f"{self.cache_path}.tmp"
            Path(tmp).write_text(json.dumps(self._cache, indent=1) + "\n")
            os.replace(tmp, self.cache_path)

    def errors(self, positions, x0, t0, total_force, energy, mu, order, nelem):
        """err_tip, err_l2, err_energy, err_force against the hard contact; err_tip_law,
        err_force_law against the penalty law at the run's mu (the finite-element error alone).
        The reference plane: x = x0 + r_1 t0 + r_2 (e_z x t0), t0 the clamped tangent."""
        L = self.rod.L
        basis = np.stack([np.asarray(t0, float), np.cross([0.0, 0.0, 1.0], t0)])      # (2, 3)

        def centreline(sol):
            return lambda s: np.asarray(x0, float) + sol.state(s)[0] @ basis

        hard, law = self.hard(), self.penalty(mu)
        tip = np.asarray(positions[-1], float)
        return {"err_tip": float(np.linalg.norm(tip - centreline(hard)([L])[0]) / L),
                "err_l2": l2_error(positions, order, nelem, L, centreline(hard)),
                "err_max": max_error(positions, order, nelem, L, centreline(hard)),
                "err_energy": float(abs(energy - self.strain_energy("hard")) / self.strain_energy("hard")),
                "err_force": float(abs(total_force - hard.f) / hard.f),
                "err_tip_law": float(np.linalg.norm(tip - centreline(law)([L])[0]) / L),
                "err_force_law": float(abs(total_force - law.f) / law.f)}


# --------------------------------------------------------------------------- options and scene
def parse_opts_file(path):
    """PETSc options file -> list of tokens (comments removed)."""
    tokens = []
    for line in Path(path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            tokens += line.split()
    return tokens


def tokens_to_dict(tokens):
    """'-key value' / '-flag' tokens -> {key: value or ''}; later occurrences win (as in PETSc)."""
    d = {}
    i = 0
    while i < len(tokens):
        t = tokens[i]
        if not t.startswith("-") or _is_number(t):
            i += 1
            continue
        if i + 1 < len(tokens) and (not tokens[i + 1].startswith("-") or _is_number(tokens[i + 1])):
            d[t[1:]] = tokens[i + 1]
            i += 2
        else:
            d[t[1:]] = ""
            i += 1
    return d


def _is_number(t):
    try:
        float(t.split(",")[0])
        return True
    except ValueError:
        return False


class _Options:
    """The two petsc4py.Options methods rodsnes.io.scene.read_scene uses, over a plain dict."""

    def __init__(self, d):
        self.d = d

    def hasName(self, name):  # noqa: N802 - petsc4py's spelling
        return name.lstrip("-") in self.d

    def getString(self, name, default=None):  # noqa: N802
        return self.d.get(name.lstrip("-"), default)


def read_case_scene(case_file, extra):
    """The solver's own Scene (stiffnesses derived exactly as the solver does) for the case + extra."""
    from rodsnes.io.scene import read_scene
    d = tokens_to_dict(parse_opts_file(case_file) + list(extra))
    return read_scene(argv=["rodsnes", "-options_file", str(case_file)], options=_Options(d))


def default_contact_penalty(case_file, extra):
    """The penalty mu0 the solver starts from: the case's -contact_penalty, else
    rodsnes.contact.default_penalty(min(EI1, EI2), eps_l, p_l) of the law (Scene.contact_law, as
    ContactTerm)."""
    from rodsnes.contact.projection import default_penalty
    sc = read_case_scene(case_file, extra)
    c = sc.contact
    if c.penalty is not None:
        return float(c.penalty)
    return float(default_penalty(min(sc.rod.EI1, sc.rod.EI2), *sc.contact_law))


# --------------------------------------------------------------------------- running the solver
def solver_command(exe=None):
    if exe:
        return exe.split()
    venv_exe = ROOT / ".venv" / "bin" / "rodsnes"
    if venv_exe.exists():
        return [str(venv_exe)]
    found = shutil.which("rodsnes")
    return [found] if found else [sys.executable, "-m", "rodsnes"]


class CliRunner:
    """Runs one (order, nelem) through the solver's CLI and measures its errors (a failed run is a row
    with converged False, never an exception)."""

    def __init__(self, case, case_file, exe=None, timeout=1800.0, ref_nelem=128, quiet=False):
        self.case, self.case_file = case, str(case_file)
        self.cmd = solver_command(exe)
        self.timeout, self.ref_nelem, self.quiet = timeout, ref_nelem, quiet
        self._scene = None
        self._ref = None           # FEReference once computed
        self._ref_error = None     # why the reference run failed (not retried)
        self._contact = None       # RollupContactReference once built

    def scene(self, extra):
        if self._scene is None:
            self._scene = read_case_scene(self.case_file, extra)
        return self._scene

    def run(self, order, nelem, np_, outdir, extra):
        """The solver on one mesh; returns (row dict, last step dict or None)."""
        if os.path.isdir(outdir):
            shutil.rmtree(outdir)   # never read a stale summary.json of an earlier study
        os.makedirs(outdir)
        cmd = list(self.cmd) + ["-options_file", self.case_file, "-rod_nelem", str(nelem), "-rod_order",
                                str(order), "-output_dir", outdir, "-quiet"] + list(extra)
        if np_ > 1:
            cmd = ["mpirun", "-n", str(np_), "--bind-to", "none"] + cmd
        env = dict(os.environ)
        env.setdefault("OMP_NUM_THREADS", "1")
        row = {"order": order, "nelem": nelem, "converged": False, "outdir": outdir, "ranks": np_}
        t0 = time.perf_counter()
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=self.timeout, env=env)
            rc, log = res.returncode, res.stdout + res.stderr
        except subprocess.TimeoutExpired as exc:
            rc, log = None, f"timeout after {self.timeout} s\n{exc.stdout or ''}{exc.stderr or ''}"
        except OSError as exc:
            rc, log = None, f"cannot run {cmd[0]}: {exc}"
        row["process_time_s"] = time.perf_counter() - t0
        Path(outdir, "run.log").write_text(" ".join(cmd) + "\n" + (log if isinstance(log, str) else ""))
        try:
            summ = output.read_summary(outdir)
        except (OSError, ValueError) as exc:
            row["note"] = f"rc={rc}, no summary.json ({type(exc).__name__}); see {outdir}/run.log"
            return row, None
        row.update({k: summ.get(k) for k in ("dofs", "wall_time_s", "newton_iterations", "load", "load_steps")})
        if summ.get("steps"):
            # the accepted steps' Newton solves; wall_time_s - step_time_s = set-up, output and the
            # rejected attempts (whose iterations newton_iterations does not count)
            row["step_time_s"] = float(sum(st.get("seconds", 0.0) for st in summ["steps"]))
        row["ranks"] = summ.get("ranks", np_)
        if not summ.get("converged") or rc != 0:
            row["note"] = f"rc={rc}, converged={summ.get('converged')}: {summ.get('failure', '')}".strip()
            return row, None
        if summ.get("load") is not None and abs(float(summ["load"]) - 1.0) > 1e-12:
            row["note"] = f"stopped at load {summ['load']}"
            return row, None
        try:
            last = output.read_step(outdir, -1)
            first = output.read_step(outdir, 0)
        except Exception as exc:  # noqa: BLE001 - recorded
            row["note"] = f"result.h5 unreadable: {type(exc).__name__}: {exc}"
            return row, None
        last["first"] = first
        row["converged"] = True
        row.update(estimate_columns(summ.get("error_estimate"), float(last["meta"]["length"])))
        return row, last

    def reference(self, np_, out, extra):
        """The overkill solution (order 4, ref_nelem elements), run once (a failure is not retried)."""
        if self._ref is None and self._ref_error is None:
            rd = os.path.join(out, "runs", f"reference_p4_n{self.ref_nelem}")
            if not self.quiet:
                print(f"reference: order 4, {self.ref_nelem} elements -> {rd}", flush=True)
            row, st = self.run(4, self.ref_nelem, np_, rd, extra)
            if st is None:
                self._ref_error = f"overkill reference run failed: {row.get('note')}"
                print(self._ref_error, file=sys.stderr, flush=True)
            else:
                L = float(st["meta"]["length"])
                self._ref = FEReference(st["positions"], float(st["attrs"]["energy"]), 4, self.ref_nelem, L)
        return self._ref

    def contact_reference(self, out, extra):
        """The planar end-contact reference, built once, cached in out/reference_rollup_contact.json."""
        if self._contact is None:
            self._contact = RollupContactReference(planar_rod(self.scene(extra)),
                                                   os.path.join(out, "reference_rollup_contact.json"))
        return self._contact

    def contact_errors(self, row, st, order, nelem, out, extra):
        """rollup_contact: the run's mu and contact force (last step's attributes) against the
        planar reference; a run on another branch is flagged in the note."""
        a = st["attrs"]
        if "contact_total_force" not in a or "contact_penalty" not in a:
            row["note"] = "no contact_total_force / contact_penalty in result.h5 (contact off?)"
            row["converged"] = False
            return row
        R0 = st["first"]["directors"][0]
        t0 = R0[:, 2]
        if abs(t0[2]) > 1e-12:
            raise ValueError("planar contact reference: the clamped tangent must lie in the xy plane")
        mu = float(a["contact_penalty"])
        row["penalty"] = mu
        row.update(self.contact_reference(out, extra).errors(
            st["positions"], st["first"]["positions"][0], t0, float(a["contact_total_force"]),
            float(a["energy"]), mu, order, nelem))
        if row["err_tip_law"] > OTHER_BRANCH:
            row["note"] = (f"another equilibrium: tip {row['err_tip_law']:.2g} L from the end contact; "
                           + row.get("note", "")).rstrip("; ")
        return row

    def __call__(self, case, order, nelem, np_, outdir, extra):
        extra = list(extra.split()) if isinstance(extra, str) else list(extra)
        row, st = self.run(order, nelem, np_, outdir, extra)
        if st is None:
            return row
        if case == "rollup_contact":
            return self.contact_errors(row, st, order, nelem, str(Path(outdir).parents[1]), extra)
        sc = self.scene(extra)
        P = st["positions"]
        E = float(st["attrs"]["energy"])
        L = float(st["meta"]["length"])
        x0, R0 = st["first"]["positions"][0], st["first"]["directors"][0]
        lam = float(st["attrs"]["load"])
        if case == "rollup":
            ref = RollupExact(L, sc.rod.EI1, np.asarray(sc.loads.end_moment) * lam, x0=x0, t0=R0[:, 2])
            if abs(sc.rod.EI1 - sc.rod.EI2) > 1e-12 * sc.rod.EI1:
                row["note"] = "EI1 != EI2: reference uses EI1"
        elif case == "mattiasson":
            row["err_tip_published"], lam_ = mattiasson_published_error(
                P, R0, x0, sc.loads.end_force, sc.rod.EI1, L, lam)
            if math.isnan(row["err_tip_published"]):
                row["note"] = f"lambda = {lam_:g} is not in the published table"
            ref = self.reference(np_, str(Path(outdir).parents[1]), extra)
            if ref is None:
                row["note"] = (row.get("note", "") + "; " + self._ref_error).lstrip("; ")
                return row
        else:
            raise ValueError(f"no reference for case {case!r}")
        row.update(ref.errors(P, E, order, nelem))
        return row


def estimate_columns(est, length):
    """est_tip, est_centreline (/ L) and est_converged of summary.json's error_estimate ({} when
    the run made none: -rod_error_estimate off)."""
    if not est:
        return {}
    out = {"est_converged": bool(est.get("converged"))}
    for col, key in (("est_tip", "tip"), ("est_centreline", "centreline")):
        if est.get(key) is not None:
            out[col] = float(est[key]) / length
    return out


# --------------------------------------------------------------------------- study, rates, outputs
def study(case, orders, nelems, np_, out, extra, runner=None, quiet=False, penalties=None, progress=None):
    """Run every (order, nelem), or with ``penalties`` = [(factor, mu), ...] every (order, penalty,
    nelem) with ``-contact_penalty mu`` appended to extra; rows with the CSV columns (NaN where
    unknown). ``runner(case, order, nelem, np, outdir, extra)`` returns a row dict; an exception is
    recorded as a failed run.  ``progress(rows)`` is called after every run."""
    if runner is None:
        runner = CliRunner(case, ROOT / "cases" / f"{case}.opts")
    extra = extra.split() if isinstance(extra, str) else list(extra)
    rows = []
    for p in orders:
        for factor, mu in (penalties or [(None, None)]):
            for ne in nelems:
                tag = f"p{p}_n{ne}" + ("" if factor is None else f"_mu{factor:g}")
                ex = extra + ([] if mu is None else ["-contact_penalty", repr(float(mu))])
                row = run_one(runner, case, p, ne, np_, os.path.join(out, "runs", tag), ex)
                if factor is not None:
                    row["penalty_factor"] = factor
                    if not np.isfinite(float(row["penalty"])):
                        row["penalty"] = float(mu)
                rows.append(row)
                if progress is not None:
                    progress(rows)
                if not quiet:
                    print(_progress_line(row, factor is not None), flush=True)
    return rows


def run_one(runner, case, p, ne, np_, rd, extra):
    """One run as a CSV row: NaN where unknown, every error NaN if the run failed."""
    try:
        r = dict(runner(case, p, ne, np_, rd, extra))
    except Exception as exc:  # noqa: BLE001 - a failed run is a row, not a crash
        r = {"converged": False, "note": f"{type(exc).__name__}: {exc}"}
    row = {c: float("nan") for c in CSV_COLUMNS}
    row.update({"case": case, "order": p, "nelem": ne, "outdir": rd, "note": "", "ranks": np_})
    row.update({k: v for k, v in r.items() if v is not None})
    if not row.get("converged"):
        for k in ERRORS + CONTACT_ERRORS + ESTIMATES + ("err_tip_published",):
            row[k] = float("nan")
        row["converged"] = False
        if r.get("error") and not row["note"]:
            row["note"] = str(r["error"])
    return row


def _progress_line(row, contact):
    status = "ok  " if row["converged"] else "FAIL"
    head = f"{status} p={row['order']} nelem={row['nelem']:4d} "
    if contact:
        head += f"mu={_fmt(float(row['penalty']))} (x{row['penalty_factor']:g}) "
    tail = (f"err_F={_fmt(row['err_force'])} err_tip_law={_fmt(row['err_tip_law'])} "
            f"err_F_law={_fmt(row['err_force_law'])} " if contact else f"err_E={_fmt(row['err_energy'])} ")
    return (head + f"dofs={_fmt(row['dofs'])} t={_fmt(row['wall_time_s'])} s its={_fmt(row['newton_iterations'])} "
            f"err_tip={_fmt(row['err_tip'])} err_l2={_fmt(row['err_l2'])} " + tail + str(row["note"]))


def _fmt(v):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "nan"
    if isinstance(v, float):
        return f"{v:.3e}"
    return str(v)


def rates(rows, column, floor=ROUNDOFF, key=lambda r: r["order"]):
    """Observed rate per group (default: per order): slope of log(err) vs log(h) over the two
    finest converged meshes whose error is above the round-off floor (NaN if fewer than two)."""
    out = {}
    for g in sorted({key(r) for r in rows}):
        pts = sorted((r["nelem"], float(r[column])) for r in rows
                     if key(r) == g and on_branch(r) and np.isfinite(float(r[column]))
                     and float(r[column]) > floor)
        if len(pts) < 2:
            out[g] = float("nan")
            continue
        (n1, e1), (n2, e2) = pts[-2], pts[-1]
        out[g] = math.log(e1 / e2) / math.log(n2 / n1)   # h = L / nelem
    return out


def penalty_slopes(rows, column="err_force"):
    """Observed penalty slope per (order, nelem): least-squares slope of log(err) against log(mu)
    over the converged runs of that mesh (NaN with fewer than two penalties)."""
    out = {}
    for g in sorted({(r["order"], r["nelem"]) for r in rows}):
        pts = [(float(r["penalty"]), float(r[column])) for r in rows
               if (r["order"], r["nelem"]) == g and on_branch(r) and np.isfinite(float(r[column]))
               and float(r[column]) > ROUNDOFF and np.isfinite(float(r["penalty"]))]
        if len({m for m, _ in pts}) < 2:
            out[g] = float("nan")
            continue
        x, y = np.log([m for m, _ in pts]), np.log([e for _, e in pts])
        out[g] = float(np.polyfit(x, y, 1)[0])
    return out


def read_csv(path):
    """Rows of a work_precision.csv as study() returns them (numbers as numbers, NaN if empty)."""
    ints, text = ("order", "nelem", "ranks"), ("case", "outdir", "note")
    rows = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            row = {c: float("nan") for c in CSV_COLUMNS}
            for k, v in r.items():
                if k in text:
                    row[k] = v
                elif k in ("converged", "est_converged"):
                    row[k] = v == "True"
                elif k in ints and v not in ("", "nan"):
                    row[k] = int(float(v))
                elif v not in ("", None):
                    row[k] = float(v)
            rows.append(row)
    return rows


def write_csv(rows, path):
    path = Path(path)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in CSV_COLUMNS})
    os.replace(tmp, path)


def plot(rows, path, case):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [c for c in ERRORS if any(r["converged"] and np.isfinite(float(r[c])) for r in rows)] or ["err_tip"]
    titles = {"err_tip": "tip error / L", "err_l2": "L2 centreline error (RMS / L)",
              "err_energy": "relative energy error", "err_max": "max centreline error / L"}
    fig, axes = plt.subplots(len(cols), 2, figsize=(10, 3.3 * len(cols) + 0.6), squeeze=False)
    orders = sorted({r["order"] for r in rows})
    cmap = plt.get_cmap("viridis")
    for i, c in enumerate(cols):
        rt = rates(rows, c)
        for j, xcol in enumerate(("wall_time_s", "dofs")):
            ax = axes[i, j]
            for k, p in enumerate(orders):
                pts = sorted((r["nelem"], float(r[xcol]), float(r[c])) for r in rows   # mesh order
                             if r["order"] == p and r["converged"] and np.isfinite(float(r[c]))
                             and float(r[c]) > 0 and np.isfinite(float(r[xcol])))
                if not pts:
                    continue
                _, x, y = zip(*pts)
                lab = f"p = {p}" + (f"  (rate {rt[p]:.2f})" if np.isfinite(rt[p]) else "")
                col = cmap(k / max(len(orders) - 1, 1) * 0.85)
                ax.loglog(x, y, "o-", color=col, label=lab, ms=4)
                x, y = estimate_series([r for r in rows if r["order"] == p], xcol, c)
                if x:
                    ax.loglog(x, y, "s--", color=col, ms=7, lw=1, mfc="none")   # visible on top
            ax.set_xlabel("wall time [s]" if xcol == "wall_time_s" else "degrees of freedom")
            ax.set_ylabel(titles[c])
            ax.grid(True, which="both", alpha=0.3)
            if j == 1:
                if c in ESTIMATE_OF:
                    ax.plot([], [], "ks--", lw=1, ms=7, mfc="none", label="estimate (solver)")
                ax.legend(fontsize=8, title="rate = slope vs h", title_fontsize=7)
    nfail = sum(1 for r in rows if not r["converged"])
    fig.suptitle(f"work-precision: {case}" + (f"  ({nfail} failed runs not shown)" if nfail else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def estimate_series(rows, xcol, err):
    """(x, y) of the estimate paired with the error column err (ESTIMATE_OF) over the converged
    rows on the reference's branch whose estimate converged, in mesh order; ([], []) if none."""
    est = ESTIMATE_OF.get(err)
    if est is None:
        return [], []
    pts = sorted((r["nelem"], float(r[xcol]), float(r[est])) for r in rows
                 if on_branch(r) and r.get("est_converged") is True and np.isfinite(float(r[est]))
                 and float(r[est]) > 0 and np.isfinite(float(r[xcol])))
    return [q[1] for q in pts], [q[2] for q in pts]


def on_branch(r):
    """A converged run on the reference's equilibrium (rollup_contact: tip within OTHER_BRANCH L of
    the penalty law's; the other cases have one branch)."""
    e = float(r.get("err_tip_law", float("nan")))
    return bool(r["converged"]) and not (np.isfinite(e) and e > OTHER_BRANCH)


def _finite(rows, *cols):
    """Converged rows on the reference's branch whose columns are all finite and positive."""
    return [r for r in rows if on_branch(r)
            and all(np.isfinite(float(r[c])) and float(r[c]) > 0 for c in cols)]


def plot_contact(rows, path, case="rollup_contact"):
    """rollup_contact, 2 x 3 panels.  Rows: tip error, force error (against the hard contact).
    Column 1: against wall time, one line per (order, penalty) over the meshes.  Column 2: against
    the mesh, solid against the hard contact, dotted against the penalty law at the run's mu (the
    finite-element part).  Column 3: the force error against mu, one line per (order, mesh), with
    mu^(-1/2); the Newton iterations of the whole load path against mu."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    orders = sorted({r["order"] for r in rows})
    factors = sorted({float(r["penalty_factor"]) for r in rows})
    meshes = sorted({r["nelem"] for r in rows})
    styles = ["o-", "s--", "^-.", "d:"]

    def colour(cmap, items, v):
        return plt.get_cmap(cmap)(items.index(v) / max(len(items) - 1, 1) * 0.85)

    def series(sel, xcol, ycol):
        """(x, y) of the converged rows, sorted by mesh then penalty."""
        pts = sorted((r["nelem"], float(r["penalty"]), float(r[xcol]), float(r[ycol]))
                     for r in _finite(sel, xcol, ycol))
        return [q[2] for q in pts], [q[3] for q in pts]

    fig, axes = plt.subplots(2, 3, figsize=(15, 9.4))
    ylab = {"err_tip": "tip error / L", "err_force": "relative contact force error"}
    for i, c in enumerate(("err_tip", "err_force")):
        for k, p in enumerate(orders):
            for f in factors:
                sel = [r for r in rows if r["order"] == p and float(r["penalty_factor"]) == f]
                col, st = colour("viridis", factors, f), styles[k % len(styles)]
                x, y = series(sel, "wall_time_s", c)
                if x:
                    axes[i, 0].loglog(x, y, st, color=col, ms=4, label=f"p = {p}, mu = {f:g} mu0")
                    for r in _finite(sel, "wall_time_s", c):      # the mesh of each point
                        axes[i, 0].annotate(str(r["nelem"]), (float(r["wall_time_s"]), float(r[c])),
                                            textcoords="offset points", xytext=(2, 2), fontsize=6, color=col)
                x, y = series(sel, "nelem", c)
                if x:
                    axes[i, 1].loglog(x, y, st, color=col, ms=4)
                x, y = series(sel, "nelem", c + "_law")
                if x:
                    axes[i, 1].loglog(x, y, ":", marker="x", color=col, ms=4, lw=1)
                x, y = estimate_series(sel, "nelem", c + "_law")
                if x:
                    axes[i, 1].loglog(x, y, "--", marker="s", mfc="none", color=col, ms=7, lw=1)
        axes[i, 0].set_xlabel("wall time [s] (labels: elements)")
        axes[i, 1].set_xlabel("elements (h = L / nelem)")
        for j in (0, 1):
            axes[i, j].set_ylabel(ylab[c])
            axes[i, j].grid(True, which="both", alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()   # (order, penalty): below the panels
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=8)
    axes[0, 1].plot([], [], "k-", label="vs hard contact (exact)")
    axes[0, 1].plot([], [], "k:", marker="x", label="vs penalty law at the run's mu (FE error)")
    axes[0, 1].plot([], [], "k--", marker="s", mfc="none", label="the solver's estimate of the FE error")
    axes[0, 1].legend(fontsize=7)

    slopes = penalty_slopes(rows, "err_force")
    for k, p in enumerate(orders):
        for n in meshes:
            sel = [r for r in rows if r["order"] == p and r["nelem"] == n]
            col, st = colour("plasma", meshes, n), styles[k % len(styles)]
            x, y = series(sel, "penalty", "err_force")
            if x:
                sl = slopes.get((p, n), float("nan"))
                axes[0, 2].loglog(x, y, st, color=col, ms=4,
                                  label=f"p = {p}, {n} el." + (f" ({sl:.2f})" if np.isfinite(sl) else ""))
            x, y = series(sel, "penalty", "newton_iterations")
            if x:
                axes[1, 2].semilogx(x, y, st, color=col, ms=4, label=f"p = {p}, {n} el.")
    ok = _finite(rows, "penalty", "err_force")
    if ok:   # mu^(-1/2) through the median run at the softest penalty
        mu_lo = min(float(r["penalty"]) for r in ok)
        e_lo = float(np.median([float(r["err_force"]) for r in ok if float(r["penalty"]) == mu_lo]))
        mus = np.array(sorted({float(r["penalty"]) for r in ok}))
        axes[0, 2].loglog(mus, e_lo * (mus / mu_lo) ** -0.5, "k--", lw=1, label="mu^(-1/2)")
    axes[0, 2].set_ylabel("relative contact force error")
    axes[0, 2].legend(fontsize=7, title="slope of log err vs log mu", title_fontsize=7)
    axes[1, 2].set_ylabel("Newton iterations (whole load path)")
    axes[1, 2].legend(fontsize=7)
    for ax in axes[:, 2]:
        ax.set_xlabel("penalty mu")
        ax.grid(True, which="both", alpha=0.3)
    nfail = sum(1 for r in rows if not r["converged"])
    nother = sum(1 for r in rows if r["converged"] and not on_branch(r))
    fig.suptitle(f"work-precision with contact: {case} (errors against the planar reference)"
                 + (f"  ({nfail} failed run(s) not shown)" if nfail else "")
                 + (f"  ({nother} run(s) on another equilibrium not shown)" if nother else ""))
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _ints(text):
    return [int(v) for v in text.split(",") if v.strip()]


def _floats(text):
    return [float(v) for v in text.split(",") if v.strip()]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("--case", choices=("rollup", "mattiasson", "rollup_contact"), default="rollup")
    ap.add_argument("--orders", type=_ints, default=[1, 2, 3, 4])
    ap.add_argument("--nelem", type=_ints, default=[2, 4, 8, 16, 32])
    ap.add_argument("--np", type=int, default=1, help="MPI ranks per run")
    ap.add_argument("--out", default=None, help="output folder (default out/work_precision_CASE)")
    ap.add_argument("--extra", default="", help='more solver options, e.g. "-load_steps 4"')
    ap.add_argument("--exe", default=None, help="solver command (default .venv/bin/rodsnes or python -m rodsnes)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    ap.add_argument("--ref-nelem", type=int, default=None,
                    help="elements of the order-4 overkill reference (mattiasson; default 4 x the finest mesh)")
    ap.add_argument("--from-csv", default=None,
                    help="no runs: plot and report the rows of this work_precision.csv (into --out)")
    ap.add_argument("--penalties", type=_floats, default=None,
                    help="rollup_contact: multipliers f of the default penalty mu0, each run at the fixed "
                         "-contact_penalty f mu0 (default 1)")
    args = ap.parse_args(argv)
    if args.penalties is not None and args.case != "rollup_contact":
        ap.error("--penalties is for --case rollup_contact")

    out = args.out or os.path.join("out", f"work_precision_{args.case}")
    os.makedirs(out, exist_ok=True)
    case_file = ROOT / "cases" / f"{args.case}.opts"
    ref_nelem = args.ref_nelem or 4 * max(args.nelem)
    runner = CliRunner(args.case, case_file, args.exe, args.timeout, ref_nelem)
    csv_path = os.path.join(out, "work_precision.csv")
    if args.from_csv:
        rows = [r for r in read_csv(args.from_csv) if r["case"] == args.case]
        write_csv(rows, csv_path)
        if args.case == "rollup_contact":
            plot_contact(rows, os.path.join(out, "work_precision.png"), args.case)
            return report_contact(rows, out)
        plot(rows, os.path.join(out, "work_precision.png"), args.case)
        return 0
    if args.case == "rollup_contact":
        mu0 = default_contact_penalty(case_file, args.extra.split())
        penalties = [(f, f * mu0) for f in (args.penalties or [1.0])]
        print(f"default penalty mu0 = {mu0:.6g}; runs at mu = " + ", ".join(f"{m:.4g}" for _, m in penalties),
              flush=True)
        rows = study(args.case, args.orders, args.nelem, args.np, out, args.extra, runner,
                     penalties=penalties, progress=lambda rows: write_csv(rows, csv_path))
        plot_contact(rows, os.path.join(out, "work_precision.png"), args.case)
        return report_contact(rows, out)
    rows = study(args.case, args.orders, args.nelem, args.np, out, args.extra, runner,
                 progress=lambda rows: write_csv(rows, csv_path))
    plot(rows, os.path.join(out, "work_precision.png"), args.case)
    all_rates = {c: rates(rows, c) for c in ERRORS}
    print("\nobserved rates vs h (two finest converged meshes; shared/REFERENCES.md expects positions "
          "O(h^(p+1)), energy O(h^(2p)); nodal values such as the tip may superconverge):")
    print("order " + " ".join(f"{c:>12s}" for c in ERRORS))
    for p in args.orders:
        print(f"{p:5d} " + " ".join(f"{all_rates[c][p]:12.2f}" for c in ERRORS))
    print("\nthe solver's estimate / the true error (converged estimates; shared sampling):")
    for p in args.orders:
        print(f"  p={p}: " + "; ".join(f"{e} / {c} {_range(estimate_ratios(rows, p, c), '.2f')}"
                                       for c, e in (("err_tip", "est_tip"), ("err_max", "est_centreline"))))
    if args.case == "mattiasson":
        # no rate: the published values are the inextensible elastica to 6 digits, so this error
        # levels off at max(6-digit rounding ~7e-7, the model difference ~ P/EA, P/GA)
        print("\nerror against the published tip (finest converged mesh per order; floor = "
              "6-digit rounding and extensibility/shear of the model):")
        for p in args.orders:
            ok = [r for r in rows if r["order"] == p and r["converged"]
                  and np.isfinite(float(r["err_tip_published"]))]
            if ok:
                r = max(ok, key=lambda r: r["nelem"])
                print(f"  p={p} nelem={r['nelem']}: {float(r['err_tip_published']):.3e}")
    Path(out, "rates.json").write_text(json.dumps(output.to_jsonable(all_rates), indent=2) + "\n")
    nfail = sum(1 for r in rows if not r["converged"])
    print(f"\n{len(rows) - nfail}/{len(rows)} runs converged; wrote {out}/work_precision.csv, "
          f"{out}/work_precision.png")
    return 0 if nfail == 0 else 1


def report_contact(rows, out):
    """rollup_contact: observed rates of the finite-element error (against the penalty law) per
    (order, penalty), penalty slopes of the hard-contact errors per (order, mesh), and the cost
    (Newton iterations, wall time) per penalty relative to the softest; rates.json; exit status."""
    def key(r):
        return (r["order"], float(r["penalty_factor"]))

    groups = sorted({key(r) for r in rows})
    fe = {c: rates(rows, c, key=key) for c in ("err_tip_law", "err_force_law", "err_tip", "err_force")}
    print("\nobserved rates vs h (two finest converged meshes): FE part (vs the penalty law) and total (vs hard)")
    print("order  mu/mu0 " + " ".join(f"{c:>14s}" for c in fe))
    for g in groups:
        print(f"{g[0]:5d} {g[1]:7g} " + " ".join(f"{fe[c][g]:14.2f}" for c in fe))
    pen = {c: penalty_slopes(rows, c) for c in ("err_force", "err_tip")}
    print("\npenalty slopes d log(err) / d log(mu) (least squares over the penalties; the penalty law: -0.5)")
    print("order nelem " + " ".join(f"{c:>10s}" for c in pen))
    for g in sorted(pen["err_force"]):
        print(f"{g[0]:5d} {g[1]:5d} " + " ".join(f"{pen[c][g]:10.2f}" for c in pen))
    print("\ncost per penalty (converged runs; ratio to the softest penalty on the same (order, mesh)):")
    base = {(r["order"], r["nelem"]): r for r in rows if r["converged"]
            and float(r["penalty_factor"]) == min(float(q["penalty_factor"]) for q in rows)}
    for f in sorted({float(r["penalty_factor"]) for r in rows}):
        sel = [r for r in rows if float(r["penalty_factor"]) == f and r["converged"]]
        its = [float(r["newton_iterations"]) / float(base[(r["order"], r["nelem"])]["newton_iterations"])
               for r in sel if (r["order"], r["nelem"]) in base]
        wt = [float(r["wall_time_s"]) / float(base[(r["order"], r["nelem"])]["wall_time_s"])
              for r in sel if (r["order"], r["nelem"]) in base]
        nfail = sum(1 for r in rows if float(r["penalty_factor"]) == f and not r["converged"])
        nother = sum(1 for r in sel if not on_branch(r))
        print(f"  mu = {f:g} mu0: {len(sel)} converged ({nother} on another equilibrium), {nfail} failed; "
              f"Newton iterations "
              f"{_range([float(r['newton_iterations']) for r in sel])} (x{_gmean(its):.2f}), wall time "
              f"{_range([float(r['wall_time_s']) for r in sel], '.1f')} s (x{_gmean(wt):.2f}), load steps "
              f"{_range([float(r['load_steps']) for r in sel])}")
    js = {c: {f"p{g[0]}_mu{g[1]:g}": v for g, v in fe[c].items()} for c in fe}
    js.update({f"penalty_slope_{c}": {f"p{g[0]}_n{g[1]}": v for g, v in pen[c].items()} for c in pen})
    Path(out, "rates.json").write_text(json.dumps(output.to_jsonable(js), indent=2) + "\n")
    nfail = sum(1 for r in rows if not r["converged"])
    print(f"\n{len(rows) - nfail}/{len(rows)} runs converged; wrote {out}/work_precision.csv, "
          f"{out}/work_precision.png")
    return 0 if nfail == 0 else 1


def estimate_ratios(rows, order, err):
    """est / err of the order's converged runs with a converged estimate (ESTIMATE_OF)."""
    est = ESTIMATE_OF[err]
    return [float(r[est]) / float(r[err]) for r in rows
            if r["order"] == order and on_branch(r) and r.get("est_converged") is True
            and float(r[err]) > ROUNDOFF and np.isfinite(float(r[est]))]


def _range(v, fmt=".0f"):
    v = [x for x in v if np.isfinite(x)]
    return f"{min(v):{fmt}}..{max(v):{fmt}}" if v else "nan"


def _gmean(v):
    v = [x for x in v if np.isfinite(x) and x > 0]
    return float(np.exp(np.mean(np.log(v)))) if v else float("nan")


if __name__ == "__main__":
    sys.exit(main())
