"""rodsnes.io.results: result.h5 round trip, restart after a partial step, summary.json, XDMF, MPI-IO."""
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the package may not be pip-installed yet
    sys.path.insert(0, str(ROOT))

from rodsnes.io import results as output  # noqa: E402
from rodsnes.model.so3 import frame_from_tangent  # noqa: E402

N = 17          # nodes
NQ = 24         # quadrature points
META = dict(case_name="fake", closed=False, length=2.0, radius=0.05, nelem=8, order=2,
            E=np.float64(1e6), nu=0.3, note=None, options={"-rod_nelem": 8})


def fake_step(k, n=N, nq=NQ, closed=False):
    """Deterministic step data: a rod bending in the x-y plane with k, fields with known values."""
    L = META["length"]
    s = np.arange(n) * L / (n if closed else n - 1)
    ang = 0.4 * k * s
    pos = np.stack([s * np.cos(ang), s * np.sin(ang), 0.01 * k * s**2], axis=1)
    R = frame_from_tangent(np.gradient(pos, axis=0))
    node = dict(positions=pos, directors=R,
                strain_v=np.stack([0 * s, 0 * s, 1 + 1e-3 * k + 0 * s], axis=1),
                strain_u=np.stack([0.1 * k + s, -s, 0.5 * k + 0 * s], axis=1),
                force_n=np.outer(s, [1.0, 2.0, 3.0]) * k,
                moment_m=np.outer(np.cos(s), [0.0, 0.0, 1.0]) * k)
    qs = (np.arange(nq) + 0.5) * L / nq
    qp = dict(qp_s=qs, gap=np.sin(qs) - 0.1 * k, contact_force=np.maximum(0.1 * k - np.sin(qs), 0.0))
    attrs = dict(load=np.float64(0.5 * k), energy=np.float32(k * 1.5), newton_iterations=np.int64(4 + k),
                 residual_norm=10.0 ** (-9 - k), writhe=0.01 * k, link=np.int32(2))
    return attrs, node, qp


def write_run(outdir, comm=None, steps=3, node_ids=None, qp_ids=None, n=N, nq=NQ, **kw):
    node_ids = np.arange(n) if node_ids is None else np.asarray(node_ids)
    qp_ids = np.arange(nq) if qp_ids is None else np.asarray(qp_ids)
    w = output.ResultWriter(outdir, comm, n, META, **kw)
    for k in range(steps):
        attrs, node, qp = fake_step(k, n, nq)
        w.write_step(k, attrs, node_ids, {a: v[node_ids] for a, v in node.items()},
                     qp_owned=qp_ids, qp_fields={a: v[qp_ids] for a, v in qp.items()}, n_qp=nq)
    w.close()
    return w


def check_steps(outdir, steps=3, n=N, nq=NQ):
    assert output.read_steps(outdir) == list(range(steps))
    meta = output.read_meta(outdir)
    assert meta["format"] == "rodsnes-result-1" and meta["last_step"] == steps - 1
    assert meta["n_nodes"] == n and meta["closed"] is False and meta["length"] == 2.0
    assert meta["case_name"] == "fake" and meta["nelem"] == 8 and meta["order"] == 2
    assert json.loads(meta["options"]) == {"-rod_nelem": 8} and meta["E"] == 1e6
    for k in range(steps):
        attrs, node, qp = fake_step(k, n, nq)
        got = output.read_step(outdir, k)
        assert got["step"] == k
        for a, v in attrs.items():
            assert got["attrs"][a] == v, a
        assert set(got["node_fields"]) == set(node) and set(got["qp_fields"]) == set(qp)
        for a, v in {**node, **qp}.items():
            assert got[a].dtype == np.float64
            np.testing.assert_array_equal(got[a], v, err_msg=a)
    assert output.read_step(outdir)["step"] == steps - 1
    assert output.read_step(outdir, -2)["step"] == steps - 2
    assert output.read_step_attrs(outdir) == [(k, output.read_step(outdir, k)["attrs"])
                                              for k in range(steps)]


def test_roundtrip_scrambled_ownership(tmp_path):
    rng = np.random.default_rng(1)
    write_run(tmp_path, node_ids=rng.permutation(N), qp_ids=rng.permutation(NQ))
    check_steps(tmp_path)
    with h5py.File(tmp_path / "result.h5", "r") as f:
        d = f["steps/00001/positions"]
        assert d.attrs["centering"] == "node" and "global frame" in d.attrs["description"]
        assert f["steps/00001/gap"].attrs["centering"] == "qp"


def test_validation(tmp_path):
    with pytest.raises(ValueError, match="radius"):
        output.ResultWriter(tmp_path, None, N, {k: v for k, v in META.items() if k != "radius"})
    w = output.ResultWriter(tmp_path, None, N, META)
    attrs, node, _ = fake_step(0)
    with pytest.raises(ValueError, match="next is 0"):
        w.write_step(-1, attrs, np.arange(N), node)
    with pytest.raises(ValueError, match="residual_norm"):
        w.write_step(0, {"load": 0.0, "energy": 0.0, "newton_iterations": 0}, np.arange(N), node)
    ids = np.arange(N)
    ids[3] = 4  # node 3 missing, node 4 twice
    with pytest.raises(ValueError, match="1 missing, 1 duplicated"):
        w.write_step(0, attrs, ids, node)
    with pytest.raises(ValueError, match="directors"):
        w.write_step(0, attrs, np.arange(N), {"positions": node["positions"]})
    with pytest.raises(ValueError, match="rows"):
        w.write_step(0, attrs, np.arange(N), {**node, "positions": node["positions"][:-1]})
    assert output.read_steps(tmp_path) == []
    w.write_step(0, attrs, np.arange(N), node)
    with pytest.raises(ValueError, match="next is 1"):
        w.write_step(2, attrs, np.arange(N), node)


def _partial_step(outdir, step):
    """What a run killed while writing `step` leaves: a group without the last_step update."""
    with h5py.File(Path(outdir) / "result.h5", "a") as f:
        g = f.create_group(f"steps/{step:05d}")
        g.create_dataset("positions", data=np.full((N, 3), np.nan))


def test_append_drops_partial_step(tmp_path):
    write_run(tmp_path, steps=2)
    _partial_step(tmp_path, 2)
    assert output.read_steps(tmp_path) == [0, 1]   # readers ignore the partial group
    assert output.read_step(tmp_path)["step"] == 1
    w = output.ResultWriter(tmp_path, None, N, META, append=True)
    assert w.last_step == 1
    assert (tmp_path / "rod.xdmf").exists()   # it only ever holds complete steps: kept on restart
    with h5py.File(tmp_path / "result.h5", "r") as f:
        assert "00002" not in f["steps"]
    attrs, node, qp = fake_step(2)
    w.write_step(2, attrs, np.arange(N), node, np.arange(NQ), qp)
    check_steps(tmp_path, 3)
    with pytest.raises(ValueError, match="nodes"):
        output.ResultWriter(tmp_path, None, N + 1, META, append=True)
    with pytest.raises(FileNotFoundError):
        output.ResultWriter(tmp_path / "nothing", None, N, META, append=True)


@pytest.mark.parametrize("where", ["before_commit", "mid_datasets"])
def test_killed_run_keeps_earlier_steps(tmp_path, where):
    """A process SIGKILLed while writing step 2 leaves steps 0, 1 readable and restartable."""
    hook = {
        "before_commit": "output.ResultWriter._commit = lambda self, f, step: (f.flush(), die()) "
                         "if step == 2 else orig_commit(self, f, step)",
        "mid_datasets": "output.ResultWriter._dataset = staticmethod(lambda g, kind, name, *a: die() "
                        "if g.name.endswith('00002') and name == 'strain_u' else orig_dataset(g, kind, name, *a))",
    }[where]
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path[:0] = [{str(ROOT)!r}, {str(Path(__file__).parent)!r}]
        from rodsnes.io import results as output
        import test_output as t
        def die():
            os.kill(os.getpid(), signal.SIGKILL)
        orig_commit = output.ResultWriter._commit
        orig_dataset = output.ResultWriter._dataset
        {hook}
        t.write_run({str(tmp_path)!r}, steps=3)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert res.returncode == -9, res.stderr
    assert output.read_steps(tmp_path) == [0, 1]
    check_steps(tmp_path, 2)
    # the XDMF view of the killed run is readable and holds only committed steps (it may lag:
    # rewrites take a bounded share of the run's time); regenerated, it holds them all
    import meshio
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "rod.xdmf")) as r:
        r.read_points_cells()
        assert 1 <= r.num_steps <= 2
    assert output.write_xdmf(tmp_path) == 2
    w = output.ResultWriter(tmp_path, None, N, META, append=True)
    attrs, node, qp = fake_step(2)
    w.write_step(2, attrs, np.arange(N), node, np.arange(NQ), qp)
    check_steps(tmp_path, 3)


def test_summary_json(tmp_path):
    summary = dict(converged=np.bool_(True), load=np.float64(1.0), energy=np.float32(2.5),
                   tip_position=np.array([1.0, 2.0, 3.0]), newton_iterations=np.int64(17),
                   load_steps=np.int32(4), wall_time_s=1.25, dofs=np.int64(102), ranks=2,
                   residual_norm=float("nan"), history=[(np.int8(1), np.float16(0.5))])
    output.write_summary(tmp_path, None, summary)
    text = (tmp_path / "summary.json").read_text()
    got = json.loads(text)  # strict JSON (no NaN token)
    assert "NaN" not in text
    assert got["converged"] is True and got["tip_position"] == [1.0, 2.0, 3.0]
    assert got["newton_iterations"] == 17 and got["energy"] == 2.5 and got["residual_norm"] is None
    assert got["history"] == [[1, 0.5]]
    assert output.read_summary(tmp_path) == got
    assert sorted(os.listdir(tmp_path)) == ["summary.json"]  # no temporary file left


def test_new_run_removes_stale_outputs(tmp_path):
    write_run(tmp_path, steps=2)
    output.write_summary(tmp_path, None, {"converged": True})
    output.ResultWriter(tmp_path, None, N, META)   # a new run in the same directory
    assert not (tmp_path / "summary.json").exists() and not (tmp_path / "rod.xdmf").exists()
    assert output.read_steps(tmp_path) == []


def test_qp_to_nodes_nearest_and_periodic():
    qs = np.array([0.9, 0.1, 0.5])          # unsorted on purpose
    vals = np.array([9.0, 1.0, 5.0])
    nodes = np.array([0.0, 0.29, 0.31, 0.69, 0.99])
    np.testing.assert_array_equal(output.qp_to_nodes(qs, vals, nodes), [1, 1, 5, 5, 9])
    # on a ring of length 1, s = 0.0 is 0.1 from the qp at 0.9 and 0.1 from 0.1: tie -> either;
    # s = 0.02 is nearer 0.1 (0.08) than 0.9 (0.12); s = 0.97 nearer 0.9 (0.07) than 0.1 (0.13)
    np.testing.assert_array_equal(output.qp_to_nodes(qs, vals, [0.02, 0.97, 0.96], period=1.0), [1, 9, 9])
    np.testing.assert_array_equal(output.qp_to_nodes([0.1, 0.8], [1.0, 8.0], [0.98], period=1.0), [1.0])


def test_xdmf_time_series(tmp_path):
    import meshio
    write_run(tmp_path)
    assert sorted(os.listdir(tmp_path)) == ["result.h5", "rod.h5", "rod.xdmf"]  # no tmp left over
    xml = (tmp_path / "rod.xdmf").read_text()
    assert 'NodesPerElement="2"' in xml and "rod.h5:/" in xml
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "rod.xdmf")) as r:
        points, cells = r.read_points_cells()
        assert r.num_steps == 3
        np.testing.assert_array_equal(points, fake_step(0)[1]["positions"])
        assert cells[0].type == "line" and len(cells[0].data) == N - 1
        np.testing.assert_array_equal(cells[0].data[:, 1] - cells[0].data[:, 0], 1)
        for k in range(3):
            t, pd, _ = r.read_data(k)
            attrs, node, qp = fake_step(k)
            assert t == attrs["load"]
            assert set(pd) == {"displacement", "d1", "d2", "d3", "strain_v", "strain_u", "force_n",
                               "moment_m", "gap", "contact_force"}
            np.testing.assert_allclose(pd["displacement"] + points, node["positions"], rtol=0, atol=1e-15)
            for j in range(3):
                np.testing.assert_array_equal(pd[f"d{j + 1}"], node["directors"][:, :, j])
            np.testing.assert_array_equal(pd["strain_u"], node["strain_u"])
            s_nodes = np.arange(N) * META["length"] / (N - 1)
            nearest = np.argmin(np.abs(qp["qp_s"][None, :] - s_nodes[:, None]), axis=1)
            np.testing.assert_array_equal(pd["gap"], qp["gap"][nearest])


def test_xdmf_rewrites_take_a_bounded_share_and_close_catches_up(tmp_path, monkeypatch):
    """The series is rewritten whole, so a long run rewrites it only while that took at most
    XDMF_SHARE of its time; close() writes the steps left out.  With the share 0 only step 0
    gets in before close."""
    import meshio
    monkeypatch.setattr(output, "XDMF_SHARE", 0.0)
    w = output.ResultWriter(tmp_path, None, N, META)
    for k in range(4):
        attrs, node, qp = fake_step(k)
        w.write_step(k, attrs, np.arange(N), node, np.arange(NQ), qp, n_qp=NQ)
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "rod.xdmf")) as r:
        r.read_points_cells()
        assert r.num_steps == 1
    w.close()
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "rod.xdmf")) as r:
        r.read_points_cells()
        assert r.num_steps == 4
        assert r.read_data(3)[0] == fake_step(3)[0]["load"]


def test_xdmf_closed_ring_and_non_monotone_load(tmp_path):
    import meshio
    meta = dict(META, closed=True)
    w = output.ResultWriter(tmp_path, None, N, meta)
    for k, load in enumerate([0.0, 1.0, 0.5]):   # unloading: time falls back to the step index
        attrs, node, _ = fake_step(k, closed=True)
        w.write_step(k, dict(attrs, load=load), np.arange(N), node)
    w.close()
    with meshio.xdmf.TimeSeriesReader(str(tmp_path / "rod.xdmf")) as r:
        _, cells = r.read_points_cells()
        assert len(cells[0].data) == N and list(cells[0].data[-1]) == [N - 1, 0]
        assert [r.read_data(k)[0] for k in range(3)] == [0.0, 1.0, 2.0]
    assert "step index" in (tmp_path / "rod.xdmf").read_text()


# --------------------------------------------------------------------------- MPI
@pytest.mark.mpi
@pytest.mark.parametrize("parallel_io,n,nq,layout", [(None, N, NQ, "interleaved"), (False, N, NQ, "interleaved"),
                                                     (None, 401, 600, "interleaved"), (None, N, NQ, "last_owns_all"),
                                                     (False, N, NQ, "last_owns_all")])
def test_mpi_interleaved_matches_serial(parallel_io, n, nq, layout):
    """Each rank owns an interleaved subset of nodes (and qps, reversed); the file equals the serial one.
    (401 nodes: > 64 runs per rank, so MPI-IO uses point selections instead of hyperslabs;
    last_owns_all: the other ranks own nothing and still take part in the collective writes.)"""
    from mpi4py import MPI
    comm = MPI.COMM_WORLD
    base = comm.bcast(tempfile.mkdtemp(prefix="rodsnes_mpi_") if comm.rank == 0 else None, root=0)
    try:
        par, ser = os.path.join(base, "par"), os.path.join(base, "ser")
        if layout == "interleaved":
            node_ids = np.arange(comm.rank, n, comm.size)
            qp_ids = np.arange(comm.rank, nq, comm.size)[::-1]
        else:
            last = comm.rank == comm.size - 1
            node_ids = np.arange(n if last else 0)
            qp_ids = np.arange(nq if last else 0)
        w = write_run(par, comm, node_ids=node_ids, qp_ids=qp_ids, n=n, nq=nq, parallel_io=parallel_io)
        assert w.parallel == (comm.size > 1 and h5py.get_config().mpi and parallel_io is None)
        comm.Barrier()
        ok = None
        if comm.rank == 0:
            try:
                write_run(ser, n=n, nq=nq)
                check_steps(par, n=n, nq=nq)
                with h5py.File(os.path.join(par, "result.h5"), "r") as fp, \
                        h5py.File(os.path.join(ser, "result.h5"), "r") as fs:
                    assert dict(fp.attrs).keys() == dict(fs.attrs).keys()
                    for k in range(3):
                        gp, gs = fp[f"steps/{k:05d}"], fs[f"steps/{k:05d}"]
                        assert sorted(gp) == sorted(gs)
                        assert dict(gp.attrs) == dict(gs.attrs)
                        for name in gs:
                            np.testing.assert_array_equal(gp[name][()], gs[name][()], err_msg=name)
                ok = True
            except BaseException as exc:  # report on every rank, never hang the others
                ok = repr(exc)
        ok = comm.bcast(ok, root=0)
        assert ok is True, ok
    finally:
        comm.Barrier()
        if comm.rank == 0:
            shutil.rmtree(base, ignore_errors=True)


def test_path_report_tables_a_path(tmp_path):
    """tools/path_report.py on a written path: steps, median/max Newton iterations and seconds per
    range of the link, jumps, largest residual and penetration over the path, and the last
    step's contact force distribution (median, 90th percentile, max and where it acts)."""
    sys.path.insert(0, str(ROOT / "tools"))
    import path_report
    its = [0, 3, 5, 40, 7, 9]
    w = output.ResultWriter(str(tmp_path), None, N, META)
    qs = (np.arange(NQ) + 0.5) * META["length"] / NQ
    for k in range(6):
        _, node, _ = fake_step(k)
        f = np.where((qs > 0.5) & (qs < 1.0), 10.0 * qs * k, 0.0)     # acts on (0.5, 1.0)
        attrs = dict(load=0.2 * k, energy=1.0 * k, link=0.5 * k, newton_iterations=its[k],
                     seconds=0.5 * its[k], residual_norm=1e-10 * (k + 1), contact_max_penetration=0.002 * k)
        if k == 3:
            attrs.update(branch_switch=1, jump=1)
        w.write_step(k, attrs, np.arange(N), node, qp_owned=np.arange(NQ),
                     qp_fields=dict(qp_s=qs, gap=f / 1e3, contact_force=f), n_qp=NQ)
    w.close()
    text = path_report.report(str(tmp_path), edges=[0, 1, 2, 3])
    lines = text.splitlines()
    assert "| 0 - 1 | 2 | 4 | 5 | 2 | 0 (0) |" in lines                  # links 0.5, 1.0
    assert "| 1 - 2 | 2 | 23.5 | 40 | 11.8 | 1 (1) |" in lines           # 1.5 (the jump), 2.0
    assert "| 2 - 3 | 1 | 9 | 9 | 4.5 | 0 (0) |" in lines
    assert "5 load steps, 64 Newton iterations" in text
    assert "largest residual of a converged step 6.00e-10 (step 5)" in text
    assert "largest penetration 1.000% of the diameter" in text
    on = f > 0
    dist = path_report.contact_distribution(output.read_step(str(tmp_path), -1))
    assert dist["active"] == on.sum() and dist["max"] == f.max()
    assert dist["median"] == pytest.approx(np.median(f[on]))
    assert dist["intervals"] == [(qs[on][0], qs[on][-1])]


def _xdmf_content(d):
    """rod.xdmf's text and every dataset of rod.h5 (name -> array)."""
    with h5py.File(d / "rod.h5", "r") as f:
        data = {}
        f.visititems(lambda name, obj: data.__setitem__(name, obj[()])
                     if isinstance(obj, h5py.Dataset) else None)
    return (d / "rod.xdmf").read_text(), data


def test_xdmf_rewrite_reads_only_new_steps(tmp_path, monkeypatch):
    """A rewrite with the writer's cache (XdmfCache) gives rod.xdmf and rod.h5 as a rewrite from
    result.h5 alone does, and reads from result.h5 the first step (the reference) and the steps
    not converted before; another reference empties the cache; a cache bounded below one step's
    data keeps nothing."""
    w = write_run(tmp_path, steps=4)
    assert sorted(w._xdmf_cache.data) == [0, 1, 2, 3]     # the writer's rewrites keep them
    fresh = tmp_path / "fresh"
    shutil.copytree(tmp_path, fresh)
    assert output.write_xdmf(fresh) == 4
    text, data = _xdmf_content(fresh)
    cache = output.XdmfCache()
    output.write_xdmf(tmp_path, cache=cache)
    assert sorted(cache.data) == [0, 1, 2, 3] and cache.nbytes > 0
    read = []
    orig = output._read_group
    monkeypatch.setattr(output, "_read_group", lambda f, k: read.append(k) or orig(f, k))
    output.write_xdmf(tmp_path, cache=cache)
    assert read == [0]                           # the reference only
    text2, data2 = _xdmf_content(tmp_path)
    assert text2 == text and data2.keys() == data.keys()
    assert all(np.array_equal(data2[k], data[k]) for k in data)
    cache.for_reference(np.zeros((N, 3)))        # another reference: nothing kept
    assert cache.data == {} and cache.nbytes == 0
    small = output.XdmfCache(limit=1)
    read.clear()
    output.write_xdmf(tmp_path, cache=small)
    output.write_xdmf(tmp_path, cache=small)
    assert small.data == {} and read == [0, 1, 2, 3] * 2


@pytest.mark.mpi
def test_a_step_rank_0_cannot_open_fails_on_every_rank_without_a_stray_message():
    """Gathered writing (parallel_io False): rank 0 cannot open result.h5 (its directory
    removed between two steps): the step's error on every rank, and every rank took part in
    every gather (before, the other ranks' rows were left for rank 0's next collective, or
    they waited in a gather rank 0 never joined)."""
    from mpi4py import MPI
    comm = MPI.COMM_WORLD
    out = comm.bcast(tempfile.mkdtemp(prefix="rodsnes_gathered_") if comm.rank == 0 else None)
    n = 8
    mine = np.arange(comm.rank, n, comm.size)
    fields = {"positions": np.zeros((len(mine), 3)),
              "directors": np.tile(np.eye(3), (len(mine), 1, 1))}
    attrs = {"load": 0.0, "energy": 0.0, "newton_iterations": 0, "residual_norm": 0.0}
    meta = dict(case_name="fake", closed=False, length=1.0, radius=0.01, nelem=n - 1, order=1)
    w = output.ResultWriter(out, comm, n, meta, xdmf=False, parallel_io=False)
    w.write_step(0, attrs, mine, fields)
    comm.Barrier()
    if comm.rank == 0:
        shutil.rmtree(out)
    comm.Barrier()
    if comm.size > 1:
        with pytest.raises(RuntimeError, match="failed on rank 0"):
            w.write_step(1, dict(attrs, load=0.5), mine, fields)
    got = comm.gather(("fresh", comm.rank), root=0)
    if comm.rank == 0:
        assert got == [("fresh", r) for r in range(comm.size)]
