/* Block LU without fill of a rank's stretch of a rod (rodsnes/solve/chain.py; plain C99, no
 * Python API, loaded with ctypes).
 *
 * The matrix is a block CSR (n block rows, row pointers ai, sorted block columns aj, values A:
 * bs x bs blocks stored column by column, as PETSc's BAIJ) whose elimination in the natural
 * order (dir = +1) or the reversed one (dir = -1) makes no fill: an open rod's chain.  The
 * factors go to V, each row copied from the matrix's values as its turn comes: the multipliers
 * L_ik = A_ik D_k^-1 of the blocks eliminated before their row ("lower"), the updated blocks
 * after them ("upper"), and each diagonal block inverted (partial pivoting inside the block;
 * no pivoting between blocks, as PETSc's own BAIJ LU); V holds them in two streams, L's and
 * U's, each in the order its substitution reads it (below).  Order position s holds row s
 * (dir +1) or n - 1 - s (dir -1).
 *
 * Because the rows last in the order are eliminated last, the solves restricted to them give
 * the inverse's trailing block without a whole substitution (chain.py).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define ROW(s) (dir > 0 ? (s) : n - 1 - (s))

/* The position of block column j in row i (binary search), or -1. */
static int find(const int *ai, const int *aj, int i, int j)
{
    int lo = ai[i], hi = ai[i + 1] - 1;
    while (lo <= hi) {
        int mid = (lo + hi) / 2;
        if (aj[mid] == j) return mid;
        if (aj[mid] < j) lo = mid + 1; else hi = mid - 1;
    }
    return -1;
}

/* The lower blocks of row i: positions from *p0 stepping by *step until p1 (exclusive), in the
 * order of elimination; the upper blocks: [*q0, *q1). */
static inline void lower_range(int dir, const int *ai, const int *diag, int i,
                               int *p0, int *p1, int *step)
{
    if (dir > 0) { *p0 = ai[i]; *p1 = diag[i]; *step = 1; }
    else { *p0 = ai[i + 1] - 1; *p1 = diag[i]; *step = -1; }
}

static inline void upper_range(int dir, const int *ai, const int *diag, int i, int *q0, int *q1)
{
    if (dir > 0) { *q0 = diag[i] + 1; *q1 = ai[i + 1]; }
    else { *q0 = ai[i]; *q1 = diag[i]; }
}

/* Symbolic phase: the diagonal's places (diag, n) and, for every update A_ij -= L_ik U_kj of
 * the elimination in its order, the place of (i, j) (target, at most cap of them; NULL: only
 * counted).  Returns the number of updates, -1 when a row has no diagonal block, -2 when the
 * elimination would fill (a block (i, j) missing). */
int64_t rodsnes_chain_plan(int n, const int *ai, const int *aj, int dir, int *diag,
                           int *target, int64_t cap)
{
    for (int i = 0; i < n; i++) {
        diag[i] = find(ai, aj, i, i);
        if (diag[i] < 0) return -1;
    }
    int64_t t = 0;
    for (int s = 0; s < n; s++) {
        int i = ROW(s), p0, p1, step;
        lower_range(dir, ai, diag, i, &p0, &p1, &step);
        for (int p = p0; p != p1; p += step) {
            int k = aj[p], q0, q1;
            upper_range(dir, ai, diag, k, &q0, &q1);
            for (int q = q0; q < q1; q++) {
                int pos = find(ai, aj, i, aj[q]);
                if (pos < 0) return -2;
                if (target != NULL && t < cap) target[t] = pos;
                t++;
            }
        }
    }
    return t;
}

/* ---- bs x bs blocks, column by column: element (r, c) at r + c bs ------------------------- */

/* C = A B (sign 0) or C -= A B (sign 1) */
static inline void block_mul(const int BS, const double *A, const double *B, double *C,
                             const int sub)
{
    for (int c = 0; c < BS; c++)
        for (int r = 0; r < BS; r++) {
            double s = 0.0;
            for (int m = 0; m < BS; m++) s += A[r + m * BS] * B[m + c * BS];
            if (sub) C[r + c * BS] -= s; else C[r + c * BS] = s;
        }
}

/* A <- A^-1 in place by Gauss-Jordan with partial pivoting (the row swaps of the elimination
 * undone as column swaps, last first); returns -1 when a pivot is 0 or not finite. */
static inline int block_invert(const int BS, double *A)
{
    int piv[8];
    for (int c = 0; c < BS; c++) {
        int pr = c;
        double big = fabs(A[c + c * BS]);
        for (int r = c + 1; r < BS; r++)
            if (fabs(A[r + c * BS]) > big) { big = fabs(A[r + c * BS]); pr = r; }
        if (!(big > 0.0) || !isfinite(big)) return -1;
        piv[c] = pr;
        if (pr != c)
            for (int m = 0; m < BS; m++) {
                double tmp = A[c + m * BS]; A[c + m * BS] = A[pr + m * BS]; A[pr + m * BS] = tmp;
            }
        double d = 1.0 / A[c + c * BS];
        A[c + c * BS] = 1.0;
        for (int m = 0; m < BS; m++) A[c + m * BS] *= d;
        for (int r = 0; r < BS; r++) {
            if (r == c) continue;
            double f = A[r + c * BS];
            A[r + c * BS] = 0.0;
            for (int m = 0; m < BS; m++) A[r + m * BS] -= f * A[c + m * BS];
        }
    }
    for (int c = BS - 1; c >= 0; c--)
        if (piv[c] != c)
            for (int r = 0; r < BS; r++) {
                double tmp = A[r + c * BS]; A[r + c * BS] = A[r + piv[c] * BS];
                A[r + piv[c] * BS] = tmp;
            }
    return 0;
}

/* Rows and columns p and q of the symmetric S exchanged (a congruence by a permutation). */
static inline void sym_swap(const int BS, double S[8][8], int p, int q)
{
    for (int j = 0; j < BS; j++) { double t = S[q][j]; S[q][j] = S[p][j]; S[p][j] = t; }
    for (int j = 0; j < BS; j++) { double t = S[j][q]; S[j][q] = S[j][p]; S[j][p] = t; }
}

/* The negative eigenvalues of the symmetric part of the block A (column by column): its
 * LDL^T with Bunch-Kaufman pivoting (1 x 1 and 2 x 2 pivots, alpha = (1 + sqrt 17) / 8), a
 * congruence, the negative eigenvalues counted on D; an exactly zero column counts as not
 * negative, a nearly singular block gets its round-off's sign, as LAPACK's would (Sylvester's
 * law of inertia; the caller's zero shift and backward-error test decide near zero).  (The pivot blocks of a symmetric matrix's LU without pivoting
 * between blocks are symmetric: H = L D L^T, a congruence, so H's inertia is the sum of
 * theirs.) */
static int block_inertia(const int BS, const double *A)
{
    const double alpha = 0.6403882032022076;
    double S[8][8];
    for (int r = 0; r < BS; r++)
        for (int c = 0; c < BS; c++) S[r][c] = 0.5 * (A[r + c * BS] + A[c + r * BS]);
    int neg = 0, k = 0;
    while (k < BS) {
        double lam = 0.0;
        int r = k;
        for (int i = k + 1; i < BS; i++)
            if (fabs(S[i][k]) > lam) { lam = fabs(S[i][k]); r = i; }
        double akk = fabs(S[k][k]);
        if (akk == 0.0 && lam == 0.0) { k++; continue; }    /* a zero column: not negative */
        int two = 0;
        if (akk < alpha * lam) {
            double sigma = 0.0;
            for (int j = k; j < BS; j++)
                if (j != r && fabs(S[r][j]) > sigma) sigma = fabs(S[r][j]);
            if (akk * sigma >= alpha * lam * lam) {
                /* 1 x 1 at k */
            } else if (fabs(S[r][r]) >= alpha * sigma) {
                sym_swap(BS, S, k, r);      /* 1 x 1 at r: swap k and r */
            } else {
                two = 1;                    /* 2 x 2 at (k, r): swap k + 1 and r */
                if (r != k + 1) sym_swap(BS, S, k + 1, r);
            }
        }
        if (!two) {
            double d = S[k][k];
            if (d < 0.0) neg++;
            for (int i = k + 1; i < BS; i++) {
                double f = S[i][k] / d;
                for (int j = k + 1; j < BS; j++) S[i][j] -= f * S[k][j];
            }
            k += 1;
        } else {
            double a = S[k][k], b = S[k + 1][k], c = S[k + 1][k + 1];
            double det = a * c - b * b;
            /* det < 0 (always, for a Bunch-Kaufman 2 x 2 pivot): one eigenvalue of each sign */
            if (det < 0.0) neg += 1;
            else if (a + c < 0.0) neg += 2;
            for (int i = k + 2; i < BS; i++)
                for (int j = k + 2; j < BS; j++) {
                    /* S_ij -= [S_ik S_i,k+1] D^-1 [S_kj; S_k+1,j] */
                    double x = S[i][k], y = S[i][k + 1], u = S[k][j], v = S[k + 1][j];
                    S[i][j] -= (x * (c * u - b * v) + y * (a * v - b * u)) / det;
                }
            k += 2;
        }
    }
    return neg;
}

/* ---- the numeric factorisation and the substitutions, for a block size known at compile
 * time (3: a planar node, 6: a node in 3-D) or any other ----------------------------------
 *
 * The factors are kept in two streams, in the order the substitutions read them (chain.py
 * lays them out): the multipliers L of the order positions 0..n-1, each row's in the order
 * of elimination, from slot lofs[s]; then per order position the inverted diagonal block at
 * slot uofs[s] and the row's upper blocks after it, to uofs[s + 1].  place[p] is the slot of
 * the matrix's block p, col[slot] its block column.  The forward substitution reads the
 * first stream, the backward one the second: each once, as PETSc's own LU keeps L and U
 * apart (rows of L and U interleaved, each sweep read all of both: 1.4 x the time at 10^4
 * planar elements, 1.6 x at 10^5). */

static inline int factor_bs(const int BS, int n, const int *ai, const int *place,
                            const int *lofs, const int *uofs, const int *col, int dir,
                            const int *target, const double *A, const signed char *kind,
                            double *V, int *neg)
{
    const int B2 = BS * BS;
    double L[64];
    int64_t t = 0;
    for (int s = 0; s < n; s++) {
        const int i = ROW(s);
        /* the row's values copied in just before its elimination (which changes this row
         * alone): one pass over the matrix, the row then in cache */
        for (int p = ai[i]; p < ai[i + 1]; p++) {
            double *v = V + (int64_t)place[p] * B2;
            if (kind[p] == 0) memcpy(v, A + (int64_t)p * B2, sizeof(double) * B2);
            else {
                memset(v, 0, sizeof(double) * B2);
                if (kind[p] == 2) for (int r = 0; r < BS; r++) v[r + r * BS] = 1.0;
            }
        }
        for (int l = lofs[s]; l < lofs[s + 1]; l++) {
            const int k = col[l], ks = dir > 0 ? k : n - 1 - k;
            double *Vl = V + (int64_t)l * B2;
            block_mul(BS, Vl, V + (int64_t)uofs[ks] * B2, L, 0);
            memcpy(Vl, L, sizeof(double) * B2);
            for (int u = uofs[ks] + 1; u < uofs[ks + 1]; u++)
                block_mul(BS, L, V + (int64_t)u * B2, V + (int64_t)target[t++] * B2, 1);
        }
        double *D = V + (int64_t)uofs[s] * B2;
        if (neg != NULL)         /* the pivot block's inertia, before it is inverted */
            *neg += block_inertia(BS, D);
        if (block_invert(BS, D)) return i + 1;
    }
    return 0;
}

/* x <- L^-1 x over the order positions first..n-1 (the entries before them are read: zero
 * where x is zero there).  Each row is summed in registers (x's rows may alias, for the
 * compiler). */
static inline void forward_bs(const int BS, int n, const int *lofs, const int *col, int dir,
                              const double *V, int first, double *x)
{
    const int B2 = BS * BS;
    double acc[8];
    for (int s = first; s < n; s++) {
        double *xi = x + (int64_t)ROW(s) * BS;
        for (int r = 0; r < BS; r++) acc[r] = xi[r];
        for (int l = lofs[s]; l < lofs[s + 1]; l++) {
            const double *A = V + (int64_t)l * B2, *xk = x + (int64_t)col[l] * BS;
            for (int c = 0; c < BS; c++)
                for (int r = 0; r < BS; r++) acc[r] -= A[r + c * BS] * xk[c];
        }
        for (int r = 0; r < BS; r++) xi[r] = acc[r];
    }
}

/* x <- U^-1 x over the order positions n-1 down to last (those after them only are read) */
static inline void backward_bs(const int BS, int n, const int *uofs, const int *col, int dir,
                               const double *V, int last, double *x)
{
    const int B2 = BS * BS;
    double acc[8];
    for (int s = n - 1; s >= last; s--) {
        double *xi = x + (int64_t)ROW(s) * BS;
        for (int r = 0; r < BS; r++) acc[r] = xi[r];
        for (int u = uofs[s] + 1; u < uofs[s + 1]; u++) {
            const double *A = V + (int64_t)u * B2, *xj = x + (int64_t)col[u] * BS;
            for (int c = 0; c < BS; c++)
                for (int r = 0; r < BS; r++) acc[r] -= A[r + c * BS] * xj[c];
        }
        const double *D = V + (int64_t)uofs[s] * B2;
        for (int r = 0; r < BS; r++) {
            double a = 0.0;
            for (int c = 0; c < BS; c++) a += D[r + c * BS] * acc[c];
            xi[r] = a;
        }
    }
}

/* The two streams' layout (above) for the block CSR (ai, aj) of n rows with diagonal blocks
 * at diag, eliminated in direction dir: place[p] the slot of block p, col[slot] its block
 * column, lofs (n + 1) per order position s the first slot of its row's multipliers (each
 * row's in its order of elimination: ascending columns for +1, descending for -1), uofs
 * (n + 1) the slot of its inverted diagonal block, its upper blocks after it in ascending
 * columns (from lofs[n]).  One pass over the pattern (chain.py's numpy took 2.8 ms at 10^4
 * planar elements). */
void rodsnes_chain_streams(int n, const int *ai, const int *aj, const int *diag, int dir,
                           int *place, int *col, int *lofs, int *uofs)
{
    lofs[0] = 0;
    for (int s = 0; s < n; s++) {
        const int i = ROW(s);
        lofs[s + 1] = lofs[s] + (dir > 0 ? diag[i] - ai[i] : ai[i + 1] - 1 - diag[i]);
    }
    uofs[0] = lofs[n];
    for (int s = 0; s < n; s++) {
        const int i = ROW(s);
        uofs[s + 1] = uofs[s] + (ai[i + 1] - ai[i]) - (lofs[s + 1] - lofs[s]);
    }
    for (int s = 0; s < n; s++) {
        const int i = ROW(s), st = ai[i], sp = ai[i + 1], d = diag[i];
        for (int p = st; p < sp; p++) {
            int slot;
            if (dir > 0) slot = p < d ? lofs[s] + (p - st) : uofs[s] + (p - d);
            else slot = p > d ? lofs[s] + (sp - 1 - p) : uofs[s] + (p == d ? 0 : 1 + (p - st));
            place[p] = slot;
            col[slot] = aj[p];
        }
    }
}

#define DISPATCH(call3, call6, callany) \
    do { if (bs == 3) { call3; } else if (bs == 6) { call6; } else { callany; } } while (0)

/* V <- the factors of the blocks A of the block CSR in the two streams (above), each block
 * taken as it is (kind 0), as zero (1) or as the identity (2: a row taken out); target: the
 * slots of plan's updates.  With neg (not NULL) the pivot blocks' negative eigenvalues are
 * added to *neg (a symmetric matrix's inertia).  Returns 0, the 1-based row of a singular
 * diagonal block, or -1 for a block size outside 1..8. */
int rodsnes_chain_factor_streams(int n, int bs, const int *ai, const int *place, const int *lofs,
                                 const int *uofs, const int *col, int dir, const int *target,
                                 const double *A, const signed char *kind, double *V, int *neg)
{
    if (bs < 1 || bs > 8) return -1;
    int r;
    DISPATCH(r = factor_bs(3, n, ai, place, lofs, uofs, col, dir, target, A, kind, V, neg),
             r = factor_bs(6, n, ai, place, lofs, uofs, col, dir, target, A, kind, V, neg),
             r = factor_bs(bs, n, ai, place, lofs, uofs, col, dir, target, A, kind, V, neg));
    return r;
}

/* x (n bs) <- U^-1 L^-1 x restricted: the forward substitution over the order positions
 * first..n-1, the backward one over n-1..last.  first = 0, last = 0: the whole solve. */
int rodsnes_chain_solve_streams(int n, int bs, const int *lofs, const int *uofs, const int *col,
                                int dir, const double *V, int first, int last, double *x)
{
    if (bs < 1 || bs > 8) return -1;
    if (first < n)
        DISPATCH(forward_bs(3, n, lofs, col, dir, V, first, x),
                 forward_bs(6, n, lofs, col, dir, V, first, x),
                 forward_bs(bs, n, lofs, col, dir, V, first, x));
    if (last < n)
        DISPATCH(backward_bs(3, n, uofs, col, dir, V, last, x),
                 backward_bs(6, n, uofs, col, dir, V, last, x),
                 backward_bs(bs, n, uofs, col, dir, V, last, x));
    return 0;
}
