"""One rodsnes run: build everything from a Scene, step the load, write results.

Files (DIR = -output_dir): result.h5 (one group per converged step, flushed per step),
rod.xdmf (+ rod.h5, ParaView), summary.json (rewritten atomically after steps, within
SUMMARY_SHARE of the wall time, and at the end, on failure and on an interruption, so a
failed or interrupted run leaves its last converged state described on disk).

A run of a conservative scene that ends on an unstable equilibrium (negative eigenvalues of the
energy Hessian, counted by the minimiser or by -stability) has failed unless unstable
equilibria were asked for: by -load_arclength, which follows unstable branches, or by
-load_path newton, which finds a zero of the residual, stable or not; then it has converged
and its last line says that the equilibrium is unstable.
"""
import os
import time

import numpy as np

from rodsnes import interrupts, petsc_lib, profiling
from rodsnes.collective import on_root
from rodsnes.model import mesh as rodmesh
from rodsnes.io import results as output
from rodsnes.model import partition
from rodsnes.model.partition import NDOF
from rodsnes.model.problem import RodProblem
from rodsnes.solve.load_path import LoadPath
from rodsnes.solve.newton import NewtonSolver
from rodsnes.terms import scene_terms, contact_term
from rodsnes.solve import estimate, linear, schur, stability
from rodsnes.solve import planar
from rodsnes.model import plane as planes
from rodsnes.model.scales import force_scale
from rodsnes.model.loads import nonconservative, takes_newton_path
from rodsnes.errors import SceneError, tell
from rodsnes.io.scene import MIN_LOAD_STEP, scene_record, record_mismatches

# Newton steps whose linear solve failed, at least, and at least half of those tried, before
# the run warns that its linear solver may be the cause (Run._warn_failed_newton_steps)
NEWTON_FAILURES = 3

# largest share of the wall time spent rewriting summary.json after load steps: its list of
# steps grows with the run (12 ms a write at 526 steps), so a write after every step would
# cost O(steps^2); it is always written at the end, on failure and on an interruption
SUMMARY_SHARE = 0.01


class Run:
    tolerance_trial = False     # set by estimate.to_tolerance on the runs it makes

    def __init__(self, scene, comm):
        self.t_start = time.perf_counter()
        linear.forget_defaults()
        self.scene, self.comm = scene, comm
        self.mpi = comm.tompi4py()
        self.rank = comm.getRank()
        self.mesh = rodmesh.build_mesh(scene.rod, scene.bc)
        self.layout = partition.Layout(comm, self.mesh)
        terms = scene_terms(scene, self.mesh, self.layout)
        # the self-contact term, or None (for tools and tests that look into it)
        self.contact = contact_term(terms)
        self.problem = RodProblem(scene, self.mesh, self.layout, terms)
        # -rod_planar: the linear solves on the in-plane block of a planar scene (planar.py)
        self.plane, self.planar_why = self._choose_model(scene)
        if self.plane is not None:
            self.problem.planar = planar.PlanarSystem(self.problem, self.plane, say=self._say)
        rod = scene.rod
        L = rod.length
        ld = scene.loads
        self.force_scale = force_scale(scene)
        self.conservative = nonconservative(scene.loads) is None
        self.path = self._choose_path(scene)
        # -load_arclength: unstable branches followed on purpose (the Newton path's continuation)
        self.arclength = scene.loads.arclength
        if self.path == "minimize":
            self.solver = LoadPath(self.problem, self.force_scale,
                                   rtol=ld.rtol,
                                   max_it=ld.max_it, quiet=scene.output.quiet)
        else:
            self.solver = NewtonSolver(self.problem, self.force_scale,
                                       check_stability=scene.stability,
                                       conservative=self.conservative)
        self.outdir = scene.output.dir
        self.quiet = scene.output.quiet
        self.step = 0
        self.lam0 = 0.0
        self.nneg0 = 0              # negative eigenvalues of the restart state (-stability)
        self.dlam0 = None           # the restart's first increment (None: the nominal one)
        self.prev0 = None           # (snapshot, load) of the step before the restart state
        self.arc0 = None            # a restart inside a pseudo-arclength continuation: its fold
        self.history = []
        self._summary_budget = output.RewriteBudget(self.t_start)  # summary.json after steps
        self._last_summary = None    # the summary made after the last step (written or not)
        self.live_trial = None       # -rod_tolerance: the trial running now (estimate.to_tolerance)
        self.estimator = estimate.ErrorEstimator.of(scene, comm, self.path == "minimize")
        self.last_estimate = None
        meta = {"case_name": scene.output.case_name, "closed": bool(rod.closed), "length": L,
                "radius": rod.radius, "nelem": rod.nelem, "order": rod.order}
        append = False
        if scene.output.restart:
            self._restart(scene.output.restart)
            if self.lam0 >= 1.0 - 1e-14:
                raise SceneError(f"-restart {scene.output.restart}: that run is complete (load "
                                 f"{self.lam0:.6f}): nothing is left to resume; drop -restart "
                                 f"for a new run", ("-restart",))
            if self.lam0 >= scene.loads.stop - 1e-14:
                raise SceneError(f"-load_stop {scene.loads.stop:g}: the run restarted from "
                                 f"{scene.output.restart} already stands at load {self.lam0:.6f}; "
                                 f"raise -load_stop (at most 1) or drop it", ("-load_stop", "-restart"))
            append = os.path.abspath(scene.output.restart) == os.path.abspath(self.outdir)
        on_root(self.mpi, self._make_output_dir)   # its refusal said on every rank
        self.writer = output.ResultWriter(self.outdir, self.mpi, self.mesh.n_nodes, meta, append=append)
        self.dofs = NDOF * self.mesh.n_nodes

    def _choose_model(self, scene):
        """(Plane or None, why 3-D): -rod_planar auto solves a planar scene in its plane, off
        in 3-D; on is refused for a scene that is not planar (SceneError naming the part that
        leaves the plane)."""
        if scene.rod.planar == "off":
            return None, "-rod_planar off"
        plane, why = planes.detect(scene, self.mesh)
        if plane is None and scene.rod.planar == "on":
            raise SceneError(planes.refusal(why), ("-rod_planar",))
        return plane, why

    def model(self):
        """summary.json's ``model``: "planar (x, y, theta per node)" (and where it went on in
        3-D), or "3-D"."""
        pl = self.problem.planar
        return "3-D" if pl is None else pl.model()

    def _say(self, text):
        if not self.quiet and self.rank == 0:
            print(text, flush=True)

    @staticmethod
    def _choose_path(scene):
        """-load_path: minimize where the loads are conservative (auto), newton otherwise or
        when pseudo-arclength continuation (-load_arclength) is asked for."""
        why = nonconservative(scene.loads)
        path = scene.loads.path
        arclength = scene.loads.arclength
        if path == "auto":
            return "newton" if takes_newton_path(scene.loads) else "minimize"
        if path == "minimize" and why:
            raise SceneError(f"-load_path minimize minimises the energy, and {why}: use "
                             "-load_path newton (or auto) with these loads", ("-load_path",))
        if path == "minimize" and arclength:
            raise SceneError("-load_arclength follows unstable branches, which an energy "
                             "minimisation never stops on: use -load_path newton with it",
                             ("-load_path", "-load_arclength"))
        return path

    # ------------------------------------------------------------------------------
    def _restart(self, rdir):
        """Resume from the last converged step of an earlier run in rdir (refused with a
        SceneError if rdir holds no readable step or a run of another scene).  Collective."""
        last, before = self._read_restart(rdir)
        self._check_restart_scene(rdir, last["meta"])
        st = self.problem.state
        pos = np.asarray(last["positions"])
        if pos.shape[0] != self.mesh.n_nodes:
            raise SceneError(f"-restart {rdir}: it holds {pos.shape[0]} nodes, this scene has "
                             f"{self.mesh.n_nodes}: use the same -rod_nelem and -rod_order")
        st.restore(st.snapshot_of_step(last))
        for term in self.problem.terms:
            term.restart(last["attrs"])            # e.g. the adapted penalty
            why = term.refuses(st.local_config()[0])
            if why is not None:
                raise SceneError(f"-restart {rdir}: {why}", ("-restart",))
        self.lam0 = float(last["attrs"]["load"])
        self.nneg0 = int(last["attrs"].get("negative_eigenvalues", 0))
        comp = last["attrs"].get("gauge_component")
        self.problem.gauge_component = None if comp is None else int(comp)
        self.step = int(last["step"])
        self.problem.set_load(self.lam0)
        # the steps the interrupted run would have taken next: its next increment, and the
        # secant predictor through the step before (none across a step flagged branch_switch:
        # files written by earlier versions)
        dlam = last["attrs"].get("next_increment")
        self.dlam0 = None if dlam is None else float(dlam)
        arc = last["attrs"].get("arclength_from")
        if arc is not None and self.arclength:
            self.arc0 = float(arc)      # dlam0 is then the continuation's next increment
        # (a checkpoint of one step has no step before it: the last state predicts)
        if before is not None:
            self.prev0 = (st.snapshot_of_step(before), float(before["attrs"]["load"]))

    def _make_output_dir(self):
        """Make -output_dir (rank 0: on_root), or a SceneError naming it."""
        try:
            os.makedirs(self.outdir, exist_ok=True)
        except OSError as exc:
            raise SceneError(f"-output_dir {self.outdir}: cannot be made "
                             f"({exc.strerror or exc}): give a writable directory",
                             ("-output_dir",)) from None

    def _read_restart(self, rdir):
        """(last, before): the last complete step of rdir's result.h5 and the step before it
        (None where there is none, or across a step flagged branch_switch), read on rank 0
        alone and sent to every rank (on_root), so that all ranks resume from one reading of
        the file (read by each, a file another run was still writing gave the ranks different
        steps and mixed states); its SceneError raised on every rank.  Collective."""
        return on_root(self.mpi, self._restart_steps, rdir)

    def _restart_steps(self, rdir):
        """_read_restart's reading (rank 0), any failure a SceneError naming -restart."""
        try:
            last = self._restart_step(rdir)
            step, before = int(last["step"]), None
            if (step >= 1 and not last["attrs"].get("branch_switch", 0)
                    and step - 1 in output.read_steps(rdir)):
                before = output.read_step(rdir, step - 1)
                # a step before at the last one's load makes no secant (the predictors divide
                # by the loads' difference): resumed without it, as from a one-step checkpoint
                if not abs(float(last["attrs"].get("load", np.nan))
                           - float(before["attrs"].get("load", np.nan))) > MIN_LOAD_STEP:
                    before = None
            for s in (last, before):
                why = None if s is None else self._unreadable_state(s)
                if why is not None:
                    raise SceneError(f"-restart {rdir}: its step {int(s['step'])} holds {why}, "
                                     f"not a state rodsnes writes: restart from another run or "
                                     f"a checkpoint, or drop -restart", ("-restart",))
            return last, before
        except SceneError:
            raise
        except Exception as exc:    # noqa: BLE001 - a SceneError, said on every rank
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise SceneError(f"-restart {rdir}: its steps cannot be read ({why}): restart from "
                             f"another run or a checkpoint, or drop -restart",
                             ("-restart",)) from None

    @staticmethod
    def _unreadable_state(step):
        """What makes a stored step no state to resume from (None: nothing): a load outside
        0..1 or not a number (a NaN load made the restarted run end at once, converged, with
        no step), positions or directors not finite, rotation quaternions not of unit length,
        a next increment not a positive number."""
        attrs = step["attrs"]
        lam = float(attrs.get("load", np.nan))
        if not 0.0 <= lam <= 1.0:
            return f"the load {lam!r}"
        for name in ("positions", "directors", "rotation"):
            v = step.get(name)
            if v is not None and not np.all(np.isfinite(np.asarray(v, dtype=float))):
                return f"{name} that are not finite"
        q = step.get("rotation")
        if q is not None and np.abs(np.linalg.norm(np.asarray(q, dtype=float), axis=1)
                                    - 1.0).max(initial=0.0) > 1e-6:
            return "rotation quaternions not of unit length"
        dlam = attrs.get("next_increment")
        if dlam is not None and not float(dlam) >= MIN_LOAD_STEP:
            return f"the next increment {float(dlam)!r} (below the load's resolution)"
        return None

    def _tip(self, fields):
        if self.mesh.closed:
            return None
        return self.layout.allgather_nodes(fields["positions"])[-1]

    @staticmethod
    def _step_record(res):
        """What a converged step reports, in result.h5 and in summary.json's history: Newton
        iterations, residual, seconds, the increment the next step starts from, negative
        eigenvalues, the fold a continuation point goes round, the minimiser's statistics."""
        rec = {"newton_iterations": res.its, "residual_norm": res.fnorm, "seconds": res.seconds}
        if hasattr(res, "next_increment"):
            rec["next_increment"] = res.next_increment
        if hasattr(res, "negative_eigenvalues"):
            rec["negative_eigenvalues"] = res.negative_eigenvalues
        if getattr(res, "arclength", False):
            rec["arclength_from"] = res.arclength_from
        for key in ("link_error", "shifts", "line_search_cuts", "escapes", "valley_points",
                    "out_of_plane_negative_eigenvalues"):
            if getattr(res, key, None) is not None:
                rec[key] = res.__dict__[key]
        return rec

    def observe(self):
        """The current state's fields, energy, the terms' reports and topology (collective);
        sets the last_* attributes that summary.json is made from.  Returns (fields, energy,
        the reports as result.h5 attributes (<term>_<key>), quadrature-point fields,
        topology)."""
        p = self.problem
        fields = p.owned_fields()
        energy = p.energy()
        reports = p.report()
        kappa = p.max_curvature()
        if kappa is not None:
            # the thickness bound on bending completes the contact model (-contact_curvature)
            reports["contact"]["max_curvature"] = kappa
        cattrs = {f"{name}_{k}": v for name, rep in reports.items() for k, v in rep.items()}
        qp = p.qp_fields()
        topo = p.topology()
        self.last_reports = reports
        if topo is not None:
            self.last_topology = topo
        self.last_fields = fields
        self.last_energy = energy
        return fields, energy, cattrs, qp, topo

    def _write(self, res):
        """Write the current state as step self.step of result.h5: load, energy, the step's
        record (res: a converged step, None for the start), the contact KKT picture and the
        topology (observe).  Returns the energy."""
        extra = {}
        if res is not None:       # HDF5 attributes: flags as 0/1
            extra = {k: int(v) if isinstance(v, bool) else v
                     for k, v in self._step_record(res).items()}
        fields, energy, cattrs, qp, topo = self.observe()
        attrs = {"load": self.problem.lam, "energy": energy, "newton_iterations": 0,
                 "residual_norm": 0.0, **extra, **cattrs, **(topo or {}), **self._estimate(res)}
        if self.problem.gauge is not None:   # the sliding gauge's held coordinate (a restart's)
            attrs["gauge_component"] = self.problem.gauge[1]
        self.writer.write_step(self.step, attrs, self.layout.owned_nodes, fields,
                               qp_owned=qp.get("ids"), qp_fields=qp.get("fields"),
                               n_qp=qp.get("n"))
        return energy

    def _estimate(self, res):
        """The converged step's a-posteriori error estimate (solve/estimate.py) as step
        attributes ({} for the start, for a step before the last with -rod_error_estimate last,
        and with -rod_error_estimate off)."""
        if res is None or not estimate.wanted(self.estimator, self.scene, self.problem.lam):
            return {}
        self.last_estimate = self.estimator.estimate(self.problem)
        return estimate.step_attrs(self.last_estimate)

    def write_summary(self, summary):
        """summary.json of this run's output directory (collective)."""
        output.write_summary(self.outdir, self.mpi, summary)

    def summary(self, converged, failed_reason=None):
        s = {"case": self.scene.output.case_name, "converged": bool(converged),
             "load": self.problem.lam, "energy": self.last_energy,
             "newton_iterations": self.solver.total_its, "load_steps": len(self.history),
             "wall_time_s": time.perf_counter() - self.t_start, "dofs": self.dofs,
             "ranks": self.comm.getSize(), "path": self.path, "model": self.model(),
             "steps": self.history}
        if self.path == "newton":
            s["predictor_retries"] = self.solver.predictor_retries
            s["stagnated_solves"] = self.solver.stagnations
        nneg = self._last_count()
        s["negative_eigenvalues"] = nneg
        # None: not counted, or loads without a potential (follower forces, 3-D end moments),
        # for which the inertia of the elastic energy's Hessian does not decide stability
        s["stable"] = None if nneg is None or not self.conservative else bool(nneg == 0)
        if "neutral_band" in self.problem.stats:
            # eigenvalues of H v = lambda M v above -neutral_band EI_min / L^4 count as neutral
            s["neutral_band"] = self.problem.stats["neutral_band"]
        tip = self._tip(self.last_fields)
        if tip is not None:
            s["tip_position"] = tip.tolist()
        if self.last_estimate is not None:
            s["error_estimate"] = estimate.summary_entry(self.last_estimate, self.estimator,
                                                         s["wall_time_s"])
        if failed_reason is not None:
            s["failure"] = failed_reason
        for term in self.problem.terms:          # a section per reporting term
            if term.name in self.last_reports:
                s[term.name] = self.last_reports[term.name]
                s[term.name].update(term.run_summary(self.problem.stats))
        if getattr(self, "last_topology", None) is not None:
            s["topology"] = self.last_topology
        gauge = self.problem.gauge_report()
        if gauge is not None:
            s["gauge"] = gauge
        return s

    def _log(self, res, energy):
        if self.quiet or self.rank != 0:
            return
        extra = "".join(term.log_text() for term in self.problem.terms)
        print(f"step {self.step:4d}  load {res.lam:.6f}  its {res.its:3d}  |F| {res.fnorm:9.3e}  "
              f"E {energy:+.6e}{extra}  {res.seconds:7.2f} s", flush=True)

    def header(self):
        """The run's first progress line: the discretisation, the path and the terms' choices
        (e.g. the contact law that -contact_model auto picked)."""
        rod = self.scene.rod
        path = {"minimize": "energy minimisation per load step",
                "newton": "Newton"}.get(self.path, self.path)
        if self.arclength:
            path = "Newton with pseudo-arclength continuation"
        parts = [f"{self.scene.output.case_name}: {rod.nelem} elements of order {rod.order}, "
                 f"{self.dofs} unknowns, {self.comm.getSize()} rank(s)", path]
        # -rod_planar: the model solved (planar.py), and why 3-D for a scene that is not planar
        parts.append(self.model() + " (in-plane unknowns only)" if self.plane is not None
                     else "3-D (" + self.planar_why + ")")
        parts += [t.describe() for t in self.problem.terms if t.describe()]
        size = self.comm.getSize()
        if size > 1 and not schur.pays(self.mesh.n_nodes, size, "mumps"):
            # below both condensation thresholds: the ranks share the residual and the tangent,
            # not the factorisation (the plectoneme's 181 nodes: 27.7 s on 2 ranks, 23 s on one)
            parts.append(f"every rank factors the whole matrix: {self.mesh.n_nodes} nodes are "
                         f"too few to share it over {size} ranks (one rank may be as fast)")
        if self.scene.stability and not self.conservative:
            parts.append("-stability: " + nonconservative(self.scene.loads).split(", so")[0]
                         + ": the Hessian's negative eigenvalues are counted but decide no "
                         "stability, and no step is cut back for them")
        if rod.kernel == "auto" and self.problem.elastic.kernel != "compiled":
            parts.append("elastic kernel in numpy, 10-20 x slower: the compiled one is not built "
                         "or older than its source (make install)")
        return "; ".join(parts)

    def execute(self):
        """Solve the scene's load path (or, with -rod_tolerance, its meshes); returns whether
        it converged.  The solver defaults it put into the options database leave it at the
        end (linear.take_back_defaults)."""
        try:
            if self.scene.rod.tolerance is not None and not self.tolerance_trial:
                return estimate.to_tolerance(self)      # the mesh chosen from the estimate
            return self._execute()
        finally:
            linear.take_back_defaults()

    def _execute(self):
        if not self.quiet and self.rank == 0:
            print(self.header(), flush=True)
        if not self.scene.output.restart:
            self.problem.set_load(0.0)
            self._write(None)
        else:
            self.observe()        # a restart that fails at once still reports its state
        ld = self.scene.loads
        # the matrices, the LU's choice and plans made before the first Newton iteration, in a
        # log stage of their own (profiling.SET_UP)
        with profiling.stage(profiling.SET_UP):
            self.solver.setup()

        failed = []             # the failed tries since the last converged step (on_fail)

        def on_step(res):
            failed.clear()
            # the step written and recorded whole: a signal meanwhile waits (interrupts.py)
            with interrupts.deferred():
                self.step += 1
                energy = self._write(res)
                self.history.append({"load": res.lam, **self._step_record(res)})
                self._log(res, energy)
                # made after every step (collective, ~0.3 ms), written when due: an
                # interruption writes the last one made (record_interruption cannot make one:
                # not collective)
                self._last_summary = self.summary(converged=False)
                if self._summary_due():
                    with self._summary_budget.spent():
                        output.write_summary(self.outdir, self.mpi, self._last_summary)
            # the PETSc objects the step dropped, destroyed (petsc_lib.release_garbage)
            petsc_lib.release_garbage(self.comm)

        def on_fail(res, dlam):
            failed.append(res)
            if not self.quiet and self.rank == 0:
                if res.reason == "stability":
                    why = "it lands on a less stable equilibrium"
                elif res.reason == "stagnation":
                    why = (f"Newton stagnated: |F| not halved in {self.solver.stagnation_its} its, "
                           f"{res.its} its")
                elif self.path == "minimize":
                    why = f"{res.reason}, {res.its} its, |g| {res.fnorm:.3e}"
                elif getattr(res, "linear_failure", None):
                    why = f"the linear solve failed, {res.linear_failure}; {res.its} Newton its"
                elif isinstance(res.reason, int):
                    why = f"SNES {linear.reason_name('SNES', res.reason)}, {res.its} its"
                else:
                    why = f"{res.reason}, {res.its} its"
                print(f"  load {res.lam:.6f} not accepted ({why}): cutting the increment "
                      f"{dlam:.3e} in half", flush=True)
            petsc_lib.release_garbage(self.comm)

        results, ok = self.solver.run(self.lam0, ld.steps, ld.max_cutbacks, ld.min_step, on_step, on_fail,
                                       nneg0=self.nneg0, dlam0=self.dlam0, prev0=self.prev0,
                                       arc0=self.arc0, stop=ld.stop)
        reason = None if ok else self.solver.fail_reason or self._newton_failed(
            ld.max_cutbacks, failed)
        if ok and self.path == "newton" and self.conservative and self._last_count() is None:
            # the Newton path counts every step only with -stability; its end is counted
            # anyway (one LDL^T), so that a zero of the residual that is unstable says so
            # (michell -load_path newton: "converged" on the circle past its threshold), and
            # one that is stable says that.  A failed count (-1) claims nothing.
            with profiling.stage(profiling.PATH_END):
                n = self.solver.negative_eigenvalues()
            if n >= 0:
                self.history[-1]["negative_eigenvalues"] = n
                self.writer.add_step_attrs(self.step, {"negative_eigenvalues": n})
        nneg = self._last_count()
        unstable = bool(nneg) and self.conservative
        self._warn_failed_newton_steps()
        self._warn_broken_promise()
        band = self.problem.stats.get("neutral_band", 0.0)
        if band > stability.FALL * stability.WARN_OVERLOAD and self.conservative and \
                self.rank == 0:
            # a band that hides more overload than that: a warning, with its size (the
            # perfect column with EA L^2/EI = 1e12 on 16 elements, band 16.8, was certified
            # straight at twice its buckling load)
            tell("warning", f"the stability count{self._on_mesh()} took eigenvalues of H v = "
                 f"lambda M v above -{band:.3g} EI/L^4 as neutral (the round-off of the Hessian of "
                 f"{self.mesh.nelem} elements, ~ EA / h^2): a state up to about "
                 f"{100 * band / stability.FALL:.3g} % past a critical load may count as "
                 f"stable; fewer elements (-rod_nelem) or a softer -rod_EA and -rod_GA "
                 f"(nearly inextensible is enough) sharpen it")
        elif band > stability.COARSE * stability.NEUTRAL:
            self._say(f"note: the stability count took eigenvalues of H v = lambda M v above "
                      f"-{band:.3g} EI/L^4 as neutral ({band / stability.NEUTRAL:.3g} x the "
                      f"default band, set by the round-off of the Hessian of {self.mesh.nelem} "
                      f"elements, ~ EA / h^2): a state that close to a critical one may count as stable; "
                      f"fewer elements (-rod_nelem) sharpen it")
        if ok and unstable and not self.unstable_asked():
            ok, reason = False, (f"the load path ends at load {self.problem.lam:.6f} on an "
                                 f"UNSTABLE equilibrium ({nneg} negative eigenvalues of the energy "
                                 f"Hessian): -load_path minimize ends on stable ones; "
                                 f"-load_arclength traces unstable branches on purpose")
        with interrupts.deferred():
            output.write_summary(self.outdir, self.mpi,
                                 self.summary(converged=ok, failed_reason=reason))
            self.writer.close()
        if self.rank == 0 and self.quiet and not ok:
            # -quiet leaves out the progress, not a failure (exit 3 said nothing)
            tell("failed", f"{reason}; results in {self.outdir}")
        if self.rank == 0 and not self.quiet:
            if not ok:
                last = "FAILED: " + reason
            elif unstable:
                last = (f"converged to an unstable equilibrium at load {self.problem.lam:.6f} "
                        f"({nneg} negative eigenvalues of the energy Hessian)")
            else:
                last = "converged"
            print(last + estimate.progress_text(self.last_estimate, self.penetration_length())
                  + f"; results in {self.outdir}", flush=True)
        return ok

    def _last_penetration(self):
        """The last state's max_penetration (of the contact diameter, from its report: observe),
        None without contact or before any report."""
        if self.contact is None:
            return None
        return (getattr(self, "last_reports", None) or {}).get("contact", {}).get(
            "max_penetration")

    def penetration_length(self):
        """The last state's deepest contact penetration in length units (max_penetration x the
        contact diameter), None without contact: the penalty's error, which the error
        estimate (the discretisation's, at the run's penalty) does not count."""
        pen = self._last_penetration()
        return None if pen is None else pen * 2.0 * self.contact.radius

    def _on_mesh(self):
        """' on the -rod_tolerance mesh of N elements of order p' for a warning of one of the
        runs -rod_tolerance makes (each mesh warns for itself), else ''."""
        if not self.tolerance_trial:
            return ""
        return (f" on the -rod_tolerance mesh of {self.mesh.nelem} elements of order "
                f"{self.mesh.order}")

    def _newton_failed(self, cutbacks, failed):
        """Why the Newton path stopped after every cut-back failed (``failed``: the results of
        the failed tries): the linear solve of its steps where the last (shortest) try failed
        there - a linear solver option that cannot solve the tangent (-ksp_type gmres
        -pc_type none: SNES reason -3 at every cut-back, and the run said only "Newton
        failed")."""
        where = f"load path stopped at load {self.problem.lam:.6f}"
        tail = "; the last converged step is in result.h5"
        failure = getattr(failed[-1], "linear_failure", None) if failed else None
        if failure:
            every = all(getattr(r, "linear_failure", None) for r in failed)
            from petsc4py import PETSc
            given = [n for n in sorted(PETSc.Options().getAll())
                     if n.startswith(("ksp_", "pc_", "planar_ksp_", "planar_pc_", "mat_mumps_",
                                      "planar_mat_mumps_")) and linear.user_chose(n)]
            # the in-plane step's copies of the Newton step's options (planar.CARRIED) are not
            # the user's, nor do options nothing read (misspelt: warned as unused) take part
            unread = {name for name, _ in (petsc_lib.options_left() or ())}
            given = [n for n in given if not (n.startswith("planar_") and n[7:] in given)
                     and n not in unread]
            why = (f"the linear solver options given ({', '.join('-' + n for n in given)}) "
                   f"cannot solve this tangent; without them rodsnes solves it by a direct LU"
                   if given else "the tangent is singular there, or its factorisation failed")
            return (f"{where}: the Newton step's linear solve failed "
                    f"{'at every try' if every else 'at the shortest step tried'} "
                    f"({failure}): {why}{tail}")
        return f"{where}: Newton failed after {cutbacks} cut-backs{tail}"

    def _warn_failed_newton_steps(self):
        """The minimiser goes on with the Hessian's step where a Newton step's linear solve
        fails (a singular tangent at an iterate), without a word; where most of them failed -
        a linear solver option that cannot solve (-mat_mumps_icntl_23 too small, an
        -interior_ or -planar_ option) - the run converged the slow way, and says so."""
        m = getattr(self.solver, "minimizer", None)
        if m is None or self.rank != 0:
            return
        tries, failed = m.newton_tries, m.newton_failures
        if failed >= NEWTON_FAILURES and 2 * failed >= tries:
            tell("warning", f"the Newton step's linear solve failed in {failed} of {tries} "
                 f"iterations{self._on_mesh()} ({m.newton_failure}): the minimiser went on "
                 f"with its Hessian steps, which converge slower; a linear solver option (-pc_*, -ksp_*, "
                 f"-mat_mumps_*, -planar_*, -interior_*) may be the cause")

    def _warn_broken_promise(self):
        """A last state deeper in contact than -contact_penetration promises: a penalty kept as
        given (-contact_penalty without -contact_penalty_adapt: the plectoneme with
        -contact_penalty 2e4 -contact_wall 0 ended 15.8 % deep, exit 0, summary.json saying
        1 % promised), or raises that did not bring it back, says so."""
        c, pen = self.contact, self._last_penetration()
        if pen is None or self.rank != 0 or not pen > c.penetration * (1.0 + 1e-6):
            return
        why = (f"-contact_penalty {c.mu:g} was kept as given (-contact_penalty_adapt raises it "
               f"where a step goes deeper; or leave -contact_penalty out)" if not c.adapt else
               f"the penalty's raises (now {c.mu:.4g}) did not bring it back; a larger "
               f"-contact_penalty, or more load steps")
        tell("warning", f"the last state{self._on_mesh()} presses {pen:.3%} of the contact "
             f"diameter deep, beyond -contact_penetration {c.penetration:g}: {why}")

    def _last_count(self):
        """The last step's count of negative eigenvalues, None where it has none or the count
        failed (Inertia.factor's -1: a factorisation MUMPS could not make)."""
        n = self.history[-1].get("negative_eigenvalues") if self.history else None
        return None if n is None or n < 0 else n

    def unstable_asked(self):
        """Whether this run may end on an unstable equilibrium: it follows unstable branches
        (-load_arclength), or the user chose -load_path newton, a zero of the residual."""
        return self.arclength or self.scene.loads.path == "newton"

    # ------------------------------------------------------------------------------
    def _restart_step(self, rdir):
        """The last complete step of rdir/result.h5, or a SceneError that says what is wrong
        with the directory (no result.h5, unreadable or cut short, no complete step)."""
        path = os.path.join(rdir, output.RESULT_FILE)
        if not os.path.isdir(rdir):
            raise SceneError(f"-restart {rdir}: not a directory (give the output directory of an "
                             f"earlier run)", ("-restart",))
        if not os.path.exists(path):
            raise SceneError(f"-restart {rdir}: holds no {output.RESULT_FILE}, so no run to go on "
                             f"from (give the output directory of an earlier run, or drop "
                             f"-restart)", ("-restart",))
        try:
            return output.read_step(rdir, -1)
        except (OSError, ValueError, KeyError, RuntimeError) as exc:
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise SceneError(f"-restart {rdir}: {path} cannot be read ({why}): it was cut short "
                             f"or damaged; restart from another run or a checkpoint, or drop "
                             f"-restart", ("-restart",)) from None

    def _check_restart_scene(self, rdir, meta):
        """Refuse a restart from a run of another scene: the mesh and rod stored with every file
        (closed, length, radius, nelem, order), and, where the file holds it (runs started by
        the rodsnes command), the whole scene record (scene.scene_record: stiffness, shape,
        supports, loads); a file without it must at least be of the same case."""
        import json
        mine = scene_record(self.scene)
        stored = {k: meta[k] for k in ("closed", "length", "radius", "nelem", "order")
                  if k in meta}
        record = meta.get("scene")
        if isinstance(record, str):
            try:
                stored.update(json.loads(record))
            except ValueError:
                record = None
        diff = record_mismatches(stored, mine)
        case, theirs = self.scene.output.case_name, meta.get("case_name")
        if not diff and not isinstance(record, str) and theirs is not None and theirs != case:
            diff = [f"case {theirs} there, {case} here (-case_name, -options_file)"]
        if diff:
            raise SceneError(f"-restart {rdir}: it holds a run of another scene: "
                             f"{'; '.join(diff)}; restart from a run of this scene (same rod, "
                             f"mesh, supports and loads), or drop -restart to start afresh",
                             ("-restart",))

    def record_scene(self):
        """Store the scene record (scene.scene_record) in result.h5 for later restarts to
        compare against (collective)."""
        self.writer.add_meta({"scene": scene_record(self.scene)})

    def _summary_due(self):
        """Whether summary.json is rewritten after this step: while the rewrites so far took at
        most SUMMARY_SHARE of the run's wall time (rank 0's clock decides for every rank: the
        write is collective).  Collective."""
        return bool(self.mpi.bcast(self._summary_budget.due(SUMMARY_SHARE), root=0))

    def _live(self):
        """The Run whose steps are being written: a -rod_tolerance trial, or this one."""
        return self.live_trial if self.live_trial is not None else self

    def _last_step_summary(self):
        """The summary made after the last step (written or not), its step list cut to that
        step (the list is the live history) and the wall time now; None before the first."""
        last = self._last_summary
        if last is None:
            return None
        return dict(last, steps=list(last["steps"][:last["load_steps"]]),
                    wall_time_s=time.perf_counter() - self.t_start)

    def record_error(self, message, by_this_rank=False):
        """summary.json after an error that ended the run (rank 0, or ``by_this_rank``: the
        rank that stopped alone; not collective): the summary made after the last step, marked
        failed with ``message`` (nothing before the first step).  Never raises: the error
        itself is what the user must see."""
        live = self._live()
        if live is not self:
            return live.record_error(message, by_this_rank)
        last = self._last_step_summary()
        if (self.rank != 0 and not by_this_rank) or last is None:
            return
        try:
            output.write_summary(self.outdir, None, dict(
                last, converged=False,
                failure=f"stopped by an error: {message}; the converged steps stay in result.h5"))
        except Exception:  # noqa: BLE001 - the run's own error is reported by the caller
            pass

    def record_interruption(self, signal_name):
        """summary.json after a SIGINT/SIGTERM: the last step's summary marked interrupted
        (output.mark_interrupted; not collective, so any rank may call it); of the trial
        running now with -rod_tolerance.  Returns it."""
        live = self._live()
        if live is not self:
            return live.record_interruption(signal_name)
        base = {"case": self.scene.output.case_name, "load": self.lam0,
                "load_steps": len(self.history), "dofs": NDOF * self.mesh.n_nodes,
                "ranks": self.comm.getSize(), "steps": self.history}
        extra = self._last_step_summary() or {"wall_time_s": time.perf_counter() - self.t_start}
        return output.mark_interrupted(self.outdir, signal_name, base=base, extra=extra)
