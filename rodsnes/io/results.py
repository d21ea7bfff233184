"""Results on disk: one HDF5 file per run, a ParaView time series, a JSON summary.

Everything a run leaves in its output directory ``DIR``:

``DIR/result.h5`` (format ``rodsnes-result-1``; the contract between solver, restart and tools)
    Root attributes
        ``format``      ``'rodsnes-result-1'``
        ``case_name``   str, name of the case
        ``closed``      bool, True for a ring (node n-1 is joined to node 0 by an element)
        ``length``      float, reference (stress-free) arclength L of the rod [length]
        ``radius``      float, cross-section radius [length] (used for contact and pictures)
        ``nelem``       int, number of elements
        ``order``       int, Lagrange degree p of the elements
        ``n_nodes``     int, number of nodes n (nelem*p + 1 open, nelem*p closed)
        ``last_step``   int, index of the newest *complete* step (-1: none yet). Readers trust only
                        steps ``<= last_step``: it is set after the step's data is written and flushed.
        ... plus every key of the ``meta`` dict the solver passes (material, loads, options, ...);
        dicts, lists of mixed type and None are stored as JSON strings.
    Group ``steps/KKKKK`` per converged load step K = 0, 1, ... (step 0 = initial configuration at load 0)
        node datasets (n, ...), row i = natural node id i (node i sits at arclength s_i along the rod):
            ``positions`` (n,3) float64   centreline r_i in the global (spatial) frame [length]
            ``directors`` (n,3,3) float64 R_i, rotation from the material to the global frame;
                                          column j of R_i is the director d_(j+1) (d3 ~ tangent)
            optional, as delivered by the solver, e.g.
            ``rotation`` (n,4)  the unit quaternion (w, x, y, z) of R_i as the solver holds it: a restart
                                resumes from it bit for bit (from ``directors`` where it is absent)
            ``strain_v`` (n,3)  material translational strain v = R^T r' (1 - v3 = axial strain) [-]
            ``strain_u`` (n,3)  material curvature u = vee(R^T R'): u1, u2 bending, u3 twist [1/length]
            ``force_n``  (n,3)  stress resultant force n in the global frame [force]
            ``moment_m`` (n,3)  stress resultant moment m in the global frame [force*length]
        quadrature-point datasets (nq,), row q = global quadrature-point id:
            ``qp_s``          arclength of the quadrature point in the reference configuration [length]
            ``gap``           gap function d = 2a - |r(s) - r(sbar)| of the slides, a the tube's radius (positive:
                              penetration; -1e300 where no candidate is near) [length]
            ``contact_force`` contact line-force magnitude [force/length]
        every dataset carries an attribute ``centering`` = ``'node'`` or ``'qp'`` (and ``description``
        for the fields listed above).
        group attributes: ``load`` (load factor lambda), ``energy`` (total potential energy [force*length]),
        ``newton_iterations``, ``residual_norm`` (2-norm of the final residual), plus any extra attribute
        the solver passes (``writhe``, ``twist``, ``link``, ``error_estimate_tip`` and
        ``error_estimate_centreline`` [length]: the a-posteriori estimate, solve/estimate.py, ...).

``DIR/rod.xdmf`` + ``DIR/rod.h5``
    The same steps as a ParaView/VisIt time series (meshio's XDMF TimeSeriesWriter); see :func:`write_xdmf`.

``DIR/summary.json``
    What the solver reports at the end of a run; see :func:`write_summary`.

Crash safety: result.h5 is closed after every step, so a run killed at any point leaves every
step ``<= last_step`` readable; ``ResultWriter(..., append=True)`` reopens it for a restart and deletes
groups newer than ``last_step``. The XDMF pair is rewritten into a temporary directory and moved into
place, so ``rod.xdmf`` never references data that is not in ``rod.h5``.
"""
import contextlib
import json
import math
import os
import shutil
import tempfile
import time
import warnings
import xml.etree.ElementTree as ET

import numpy as np

from rodsnes.collective import on_root

FORMAT = "rodsnes-result-1"
RESULT_FILE = "result.h5"
SUMMARY_FILE = "summary.json"
XDMF_FILE = "rod.xdmf"
XDMF_SHARE = 0.02       # largest share of a run's wall time spent rewriting rod.xdmf (ResultWriter)
XDMF_CACHE_BYTES = 256 * 2 ** 20   # point data of converted steps a writer keeps (XdmfCache)
XDMF_H5 = "rod.h5"

REQUIRED_META = ("case_name", "closed", "length", "radius", "nelem", "order")
REQUIRED_STEP_ATTRS = ("load", "energy", "newton_iterations", "residual_norm")
REQUIRED_NODE_FIELDS = {"positions": (3,), "directors": (3, 3)}
# keys of the dict returned by read_step that are not fields
RESERVED_NAMES = ("step", "attrs", "meta", "node_fields", "qp_fields")

FIELD_DOC = {
    "positions": "centreline position r, global frame [length]",
    "directors": "rotation R material->global; column j = director d_(j+1), d3 ~ tangent [-]",
    "rotation": "unit quaternion (w, x, y, z) of R as the solver holds it (a restart resumes "
                "from it bit for bit) [-]",
    "strain_v": "material translational strain v = R^T r' (shear v1, v2; stretch v3) [-]",
    "strain_u": "material curvature u = vee(R^T R') (bending u1, u2; twist u3) [1/length]",
    "force_n": "stress resultant force n, global frame [force]",
    "moment_m": "stress resultant moment m, global frame [force*length]",
    "qp_s": "reference arclength of the quadrature point [length]",
    "gap": "gap function d = 2a - distance to the closest point, a the contact tube's radius "
           "(positive: penetration; "
           "-1e300: no candidate near) [length]",
    "contact_force": "contact line-force magnitude at the quadrature point [force/length]",
}


# --------------------------------------------------------------------------- small helpers
class _SerialComm:
    """The part of an mpi4py communicator this module uses, for serial use without MPI."""

    rank = 0
    size = 1

    def bcast(self, obj, root=0):
        return obj

    def gather(self, obj, root=0):
        return [obj]

    def allgather(self, obj):
        return [obj]

    def allreduce(self, obj, op=None):
        return obj

    def Barrier(self):
        pass


def _as_comm(comm):
    """mpi4py communicator from None (serial), a petsc4py Comm or an mpi4py Comm."""
    if comm is None:
        return _SerialComm()
    if hasattr(comm, "tompi4py"):
        return comm.tompi4py()
    return comm


def _h5py():
    import h5py

    return h5py


def _open_h5(path, mode, **kw):
    """h5py.File without HDF5's advisory file lock.

    The writer must never fail because a reader (render.py on a running job) holds the file, and a
    reader must not block the writer; consistency comes from the ``last_step`` protocol instead.
    """
    h5py = _h5py()
    try:
        return h5py.File(path, mode, locking=False, **kw)
    except TypeError:  # h5py/HDF5 without the locking switch
        return h5py.File(path, mode, **kw)


def _collective(comm, fn, *args):
    """Run ``fn`` on rank 0 only (collective.on_root) and re-raise its exception on every rank as
    a RuntimeError naming it (no deadlock on error); every rank returns rank 0's result."""
    try:
        return on_root(comm, fn, *args)
    except Exception as exc:  # noqa: BLE001 - said the same way on every rank
        if comm.size == 1:
            raise
        raise RuntimeError(f"rank 0 failed: {type(exc).__name__}: {exc}") from None


def _attr_value(v):
    """A value h5py can store as an attribute (dict/None/mixed lists become JSON strings)."""
    if isinstance(v, (str, bytes, bool, int, float, np.generic)):
        return v
    if v is None or isinstance(v, dict):
        return json.dumps(to_jsonable(v))
    if isinstance(v, (list, tuple, np.ndarray)):
        a = np.asarray(v)
        if a.dtype.kind in "biuf" and a.size > 0:
            return a
        return json.dumps(to_jsonable(v))
    return str(v)


def _from_attr(v):
    """Plain Python value of an HDF5 attribute."""
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray):
        return v
    if isinstance(v, np.generic):
        return v.item()
    return v


def to_jsonable(obj):
    """Plain JSON types from numpy scalars/arrays, tuples, paths; non-finite floats become None."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return str(obj)


def _step_name(step):
    return f"{int(step):05d}"


def _runs(ids):
    """Start and length of the runs of consecutive integers in a sorted id array."""
    if len(ids) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    brk = np.flatnonzero(np.diff(ids) != 1) + 1
    starts = np.concatenate([[0], brk])
    lens = np.diff(np.concatenate([starts, [len(ids)]]))
    return ids[starts], lens


def _select_rows(space, ids, starts, lens, shape):
    """Select the rows ``ids`` (sorted) of an (N,)+shape HDF5 dataspace.

    A union of hyperslabs (one per run of consecutive ids) when the runs are few, as for a
    partition into chains; a point selection when they are many (interleaved ids), because HDF5's
    OR-ing of many hyperslabs costs O(runs^2) (10k runs: seconds; points: milliseconds).
    """
    from h5py import h5s

    space.select_none()
    if len(ids) == 0:
        return
    if len(starts) <= 64:
        zeros = (0,) * len(shape)
        for st, ln in zip(starts.tolist(), lens.tolist()):
            space.select_hyperslab((st,) + zeros, (ln,) + shape, op=h5s.SELECT_OR)
        return
    inner = np.indices(shape).reshape(len(shape), -1).T if shape else np.zeros((1, 0), np.int64)
    k = len(inner)
    coords = np.empty((len(ids) * k, 1 + len(shape)), np.uint64)
    coords[:, 0] = np.repeat(ids, k)
    coords[:, 1:] = np.tile(inner, (len(ids), 1))
    space.select_elements(coords)


# --------------------------------------------------------------------------- writer
class ResultWriter:
    """Writes ``DIR/result.h5`` (and, by default, the XDMF time series) step by step.

    Parameters
    ----------
    outdir : str or Path
        Output directory (created if missing).
    comm : mpi4py/petsc4py communicator or None (serial)
        Every method is collective over it.
    n_nodes : int
        Global number of nodes.
    meta : dict
        Run description stored as root attributes; must hold ``case_name``, ``closed``, ``length``,
        ``radius``, ``nelem``, ``order`` (see the module docstring); any other key is stored too.
    append : bool
        False: start a new file (an old result.h5, rod.xdmf/rod.h5 and summary.json are removed).
        True: restart: reopen the existing result.h5 (``n_nodes`` must match), keep steps
        ``<= last_step``, delete newer (partial) step groups (summary.json is removed, rod.xdmf kept);
        the next step must be ``last_step + 1``; root attribute ``restarted_after_step`` records it.
    xdmf : bool
        Keep ``rod.xdmf``/``rod.h5`` up to date (rank 0).  The whole series is rewritten each time
        (cost grows with the number of steps), so after a step it is rewritten only while the
        rewrites so far took at most ``XDMF_SHARE`` (2 %) of the writer's wall time, and at
        :meth:`close` when steps were left out: a long run's view lags by a bounded share of its
        time instead of costing O(steps^2) (regenerate it at any moment with
        ``python -m rodsnes.io.results DIR``).  The writer keeps the converted point data of the
        steps (``XdmfCache``, up to XDMF_CACHE_BYTES), so a rewrite reads and converts only the
        new steps from result.h5 (at 527 steps of 181 nodes 0.77 s against 3.65 s).  With False
        call :func:`write_xdmf` at the end.
    parallel_io : bool or None
        None (default): collective MPI-IO (h5py ``mpio`` driver) when ``comm.size > 1`` and h5py is built
        with MPI, else gather to rank 0. False forces the gather (e.g. on file systems without MPI-IO).
    """

    def __init__(self, outdir, comm, n_nodes, meta, append=False, xdmf=True, parallel_io=None):
        self.comm = _as_comm(comm)
        self.outdir = os.fspath(outdir)
        self.path = os.path.join(self.outdir, RESULT_FILE)
        self.n_nodes = int(n_nodes)
        self.xdmf = bool(xdmf)
        self._xdmf_budget = RewriteBudget()   # time spent rewriting rod.xdmf/rod.h5 (rank 0)
        self._xdmf_stale = False        # a step is in result.h5 but not in rod.xdmf yet
        self._xdmf_cache = XdmfCache()  # converted steps, so that a rewrite reads only new ones
        mpi_h5 = bool(_h5py().get_config().mpi)
        if parallel_io and not mpi_h5:
            raise RuntimeError("parallel_io=True but h5py has no MPI support (run under mpirun?)")
        self.parallel = self.comm.size > 1 and mpi_h5 and parallel_io is not False
        self._checked_owned = {}
        meta = dict(meta or {})
        missing = [k for k in REQUIRED_META if k not in meta]
        if missing:
            raise ValueError(f"ResultWriter: meta lacks {missing} (required: {list(REQUIRED_META)})")
        bad = [k for k in meta if k in ("format", "last_step", "n_nodes")]
        if bad:
            raise ValueError(f"ResultWriter: meta keys {bad} are set by the writer itself")
        self.meta = meta
        if append:
            self.last_step = _collective(self.comm, self._reopen)
        else:
            _collective(self.comm, self._create)
            self.last_step = -1
        self.comm.Barrier()

    # -- file set-up (rank 0) --
    def _root_attrs(self):
        attrs = {"format": FORMAT, "n_nodes": self.n_nodes}
        for k, v in self.meta.items():
            attrs[k] = v
        attrs["closed"] = bool(attrs["closed"])
        return attrs

    def _remove_stale(self, names=(SUMMARY_FILE, XDMF_FILE, XDMF_H5)):
        for name in names:
            p = os.path.join(self.outdir, name)
            if os.path.exists(p):
                os.remove(p)

    def _create(self):
        os.makedirs(self.outdir, exist_ok=True)
        self._remove_stale()
        with _open_h5(self.path, "w") as f:
            for k, v in self._root_attrs().items():
                f.attrs[k] = _attr_value(v)
            f.attrs["last_step"] = -1
            f.create_group("steps")

    def _reopen(self):
        if not os.path.exists(self.path):
            raise FileNotFoundError(f"append=True but {self.path} does not exist")
        with _open_h5(self.path, "a") as f:
            fmt = _from_attr(f.attrs.get("format", ""))
            if fmt != FORMAT:
                raise ValueError(f"{self.path}: format {fmt!r}, expected {FORMAT!r}")
            n_old = int(f.attrs["n_nodes"])
            if n_old != self.n_nodes:
                raise ValueError(f"{self.path}: has {n_old} nodes, the restarted run has {self.n_nodes}")
            last = int(f.attrs["last_step"])
            steps = f.require_group("steps")
            for name in list(steps.keys()):
                if int(name) > last:
                    del steps[name]
            for k, v in self._root_attrs().items():
                f.attrs[k] = _attr_value(v)
            f.attrs["restarted_after_step"] = last
        # the summary described the earlier process; rod.xdmf holds only steps <= last_step: it stays
        self._remove_stale((SUMMARY_FILE,))
        return last

    # -- validation (collective, consistent on every rank) --
    def _check_owned(self, kind, ids, n_total):
        prev = self._checked_owned.get(kind)
        same = prev is not None and prev.shape == ids.shape and np.array_equal(prev, ids)
        if self.comm.allreduce(0 if same else 1) == 0:
            return
        ok_local = bool(len(ids) == 0 or (ids.min() >= 0 and ids.max() < n_total))
        if not all(self.comm.allgather(ok_local)):
            raise ValueError(f"{kind} ids out of range [0, {n_total})")
        counts = np.bincount(ids, minlength=n_total).astype(np.int32)
        if self.comm.size > 1:
            from mpi4py import MPI

            total = np.empty_like(counts)
            self.comm.Allreduce(counts, total, op=MPI.SUM)
        else:
            total = counts
        if not np.all(total == 1):
            raise ValueError(
                f"{kind} ids must be disjoint across ranks and cover 0..{n_total - 1}: "
                f"{int(np.sum(total == 0))} missing, {int(np.sum(total > 1))} duplicated"
            )
        self._checked_owned[kind] = ids.copy()

    def _specs(self, kind, fields, n_own):
        """Global (name, trailing shape, dtype) of each field, checked to agree on all ranks."""
        local = {}
        for name, a in (fields or {}).items():
            a = np.asarray(a)
            if name in RESERVED_NAMES:
                raise ValueError(f"field name {name!r} is reserved")
            if a.shape[:1] != (n_own,) and not (n_own == 0 and a.size == 0):
                raise ValueError(f"{kind} field {name!r}: {a.shape[0] if a.ndim else 'scalar'} rows, "
                                 f"expected {n_own} (one per owned {kind})")
            kind_ = "f" if a.dtype.kind in "fc" or a.size == 0 else a.dtype.kind
            local[name] = (a.shape[1:] if a.size or a.ndim > 1 else None, kind_)
        everyone = self.comm.allgather(local)
        names = sorted(everyone[0])
        if any(sorted(d) != names for d in everyone):
            raise ValueError(f"{kind} fields differ between ranks: {[sorted(d) for d in everyone]}")
        specs = []
        for name in names:
            shapes = {d[name][0] for d in everyone if d[name][0] is not None}
            kinds = {d[name][1] for d in everyone}
            if len(shapes) > 1:
                raise ValueError(f"{kind} field {name!r}: trailing shapes differ between ranks {shapes}")
            shape = shapes.pop() if shapes else ()
            dtype = np.float64 if "f" in kinds or not kinds <= set("iub") else np.int64
            if name in REQUIRED_NODE_FIELDS and kind == "node" and shape != REQUIRED_NODE_FIELDS[name]:
                raise ValueError(f"node field {name!r} must be (n,{','.join(map(str, REQUIRED_NODE_FIELDS[name]))})"
                                 f", got trailing shape {shape}")
            specs.append((name, tuple(shape), dtype))
        return specs

    # -- the step --
    def write_step(self, step, attrs, owned_nodes, node_fields, qp_owned=None, qp_fields=None, n_qp=None):
        """Write one converged load step (collective) and commit it (``last_step = step``).

        step : int, must be ``last_step + 1``. The first step of a new file is normally 0 (the initial
            configuration); a run restarted from another directory may start its new file at k > 0.
        attrs : dict with ``load``, ``energy``, ``newton_iterations``, ``residual_norm`` and any extra
            scalars (``writhe``, ``twist``, ``link``, ...); rank 0's dict is written.
        owned_nodes : int array, this rank's natural node ids (disjoint across ranks, union = all nodes,
            any order).
        node_fields : dict name -> array (len(owned_nodes), ...), rows in the order of owned_nodes; must
            hold ``positions`` (.,3) and ``directors`` (.,3,3) (see the module docstring for the others).
        qp_owned, qp_fields, n_qp : the same for quadrature-point fields (global qp ids 0..n_qp-1);
            n_qp defaults to the sum of len(qp_owned) over ranks.
        """
        step = int(step)
        if step < 0 or (self.last_step >= 0 and step != self.last_step + 1):
            raise ValueError(f"write_step({step}): steps are written in order, next is {self.last_step + 1}")
        attrs = self.comm.bcast(dict(attrs) if self.comm.rank == 0 else None, root=0)
        missing = [k for k in REQUIRED_STEP_ATTRS if k not in attrs]
        if missing:
            raise ValueError(f"write_step: attrs lack {missing} (required: {list(REQUIRED_STEP_ATTRS)})")

        owned = np.asarray(owned_nodes, dtype=np.int64).ravel()
        self._check_owned("node", owned, self.n_nodes)
        node_specs = self._specs("node", node_fields, len(owned))
        absent = [k for k in REQUIRED_NODE_FIELDS if k not in {s[0] for s in node_specs}]
        if absent:
            raise ValueError(f"write_step: node_fields lack {absent}")
        groups = [("node", owned, self.n_nodes, node_specs, node_fields)]

        has_qp = self.comm.allreduce(1 if qp_fields else 0)
        if has_qp:
            qp_ids = np.asarray(qp_owned if qp_owned is not None else [], dtype=np.int64).ravel()
            nq = self.comm.allreduce(len(qp_ids)) if n_qp is None else int(n_qp)
            self._check_owned("qp", qp_ids, nq)
            qp_specs = self._specs("qp", qp_fields or {}, len(qp_ids))
            clash = {s[0] for s in qp_specs} & {s[0] for s in node_specs}
            if clash:
                raise ValueError(f"names used for both node and qp fields: {sorted(clash)}")
            groups.append(("qp", qp_ids, nq, qp_specs, qp_fields or {}))

        # sort this rank's rows by global id once per group
        prepared = []
        for kind, ids, n_total, specs, fields in groups:
            order = np.argsort(ids, kind="stable")
            prepared.append((kind, ids[order], order, n_total, specs, fields))

        if self.parallel:
            self._write_parallel(step, attrs, prepared)
        else:
            self._write_gathered(step, attrs, prepared)
        self.last_step = step
        if self.xdmf and self.comm.rank == 0:
            self._xdmf_stale = True
            if self._xdmf_budget.due(XDMF_SHARE):
                self._update_xdmf()

    def _update_xdmf(self):
        """Rewrite rod.xdmf/rod.h5 from result.h5 (rank 0), timing it."""
        with self._xdmf_budget.spent():
            try:
                write_xdmf(self.outdir, cache=self._xdmf_cache)
                self._xdmf_stale = False
            except Exception as exc:  # noqa: BLE001 - result.h5 is complete; the view is derived
                warnings.warn(f"rod.xdmf not updated after step {self.last_step}: "
                              f"{type(exc).__name__}: {exc} (regenerate with: "
                              f"python -m rodsnes.io.results {self.outdir})")

    def _group_setup(self, f, step, attrs):
        steps = f.require_group("steps")
        name = _step_name(step)
        if name in steps:  # leftover of an interrupted write (never committed)
            del steps[name]
        g = steps.create_group(name)
        for k, v in attrs.items():
            g.attrs[k] = _attr_value(v)
        return g

    @staticmethod
    def _dataset(g, kind, name, n_total, shape, dtype):
        d = g.create_dataset(name, shape=(n_total,) + shape, dtype=dtype)
        d.attrs["centering"] = kind
        if name in FIELD_DOC:
            d.attrs["description"] = FIELD_DOC[name]
        return d

    def _commit(self, f, step):
        """Make the step visible to readers: data flushed first, then ``last_step``."""
        f.flush()
        f.attrs["last_step"] = step
        f.flush()

    def _write_parallel(self, step, attrs, prepared):
        from h5py import h5fd, h5p, h5s

        f = _open_h5(self.path, "a", driver="mpio", comm=self.comm)
        try:
            g = self._group_setup(f, step, attrs)
            dxpl = h5p.create(h5p.DATASET_XFER)
            dxpl.set_dxpl_mpio(h5fd.MPIO_COLLECTIVE)
            for kind, ids, order, n_total, specs, fields in prepared:
                starts, lens = _runs(ids)
                for name, shape, dtype in specs:
                    d = self._dataset(g, kind, name, n_total, shape, dtype)
                    rows = np.asarray(fields[name], dtype=dtype).reshape((len(ids),) + shape)
                    rows = np.ascontiguousarray(rows[order])
                    fspace = d.id.get_space()
                    _select_rows(fspace, ids, starts, lens, shape)
                    if len(ids):
                        mspace = h5s.create_simple(rows.shape)
                    else:  # nothing owned: take part in the collective call with an empty selection
                        rows = np.zeros((1,) + shape, dtype)
                        mspace = h5s.create_simple(rows.shape)
                        mspace.select_none()
                    d.id.write(mspace, fspace, rows, dxpl=dxpl)
            self._commit(f, step)
        finally:
            f.close()

    def _gather_rows(self, ids, rows):
        """Rank 0: (all ids, all rows) concatenated over ranks; others: (None, None)."""
        if self.comm.size == 1:
            return ids, rows
        from mpi4py import MPI

        counts = self.comm.gather(len(ids), root=0)
        row_bytes = int(np.prod(rows.shape[1:], dtype=np.int64)) * rows.itemsize
        if self.comm.rank == 0:
            n = int(sum(counts))
            all_ids = np.empty(n, np.int64)
            all_rows = np.empty((n,) + rows.shape[1:], rows.dtype)
            c = np.asarray(counts, np.int64)
            disp = np.concatenate([[0], np.cumsum(c)[:-1]])
            self.comm.Gatherv(ids, [all_ids, c, disp, MPI.INT64_T], root=0)
            self.comm.Gatherv(rows.view(np.uint8).ravel(),
                              [all_rows.view(np.uint8).ravel(), c * row_bytes, disp * row_bytes, MPI.BYTE],
                              root=0)
            return all_ids, all_rows
        self.comm.Gatherv(ids, None, root=0)
        self.comm.Gatherv(rows.view(np.uint8).ravel(), None, root=0)
        return None, None

    def _write_gathered(self, step, attrs, prepared):
        """Gather each field to rank 0, which writes it.  Every rank takes part in every
        gather whatever happens on rank 0 (a file rank 0 cannot open: the step's error is
        said on every rank after the gathers, none is left waiting in one)."""
        f = g = None
        err = None
        if self.comm.rank == 0:
            try:
                f = _open_h5(self.path, "a")
                g = self._group_setup(f, step, attrs)
            except Exception as exc:  # noqa: BLE001 - reported on all ranks below
                if f is not None:
                    f.close()
                    f = None
                if self.comm.size == 1:
                    raise
                err = f"{type(exc).__name__}: {exc}"
        try:
            for kind, ids, order, n_total, specs, fields in prepared:
                for name, shape, dtype in specs:
                    rows = np.ascontiguousarray(
                        np.asarray(fields[name], dtype=dtype).reshape((len(ids),) + shape)[order])
                    all_ids, all_rows = self._gather_rows(ids, rows)
                    if self.comm.rank == 0 and err is None:
                        try:
                            full = np.empty((n_total,) + shape, dtype)
                            full[all_ids] = all_rows
                            self._dataset(g, kind, name, n_total, shape, dtype)[...] = full
                        except Exception as exc:  # noqa: BLE001 - reported on all ranks below
                            err = f"{type(exc).__name__}: {exc}"
            if self.comm.rank == 0 and err is None:
                self._commit(f, step)
        except Exception as exc:  # noqa: BLE001
            if self.comm.size == 1:
                raise
            err = err or f"{type(exc).__name__}: {exc}"
        finally:
            if f is not None:
                f.close()
        err = self.comm.bcast(err, root=0)
        if err is not None:
            raise RuntimeError(f"writing step {step} of {self.path} failed on rank 0: {err}")

    def add_meta(self, extra):
        """Store more root attributes (e.g. the scene record) in result.h5 (collective)."""
        extra = {k: v for k, v in dict(extra).items() if k not in ("format", "last_step", "n_nodes")}
        self.meta.update(extra)

        def _add():
            with _open_h5(self.path, "a") as f:
                for k, v in extra.items():
                    f.attrs[k] = _attr_value(v)

        _collective(self.comm, _add)

    def add_step_attrs(self, step, extra):
        """Store more attributes of a written step (e.g. the Newton path's end count) in
        result.h5 (collective)."""
        def _add():
            with _open_h5(self.path, "a") as f:
                g = f["steps"][_step_name(step)]
                for k, v in dict(extra).items():
                    g.attrs[k] = _attr_value(v)

        _collective(self.comm, _add)

    def close(self):
        """Bring rod.xdmf/rod.h5 up to date if steps were left out (rank 0); nothing else stays
        open between steps (collective)."""
        if self.xdmf and self.comm.rank == 0 and self._xdmf_stale:
            self._update_xdmf()
        self.comm.Barrier()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# --------------------------------------------------------------------------- summary
def write_summary(outdir, comm, summary):
    """Rank 0 writes ``DIR/summary.json`` atomically (temporary file, fsync, os.replace); collective.

    numpy scalars/arrays become plain JSON numbers/lists; NaN and infinities become ``null`` (strict JSON).
    The solver's keys: converged, load, energy, tip_position [x,y,z], newton_iterations, load_steps,
    wall_time_s, dofs, ranks.
    """
    _collective(_as_comm(comm), _write_summary_file, outdir, summary)


def _write_summary_file(outdir, summary):
    """summary.json written atomically: a temporary file, fsync, os.replace (any one process)."""
    os.makedirs(outdir, exist_ok=True)
    text = json.dumps(to_jsonable(summary), indent=2, sort_keys=True, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=".summary_", suffix=".json.tmp", dir=outdir)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, os.path.join(outdir, SUMMARY_FILE))
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def mark_interrupted(outdir, signal_name, base=None, extra=None):
    """Record in DIR/summary.json that the run was stopped by ``signal_name`` (not collective:
    any process that catches the signal may call it; the write is atomic).  The summary the run
    wrote after its last converged step is kept and marked ``"interrupted": true``, ``"signal"``,
    ``"converged": false`` and a ``failure`` that says where to go on from; ``base`` is the
    summary to start from when there is none yet, ``extra`` keys (e.g. the wall time) are set
    in any case.  Returns the summary written."""
    try:
        summary = read_summary(outdir)
    except (OSError, ValueError):
        summary = dict(base or {})
    last = load = None
    try:
        last, load = _retry_read(outdir, _last_step_load, tries=1)
    except (OSError, ValueError, KeyError, RuntimeError, IndexError):
        pass
    where = (f"the last converged step ({last}, load {load:.6f}) is in "
             f"{os.path.join(outdir, RESULT_FILE)}: go on with -restart {outdir}"
             if last is not None else "no step was written")
    summary.update(extra or {})
    if last is not None:
        summary["last_step"] = last
    summary.update(converged=False, interrupted=True, signal=signal_name,
                   failure=f"interrupted by {signal_name}; {where}")
    _write_summary_file(outdir, summary)
    return summary


def _last_step_load(f):
    k = _steps_of(f)[-1]
    return k, float(_from_attr(f["steps"][_step_name(k)].attrs["load"]))


def check_output_dir(outdir):
    """Why ``outdir`` cannot take a run's results (None if it can): it is a file, lies under a
    file, cannot be created, or cannot be written.  Creates the directory if missing."""
    path = os.path.abspath(outdir)
    if os.path.exists(path) and not os.path.isdir(path):
        return "is a file, not a directory; give a directory (it is created if missing)"
    parent = path
    while parent and not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if parent and not os.path.isdir(parent):
        return f"lies under {parent}, which is a file; give a directory path"
    try:
        os.makedirs(path, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".rodsnes_probe_", dir=path)
        os.close(fd)
        os.remove(probe)
    except OSError as exc:
        return f"cannot be written ({exc.strerror or exc}); give a directory you may write in"
    return None


def read_summary(outdir):
    """The dict of ``DIR/summary.json``."""
    with open(os.path.join(outdir, SUMMARY_FILE)) as fh:
        return json.load(fh)


# --------------------------------------------------------------------------- readers
def _retry_read(outdir, fn, tries=20, wait=0.25):
    """Open result.h5 read-only and apply fn; retry a little if a writer is mid-step."""
    path = os.path.join(outdir, RESULT_FILE)
    if not os.path.exists(path):
        raise FileNotFoundError(path)
    for i in range(tries):
        try:
            with _open_h5(path, "r") as f:
                if _from_attr(f.attrs.get("format", "")) != FORMAT:
                    raise ValueError(f"{path} is not a {FORMAT} file")
                return fn(f)
        except (OSError, KeyError, RuntimeError) as exc:
            if i == tries - 1 or _damaged(exc):
                raise
            time.sleep(wait)


DAMAGE_SIGNS = ("truncated file", "file signature not found", "bad object header",
                "bad symbol table", "is not a directory", "permission denied")


def _damaged(exc):
    """An error that waiting for a writer will not cure: a file cut short (a copy that stopped,
    a full disk), not an HDF5 file, unreadable."""
    text = str(exc).lower()
    return any(sign in text for sign in DAMAGE_SIGNS)


def _steps_of(f):
    last = int(f.attrs["last_step"])
    have = f["steps"].keys() if "steps" in f else []
    return sorted(int(k) for k in have if int(k) <= last)


def read_meta(outdir):
    """Root attributes of ``DIR/result.h5`` as a dict of plain Python values."""
    return _retry_read(outdir, lambda f: {k: _from_attr(v) for k, v in f.attrs.items()})


def read_steps(outdir):
    """Indices of the complete steps (``<= last_step``) in ``DIR/result.h5``, ascending."""
    return _retry_read(outdir, _steps_of)


def _read_group(f, step):
    steps = _steps_of(f)
    if not steps:
        raise ValueError("no complete step in the file")
    k = steps[step] if step < 0 else int(step)
    if k not in steps:
        raise KeyError(f"step {k} is not complete (complete: {steps[0]}..{steps[-1]})")
    g = f["steps"][_step_name(k)]
    out = {"step": k, "attrs": {a: _from_attr(v) for a, v in g.attrs.items()},
           "meta": {a: _from_attr(v) for a, v in f.attrs.items()}}
    node, qp = [], []
    for name, d in g.items():
        out[name] = d[()]
        (qp if _from_attr(d.attrs.get("centering", "node")) == "qp" else node).append(name)
    out["node_fields"] = tuple(sorted(node))
    out["qp_fields"] = tuple(sorted(qp))
    return out


def read_step(outdir, step=-1):
    """One complete step of ``DIR/result.h5`` (serial).

    ``step`` is a step index, or negative to count from the newest complete step (-1 = last).
    Returns a dict: ``step`` (int), ``attrs`` (load, energy, ...), ``meta`` (root attributes),
    ``positions`` (n,3), ``directors`` (n,3,3), every other dataset by name, and the tuples
    ``node_fields`` / ``qp_fields`` naming which datasets are per node and per quadrature point.
    """
    return _retry_read(outdir, lambda f: _read_group(f, step))


def read_history(outdir, steps=None):
    """All complete steps (or the given ones) as a list of read_step dicts, one file open."""
    def _all(f):
        ks = _steps_of(f) if steps is None else list(steps)
        return [_read_group(f, k) for k in ks]

    return _retry_read(outdir, _all)


def read_step_attrs(outdir):
    """(step, attrs) of every complete step, attributes only: no datasets read (a long path)."""
    def _attrs(f):
        return [(k, {a: _from_attr(v) for a, v in f["steps"][_step_name(k)].attrs.items()})
                for k in _steps_of(f)]

    return _retry_read(outdir, _attrs)


# --------------------------------------------------------------------------- derived node data
def node_arclength(meta):
    """Reference arclength of the nodes, assuming the uniform mesh with equispaced Lagrange nodes
    (node i at s_i = i L / (n-1) on an open rod, i L / n on a closed one)."""
    n = int(meta["n_nodes"])
    L = float(meta["length"])
    closed = bool(meta["closed"])
    return np.arange(n) * (L / (n if closed else max(n - 1, 1)))


def qp_to_nodes(qp_s, values, node_s, period=None):
    """Value at each node of its nearest quadrature point in reference arclength (no averaging).

    ``period`` (the length of a closed rod) makes the distance periodic. Vectorised (searchsorted).
    """
    qp_s = np.asarray(qp_s, float)
    values = np.asarray(values)
    node_s = np.asarray(node_s, float)
    order = np.argsort(qp_s, kind="stable")
    s_sorted = qp_s[order]
    nq = len(s_sorted)
    j = np.searchsorted(s_sorted, node_s)
    left = np.clip(j - 1, 0, nq - 1)
    right = np.clip(j, 0, nq - 1)
    cand = [left, right]
    if period:
        cand += [np.zeros_like(j), np.full_like(j, nq - 1)]  # wrap-around candidates
    best = cand[0]
    best_d = np.full(node_s.shape, np.inf)
    for c in cand:
        d = np.abs(s_sorted[c] - node_s)
        if period:
            d = np.minimum(d, period - d)
        take = d < best_d
        best = np.where(take, c, best)
        best_d = np.where(take, d, best_d)
    return values[order[best]]


# --------------------------------------------------------------------------- XDMF
def _xdmf_writer_class():
    import meshio

    class _Writer(meshio.xdmf.TimeSeriesWriter):
        """meshio 5's TimeSeriesWriter with three fixes: the .h5 is created next to the .xdmf (meshio
        opens it relative to the working directory), datasets get deterministic names (so an older
        .xdmf stays consistent with a newer .h5), and Polyline topologies say NodesPerElement=2."""

        def __enter__(self):
            self.h5_filename = str(self.filename.with_suffix(".h5"))
            self.h5_file = _open_h5(self.h5_filename, "w")
            self._name = None
            return self

        def numpy_to_xml_string(self, data):
            name = self._name
            self._name = None
            if name is None:  # not through our named paths: fall back to meshio's numbering
                return super().numpy_to_xml_string(data)
            self.h5_file.create_dataset(name, data=data)
            return os.path.basename(self.h5_filename) + ":/" + name

        def write_points_cells(self, points, cells):
            grid = ET.SubElement(self.domain, "Grid", Name=self.mesh_name, GridType="Uniform")
            self._name = "mesh/points"
            self.points(grid, np.asarray(points))
            self._name = "mesh/cells"
            self.cells(cells, grid)
            for topo in grid.iter("Topology"):
                if topo.get("TopologyType") == "Polyline":
                    topo.set("NodesPerElement", "2")
            self.has_mesh = True

        def write_named(self, t, prefix, point_data):
            grid = ET.SubElement(self.collection, "Grid")
            ptr = f'xpointer(//Grid[@Name="{self.mesh_name}"]/*[self::Topology or self::Geometry])'
            ET.SubElement(grid, "{http://www.w3.org/2003/XInclude}include", xpointer=ptr)
            ET.SubElement(grid, "Time", Value=repr(float(t)))
            for name, data in point_data.items():
                self._name = f"{prefix}/{name}"
                self.point_data({name: data}, grid)

    return _Writer


def xdmf_point_data(step, ref_positions, meta):
    """Point data of one step as exported to XDMF (all (n,) or (n,k) float64, global frame):

    ``displacement`` = positions - positions of the file's first step (the XDMF geometry is its
    centreline: step 0 of a run; for a restart into a new directory the first step it wrote,
    the one after the resumed step; apply
    ParaView's *Warp By Vector* with it to see the deformed rod), ``d1``, ``d2``, ``d3`` (the
    directors), every other node field under its own name ((n,3,3) fields as three columns
    ``name_1..3``), and every quadrature-point field except ``qp_s`` interpolated to the nodes by
    taking the *nearest quadrature point* in reference arclength (``gap``, ``contact_force``).
    """
    pd = {"displacement": step["positions"] - ref_positions}
    R = step["directors"]
    for j in range(3):
        pd[f"d{j + 1}"] = np.ascontiguousarray(R[:, :, j])
    for name in step["node_fields"]:
        if name in ("positions", "directors", "rotation"):     # rotation: d1, d2, d3 again
            continue
        a = np.asarray(step[name], dtype=np.float64)
        if a.ndim == 3:
            for j in range(a.shape[2]):
                pd[f"{name}_{j + 1}"] = np.ascontiguousarray(a[:, :, j])
        else:
            pd[name] = a.reshape(len(a), -1) if a.ndim > 2 else a
    if step["qp_fields"] and "qp_s" in step:
        s_nodes = node_arclength(meta)
        period = float(meta["length"]) if bool(meta["closed"]) else None
        for name in step["qp_fields"]:
            if name == "qp_s":
                continue
            pd[name] = np.asarray(qp_to_nodes(step["qp_s"], step[name], s_nodes, period), np.float64)
    return pd


class RewriteBudget:
    """The time spent on a file that is rewritten whole to stay current (rod.xdmf; the run's
    summary.json), kept within a share of the wall time since ``start`` (default: now): a
    rewrite is ``due(share)`` while the rewrites so far took at most that share; ``spent()``
    times one."""

    def __init__(self, start=None):
        self.start = time.perf_counter() if start is None else float(start)
        self.seconds = 0.0

    def due(self, share):
        return self.seconds <= share * (time.perf_counter() - self.start)

    @contextlib.contextmanager
    def spent(self):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds += time.perf_counter() - t0


class XdmfCache:
    """Point data of steps already converted for rod.xdmf (xdmf_point_data), by step, up to
    ``limit`` bytes (steps beyond it are read from result.h5 at every rewrite).  Valid for one
    reference (step 0's positions, ``for_reference`` at every rewrite): another one empties it."""

    def __init__(self, limit=None):
        self.limit = XDMF_CACHE_BYTES if limit is None else int(limit)
        self.data, self.nbytes, self.ref = {}, 0, None

    def for_reference(self, ref):
        if self.ref is None or self.ref.shape != ref.shape or not np.array_equal(self.ref, ref):
            self.data, self.nbytes, self.ref = {}, 0, np.array(ref, copy=True)

    def get(self, step):
        return self.data.get(step)

    def put(self, step, point_data):
        n = sum(a.nbytes for a in point_data.values())
        if self.nbytes + n <= self.limit:
            self.data[step] = point_data
            self.nbytes += n


def write_xdmf(outdir, cache=None):
    """(Re)write ``DIR/rod.xdmf`` + ``DIR/rod.h5`` from every complete step of ``DIR/result.h5``.

    Serial (the writer calls it on rank 0); returns the number of steps written. The rod is a polyline
    (meshio cell type ``line``, one segment per pair of consecutive nodes, closing segment n-1 -> 0
    for a closed rod) on the file's first step's centreline (xdmf_point_data); time = load factor (or the step index if the loads are
    not strictly increasing, e.g. after an unloading path; an ``Information`` element in the file
    says which). Point data: see :func:`xdmf_point_data`. Both files are written into a temporary
    directory inside DIR and moved into place with os.replace, .h5 first: datasets have names fixed
    per step and field, so at every moment the .xdmf on disk references only data present in the .h5
    on disk. Steps are streamed one at a time (memory of one step), but the whole series is rewritten.
    ``cache``: an :class:`XdmfCache` whose steps are not read and converted again (ResultWriter's).
    """
    outdir = os.fspath(outdir)

    def _write(f):
        steps = _steps_of(f)
        if not steps:
            return 0
        first = _read_group(f, steps[0])
        meta = first["meta"]
        n = int(meta["n_nodes"])
        ref = first["positions"]
        seg = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
        if bool(meta["closed"]) and n > 2:
            seg = np.vstack([seg, [[n - 1, 0]]])
        loads = np.array([float(f["steps"][_step_name(k)].attrs["load"]) for k in steps])
        use_load = len(loads) < 2 or bool(np.all(np.diff(loads) > 0))
        times = loads if use_load else np.asarray(steps, float)

        Writer = _xdmf_writer_class()
        tmpdir = tempfile.mkdtemp(prefix=".rod_xdmf_", dir=outdir)
        try:
            xdmf_tmp = os.path.join(tmpdir, XDMF_FILE)
            with Writer(xdmf_tmp) as w:
                info = ET.SubElement(w.domain, "Information", Name="time",
                                     Value="load factor" if use_load else "step index (loads not increasing)")
                info.text = ("rodsnes: geometry = the first step of result.h5; apply Warp By "
                             "Vector with 'displacement'")
                w.write_points_cells(ref, [("line", seg.astype(np.int64))])
                if cache is not None:
                    cache.for_reference(ref)
                for k, t in zip(steps, times):
                    pd = cache.get(k) if cache is not None else None
                    if pd is None:
                        h = first if k == steps[0] else _read_group(f, k)
                        pd = xdmf_point_data(h, ref, meta)
                        if cache is not None:
                            cache.put(k, pd)
                    w.write_named(t, f"step{k:05d}", pd)
            os.replace(os.path.join(tmpdir, XDMF_H5), os.path.join(outdir, XDMF_H5))
            os.replace(xdmf_tmp, os.path.join(outdir, XDMF_FILE))
        finally:
            shutil.rmtree(tmpdir, ignore_errors=True)
        return len(steps)

    return _retry_read(outdir, _write)


def _main(argv=None):
    """``python -m rodsnes.io.results DIR``: regenerate rod.xdmf/rod.h5 from result.h5."""
    import argparse

    ap = argparse.ArgumentParser(description=_main.__doc__)
    ap.add_argument("outdir")
    args = ap.parse_args(argv)
    n = write_xdmf(args.outdir)
    print(f"wrote {os.path.join(args.outdir, XDMF_FILE)} ({n} steps)")


if __name__ == "__main__":
    _main()
