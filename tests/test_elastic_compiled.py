"""The compiled elastic kernel (rodsnes/model/_elastic_kernel.c through rodsnes/model/elastic_compiled.py)
equals the einsum reference of ElasticRod.element_terms to round-off: energy, residual and both
tangents, orders 1-4, full and reduced quadrature, with the curvature bound active or not, on
deformed states whose nodal quaternions come with either sign.

`make install` (pip install -e .) builds the kernel: a missing library is a failure, not a skip."""
import os

import numpy as np
import pytest

from rodsnes.model import elastic, elastic_compiled, so3

STIFF = [3.0, 4.0, 50.0, 1.0, 2.0, 1.5]   # GA1, GA2, EA, EI1, EI2, GJ
TOL = 1e-12


def deformed_elements(p, nq, ne, rng, h=0.3):
    """Consecutive elements of a rod bent and twisted along a smooth rotation field, plus noise;
    nodal quaternions with random signs (node 0 included), reference strains near a straight
    rod."""
    nn = p + 1
    s = (np.arange(ne)[:, None] * p + np.arange(nn)[None, :]) * (h / p)
    theta = np.stack([0.7 * s, 1.3 * np.sin(s), 2.1 * s], axis=-1)
    theta += 0.15 * rng.normal(size=theta.shape)
    qe = so3.qexp(theta)
    qe *= np.where(rng.random((ne, nn)) < 0.4, -1.0, 1.0)[..., None]
    xe = np.stack([s, 0.2 * np.sin(2.0 * s), 0.1 * s**2], axis=-1)
    xe += 0.02 * rng.normal(size=xe.shape)
    e0 = rng.normal(size=(ne, nq, 6)) * 0.1 + [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    return qe, xe, e0


def make_rod(p, nq, ne, rng, bound, elements=deformed_elements):
    """A rod of ``elements`` (qe, xe, e0 of (p, nq, ne, rng)) with their e0; with ``bound`` a
    curvature bound that acts at about 60 % of the points."""
    rod = elastic.ElasticRod(p, nq, 0.3, STIFF)
    qe, xe, e0 = elements(p, nq, ne, rng)
    rod.set_reference(e0)
    if bound:
        kappa = np.linalg.norm(rod.strains(qe, xe)[..., 3:5], axis=-1)
        rod.set_curvature_limit(np.quantile(kappa, 0.4), 30.0)
        assert 0.4 < np.mean(kappa > rod.kappa_max) < 0.8     # the bound acts at many points
    return rod, qe, xe


def assert_same(got, ref, what):
    for name, a, b in zip(("energy", "residual", "tangent"), got, ref):
        if b is None:
            assert a is None, f"{what}: {name} should be None"
            continue
        assert a.dtype == np.float64 and a.shape == b.shape, f"{what}: {name} {a.shape} vs {b.shape}"
        err = np.abs(a - b).max() / np.abs(b).max()
        assert err < TOL, f"{what}: {name} relative error {err:.2e}"


def test_kernel_is_built_in_the_package():
    """pip install -e . puts the shared library where the loader finds it."""
    path = elastic_compiled.library_path()
    assert path is not None, "rodsnes.model._elastic_kernel is not built: run `make install`"
    assert os.path.dirname(path) == os.path.dirname(elastic_compiled.__file__)
    assert elastic_compiled.available()


@pytest.mark.parametrize("bound", [False, True], ids=["free", "curvature_bound"])
@pytest.mark.parametrize("p,nq", [(1, 1), (1, 2), (2, 2), (2, 3), (3, 3), (3, 4), (4, 4), (4, 5)])
def test_compiled_equals_reference(p, nq, bound):
    rng = np.random.default_rng(100 * p + 10 * nq + bound)
    rod, qe, xe = make_rod(p, nq, 40, rng, bound)
    for symmetric in (False, True):
        ref = rod.element_terms_reference(qe, xe, tangent=True, symmetric=symmetric)
        got = elastic_compiled.element_terms(rod, qe, xe, None, True, symmetric)
        assert_same(got, ref, f"p={p} nq={nq} bound={bound} symmetric={symmetric}")
    ref = rod.element_terms_reference(qe, xe, tangent=False)
    got = elastic_compiled.element_terms(rod, qe, xe, None, False, False)
    assert_same(got, ref, f"p={p} nq={nq} bound={bound} residual only")
    # and the batched numpy kernel, on the consistent tangent
    assert_same(elastic_compiled.element_terms(rod, qe, xe),
                rod.element_terms_numpy(qe, xe), f"p={p} nq={nq} bound={bound} vs numpy")
    # the energy alone (the line searches'), per element and summed as ElasticRod.energy does
    en = elastic_compiled.element_energy(rod, qe, xe)
    assert np.abs(en - ref[0]).max() <= TOL * np.abs(ref[0]).max(), f"p={p} nq={nq} energy alone"
    W, _, _ = rod.law(rod.strains(qe, xe), rod.e0)
    assert rod.kernel == "compiled"
    assert abs(rod.energy(qe, xe) - np.sum(W @ rod.wJ)) <= TOL * np.sum(np.abs(W @ rod.wJ))


def test_sign_of_nodal_quaternions_is_irrelevant():
    """q and -q are the same rotation: flipping any node's quaternion (node 0 too) changes
    nothing but the sign convention, which align_signs removes."""
    rng = np.random.default_rng(5)
    rod, qe, xe = make_rod(3, 4, 30, rng, bound=True)
    flipped = qe * np.where(rng.random(qe.shape[:2]) < 0.5, -1.0, 1.0)[..., None]
    a = elastic_compiled.element_terms(rod, qe, xe)
    b = elastic_compiled.element_terms(rod, flipped, xe)
    assert_same(b, a, "flipped signs")


def test_explicit_reference_strains_and_non_contiguous_input():
    """e0 given explicitly overrides rod.e0; strided inputs (a gather such as q[lconn]) work."""
    rng = np.random.default_rng(11)
    rod, qe, xe = make_rod(2, 3, 20, rng, bound=False)
    e0 = rod.e0 + 0.05 * rng.normal(size=rod.e0.shape)
    ref = rod.element_terms_reference(qe, xe, e0)
    got = elastic_compiled.element_terms(rod, np.asfortranarray(qe), xe[:, :, :], e0)
    assert_same(got, ref, "explicit e0")
    assert np.abs(got[0] - rod.element_terms_reference(qe, xe)[0]).max() > 1e-6


def test_curvature_bound_below_every_flexure_and_above_all():
    """The bound active at every point, and set but active nowhere (= no bound)."""
    rng = np.random.default_rng(3)
    rod, qe, xe = make_rod(3, 3, 25, rng, bound=False)
    kappa = np.linalg.norm(rod.strains(qe, xe)[..., 3:5], axis=-1)
    free = elastic_compiled.element_terms(rod, qe, xe)
    rod.set_curvature_limit(0.5 * kappa.min(), 10.0)
    assert_same(elastic_compiled.element_terms(rod, qe, xe), rod.element_terms_reference(qe, xe),
                "bound everywhere")
    assert np.all(elastic_compiled.element_terms(rod, qe, xe)[0] > free[0])
    rod.set_curvature_limit(2.0 * kappa.max(), 10.0)
    assert_same(elastic_compiled.element_terms(rod, qe, xe), free, "bound nowhere")


def test_no_elements():
    rod = elastic.ElasticRod(3, 3, 0.3, STIFF)
    rod.set_reference(np.zeros((0, 3, 6)))
    E, vec, H = elastic_compiled.element_terms(rod, np.zeros((0, 4, 4)), np.zeros((0, 4, 3)))
    assert E.shape == (0,) and vec.shape == (0, 4, 6) and H.shape == (0, 24, 24)
    assert elastic_compiled.element_energy(rod, np.zeros((0, 4, 4)), np.zeros((0, 4, 3))).shape == (0,)
    assert rod.energy(np.zeros((0, 4, 4)), np.zeros((0, 4, 3))) == 0.0


def test_reused_arrays_give_the_same_terms():
    """``reuse`` writes into arrays kept on the rod (RodProblem's residual and Jacobian): the
    same terms as fresh arrays, the same arrays from call to call of one size, new ones when the
    element count changes."""
    rng = np.random.default_rng(7)
    rod, qe, xe = make_rod(3, 4, 30, rng, bound=False)
    fresh = rod.element_terms(qe, xe)
    a = rod.element_terms(qe, xe, reuse=True)
    assert_same(a, fresh, "reused")
    b = rod.element_terms(qe[::-1], xe[::-1], reuse=True)
    assert b[2] is a[2] and b[1] is a[1]
    assert_same(b, rod.element_terms(qe[::-1], xe[::-1]), "reused, other state")
    r = rod.element_terms(qe, xe, tangent=False, reuse=True)
    assert r[2] is None and r[1] is a[1]
    c = rod.element_terms(qe[:10], xe[:10], rod.e0[:10], reuse=True)
    assert c[2].shape == (10, 24, 24)
    with pytest.raises(ValueError, match="out does not match"):
        elastic_compiled.element_terms(rod, qe, xe, out=c)


def test_a_library_older_than_its_source_falls_back_and_the_run_says_so(monkeypatch):
    """A built library that lacks a function its module declares (built from an older source)
    does not load: the numpy kernel runs, and the run's first line says why and what to do."""
    from rodsnes import compiled
    from conftest import build_run

    def declare(lib):
        return lib.no_such_function_in_this_library
    assert compiled.load("rodsnes.model._elastic_kernel", declare) is False
    monkeypatch.setattr(elastic, "compiled_available", lambda: False)
    run = build_run("mattiasson")
    assert run.problem.elastic.kernel == "numpy"
    assert "elastic kernel in numpy" in run.header() and "make install" in run.header()
    monkeypatch.undo()
    assert "elastic kernel" not in build_run("mattiasson").header()


def test_foreign_calls_check_arrays_before_the_call_and_let_signals_through():
    """compiled.Foreign turns arrays into addresses in Python, before the C call: a wrong dtype
    or layout is a TypeError, and an exception raised meanwhile (the Interrupted of a SIGINT)
    reaches the caller as itself; with numpy's ndpointer argtypes that work ran inside ctypes'
    argument conversion and the interrupt came out as ctypes.ArgumentError, a traceback
    instead of the interrupted run's exit (tests/test_refusals.py::test_an_interrupted_run_says_so,
    an intermittent failure)."""
    import ctypes

    from rodsnes import compiled
    energy = elastic_compiled._load().energy
    rng = np.random.default_rng(2)
    rod, qe, xe = make_rod(2, 3, 5, rng, bound=False)
    args, (ne, nn, nq) = elastic_compiled._inputs(rod, qe, xe, None)
    out = np.empty(ne)
    assert energy(ne, nn, nq, *args, out) == 0
    assert np.allclose(out, rod.element_terms_reference(qe, xe)[0], rtol=1e-12)
    with pytest.raises(TypeError, match="C-contiguous float64"):
        energy(ne, nn, nq, *args, np.empty(ne, dtype=np.float32))
    with pytest.raises(TypeError, match="C-contiguous float64"):
        energy(ne, nn, nq, *args, np.empty((ne, 2))[:, 0])

    class Interrupted(KeyboardInterrupt):
        pass

    class Signalled(np.ndarray):
        @property
        def __array_interface__(self):
            raise Interrupted(2)

    with pytest.raises(Interrupted):
        energy(ne, nn, nq, *args, np.empty(ne).view(Signalled))
    assert not issubclass(Interrupted, ctypes.ArgumentError)


@pytest.mark.parametrize("p", [1, 2, 3, 4])
@pytest.mark.parametrize("comps", [(0, 1, 5), (0, 2, 4), (2, 1, 3), (3,), (5, 4, 3, 2, 1, 0)])
def test_tangent_cut_to_components_in_the_kernel(p, comps):
    """comps: the kernel's tangents cut to those components of every node, bit for bit the
    entries of its full tangents (rows and columns (node, component), in the order given),
    in fresh and in reused arrays, both tangents; the numpy path's cut the same to round-off."""
    rng = np.random.default_rng(7 + p)
    rod, qe, xe = make_rod(p, p, 5, rng, False)
    idx = (6 * np.arange(p + 1)[:, None] + np.asarray(comps)[None, :]).ravel()
    for symmetric in (False, True):
        full = rod.element_terms(qe, xe, symmetric=symmetric)
        cut = rod.element_terms(qe, xe, symmetric=symmetric, comps=comps)
        again = rod.element_terms(qe, xe, symmetric=symmetric, comps=comps, reuse=True)
        ref = full[2][:, idx[:, None], idx[None, :]]
        for got in (cut, again):
            assert got[2].shape == (5, len(comps) * (p + 1), len(comps) * (p + 1))
            assert np.array_equal(got[2], ref)
            assert np.array_equal(got[0], full[0]) and np.array_equal(got[1], full[1])
        rod.kernel = "numpy"
        assert_same(rod.element_terms(qe, xe, symmetric=symmetric, comps=comps), cut, "numpy cut")
        rod.kernel = "compiled"
    with pytest.raises(ValueError):
        elastic_compiled.element_terms(rod, qe, xe, comps=(0, 6))


@pytest.mark.parametrize("p,nq", [(1, 2), (2, 3), (3, 3), (3, 4), (4, 5), (7, 8)])
def test_strains_in_c_equal_numpy(p, nq):
    """The strains at the quadrature points (ElasticRod.strains) and at the element's nodes
    (strains_at_nodes, the output's) in C equal their numpy forms to 1e-13 relative, on
    deformed elements with quaternions of either sign and of norms 0.5-2 (e = Nz / |p|^2)."""
    rng = np.random.default_rng(p)
    rod = elastic.ElasticRod(p, nq, 0.3, STIFF)
    assert rod.kernel == "compiled"
    qe, xe, _ = deformed_elements(p, nq, 9, rng)
    qe = qe * rng.uniform(0.5, 2.0, size=qe.shape[:2])[..., None]
    for got, ref in ((rod.strains(qe, xe), rod.strains_numpy(qe, xe)),
                     (elastic.strains_at_nodes(p, 0.3, qe, xe, compiled=True),
                      elastic.strains_at_nodes(p, 0.3, qe, xe, compiled=False))):
        assert got.shape == ref.shape and got.shape[2] == 6
        assert np.abs(got - ref).max() <= 1e-13 * np.abs(ref).max()
        assert np.abs(ref[..., 3:]).max() > 0.1          # bent and twisted: something compared
    assert rod.strains(qe[:0], xe[:0]).shape == (0, nq, 6)


@pytest.mark.parametrize("p", [1, 2, 3, 4])
@pytest.mark.parametrize("closed", [False, True])
def test_node_residual_equals_the_summed_element_rows(p, closed):
    """ElasticRod.node_residual (the kernel gathering the elements' nodes and summing their
    rows per node) equals element_terms of the gathered elements with the rows summed per node
    in the elements' order (np.add.at), bit for bit, on a chain of elements sharing end nodes
    (a ring: the last element ends at node 0), nodes held in shuffled rows, at every lane width
    (7 elements: the last group padded); the numpy kernel's form the same to round-off."""
    rng = np.random.default_rng(30 + p + 10 * closed)
    ne, nq = 7, p + 1
    qe, xe, e0 = deformed_elements(p, nq, ne, rng)
    n = ne * p + (0 if closed else 1)
    conn = (np.arange(ne)[:, None] * p + np.arange(p + 1)[None, :]) % n
    rows = rng.permutation(n + 3)[:n]                   # node k in row rows[k] of n + 3
    qn, xn = np.zeros((n + 3, 4)), np.zeros((n + 3, 3))
    qn[rows[conn]], xn[rows[conn]] = qe, xe             # shared nodes: the later element's
    conn = rows[conn]
    rod = elastic.ElasticRod(p, nq, 0.3, STIFF)
    rod.set_reference(e0)
    energy, F = rod.node_residual(qn, xn, conn)
    e_ref, vec, _ = rod.element_terms(qn[conn], xn[conn], tangent=False)
    ref = np.zeros_like(F)
    np.add.at(ref, conn.ravel(), vec.reshape(-1, 6))
    assert np.array_equal(F, ref) and np.array_equal(energy, e_ref)
    assert np.abs(F).max() > 0.1 and not F[np.setdiff1d(np.arange(n + 3), rows)].any()
    for lanes in (1, 2, 4):     # one element at a time, 2 or 4 at once: the same bits
        try:
            e_l, F_l = elastic_compiled.node_residual(rod, qn, xn, conn, lanes=lanes)
        except ValueError:
            assert lanes == 4       # no AVX2 here
            continue
        assert np.array_equal(F_l, F) and np.array_equal(e_l, energy), lanes
    rod_np = elastic.ElasticRod(p, nq, 0.3, STIFF, kernel="numpy")
    rod_np.set_reference(e0)
    e_np, F_np = rod_np.node_residual(qn, xn, conn)
    assert np.abs(F_np - F).max() <= 1e-12 * np.abs(F).max()
    assert np.abs(e_np - energy).max() <= 1e-12 * np.abs(energy).max()


@pytest.mark.parametrize("p", [1, 3, 4])
def test_node_energy_equals_the_gathered_elements_energy(p):
    """ElasticRod.node_energy (the kernel gathering the elements' nodes) equals energy of the
    gathered elements bit for bit, on a chain with shuffled node rows and the curvature bound
    acting; the numpy kernel's the same to round-off."""
    rng = np.random.default_rng(40 + p)
    rod, qe, xe = make_rod(p, p + 1, 9, rng, bound=True)
    n = 9 * p + 1
    conn = np.arange(9)[:, None] * p + np.arange(p + 1)[None, :]
    rows = rng.permutation(n)
    qn, xn = np.zeros((n, 4)), np.zeros((n, 3))
    qn[rows[conn]], xn[rows[conn]] = qe, xe
    conn = rows[conn]
    E = rod.node_energy(qn, xn, conn)
    assert E == rod.energy(qn[conn], xn[conn]) and abs(E) > 0.0
    rod_np = elastic.ElasticRod(p, p + 1, 0.3, STIFF, kernel="numpy")
    rod_np.set_reference(rod.e0)
    rod_np.set_curvature_limit(rod.kappa_max, rod.mu_kappa)
    assert abs(rod_np.node_energy(qn, xn, conn) - E) <= 1e-12 * abs(E)


@pytest.mark.parametrize("bound", [False, True], ids=["free", "curvature_bound"])
@pytest.mark.parametrize("p,nq,ne", [(1, 1, 6), (2, 2, 5), (3, 3, 37), (3, 4, 3), (4, 4, 2),
                                     (7, 6, 9), (3, 3, 1)])
def test_one_two_and_four_lanes_give_the_same_terms(p, nq, ne, bound):
    """The 3-D element one at a time, 2 at once (SSE2) or 4 (AVX2, where the processor has it):
    one source (_elastic_lanes.h), the same arithmetic lane by lane, so the same energies,
    residuals and tangents bit for bit - full and cut (comps), consistent and symmetric, element
    counts that fill the last group or not; the default is the widest."""
    rng = np.random.default_rng(11 * p + nq + ne + bound)
    rod, qe, xe = make_rod(p, nq, ne, rng, bound)
    for symmetric in (False, True):
        for comps in (None, (0, 1, 5)):
            kw = dict(tangent=True, symmetric=symmetric, comps=comps)
            one = elastic_compiled.element_terms(rod, qe, xe, rod.e0, lanes=1, **kw)
            for a, b in zip(elastic_compiled.element_terms(rod, qe, xe, rod.e0, **kw), one):
                assert np.array_equal(a, b)
            for lanes in (2, 4):
                try:
                    got = elastic_compiled.element_terms(rod, qe, xe, rod.e0, lanes=lanes, **kw)
                except ValueError:
                    assert lanes == 4           # no AVX2 here
                    continue
                for a, b in zip(got, one):
                    assert np.array_equal(a, b), (lanes, symmetric, comps)
    with pytest.raises(RuntimeError):
        elastic_compiled.element_terms(rod, qe, xe, rod.e0, lanes=3)
