"""The LU without fill of a rank's stretch (rodsnes/solve/chain.py): against dense LU on
random chains of cubic elements, block sizes 3 and 6, both directions of elimination; the
substitutions over the last rows give the inverse's trailing block; a pattern that fills, a
singular block, the separator taken out."""
import types

import numpy as np
import pytest
from petsc4py import PETSc

from rodsnes.solve import chain

pytestmark = pytest.mark.skipif(not chain.available(), reason="chain kernel not built")


def _chain_matrix(ne, bs, order=3, closed=False, seed=0, pivoting=False):
    """A SeqBAIJ matrix of ne elements of order+1 nodes (a chain, or a ring), random
    non-symmetric element blocks, diagonally dominant enough to factor without pivoting
    between blocks; with ``pivoting`` every node's first two rows swapped and the first
    diagonal entry zero (the first pivot block of either order has a zero first pivot: the
    block's own partial pivoting needed).  Returns (PETSc matrix, dense copy)."""
    rng = np.random.default_rng(seed)
    nn = order * ne + (0 if closed else 1)
    conn = (np.arange(ne)[:, None] * order + np.arange(order + 1)) % nn
    k = (order + 1) * bs
    dense = np.zeros((nn * bs, nn * bs))
    for e in range(ne):
        M = rng.standard_normal((k, k))
        K = M @ M.T + k * np.eye(k) + 0.5 * rng.standard_normal((k, k))
        idx = (conn[e][:, None] * bs + np.arange(bs)).ravel()
        dense[np.ix_(idx, idx)] += K
    if pivoting:        # swap the first two rows of every node's block row
        for a in range(nn):
            r = a * bs
            dense[[r, r + 1]] = dense[[r + 1, r]]
            dense[r, r] = 0.0
    A = PETSc.Mat().createBAIJ((nn * bs, nn * bs), bs, nnz=2 * order + 1, comm=PETSc.COMM_SELF)
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    for e in range(ne):
        c = conn[e].astype(PETSc.IntType)
        idx = (conn[e][:, None] * bs + np.arange(bs)).ravel()
        A.setValuesBlocked(c, c, dense[np.ix_(idx, idx)].ravel(), addv=PETSc.InsertMode.INSERT)
    A.assemble()
    return A, dense


def _plan(A, direction):
    ai, aj = A.getRowIJ(compressed=True)
    return chain.ChainLU.plan(ai, aj, A.getBlockSize(), direction)


def _numpy_streams(ai, aj, diag, direction):
    """The factors' two streams (_chain_kernel.c): (place, col, lofs, uofs) - the slot of each
    block of the CSR, the block column of each slot, and per order position s the first slot
    of its row's multipliers (lofs, slots 0 .. nL - 1, each row's in its order of
    elimination: ascending columns for +1, descending for -1) and of its inverted diagonal
    block, its upper blocks after it in ascending columns (uofs, from nL).  int32 each."""
    n = len(ai) - 1
    ai = np.asarray(ai, dtype=np.int64)
    diag = np.asarray(diag, dtype=np.int64)
    rows = np.arange(n) if direction > 0 else np.arange(n)[::-1]     # the row at position s
    start, stop, d = ai[rows], ai[rows + 1], diag[rows]
    nlow = d - start if direction > 0 else stop - 1 - d
    lofs = np.concatenate([[0], np.cumsum(nlow)])
    uofs = lofs[-1] + np.concatenate([[0], np.cumsum(stop - start - nlow)])
    place = np.empty(int(ai[-1]), dtype=np.int64)
    length = stop - start
    s = np.repeat(np.arange(n), length)                 # order position of every block ...
    p = np.arange(int(length.sum())) - np.repeat(np.cumsum(length) - length, length) \
        + np.repeat(start, length)                      # ... and its place in the CSR
    ds, ls, us = d[s], lofs[s], uofs[s]
    if direction > 0:
        place[p] = np.where(p < ds, ls + (p - start[s]), us + (p - ds))
    else:
        place[p] = np.where(p > ds, ls + (stop[s] - 1 - p), us + np.where(
            p == ds, 0, 1 + (p - start[s])))
    col = np.empty_like(place)
    col[place] = np.asarray(aj, dtype=np.int64)
    as32 = lambda a: np.ascontiguousarray(a, dtype=np.int32)
    return as32(place), as32(col), as32(lofs), as32(uofs)
    # (the layout's reference in numpy: rodsnes_chain_streams does it in C)


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("order, closed", [(1, False), (3, False), (2, True)])
def test_the_streams_layout_is_the_numpy_reference(direction, order, closed):
    """The kernel's layout of the factors' streams (rodsnes_chain_streams) against its
    reference in numpy, for chains of orders 1 and 3 and a ring (whose pattern the chain LU
    would refuse: the layout is still defined)."""
    A, _ = _chain_matrix(5, 3, order=order, closed=closed)
    ai, aj = (np.ascontiguousarray(a, dtype=np.int32) for a in A.getRowIJ(compressed=True))
    n = len(ai) - 1
    diag = np.array([ai[i] + np.flatnonzero(aj[ai[i]:ai[i + 1]] == i)[0] for i in range(n)],
                    dtype=np.int32)
    for got, ref in zip(chain._streams(ai, aj, diag, direction),
                        _numpy_streams(ai, aj, diag, direction)):
        assert got.dtype == np.int32 and np.array_equal(got, ref)


@pytest.mark.parametrize("bs", [3, 6, 2])
@pytest.mark.parametrize("direction", [1, -1])
def test_the_chain_lu_solves_as_dense_lu(bs, direction):
    A, dense = _chain_matrix(12, bs, seed=bs)
    lu = _plan(A, direction)
    assert lu is not None and lu.factor(A)
    b = np.random.default_rng(1).standard_normal(dense.shape[0])
    x = lu.solve(b.copy())
    ref = np.linalg.solve(dense, b)
    assert np.abs(x - ref).max() <= 1e-12 * np.abs(ref).max()
    # the values were copied: the matrix keeps its own
    assert np.array_equal(A.convert("dense").getDenseArray(), dense)


@pytest.mark.parametrize("direction", [1, -1])
def test_each_block_is_inverted_with_partial_pivoting(direction):
    """The first pivot block of the order with a zero first pivot: still the dense solution."""
    A, dense = _chain_matrix(6, 3, seed=3, pivoting=True)
    lu = _plan(A, direction)
    assert lu.factor(A)
    b = np.arange(dense.shape[0], dtype=float)
    assert np.allclose(lu.solve(b.copy()), np.linalg.solve(dense, b), rtol=1e-11, atol=0)


@pytest.mark.parametrize("direction", [1, -1])
def test_the_tail_substitutions_give_the_inverses_trailing_block(direction):
    """The substitutions over the order positions t..n-1 of a vector zero outside them: the
    forward one and the backward one give A^-1's block on those rows (what RankSchur uses
    next to the separator), and a forward one alone L^-1 there."""
    bs = 3
    A, dense = _chain_matrix(10, bs, seed=5)
    lu = _plan(A, direction)
    assert lu.factor(A)
    n = lu.n
    t = n - 4
    rows = np.sort(lu.order_position(np.arange(t, n)))
    idx = (rows[:, None] * bs + np.arange(bs)).ravel()
    inv = np.linalg.inv(dense)
    for j, col in enumerate(idx):
        w = np.zeros(n * bs)
        w[col] = 1.0
        lu.solve(w, t, t)
        assert np.abs(w[idx] - inv[idx, col]).max() <= 1e-12 * np.abs(inv).max()
    # the forward substitution alone over the tail: L^-1 on it (L of the dense block LU without
    # pivoting in the same order, unit diagonal blocks, of the vector zero outside the tail);
    # then the backward one: the same as both in one call
    perm = (lu.order_position(np.arange(n))[:, None] * bs + np.arange(bs)).ravel()
    Up = dense[np.ix_(perm, perm)].copy()
    Lp = np.eye(len(Up))
    for c in range(n - 1):              # block Doolittle in the order's numbering
        k = slice(c * bs, (c + 1) * bs)
        below = slice((c + 1) * bs, None)
        Lp[below, k] = Up[below, k] @ np.linalg.inv(Up[k, k])
        Up[below] -= Lp[below, k] @ Up[k]
    v = np.zeros(n * bs)
    v[idx] = np.random.default_rng(3).standard_normal(len(idx))
    want = np.linalg.solve(Lp, v[perm])
    w = v.copy()
    lu.solve(w, t, n)
    assert np.allclose(w[perm], want, rtol=1e-11, atol=1e-12 * np.abs(want).max())
    lu.solve(w, n, t)
    both = lu.solve(v.copy(), t, t)
    assert np.array_equal(w, both)
    # whole forward then the tail's backward: A^-1 b on the tail, the rest untouched
    b = np.random.default_rng(2).standard_normal(n * bs)
    z = lu.solve(b.copy(), 0, n)
    w = np.zeros(n * bs)
    w[idx] = z[idx]
    lu.solve(w, n, t)
    assert np.allclose(w[idx], np.linalg.solve(dense, b)[idx], rtol=1e-11, atol=1e-13)


def test_a_pattern_that_fills_or_lacks_a_diagonal_has_no_chain_lu():
    """A ring's closing element couples the first and last nodes: eliminated in either
    order it fills, so no ChainLU (PETSc's LU then, with AMD)."""
    A, _ = _chain_matrix(6, 3, closed=True)
    assert _plan(A, 1) is None and _plan(A, -1) is None
    ai, aj = A.getRowIJ(compressed=True)
    keep = np.ones(len(aj), dtype=bool)
    keep[ai[2]:ai[3]] = aj[ai[2]:ai[3]] != 2            # row 2 without its diagonal block
    ai2 = np.concatenate([[0], np.cumsum([keep[ai[i]:ai[i + 1]].sum()
                                          for i in range(len(ai) - 1)])])
    assert chain.ChainLU.plan(ai2, aj[keep], 3, 1) is None


@pytest.mark.parametrize("direction", [1, -1])
def test_a_singular_block_fails_the_factorisation(direction):
    """A node whose rows and columns are zero: its diagonal block is singular at its turn,
    factor() says so and names its row."""
    A, _ = _chain_matrix(4, 3, seed=7)
    lu = _plan(A, direction)
    ai, aj = A.getRowIJ(compressed=True)
    rows = np.repeat(np.arange(len(ai) - 1), np.diff(ai))
    values = _values(A)
    assert lu.factor(values=values)
    values.reshape(-1, 9)[(rows == 5) | (aj == 5)] = 0.0
    assert not lu.factor(values=values) and lu.failed_row == 5


def _values(A):
    """The SeqBAIJ matrix's value array (blocks column by column), a copy."""
    bs = A.getBlockSize()
    ai, aj = A.getRowIJ(compressed=True)
    rows = np.repeat(np.arange(len(ai) - 1), np.diff(ai))
    d = A.convert("dense").getDenseArray()
    out = np.empty((len(aj), bs, bs))
    for p, (i, j) in enumerate(zip(rows, aj)):
        out[p] = d[i * bs:(i + 1) * bs, j * bs:(j + 1) * bs].T     # column by column
    return out.ravel()


@pytest.mark.parametrize("direction,s", [(1, 7), (-1, 7), (1, 17), (-1, 0)])
def test_the_separator_taken_out(direction, s):
    """Block rows ``out`` taken out, in the middle or at the end of the order (where a rank's
    separator node sits): the solve of the matrix with node s's rows and columns those of the
    identity, the matrix itself unchanged."""
    bs = 3
    A, dense = _chain_matrix(6, bs, seed=11)
    ai, aj = A.getRowIJ(compressed=True)
    lu = chain.ChainLU.plan(ai, aj, bs, direction, out=[s])
    assert lu.factor(A)
    _solves_with_rows_taken_out(lu, dense, [s], bs, seed=4)
    assert np.array_equal(A.convert("dense").getDenseArray(), dense)


def _solves_with_rows_taken_out(lu, dense, out, bs, seed):
    """lu (factored) solves as the dense matrix with the block rows and columns ``out`` those
    of the identity."""
    ref = dense.copy()
    for r in set(out):
        idx = np.arange(r * bs, (r + 1) * bs)
        ref[idx, :] = 0.0
        ref[:, idx] = 0.0
        ref[idx, idx] = 1.0
    b = np.random.default_rng(seed).standard_normal(dense.shape[0])
    assert np.allclose(lu.solve(b.copy()), np.linalg.solve(ref, b), rtol=1e-11, atol=1e-13)


@pytest.mark.parametrize("out", [[0], [18], [7, 3], [3, 7, 3], [0, 1, 2, 17, 18]])
def test_the_blocks_of_the_rows_taken_out(out):
    """How each block enters the factorisation (ChainLU.kind), found from the taken rows' own
    slots and a pass over the columns: 2 on a taken row's diagonal block, 1 on its other blocks
    and on every block in a taken column, 0 elsewhere - the definition, for rows at the ends
    and inside the chain, unsorted and repeated; and the solve is that of the matrix with
    those rows and columns the identity's."""
    bs = 3
    A, dense = _chain_matrix(6, bs, seed=5)
    ai, aj = A.getRowIJ(compressed=True)
    n = len(ai) - 1
    lu = chain.ChainLU.plan(ai, aj, bs, 1, out=out)
    rows = np.repeat(np.arange(n), np.diff(ai))
    taken = np.isin(rows, out) | np.isin(aj, out)
    assert np.array_equal(lu.kind, np.where(taken, np.where(rows == aj, 2, 1), 0))
    assert lu.factor(A)
    _solves_with_rows_taken_out(lu, dense, out, bs, seed=6)


@pytest.mark.parametrize("bs", [3, 6])
@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("shift", [0.0, 30.0, 60.0])
def test_the_pivot_blocks_count_a_symmetric_matrixs_negative_eigenvalues(bs, direction, shift):
    """A symmetric chain shifted down by ``shift`` (0 to a few dozen negative eigenvalues): the
    negative eigenvalues of the pivot blocks add up to the matrix's (numpy's eigvalsh)."""
    A, dense = _chain_matrix(10, bs, seed=20 + bs)
    sym = 0.5 * (dense + dense.T)
    sym -= shift * np.eye(len(sym))
    ai, aj = A.getRowIJ(compressed=True)
    lu = chain.ChainLU.plan(ai, aj, bs, direction)
    assert lu.factor(values=_values_of_dense(sym, ai, aj, bs), inertia=True)
    want = int((np.linalg.eigvalsh(sym) < 0).sum())
    assert lu.negative == want
    assert (shift == 0.0) == (want == 0)
    assert lu.factor(values=_values_of_dense(sym, ai, aj, bs)) and lu.negative is None


def _values_of_dense(dense, ai, aj, bs):
    """The block CSR (ai, aj) values of ``dense`` (blocks column by column)."""
    rows = np.repeat(np.arange(len(ai) - 1), np.diff(ai))
    out = np.empty((len(aj), bs, bs))
    for p, (i, j) in enumerate(zip(rows, aj)):
        out[p] = dense[i * bs:(i + 1) * bs, j * bs:(j + 1) * bs].T
    return out.ravel()


@pytest.mark.parametrize("bs", [2, 3, 6, 8])
def test_a_pivot_blocks_inertia_with_bunch_kaufman_pivots(bs):
    """One block (a chain of one node): its negative eigenvalues by its own LDL^T with
    Bunch-Kaufman pivoting, for random symmetric blocks with a zero diagonal (2 x 2 pivots
    needed), indefinite ones and definite ones of either sign (numpy's eigvalsh)."""
    rng = np.random.default_rng(bs)
    ai, aj = np.array([0, 1]), np.array([0])
    lu = chain.ChainLU.plan(ai, aj, bs, 1)
    for trial in range(200):
        M = rng.standard_normal((bs, bs))
        M = M + M.T
        kind = trial % 4
        if kind == 0:
            np.fill_diagonal(M, 0.0)
        elif kind == 2:
            M = M @ M.T + 0.1 * np.eye(bs)
        elif kind == 3:
            M = -(M @ M.T) - 0.1 * np.eye(bs)
        assert lu.factor(values=M.T.ravel(), inertia=True)
        assert lu.negative == int((np.linalg.eigvalsh(M) < 0).sum()), (trial, M)


@pytest.mark.parametrize("bs", [2, 3, 6, 8])
def test_a_block_needing_every_row_exchange_is_inverted(bs):
    """One block (a chain of one node) whose rows are a permutation of a well-conditioned
    matrix's with zeros on the diagonal, so that partial pivoting exchanges rows at every step:
    the solve is the dense one (block_invert's exchanges undone as column exchanges)."""
    rng = np.random.default_rng(10 + bs)
    lu = chain.ChainLU.plan(np.array([0, 1]), np.array([0]), bs, 1)
    for trial in range(50):
        M = rng.standard_normal((bs, bs)) + 3.0 * np.eye(bs)
        M = M[rng.permutation(bs)][:, ::-1] if trial % 2 else M[::-1]
        np.fill_diagonal(M, 0.0)
        if abs(np.linalg.det(M)) < 1e-3:
            continue
        b = rng.standard_normal(bs)
        assert lu.factor(values=M.T.ravel())
        assert np.allclose(lu.solve(b.copy()), np.linalg.solve(M, b), rtol=1e-10, atol=1e-12)


_NO_PROBLEM = types.SimpleNamespace(stats={})     # no new patterns counted: matrices alone


def _ksp_with(pc_context, A):
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setType("preonly")
    ksp.getPC().setType("python")
    ksp.getPC().setPythonContext(pc_context)
    ksp.setOperators(A)
    return ksp


def test_the_chain_pc_solves_as_dense_lu_and_follows_new_values_and_patterns():
    """chain.ChainPC, the Newton step's PC on one rank: a KSP solve equals the dense solve;
    new values in the same matrix are factored again (the KSP sees the matrix's state); a
    matrix of another pattern is planned anew; one that fills (a ring) goes to PETSc's LU."""
    A, dense = _chain_matrix(9, 3, seed=31)
    ctx = chain.ChainPC(_NO_PROBLEM)
    ksp = _ksp_with(ctx, A)
    b = A.createVecLeft()
    b.setArray(np.random.default_rng(2).standard_normal(dense.shape[0]))
    x = b.duplicate()
    ksp.solve(b, x)
    assert np.allclose(x.getArray(), np.linalg.solve(dense, b.getArray()), rtol=1e-11, atol=1e-13)
    first = ctx.lu
    A.scale(2.0)                                    # new values: solved with them
    ksp.solve(b, x)
    assert ctx.lu is first and ctx.fallback is None
    assert np.allclose(x.getArray(), np.linalg.solve(2.0 * dense, b.getArray()), rtol=1e-11,
                       atol=1e-13)
    B, dense_b = _chain_matrix(27, 3, order=1, seed=32)     # another chain: planned anew
    ksp.setOperators(B)
    b2, x2 = B.createVecLeft(), B.createVecLeft()
    b2.setArray(np.arange(dense_b.shape[0], dtype=float))
    ksp.solve(b2, x2)
    assert ctx.lu is not first and ctx.lu.n == 28 and ctx.lu.aj.size == 28 + 2 * 27
    assert np.allclose(x2.getArray(), np.linalg.solve(dense_b, b2.getArray()), rtol=1e-11,
                       atol=1e-13)
    R, dense_r = _chain_matrix(28, 3, order=1, seed=33, closed=True)    # a ring fills: PETSc's LU
    ksp.setOperators(R)
    b3, x3 = R.createVecLeft(), R.createVecLeft()
    b3.setArray(np.ones(dense_r.shape[0]))
    ksp.solve(b3, x3)
    assert ctx.lu is None and ctx.fallback is not None
    assert np.allclose(x3.getArray(), np.linalg.solve(dense_r, b3.getArray()), rtol=1e-11,
                       atol=1e-13)
    ksp.destroy()


def test_a_singular_block_fails_the_chain_pc():
    """A zero node (its rows and columns): the factorisation fails, the KSP says its PC failed
    (as at PETSc's LU's zero pivot) and the solution is not finite; the next good values solve
    again (the failed reason cleared)."""
    A, dense = _chain_matrix(4, 3, seed=7)
    good = A.copy()
    rows = np.arange(5 * 3, 6 * 3).astype(PETSc.IntType)
    A.zeroRowsColumns(rows, diag=0.0)
    ksp = _ksp_with(chain.ChainPC(_NO_PROBLEM), A)
    b = A.createVecLeft()
    b.set(1.0)
    x = b.duplicate()
    ksp.solve(b, x)
    assert ksp.getConvergedReason() == PETSc.KSP.ConvergedReason.DIVERGED_PCSETUP_FAILED  # -11
    assert not np.isfinite(x.getArray()).any()       # the KSP's Inf over the PC's NaN
    good.copy(A)                                    # the same pattern, good values
    ksp.solve(b, x)
    assert ksp.getConvergedReason() > 0
    assert np.allclose(x.getArray(), np.linalg.solve(dense, b.getArray()), rtol=1e-11, atol=1e-13)
    ksp.destroy()


def test_a_pattern_changed_in_place_is_planned_anew():
    """A block added to the same matrix (the same handle; node 7 coupled to node 5, which
    makes no fill) makes a new plan, never the old one's places (ChainLU.factor sees another
    count of blocks; PETSc 3.18's BAIJ keeps its nonzero state there)."""
    A, dense = _chain_matrix(6, 3, seed=9)
    ctx = chain.ChainPC(_NO_PROBLEM)
    ksp = _ksp_with(ctx, A)
    b = A.createVecLeft()
    b.set(1.0)
    x = b.duplicate()
    ksp.solve(b, x)
    first = ctx.lu
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    A.setValuesBlocked([7], [5], np.full(9, 0.01), addv=PETSc.InsertMode.ADD)
    A.assemble()
    dense[21:24, 15:18] += 0.01
    ksp.solve(b, x)
    assert ctx.lu is not first and ctx.lu is not None and ctx.fallback is None
    assert np.allclose(x.getArray(), np.linalg.solve(dense, b.getArray()), rtol=1e-11, atol=1e-13)
    ksp.reset()                                     # nothing of the old matrices kept
    assert ctx.lu is None and ctx.fallback is None
    ksp.destroy()


def test_the_chain_pc_says_what_it_is_in_ksp_view(tmp_path):
    """-ksp_view names the chain LU, its size and order."""
    A, _ = _chain_matrix(5, 3, seed=40)
    ksp = _ksp_with(chain.ChainPC(_NO_PROBLEM), A)
    b = A.createVecLeft()
    b.set(1.0)
    ksp.solve(b, b.duplicate())
    path = str(tmp_path / "view.txt")
    viewer = PETSc.Viewer().createASCII(path, comm=PETSc.COMM_SELF)
    ksp.view(viewer)
    viewer.destroy()
    text = open(path).read()
    assert "rodsnes' chain LU" in text and "16 block rows of size 3" in text
    ksp.destroy()
