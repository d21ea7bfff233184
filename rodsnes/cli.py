"""rodsnes command line: scene -> mesh -> layout -> problem -> load stepping -> output.

    mpirun -n 2 rodsnes -options_file cases/rollup.opts -rod_nelem 64 -snes_monitor

Exit codes: 0 converged to load 1 (or -load_stop); 2 refused before the solve (bad input: one
line per problem on stderr, ``rodsnes: error: ...``, naming the option and the fix; a retired
option says what replaced it); 3 the load path failed (the last converged step stays in
DIR/result.h5 and DIR/summary.json says so), or a conservative scene ended on an unstable
equilibrium that was not asked for (asked for: -load_arclength, or -load_path newton, whose
last line then says "unstable" with exit code 0);
4 an internal error (a defect, or a failure of one rank alone: _failed); 128 + N stopped by
signal N (130 SIGINT, 143 SIGTERM): summary.json says ``"interrupted": true`` and the steps
written stay readable.

Before the solve the command also checks what the options database itself cannot: the
-options_file files (before PETSc reads them), PETSc solver types and numbers, the output
directory, whether the scene can be solved as given (scene.check_solvable), and it sets up the
Newton path's linear solver once on a small matrix.  Options that do nothing are reported as
warnings (``rodsnes: warning: ...`` on stderr, rank 0): rodsnes options the scene does not use
(scene.unused_options) and PETSc options nothing read, as PETSc's -options_left, with the
closest known option.
"""
import os
import re
import shlex
import signal
import sys
import tempfile
import time

from rodsnes import interrupts
from rodsnes.errors import tell
from rodsnes.interrupts import Interrupted

# Nothing here imports petsc4py.PETSc at module level, and neither may any rodsnes module this
# file imports at its top: PETSc has to start with the command line's options (_start_petsc),
# or options read only at PetscInitialize (-log_view: "Must use -log_view ... before calling
# this routine" at PetscFinalize, exit 1 after a converged run) are lost.  The solver modules
# are imported inside the functions that run after the start (tests/test_cli.py).

EXIT_REFUSED, EXIT_FAILED, EXIT_INTERNAL = 2, 3, 4

# after an error, the seconds every rank waits for the others to have stopped too (_failed):
# beyond them the error is taken for this rank's alone and the job is aborted
AGREE_SECONDS = 5.0

LINESEARCH_TYPES = ("basic", "bt", "l2", "cp", "nleqerr", "shell", "ncglinear")

COMMON_PETSC_OPTIONS = (
    "snes_type snes_monitor snes_monitor_short snes_converged_reason snes_view snes_rtol "
    "snes_atol snes_stol snes_max_it snes_max_funcs snes_divergence_tolerance snes_lag_jacobian "
    "snes_linesearch_type snes_linesearch_monitor snes_linesearch_damping snes_linesearch_max_it "
    "snes_test_jacobian snes_ksp_ew snes_mf_operator "
    "ksp_type ksp_rtol ksp_atol ksp_dtol ksp_max_it ksp_monitor ksp_monitor_true_residual "
    "ksp_converged_reason ksp_view ksp_gmres_restart ksp_norm_type ksp_initial_guess_nonzero "
    "pc_type pc_factor_mat_solver_type pc_factor_shift_type pc_factor_levels "
    "pc_factor_mat_ordering_type pc_asm_overlap pc_asm_type pc_gamg_type pc_mg_levels "
    "pc_fieldsplit_type sub_ksp_type sub_pc_type sub_pc_factor_levels mat_type mat_view "
    "mat_mumps_icntl_4 mat_mumps_icntl_7 mat_mumps_icntl_13 mat_mumps_icntl_14 "
    "mat_mumps_icntl_23 mat_mumps_icntl_24 mat_mumps_cntl_1 mat_mumps_cntl_3 log_view "
    "options_left options_view help version info malloc_debug malloc_dump memory_view "
    "on_error_abort no_signal_handler").split()
"""PETSc options a rodsnes user is likely to mean (did-you-mean for an option nothing read)."""

FINALIZE_READ = ("options_left", "options_view", "malloc_dump", "malloc_view", "memory_view",
                 "objects_dump", "log_view", "log_all", "log_summary", "log_trace", "history")
"""PETSc options read at PetscInitialize or PetscFinalize, never left over in a run."""

LATE_READ = re.compile(r"(^|_)(view|converged_reason|monitor\w*)$|_view_|_test_")
"""PETSc options read during or at the end of a solve: reported only after the run (so are
those of rodsnes' own solvers, scene.SOLVER_PREFIXES, which are made during the run: the
stability count's and the planar step's at the first load step, the error estimate's after
the last)."""

NUMERIC_SUFFIXES = ("_rtol", "_atol", "_stol", "_dtol", "_max_it", "_max_funcs",
                    "_divergence_tolerance", "_gmres_restart", "_asm_overlap", "_damping",
                    "_factor_levels", "_lag_jacobian", "_lag_preconditioner", "_mg_levels")
NUMERIC_PATTERN = re.compile(r"mat_mumps_i?cntl_\d+$")


def _rank_from_env():
    """This process's MPI rank before MPI is up (mpirun's environment), 0 if serial."""
    for key in ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK"):
        if os.environ.get(key, "").isdigit():
            return int(os.environ[key])
    return 0


def _say(rank, kind, text):
    """``rodsnes: <kind>: <line>`` on stderr, one per line of text, on rank 0 only."""
    if rank == 0:
        tell(kind, text)


# --------------------------------------------------------------------------- -options_file
FP_TRAP = ("-fp_trap makes every floating-point exception abort the run, and rodsnes meets "
           "some on purpose (an infinite energy beyond the contact's wall, masked divisions in "
           "numpy; the run ended at start-up, exit 72, with PETSc's 'unknown floating point "
           "error'): drop it")


def _traps(value):
    """Whether -fp_trap with this value (None: none, which PETSc takes for true) turns the
    trapping on."""
    return value is None or value.lower() not in ("0", "false", "no", "off")


def _options_file_line_problem(tokens):
    """What PETSc would refuse in one options-file line (its tokens, comment stripped)."""
    first = tokens[0]
    if first.lower() == "alias":
        return None if len(tokens) == 3 else "an alias line is 'alias -new -old'"
    if not first.startswith("-") or first == "-":
        return f"'{first}' is not an option (an option starts with '-')"
    if first == "-fp_trap" and _traps(tokens[1] if len(tokens) > 1 else None):
        return FP_TRAP
    more = [t for t in tokens[1:] if _is_option_token(t)]
    if more:
        return f"two options on one line ({first} and {more[0]}): one option per line"
    if len(tokens) > 2:
        return (f"{first} has more than one value ({' '.join(tokens[1:])}): a vector is "
                f"written without spaces, e.g. 0,0,1")
    return None


def _is_option_token(tok):
    """A token PETSc takes for an option name: '-' and not a number (-1, -.5, -1e3 are values)."""
    if not tok.startswith("-") or tok == "-":
        return False
    try:
        float(tok.split(",")[0])
        return False
    except ValueError:
        return True


def options_file_problems(argv):
    """Messages for every -options_file of argv that PETSc would refuse: missing, a directory,
    unreadable, or holding a line that is not '-option [value]', a '#' comment or an alias."""
    out = []
    for i, arg in enumerate(argv):
        if arg != "-options_file":
            continue
        path = argv[i + 1] if i + 1 < len(argv) else None
        if path is None or (path.startswith("-") and not os.path.exists(path)):
            out.append("-options_file needs a file name (-options_file cases/mattiasson.opts)")
            continue
        if not os.path.exists(path):
            out.append(f"-options_file {path}: no such file (check the path; cases are in cases/)")
        elif os.path.isdir(path):
            out.append(f"-options_file {path}: is a directory; give an options file in it "
                       f"(e.g. {os.path.join(path, 'case.opts')})")
        else:
            problem = _options_file_problem(path)
            if problem:
                out.append(f"-options_file {path}: {problem}")
    return out


def command_line_problems(argv):
    """Messages for command-line words PETSc would take without a word: an option written with
    two dashes (--rod_nelem 16 was stored as '--rod_nelem' and the run used 8 elements) and a
    word that is neither an option nor the value of the option before it (a vector written
    with spaces, a dash forgotten): both were ignored, exit 0; -fp_trap turned on here or in
    PETSC_OPTIONS (FP_TRAP)."""
    out = []
    value_ok = False                # the word before was an option name, awaiting its value
    words = list(argv[1:])
    # PETSC_OPTIONS too: PETSc reads it at its start, before rodsnes could say a word
    every = words + shlex.split(os.environ.get("PETSC_OPTIONS", ""))
    for i, tok in enumerate(every):
        nxt = every[i + 1] if i + 1 < len(every) else None
        if tok == "-fp_trap" and _traps(None if nxt is None or _is_option_token(nxt) else nxt):
            out.append(FP_TRAP + (" (from PETSC_OPTIONS)" if i >= len(words) else ""))
    for tok in words:
        if _is_option_token(tok):
            if tok.startswith("--"):
                out.append(f"'{tok}': an option takes one dash ({tok[1:]})")
            value_ok = True
            continue
        if not value_ok:
            out.append(f"'{tok}' is neither an option nor the value of the option before it "
                       f"(an option starts with '-', one value follows it, and a vector is "
                       f"written without spaces, e.g. 0,0,1)")
        value_ok = False
    return out


def _options_file_problem(path, chain=()):
    """What PETSc would refuse in the options file ``path`` (None: nothing), the files it
    includes (-options_file lines, as PETSc reads them) followed: a missing one, or one that
    includes itself again (``chain``: the files that led here; PETSc followed such a loop until
    its stack overflowed, signal 11, no message)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            lines = fh.read().splitlines()
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    chain = chain + (os.path.realpath(path),)
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0]
        try:
            tokens = shlex.split(text)
        except ValueError:
            tokens = text.split()
        if not tokens:
            continue
        problem = _options_file_line_problem(tokens)
        if problem:
            return (f"line {number} '{line.strip()}': {problem}; each line holds one "
                    f"'-option value', '#' starts a comment")
        if tokens[0] == "-options_file" and len(tokens) > 1:
            inner = tokens[1]
            where = f"line {number} '{line.strip()}'"
            if not os.path.isfile(inner):
                return (f"{where}: {inner}: no such file" if not os.path.exists(inner) else
                        f"{where}: {inner}: is not a file")
            if os.path.realpath(inner) in chain:
                return (f"{where}: includes {inner}, which includes this file again (an "
                        f"options file must not include itself); drop the line")
            problem = _options_file_problem(inner, chain)
            if problem:
                return f"{where}: {inner}: {problem}"
    return None


# --------------------------------------------------------------------------- PETSc start-up
def _petsc_started():
    mod = sys.modules.get("petsc4py.PETSc")
    return mod is not None and mod.Sys.isInitialized()


def _start_petsc(argv):
    """Start PETSc with argv's options (None), or return why it refused them.  PETSc prints its
    errors itself at start-up, so its stderr is captured and only the message kept.  If PETSc
    is already running (cli.main called in-process), argv's options are added to its database."""
    import petsc4py
    if _petsc_started():
        from petsc4py import PETSc
        try:
            PETSc.Options().insertString(" ".join(shlex.quote(a) for a in argv[1:]))
        except PETSc.Error:
            return petsc_error_text() or "PETSc refused the options"
        return None
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        failed = None
        try:
            petsc4py.init(argv)
            from petsc4py import PETSc  # noqa: F401  (PetscInitialize runs at this import)
        except Exception as exc:  # noqa: BLE001 - any start-up failure is reported in one line
            failed = exc
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    if failed is None:
        sys.stderr.write(text)
        return None
    msgs = [m.group(1).strip() for m in re.finditer(r"PETSC ERROR: (.*)", text)]
    msgs = [m for m in msgs if m and not m.startswith(("-", "#", "See ", "Petsc ", "Configure",
                                                         "Libraries", "/", "PETSc", "Option left",
                                                         "Invalid argument", "--"))
            and " at " not in m]
    return "PETSc could not start: " + (msgs[-1] if msgs else str(failed))


# --------------------------------------------------------------------------- PETSc's options
def _type_names(kind):
    from petsc4py import PETSc
    if kind == "SNESLineSearch":
        return LINESEARCH_TYPES
    cls = {"KSP": PETSc.KSP.Type, "PC": PETSc.PC.Type, "SNES": PETSc.SNES.Type,
           "MatSolver": PETSc.Mat.SolverType, "Mat": PETSc.Mat.Type}[kind]
    return tuple(sorted(v for k, v in vars(cls).items() if k.isupper() and isinstance(v, str)))


COMMON_TYPES = {"KSP": "preonly gmres fgmres cg minres bcgs richardson",
                "PC": "lu cholesky ilu icc jacobi bjacobi asm gamg none",
                "SNES": "newtonls newtontr qn ngmres", "MatSolver": "mumps petsc superlu_dist",
                "SNESLineSearch": " ".join(LINESEARCH_TYPES), "Mat": "aij baij sbaij"}
"""The types named in a refusal when no close one is found."""

TYPE_OPTIONS = (("pc_factor_mat_solver_type", "MatSolver", "LU/Cholesky package"),
                ("snes_linesearch_type", "SNESLineSearch", "SNES line search"),
                ("snes_type", "SNES", "nonlinear solver (SNES)"),
                ("ksp_type", "KSP", "Krylov method (KSP)"),
                ("pc_type", "PC", "preconditioner (PC)"),
                ("mat_type", "Mat", "matrix type"))
"""Option-name endings whose value must be a PETSc type: (suffix, kind, what)."""


UNUSABLE_SNES = {
    "vinewtonrsls": "the bounds of a variational inequality",
    "vinewtonssls": "the bounds of a variational inequality",
    "shell": "a solver of your own (SNESShellSetSolve)",
    "python": "a solver of your own (a Python class)",
    "composite": "its sub-solvers, set up by a program",
    "fas": "a hierarchy of meshes (a DM)",
    "nasm": "subdomains of a mesh (a DM)",
    "aspin": "subdomains of a mesh (a DM)",
    "patch": "a mesh's patches (a DMPlex)",
    "ngs": "a nonlinear Gauss-Seidel sweep of your own",
    "ksptransposeonly": "a linear problem solved with its transpose"}
"""PETSc's nonlinear solvers that need what rodsnes does not give them (a run with one failed
every Newton solve; -snes_type vinewtonssls crashed the planar Newton path, signal 11)."""


def _did_you_mean(word, names):
    from rodsnes.io.scene import _suggest, _or_list
    close = _suggest(word.lower(), list(names), cutoff=0.7)
    return f"; did you mean {_or_list(list(close))}?" if close else ""


def petsc_option_problems(opts):
    """Messages for PETSc options whose value cannot work: an unknown solver type (-ksp_type,
    -pc_type, -snes_type, -snes_linesearch_type, -pc_factor_mat_solver_type, -mat_type, any
    prefix) or a tolerance, iteration count or MUMPS control that is not a number."""
    out = []
    for name, value in sorted(opts.getAll().items()):
        low = name.lower()
        value = "" if value is None else str(value).strip()
        for suffix, kind, what in TYPE_OPTIONS:
            if low.endswith(suffix):
                names = _type_names(kind)
                if value.lower() not in names:
                    hint = _did_you_mean(value, names) or (
                        "; e.g. " + ", ".join(COMMON_TYPES[kind].split()))
                    out.append(f"-{name} {value}: not a PETSc {what}{hint} (-help -snes_view "
                               f"lists them all)")
                elif kind == "SNES" and value.lower() in UNUSABLE_SNES:
                    out.append(f"-{name} {value}: PETSc's {value.lower()} needs "
                               f"{UNUSABLE_SNES[value.lower()]}, which rodsnes does not give "
                               f"it; use newtonls (the default), newtontr, qn or ngmres")
                break
        else:
            if low.endswith(NUMERIC_SUFFIXES) or NUMERIC_PATTERN.search(low):
                try:
                    float(value)
                except ValueError:
                    out.append(f"-{name} {value}: not a number (PETSc reads a number here, e.g. "
                               f"-{name} {'1e-8' if low.endswith('tol') else '10'})")
            elif low.endswith(("view", "monitor")):
                why = _viewer_file_problem(value)
                if why:
                    out.append(f"-{name} {value}: {why}")
                    opts.delValue(name)     # else PETSc opens it at exit, its error block after

    return out


def _viewer_file_problem(value):
    """What keeps a viewer option's file (-log_view :DIR/FILE, ascii:FILE:format ...) from
    being written, or None: PETSc opens it when it views, at the end of a solve or of the run,
    and then prints its error block after the results."""
    parts = value.split(":")
    if len(parts) < 2 or parts[0] not in ("", "ascii", "binary", "hdf5", "vtk") or not parts[1] \
            or "$" in parts[1] or "~" in parts[1]:      # PETSc expands ${HOMEDIRECTORY} ...
        return None
    if os.path.exists(parts[1]):
        return None if os.access(parts[1], os.W_OK) else "its file cannot be written"
    folder = os.path.dirname(os.path.abspath(parts[1]))
    if not os.path.isdir(folder):
        return f"its file's directory {folder} does not exist; give one that does"
    if not os.access(folder, os.W_OK):
        return f"its file's directory {folder} cannot be written; give one that can"
    return None


def petsc_error_text():
    """The message of the PETSc error just raised (petsc4py keeps its lines), without the
    'function() at file:line' lines."""
    from petsc4py import PETSc
    lines = [l.strip() for l in getattr(PETSc.Error, "_traceback_", []) or []]
    msgs = [l for l in lines if l and not re.match(r"\w+\(\) at ", l)
            and not l.startswith("Unknown type. Check")]
    return msgs[-1] if msgs else ""


def _unfit_factorisation(package, mtype, values, opts):
    """The line for a factorisation package that cannot factor the Jacobian's matrix type:
    with petsc or mumps, which factor rodsnes' block matrix, the user's -mat_type is the cause
    (leave it out, or take mumps); another package is itself the cause (take one of those)."""
    given = opts.getString("mat_type", "")
    if given and package in ("petsc", "mumps"):
        fix = "leave -mat_type out (rodsnes' block matrix, which petsc and mumps factor)"
        if package != "mumps":
            fix += " or use -pc_factor_mat_solver_type mumps"
        return (f"-mat_type {given}: the LU of {package} cannot factor the Jacobian as {mtype}; "
                f"{fix}")
    option = values.get(package, "pc_factor_mat_solver_type")
    others = " or ".join(p for p in ("petsc (the default)", "mumps") if p.split()[0] != package)
    return (f"-{option} {package}: {package} cannot factor rodsnes' Jacobian ({mtype}, blocks "
            f"of a node's unknowns); use {others}")


def petsc_error_message(exc, opts, comm):
    """One line for a PETSc error raised while setting up or running the solver, naming the
    option whose value caused it where the message allows."""
    text = petsc_error_text()
    values = {str(v).strip(): n for n, v in opts.getAll().items() if v is not None}
    m = re.search(r"Unable to find requested (\S+) type (\S+)", text)
    if m:
        kind, value = m.group(1), m.group(2)
        option = values.get(value, f"{kind.lower()}_type")
        return (f"-{option} {value}: this PETSc has no {kind} type {value} (a misspelling, or a "
                f"package PETSc was built without){_did_you_mean(value, _known(kind))}")
    m = re.search(r"Input string (\S+) has no (\w+) value", text)
    if m:
        option = values.get(m.group(1), "?")
        what = "an integer" if m.group(2) == "integer" else "a number"
        return f"-{option} {m.group(1)}: not {what} (PETSc reads {what} here)"
    m = re.search(r"Could not locate solver type (\S+) for factorization type (\S+) and matrix "
                  r"type (\S+)", text)
    if m:
        option = values.get(m.group(1), "pc_factor_mat_solver_type")
        return (f"-{option} {m.group(1)}: this PETSc has no {m.group(2)} factorisation of "
                f"rodsnes' Jacobian ({m.group(3)}) by {m.group(1)} (not built with it); use "
                f"petsc (the default) or mumps")
    m = (re.search(r"MatSolverType (\S+) does not support factorization type \S+ for matrix "
                   r"type (\S+)", text)
         or re.search(r"MatSolverType (\S+) does not support matrix type (\S+)", text))
    if m:
        return _unfit_factorisation(m.group(1), m.group(2), values, opts)
    m = re.search(r"Only MAT_SHIFT_NONE and MAT_SHIFT_INBLOCKS are supported for (\w+)", text)
    if m:
        value = next((v for v in ("nonzero", "positive_definite", "NONZERO",
                                  "POSITIVE_DEFINITE") if v in values), "?")
        option = values.get(value, "pc_factor_shift_type")
        return (f"-{option} {value}: the LU of rodsnes' block matrix ({m.group(1)}) shifts none or "
                f"inblocks; use inblocks, or -mat_type aij for {value}")
    m = re.search(r"Unknown or unregistered type: (\S+)", text)
    if m and m.group(1) in values:
        return (f"-{values[m.group(1)]} {m.group(1)}: not a type PETSc knows there (a misspelling, "
                f"or a package PETSc was built without)")
    m = re.search(r"No method (\w+) for Mat of type (\S+)", text)
    if m:
        from rodsnes.solve.linear import is_default
        pc = next((f"-{n} {v}" for n, v in sorted(opts.getAll().items())
                   if n.endswith("pc_type") and v and not is_default(n)), "a preconditioner")
        return (f"{pc}: it needs a matrix operation ({m.group(1)}) that rodsnes' block matrix "
                f"({m.group(2)}) lacks; add -mat_type aij, or use lu (the default)")
    m = re.search(r"Unknown logical value: (\S+)", text)
    if m:
        option = values.get(m.group(1), "?")
        return f"-{option} {m.group(1)}: not true or false"
    return (f"PETSc: {text or exc} (check the PETSc options given; "
            f"run with -help -snes_view to list them)")


def _known(kind):
    try:
        return _type_names(kind)
    except KeyError:
        return ()


def unused_petsc_warnings(given, late, made=None):
    """Warnings for the options of ``given`` (the names the user set) that nothing has read:
    ``late`` False: before the solve, leaving out those read only at the end of a solve
    or by a solver made during the run (LATE_READ, scene.SOLVER_PREFIXES); True: after the
    run, those.  Options read at PetscFinalize are left alone.  ``made``: the prefixes of
    rodsnes' own solvers the run made (linear.solvers_made; None: not known)."""
    from rodsnes import petsc_lib
    from rodsnes.io import scene as scn
    left = petsc_lib.options_left()
    if left is None:
        return []
    rodsnes = {o.name.lower() for o in scn.OPTIONS}
    given = {g.lower() for g in given}
    out = []
    for name, value in sorted(left):
        low = name.lower()
        if (low not in given or low in rodsnes or low in FINALIZE_READ
                or (bool(LATE_READ.search(low)) or low.startswith(scn.SOLVER_PREFIXES)) != late):
            continue
        shown = f"-{name}" + (f" {value}" if value else "")
        close = _closest(low, COMMON_PETSC_OPTIONS)
        other = next((o + low[len(p):] for p, o in SIBLING_PREFIXES if low.startswith(p)), None)
        if other is not None:
            # the stability count of the other kind of run: a planar run's is -planar_stability_
            hint = (f": this run's stability count takes -{other} (a planar run's "
                    f"-planar_stability_, a 3-D run's -stability_)")
        elif low.startswith(tuple(SOLVER_RUNS_WHEN)):
            # a solver of rodsnes' own: one this run did not make (a "did you mean" of the
            # unprefixed option sent the user to the Newton step's solver), or one it made
            # that does not read it (another kind of solver, or misspelt)
            pre = next(p for p in SOLVER_RUNS_WHEN if low.startswith(p))
            rest = low[len(pre):]
            near = _closest(rest, COMMON_PETSC_OPTIONS, pre)
            if made is not None and pre not in made:
                hint = f" (the -{pre} solver runs {SOLVER_RUNS_WHEN[pre]}: this run made none)"
            elif near and rest not in COMMON_PETSC_OPTIONS:
                hint = f": did you mean {near}?"
            else:
                hint = (f" (this run's -{pre} solver does not read it: not an option of its "
                        f"kind of solver)")
        elif low in COMMON_PETSC_OPTIONS or not close:
            hint = " (nothing in this run reads it: it does not apply to this load path or " \
                   "scene, or is misspelt)"
        else:
            hint = f": did you mean {close}?"
        out.append(f"option {shown} was not used{hint}")
    return out


# the stability counts' option prefixes: one of them runs, by the run's kind (planar or 3-D)
SIBLING_PREFIXES = (("stability_", "planar_stability_"), ("planar_stability_", "stability_"))
# rodsnes' other solvers (scene.SOLVER_PREFIXES) and when a run makes them
SOLVER_RUNS_WHEN = {
    "interior_": "on several ranks where contact fills the Jacobian, MUMPS's LU of each "
                 "rank's stretch",
    "estimate_": "where the error estimate is on (-rod_error_estimate)",
    "planar_": "in a planar run (-rod_planar)"}


def _closest(word, names, prefix=""):
    """'-a', '-a or -b' ...: the names closest to word (scene._suggest), or ''; each shown
    behind the options ``prefix`` (-planar_a ...)."""
    from rodsnes.io.scene import _suggest, _or_list
    close = _suggest(word, list(names))
    return _or_list(["-" + prefix + c for c in close]) if close else ""


# the Newton steps' solvers a user may set under a prefix (docs/solver.md, Linear solvers and their options):
# prefix -> the matrix they factor (BAIJ block size, whether -mat_type makes it)
LU_PREFIXES = {"": (6, True), "planar_": (3, False), "estimate_": (6, True)}
# preconditioners that are no solve with -ksp_type preonly (one sweep, one cycle, an incomplete
# factorisation): the Newton step would be garbage (others - lu, redundant, svd, ksp, bjacobi
# with a factorisation in its block - may solve, and are left to the user)
NOT_A_SOLVE = ("none", "jacobi", "pbjacobi", "vpbjacobi", "sor", "eisenstat", "ilu",
               "kaczmarz", "gamg", "ml", "hypre", "mg")
# the stability counts take the inertia from MUMPS's LDL^T (INFOG(12)) or rodsnes' own
INERTIA_PREFIXES = ("stability_", "planar_stability_")


def check_newton_linear_solver(comm):
    """Set up the linear solvers as the options make them, before the Run is built and writes
    anything, instead of failing every load step or being dropped for another step in silence:
    the Newton path's (preonly + LU, solve/linear.py, then the options database) on a small
    matrix of the Jacobian's type (BAIJ, 6 x 6 blocks, or -mat_type's; three blocks per rank),
    and each prefixed LU the user gave options to (-planar_: the in-plane step's, blocks of 3;
    -estimate_: the error estimate's) on one of its own: a KSP, PC or factorisation package
    that does not exist or cannot factor them raises its PETSc.Error here.  The stability
    counts' solvers (-stability_ ...) must be MUMPS's LDL^T (check_solver_kinds).
    Collective."""
    from petsc4py import PETSc
    from rodsnes.solve.linear import user_chose
    check_solver_kinds()
    opts = PETSc.Options()
    for prefix, (bs, mat_type) in LU_PREFIXES.items():
        given = [n for n in opts.getAll() if n.startswith(prefix + "pc_")
                 or n.startswith(prefix + "ksp_")]
        if prefix and not any(user_chose(n) for n in given):
            continue
        kind = opts.getString("mat_type", PETSc.Mat.Type.BAIJ) if mat_type else PETSc.Mat.Type.BAIJ
        _check_linear_solver(comm, prefix, bs, kind)


def check_solver_kinds():
    """The factorisations whose kind rodsnes relies on, refused otherwise, naming the option:
    the stability counts' (INERTIA_PREFIXES) count negative pivots, MUMPS's LDL^T (PCCHOLESKY,
    INFOG(12)) or rodsnes' own where no solver option is given; the Newton steps' (LU_PREFIXES)
    factor a tangent that is not symmetric away from equilibrium, so no Cholesky (PETSc's
    reads one triangle: the helix failed, the cantilever took 986 iterations for 22); the
    interiors' (-interior_) are MUMPS's LU, whose Schur complement the condensation takes."""
    from petsc4py import PETSc
    from rodsnes.io.scene import SceneError
    opts = PETSc.Options()
    given = opts.getString          # (name, default): the default where it is not set
    problems = []
    newton_refused = False
    for prefix in LU_PREFIXES:
        # the in-plane step takes the Newton step's options where it has none of its own (its
        # inherited ones are the Newton step's to refuse, once)
        inherit = prefix == "planar_"
        own_pc, own_ksp = (opts.hasName(prefix + n) for n in ("pc_type", "ksp_type"))
        if inherit and not (own_pc or (own_ksp and not newton_refused)):
            continue
        before = len(problems)
        pc = given(prefix + "pc_type", given("pc_type", "") if inherit else "").lower()
        ksp = given(prefix + "ksp_type", given("ksp_type", "preonly") if inherit else
                    "preonly").lower()
        # the options as given (an inherited one is the unprefixed option)
        pc_opt = prefix + "pc_type" if own_pc else "pc_type"
        ksp_opt = "ksp_type" if inherit and not own_ksp and opts.hasName("ksp_type") \
            else prefix + "ksp_type"
        if pc == "cholesky" or (pc == "icc" and ksp == "preonly"):
            problems.append(f"-{pc_opt} {pc}: the Newton step's tangent is not symmetric "
                            f"away from equilibrium, and {pc} factors one triangle of it; use "
                            f"lu (the default)")
        elif ksp == "preonly" and pc in NOT_A_SOLVE:
            # one application of a preconditioner for the solve: no Newton step (the
            # cantilever with -pc_type jacobi: 9680 iterations, then a failed path)
            problems.append(f"-{pc_opt} {pc}: with -{ksp_opt} preonly (the default) the "
                            f"Newton step would be one application of it, not a solve; use lu "
                            f"(the default), or an iterative -{ksp_opt} (gmres) with it")
        newton_refused = newton_refused or (not prefix and len(problems) > before)
    for name, want in (("interior_pc_type", "lu"), ("interior_pc_factor_mat_solver_type",
                                                     "mumps")):
        if given(name, want).lower() != want:
            problems.append(f"-{name} {given(name, want)}: where contact fills the Jacobian, "
                            f"each rank's stretch is factored by MUMPS's LU, which also gives "
                            f"the Schur complement where the stretches meet; leave -{name} out "
                            f"(-interior_mat_mumps_* options are taken)")
    for prefix in INERTIA_PREFIXES:
        pc = given(prefix + "pc_type", "cholesky").lower()
        package = given(prefix + "pc_factor_mat_solver_type", "mumps").lower()
        if pc != "cholesky":
            problems.append(f"-{prefix}pc_type {pc}: the stability count factors the Hessian "
                            f"by an LDL^T and counts its negative pivots; use cholesky (or "
                            f"leave it out)")
        if package != "mumps":
            problems.append(f"-{prefix}pc_factor_mat_solver_type {package}: the stability count "
                            f"takes the negative pivots from MUMPS's LDL^T; use mumps (or leave "
                            f"it out: rodsnes' own LDL^T where it applies, MUMPS elsewhere)")
    if problems:
        raise SceneError("\n".join(problems))


def _check_linear_solver(comm, prefix, ndof, kind):
    """The KSP of options prefix ``prefix`` set up as the options make it (its LU defaults
    first, taken back after) on a small symmetric positive definite matrix of type ``kind`` and
    block size ``ndof``, every node coupled to the first (an arrow, which a fill-reducing
    ordering permutes): an ordering or a factorisation that cannot take the Jacobian's
    couplings fails here too (PETSc's ICC of BAIJ refuses any ordering but natural)."""
    from petsc4py import PETSc
    A = PETSc.Mat().create(comm=comm)
    A.setOptionsPrefix("rodsnes_solver_check_")         # no -mat_view of this matrix
    A.setSizes(((3 * ndof, None), (3 * ndof, None)), bsize=ndof)
    A.setType(kind)
    n = A.getSize()[0]
    A.setPreallocationNNZ((3 * ndof, n))
    lo, hi = A.getOwnershipRange()
    for i in range(lo, hi):
        if i < ndof:                    # the first node: coupled to every other
            A.setValue(i, i, float(n // ndof + 1))
            for j in range(i + ndof, n, ndof):
                A.setValue(i, j, -1.0)
        else:                           # every other node: coupled to the first
            A.setValue(i, i, 2.0)
            A.setValue(i, i % ndof, -1.0)
    A.assemble()
    from rodsnes.solve.linear import lu_defaults
    added = []                      # the defaults go again once the check is done: the solver
    lu_defaults(comm, prefix, added=added)  # sets them itself and must see what the user chose
    ksp = PETSc.KSP().create(comm=comm)
    try:
        ksp.setOptionsPrefix(prefix)
        ksp.setFromOptions()
        ksp.setOperators(A)
        ksp.setUp()                     # the factorisation, without a solve's monitors and views
    finally:
        ksp.destroy()
        A.destroy()
        for name in added:
            PETSc.Options().delValue(name)


def _load_path(scene):
    """The load path the Run will take (Run._choose_path where there is one, else newton)."""
    choose = getattr(Run, "_choose_path", None)
    return choose(scene) if choose is not None else "newton"


# --------------------------------------------------------------------------- signals
class _signals:
    """SIGINT and SIGTERM raise Interrupted while the run is on (interrupts.handler: not inside
    the writing of the output, interrupts.deferred); the old handlers come back after it."""

    NAMES = (signal.SIGINT, signal.SIGTERM)

    def __enter__(self):
        self.old = {}
        try:
            for s in self.NAMES:
                self.old[s] = signal.signal(s, interrupts.handler)
        except ValueError:          # not the main thread: leave signals alone
            pass
        return self

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)
        return False


# --------------------------------------------------------------------------- main
def small_pages_for_numpy():
    """numpy asks the kernel for transparent huge pages for every large array
    (madvise(MADV_HUGEPAGE)); under the kernels' usual setting (transparent_hugepage/defrag
    "madvise") each first touch of such an array may then wait for the kernel to compact
    memory into 2 MB pages.  A run makes large arrays once per pattern (the chain LU's factors,
    the element tangents' chunks, the error estimate's enriched problem): the cantilever's
    default run at 10^4 elements took 3.37-3.43 s with them and 3.06-3.17 s without (the first
    factorisation of the estimate's matrix 217 against 56 ms), the Newton iterations no
    slower (25.6-26.1 against 26.2-29.3 ms; docs/speed.md).  So the run's process gives 4 kB
    pages to numpy, unless NUMPY_MADVISE_HUGEPAGE is set (numpy's own switch, then
    followed)."""
    if "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return
    import numpy
    core = getattr(numpy, "_core", None) or getattr(numpy, "core", None)
    setter = getattr(getattr(core, "multiarray", None), "_set_madvise_hugepage", None)
    if setter is not None:
        setter(False)


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    small_pages_for_numpy()
    rank = _rank_from_env()
    problems = command_line_problems(argv) + options_file_problems(argv)
    if problems:
        _say(rank, "error", "\n".join(problems))
        return EXIT_REFUSED
    failed = _start_petsc(argv)
    if failed:
        _say(rank, "error", failed)
        return EXIT_REFUSED
    from petsc4py import PETSc
    from rodsnes.io import scene as scn
    comm = PETSc.COMM_WORLD
    rank = comm.getRank()
    opts = PETSc.Options()
    given = set(opts.getAll())              # what the user set (the solvers add defaults)
    if opts.hasName("help") or opts.hasName("h"):
        if rank == 0:
            print(scn.help_text(), flush=True)
            print("PETSc's own options (-snes_*, -ksp_*, -pc_*, -mat_*, -log_view ...) work as "
                  "usual; run with -help -snes_view to list them.", flush=True)
        return 0
    # a communicator of its own for the ranks' agreement after an error (_failed): the ranks
    # still waiting in a collective of the solver's communicator never take part in it
    agree = comm.tompi4py().Dup()
    try:
        with _signals():
            try:
                run = _prepare(argv, comm, opts, rank, given)
            except scn.SceneError as err:
                _say(rank, "error", err)
                return EXIT_REFUSED
            except PETSc.Error as err:
                return _failed(agree, None, petsc_error_message(err, opts, comm),
                               code=EXIT_REFUSED)
            except Interrupted as sig:
                _say(rank, "error", f"interrupted by {sig.name} before the run started")
                return 128 + sig.signum
            except Exception as exc:  # noqa: BLE001 - a defect: said, never a hang (_failed)
                return _failed(agree, None, *_internal(exc, None, agree), code=EXIT_INTERNAL)
            try:
                ok = run.execute()
            except Interrupted as sig:
                return _interrupted(run, sig)
            except scn.SceneError as err:       # a trial of -rod_tolerance's that cannot run
                return _failed(agree, run, str(err), code=EXIT_REFUSED)
            except PETSc.Error as err:
                return _failed(agree, run, petsc_error_message(err, opts, comm),
                               code=EXIT_REFUSED)
            except Exception as exc:  # noqa: BLE001 - a defect: said, never a hang (_failed)
                return _failed(agree, run, *_internal(exc, run, agree), code=EXIT_INTERNAL)
    finally:
        agree.Free()            # every rank is here (a rank that stopped alone aborted)
    from rodsnes.solve.linear import solvers_made
    for line in unused_petsc_warnings(given, late=True, made=solvers_made()):
        _say(rank, "warning", line)
    _release_petsc_objects(comm)
    return 0 if ok else EXIT_FAILED


def _all_ranks_reach(agree):
    """Whether every rank of ``agree`` reaches this point within AGREE_SECONDS: a non-blocking
    barrier on a communicator of its own, which a rank still inside a collective of the
    solver (waiting for the rank that raised) never joins."""
    if agree.size == 1:
        return True
    req = agree.Ibarrier()
    t_end = time.monotonic() + AGREE_SECONDS
    while not req.Test():
        if time.monotonic() > t_end:
            return False
        time.sleep(0.002)
    return True


def _internal(exc, run, agree):
    """(line, traceback) of an internal error (an exception no part of rodsnes expected): its
    type, message and rank (of ``agree``), and where its traceback is (DIR/error_rank<r>.txt,
    to be reported; where there is no output directory yet, the traceback text, printed
    after the line)."""
    import traceback
    rank, size = agree.rank, agree.size
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    where, trailer = "printed below", text
    outdir = getattr(run, "outdir", None)
    if outdir and os.path.isdir(outdir):
        path = os.path.join(outdir, f"error_rank{rank}.txt")
        try:
            with open(path, "w") as fh:
                fh.write(text)
            where, trailer = path, None
        except OSError:
            pass
    on = f" on rank {rank} of {size}" if size > 1 else ""
    return (f"internal error{on}: {type(exc).__name__}: {exc} (a defect of rodsnes: please "
            f"report it with the options and the traceback, {where})"), trailer


def _failed(agree, run, message, trailer=None, code=EXIT_FAILED):
    """The end of a run stopped by an error (PETSc's, or an internal one: ``message`` and the
    ``trailer`` printed after it): the message, the last converged step kept (summary.json
    marked failed; result.h5 holds the steps written), exit ``code``.  Every rank that raised
    gets here; those that did not are waiting in a collective for it, and would wait for ever.
    So the ranks first agree (_all_ranks_reach): where all stopped alike (bad options, a defect
    every rank meets) rank 0 says it and writes the summary; where one rank stopped alone it
    says so itself, marks the summary itself, and aborts the job (MPI_Abort with ``code``): a
    nonzero exit, never a hang.  A signal meanwhile is dropped: the run is ending already."""
    rank = agree.rank
    with interrupts.deferred(keep=False):
        together = _all_ranks_reach(agree)
        if together:
            if run is not None:
                run.record_error(message)
            _say(rank, "error", message)
            if trailer and rank == 0:
                print(trailer, file=sys.stderr, flush=True)
            return code
        if run is not None:
            run.record_error(message, by_this_rank=True)
        tell("error", message)
        if trailer:
            print(trailer, file=sys.stderr, flush=True)
        print(f"rodsnes: error: the other ranks did not stop within {AGREE_SECONDS:g} s: the "
              f"job is aborted (exit code {code})", file=sys.stderr, flush=True)
        agree.Abort(code)
    return code


def _release_petsc_objects(comm):
    """Destroy, on every rank together, the PETSc objects parked in petsc4py's garbage so far
    (handles the run dropped; petsc4py 3.18 parks an object on a parallel communicator instead
    of destroying it, and PetscFinalize destroys what is parked on every rank).  Collective:
    the end of a run that every rank reaches.  Without it the bench coil on 2 ranks hung at
    exit under -log_view or -options_left: one rank waited in MPI_Comm_dup for PetscFinalize's
    viewer while the other was in MPI_Finalize (the ranks' PETSc copies of the communicator
    freed unevenly; the object that made the difference was not identified).  With it that
    run, the Euler column, rollup_contact and the plectoneme end (tests/test_finalize_views.py)."""
    import gc
    from rodsnes import petsc_lib
    gc.collect()
    petsc_lib.release_garbage(comm)


def _prepare(argv, comm, opts, rank, given):
    """Everything before the solve: the scene, its checks, the output directory, the Run,
    its linear solver set up once, the scene record, the warnings.  Returns the Run."""
    from rodsnes.io import results as output
    from rodsnes.io import scene as scn
    from rodsnes.run import Run
    scn.check_unknown_options(opts)
    scene = scn.read_scene(argv, opts)
    scn.check_solvable(scene)
    problems = petsc_option_problems(opts)
    if problems:
        raise scn.SceneError("\n".join(problems))
    check_newton_linear_solver(comm)        # both load paths factor the tangent with it
    why = output.check_output_dir(scene.output.dir) if rank == 0 else None
    why = comm.tompi4py().bcast(why, root=0)
    if why:
        raise scn.SceneError(f"-output_dir {scene.output.dir}: {why}", ("-output_dir",))
    run = Run(scene, comm)
    run.record_scene()
    for line in scn.unused_options(scene, opts, path=getattr(run, "path", None)):
        _say(rank, "warning", line)
    for line in unused_petsc_warnings(given, late=False):
        _say(rank, "warning", line)
    return run


def _interrupted(run, sig):
    """A run stopped by SIGINT/SIGTERM: summary.json marked interrupted (by whichever rank
    gets here: not collective), one line, exit 128 + signal (every rank, under MPI)."""
    try:
        with interrupts.deferred(keep=False):   # a second signal: the run is ending already
            run.record_interruption(sig.name)
    except Exception as exc:  # noqa: BLE001 - the exit must happen whatever the disk says
        tell("warning", f"summary.json not marked interrupted: {exc}")
    _say(run.rank, "error", f"interrupted by {sig.name}; the steps written stay in "
                            f"{run.outdir}/result.h5 and summary.json says so: go on with "
                            f"-restart {run.outdir}")
    code = 128 + sig.signum
    if run.comm.getSize() > 1:
        time.sleep(0.5)             # let the other ranks mark it too before the abort
        run.mpi.Abort(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
