"""Read and validate every rodsnes option from the PETSc options database.

A scene is a PETSc options file (``cases/*.opts``); every value can be
overridden on the command line (the last occurrence wins, as usual in PETSc).
All rodsnes options live in ONE table, :class:`O`: its attribute names are the
option names (without the leading dash), and reading, :func:`help_text` and
:func:`check_unknown_options` are all derived from it.

Conventions used by the derived quantities (circular cross-section of radius r,
director d3 = tangent, d1/d2 the section axes):

    A  = pi r^2            cross-section area
    I  = pi r^4 / 4        second moment of area about d1 and about d2
    J  = pi r^4 / 2        polar moment (torsion constant of a circle)
    G  = E / (2 (1 + nu))  shear modulus from Young's modulus and Poisson's ratio
    nu = E / (2 G) - 1     Poisson's ratio when G is given instead
    k  = 6 (1 + nu) / (7 + 6 nu)   Timoshenko's shear coefficient of a circle
    EA = E A,  GA1 = GA2 = k G A,  EI1 = EI2 = E I,  GJ = G J

Any stiffness given directly (``-rod_EA``, ``-rod_GA``, ``-rod_EI`` or
``-rod_EI1``/``-rod_EI2``, ``-rod_GJ``) replaces the derived value of that
stiffness only.

Every problem is reported as a :class:`SceneError` whose message names the
option(s) involved and the accepted range or the fix.  Checks are collected,
so one run reports all independent mistakes at once (one per line).
"""
import difflib
import math
import os
import sys
from dataclasses import dataclass, field
from types import SimpleNamespace
from pathlib import PurePath
from typing import Optional, Tuple

import numpy as np

from rodsnes.errors import SceneError
from rodsnes.model.scales import force_scale, force_scale_terms, residual_floor

__all__ = ["SceneError", "Rod", "BC", "Loads", "Contact", "Output", "Scene",
           "O", "OPTIONS", "read_scene", "help_text", "check_unknown_options"]


# ----------------------------------------------------------------------------
# The option table
# ----------------------------------------------------------------------------
REAL, INT, BOOL, STR, CHOICE, VEC3 = "real", "int", "bool", "string", "choice", "vec3"

SECTIONS = {
    "rod": "Rod: length, cross-section and material",
    "shape": "Rod: reference shape",
    "disc": "Discretisation",
    "bc": "Boundary conditions",
    "load": "Loads and load stepping",
    "contact": "Self-contact",
    "output": "Output and restart",
    "analysis": "Analysis",
}


class _Range:
    """An interval written like "(0,inf)", "[0,inf)", "(-1,0.5]", "[1,4]"."""

    def __init__(self, text):
        t = text.replace(" ", "")
        self.text = text
        self.lo_closed, self.hi_closed = t[0] == "[", t[-1] == "]"
        lo, hi = t[1:-1].split(",")
        self.lo, self.hi = float(lo), float(hi)

    def __contains__(self, x):
        above = x >= self.lo if self.lo_closed else x > self.lo
        below = x <= self.hi if self.hi_closed else x < self.hi
        return above and below

    def describe(self, integer=False):
        lo_inf, hi_inf = math.isinf(self.lo), math.isinf(self.hi)
        if hi_inf and not lo_inf:
            return "must be %s %s" % (">=" if self.lo_closed else ">", _fmt(self.lo))
        if lo_inf and not hi_inf:
            return "must be %s %s" % ("<=" if self.hi_closed else "<", _fmt(self.hi))
        if integer and self.lo_closed and self.hi_closed:
            return "must be in %d..%d" % (self.lo, self.hi)
        return "must be in %s%s, %s%s" % ("[" if self.lo_closed else "(", _fmt(self.lo),
                                          _fmt(self.hi), "]" if self.hi_closed else ")")


class Opt:
    """One rodsnes option: type, default, help, section, accepted range.

    The name is the attribute name in :class:`O` (set by ``__set_name__``), so
    it is written exactly once.  ``shown`` is the default as printed by
    :func:`help_text` when it is derived rather than a constant; ``note`` is the
    explanation appended to range errors; ``metavar`` is the value form
    (e.g. "fx,fy,fz").
    """

    def __init__(self, kind, default, help, section, rng=None, choices=(),
                 shown=None, note=None, metavar=None):
        self.kind, self.default, self.help, self.section = kind, default, help, section
        self.rng = _Range(rng) if rng else None
        self.choices = tuple(choices)
        self.shown, self.note, self.metavar = shown, note, metavar
        self.name = None

    def __set_name__(self, owner, name):
        self.name = name

    @property
    def flag(self):
        """The option as typed: ``-`` + name."""
        return "-" + self.name

    def __repr__(self):
        return "Opt(%s)" % self.flag

    def example(self):
        """An example of a valid value (for error messages)."""
        if self.kind == VEC3:
            return "0,0,1"
        if self.kind == CHOICE:
            return self.choices[0]
        if self.kind == BOOL:
            return "true"
        if self.kind in (REAL, INT) and self.default is not None:
            return _fmt(self.default) if self.kind == REAL else str(self.default)
        return {REAL: "1.5", INT: "4", STR: "NAME"}[self.kind]

    def shown_default(self):
        if self.shown is not None:
            return self.shown
        d = self.default
        if self.kind == BOOL:
            return "true" if d else "false"
        if self.kind == REAL:
            return _fmt_petsc(d)
        if self.kind == VEC3:
            return ",".join(_fmt_petsc(x) for x in d)
        return str(d)


MIN_LOAD_STEP = 1e-12
"""The smallest load increment (-load_min_step's least value, a restart's stored increment at
least): below it a load factor near 1 does not change in double precision."""


class O:
    """THE rodsnes option table (attribute name = option name, no dash)."""
    # --- rod: length, cross-section, material -------------------------------
    rod_length = Opt(REAL, 1.0, "rod length L (arclength of the centreline)", "rod",
                     rng="(0,inf)", note="the rod's length, in length units")
    rod_radius = Opt(REAL, 0.01, "cross-section radius r (circular section)", "rod",
                     rng="(0,inf)", note="the rod's cross-section radius, in length units")
    rod_youngs = Opt(REAL, 1e6, "Young's modulus E", "rod", rng="(0,inf)",
                     note="Young's modulus, force per area")
    rod_shear = Opt(REAL, None, "shear modulus G (give this or -rod_poisson, not both)", "rod",
                    rng="(0,inf)", shown="E/(2(1+nu))", note="shear modulus, force per area")
    rod_poisson = Opt(REAL, 0.5, "Poisson's ratio nu: G = E/(2(1+nu))", "rod",
                      rng="(-1,0.5]", note="Poisson's ratio of an isotropic material")
    rod_shear_coefficient = Opt(REAL, None, "Timoshenko shear coefficient k: GA = k G A", "rod",
                                rng="(0,inf)", shown="6(1+nu)/(7+6nu)",
                                note="shear correction factor, about 0.9 for a circle")
    rod_EA = Opt(REAL, None, "axial stiffness EA (replaces E pi r^2)", "rod",
                 rng="(0,inf)", shown="E A", note="a stiffness")
    rod_GA = Opt(REAL, None, "shear stiffness GA, both directions (replaces k G pi r^2)", "rod",
                 rng="(0,inf)", shown="k G A", note="a stiffness")
    rod_EI = Opt(REAL, None, "bending stiffness EI about d1 and d2 (replaces E pi r^4/4)", "rod",
                 rng="(0,inf)", shown="E I", note="a stiffness")
    rod_EI1 = Opt(REAL, None, "bending stiffness about d1 (not with -rod_EI)", "rod",
                  rng="(0,inf)", shown="E I", note="a stiffness")
    rod_EI2 = Opt(REAL, None, "bending stiffness about d2 (not with -rod_EI)", "rod",
                  rng="(0,inf)", shown="E I", note="a stiffness")
    rod_GJ = Opt(REAL, None, "torsional stiffness GJ (replaces G pi r^4/2)", "rod",
                 rng="(0,inf)", shown="G J", note="a stiffness")
    rod_kappa0 = Opt(VEC3, None, "intrinsic curvature and twist u_hat "
                     "(default: the strains of the reference shape, i.e. stress-free)", "rod",
                     shown="reference shape", metavar="k1,k2,k3")
    # --- reference shape --------------------------------------------------------
    rod_shape = Opt(CHOICE, "straight", "reference centreline", "shape",
                    choices=("straight", "arc", "circle", "helix"))
    rod_arc_radius = Opt(REAL, None, "radius R of an arc (give R or -rod_arc_angle) or circle "
                         "(default L/(2 pi))", "shape", rng="(0,inf)", shown="none",
                         note="radius of the reference arc")
    rod_arc_angle = Opt(REAL, None, "opening angle of an arc in degrees, L = R angle", "shape",
                        rng="(0,360]", shown="none",
                        note="an open arc spans at most 360 degrees; "
                             "for a closed ring use -rod_shape circle")
    rod_helix_radius = Opt(REAL, None, "helix radius (distance of the centreline from the axis)",
                           "shape", rng="(0,inf)", shown="none", note="radius of the helix")
    rod_helix_pitch = Opt(REAL, None, "helix pitch, rise per turn (negative: left-handed); "
                          "the helix has arclength L", "shape", shown="none")
    rod_closed = Opt(BOOL, False, "closed ring (needs -rod_shape circle, which implies it)",
                     "shape", shown="false (true for circle)")
    rod_closed_gauge = Opt(BOOL, True, "closed ring of uniform stress-free strains: hold one "
                           "coordinate of the node opposite node 0 (removes the ring sliding along "
                           "itself, a symmetry; its reaction is reported)", "shape")
    rod_twist_turns = Opt(REAL, 0.0, "initial twist of the director frame about the tangent, "
                          "in turns, uniform along s (whole turns on a closed rod)", "shape")
    rod_imperfection = Opt(REAL, 0.0, "imperfection a: reference centreline displaced by "
                           "the first buckling mode of the supports, amplitude a along d1 "
                           "(cantilever a(1-cos(pi s/2L)); clamped-clamped and clamped-sliding "
                           "a(1-cos(2 pi s/L))/2; else a sin(pi s/L); closed rods: "
                           "a sin(4 pi s/L) along d2, the writhing mode), length units", "shape")
    # --- discretisation ---------------------------------------------------------
    rod_nelem = Opt(INT, 16, "number of finite elements", "disc", rng="[1,inf)",
                    note="number of elements along the rod")
    rod_order = Opt(INT, 3, "polynomial degree p of the Lagrange elements", "disc",
                    rng="[1,4]", note="element polynomial degree")
    rod_quadrature = Opt(CHOICE, "reduced", "Gauss rule: full (p+1 points) or reduced (p points)",
                         "disc", choices=("full", "reduced"))
    rod_kernel = Opt(CHOICE, "auto", "elastic element kernel: compiled (fused C, built by the "
                     "install), numpy (batched arrays), reference (einsum transcription, slow), "
                     "auto (compiled if built, else numpy); all agree to 1e-12", "disc",
                     choices=("auto", "compiled", "numpy", "reference"))
    rod_error_estimate = Opt(CHOICE, "last", "estimate the discretisation error (tip and "
                             "centreline, length units; summary.json error_estimate, result.h5 "
                             "per step): the solution of order p+1 on the same elements, a Newton "
                             "solve from this one, against it; at the last step (last), at every "
                             "converged step (every, ~10-20 % more time) or not at all (off)",
                             "disc", choices=("last", "every", "off"))
    rod_tolerance = Opt(REAL, None, "choose the mesh: from a coarse one, refine (and pick the "
                        "order unless -rod_order is given) until the estimated centreline error "
                        "is below this, at the least predicted cost", "disc", rng="(0,inf)",
                        shown="none", note="an error in length units, e.g. 1e-6")
    rod_planar = Opt(CHOICE, "auto", "a scene whose shape, directors, supports and loads lie in "
                     "one coordinate plane is solved on its in-plane unknowns (x, y, theta per "
                     "node: half the unknowns; each step's out-of-plane stability checked by the "
                     "minimiser, on -load_path newton with -stability): auto "
                     "(when the scene is planar), on (refused for a scene that is not), off (3-D)",
                     "disc", choices=("auto", "on", "off"))
    # --- boundary conditions ----------------------------------------------------
    bc_start = Opt(CHOICE, "clamped", "support of the end s = 0", "bc",
                   choices=("clamped", "pinned", "free"), shown="clamped (free on a closed rod)")
    bc_end = Opt(CHOICE, "free", "support of the end s = L", "bc",
                 choices=("clamped", "pinned", "free", "sliding"))
    bc_end_turns = Opt(REAL, 0.0, "turns imposed on the end s = L about its tangent "
                       "(end clamped or sliding)", "bc")
    # --- loads ------------------------------------------------------------------
    load_end_force = Opt(VEC3, (0.0, 0.0, 0.0), "force at the end s = L", "load",
                         metavar="fx,fy,fz")
    load_end_force_follower = Opt(BOOL, False, "the end force turns with the end cross-section "
                                  "(follower load)", "load")
    load_end_moment = Opt(VEC3, (0.0, 0.0, 0.0), "moment at the end s = L", "load",
                          metavar="mx,my,mz")
    load_gravity = Opt(VEC3, (0.0, 0.0, 0.0), "distributed load, force per unit length", "load",
                       metavar="gx,gy,gz")
    load_twist_turns = Opt(REAL, 0.0, "excess link put in by lowering the natural twist: "
                           "u_hat_3 -= lambda 2 pi T / L (turns over the whole rod; rings too)",
                           "load")
    load_steps = Opt(INT, 1, "number of load increments (load factor 0 -> 1)", "load",
                     rng="[1,inf)", note="number of load steps")
    load_path = Opt(CHOICE, "auto", "how each load step is solved: minimize (Newton on the total "
                    "energy with an inertia-controlled shift: every step ends on a stable "
                    "equilibrium), newton (a zero of the residual, with cut-back; the only choice "
                    "for follower loads and 3-D end moments); auto: minimize where the loads are "
                    "conservative", "load", choices=("auto", "minimize", "newton"))
    load_max_it = Opt(INT, 200, "-load_path minimize: Newton iterations after which a load step "
                      "that has stopped lowering the energy fails (and is cut back); one still "
                      "descending (a jump past a fold) goes on, up to 10 times as many",
                      "load", rng="[1,inf)", note="a number of Newton iterations")
    load_predictor = Opt(BOOL, True, "-load_path newton: start each load step from the secant "
                         "predictor through the last two converged states", "load")
    load_retraction = Opt(BOOL, True, "-load_path newton: take each Newton step along the "
                          "rod's retraction, its positions following the turn of its frames, "
                          "so that a step that turns a stiff rod does not stretch it (without "
                          "contact, with -snes_linesearch_type basic, the default; off: "
                          "straight steps)", "load")
    load_max_cutbacks = Opt(INT, 10, "times a failed increment may be halved", "load",
                            rng="[0,inf)", note="number of step halvings")
    load_stagnation_its = Opt(INT, 15, "-load_path newton: a Newton solve whose residual has not "
                              "halved in this many iterations fails (and the step is cut back); "
                              "0: only -snes_max_it",
                              "load", rng="[0,inf)", note="a number of Newton iterations")
    load_arclength = Opt(BOOL, False, "at a fold of the load path (every cut-back failed), follow "
                         "the branch around it by pseudo-arclength continuation, through its "
                         "unstable part, until it goes on stable with the load increasing "
                         "(else the run ends at the fold); the Newton path (-load_path auto or "
                         "newton)", "load")
    load_arclength_max_steps = Opt(INT, 200, "pseudo-arclength continuation: most steps around "
                                   "one fold", "load", rng="[1,inf)", note="a number of steps")
    load_arclength_its = Opt(INT, 8, "pseudo-arclength continuation: Newton iterations per step "
                             "aimed at (fewer: a longer next step, more: a shorter one)", "load",
                             rng="[2,inf)", note="a number of Newton iterations")
    load_min_step = Opt(REAL, 1e-6, "smallest load-factor increment after cutbacks", "load",
                        rng="[%g,1]" % MIN_LOAD_STEP, note="a fraction of the full load, from "
                        "%g (below it a load factor near 1 does not change in double precision)"
                        % MIN_LOAD_STEP)
    load_stop = Opt(REAL, 1.0, "end the run at this load factor (a long batch run in stages, "
                    "each resumed with -restart, perhaps with other settings); the load grid "
                    "of -load_steps is that of 0 -> 1", "load", rng="(0,1]",
                    note="a fraction of the full load")
    # --- contact ----------------------------------------------------------------
    contact = Opt(BOOL, False, "enable frictionless self-contact", "contact")
    contact_penalty = Opt(REAL, None, "penalty stiffness", "contact", rng="(0,inf)",
                          shown="automatic", note="contact penalty stiffness")
    contact_penetration = Opt(REAL, 0.01, "largest penetration the penalty promises, as a fraction "
                              "of the contact diameter 2 radius: sets the default penalty and the bound "
                              "-contact_penalty_adapt keeps", "contact", rng="(0,0.5]",
                              note="a fraction of the contact diameter, e.g. 0.01 for 1 %")
    contact_standoff = Opt(REAL, 0.0, "how far apart strands that touch lightly may stand, as a "
                           "fraction of the contact diameter: the contact law acts from "
                           "2 radius (1 + standoff) and keeps every penetration of the tube of "
                           "-contact_radius within -contact_penetration; a positive standoff "
                           "makes the law softer (fewer Newton iterations), 0 is the penalty at "
                           "the tube (at most 0.1: the exclusion pi radius (1 + standoff) "
                           "hides no more than (pi standoff / 4)^2 of the diameter in a "
                           "tight bend)", "contact", rng="[0,0.1]",
                           note="a fraction of the contact diameter, e.g. 0.02 for 2 %")
    contact_penalty_adapt = Opt(BOOL, True, "after a converged load step whose penetration exceeds "
                                "-contact_penetration, raise the penalty and solve the step again "
                                "(with -contact_wall: after one whose contact presses into the "
                                "wall, raise it for the next step)",
                                "contact", shown="true unless -contact_penalty is given")
    contact_wall = Opt(BOOL, True, "the pair potential (-contact_model potential) keeps "
                       "-contact_penetration as a wall: a barrier over its last half whose "
                       "energy is infinite at the promised penetration, so that no step goes "
                       "deeper and none is solved twice (-contact_penalty_adapt raises the "
                       "penalty between steps instead; false: the penalty alone)",
                       "contact")
    contact_radius = Opt(REAL, None, "contact radius (distance of closest approach / 2)",
                         "contact", rng="(0,inf)", shown="rod radius",
                         note="radius of the contact tube, in length units")
    contact_exclusion = Opt(REAL, None, "arclength below which point pairs are never in contact",
                            "contact", rng="[0,inf)", shown="automatic",
                            note="an arclength, in length units")
    contact_curvature = Opt(BOOL, True, "the contact tube also bounds bending: flexure above "
                            "1/radius is penalised (stiffness EI / -contact_penetration), so the "
                            "exclusion pi*radius hides no penetration", "contact")
    contact_model = Opt(CHOICE, "auto", "contact law: projection (the gap to the closest "
                        "point, penalty (mu/2) int <d>^2 ds), potential (a pair potential "
                        "(k/2) int int <2 eps - |r(s) - r(sigma)|>^2 between centreline points, "
                        "smooth where closest points are not unique: tight plies) or auto (the "
                        "potential where the mesh resolves it, else projection; the run says "
                        "which)", "contact", choices=("auto", "projection", "potential"))
    contact_zones = Opt(BOOL, True, "integrate the penalty over the contact zones (d > 0, found by "
                        "root finding) instead of at fixed Gauss points (-contact_model "
                        "projection)", "contact")
    contact_supports = Opt(BOOL, True, "with -bc_start clamped -bc_end sliding, the clamps' mounts "
                           "are obstacles: the axis behind the start and beyond the end, along "
                           "which the link is counted (a rod going round a clamp would change it)",
                           "contact")
    contact_quadrature = Opt(INT, None, "points per element for the contact integral (with "
                             "-contact_model potential: of both integrals, automatic = 12 on "
                             "the stretch a contact touches)", "contact",
                             rng="[1,inf)", shown="order+2",
                             note="quadrature points per element")
    # --- output -----------------------------------------------------------------
    output_dir = Opt(STR, None, "output directory", "output", shown="out/<case name>",
                     metavar="DIR")
    quiet = Opt(BOOL, False, "no progress output (a failure is still said, on stderr)", "output")
    restart = Opt(STR, None, "restart from the state saved in DIR", "output", shown="none",
                  metavar="DIR")
    case_name = Opt(STR, None, "case name (default: basename of the last -options_file under a "
                    "cases/ directory, else of the last -options_file, else 'default')",
                    "output", shown="from -options_file", metavar="NAME")
    # --- analysis ---------------------------------------------------------------
    stability = Opt(BOOL, False, "-load_path newton: count the negative eigenvalues of the "
                    "energy Hessian at each converged step (a step that lands on a less stable "
                    "equilibrium than it left is cut back); the minimiser counts them always",
                    "analysis")


_MINIMISER = "conservative load steps are energy minimisations (-load_path minimize, the default)"
RETIRED = {
    "stability_switch": "branch switching: " + _MINIMISER + ", which end on stable equilibria; "
                        "use -load_arclength to follow unstable branches",
    "stability_switch_restart": "branch switching: " + _MINIMISER + ", which end on stable "
                                "equilibria, from a restart state too; use -load_arclength to "
                                "follow unstable branches",
    "stability_perturbation": "branch switching: " + _MINIMISER + ", which leave an unstable "
                              "equilibrium along negative curvature by themselves",
    "stability_relax_max_it": "the relaxation of branch switching: " + _MINIMISER + "; their "
                              "iterations are -load_max_it",
    "stability_jump_overshoot": "the fold jump: " + _MINIMISER + ", which go past a fold by "
                                "descent; use -load_arclength to follow the branch around it",
    "load_damped_its": "the Levenberg-Marquardt fallback: " + _MINIMISER + ", with a line "
                       "search; on -load_path newton a failed step is cut back "
                       "(-load_max_cutbacks, -load_min_step)",
}
"""Options rodsnes once had, each with what replaced it: given, they are refused by name."""


OPTIONS = tuple(v for v in vars(O).values() if isinstance(v, Opt))
"""All rodsnes options in table order."""

RODSNES_PREFIXES = ("rod_", "bc_", "load_", "contact", "output_", "restart", "quiet",
                    "case_", "stability")
"""An option starting with one of these must be in :data:`OPTIONS`."""

PETSC_PREFIXES = (
    "snes_", "ksp_", "pc_", "mat_", "vec_", "log_", "options_", "info", "malloc", "help",
    "version", "on_error", "sf_", "dm_", "petscpartitioner_", "viewer_", "draw_", "mpi_",
    "fp_trap", "no_signal_handler", "start_in_debugger", "debugger", "check_", "objects_",
    "memory_", "saws", "python", "use_gpu", "device", "citations", "skip_petscrc", "history",
    "viewer", "tao_", "ts_", "is_", "ao_", "pf_", "random_", "matload_", "matmatmult_",
    "matptap_", "bv_", "eps_", "st_", "svd_", "nep_", "pep_", "mfn_", "ds_", "fn_", "rg_",
    "sub_", "fieldsplit_", "mg_", "redundant_")
"""Options with these prefixes belong to PETSc/SLEPc and are left to PETSc."""

SOLVER_PREFIXES = ("planar_stability_", "stability_", "estimate_", "planar_", "interior_")
"""Options prefixes of rodsnes' own PETSc solvers (stability_: the inertia count's LDL^T,
estimate_: the error estimate's SNES, planar_: the planar run's in-plane solves,
planar_stability_: its LDL^T, interior_: on several ranks the MUMPS LU of each rank's stretch,
solve/schur.py): -stability_mat_mumps_icntl_7 5 is PETSc's option -mat_mumps_icntl_7 of that
solver."""


def is_petsc_option(name):
    """Whether option ``name`` (lower case, no dash) is left to PETSc: a PETSc prefix, alone or
    after one of rodsnes' solver prefixes, and no rodsnes prefix otherwise."""
    for pre in SOLVER_PREFIXES:
        if name.startswith(pre):
            return name[len(pre):].startswith(PETSC_PREFIXES)
    return not name.startswith(RODSNES_PREFIXES) and name.startswith(PETSC_PREFIXES)


# ----------------------------------------------------------------------------
# Scene dataclasses
# ----------------------------------------------------------------------------
@dataclass(eq=False)  # holds numpy arrays: compare fields, not objects
class Rod:
    """Rod geometry, stiffness and discretisation.

    Stiffnesses (see the module docstring): EA = E pi r^2, GA1 = GA2 = k G pi r^2,
    EI1 = EI2 = E pi r^4/4, GJ = G pi r^4/2, each replaced by its direct option
    if given.  ``youngs``/``shear_modulus``/``poisson``/``shear_coefficient`` are
    None when they entered no stiffness (all stiffnesses they would determine
    were given directly).  Shape fields that do not apply to ``shape`` are None:
    arc_radius/arc_angle_deg are set for 'arc' and 'circle' (L = R angle),
    helix_radius/helix_pitch for 'helix'.
    """
    length: float
    radius: float
    EA: float
    GA1: float
    GA2: float
    EI1: float
    EI2: float
    GJ: float
    kappa0: Optional[np.ndarray]
    shape: str
    arc_radius: Optional[float]
    arc_angle_deg: Optional[float]
    helix_radius: Optional[float]
    helix_pitch: Optional[float]
    closed: bool
    twist_turns: float
    imperfection: float
    nelem: int
    order: int
    quadrature: str
    youngs: Optional[float]
    shear_modulus: Optional[float]
    poisson: Optional[float]
    shear_coefficient: Optional[float]
    closed_gauge: bool = True
    kernel: str = "auto"
    error_estimate: str = "last"      # -rod_error_estimate last|every|off (solve/estimate.py)
    tolerance: Optional[float] = None  # -rod_tolerance: the mesh is chosen (solve/estimate.py)
    planar: str = "auto"              # -rod_planar auto|on|off (solve/planar.py)

    @property
    def area(self):
        """A = pi r^2."""
        return math.pi * self.radius ** 2

    @property
    def C_shear_stretch(self):
        """diag(GA1, GA2, EA): stiffness of the strains (v1, v2, v3) in the director frame."""
        return np.diag([self.GA1, self.GA2, self.EA])

    @property
    def C_bend_twist(self):
        """diag(EI1, EI2, GJ): stiffness of the curvatures (u1, u2, u3) in the director frame."""
        return np.diag([self.EI1, self.EI2, self.GJ])

    @property
    def arc_angle(self):
        """Arc opening angle in radians (L / arc_radius), None unless arc/circle."""
        return None if self.arc_angle_deg is None else math.radians(self.arc_angle_deg)

    @property
    def helix_turns(self):
        """Number of helix turns: L / sqrt((2 pi R)^2 + pitch^2); None unless helix."""
        if self.helix_radius is None:
            return None
        return self.length / math.hypot(2 * math.pi * self.helix_radius, self.helix_pitch)


@dataclass
class BC:
    """Supports of s = 0 (start) and s = L (end); end_turns: imposed end rotation in turns."""
    start: str
    end: str
    end_turns: float


@dataclass(eq=False)  # holds numpy arrays: compare fields, not objects
class Loads:
    """Loads at load factor 1, applied in ``steps`` equal increments of the load factor."""
    end_force: np.ndarray
    end_force_follower: bool
    end_moment: np.ndarray
    gravity: np.ndarray
    steps: int
    max_cutbacks: int
    min_step: float
    twist_turns: float = 0.0
    stop: float = 1.0
    path: str = "auto"
    max_it: int = 200
    rtol: float = 1e-10              # -snes_rtol: |g| <= rtol x the force scale
    atol: float = 0.0                # -snes_atol: |F| <= atol accepted too (Newton path)
    predictor: bool = True           # the Newton path's secant predictor
    retraction: bool = True          # the Newton path's steps along the retraction
    stagnation_its: int = 15
    arclength: bool = False          # pseudo-arclength continuation at folds
    arclength_max_steps: int = 200
    arclength_its: int = 8


def law_tube(radius, penetration, standoff):
    """(eps_l, p_l): the radius and the promised penetration of the contact law for a tube of
    ``radius`` whose penetrations are promised within ``penetration`` of its diameter, and whose
    strands may stand ``standoff`` of its diameter apart while they touch lightly.  The law acts
    from 2 eps_l = 2 radius (1 + standoff); its promised depth p_l 2 eps_l reaches
    penetration x 2 radius into the tube: p_l = (standoff + penetration) / (1 + standoff)
    (docs/contact.md, The standoff)."""
    s = float(standoff)
    return float(radius) * (1.0 + s), (s + float(penetration)) / (1.0 + s)


@dataclass
class Contact:
    """Self-contact settings; None means automatic (radius None = the rod radius)."""
    enabled: bool
    penalty: Optional[float]
    radius: Optional[float]
    exclusion: Optional[float]
    quadrature: int
    zones: bool = True
    penetration: float = 0.01       # promised largest penetration, fraction of 2 radius
    standoff: float = 0.0           # the law acts from 2 eps (1 + standoff) (law_tube)
    adapt: bool = True              # raise mu after a step that breaks the promise
    wall: bool = True               # the pair potential's promise as a wall (potential.py)
    curvature: bool = True          # thickness bound on bending: flexure <= 1/eps (elastic.py)
    supports: bool = True           # the clamps' mounts as obstacles (support.py)
    model: str = "projection"       # contact law: projection (contact/projection.py), potential (contact/potential.py)
    model_auto: bool = False        # the law was chosen by -contact_model auto (_contact_law)
    potential_points: Optional[int] = None   # -contact_quadrature with the potential (nqp)


@dataclass
class Output:
    dir: str
    quiet: bool
    restart: Optional[str]
    case_name: str


@dataclass(eq=False)  # holds numpy arrays: compare fields, not objects
class Scene:
    """Everything read from the options database.

    ``given`` is the sorted tuple of option names (no dash) explicitly present.
    """
    rod: Rod
    bc: BC
    loads: Loads
    contact: Contact
    output: Output
    stability: bool = False
    given: Tuple[str, ...] = field(default_factory=tuple)

    @property
    def contact_radius(self):
        """The effective contact radius: -contact_radius, else the rod radius."""
        return self.contact.radius if self.contact.radius is not None else self.rod.radius

    @property
    def contact_law(self):
        """(law radius, law penetration) of the contact law: law_tube of the contact radius,
        -contact_penetration and -contact_standoff."""
        c = self.contact
        return law_tube(self.contact_radius, c.penetration, c.standoff)

    def describe(self):
        """A short multi-line human-readable summary (for the log header)."""
        r = self.rod
        shape = r.shape
        if r.shape in ("arc", "circle"):
            shape += " R=%g angle=%gdeg" % (r.arc_radius, r.arc_angle_deg)
        elif r.shape == "helix":
            shape += " R=%g pitch=%g (%.3g turns)" % (r.helix_radius, r.helix_pitch, r.helix_turns)
        lines = [
            "case %s -> %s" % (self.output.case_name, self.output.dir),
            "rod L=%g r=%g %s%s twist=%g turns" % (r.length, r.radius, shape,
                                                  " closed" if r.closed else "", r.twist_turns),
            "stiffness EA=%g GA=%g,%g EI=%g,%g GJ=%g" % (r.EA, r.GA1, r.GA2, r.EI1, r.EI2, r.GJ),
            "mesh %d elements of order %d, %s quadrature" % (r.nelem, r.order, r.quadrature),
            "bc start=%s end=%s end_turns=%g" % (self.bc.start, self.bc.end, self.bc.end_turns),
            "loads F=%s%s M=%s g=%s in %d steps" % (
                _fmt_vec(self.loads.end_force), " (follower)" if self.loads.end_force_follower
                else "", _fmt_vec(self.loads.end_moment), _fmt_vec(self.loads.gravity),
                self.loads.steps),
            "contact %s" % ("on, radius %g, standoff %g" % (self.contact_radius,
                                                            self.contact.standoff)
                            if self.contact.enabled else "off"),
        ]
        return "\n".join(lines)


# ----------------------------------------------------------------------------
# Formatting and parsing helpers
# ----------------------------------------------------------------------------
def _fmt(x):
    return "%g" % x


def _fmt_petsc(x):
    """Reals as PETSc prints them: 1 -> '1.', 0.01 -> '0.01', 1e6 -> '1e+06'."""
    s = "%g" % x
    return s if any(c in s for c in ".eEn") else s + "."


def _fmt_vec(v):
    return ",".join(_fmt(x) for x in v)


_TRUE = ("", "1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def _parse_real(s):
    x = float(s)
    if not math.isfinite(x):
        raise ValueError("not a finite number")
    return x


def _parse(opt, s):
    """Parse the raw string ``s`` of ``opt``; ValueError(problem) if malformed."""
    t = s.strip()
    if opt.kind == BOOL:
        if t.lower() in _TRUE:
            return True
        if t.lower() in _FALSE:
            return False
        raise ValueError("not a true/false value (use %s alone, or %s true / %s false; "
                         "1/0, yes/no, on/off are accepted too)" % ((opt.flag,) * 3))
    if t == "":
        raise ValueError("given without a value (expected e.g. %s %s)" % (opt.flag, opt.example()))
    if opt.kind == REAL:
        try:
            return _parse_real(t)
        except ValueError:
            raise ValueError("not a real number (expected e.g. %s %s)"
                             % (opt.flag, opt.example())) from None
    if opt.kind == INT:
        try:
            return int(t)
        except ValueError:
            pass
        try:
            x = float(t)
        except ValueError:
            x = None
        if x is not None and math.isfinite(x) and x == int(x):
            return int(x)
        raise ValueError("not an integer (expected e.g. %s %s)" % (opt.flag, opt.example()))
    if opt.kind == CHOICE:
        if t.lower() in opt.choices:
            return t.lower()
        close = difflib.get_close_matches(t.lower(), opt.choices, n=1)
        hint = " (did you mean %s?)" % close[0] if close else ""
        raise ValueError("not an accepted value; accepted: %s%s" % (", ".join(opt.choices), hint))
    if opt.kind == VEC3:
        parts = [p.strip() for p in t.split(",")]
        form = "three comma-separated numbers %s, e.g. %s %s" % (opt.metavar, opt.flag,
                                                                  opt.example())
        if len(parts) != 3:
            raise ValueError("expected %s; got %d value%s"
                             % (form, len(parts), "" if len(parts) == 1 else "s"))
        try:
            return np.array([_parse_real(p) for p in parts], dtype=float)
        except ValueError:
            raise ValueError("expected %s; not all are finite numbers" % form) from None
    return t  # STR


def _default_options():
    from petsc4py import PETSc
    return PETSc.Options()


class _Reader:
    """Reads every option of the table once; parse problems are collected."""

    def __init__(self, options):
        self.values, self.raw, self.errors = {}, {}, []
        self.options = options
        for opt in OPTIONS:
            if not options.hasName(opt.name):
                self.values[opt] = opt.default
                continue
            s = options.getString(opt.name, "")
            s = "" if s is None else str(s)
            self.raw[opt] = s
            try:
                self.values[opt] = _parse(opt, s)
            except ValueError as e:
                shown = "%s = %s" % (opt.flag, s) if s.strip() else opt.flag
                self.errors.append((shown + ": " + str(e), opt.flag))
                self.values[opt] = None

    def given(self, opt):
        return opt in self.raw


class _Checks:
    """Collects problems; raise_if_any() raises them all in one SceneError."""

    def __init__(self, reader):
        self.r = reader
        self.msgs, self.opts = [], []

    def __getitem__(self, opt):
        return self.r.values[opt]

    def given(self, opt):
        return self.r.given(opt)

    def show(self, opt, value=None):
        """'-opt = raw' for given options, '-opt = value' (the default) otherwise."""
        if self.given(opt) and self.r.raw[opt].strip():
            return "%s = %s" % (opt.flag, self.r.raw[opt].strip())
        v = self[opt] if value is None else value
        if isinstance(v, np.ndarray):
            v = _fmt_vec(v)
        elif isinstance(v, float):
            v = _fmt(v)
        return "%s = %s" % (opt.flag, v)

    def fail(self, msg, *opts):
        self.msgs.append(msg)
        self.opts.extend(o.flag for o in opts)

    def raise_if_any(self):
        if self.msgs:
            raise SceneError("\n".join(self.msgs), self.opts)


def _close(a, b, rtol=1e-6):
    return abs(a - b) <= rtol * max(abs(a), abs(b))


# ----------------------------------------------------------------------------
# Case name
# ----------------------------------------------------------------------------
def _case_name_from_argv(argv):
    """Basename (without .opts) of the last ``-options_file X`` whose path lies
    under a directory called ``cases``; else of the last ``-options_file``;
    else 'default'."""
    files = [argv[i + 1] for i in range(len(argv) - 1) if argv[i] == "-options_file"]
    in_cases = [f for f in files if "cases" in PurePath(f).parent.parts]
    pick = in_cases[-1] if in_cases else (files[-1] if files else None)
    if pick is None:
        return "default"
    name = os.path.basename(pick.rstrip("/"))
    if name.endswith(".opts"):
        name = name[:-len(".opts")]
    return name or "default"


# ----------------------------------------------------------------------------
# read_scene
# ----------------------------------------------------------------------------
MAX_LOAD_STEPS = 1e7
"""The most -load_steps (at ~1 ms a step, three hours of load steps at least)."""
MIN_LENGTH, MAX_LENGTH = 1e-40, 1e40
"""The lengths a scene may hold (-rod_length 1e150 overflowed L^4, -contact_radius 1e-170 the
contact law's points per element: tracebacks)."""
LENGTH_OPTIONS = (O.rod_length, O.rod_arc_radius, O.rod_helix_radius, O.rod_helix_pitch,
                  O.rod_imperfection, O.contact_radius, O.contact_exclusion)
# (-rod_radius's own check, _check_stiffness, names the stiffnesses its powers make)


def read_scene(argv=None, options=None):
    """Read, derive and validate the scene.

    ``options``: a petsc4py ``PETSc.Options()`` (default: the global database);
    ``argv``: the command line (default ``sys.argv``), used only to derive the
    case name.  Raises :class:`SceneError` listing every problem found.
    Does not check for unknown options: call :func:`check_unknown_options`.
    Every option of the table is read (so PETSc counts it as used), whether or
    not it applies (e.g. -rod_helix_radius with -rod_shape straight is ignored).
    """
    if options is None:
        options = _default_options()
    if argv is None:
        argv = sys.argv
    reader = _Reader(options)
    if reader.errors:
        raise SceneError("\n".join(m for m, _ in reader.errors), [f for _, f in reader.errors])
    c = _Checks(reader)

    # 1. every option on its own: range checks from the table
    for opt in OPTIONS:
        v = c[opt]
        if opt.rng is None or v is None or not c.given(opt):
            continue
        if v not in opt.rng:
            note = " (%s)" % opt.note if opt.note else ""
            c.fail("%s: %s%s" % (c.show(opt), opt.rng.describe(opt.kind == INT), note), opt)
    # lengths whose powers (up to the sixth: L^4 in the stability's neutral band, eps^2 in the
    # contact law's support) stay in double precision
    for opt in LENGTH_OPTIONS:
        v = c[opt]
        if c.given(opt) and v is not None and v != 0.0 and not \
                MIN_LENGTH <= abs(v) <= MAX_LENGTH:
            c.fail("%s: a length outside %s .. %s, where the solver's powers of the lengths "
                   "leave double precision; choose units that keep the lengths near 1 (e.g. mm "
                   "or km)" % (c.show(opt), _fmt(MIN_LENGTH), _fmt(MAX_LENGTH)), opt)
    c.raise_if_any()

    # 2. combinations and derived quantities
    rod, material = _rod(c)
    bc = _bc(c, rod)
    loads = _loads(c, rod, bc)
    contact = _contact(c, rod, bc)
    output = _output(c, argv)
    c.raise_if_any()
    rod = Rod(**rod, **material)
    return tolerance_start(Scene(rod=rod, bc=bc, loads=loads, contact=contact, output=output,
                                 stability=bool(c[O.stability]),
                                 given=tuple(sorted(o.name for o in reader.raw))))


def _snes_tolerance(options, name, default):
    """-snes_rtol or -snes_atol (``name``) as a number (``default`` when absent; a malformed
    value is refused with its fix by cli.petsc_option_problems)."""
    try:
        return float(options.getReal(name, default))
    except Exception:
        return default


def helix_curvature(radius, pitch):
    """Curvature R / (R^2 + c^2) of a helix of radius R and rise per turn 2 pi c."""
    c = pitch / (2.0 * math.pi)
    return radius / (radius ** 2 + c ** 2)


def helix_turn_distance(radius, pitch, exclusion=0.0):
    """The shortest distance from a point of a helix of radius R and rise per turn P to the
    points at least ``exclusion`` of arclength away: min over phi of |x(0) - x(phi)|,
    x(phi) = (R cos phi, R sin phi, P phi / 2 pi), phi from max(pi, the exclusion's angle)
    over two turns (about P cos alpha, alpha the pitch angle, where the neighbouring turn is
    the nearest; a steep helix's nearest admissible point may lie within its first turn)."""
    from scipy.optimize import minimize_scalar
    R, P = float(radius), abs(float(pitch))
    c = P / (2.0 * math.pi)
    lo = max(math.pi, float(exclusion) / math.hypot(R, c))

    def d2(phi):
        return (2.0 * R * np.sin(0.5 * phi)) ** 2 + (c * phi) ** 2
    phi = np.linspace(lo, lo + 4.0 * math.pi, 801)
    k = int(np.argmin(d2(phi)))
    a, b = phi[max(k - 1, 0)], phi[min(k + 1, len(phi) - 1)]
    res = minimize_scalar(d2, bounds=(a, b), method="bounded", options={"xatol": 1e-13})
    return math.sqrt(min(res.fun, d2(phi[k])))


def _rod(c):
    L, r = c[O.rod_length], c[O.rod_radius]
    if r >= L / 2:
        c.fail("%s with %s: the radius must be well below half the length (a rod is slender; "
               "check the units of both)" % (c.show(O.rod_radius), c.show(O.rod_length)),
               O.rod_radius, O.rod_length)

    # --- material and stiffness
    E = c[O.rod_youngs]
    shear_given = c.given(O.rod_shear)
    if shear_given and c.given(O.rod_poisson):
        c.fail("%s and %s: give the shear modulus or Poisson's ratio, not both "
               "(G = E/(2(1+nu)))" % (c.show(O.rod_shear), c.show(O.rod_poisson)),
               O.rod_shear, O.rod_poisson)
    if c.given(O.rod_EI) and (c.given(O.rod_EI1) or c.given(O.rod_EI2)):
        both = [o for o in (O.rod_EI1, O.rod_EI2) if c.given(o)]
        c.fail("%s together with %s: give -rod_EI (both axes) or -rod_EI1/-rod_EI2, not both"
               % (c.show(O.rod_EI), " and ".join(c.show(o) for o in both)), O.rod_EI, *both)
    if shear_given:
        G = c[O.rod_shear]
        nu = E / (2.0 * G) - 1.0            # nu = E/(2G) - 1
    else:
        nu = c[O.rod_poisson]
        G = E / (2.0 * (1.0 + nu))          # G = E/(2(1+nu))
    k_given = c.given(O.rod_shear_coefficient)
    k = c[O.rod_shear_coefficient] if k_given else 6.0 * (1.0 + nu) / (7.0 + 6.0 * nu)
    A = math.pi * r ** 2
    I = math.pi * r ** 4 / 4.0
    J = math.pi * r ** 4 / 2.0
    EI = c[O.rod_EI] if c.given(O.rod_EI) else None

    def direct(opt, derived):
        return c[opt] if c.given(opt) else derived

    EA = direct(O.rod_EA, E * A)
    GA = direct(O.rod_GA, k * G * A)
    EI1 = direct(O.rod_EI1, EI if EI is not None else E * I)
    EI2 = direct(O.rod_EI2, EI if EI is not None else E * I)
    GJ = direct(O.rod_GJ, G * J)
    ei1_direct = c.given(O.rod_EI1) or EI is not None
    ei2_direct = c.given(O.rod_EI2) or EI is not None

    # which material constants actually entered a stiffness
    k_used = not c.given(O.rod_GA)
    G_used = k_used or not c.given(O.rod_GJ)
    nu_used = (G_used and not shear_given) or (k_used and not k_given)
    E_used = (not (c.given(O.rod_EA) and ei1_direct and ei2_direct)) or nu_used
    if shear_given and nu_used and not (-1.0 < nu <= 0.5):
        c.fail("%s with %s implies Poisson's ratio nu = E/(2G) - 1 = %.4g, outside (-1, 0.5] "
               "(an isotropic material has G >= E/3); for a non-isotropic section give "
               "-rod_shear_coefficient or the shear stiffness -rod_GA directly"
               % (c.show(O.rod_shear), c.show(O.rod_youngs), nu), O.rod_shear, O.rod_youngs)
    material = dict(youngs=float(E) if E_used else None,
                    shear_modulus=float(G) if G_used else None,
                    poisson=float(nu) if nu_used else None,
                    shear_coefficient=float(k) if k_used else None)

    # --- reference shape
    shape = c[O.rod_shape]
    closed_given = c.given(O.rod_closed)
    arc_R = arc_deg = hel_R = hel_p = None
    if closed_given and c[O.rod_closed] and shape != "circle":
        c.fail("-rod_closed with %s: a closed rod needs -rod_shape circle" % c.show(O.rod_shape),
               O.rod_closed, O.rod_shape)
    if shape == "circle":
        if closed_given and not c[O.rod_closed]:
            c.fail("%s with -rod_shape circle: a circle is a closed ring; for an open ring use "
                   "-rod_shape arc -rod_arc_angle 360" % c.show(O.rod_closed),
                   O.rod_closed, O.rod_shape)
        arc_R, arc_deg = L / (2.0 * math.pi), 360.0
        if c.given(O.rod_arc_radius) and not _close(c[O.rod_arc_radius], arc_R):
            c.fail("%s with %s and -rod_shape circle: a closed ring of length L has radius "
                   "L/(2 pi) = %.10g; drop -rod_arc_radius or change -rod_length"
                   % (c.show(O.rod_arc_radius), c.show(O.rod_length), arc_R),
                   O.rod_arc_radius, O.rod_length)
        if c.given(O.rod_arc_angle) and not _close(c[O.rod_arc_angle], 360.0):
            c.fail("%s with -rod_shape circle: a circle spans 360 degrees; drop -rod_arc_angle"
                   % c.show(O.rod_arc_angle), O.rod_arc_angle, O.rod_shape)
    elif shape == "arc":
        R_given, a_given = c.given(O.rod_arc_radius), c.given(O.rod_arc_angle)
        if not (R_given or a_given):
            c.fail("-rod_shape arc needs -rod_arc_radius R or -rod_arc_angle DEG "
                   "(the other follows from -rod_length = R * angle)",
                   O.rod_shape, O.rod_arc_radius, O.rod_arc_angle)
        elif R_given and a_given:
            R, deg = c[O.rod_arc_radius], c[O.rod_arc_angle]
            if not _close(R * math.radians(deg), L):
                c.fail("%s and %s are inconsistent with %s: R * angle = %.6g, not L; give only "
                       "one of -rod_arc_radius and -rod_arc_angle"
                       % (c.show(O.rod_arc_radius), c.show(O.rod_arc_angle), c.show(O.rod_length),
                          R * math.radians(deg)), O.rod_arc_radius, O.rod_arc_angle, O.rod_length)
            arc_R, arc_deg = L / math.radians(deg), deg
        elif R_given:
            arc_R = c[O.rod_arc_radius]
            arc_deg = math.degrees(L / arc_R)
            if arc_deg > 360.0 * (1 + 1e-12):
                c.fail("%s with %s makes an arc of %.6g degrees > 360: an open arc spans at most "
                       "a full turn; for a closed ring use -rod_shape circle"
                       % (c.show(O.rod_arc_radius), c.show(O.rod_length), arc_deg),
                       O.rod_arc_radius, O.rod_length)
        else:
            arc_deg = c[O.rod_arc_angle]
            arc_R = L / math.radians(arc_deg)
    elif shape == "helix":
        missing = [o for o in (O.rod_helix_radius, O.rod_helix_pitch) if not c.given(o)]
        if missing:
            c.fail("-rod_shape helix needs %s (radius and rise per turn; the helix has arclength "
                   "-rod_length)" % " and ".join(o.flag for o in missing), O.rod_shape, *missing)
        else:
            hel_R, hel_p = c[O.rod_helix_radius], c[O.rod_helix_pitch]
            if hel_p == 0.0:
                c.fail("%s: the pitch must be nonzero (negative: left-handed); a helix of zero "
                       "pitch is a circle (-rod_shape circle)" % c.show(O.rod_helix_pitch),
                       O.rod_helix_pitch)
    if arc_R is not None and arc_R <= r:
        c.fail("%s with %s: the reference arc radius %.6g is not larger than the rod radius, so "
               "the rod would fold through itself; use a larger radius (or a longer rod)"
               % (c.show(O.rod_radius), c.show(O.rod_length), arc_R),
               O.rod_radius, O.rod_arc_radius)
    if hel_R is not None and hel_p:
        kappa = helix_curvature(hel_R, hel_p)
        if kappa * r >= 1.0:
            c.fail("%s, %s with %s: helix curvature %.6g exceeds 1/radius, so the rod would fold "
                   "through itself" % (c.show(O.rod_helix_radius), c.show(O.rod_helix_pitch),
                                       c.show(O.rod_radius), kappa),
                   O.rod_helix_radius, O.rod_helix_pitch, O.rod_radius)
    closed = shape == "circle"
    twist = c[O.rod_twist_turns]
    if closed and abs(twist - round(twist)) > 1e-9:
        c.fail("%s on a closed ring: the director frame must close up, so the twist must be a "
               "whole number of turns" % c.show(O.rod_twist_turns), O.rod_twist_turns)
    if closed and c[O.rod_nelem] * c[O.rod_order] < 3:
        c.fail("%s, %s: a closed ring needs at least 3 nodes (nelem * order >= 3)"
               % (c.show(O.rod_nelem), c.show(O.rod_order)), O.rod_nelem, O.rod_order)
    kappa0 = c[O.rod_kappa0]
    if kappa0 is not None and math.hypot(kappa0[0], kappa0[1]) * r >= 1.0:
        c.fail("%s with %s: the intrinsic flexure |(k1, k2)| = %.6g is not below 1/radius = "
               "%.6g, so the rod would fold through itself on the inside of its bend; use a "
               "gentler curvature or a thinner rod"
               % (c.show(O.rod_kappa0), c.show(O.rod_radius), math.hypot(kappa0[0], kappa0[1]),
                  1.0 / r), O.rod_kappa0, O.rod_radius)
    if c[O.rod_kernel] == "compiled":
        from rodsnes.model.elastic import compiled_available
        if not compiled_available():
            c.fail("%s: the compiled elastic kernel is not built on this machine; run `make "
                   "install` (it compiles rodsnes/model/_elastic_kernel.c) or use -rod_kernel auto"
                   % c.show(O.rod_kernel), O.rod_kernel)
    rod = dict(length=float(L), radius=float(r), EA=float(EA), GA1=float(GA), GA2=float(GA),
               EI1=float(EI1), EI2=float(EI2), GJ=float(GJ),
               kappa0=None if kappa0 is None else np.array(kappa0, dtype=float),
               shape=shape, arc_radius=_f(arc_R), arc_angle_deg=_f(arc_deg),
               helix_radius=_f(hel_R), helix_pitch=_f(hel_p), closed=closed,
               twist_turns=float(twist), imperfection=float(c[O.rod_imperfection]),
               nelem=int(c[O.rod_nelem]), order=int(c[O.rod_order]),
               quadrature=c[O.rod_quadrature], closed_gauge=bool(c[O.rod_closed_gauge]),
               kernel=c[O.rod_kernel], error_estimate=c[O.rod_error_estimate],
               tolerance=_f(c[O.rod_tolerance]), planar=c[O.rod_planar])
    _check_tolerance(c, L)
    return rod, material


TOLERANCE_START_NELEM = 4
"""-rod_tolerance without -rod_nelem: the first (coarse) mesh, raised until the mesh checks pass."""


def _check_tolerance(c, L):
    """-rod_tolerance needs the estimate, a fresh start, and an error double precision resolves."""
    if not c.given(O.rod_tolerance):
        return
    tol = c[O.rod_tolerance]
    if c[O.rod_error_estimate] == "off":
        c.fail("%s with %s: the mesh is chosen from the error estimate; drop %s off"
               % (c.show(O.rod_tolerance), c.show(O.rod_error_estimate),
                  O.rod_error_estimate.flag), O.rod_tolerance, O.rod_error_estimate)
    if tol < 1e-10 * L:
        c.fail("%s: below what double precision resolves on a rod of length %g (1e-10 L = %.1e); "
               "use -rod_tolerance %.0e or more" % (c.show(O.rod_tolerance), L, 1e-10 * L,
                                                   1e-10 * L), O.rod_tolerance)
    if c.given(O.restart):
        c.fail("%s with %s: a restart goes on on the mesh of the run it resumes; drop one of them"
               % (c.show(O.rod_tolerance), c.show(O.restart)), O.rod_tolerance, O.restart)


def tolerance_start(scene):
    """The coarse first mesh of -rod_tolerance when -rod_nelem is not given: TOLERANCE_START_NELEM
    elements, doubled until contact (_check_contact_mesh) and the element turns
    (_check_element_turns) allow it.  Returns the scene with that mesh."""
    from dataclasses import replace
    from rodsnes.model.mesh import build_mesh
    if scene.rod.tolerance is None or "rod_nelem" in scene.given:
        return scene
    n = TOLERANCE_START_NELEM
    while True:
        trial = replace(scene, rod=replace(scene.rod, nelem=n))
        msgs = []
        _check_contact_mesh(trial, lambda m, *o: msgs.append(m))
        _check_element_turns(trial, build_mesh(trial.rod, trial.bc), lambda m, *o: msgs.append(m))
        if not msgs or n >= 1 << 16:
            return trial
        n *= 2


def _f(x):
    return None if x is None else float(x)


def _bc(c, rod):
    closed = rod["closed"]
    if closed:
        for opt in (O.bc_start, O.bc_end):
            if c.given(opt) and c[opt] != "free":
                c.fail("%s on a closed ring: a closed rod has no ends (the solver removes the "
                       "rigid-body motion itself); drop %s" % (c.show(opt), opt.flag), opt)
        start, end = "free", "free"
    else:
        start, end = c[O.bc_start], c[O.bc_end]
    turns = c[O.bc_end_turns]
    if turns != 0.0:
        if closed:
            c.fail("%s on a closed ring: a ring has no end to turn; give the twist with "
                   "-rod_twist_turns (whole turns)" % c.show(O.bc_end_turns), O.bc_end_turns)
        elif end in ("pinned", "free"):
            c.fail("%s with -bc_end %s: nothing to turn (the end rotates freely); use -bc_end "
                   "clamped or sliding" % (c.show(O.bc_end_turns), end), O.bc_end_turns, O.bc_end)
    return BC(start=start, end=end, end_turns=float(turns))


def _loads(c, rod, bc):
    F = np.array(c[O.load_end_force], dtype=float)
    M = np.array(c[O.load_end_moment], dtype=float)
    g = np.array(c[O.load_gravity], dtype=float)
    if rod["closed"]:
        for opt, v in ((O.load_end_force, F), (O.load_end_moment, M)):
            if np.any(v != 0.0):
                c.fail("%s on a closed ring: a closed rod has no end to load" % c.show(opt), opt)
    else:
        if np.any(F != 0.0) and bc.end in ("clamped", "pinned"):
            c.fail("%s with -bc_end %s: the end cannot move, so the force does nothing; use "
                   "-bc_end free (or sliding, for a force along the end's tangent)"
                   % (c.show(O.load_end_force), bc.end),
                   O.load_end_force, O.bc_end)
        if np.any(M != 0.0) and bc.end == "clamped":
            c.fail("%s with -bc_end clamped: the end cannot turn, so the moment does nothing; use "
                   "-bc_end free or pinned (or -bc_end_turns to turn it)"
                   % c.show(O.load_end_moment), O.load_end_moment, O.bc_end)
    unsupported = rod["closed"] or (bc.start == "free" and bc.end == "free")
    if unsupported and np.any(g != 0.0):
        where = "a closed ring" if rod["closed"] else "-bc_start free and -bc_end free"
        c.fail("%s on %s: nothing supports the rod, so there is no static equilibrium; "
               "%s" % (c.show(O.load_gravity), where,
                                   "drop -load_gravity" if rod["closed"]
                                   else "support an end (-bc_start clamped)"),
               O.load_gravity, O.bc_start)
    if unsupported and not rod["closed"] and (np.any(F != 0.0) or np.any(M != 0.0)):
        c.fail("end load with -bc_start free and -bc_end free: nothing balances it, so there is "
               "no static equilibrium; support the start (-bc_start clamped or pinned)",
               O.load_end_force, O.load_end_moment, O.bc_start)
    steps = c[O.load_steps]
    if steps > MAX_LOAD_STEPS:
        # 1e300 steps: increments below the load's resolution; the Newton path keeps 1 / steps
        # as its increment (1e9 steps of 1e-9 ran for months), the minimiser grows its own
        c.fail("%s: increments of %s, which no run of load steps gets through (each at least a "
               "residual and a factorisation) and below %g do not change the load in double "
               "precision; use at most %s load steps" % (c.show(O.load_steps), _fmt(1.0 / steps),
                                                         MIN_LOAD_STEP, _fmt(MAX_LOAD_STEPS)),
               O.load_steps)
    return Loads(end_force=F, end_force_follower=bool(c[O.load_end_force_follower]),
                 end_moment=M, gravity=g, steps=int(c[O.load_steps]),
                 max_cutbacks=int(c[O.load_max_cutbacks]), min_step=float(c[O.load_min_step]),
                 twist_turns=float(c[O.load_twist_turns]), stop=float(c[O.load_stop]),
                 path=str(c[O.load_path]), max_it=int(c[O.load_max_it]),
                 rtol=_snes_tolerance(c.r.options, "snes_rtol", 1e-10),
                 atol=_snes_tolerance(c.r.options, "snes_atol", 0.0),
                 predictor=bool(c[O.load_predictor]), retraction=bool(c[O.load_retraction]),
                 stagnation_its=int(c[O.load_stagnation_its]),
                 arclength=bool(c[O.load_arclength]),
                 arclength_max_steps=int(c[O.load_arclength_max_steps]),
                 arclength_its=int(c[O.load_arclength_its]))


def _contact(c, rod, bc):
    enabled = bool(c[O.contact])
    rc = _f(c[O.contact_radius])
    q = c[O.contact_quadrature]
    rcontact = rc if rc is not None else rod["radius"]
    if enabled and rod["helix_radius"] is not None and rod["helix_pitch"]:
        if abs(rod["helix_pitch"]) < 2.0 * rcontact:
            c.fail("%s with contact radius %g: neighbouring turns interpenetrate in the reference "
                   "helix (|pitch| < 2 * contact radius), which self-contact cannot start from"
                   % (c.show(O.rod_helix_pitch), rcontact), O.rod_helix_pitch, O.contact_radius)
    if enabled and rod["shape"] == "arc" and not rod["closed"] and \
            rod["arc_radius"] is not None and rod["arc_angle_deg"] is not None:
        # an open arc of nearly a whole turn: its ends start closer than the tube allows (the
        # potential's start not finite, exit 3; the projection's ends pushed apart, exit 0)
        theta = math.radians(abs(rod["arc_angle_deg"]))
        gap = 2.0 * rod["arc_radius"] * abs(math.sin(0.5 * theta)) if theta < 2 * math.pi \
            else 0.0
        if theta > math.pi and gap < 2.0 * rcontact:
            # the widest angle whose ends keep the diameter apart, the rod's length kept
            # (R = L / angle): bisection of (L / t) sin(t / 2) = radius on (pi, 2 pi)
            lo, hi = math.pi, 2.0 * math.pi
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if rod["length"] / mid * math.sin(0.5 * mid) > rcontact \
                    else (lo, mid)
            most = math.degrees(lo)
            if c.given(O.rod_arc_angle):
                shown, fix = c.show(O.rod_arc_angle), "an angle below %.4g degrees" % most
            else:           # the radius given: the length that keeps the ends apart
                R = rod["arc_radius"]
                longest = R * (2.0 * math.pi - 2.0 * math.asin(min(1.0, rcontact / R)))
                shown = "-rod_shape arc of radius %.6g (%.4g degrees)" % (
                    R, abs(rod["arc_angle_deg"]))
                fix = "a -rod_length below %.4g" % longest
            c.fail("%s with contact radius %g: the arc's ends start %.3g apart, closer than "
                   "the tube's diameter (%.3g), which self-contact cannot start from; use %s "
                   "(or -rod_shape circle -rod_closed for a ring)"
                   % (shown, rcontact, gap, 2.0 * rcontact, fix),
                   O.rod_arc_angle, O.rod_arc_radius, O.contact_radius)
    standoff = float(c[O.contact_standoff]) if enabled else 0.0
    rlaw, plaw = law_tube(rcontact, c[O.contact_penetration], standoff)
    if enabled:
        bends = []                  # (reference curvature, the options that set it, as shown)
        if rod["arc_radius"] is not None:
            shown = (c.show(O.rod_arc_radius) if c.given(O.rod_arc_radius) else
                     "-rod_shape %s of radius %.6g" % (rod["shape"], rod["arc_radius"]))
            bends.append((1.0 / rod["arc_radius"], (O.rod_arc_radius,), shown))
        if rod["helix_radius"] is not None and rod["helix_pitch"]:
            bends.append((helix_curvature(rod["helix_radius"], rod["helix_pitch"]),
                          (O.rod_helix_radius, O.rod_helix_pitch),
                          "%s, %s" % (c.show(O.rod_helix_radius), c.show(O.rod_helix_pitch))))
        if rod["kappa0"] is not None:
            bends.append((float(np.hypot(*rod["kappa0"][:2])), (O.rod_kappa0,),
                          c.show(O.rod_kappa0)))
        for kappa, opts, shown in bends:
            if c[O.contact_curvature] and kappa * rcontact > 1.0:
                c.fail("%s: the reference centreline bends to curvature %.6g, above 1/contact "
                       "radius = %.6g, which the contact tube's thickness bound forbids; use a "
                       "smaller -contact_radius, a gentler reference shape, or "
                       "-contact_curvature false" % (shown, kappa, 1.0 / rcontact),
                       *opts, O.contact_radius, O.contact_curvature)
            elif standoff > 0 and kappa * rlaw > 1.0:
                # the law's tube would fold on itself: the unloaded rod would be pushed apart
                most = 1.0 / (kappa * rcontact) - 1.0
                c.fail("%s with %s: the reference centreline bends to curvature %.6g, above "
                       "1/(contact radius x (1 + standoff)) = %.6g, where the contact law's tube "
                       "folds on itself and would bend the unloaded rod; %s or a gentler "
                       "reference shape"
                       % (shown, c.show(O.contact_standoff), kappa, 1.0 / rlaw,
                          "use a standoff below %.3g" % most if most > 0 else "no standoff"),
                       *opts, O.contact_standoff)
    if enabled and c.given(O.contact_supports) and c[O.contact_supports] and \
            (rod["closed"] or bc.start != "clamped" or bc.end != "sliding"):
        c.fail("%s: the clamps' mounts are modelled for an open rod clamped at its start and "
               "sliding at its end (-bc_start clamped -bc_end sliding, here %s, %s); drop the "
               "option or change the supports" % (c.show(O.contact_supports), bc.start, bc.end),
               O.contact_supports, O.bc_start, O.bc_end)
    if enabled and rod["helix_radius"] is not None and rod["helix_pitch"] and standoff > 0:
        # the law's tube may not touch in the stress-free shape (an unloaded coil would move)
        excl = _f(c[O.contact_exclusion])
        gap = helix_turn_distance(rod["helix_radius"], rod["helix_pitch"],
                                  math.pi * rlaw if excl is None else excl) / (2 * rcontact) - 1
        if standoff >= gap:
            allow = ("use a standoff below %.3g" % gap if gap > 0 else
                     "this coil allows none (its turns are no further apart than the diameter)")
            c.fail("%s with %s, %s: the contact law acts from %.6g x the contact diameter, "
                   "which the reference helix's neighbouring turns are closer than (%.6g x), "
                   "so the unloaded coil would be pushed apart; %s"
                   % (c.show(O.contact_standoff), c.show(O.rod_helix_radius),
                      c.show(O.rod_helix_pitch), 1 + standoff, 1 + gap, allow),
                   O.contact_standoff, O.rod_helix_pitch)
    model = _contact_law(c, rod, rlaw, plaw)
    if enabled and model == "potential" and c.given(O.contact_zones):
        c.fail("%s: contact zones belong to the closest-point law; -contact_model potential "
               "integrates at fixed points (-contact_quadrature); drop the option"
               % c.show(O.contact_zones), O.contact_zones, O.contact_model)
    if enabled and model == "potential" and q is None:
        from rodsnes.contact.potential import DENSITY, MAX_POINTS, support_length
        need = _potential_points(rod, rlaw, plaw)
        h = rod["length"] / rod["nelem"]
        if need > MAX_POINTS:
            c.fail("%s: the pair potential resolves a contact by %d quadrature points on the "
                   "stretch 2 t0 = %.4g a point touches at the promised penetration, which "
                   "takes %d points per element of length %.4g (more than %d); refine the mesh "
                   "(-rod_nelem %d or more), set the points per element with "
                   "-contact_quadrature, or use -contact_model projection"
                   % (c.show(O.contact_model), DENSITY, support_length(rlaw, plaw), need, h,
                      MAX_POINTS, int(np.ceil(rod["nelem"] * need / MAX_POINTS))),
                   O.contact_model, O.rod_nelem, O.contact_quadrature)
    penalty = _f(c[O.contact_penalty])
    # a penalty the user chose is kept as given unless adaptation is asked for explicitly
    adapt = bool(c[O.contact_penalty_adapt]) if c.given(O.contact_penalty_adapt) else penalty is None
    return Contact(enabled=enabled, penalty=penalty, radius=rc,
                   exclusion=_f(c[O.contact_exclusion]),
                   quadrature=int(q) if q is not None and model != "potential"
                   else rod["order"] + 2,
                   potential_points=int(q) if q is not None and model == "potential"
                   else None,
                   zones=bool(c[O.contact_zones]), model=model,
                   model_auto=c[O.contact_model] == "auto",
                   penetration=float(c[O.contact_penetration]), standoff=standoff,
                   adapt=adapt, wall=bool(c[O.contact_wall]),
                   curvature=bool(c[O.contact_curvature]),
                   supports=bool(c[O.contact_supports]))


def _potential_points(rod, rlaw, plaw):
    """Quadrature points per element the pair potential needs on this mesh
    (contact.potential.points_per_element at the law's promised penetration, law_tube)."""
    from rodsnes.contact.potential import MAX_POINTS, points_per_element
    try:
        with np.errstate(divide="ignore", over="ignore", invalid="ignore", under="ignore"):
            return points_per_element(rod["length"] / rod["nelem"], rlaw, plaw)
    except (OverflowError, ValueError, ZeroDivisionError):
        return MAX_POINTS + 1           # a law no mesh resolves (its radius under- or overflows)


def _contact_law(c, rod, rlaw, plaw):
    """The contact law of -contact_model: as given, or for auto the pair potential where the
    mesh resolves it (its automatic points per element within MAX_POINTS) and contact zones
    were not asked for, else the closest-point projection; -contact_quadrature then applies to
    the law picked."""
    model = str(c[O.contact_model])
    if model != "auto":
        return model
    from rodsnes.contact.potential import MAX_POINTS
    if c.given(O.contact_zones) or _potential_points(rod, rlaw, plaw) > MAX_POINTS:
        return "projection"
    return "potential"


def _output(c, argv):
    if c.given(O.case_name):
        name = c[O.case_name]
        if "/" in name or name in (".", ".."):
            c.fail("%s: a case name is a plain name, not a path (it names out/<case name>)"
                   % c.show(O.case_name), O.case_name)
    else:
        name = _case_name_from_argv(list(argv))
    out = c[O.output_dir] if c.given(O.output_dir) else os.path.join("out", name)
    restart = c[O.restart]
    if restart is not None and not os.path.exists(restart):
        c.fail("%s: no such directory (give the output directory of an earlier run)"
               % c.show(O.restart), O.restart)
    return Output(dir=out, quiet=bool(c[O.quiet]), restart=restart, case_name=name)


# ----------------------------------------------------------------------------
# help and unknown options
# ----------------------------------------------------------------------------
def help_text():
    """PETSc-style listing of every rodsnes option, grouped by section:
    ``  -rod_length <1.>: rod length L ...``."""
    lines = []
    for key, title in SECTIONS.items():
        opts = [o for o in OPTIONS if o.section == key]
        if not opts:
            continue
        lines.append("%s %s" % (title, "-" * max(3, 72 - len(title))))
        for o in opts:
            s = "  %s <%s>: %s" % (o.flag, o.shown_default(), o.help)
            if o.kind == CHOICE:
                s += " (one of) " + " ".join(o.choices)
            elif o.kind == VEC3:
                s += " (as %s)" % o.metavar
            lines.append(s)
    return "\n".join(lines) + "\n"


def _or_list(items):
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def _suggest(word, names, n=3, cutoff=0.6, spread=0.1):
    """Closest names (difflib), keeping only those nearly as close as the best."""
    close = difflib.get_close_matches(word, names, n=n, cutoff=cutoff)
    if not close:
        return []
    ratio = [difflib.SequenceMatcher(None, word, m).ratio() for m in close]
    return [m for m, q in zip(close, ratio) if q >= ratio[0] - spread]


def check_unknown_options(options=None):
    """Raise SceneError if the database holds an option that is neither a
    rodsnes option nor starts with a known PETSc prefix (any option starting
    with a rodsnes prefix must be a rodsnes option).  All unknown options are
    listed, one per line in alphabetical order, with the closest rodsnes options
    as suggestions; a retired option (:data:`RETIRED`) says what replaced it.
    Option names are compared case-insensitively, as PETSc does."""
    if options is None:
        options = _default_options()
    known = {o.name.lower(): o.name for o in OPTIONS}
    msgs, bad = [], []
    for name in sorted(options.getAll(), key=str.lower):
        low = name.lower()
        if low in known:
            continue
        if low in RETIRED:
            msgs.append("-%s was retired with %s" % (low, RETIRED[low]))
            bad.append("-" + name)
            continue
        if is_petsc_option(low):
            continue
        close = _suggest(low.lstrip("-"), list(known))
        if close:
            hint = ": did you mean %s?" % _or_list(["-" + known[k] for k in close])
        elif low.startswith(RODSNES_PREFIXES):
            hint = ": not a rodsnes option (run with -help to list them)"
        else:
            hint = ": neither a rodsnes nor a PETSc option (run with -help to list them)"
        msgs.append("unknown option -%s%s" % (name, hint))
        bad.append("-" + name)
    if msgs:
        raise SceneError("\n".join(msgs), bad)


# ----------------------------------------------------------------------------
# Scenes that read correctly but cannot be solved as given
# ----------------------------------------------------------------------------
MAX_ELEMENT_TURN = 0.75 * math.pi
"""Largest turn of the frames across one element (rad): the rotation interpolation takes
rotations relative to a node of the element, unique only below half a turn (a ring of two cubic
elements, 180 degrees each, fails; of three, 120 degrees each, converges to its 24-element
energy within 2e-7)."""

CONTACT_MAX_ELEMENT = 8.0
"""Longest element of a contact scene, in contact radii: rollup_contact with 8 elements (12.5
radii) lands on another equilibrium, 0.11 L from the contact; with 16 (6.25 radii) it is within
1e-4 L of the exact one (docs/data/work_precision_contact.csv)."""

MAX_IMPERFECT_STRETCH = 0.1
"""An imperfection may lengthen the stress-free centreline by at most this fraction of L."""

FORCE_RANGE = (1e-140, 1e140)
"""The force scale a problem may have: PETSc's norms square the residual (a Mattiasson twin
scaled by 1e-200 had |F| = 0 and was accepted unloaded; by 1e200, |F| = inf)."""

MAX_ROUNDOFF_SHARE = 0.1
"""The residual's roundoff floor may be at most this fraction of the force scale."""

MEMORY_BASE, MEMORY_PER_NODE = 0.15e9, 1.0e4
"""Bytes of a run without contact: the start-up, and per node (Jacobian, MUMPS LU factors,
vectors); measured on the cantilever, 0.41 GB at 10^4 and 2.97 GB at 10^5 cubic elements
(docs/bench_scaling.md).  Contact adds more, growing with the pairs in contact."""


def _count(n):
    """A count for a message: the integer, or '%.3g' from 1e9 on (a 300-digit -rod_nelem said
    nothing)."""
    return "%d" % n if n < 1e9 else "%.3g" % n


def _show(flag, value):
    if isinstance(value, np.ndarray):
        value = _fmt_vec(value)
    elif isinstance(value, float):
        value = _fmt(value)
    return "%s = %s" % (flag, value)


def _bytes(n):
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= size:
            return "%.3g %s" % (n / size, unit)
    return "%.3g kB" % (n / 1e3)


def physical_memory():
    """Bytes of physical memory of this machine (None if unknown)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _check_memory(scene, fail, memory):
    """-rod_nelem too large for this machine's memory, or for PETSc's indices."""
    r = scene.rod
    nodes = r.nelem * r.order + (0 if r.closed else 1)
    need = MEMORY_BASE + MEMORY_PER_NODE * nodes
    try:
        from petsc4py import PETSc
        index_max = int(np.iinfo(PETSc.IntType).max)
    except ImportError:
        index_max = int(np.iinfo(np.int32).max)
    index_fit = index_max // (6 * r.order)
    if memory is not None and need > memory:
        fit = min(int((memory - MEMORY_BASE) / MEMORY_PER_NODE / r.order), index_fit)
        fail("%s: %.3g nodes need about %s of memory (%s per node for the Jacobian and its LU "
             "factors, more with contact), this machine has %s; use -rod_nelem %d or fewer"
             % (_show("-rod_nelem", r.nelem), nodes, _bytes(need), _bytes(MEMORY_PER_NODE),
                _bytes(memory), max(fit, 1)), O.rod_nelem)
        return False
    if 6 * nodes > index_max:
        fail("%s: %.3g nodes make %.3g unknowns, more than this PETSc's indices count (%d); "
             "use -rod_nelem %d or fewer" % (_show("-rod_nelem", r.nelem), nodes, 6.0 * nodes,
                                             index_max, index_fit), O.rod_nelem)
        return False
    return True


_STIFFNESSES = (("EA", (O.rod_EA,), "E pi r^2"), ("GA1", (O.rod_GA,), "k G pi r^2"),
                ("GA2", (O.rod_GA,), "k G pi r^2"), ("EI1", (O.rod_EI1, O.rod_EI), "E pi r^4/4"),
                ("EI2", (O.rod_EI2, O.rod_EI), "E pi r^4/4"), ("GJ", (O.rod_GJ,), "G pi r^4/2"))
"""(stiffness, the options that give it directly, its formula from the material)."""


def _force_scale_cause(scene):
    """(what, options) of the largest term of scales.force_scale_terms (-load_twist_turns 1e300
    was blamed on -rod_EI and the units)."""
    ld, bc = scene.loads, scene.bc
    terms = force_scale_terms(scene)
    name = max(terms, key=lambda k: terms[k] if math.isfinite(terms[k]) else math.inf)
    if name == "bending":
        return "the bending stiffness (%s)" % (
            "-rod_EI" if {"rod_EI", "rod_EI1", "rod_EI2"} & set(scene.given)
            else "-rod_youngs, -rod_radius"), (O.rod_EI, O.rod_youngs)
    if name == "turns":
        end = abs(float(getattr(bc, "end_turns", 0.0) or 0.0))
        if end >= abs(float(ld.twist_turns or 0.0)):
            return _show("-bc_end_turns", end), (O.bc_end_turns,)
        return _show("-load_twist_turns", float(ld.twist_turns)), (O.load_twist_turns,)
    opt = getattr(O, "load_" + name)
    return _show(opt.flag, getattr(ld, name)), (opt,)


def _check_stiffness(scene, fail):
    """A stiffness that underflows to 0 (or to a subnormal) or overflows in double precision, a
    problem whose forces PETSc's norms cannot square, and a rod so slender (or a mesh so fine)
    that the residual's roundoff swamps the forces."""
    r = scene.rod
    causes = {}                     # (options shown, what happened) -> [stiffness names]
    opts = []
    for name, direct, formula in _STIFFNESSES:
        v = getattr(r, name)
        if math.isfinite(v) and v >= sys.float_info.min:
            continue
        how = ("overflow%s to infinity" if not math.isfinite(v) else "underflow%s to 0"
               if v == 0.0 else "%s subnormal (below %.3g)" % ("%s", sys.float_info.min))
        given = [o for o in direct if o.name in scene.given]
        if given:
            key = ("%s = %.3g" % (given[0].flag, v), how)
            opts.append(given[0])
        else:
            key = ("%s with %s" % (_show("-rod_radius", r.radius),
                                   _show("-rod_youngs", r.youngs) if r.youngs is not None
                                   else "the material"), how)
            opts += [O.rod_radius, O.rod_youngs]
            name = "%s = %s" % (name, formula)
        causes.setdefault(key, []).append(name)
    for (shown, how), names in causes.items():
        plural = len(names) > 1
        how = how % ("" if plural else "s") if "subnormal" not in how else \
            how % ("are" if plural else "is")
        fail("%s: in double precision the stiffness%s %s %s, so the rod has no usable stiffness; "
             "choose units that keep the stiffnesses near 1 (e.g. mm and N)%s"
             % (shown, "es" if plural else "", ", ".join(names), how,
                "" if shown.startswith("-rod_E") or shown.startswith("-rod_G") else
                ", or give -rod_EA, -rod_GA, -rod_EI, -rod_GJ directly"), *dict.fromkeys(opts))
    if causes:
        return
    scale = force_scale(scene)
    if not FORCE_RANGE[0] <= scale <= FORCE_RANGE[1]:
        cause, opts = _force_scale_cause(scene)
        fail("the forces of the problem (EI/L^2 + loads = %.3g, most of it from %s) are outside "
             "%g .. %g, where PETSc's norms of the residual (sums of squares) still work in double "
             "precision; choose units that keep the stiffnesses and loads near 1 (e.g. mm and N)"
             "%s" % (scale, cause, FORCE_RANGE[0], FORCE_RANGE[1],
                     ", or fewer turns" if O.bc_end_turns in opts or O.load_twist_turns in opts
                     else ""), *opts)
        return
    floor = residual_floor(r)
    if floor > MAX_ROUNDOFF_SHARE * scale:
        # the stiffness that makes the floor (residual_floor: stretch/shear, or bending/twist
        # over L), named: -rod_GJ 1e300 was blamed on the stretch stiffness 1e6
        stretch = max((r.EA, "EA"), (r.GA1, "GA"), (r.GA2, "GA"))
        bend = max((r.EI1, "EI"), (r.EI2, "EI"), (r.GJ, "GJ"))
        if stretch[0] >= bend[0] / r.length:
            what, value, fix, opt = ("stretch stiffness " + stretch[1], stretch[0],
                                     "a thicker rod, a softer -rod_EA and -rod_GA (nearly "
                                     "inextensible is enough)", O.rod_EA)
        else:
            what, value, fix, opt = ("%s / L" % bend[1], bend[0] / r.length,
                                     "a -rod_%s near the others" % bend[1], getattr(O, "rod_" + bend[1]))
        fail("%s, %s with %s: the residual's roundoff (%.3g, from the %s %.3g over "
             "%d nodes) exceeds %g of the forces of the problem (%.3g: EI/L^2 + loads), so double "
             "precision cannot resolve the equilibrium; use %s, or fewer elements"
             % (_show("-rod_radius", r.radius), _show("-rod_length", r.length),
                _show("-rod_nelem", r.nelem), floor, what, value,
                r.nelem * r.order + 1, MAX_ROUNDOFF_SHARE, scale, fix),
             O.rod_radius, opt, O.rod_nelem)


def _check_supports(scene, fail):
    """A rod pinned at one end and free at the other turns freely about the pin: a mechanism."""
    r, bc, ld = scene.rod, scene.bc, scene.loads
    if r.closed or sorted((bc.start, bc.end)) != ["free", "pinned"]:
        return
    loaded = [(o, v) for o, v in ((O.load_end_force, ld.end_force),
                                  (O.load_end_moment, ld.end_moment), (O.load_gravity, ld.gravity))
              if np.any(v != 0.0)]
    if not loaded:
        return
    pin = "-bc_start" if bc.start == "pinned" else "-bc_end"
    why = ("a pin takes no moment, so nothing balances the end moment (there is no equilibrium)"
           if np.any(ld.end_moment != 0.0) else "the unloaded rod's stiffness is singular, and the "
           "load would swing it about the pin as a rigid body")
    fail("%s with -bc_start %s -bc_end %s: the rod turns freely about the pin (a mechanism): %s; "
         "clamp that end (%s clamped) or support the other one"
         % (", ".join(_show(o.flag, v) for o, v in loaded), bc.start, bc.end, why, pin),
         *(o for o, _ in loaded), O.bc_start, O.bc_end)


# the largest -snes_atol, as a share of the force scale: an absolute tolerance above it accepts
# states whose forces are off by more than that share of the problem's (at the force scale
# itself, the unloaded rod of the first load step: exit 0, the rod unmoved)
MAX_ATOL_SHARE = 1e-6
_PETSC_ATOL = SimpleNamespace(flag="-snes_atol")    # a PETSc option, for fail()'s option list
# the largest -snes_rtol (every load path holds |g| <= rtol x the force scale): the same share
# (-snes_rtol 1 or more accepted the unloaded rod on every path, exit 0)
MAX_RTOL = MAX_ATOL_SHARE
_PETSC_RTOL = SimpleNamespace(flag="-snes_rtol")


def _check_tolerances(scene, fail):
    """-snes_rtol (every path) and -snes_atol (where the Newton path reads it; the minimiser
    does not: there it is an unused option) must not be a sizeable share of the forces the
    equilibrium is made of."""
    from rodsnes.model.loads import takes_newton_path
    ld = scene.loads
    rtol = ld.rtol
    if not 0.0 <= rtol <= MAX_RTOL:
        why = ("every load step holds the residual to -snes_rtol x the problem's force scale "
               "(EI/L^2 + loads), so a tolerance above %g may leave the forces off by more than "
               "that share of them (from 1 on, the first load step's unloaded rod already meets "
               "it)" % MAX_RTOL) if rtol > MAX_RTOL else "not a tolerance"
        fail("-snes_rtol = %s: %s; use a -snes_rtol from 0 to %g (default 1e-10)"
             % (_fmt(rtol), why, MAX_RTOL), _PETSC_RTOL)
    if not takes_newton_path(ld):
        return
    atol, scale = ld.atol, force_scale(scene)
    if not atol <= MAX_ATOL_SHARE * scale:
        fail("-snes_atol = %s: %.3g of the problem's force scale (%.3g: EI/L^2 + loads), so a "
             "residual that small may leave the forces off by that much - the first load step's "
             "unloaded rod already meets it; the tolerance is relative to that scale: use "
             "-snes_rtol (default 1e-10), or an -snes_atol below %.3g"
             % (_fmt(atol), atol / scale, scale, MAX_ATOL_SHARE * scale), _PETSC_ATOL)


def _check_sliding_end(scene, mesh, fail):
    """A sliding end moves along its tangent alone, its cross-section held: an end load's other
    components do nothing (the rod would stay unloaded, exit 0), and with a free start nothing
    holds the rod along the tangent (a mechanism under any load along it)."""
    r, bc, ld = scene.rod, scene.bc, scene.loads
    if r.closed or bc.end != "sliding":
        return
    from rodsnes.model.problem import sliding_axis
    axis = sliding_axis(np.asarray(mesh.q_init[-1], dtype=float))
    if axis is None:
        return              # a tangent off the axes: refused as such (model.problem.Constraints)
    name = "xyz"[axis]
    F = np.asarray(ld.end_force, dtype=float)
    off = [c for c in range(3) if c != axis and F[c] != 0.0]
    if off:
        fail("%s with -bc_end sliding: the end slides along its tangent (%s) alone, so the "
             "force's %s component%s do%s nothing; load it along %s, or use -bc_end free"
             % (_show(O.load_end_force.flag, F), name, " and ".join("xyz"[c] for c in off),
                "s" if len(off) > 1 else "", "" if len(off) > 1 else "es", name),
             O.load_end_force, O.bc_end)
    if np.any(np.asarray(ld.end_moment, dtype=float) != 0.0):
        fail("%s with -bc_end sliding: the end's cross-section is held (it slides without "
             "turning), so the moment does nothing; use -bc_end free or pinned (or -bc_end_turns "
             "to turn it)" % _show(O.load_end_moment.flag, ld.end_moment),
             O.load_end_moment, O.bc_end)
    g = np.asarray(ld.gravity, dtype=float)
    # the net load along the slide (the end force and gravity over the rod's length; both
    # held by nothing), beyond round-off of the two
    net, size = F[axis] + g[axis] * r.length, abs(F[axis]) + abs(g[axis]) * r.length
    if bc.start == "free" and size > 0.0 and abs(net) > 1e-12 * size:
        loaded = [(o, v) for o, v in ((O.load_end_force, F), (O.load_gravity, g)) if v[axis] != 0.0]
        fail("%s with -bc_start free -bc_end sliding: nothing holds the rod along %s (the end "
             "slides, the start is free), so the load's net %s component (%.3g) has no "
             "equilibrium; support the start (-bc_start clamped or pinned)"
             % (", ".join(_show(o.flag, v) for o, v in loaded), name, name, net),
             *(o for o, _ in loaded), O.bc_start, O.bc_end)


def _imperfection_limit(rod, bc, target):
    """The |amplitude| at which the imperfect centreline is ``target`` long (bisection)."""
    from dataclasses import replace
    from rodsnes.model.mesh import reference_length
    lo, hi = 0.0, abs(rod.imperfection)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if reference_length(replace(rod, imperfection=mid), bc, samples=1024) > target:
            hi = mid
        else:
            lo = mid
    return lo


def _check_imperfection(scene, fail):
    """An imperfection so large that the stress-free rod is no longer -rod_length long."""
    from rodsnes.model.mesh import reference_length
    r = scene.rod
    if r.imperfection == 0.0:
        return
    length = reference_length(r, scene.bc)
    if length > (1.0 + MAX_IMPERFECT_STRETCH) * r.length:
        limit = _imperfection_limit(r, scene.bc, (1.0 + MAX_IMPERFECT_STRETCH) * r.length)
        fail("%s with %s: the imperfection makes the stress-free centreline %.3g times as long as "
             "the rod (an imperfection is a small seed of the buckling mode, in length units, "
             "e.g. 1e-3 L); use |a| below %.3g (%g longer)"
             % (_show("-rod_imperfection", r.imperfection), _show("-rod_length", r.length),
                length / r.length, limit, MAX_IMPERFECT_STRETCH), O.rod_imperfection)


def contact_exclusion(scene):
    """The exclusion arclength of the contact: -contact_exclusion, else pi x the law's radius
    (law_tube: the contact radius with its standoff)."""
    c = scene.contact
    return c.exclusion if c.exclusion is not None else math.pi * scene.contact_law[0]


def _check_contact_reach(scene, fail):
    """Contact that can never happen (exclusion as long as the rod) or always happens (an
    exclusion shorter than the contact diameter)."""
    c, r = scene.contact, scene.rod
    if not c.enabled:
        return
    eps, delta = scene.contact_radius, contact_exclusion(scene)
    grow = scene.contact_law[0] / eps       # the law's radius over the tube's (law_tube)
    span = r.length / 2 if r.closed else r.length
    where = "half the ring" if r.closed else "the rod"
    if c.exclusion is None and delta >= span:
        law = " x (1 + -contact_standoff %g)" % c.standoff if c.standoff else ""
        pi = "(pi (1 + -contact_standoff %g))" % c.standoff if c.standoff else "pi"
        fail("%s: the exclusion arclength pi x radius%s = %.4g is not shorter than %s (%.4g), "
             "so no two points of the rod can ever touch and contact would do nothing; a "
             "contact radius below %.4g (%s / %s)%s allows contact, or drop -contact"
             % (_show("-contact_radius", eps), law, delta, where, span, span / math.pi / grow,
                "L/2" if r.closed else "L", pi,
                " or a smaller -contact_standoff" if c.standoff else ""),
             O.contact_radius, O.contact, *((O.contact_standoff,) if c.standoff else ()))
    elif c.exclusion is not None and delta >= span:
        fail("%s: not shorter than %s (%.4g), so no two points of the rod can ever touch and "
             "contact would do nothing; use a shorter exclusion (default pi x contact radius%s "
             "= %.4g) or drop -contact" % (_show("-contact_exclusion", delta), where, span,
                                           " x (1 + standoff)" if c.standoff else "",
                                           math.pi * eps * grow), O.contact_exclusion, O.contact)
    elif c.exclusion is not None and delta < 2.0 * eps * grow:
        fail("%s with contact radius %g and standoff %g: points less than the law's diameter "
             "2 x radius x (1 + standoff) = %.4g apart along the rod are always closer than that "
             "in space, so the rod would be in contact with its own neighbourhood; use at least "
             "%.4g (default pi x radius x (1 + standoff) = %.4g)"
             % (_show("-contact_exclusion", delta), eps, c.standoff, 2 * eps * grow,
                2 * eps * grow, math.pi * eps * grow),
             O.contact_exclusion, O.contact_radius, O.contact_standoff)


# a -contact_penalty this far from the default (contact.projection.default_penalty) either way:
# 1e20 and 1e300 on michell_contact stalled the minimiser for hours (|g| and E unchanged),
# the penalty sweep's 1000 x took twice the iterations
MAX_PENALTY_FACTOR = 1e6


def _check_contact_penalty(scene, fail):
    """A -contact_penalty more than MAX_PENALTY_FACTOR times the default, or less than its
    inverse: the contact's stiffness out of all proportion to the rod's."""
    from rodsnes.contact.projection import default_penalty
    c, r = scene.contact, scene.rod
    if not c.enabled or c.penalty is None:
        return
    eps, law_penetration = scene.contact_law
    mu0 = default_penalty(min(r.EI1, r.EI2), eps, law_penetration)
    if not mu0 / MAX_PENALTY_FACTOR <= c.penalty <= mu0 * MAX_PENALTY_FACTOR:
        fail("-contact_penalty = %s: %.3g times the default %.3g (the penalty that keeps "
             "-contact_penetration %g against the rod's bending stiffness), so the contact's "
             "stiffness is out of all proportion to the rod's; give a penalty within a factor %.0e of "
             "the default, or leave it out (-contact_penalty_adapt then raises it as the "
             "contact presses)" % (_fmt(c.penalty), c.penalty / mu0, mu0, c.penetration,
                                   MAX_PENALTY_FACTOR), O.contact_penalty)


def _check_contact_mesh(scene, fail):
    """Contact needs elements no longer than CONTACT_MAX_ELEMENT contact radii."""
    c, r = scene.contact, scene.rod
    if not c.enabled:
        return
    eps, h = scene.contact_radius, r.length / r.nelem
    if h > CONTACT_MAX_ELEMENT * eps:
        need = math.ceil(r.length / (CONTACT_MAX_ELEMENT * eps))
        fail("%s with contact radius %g: elements of length %.4g (%.3g contact radii) are too "
             "long to resolve a contact (at most %g radii); use -rod_nelem %s or more"
             % (_show("-rod_nelem", r.nelem), eps, h, h / eps, CONTACT_MAX_ELEMENT, _count(need)),
             O.rod_nelem, O.contact_radius)


def _load_turn_per_element(scene):
    """((rad) a lower bound of the turn per element the loads force, its cause) from what is
    known before the solve: prescribed end turns spread over the rod, and an end moment alone
    on a cantilever (then the internal moment is that moment everywhere, the flexure at least
    |M| / max stiffness)."""
    r, bc, ld = scene.rod, scene.bc, scene.loads
    h = r.length / r.nelem
    turns = []
    if bc.end_turns:
        turns.append((2 * math.pi * abs(bc.end_turns) * h / r.length,
                      _show("-bc_end_turns", bc.end_turns), O.bc_end_turns))
    M = float(np.linalg.norm(ld.end_moment))
    if (M and (bc.start, bc.end) == ("clamped", "free") and not np.any(ld.end_force)
            and not np.any(ld.gravity)):
        turns.append((M * h / max(r.EI1, r.EI2, r.GJ), _show("-load_end_moment", ld.end_moment),
                       O.load_end_moment))
    return max(turns, key=lambda t: t[0]) if turns else (0.0, None, None)


# the most elements a frame's turning may ask for before the mesh is made: far beyond any
# machine's memory (_check_memory), and below the count at which the frames' angles lose
# their digits in double precision
MAX_ELEMENTS_NEEDED = 1e9


def _check_frame_turns(scene, fail):
    """Frames that turn so fast along the rod (mesh.frame_rate_bound: -rod_twist_turns, a
    helix's pitch, an imperfection) that no mesh of MAX_ELEMENTS_NEEDED elements holds them:
    refused before the mesh is made (their angles overflow it).  Returns whether the mesh may
    be made."""
    from rodsnes.model.mesh import frame_rate_bound
    r = scene.rod
    rate = frame_rate_bound(r, scene.bc)
    need = rate * r.length / MAX_ELEMENT_TURN
    if need <= MAX_ELEMENTS_NEEDED:
        return True
    twist = 2 * math.pi * abs(r.twist_turns) / r.length
    if twist >= 0.5 * rate or not math.isfinite(twist):
        what, opts = _show("-rod_twist_turns", r.twist_turns), (O.rod_twist_turns,)
    else:
        what, opts = "the %s rod's shape" % r.shape, (O.rod_shape,)
    fail("%s: the frames turn so fast along the rod that the rotation interpolation's %.0f "
         "degrees an element at most would take %s elements (more than %.0e); use fewer turns"
         % (what, math.degrees(MAX_ELEMENT_TURN),
            "%.3g" % need if math.isfinite(need) else "infinitely many", MAX_ELEMENTS_NEEDED),
         *opts)
    return False


def _check_element_turns(scene, mesh, fail):
    """Elements across which the frames turn by MAX_ELEMENT_TURN or more: in the reference
    shape (a ring, a helix, -rod_twist_turns) or, certainly, under the loads."""
    from rodsnes.model.mesh import element_turns
    r = scene.rod
    ref = float(element_turns(mesh, r, scene.bc).max())
    load, cause, opt = _load_turn_per_element(scene)
    turn = max(ref, load)
    if turn < MAX_ELEMENT_TURN:
        return
    need = math.floor(r.nelem * turn / MAX_ELEMENT_TURN) + 1
    if load > ref:
        what = "%s turns the frames by at least %.4g degrees per element" % (cause,
                                                                              math.degrees(load))
        opts = (O.rod_nelem, opt)
    else:
        what = "the frames of the %s%s turn by %.4g degrees across an element" % (
            "closed ring" if r.closed else "%s rod" % r.shape,
            " with -rod_twist_turns %g" % r.twist_turns if r.twist_turns else "",
            math.degrees(ref))
        opts = (O.rod_nelem, O.rod_shape)
    fail("%s: %s, which the rotation interpolation cannot represent (below %.0f degrees); use "
         "-rod_nelem %s or more" % (_show("-rod_nelem", r.nelem), what,
                                    math.degrees(MAX_ELEMENT_TURN), _count(need)), *opts)


def _check_planar(scene, mesh, fail):
    """-rod_planar on for a scene that is not planar (model/plane.py: which part leaves the
    plane)."""
    if scene.rod.planar != "on":
        return
    from rodsnes.model.plane import detect, refusal
    plane, why = detect(scene, mesh)
    if plane is None:
        fail(refusal(why), O.rod_planar)


def check_solvable(scene, memory="machine"):
    """Raise SceneError if the scene, valid option by option, cannot be solved as given: a
    mesh too large for the machine (``memory`` in bytes, "machine": this one's, None: no
    limit), a stiffness that under- or overflows or a rod too slender for double precision, a
    mechanism (pinned and free ends under load), an imperfection that is not small, contact
    that can never happen or always happens, elements too long for contact, and elements whose
    frames turn by MAX_ELEMENT_TURN or more (rings of one or two elements, twisted or bent
    rods on too few elements).  Every message names the options and the smallest fix."""
    from rodsnes.model.mesh import build_mesh
    msgs, opts = [], []

    def fail(msg, *options):
        msgs.append(msg)
        opts.extend(o.flag for o in options)

    if _check_memory(scene, fail, physical_memory() if memory == "machine" else memory):
        _check_stiffness(scene, fail)
        _check_supports(scene, fail)
        _check_tolerances(scene, fail)
        _check_imperfection(scene, fail)
        _check_contact_reach(scene, fail)
        _check_contact_mesh(scene, fail)
        _check_contact_penalty(scene, fail)
        if _check_frame_turns(scene, fail):
            mesh = build_mesh(scene.rod, scene.bc)
            _check_element_turns(scene, mesh, fail)
            _check_sliding_end(scene, mesh, fail)
            _check_planar(scene, mesh, fail)
    if msgs:
        raise SceneError("\n".join(msgs), opts)


# ----------------------------------------------------------------------------
# Options that do nothing in this scene (warnings, as PETSc's -options_left)
# ----------------------------------------------------------------------------
_PATH_ONLY = {"load_max_it": "minimize", "load_predictor": "newton",
              "load_stagnation_its": "newton", "load_retraction": "newton",
              # the minimisation counts the inertia of every step anyway
              "stability": "newton"}
"""Options read by one load path only (-load_path, run.path)."""


def _idle_reasons(scene, options, path):
    """(option, why it does nothing) for every option given that this scene does not use."""
    r, c, ld = scene.rod, scene.contact, scene.loads
    given = set(scene.given)
    out = []
    if r.shape not in ("arc", "circle"):
        out += [(o, "it shapes an arc or a circle (-rod_shape arc), and this rod is %s" % r.shape)
                for o in (O.rod_arc_radius, O.rod_arc_angle)]
    if r.shape != "helix":
        out += [(o, "it shapes a helix (-rod_shape helix), and this rod is %s" % r.shape)
                for o in (O.rod_helix_radius, O.rod_helix_pitch)]
    if not r.closed:
        out.append((O.rod_closed_gauge, "it holds a closed ring, and this rod is open"))
    if not c.enabled:
        out += [(o, "self-contact is off (add -contact)") for o in OPTIONS
                if o.section == "contact" and o is not O.contact]
    elif c.model != "potential":
        out.append((O.contact_wall, "the wall is the pair potential's (-contact_model "
                                    "potential), and this run's contact law is %s" % c.model))
    if not bool(options.getBool("load_arclength", False)):
        out += [(o, "it acts with -load_arclength only")
                for o in (O.load_arclength_its, O.load_arclength_max_steps)]
    if not np.any(ld.end_force):
        out.append((O.load_end_force_follower, "there is no end force (-load_end_force)"))
    if c.enabled and path == "newton":
        out.append((O.load_retraction, "with contact the Newton steps are straight (the "
                                       "contact's move limits bound the straight move)"))
    search = options.getAll().get("snes_linesearch_type")     # (a peek: marks nothing used)
    if path == "newton" and search not in (None, "basic") and not c.enabled:
        out.append((O.load_retraction, "it acts with -snes_linesearch_type basic only, and this "
                                       "run's line search is %s" % search))
    direct = "every stiffness it would enter is given directly"
    for opt, value in ((O.rod_youngs, r.youngs), (O.rod_poisson, r.poisson),
                       (O.rod_shear, r.shear_modulus), (O.rod_shear_coefficient,
                                                        r.shear_coefficient)):
        if value is None:
            out.append((opt, direct + " (-rod_EA, -rod_GA, -rod_EI, -rod_GJ)"))
    if path is not None:
        out += [(getattr(O, n), "it acts on -load_path %s only, and this run's path is %s"
                 % (p, path)) for n, p in _PATH_ONLY.items() if p != path]
    return [(o, why) for o, why in out if o.name in given]


def unused_options(scene, options=None, path=None):
    """Warnings (one line each) for rodsnes options given that do nothing in this scene, e.g.
    -rod_arc_radius on a straight rod or -contact_penalty without -contact; ``path`` is the
    run's load path (run.path), for the options of one path only."""
    options = _default_options() if options is None else options
    lines = []
    for opt, why in _idle_reasons(scene, options, path):
        raw = options.getString(opt.name, "")
        shown = "%s = %s" % (opt.flag, raw.strip()) if raw and raw.strip() else opt.flag
        lines.append("%s does nothing: %s; drop it" % (shown, why))
    return lines


# ----------------------------------------------------------------------------
# The scene a result file was computed for (-restart compares it)
# ----------------------------------------------------------------------------
RECORD_OPTIONS = {
    "length": "-rod_length", "radius": "-rod_radius", "closed": "-rod_shape",
    "nelem": "-rod_nelem", "order": "-rod_order", "shape": "-rod_shape",
    "EA": "-rod_EA/-rod_youngs", "GA1": "-rod_GA/-rod_youngs", "GA2": "-rod_GA/-rod_youngs",
    "EI1": "-rod_EI/-rod_youngs", "EI2": "-rod_EI/-rod_youngs", "GJ": "-rod_GJ/-rod_youngs",
    "kappa0": "-rod_kappa0", "arc_radius": "-rod_arc_radius/-rod_arc_angle",
    "helix_radius": "-rod_helix_radius", "helix_pitch": "-rod_helix_pitch",
    "twist_turns": "-rod_twist_turns", "imperfection": "-rod_imperfection",
    "bc_start": "-bc_start", "bc_end": "-bc_end", "bc_end_turns": "-bc_end_turns",
    "end_force": "-load_end_force", "end_force_follower": "-load_end_force_follower",
    "end_moment": "-load_end_moment", "gravity": "-load_gravity",
    "load_twist_turns": "-load_twist_turns",
}
"""What a restart must share with the run it goes on from (the rod, its mesh, supports and
loads: the load factor of the stored state means these loads), and the options that set it.
Solver, contact and output settings may change between stages."""


def scene_record(scene):
    """The physical scene as a JSON-able dict of RECORD_OPTIONS' keys (stored in result.h5)."""
    r, bc, ld = scene.rod, scene.bc, scene.loads

    def vec(v):
        return None if v is None else [float(x) for x in v]

    return {"length": r.length, "radius": r.radius, "closed": bool(r.closed), "nelem": r.nelem,
            "order": r.order, "shape": r.shape, "EA": r.EA, "GA1": r.GA1, "GA2": r.GA2,
            "EI1": r.EI1, "EI2": r.EI2, "GJ": r.GJ, "kappa0": vec(r.kappa0),
            "arc_radius": r.arc_radius, "helix_radius": r.helix_radius,
            "helix_pitch": r.helix_pitch, "twist_turns": r.twist_turns,
            "imperfection": r.imperfection, "bc_start": bc.start, "bc_end": bc.end,
            "bc_end_turns": bc.end_turns, "end_force": vec(ld.end_force),
            "end_force_follower": bool(ld.end_force_follower), "end_moment": vec(ld.end_moment),
            "gravity": vec(ld.gravity), "load_twist_turns": ld.twist_turns}


def _same_value(a, b, rtol=1e-12):
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same_value(x, y, rtol) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, str) or isinstance(b, str):
        return a == b
    if a is None or b is None:
        return a is None and b is None
    return abs(float(a) - float(b)) <= rtol * max(abs(float(a)), abs(float(b)))


def _record_value(v):
    if isinstance(v, (list, tuple)):
        return ",".join(_fmt(float(x)) for x in v)
    if isinstance(v, float):
        return _fmt(v)
    return str(v)


def record_mismatches(stored, current):
    """Differences between two scene records (keys of either; a key missing from the stored
    record, written by an older rodsnes, is not compared): a list of 'name X there, Y here
    (-option)'."""
    out = []
    for key in RECORD_OPTIONS:
        if key not in stored or key not in current:
            continue
        if not _same_value(stored[key], current[key]):
            out.append("%s %s there, %s here (%s)" % (key, _record_value(stored[key]),
                                                      _record_value(current[key]),
                                                      RECORD_OPTIONS[key]))
    return out
