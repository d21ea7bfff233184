"""Every input gives the right result or a clear refusal (issue 29): table-driven.

A refusal is one line per problem on stderr, ``rodsnes: error: ...``, naming the option and
the fix, exit code 2, no traceback; an option that does nothing is a warning line,
``rodsnes: warning: ...``, and the run goes on; a run stopped by SIGINT/SIGTERM exits 128 +
the signal with summary.json marked interrupted.  Most runs are in-process (cli.main, PETSc
already running: the command line's options go into the cleared database); the start-up and
the signals are checked in subprocesses.
"""
import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from conftest import ROOT, clear_options
from rodsnes import cli
from rodsnes.io import results as output

CASES = os.path.join(ROOT, "cases")
MATT = ("-options_file", os.path.join(CASES, "mattiasson.opts"), "-quiet")
ROLLUP = ("-options_file", os.path.join(CASES, "rollup.opts"), "-quiet")
ROLLUP_CONTACT = ("-options_file", os.path.join(CASES, "rollup_contact.opts"), "-quiet")
MICHELL = ("-options_file", os.path.join(CASES, "michell.opts"), "-quiet")
EULER = ("-options_file", os.path.join(CASES, "euler.opts"), "-quiet")
TWO_TURNS = ("-options_file", os.path.join(CASES, "rollup_two_turns.opts"), "-quiet")
# a cantilever whose stiffnesses come from E and the radius (Mattiasson's lambda = 10)
CANTILEVER = ("-rod_length", "1", "-rod_radius", "0.01", "-rod_youngs", "1e6", "-rod_nelem", "8",
              "-load_end_force", "0,-0.0785398163397448,0", "-load_steps", "5", "-quiet")


def rodsnes(capsys, *args, out):
    """cli.main in-process on a cleared options database; (exit code, stdout, stderr)."""
    clear_options()
    try:
        rc = cli.main(["rodsnes", *map(str, args), "-output_dir", str(out)])
    finally:
        clear_options()
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def refused(capsys, tmp_path, args, expects, lines=1):
    rc, out, err = rodsnes(capsys, *args, out=tmp_path / "out")
    assert rc == 2, err
    errors = [l for l in err.splitlines() if l.strip()]
    assert errors and all(l.startswith("rodsnes: error: ") for l in errors), err
    assert len(errors) == lines, err
    for e in expects:
        assert e in err, err
    assert "Traceback" not in err and "PETSC ERROR" not in err
    assert not (tmp_path / "out" / "result.h5").exists()
    return err


def summary(d):
    return json.loads((d / "summary.json").read_text())


# ------------------------------------------------------------------------ refusals, in-process
REFUSALS = [
    # contact switched off (or always on) by its own radius or exclusion
    ("contact_radius_open", MATT + ("-contact", "-contact_radius", "0.4"),
     ["-contact_radius = 0.4", "pi x radius = 1.257 is not shorter than the rod (1)",
      "no two points of the rod can ever touch", "below 0.3183"]),
    ("contact_radius_standoff", MATT + ("-contact", "-contact_radius", "0.4",
                                        "-contact_standoff", "0.02"),
     ["-contact_radius = 0.4", "pi x radius x (1 + -contact_standoff 0.02) = 1.282 is not "
      "shorter than the rod (1)", "below 0.3121 (L / (pi (1 + -contact_standoff 0.02)))"]),
    ("contact_radius_ring", MICHELL + ("-contact", "-contact_radius", "0.2",
                                       "-contact_curvature", "0"),
     ["-contact_radius = 0.2", "not shorter than half the ring (0.5)", "below 0.1592"]),
    ("contact_exclusion_long", MATT + ("-contact", "-rod_nelem", "16", "-contact_radius", "0.02",
                                       "-contact_exclusion", "2"),
     ["-contact_exclusion = 2: not shorter than the rod (1)", "drop -contact"]),
    ("contact_exclusion_short", MATT + ("-contact", "-rod_nelem", "16", "-contact_radius", "0.02",
                                        "-contact_exclusion", "0.001"),
     ["-contact_exclusion = 0.001 with contact radius 0.02", "always closer",
      "use at least 0.04"]),
    ("contact_circle_thicker_than_bend", MICHELL + ("-contact", "-contact_radius", "0.2"),
     ["-rod_shape circle of radius 0.159155: the reference centreline bends to curvature"]),
    # meshes that cannot represent the scene
    ("ring_of_one", MICHELL + ("-rod_nelem", "1"),
     ["-rod_nelem = 1: the frames of the closed ring turn by 360 degrees across an element",
      "use -rod_nelem 3 or more"]),
    ("ring_of_two", MICHELL + ("-rod_nelem", "2"),
     ["turn by 180 degrees across an element", "use -rod_nelem 3 or more"]),
    ("ring_of_two_quartic", MICHELL + ("-rod_nelem", "2", "-rod_order", "4"),
     ["use -rod_nelem 3 or more"]),
    ("twisted_rod_two_elements", MATT + ("-rod_nelem", "2", "-rod_twist_turns", "1"),
     ["straight rod with -rod_twist_turns 1 turn by 180 degrees", "use -rod_nelem 3 or more"]),
    # whole turns between two nodes, which their frames alone do not show: a ring twisted by
    # 73 turns on 24 elements was solved as one twisted by 1 turn (link 1, exit 0), a helix of
    # one turn a node interval as a straight rod, a ring on one linear element as unloaded
    ("ring_twisted_by_whole_turns_between_nodes",
     MICHELL + ("-rod_twist_turns", "73", "-load_twist_turns", "0", "-load_steps", "1"),
     ["-rod_nelem = 24: the frames of the closed ring with -rod_twist_turns 73 turn by 1095 "
      "degrees across an element", "use -rod_nelem 195 or more"]),
    ("helix_of_a_turn_a_node_interval",
     MATT + ("-rod_shape", "helix", "-rod_helix_radius", "0.005", "-rod_helix_pitch",
             "0.027370616927686796", "-rod_radius", "0.001", "-load_end_force", "0,0,0",
             "-load_gravity", "0,-1,0"),
     ["the frames of the helix rod turn by 1080 degrees across an element",
      "use -rod_nelem 65 or more"]),
    ("full_arc_on_one_linear_element",
     MATT + ("-rod_shape", "arc", "-rod_arc_angle", "360", "-rod_nelem", "1", "-rod_order", "1",
             "-load_end_force", "0,-1,0"),
     ["the frames of the arc rod turn by 360 degrees across an element",
      "use -rod_nelem 3 or more"]),
    ("twist_beyond_any_mesh", MATT + ("-rod_twist_turns", "1e300"),
     ["-rod_twist_turns = 1e+300: the frames turn so fast along the rod", "2.67e+300 elements",
      "use fewer turns"]),
    ("rollup_one_element", ROLLUP + ("-rod_nelem", "1"),
     ["-load_end_moment = 0,0,62.8319 turns the frames by at least 360 degrees per element",
      "use -rod_nelem 3 or more"]),
    ("end_turns_two_elements", MATT + ("-rod_nelem", "2", "-bc_end", "clamped",
                                       "-load_end_force", "0,0,0", "-bc_end_turns", "1"),
     ["-bc_end_turns = 1 turns the frames by at least 180 degrees", "use -rod_nelem 3"]),
    ("contact_coarse", ROLLUP_CONTACT + ("-rod_nelem", "8"),
     ["-rod_nelem = 8 with contact radius 0.1: elements of length 1.25 (12.5 contact radii)",
      "use -rod_nelem 13 or more"]),
    # failures that did not name their cause
    ("pinned_start_end_moment", MATT + ("-bc_start", "pinned", "-load_end_force", "0,0,0",
                                        "-load_end_moment", "0,0,1"),
     ["-load_end_moment = 0,0,1 with -bc_start pinned -bc_end free", "a mechanism",
      "nothing balances the end moment", "-bc_start clamped"]),
    ("pinned_start_force", MATT + ("-bc_start", "pinned"),
     ["-load_end_force = 0,-10,0 with -bc_start pinned -bc_end free", "a mechanism"]),
    ("pinned_end_gravity", MATT + ("-bc_start", "free", "-bc_end", "pinned", "-load_end_force",
                                   "0,0,0", "-load_gravity", "0,-1,0"),
     ["-load_gravity = 0,-1,0 with -bc_start free -bc_end pinned", "-bc_end clamped"]),
    # a sliding end's held directions: the rod stayed unloaded, exit 0
    ("sliding_end_lateral_force", MATT + ("-bc_end", "sliding"),
     ["-load_end_force = 0,-10,0 with -bc_end sliding", "slides along its tangent (x) alone",
      "the force's y component does nothing", "load it along x, or use -bc_end free"]),
    ("sliding_end_moment", MATT + ("-bc_end", "sliding", "-load_end_force", "0,0,0",
                                   "-load_end_moment", "0,0,5"),
     ["-load_end_moment = 0,0,5 with -bc_end sliding", "the moment does nothing"]),
    ("sliding_end_free_start", MATT + ("-bc_start", "free", "-bc_end", "sliding",
                                       "-load_end_force", "0,0,0", "-load_gravity", "-1,0,0"),
     ["-load_gravity = -1,0,0 with -bc_start free -bc_end sliding", "nothing holds the rod "
      "along x", "-bc_start clamped or pinned"]),
    # command-line words PETSc kept or dropped without a word (the run went on, exit 0)
    ("two_dash_option", MATT + ("--rod_nelem", "16"),
     ["'--rod_nelem': an option takes one dash (-rod_nelem)"]),
    ("stray_word", MATT + ("-load_end_force", "0,-10", ",0"),
     ["',0' is neither an option nor the value of the option before it",
      "a vector is written without spaces, e.g. 0,0,1"]),
    # an open arc of nearly a whole turn with contact: its ends start inside each other's tube
    ("arc_ends_overlap", ("-rod_length", "1", "-rod_radius", "0.01", "-rod_EA", "1e6",
                          "-rod_GA", "1e6", "-rod_EI", "1", "-rod_GJ", "1", "-rod_nelem", "64",
                          "-rod_shape", "arc", "-rod_arc_angle", "355", "-contact", "-quiet"),
     ["-rod_arc_angle = 355 with contact radius 0.01: the arc's ends start 0.0141 apart",
      "use an angle below 352.9 degrees (or -rod_shape circle -rod_closed for a ring)"]),
    # an absolute tolerance at the loads' size: the unloaded rod was accepted, exit 0
    ("snes_atol_at_load_size", MATT + ("-load_path", "newton", "-snes_atol", "1"),
     ["-snes_atol = 1: 0.0909 of the problem's force scale (11: EI/L^2 + loads)",
      "the first load step's unloaded rod already meets it", "use -snes_rtol",
      "an -snes_atol below 1.1e-05"]),
    # a relative tolerance at the loads' size: the unloaded rod was accepted on either path,
    # exit 0 (the tip unmoved, the error estimate 0)
    ("snes_rtol_at_load_size", MATT + ("-snes_rtol", "1"),
     ["-snes_rtol = 1: every load step holds the residual to -snes_rtol x the problem's force "
      "scale", "the first load step's unloaded rod already meets it",
      "use a -snes_rtol from 0 to 1e-06 (default 1e-10)"]),
    ("snes_rtol_newton_inf", MATT + ("-load_path", "newton", "-snes_rtol", "inf"),
     ["-snes_rtol = inf: every load step holds", "use a -snes_rtol from 0 to 1e-06"]),
    ("snes_rtol_nan", MATT + ("-snes_rtol", "nan"),
     ["-snes_rtol = nan: not a tolerance; use a -snes_rtol from 0 to 1e-06"]),
    # a penalty out of all proportion to the rod: 1e20 on michell_contact stalled the
    # minimiser (|g| and E unchanged over minutes)
    ("penalty_beyond_proportion",
     ("-options_file", os.path.join(CASES, "michell_contact.opts"), "-quiet",
      "-contact_penalty", "1e20"),
     ["-contact_penalty = 1e+20: 2.55e+13 times the default 3.93e+06",
      "give a penalty within a factor 1e+06 of the default, or leave it out"]),
    # load steps no run gets through: 1e9 on the Newton path ran for months, 1e300 below the
    # load's resolution (200 steps with -load_min_step 0.01 stay fine, as 2e6 on the default
    # path, whose increment grows)
    ("load_steps_beyond_any_run", MATT + ("-load_steps", "1e9"),
     ["-load_steps = 1e9: increments of 1e-09", "use at most 1e+07 load steps"]),
    ("imperfection_ten_lengths", EULER + ("-rod_imperfection", "10"),
     ["-rod_imperfection = 10 with -rod_length = 1", "10.1 times as long as the rod",
      "use |a| below 0.417"]),
    ("radius_underflow", CANTILEVER + ("-rod_radius", "1e-90"),
     ["-rod_radius = 1e-90 with -rod_youngs = 1e+06: in double precision the stiffnesses "
      "EI1 = E pi r^4/4, EI2 = E pi r^4/4, GJ = G pi r^4/2 underflow to 0", "no usable stiffness",
      "give -rod_EA, -rod_GA, -rod_EI, -rod_GJ directly"]),
    ("radius_subnormal", CANTILEVER + ("-rod_radius", "1e-80"),
     ["-rod_radius = 1e-80", "are subnormal (below 2.23e-308)"]),
    ("stiffness_subnormal", MATT + ("-rod_EI", "1e-320"),
     ["-rod_EI = 1e-320: in double precision the stiffnesses EI1, EI2 are subnormal"]),
    ("forces_too_small_to_square", MATT + ("-rod_EA", "1e-194", "-rod_GA", "1e-194", "-rod_EI",
                                          "1e-200", "-rod_GJ", "1e-200", "-load_end_force",
                                          "0,-1e-199,0"),
     ["the forces of the problem (EI/L^2 + loads = 1.1e-199", "outside 1e-140 .. 1e+140"]),
    ("forces_too_large_to_square", CANTILEVER + ("-rod_youngs", "1e300", "-rod_radius", "0.4"),
     ["the forces of the problem (EI/L^2 + loads = 2.01e+298, most of it from the bending "
      "stiffness (-rod_youngs, -rod_radius))"]),
    # the largest term named: -load_twist_turns 1e300 was blamed on -rod_EI and the units
    ("forces_of_a_twist_load", MATT + ("-load_twist_turns", "1e300"),
     ["the forces of the problem (EI/L^2 + loads = 6.28e+300, most of it from "
      "-load_twist_turns = 1e+300)", "or fewer turns"]),
    ("too_slender", CANTILEVER + ("-rod_radius", "1e-7", "-load_end_force", "0,-7.85e-22,0"),
     ["-rod_radius = 1e-07", "the residual's roundoff", "cannot resolve the equilibrium"]),
    ("nelem_1e9", MATT + ("-rod_nelem", "1e9"),
     ["-rod_nelem = 1000000000: 3e+09 nodes need about 30 TB of memory",
      "use -rod_nelem"]),
    # PETSc options that used to end in a raw PETSc error block or a traceback
    ("ksp_type", MATT + ("-ksp_type", "nonsense"),
     ["-ksp_type nonsense: not a PETSc Krylov method (KSP)", "preonly"]),
    ("ksp_type_close", MATT + ("-ksp_type", "gmrez"), ["did you mean gmres"]),
    ("snes_type", MATT + ("-snes_type", "bogus"),
     ["-snes_type bogus: not a PETSc nonlinear solver (SNES)", "newtonls"]),
    ("pc_type", MATT + ("-pc_type", "lux"), ["-pc_type lux", "did you mean lu"]),
    ("sub_pc_type", MATT + ("-sub_pc_type", "iluu"), ["-sub_pc_type iluu", "did you mean ilu"]),
    ("linesearch", MATT + ("-snes_linesearch_type", "bts"),
     ["-snes_linesearch_type bts: not a PETSc SNES line search", "did you mean bt"]),
    ("snes_rtol", MATT + ("-snes_rtol", "abc"),
     ["-snes_rtol abc: not a number", "-snes_rtol 1e-8"]),
    ("ksp_max_it", MATT + ("-ksp_max_it", "many"), ["-ksp_max_it many: not a number"]),
    ("mumps_icntl", MATT + ("-mat_mumps_icntl_14", "abc"), ["-mat_mumps_icntl_14 abc: not a number"]),
    ("snes_max_it_real", MATT + ("-load_path", "newton", "-snes_max_it", "1.5"),
     ["-snes_max_it 1.5: not an integer"]),
    ("snes_bool", MATT + ("-load_path", "newton", "-snes_ksp_ew", "maybe"),
     ["-snes_ksp_ew maybe: not true or false"]),
    ("solver_package_unknown", MATT + ("-load_path", "newton", "-pc_factor_mat_solver_type",
                                       "nosuch"),
     ["-pc_factor_mat_solver_type nosuch: not a PETSc LU/Cholesky package"]),
    ("solver_package_unfit", MATT + ("-load_path", "newton", "-pc_factor_mat_solver_type",
                                     "superlu"),
     ["-pc_factor_mat_solver_type superlu: superlu cannot factor rodsnes' Jacobian",
      "use petsc (the default) or mumps"]),
    ("mat_type_unfit", MATT + ("-mat_type", "sbaij"),
     ["-mat_type sbaij: the LU of petsc cannot factor the Jacobian as seqsbaij",
      "leave -mat_type out", "or use -pc_factor_mat_solver_type mumps"]),
    ("mat_type_mpi_one_rank", MATT + ("-mat_type", "mpibaij"),
     ["-mat_type mpibaij: the LU of petsc cannot factor the Jacobian as mpibaij"]),
    ("mat_type_unfit_mumps", MATT + ("-mat_type", "sbaij", "-pc_factor_mat_solver_type", "mumps"),
     ["-mat_type sbaij: the LU of mumps cannot factor", "leave -mat_type out (rodsnes' block "
      "matrix, which petsc and mumps factor)"]),
    ("solver_package_unfit_with_mat_type", MATT + ("-mat_type", "baij",
                                                   "-pc_factor_mat_solver_type", "superlu"),
     ["-pc_factor_mat_solver_type superlu: superlu cannot factor", "use petsc (the default) or "
      "mumps"]),
    # the prefixed solvers are checked as the Newton step's is (they fell back to another step
    # in silence, or failed the run later as if the scene had no equilibrium)
    ("planar_package_unfit", MATT + ("-planar_pc_factor_mat_solver_type", "superlu"),
     ["-planar_pc_factor_mat_solver_type superlu: superlu cannot factor", "use petsc"]),
    ("estimate_package_unfit", MATT + ("-estimate_pc_factor_mat_solver_type", "superlu"),
     ["-estimate_pc_factor_mat_solver_type superlu: superlu cannot factor"]),
    ("stability_package_unfit", MATT + ("-stability_pc_factor_mat_solver_type", "petsc"),
     ["-stability_pc_factor_mat_solver_type petsc: the stability count takes the negative "
      "pivots from MUMPS's LDL^T; use mumps"]),
    ("planar_stability_pc_unfit", MATT + ("-planar_stability_pc_type", "lu"),
     ["-planar_stability_pc_type lu: the stability count factors the Hessian by an LDL^T",
      "use cholesky"]),
    # a Cholesky of the Newton step's tangent (not symmetric): PETSc's reads one triangle
    ("newton_cholesky", MATT + ("-pc_type", "cholesky"),
     ["-pc_type cholesky: the Newton step's tangent is not symmetric", "use lu (the default)"]),
    ("planar_icc_direct", MATT + ("-planar_pc_type", "icc"),
     ["-planar_pc_type icc: the Newton step's tangent is not symmetric"]),
    ("interior_package", MATT + ("-interior_pc_factor_mat_solver_type", "petsc"),
     ["-interior_pc_factor_mat_solver_type petsc: where contact fills the Jacobian",
      "MUMPS's LU", "leave -interior_pc_factor_mat_solver_type out"]),
    ("shift_type_unfit", MATT + ("-pc_factor_shift_type", "nonzero"),
     ["-pc_factor_shift_type nonzero: the LU of rodsnes' block matrix", "use inblocks"]),
    ("ordering_unknown", MATT + ("-pc_factor_mat_ordering_type", "foo"),
     ["-pc_factor_mat_ordering_type foo: not a type PETSc knows"]),
    ("pc_needs_aij", MATT + ("-rod_planar", "off", "-ksp_type", "gmres", "-pc_type", "gamg"),
     ["-pc_type gamg: it needs a matrix operation (creategraph)", "add -mat_type aij"]),
    ("pc_unfit", MATT + ("-load_path", "newton", "-ksp_type", "gmres", "-pc_type", "ml"),
     ["PETSc: ", "ML"]),
    # preonly (the default) with a preconditioner that does not factor: no Newton step at all
    # (the cantilever with -pc_type jacobi: 9680 iterations, then a failed path)
    # a viewer's file PETSc would open at exit, printing its error block after the results
    ("log_view_missing_directory", MATT + ("-log_view", ":/nonexistent_rodsnes_dir/lv.txt"),
     ["-log_view :/nonexistent_rodsnes_dir/lv.txt: its file's directory "
      "/nonexistent_rodsnes_dir does not exist"]),
    ("preonly_jacobi", MATT + ("-pc_type", "jacobi"),
     ["-pc_type jacobi: with -ksp_type preonly (the default) the Newton step would be one "
      "application of it, not a solve", "an iterative -ksp_type (gmres) with it"]),
    ("planar_preonly_none", MATT + ("-planar_pc_type", "none"),
     ["-planar_pc_type none: with -planar_ksp_type preonly"]),
    ("estimate_preonly_ilu", MATT + ("-estimate_pc_type", "ilu"),
     ["-estimate_pc_type ilu: with -estimate_ksp_type preonly"]),
    # retired options say what replaced them
    ("retired_stability_switch", MATT + ("-stability", "-stability_switch", "0"),
     ["-stability_switch was retired with branch switching: conservative load steps are energy "
      "minimisations (-load_path minimize, the default), which end on stable equilibria; use "
      "-load_arclength to follow unstable branches"]),
    ("retired_stability_switch_restart", MATT + ("-stability_switch_restart",),
     ["-stability_switch_restart was retired with branch switching",
      "from a restart state too", "-load_arclength"]),
    ("retired_stability_perturbation", MATT + ("-stability_perturbation", "0.1"),
     ["-stability_perturbation was retired with branch switching",
      "leave an unstable equilibrium along negative curvature"]),
    ("retired_stability_relax_max_it", MATT + ("-stability_relax_max_it", "600"),
     ["-stability_relax_max_it was retired with the relaxation of branch switching",
      "-load_max_it"]),
    ("retired_stability_jump_overshoot", MATT + ("-stability_jump_overshoot", "1e-3"),
     ["-stability_jump_overshoot was retired with the fold jump", "go past a fold by descent",
      "-load_arclength to follow the branch around it"]),
    ("retired_load_damped_its", MATT + ("-load_path", "newton", "-load_damped_its", "40"),
     ["-load_damped_its was retired with the Levenberg-Marquardt fallback",
      "on -load_path newton a failed step is cut back (-load_max_cutbacks, -load_min_step)"]),
]


@pytest.mark.parametrize("args, expects", [r[1:] for r in REFUSALS], ids=[r[0] for r in REFUSALS])
def test_refused_before_the_solve(capsys, tmp_path, args, expects):
    refused(capsys, tmp_path, args, expects)


def test_independent_problems_are_all_listed(capsys, tmp_path):
    refused(capsys, tmp_path, MATT + ("-contact", "-contact_exclusion", "2"),
            ["-contact_exclusion = 2", "-rod_nelem = 8 with contact radius 0.01"], lines=2)
    refused(capsys, tmp_path, MATT + ("-stability_switch", "1", "-load_damped_its", "3"),
            ["-stability_switch was retired", "-load_damped_its was retired"], lines=2)


def test_solvable_neighbours_of_the_refusals_are_accepted():
    """The smallest meshes and largest values the refusals name are accepted."""
    from conftest import set_options
    from rodsnes.io.scene import check_solvable, read_scene
    for case, kw in [("michell", dict(rod_nelem=3)), ("michell", dict(rod_nelem=3, rod_order=1)),
                     ("rollup", dict(rod_nelem=3)), ("rollup_contact", dict(rod_nelem=13)),
                     ("euler", dict(rod_imperfection=0.4)), ("plectoneme", {}),
                     ("michell_contact", {}), ("bench_coil", {}), ("helix", {}),
                     ("mattiasson", dict(bc_start="pinned", bc_end="pinned",
                                         load_end_force="0,0,0", load_gravity="0,-1,0")),
                     ("mattiasson", dict(contact=True, rod_nelem=13, contact_radius=0.3))]:
        check_solvable(read_scene(["rodsnes"], set_options(case, **kw)))


# ------------------------------------------------------------------------ options files
def test_options_files(capsys, tmp_path):
    bad = {"garbage.opts": ("-rod_length 1\ngarbage line\n",
                            "line 2 'garbage line': 'garbage' is not an option"),
           "two.opts": ("-rod_length 1 -rod_radius 0.01\n", "two options on one line"),
           "extra.opts": ("-load_end_force 0, -10, 0\n", "has more than one value"),
           "dash.opts": ("-\n", "'-' is not an option")}
    for name, (text, expect) in bad.items():
        (tmp_path / name).write_text(text)
        refused(capsys, tmp_path, ("-options_file", tmp_path / name),
                [f"-options_file {tmp_path / name}: {expect}" if "line 2" in expect else expect,
                 "'#' starts a comment"])
    refused(capsys, tmp_path, ("-options_file", tmp_path / "missing.opts"),
            [f"-options_file {tmp_path / 'missing.opts'}: no such file"])
    refused(capsys, tmp_path, ("-options_file", tmp_path), ["is a directory"])
    refused(capsys, tmp_path, MATT + ("-options_file",), ["-options_file needs a file name"])
    # files they include: a missing one, and a loop (PETSc followed it until its stack
    # overflowed: signal 11, no message)
    (tmp_path / "self.opts").write_text(f"-options_file {tmp_path / 'self.opts'}\n")
    refused(capsys, tmp_path, ("-options_file", tmp_path / "self.opts"),
            [f"includes {tmp_path / 'self.opts'}, which includes this file again"])
    (tmp_path / "a.opts").write_text(f"-options_file {tmp_path / 'b.opts'}\n")
    (tmp_path / "b.opts").write_text(f"-options_file {tmp_path / 'a.opts'}\n")
    refused(capsys, tmp_path, ("-options_file", tmp_path / "a.opts"),
            [f"{tmp_path / 'b.opts'}: line 1 '-options_file {tmp_path / 'a.opts'}'",
             "an options file must not include itself"])
    (tmp_path / "nested.opts").write_text(f"-options_file {tmp_path / 'gone.opts'}\n")
    refused(capsys, tmp_path, ("-options_file", tmp_path / "nested.opts"),
            [f"{tmp_path / 'gone.opts'}: no such file"])
    # negative values, comments and blank lines are fine: the scene then judges the value
    (tmp_path / "neg.opts").write_text("# comment\n\n-rod_length -1   # negative\n")
    refused(capsys, tmp_path, ("-options_file", tmp_path / "neg.opts"),
            ["-rod_length = -1: must be > 0"])


# ------------------------------------------------------------------------ output directory
def test_output_directory_that_cannot_take_the_results(capsys, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out, expect in [(afile, "is a file, not a directory"),
                        (afile / "sub", f"lies under {afile}, which is a file"),
                        ("/proc/rodsnes_out", "cannot be written")]:
        clear_options()
        rc = cli.main(["rodsnes", *MATT, "-output_dir", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and f"rodsnes: error: -output_dir {out}: {expect}" in err, err
        assert len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------------ silent wrong answers
def _tip(d):
    return np.array(summary(d)["tip_position"])


@pytest.mark.parametrize("path", ["newton", "auto"])
def test_a_rescaled_problem_gives_the_same_dimensionless_tip(capsys, tmp_path, path):
    """Mattiasson's cantilever and its twin with every stiffness and the load x 1e-12 (and
    x 1e12): the same tip to 1e-8 (before: the tiny twin was accepted at iteration 0, unloaded,
    because |F| was below an absolute tolerance)."""
    rc, _, err = rodsnes(capsys, *MATT, "-load_path", path, out=tmp_path / "ref")
    assert rc == 0, err
    ref = _tip(tmp_path / "ref")
    assert abs(ref[1] + 0.8106) < 1e-3              # the elastica: v/L = 0.810609
    for s in (1e-12, 1e12):
        d = tmp_path / f"s{s:g}"
        rc, _, err = rodsnes(capsys, *MATT, "-load_path", path, "-rod_EA", 1e6 * s,
                             "-rod_GA", 1e6 * s, "-rod_EI", s, "-rod_GJ", s,
                             "-load_end_force", f"0,{-10 * s!r},0", out=d)
        assert rc == 0, err
        assert np.abs(_tip(d) - ref).max() < 1e-8
        assert summary(d)["newton_iterations"] > 5


def test_a_rescaled_youngs_modulus_gives_the_same_tip(capsys, tmp_path):
    """The same through -rod_youngs (stiffnesses from E and the radius): E and the load x 1e-12."""
    rc, _, err = rodsnes(capsys, *CANTILEVER, "-load_path", "newton", out=tmp_path / "a")
    assert rc == 0 and "warning" not in err, err
    rc, _, err = rodsnes(capsys, *CANTILEVER, "-load_path", "newton", "-rod_youngs", "1e-6",
                         "-load_end_force", f"0,{-0.0785398163397448e-12!r},0",
                         out=tmp_path / "b")
    assert rc == 0, err
    assert np.abs(_tip(tmp_path / "a") - _tip(tmp_path / "b")).max() < 1e-8
    assert abs(_tip(tmp_path / "a")[1] + 0.8106) < 1e-3


# ------------------------------------------------------------------------ restart
@pytest.fixture
def first_run(capsys, tmp_path):
    d = tmp_path / "first"
    rc, _, err = rodsnes(capsys, *MATT, "-load_steps", "4", "-load_stop", "0.5", out=d)
    assert rc == 0, err
    return d


RESTART_MISMATCHES = [
    (("-rod_length", "2"), "length 1 there, 2 here (-rod_length)"),
    (("-rod_radius", "0.02"), "radius 0.01 there, 0.02 here (-rod_radius)"),
    (("-rod_EI", "2"), "EI1 1 there, 2 here (-rod_EI/-rod_youngs)"),
    (("-load_end_force", "0,-5,0"), "end_force 0,-10,0 there, 0,-5,0 here (-load_end_force)"),
    (("-rod_imperfection", "0.001"), "imperfection 0 there, 0.001 here"),
    (("-rod_nelem", "16"), "nelem 8 there, 16 here (-rod_nelem)"),
]


@pytest.mark.parametrize("change, expect", RESTART_MISMATCHES,
                         ids=[c[0][0] for c in RESTART_MISMATCHES])
def test_a_restart_from_another_scene_is_refused(capsys, tmp_path, first_run, change, expect):
    refused(capsys, tmp_path, MATT + ("-load_steps", "4", "-restart", first_run) + change,
            [f"-restart {first_run}: it holds a run of another scene", expect,
             "drop -restart to start afresh"])


def test_a_restart_of_another_case_with_the_same_nodes_is_refused(capsys, tmp_path):
    """Euler's column and the two-turn roll-up: both L = 1, radius 0.01, 16 cubic elements."""
    d = tmp_path / "euler"
    rc, _, err = rodsnes(capsys, *EULER, "-load_steps", "2", "-load_stop", "0.5", out=d)
    assert rc == 0, err
    err = refused(capsys, tmp_path, TWO_TURNS + ("-restart", d), ["EI1 1 there, 2 here"])
    assert "end_moment 0,0,0 there" in err
    # a file from before the scene record: the case name must agree
    with h5py.File(d / "result.h5", "r+") as f:
        del f.attrs["scene"]
    refused(capsys, tmp_path, TWO_TURNS + ("-restart", d),
            ["case euler there, rollup_two_turns here"])


def test_a_restart_with_other_solver_settings_goes_on(capsys, tmp_path, first_run):
    rc, _, err = rodsnes(capsys, *MATT, "-load_steps", "4", "-restart", first_run,
                         "-snes_rtol", "1e-9", "-load_path", "newton", out=tmp_path / "next")
    assert rc == 0, err
    s = summary(tmp_path / "next")
    assert s["converged"] and s["load"] == 1.0


def test_restart_directories_without_a_readable_run(capsys, tmp_path, first_run):
    empty = tmp_path / "empty"
    empty.mkdir()
    refused(capsys, tmp_path, MATT + ("-restart", empty),
            [f"-restart {empty}: holds no result.h5"])
    afile = tmp_path / "afile"
    afile.write_text("x")
    refused(capsys, tmp_path, MATT + ("-restart", afile), [f"-restart {afile}: not a directory"])
    cut = tmp_path / "cut"
    cut.mkdir()
    data = (first_run / "result.h5").read_bytes()
    (cut / "result.h5").write_bytes(data[: len(data) // 2])
    t0 = time.perf_counter()
    refused(capsys, tmp_path, MATT + ("-restart", cut),
            [f"-restart {cut}: {cut / 'result.h5'} cannot be read", "truncated file",
             "cut short or damaged"])
    assert time.perf_counter() - t0 < 3.0            # no waiting for a writer that is not there
    nostep = tmp_path / "nostep"
    output.ResultWriter(nostep, None, 25, {"case_name": "mattiasson", "closed": False,
                                           "length": 1.0, "radius": 0.01, "nelem": 8,
                                           "order": 3}).close()
    refused(capsys, tmp_path, MATT + ("-restart", nostep), ["no complete step in the file"])


# ------------------------------------------------------------------------ options that do nothing
WARNINGS = [
    ("arc_radius_on_straight", MATT + ("-rod_arc_radius", "0.5"),
     "-rod_arc_radius = 0.5 does nothing: it shapes an arc or a circle (-rod_shape arc), and "
     "this rod is straight; drop it"),
    ("helix_pitch_on_straight", MATT + ("-rod_helix_pitch", "0.1"),
     "-rod_helix_pitch = 0.1 does nothing: it shapes a helix"),
    ("penalty_without_contact", MATT + ("-contact_penalty", "1e4"),
     "-contact_penalty = 1e4 does nothing: self-contact is off (add -contact)"),
    ("youngs_with_direct_stiffness", MATT + ("-rod_youngs", "2e6"),
     "-rod_youngs = 2e6 does nothing: every stiffness it would enter is given directly"),
    ("newton_option_on_the_minimising_path", MATT + ("-load_stagnation_its", "5"),
     "-load_stagnation_its = 5 does nothing: it acts on -load_path newton only"),
    ("arclength_option", MATT + ("-load_arclength_its", "5"),
     "-load_arclength_its = 5 does nothing: it acts with -load_arclength only"),
    ("follower_without_force", ROLLUP + ("-load_end_force_follower",),
     "-load_end_force_follower does nothing: there is no end force"),
    ("wall_with_the_closest_point_law", ROLLUP_CONTACT + ("-contact_model", "projection",
                                                         "-contact_wall", "0"),
     "-contact_wall = 0 does nothing: the wall is the pair potential's (-contact_model "
     "potential), and this run's contact law is projection; drop it"),
    ("gauge_on_open_rod", MATT + ("-rod_closed_gauge", "0"),
     "-rod_closed_gauge = 0 does nothing: it holds a closed ring"),
    ("misspelt_petsc_option", MATT + ("-snes_monitr",),
     "option -snes_monitr was not used: did you mean -snes_monitor?"),
    ("misspelt_ksp_option", MATT + ("-load_path", "newton", "-ksp_rtoll", "1e-8"),
     "option -ksp_rtoll 1e-8 was not used: did you mean -ksp_rtol?"),
    ("newton_option_on_the_minimising_path", MATT + ("-load_path", "minimize",
                                                     "-snes_linesearch_type", "bt"),
     "option -snes_linesearch_type bt was not used (nothing in this run reads it"),
    ("minimiser_option_on_the_newton_path", MATT + ("-load_path", "newton", "-load_max_it", "50"),
     "-load_max_it = 50 does nothing: it acts on -load_path minimize only"),
    ("view_read_after_the_solve", MATT + ("-load_path", "minimize", "-snes_view"),
     "option -snes_view was not used"),
    ("solver_this_run_does_not_make", MATT + ("-interior_mat_mumps_icntl_14", "80"),
     "option -interior_mat_mumps_icntl_14 80 was not used (the -interior_ solver runs on "
     "several ranks where contact fills the Jacobian, MUMPS's LU of each rank's stretch: this "
     "run made none)"),
    ("option_of_a_solver_this_run_makes", MATT + ("-planar_mat_mumps_icntl_14", "80"),
     "option -planar_mat_mumps_icntl_14 80 was not used (this run's -planar_ solver does not "
     "read it: not an option of its kind of solver)"),
    ("misspelt_option_of_a_solver_this_run_makes", MATT + ("-estimate_snes_max_iy", "3"),
     "option -estimate_snes_max_iy 3 was not used: did you mean -estimate_snes_max_it?"),
    ("misspelt_in_plane_ksp_option", MATT + ("-planar_ksp_typ", "gmres"),
     "option -planar_ksp_typ gmres was not used: did you mean -planar_ksp_type?"),
    ("retraction_on_the_minimising_path", MATT + ("-load_retraction", "1"),
     "-load_retraction = 1 does nothing: it acts on -load_path newton only"),
    ("retraction_with_contact", ROLLUP_CONTACT + ("-load_retraction", "1"),
     "-load_retraction = 1 does nothing: with contact the Newton steps are straight"),
]


@pytest.mark.parametrize("args, expect", [w[1:] for w in WARNINGS], ids=[w[0] for w in WARNINGS])
def test_an_option_that_does_nothing_is_reported(capsys, tmp_path, args, expect):
    rc, out, err = rodsnes(capsys, *args, "-load_stop", "0.2", "-load_steps", "5",
                           out=tmp_path / "out")
    assert rc == 0, err
    warnings = [l for l in err.splitlines() if l.strip()]
    assert len(warnings) == 1 and warnings[0].startswith("rodsnes: warning: "), err
    assert expect in err, err


def test_options_that_act_are_not_reported(capsys, tmp_path):
    rc, _, err = rodsnes(capsys, *MATT, "-load_path", "newton", "-snes_view", "-ksp_view",
                         "-snes_converged_reason", "-snes_rtol", "1e-9", "-load_stop", "0.2",
                         out=tmp_path / "out")
    assert rc == 0 and "warning" not in err, err
    rc, _, err = rodsnes(capsys, *MICHELL, "-load_stop", "0.04", out=tmp_path / "ring")
    assert rc == 0 and "warning" not in err, err          # -bc_start free on a ring is what it is
    # rodsnes' own solvers read their options during the run (the planar stability count's
    # LDL^T and the planar step at the first load step, the error estimate after the last)
    rc, _, err = rodsnes(capsys, *MATT, "-estimate_pc_factor_mat_solver_type", "mumps",
                         "-planar_stability_mat_mumps_icntl_14", "80", "-planar_ksp_type",
                         "preonly", "-load_stop", "0.2", out=tmp_path / "estimate")
    assert rc == 0 and "warning" not in err, err
    # the 3-D stability count's are read where it runs, not by a planar run that stays planar
    rc, _, err = rodsnes(capsys, *MATT, "-stability_mat_mumps_icntl_14", "80",
                         "-load_stop", "0.2", out=tmp_path / "planar")
    assert rc == 0 and "-stability_mat_mumps_icntl_14 80 was not used" in err, err
    assert "this run's stability count takes -planar_stability_mat_mumps_icntl_14" in err, err
    rc, _, err = rodsnes(capsys, *MATT, "-stability_mat_mumps_icntl_14", "80", "-rod_planar",
                         "off", "-load_stop", "0.2", out=tmp_path / "3d")
    assert rc == 0 and "warning" not in err, err


# ------------------------------------------------------------------------ unstable ends
EULER_LOUD = ("-options_file", os.path.join(CASES, "euler.opts"), "-stability",
              "-rod_imperfection", "0", "-load_steps", "4")


@pytest.mark.parametrize("asked", [("-load_path", "newton"), ("-load_arclength",)],
                         ids=["newton", "arclength"])
def test_an_unstable_end_asked_for_converges_and_says_so(capsys, tmp_path, asked):
    """The perfect Euler column at 1.2 P_cr on -load_path newton (a zero of the residual, which
    is what was asked for) or with -load_arclength (unstable branches followed on purpose) ends
    on the straight, unstable column: exit 0, the last line says unstable, summary.json
    converged and stable false."""
    d = tmp_path / "out"
    rc, out, err = rodsnes(capsys, *EULER_LOUD, *asked, out=d)
    assert rc == 0, err
    last = out.strip().splitlines()[-1]
    assert last.startswith("converged to an unstable equilibrium at load 1.000000 (2 negative "
                           "eigenvalues of the energy Hessian)"), last
    s = summary(d)
    assert s["converged"] is True and s["stable"] is False and s["negative_eigenvalues"] == 2


def test_a_newton_path_with_an_energy_counts_its_end(capsys, tmp_path):
    """-load_path newton without -stability on a conservative scene (the twisted ring past its
    threshold stays on the circle, a zero of the residual): its end is counted anyway, and the
    last line and summary.json say it is unstable (they said "converged", "stable" null)."""
    d = tmp_path / "out"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "michell.opts"),
                           "-rod_nelem", "12", "-load_path", "newton", out=d)
    assert rc == 0, err
    last = out.strip().splitlines()[-1]
    assert last.startswith("converged to an unstable equilibrium at load 1.000000"), last
    s = summary(d)
    assert s["stable"] is False and s["negative_eigenvalues"] > 0
    assert all("negative_eigenvalues" not in step for step in s["steps"][:-1])


def test_a_newton_path_end_count_says_stable_or_claims_nothing(capsys, tmp_path, monkeypatch):
    """The end count of a Newton path is recorded whatever it finds: none says "stable" (the
    Euler column below its buckling load, on a mesh of 12 elements or of 1500: the count is
    of H v = lambda M v, stability.neutral_shift, not of H's own eigenvalues, which shrink
    with h); a failed count (-1: a factorisation MUMPS could not make, taken for "unstable"
    before) leaves "stable" null and the line "converged"."""
    from rodsnes.solve.newton import NewtonSolver
    for nelem in ("12", "1500"):
        d = tmp_path / f"euler{nelem}"
        rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "euler.opts"),
                               "-rod_nelem", nelem, "-load_path", "newton", "-rod_planar", "off",
                               "-rod_error_estimate", "off", "-load_end_force", "-2.0,0,0",
                               "-load_steps", "2", out=d)
        assert rc == 0, err
        s = summary(d)
        assert s["stable"] is True and s["negative_eigenvalues"] == 0
        # and result.h5's last step has it (it was in summary.json only)
        with h5py.File(d / "result.h5", "r") as f:
            last = f["steps"][sorted(f["steps"])[-1]].attrs
            assert last["negative_eigenvalues"] == 0
        # the neutral band (EI/L^4): 0.01, widened by the Hessian's round-off at 1500
        # elements, which a note says
        coarse = "note: the stability count took eigenvalues" in out
        if nelem == "12":
            assert s["neutral_band"] == pytest.approx(0.01) and not coarse
        else:
            assert 0.1 < s["neutral_band"] < 0.2 and coarse, s["neutral_band"]
    monkeypatch.setattr(NewtonSolver, "negative_eigenvalues", lambda self: -1)
    d = tmp_path / "failed"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "michell.opts"),
                           "-rod_nelem", "12", "-load_path", "newton", out=d)
    assert rc == 0, err
    assert out.strip().splitlines()[-1].startswith("converged;"), out
    s = summary(d)
    assert s["stable"] is None and s["negative_eigenvalues"] is None


def test_a_newton_path_out_of_cut_backs_is_no_fold(capsys, tmp_path):
    """The cut-backs run out before the step has shrunk to -load_min_step: the plain line,
    not the fold's."""
    d = tmp_path / "out"
    rc, out, err = rodsnes(capsys, *MATT, "-load_path", "newton", "-snes_max_it", "2",
                           "-load_max_cutbacks", "1", out=d)
    assert rc == 3, err
    failure = summary(d)["failure"]
    assert "Newton failed after 1 cut-backs" in failure and "fold" not in failure, failure


def test_a_newton_path_at_a_fold_says_what_goes_on_from_there(capsys, tmp_path):
    """-load_path newton -stability on the imperfect twisted ring stops at the fold just below
    Michell's threshold: no equilibrium near the last one however short the step.  The line
    says so and what follows the path further (it said only "Newton failed after 10
    cut-backs")."""
    d = tmp_path / "out"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "michell.opts"),
                           "-rod_nelem", "12", "-load_path", "newton", "-stability", out=d)
    assert rc == 3, err
    last = out.strip().splitlines()[-1]
    assert "Newton found no equilibrium near the last one however short the step" in last
    assert "-load_arclength follows the branch around a fold" in last
    assert "-load_path minimize descends past it" in last
    assert "however short the step" in summary(d)["failure"]


def test_an_unstable_end_not_asked_for_fails(capsys, tmp_path, monkeypatch):
    """A conservative run on the default path whose last step is unstable (faked: the
    minimiser's steps end stable) has failed: exit 3, the last line says UNSTABLE."""
    from rodsnes.solve import minimize
    solve = minimize.EnergyMinimizer.solve_at

    def unstable(self, lam):
        res = solve(self, lam)
        res.negative_eigenvalues = 1 if res.converged else res.negative_eigenvalues
        return res
    monkeypatch.setattr(minimize.EnergyMinimizer, "solve_at", unstable)
    d = tmp_path / "out"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "euler.opts"),
                           "-load_steps", "2", out=d)
    assert rc == 3, err
    last = out.strip().splitlines()[-1]
    assert last.startswith("FAILED: the load path ends at load 1.000000 on an UNSTABLE "
                           "equilibrium (1 negative eigenvalues"), last
    s = summary(d)
    assert s["converged"] is False and s["stable"] is False and "UNSTABLE" in s["failure"]


# ------------------------------------------------------------------------ subprocesses
def _command(*args):
    env = dict(os.environ)
    for k in list(env):          # a serial subprocess must not inherit mpirun's rank variables
        if k.startswith(("OMPI_COMM_WORLD", "PMIX_", "PMI_")):
            del env[k]
    return dict(args=[sys.executable, "-m", "rodsnes", *map(str, args)], cwd=ROOT, env=env,
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_the_command_refuses_in_one_line_from_start_up_to_set_up(tmp_path):
    """As a user meets it: PETSc never prints its error block, Python never a traceback."""
    (tmp_path / "bad.opts").write_text("-rod_length 1\ngarbage\n")
    for args, expect in [(("-options_file", tmp_path / "bad.opts"), "line 2 'garbage'"),
                         (MATT + ("-snes_type", "bogus"), "-snes_type bogus"),
                         (MATT + ("-load_path", "newton", "-pc_factor_mat_solver_type",
                                  "superlu"), "superlu cannot factor")]:
        p = subprocess.run(**_command(*args, "-output_dir", tmp_path / "out"), timeout=120)
        assert p.returncode == 2, p.stderr
        assert p.stderr.startswith("rodsnes: error: ") and expect in p.stderr, p.stderr
        assert len(p.stderr.strip().splitlines()) == 1, p.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_an_interrupted_run_says_so(tmp_path, sig):
    d = tmp_path / "run"
    proc = subprocess.Popen(**_command(*MATT, "-load_path", "newton", "-load_steps", "20000",
                                       "-output_dir", d))
    try:
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end:
            if (d / "summary.json").exists() and summary(d)["load_steps"] >= 3:
                break
            time.sleep(0.1)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and f"rodsnes: error: interrupted by {sig.name}" in err
    s = summary(d)
    assert s["interrupted"] is True and s["signal"] == sig.name and s["converged"] is False
    last = output.read_step(str(d), -1)                  # the steps written stay readable
    assert s["last_step"] == last["step"] >= 3
    # the history is the run's own, not that of the last periodic rewrite (the signal may fall
    # between a step's write and its entry in the history)
    assert last["step"] - 1 <= s["load_steps"] == len(s["steps"]) <= last["step"]
    # and the rest of it (load, energy) is that of the same step, not of the last rewrite
    step = output.read_step(str(d), s["load_steps"])
    assert s["load"] == step["attrs"]["load"] and s["energy"] == step["attrs"]["energy"]
    assert f"({last['step']}, load {last['attrs']['load']:.6f})" in s["failure"]
    assert f"-restart {d}" in s["failure"]


@pytest.mark.parametrize("stop", ["SIGTERM", "error"])
def test_a_stopped_run_describes_its_last_step(capsys, tmp_path, monkeypatch, stop):
    """summary.json is rewritten only within a share of the wall time; a run stopped by a
    signal or by an error still describes its last converged step (the summary made after it),
    not an older rewrite: here no rewrite happens before the stop after step 4."""
    from petsc4py import PETSc
    from rodsnes.run import Run

    def due(self):
        if self.step == 4:
            if stop == "error":
                raise PETSc.Error(73)
            raise cli.Interrupted(signal.SIGTERM)
        return False
    monkeypatch.setattr(Run, "_summary_due", due)
    d = tmp_path / "out"
    rc, _, err = rodsnes(capsys, *MATT, "-load_path", "newton", "-load_steps", "10", out=d)
    assert rc == (128 + signal.SIGTERM if stop == "SIGTERM" else 2), err
    s = summary(d)
    last = output.read_step(str(d), -1)
    assert s["load_steps"] == len(s["steps"]) == last["step"] == 4
    assert s["load"] == last["attrs"]["load"] and s["energy"] == last["attrs"]["energy"]
    assert s["converged"] is False
    assert ("stopped by an error" if stop == "error" else "interrupted by SIGTERM") in s["failure"]


def test_an_interrupted_tolerance_trial_describes_itself(capsys, tmp_path, monkeypatch):
    """With -rod_tolerance every trial is a run into the same directory: an interruption in
    the second trial describes that trial (its mesh, its steps), not the first."""
    from rodsnes.run import Run
    trials = []

    def due(self):
        if self not in trials:
            trials.append(self)
        if len(trials) == 2 and self.step == 3:
            raise cli.Interrupted(signal.SIGTERM)
        return False
    monkeypatch.setattr(Run, "_summary_due", due)
    d = tmp_path / "out"
    rc, _, err = rodsnes(capsys, *MATT, "-load_path", "newton", "-load_steps", "10",
                         "-rod_tolerance", "1e-7", out=d)
    assert rc == 128 + signal.SIGTERM and len(trials) == 2, err
    s = summary(d)
    last = output.read_step(str(d), -1)
    assert s["dofs"] == 6 * output.read_meta(str(d))["n_nodes"] == trials[1].dofs != trials[0].dofs
    assert s["load_steps"] == last["step"] == 3 and s["load"] == last["attrs"]["load"]


def test_the_solver_check_uses_the_jacobians_mat_type():
    """-mat_type aij makes the Jacobian AIJ (partition.Layout.create_matrix), which packages
    that cannot take BAIJ factor: the set-up check builds its matrix of that type, so
    -mat_type aij -pc_factor_mat_solver_type superlu is not refused; without -mat_type it is."""
    from petsc4py import PETSc

    from rodsnes.cli import check_newton_linear_solver
    opts = PETSc.Options()
    opts["pc_factor_mat_solver_type"] = "superlu"
    try:
        with pytest.raises(PETSc.Error):
            check_newton_linear_solver(PETSc.COMM_SELF)
        opts["mat_type"] = "aij"
        check_newton_linear_solver(PETSc.COMM_SELF)
    finally:
        for name in ("pc_factor_mat_solver_type", "mat_type"):
            opts.delValue(name)


def test_petscs_lu_is_ordered_by_amd_and_no_other_preconditioner_is():
    """solve/linear.py: PETSc's own LU (PCLU with the petsc package, or PCREDUNDANT over it) is
    ordered by AMD unless the user gave an ordering, which on several ranks is carried over to
    the redundant LU; another preconditioner gets no ordering (PETSc's ICC of a BAIJ matrix
    takes only the natural one), and an ordering it cannot take is refused by the set-up
    check, whose matrix a fill-reducing ordering permutes."""
    from petsc4py import PETSc

    from rodsnes.cli import check_newton_linear_solver
    from rodsnes.solve import linear
    opts = PETSc.Options()
    names = ("ksp_type", "pc_type", "pc_factor_mat_solver_type", "pc_factor_mat_ordering_type",
             "redundant_pc_factor_mat_ordering_type")
    saved = {n: opts.getString(n) for n in names if opts.hasName(n)}

    def clear():
        for n in names:
            opts.delValue(n)
    try:
        clear()
        linear.lu_defaults(PETSc.COMM_SELF)
        assert opts.getString("pc_factor_mat_ordering_type") == "amd" == linear.lu_ordering("")
        clear()
        opts["pc_type"] = "icc"         # a preconditioner (with preonly it is refused)
        opts["ksp_type"] = "gmres"
        linear.lu_defaults(PETSc.COMM_SELF)
        assert not opts.hasName("pc_factor_mat_ordering_type") and linear.lu_ordering("") is None
        check_newton_linear_solver(PETSc.COMM_SELF)
        opts["pc_factor_mat_ordering_type"] = "amd"
        with pytest.raises(PETSc.Error, match="reordering"):
            check_newton_linear_solver(PETSc.COMM_SELF)
        clear()
        opts["pc_type"] = "redundant"
        opts["pc_factor_mat_ordering_type"] = "rcm"
        linear.ordering_default("")
        assert opts.getString("redundant_pc_factor_mat_ordering_type") == "rcm"
        assert linear.lu_ordering("") == "rcm"
    finally:
        clear()
        for n, v in saved.items():
            opts[n] = v


def test_a_signal_inside_the_writing_of_a_step_waits_for_it(capsys, tmp_path, monkeypatch):
    """A SIGTERM that arrives while result.h5 commits a step (inside h5py's attribute
    creation, where it had cut h5py's own clean-up: a KeyError, a traceback and exit 1 in a CI
    run) is raised when the step is written: the step committed, the run's message, exit 128 +
    SIGTERM (interrupts.deferred)."""
    import os
    from rodsnes.io import results as out_mod
    cls = out_mod.ResultWriter
    real = cls._commit

    def commit(self, f, step):
        if step == 3:
            os.kill(os.getpid(), signal.SIGTERM)    # delivered at the next bytecode: inside
        return real(self, f, step)
    monkeypatch.setattr(cls, "_commit", commit)
    d = tmp_path / "out"
    rc, _, err = rodsnes(capsys, *MATT, "-load_path", "newton", "-load_steps", "10", out=d)
    assert rc == 128 + signal.SIGTERM, err
    assert "interrupted by SIGTERM" in err and "Traceback" not in err
    last = output.read_step(str(d), -1)
    assert last["step"] == 3                        # written whole, then the interruption
    assert summary(d)["load_steps"] == 3


def test_deferred_keeps_a_signal_until_its_section_ends():
    """interrupts.deferred: nothing raised inside, Interrupted at the end of the outermost
    section; dropped with keep=False; outside a section at once."""
    import os
    from rodsnes import interrupts
    old = signal.signal(signal.SIGTERM, interrupts.handler)
    try:
        reached = []
        with pytest.raises(interrupts.Interrupted) as info:
            with interrupts.deferred():
                with interrupts.deferred():
                    os.kill(os.getpid(), signal.SIGTERM)
                    reached.append("inner")
                reached.append("outer")
        assert reached == ["inner", "outer"] and info.value.signum == signal.SIGTERM
        with interrupts.deferred(keep=False):
            os.kill(os.getpid(), signal.SIGTERM)
        with pytest.raises(interrupts.Interrupted):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):                   # the handler runs between bytecodes
                pass
    finally:
        signal.signal(signal.SIGTERM, old)


@pytest.mark.mpi
def test_an_output_dir_rank_0_cannot_make_is_refused_on_every_rank():
    """A Run built through the API (no rodsnes command's check before it) whose -output_dir
    rank 0 cannot make: a SceneError naming the option on every rank, none left waiting."""
    import tempfile
    from mpi4py import MPI
    from conftest import build_run
    from rodsnes.errors import SceneError
    comm = MPI.COMM_WORLD
    blocker = None
    if comm.rank == 0:
        fd, blocker = tempfile.mkstemp(prefix="rodsnes_not_a_dir_")
        os.close(fd)
    blocker = comm.bcast(blocker)
    try:
        with pytest.raises(SceneError, match="-output_dir") as err:
            build_run("mattiasson", outdir=os.path.join(blocker, "out"))
        assert err.value.options == ("-output_dir",)
    finally:
        comm.Barrier()
        if comm.rank == 0:
            os.remove(blocker)


def test_what_the_new_refusals_leave_alone(capsys, tmp_path):
    """-snes_atol on the minimise path, which does not read it (a warning, not a refusal),
    and a free start with a sliding end whose axial loads balance (end force against gravity
    along the slide) run as before."""
    rc, out, err = rodsnes(capsys, *MATT, "-rod_error_estimate", "off", "-snes_atol", "1",
                           out=tmp_path / "atol")
    assert rc == 0 and "error" not in err, err
    rc, out, err = rodsnes(capsys, *MATT, "-rod_error_estimate", "off", "-bc_start", "free",
                           "-bc_end", "sliding", "-load_end_force", "-1,0,0", "-load_gravity",
                           "1,0,0", out=tmp_path / "balanced")
    assert rc == 0, err


def test_a_failed_tolerance_run_says_so_under_quiet(capsys, tmp_path):
    """-rod_tolerance whose trials all converge but whose mesh would be too large: exit 3, and
    with -quiet the failure is still said on stderr."""
    rc, out, err = rodsnes(capsys, *MATT, "-rod_tolerance", "1e-10", "-rod_order", "1",
                           out=tmp_path / "tol")
    assert rc == 3 and "rodsnes: failed: -rod_tolerance 1e-10: the estimate" in err, err


def test_a_wide_neutral_band_is_a_warning_with_its_overload(capsys, tmp_path):
    """Where the Hessian's round-off widens the neutral band past 5 % of overload (the band over
    stability.FALL, 13.4 EI/L^4 per unit of relative load for the Euler column), the count may
    certify a state well past a critical load: the perfect column with EA L^2/EI = 1e12 on 16
    elements (band 16.8 EI/L^4) at twice its buckling load is left straight and counted
    stable.  A warning on stderr (not a note on stdout, which -quiet silenced) says how far
    past a critical load a state may be and what sharpens the count; the case's own column
    (band 0.01) has none."""
    d = tmp_path / "slender"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "euler.opts"),
                           "-rod_imperfection", "0", "-rod_EI", "1e-6", "-rod_GJ", "1e-6",
                           "-load_end_force", "-4.934802e-6,0,0", "-rod_error_estimate", "off",
                           out=d)
    assert summary(d)["neutral_band"] > 16.0
    assert "rodsnes: warning: the stability count took eigenvalues of H v = lambda M v above " \
           "-16.8 EI/L^4 as neutral" in err, err
    assert "a state up to about 126 % past a critical load may count as stable" in err
    assert "-rod_nelem" in err and "-rod_EA" in err
    d = tmp_path / "case"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "euler.opts"),
                           "-rod_error_estimate", "off", out=d)
    assert rc == 0 and summary(d)["stable"] is True and "warning" not in err, err


def test_a_snes_that_stops_short_fails_the_step(capsys, tmp_path):
    """A step is converged only where the residual at its state meets the tolerance, whatever
    the SNES says: -snes_type ksponly takes one linear step and reports CONVERGED_ITS (the
    roll-up ended at the wrong tip, |F| NaN, exit 0).  Now the step fails (exit 3, the reason
    in summary.json), and with -quiet the failure is still said on stderr."""
    d = tmp_path / "ksponly"
    rc, out, err = rodsnes(capsys, *ROLLUP, "-snes_type", "ksponly", "-load_max_cutbacks", "1",
                           out=d)
    assert rc == 3, err
    s = summary(d)
    assert s["converged"] is False and "Newton failed" in s["failure"], s
    assert "rodsnes: failed: load path stopped" in err and not out.strip(), (out, err)


def test_a_linear_solver_that_fails_every_newton_step_is_named(capsys, tmp_path):
    """The minimiser takes the Hessian's step where a Newton step's linear solve fails; where
    most of them fail (here MUMPS allowed 1 MB: -mat_mumps_icntl_23 1, which the in-plane step
    takes over too) the run converges the slow way and warns, naming the linear solver's
    options; a run whose Newton steps solve says nothing of it."""
    rc, out, err = rodsnes(capsys, *MATT, "-rod_nelem", "400", "-pc_factor_mat_solver_type",
                           "mumps", "-mat_mumps_icntl_23", "1", out=tmp_path / "capped")
    assert rc == 0, err
    assert "rodsnes: warning: the Newton step's linear solve failed in" in err, err
    assert "a linear solver option" in err and "-mat_mumps_*" in err, err
    # which solve, in its options' words (it said "the in-plane solve failed")
    assert ("the in-plane solve failed: KSP DIVERGED_PCSETUP_FAILED; -planar_ksp_type "
            "preonly, -planar_pc_type lu by mumps") in err, err
    rc, out, err = rodsnes(capsys, *MATT, "-rod_nelem", "400", "-pc_factor_mat_solver_type",
                           "mumps", out=tmp_path / "plain")
    assert rc == 0 and "linear solve failed" not in err, err


def test_a_penalty_kept_as_given_that_breaks_the_promise_says_so(capsys, tmp_path):
    """-contact_penalty given (not adapted: -contact_penalty_adapt is off then) that lets the
    roll-up sink 8 % of the diameter into itself: the run converges (the answer for that
    penalty) and warns that the promise -contact_penetration is not kept, naming the way to
    keep it (the plectoneme with -contact_penalty 2e4 -contact_wall 0 ended 15.8 % deep
    without a word, summary.json saying 1 % promised)."""
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "rollup_contact.opts"),
                           "-contact_penalty", "1e2", out=tmp_path / "soft")
    assert rc == 0, err
    assert "rodsnes: warning: the last state presses 8.3" in err, err
    assert ("beyond -contact_penetration 0.01: -contact_penalty 100 was kept as given "
            "(-contact_penalty_adapt raises it") in err, err
    s = summary(tmp_path / "soft")
    pen = s["contact"]["max_penetration"]
    assert pen > 0.08
    # the last line: what the error estimate does not count, the penalty's (its depth)
    last = out.strip().splitlines()[-1]
    assert (f"(the mesh's, at this penalty; the contact sinks up to "
            f"{pen * 2 * s['contact']['radius']:.1e} deep)") in last, last


def test_each_tolerance_mesh_warns_for_itself(capsys, tmp_path):
    """-rod_tolerance makes a run per mesh, and each warns of its own failed Newton steps
    (GMRES with Jacobi breaks down on the in-plane tangent): the warnings name their mesh
    (two identical lines before)."""
    rc, out, err = rodsnes(capsys, *MATT, "-rod_tolerance", "1e-6", "-pc_type", "jacobi",
                           "-ksp_type", "gmres", "-ksp_max_it", "20", out=tmp_path / "o")
    assert rc == 0, err
    warned = [ln for ln in err.splitlines() if "linear solve failed" in ln]
    meshes = [ln.split("-rod_tolerance mesh of ")[1].split(" (")[0] for ln in warned]
    assert len(warned) >= 2 and len(set(meshes)) == len(warned), err


@pytest.mark.parametrize("planar", ["on", "off"])
def test_a_newton_path_whose_linear_solve_fails_names_it(capsys, tmp_path, planar):
    """An iterative linear solve that cannot solve the Newton step's tangent (GMRES without a
    preconditioner, 20 iterations) fails every try: each cut-back and the run's end name the
    linear solve, its reason and its options (they said "SNES reason -3" and "Newton failed
    after 1 cut-backs"); a step that fails otherwise keeps the plain line
    (test_a_newton_path_out_of_cut_backs_is_no_fold)."""
    d = tmp_path / "out"
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "mattiasson.opts"),
                           "-rod_planar", planar, "-load_path", "newton", "-ksp_type", "gmres",
                           "-pc_type", "none", "-ksp_max_it", "20", "-load_max_cutbacks", "1",
                           "-ksp_typo", "x", out=d)
    assert rc == 3, err
    pre = "-planar_" if planar == "on" else "-"
    step = [ln for ln in out.splitlines() if "not accepted" in ln]
    assert len(step) == 2 and all(
        f"the linear solve failed, KSP DIVERGED_MAX_IT after 20 iterations; {pre}ksp_type "
        f"gmres, {pre}pc_type none" in ln for ln in step), out
    failure = summary(d)["failure"]
    assert "the Newton step's linear solve failed at every try (KSP DIVERGED_MAX_IT" in failure
    assert ("the linear solver options given (-ksp_max_it, -ksp_type, -pc_type) cannot solve "
            "this tangent") in failure and "Newton failed" not in failure, failure


def test_the_in_plane_step_takes_the_newton_steps_solver_options():
    """A planar run's in-plane step takes every option of the Newton step's KSP, PC and
    factorisation (options/iterative.opts: its tolerance, overlap and subdomain solver were
    dropped, the cantilever of 200 elements took 122 iterations for 22); its own -planar_
    options win."""
    from petsc4py import PETSc
    from conftest import run_case
    run = run_case("mattiasson", load_steps=1, ksp_type="gmres", pc_type="asm",
                   ksp_rtol=1e-12, pc_asm_overlap=2, sub_pc_type="lu", planar_ksp_max_it=77)
    ksp = run.problem.planar.ksp
    assert run.ok and ksp.getType() == "gmres" and ksp.getPC().getType() == "asm"
    rtol, _, _, max_it = ksp.getTolerances()
    assert rtol == 1e-12 and max_it == 77
    assert PETSc.Options().getInt("planar_pc_asm_overlap") == 2
    assert PETSc.Options().getString("planar_sub_pc_type") == "lu"


def test_a_hessian_that_cannot_be_factored_says_so(capsys, tmp_path):
    """A stability count whose every factorisation fails (MUMPS allowed 1 MB:
    -stability_mat_mumps_icntl_23 1) fails the step with that reason and its options, not as a
    state without a positive definite shift."""
    rc, out, err = rodsnes(capsys, "-options_file", os.path.join(CASES, "bench_coil.opts"),
                           "-quiet", "-stability_mat_mumps_icntl_23", "1", out=tmp_path / "o")
    assert rc == 3, err
    assert "the Hessian's factorisation failed at every shift" in err, err
    assert "-stability_*" in err and "no positive definite shift" not in err, err


@pytest.mark.parametrize("options", [
    {"pc_type": "svd"}, {"pc_type": "ksp"}, {"pc_type": "bjacobi", "sub_pc_type": "lu"},
    {"pc_type": "redundant", "redundant_pc_factor_mat_solver_type": "mumps"},
    {"mat_type": "mpiaij", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
    {"ksp_type": "gmres", "pc_type": "ilu"}, {"ksp_type": "gmres", "pc_type": "jacobi"},
    {"stability_pc_factor_mat_solver_type": "MUMPS"},
    {"interior_pc_factor_mat_solver_type": "MUMPS"},
    {"planar_pc_factor_mat_solver_type": "mumps"},
    {"log_view": ":${HOMEDIRECTORY}/rodsnes_log.txt"}, {"log_view": ":/dev/null"},
    {"log_view": ""}, {"log_view": "::ascii_info_detail"}, {"snes_monitor_short": ""}],
    ids=lambda o: " ".join(f"-{k} {v}" for k, v in o.items()))
def test_solver_neighbours_of_the_refusals_are_accepted(options):
    """What the solver refusals must let through: preconditioners that are a whole solve with
    preonly (svd, an inner KSP, block Jacobi with LU in its block, redundant), MUMPS of an
    MPI type on one rank (the estimate keeps its own LU), iterative solves with any
    preconditioner, package names in any case, viewer files PETSc can write or expands."""
    from petsc4py import PETSc
    from rodsnes import cli
    opts = PETSc.Options()
    for k, v in options.items():
        opts[k] = v
    assert cli.petsc_option_problems(opts) == []
    cli.check_newton_linear_solver(PETSc.COMM_WORLD)


@pytest.mark.parametrize("snes_type, needs", [("vinewtonssls", "variational inequality"),
                                              ("fas", "a hierarchy of meshes"),
                                              ("shell", "a solver of your own")])
def test_a_nonlinear_solver_rodsnes_cannot_feed_is_refused(snes_type, needs):
    """-snes_type of a PETSc solver that needs what rodsnes does not give it (bounds, a DM, a
    solver of one's own): refused before the run with the usable ones named (vinewtonssls
    crashed the planar Newton path with signal 11; the others failed every Newton solve and
    ended 'Newton failed after 10 cut-backs' without naming -snes_type)."""
    from rodsnes.cli import petsc_option_problems
    from petsc4py import PETSc
    opts = PETSc.Options()
    opts.setValue("snes_type", snes_type)
    try:
        msgs = petsc_option_problems(opts)
    finally:
        opts.delValue("snes_type")
    assert len(msgs) == 1 and msgs[0].startswith(f"-snes_type {snes_type}: PETSc's")
    assert needs in msgs[0] and "use newtonls (the default), newtontr, qn or ngmres" in msgs[0]


def test_fp_trap_is_refused_on_the_command_line_and_in_a_file(capsys, tmp_path):
    """-fp_trap made every floating-point exception abort the run, and rodsnes meets some on
    purpose: the run ended at start-up with PETSc's 'unknown floating point error', exit 72,
    no rodsnes line.  Refused, on the command line and in an options file."""
    refused(capsys, tmp_path, MATT + ("-fp_trap",), ["-fp_trap makes every floating-point "
                                                      "exception abort the run", "drop it"])
    (tmp_path / "trap.opts").write_text("-fp_trap\n")
    refused(capsys, tmp_path, MATT + ("-options_file", tmp_path / "trap.opts"),
            ["line 1 '-fp_trap': -fp_trap makes every floating-point exception abort the run"])
    # switched off, it is no problem
    from rodsnes.cli import command_line_problems, _options_file_problem
    assert command_line_problems(["rodsnes", "-fp_trap", "0", "-rod_nelem", "4"]) == []
    (tmp_path / "off.opts").write_text("-fp_trap false\n")
    assert _options_file_problem(str(tmp_path / "off.opts")) is None


def test_fp_trap_in_petsc_options_is_refused(monkeypatch):
    """PETSC_OPTIONS=-fp_trap aborted at start-up (exit 72, no rodsnes line) as well."""
    from rodsnes.cli import command_line_problems
    monkeypatch.setenv("PETSC_OPTIONS", "-fp_trap -malloc_debug 0")
    msgs = command_line_problems(["rodsnes", "-rod_nelem", "4"])
    assert len(msgs) == 1 and msgs[0].endswith("drop it (from PETSC_OPTIONS)")


def test_a_huge_torsional_stiffness_is_named(capsys, tmp_path):
    """The residual's roundoff floor made by GJ (-rod_GJ 1e300) was blamed on the stretch
    stiffness 1e6 with a thicker rod as the fix: the stiffness that makes it is named."""
    refused(capsys, tmp_path, MATT + ("-rod_GJ", "1e300"),
            ["from the GJ / L 1e+300 over 25 nodes", "use a -rod_GJ near the others"])


def test_a_retraction_asked_for_with_another_line_search_is_warned_about(capsys, tmp_path):
    """-load_retraction acts with the basic line search only: given with bt it was ignored
    without a word (the run the same as with -load_retraction 0)."""
    rc, _, err = rodsnes(capsys, *ROLLUP, "-load_retraction", "-snes_linesearch_type", "bt",
                         out=tmp_path / "bt")
    assert rc == 0, err
    assert ("rodsnes: warning: -load_retraction does nothing: it acts with "
            "-snes_linesearch_type basic only, and this run's line search is bt") in err
    rc, _, err = rodsnes(capsys, *ROLLUP, "-load_retraction", out=tmp_path / "basic")
    assert rc == 0 and "-load_retraction" not in err, err
