/* Element blocks added straight into the value array of a PETSc BAIJ or SBAIJ matrix
 * (rodsnes/model/assembly.py, loaded with ctypes; plain C99, no Python API).
 *
 *   int rodsnes_add_element_blocks(double *a, const int32_t *pos, const double *V,
 *                          int64_t ne, int k, int bs);
 *
 * V (ne, k bs, k bs), row-major: the tangents of ne groups of k nodes, bs unknowns a node.
 * pos (ne, k, k): the place of each node pair's block in the matrix's block CSR (its blocks'
 * values a[pos bs^2 ...], bs x bs column by column, PETSc's storage), or -1: not added here.
 * Adds V's blocks there (ADD_VALUES).  Returns 1 for a block size it is not made for.
 */
#include "_element_blocks.h"

int rodsnes_add_element_blocks(double *a, const int32_t *pos, const double *V, int64_t ne, int k,
                       int bs)
{
    return add_element_blocks(a, pos, (const signed char *)0, V, ne, k, bs);
}

/*   int64_t rodsnes_element_places(int64_t ne, int k, const int64_t *L,
 *                                  const signed char *direct, int64_t nrows,
 *                                  const int32_t *ai, const int32_t *aj, int upper,
 *                                  int32_t *pos, signed char *first, signed char *seen);
 *
 * The places of the blocks of ne groups of k block rows L (ne, k) (local rows and columns)
 * in a block CSR of nrows rows (ai, aj: the columns of each row sorted), for the groups with
 * direct[e] != 0: pos (ne, k, k) the place of block (L[e, a], L[e, b]), or -1 (a group not
 * direct, a block the pattern lacks, and where ``upper``, the matrix keeping its upper blocks
 * alone, a lower block);
 * first (ne, k, k) 1 at each block's first addition in the order (group, row, column);
 * seen (ai[nrows], zero on entry) 1 at every block a direct group holds.  Returns how many
 * blocks of direct groups the pattern lacks (0: every one in place).  assembly.py's
 * ElementBlocks; the numpy way there does the same (a search over every block's code). */
int64_t rodsnes_element_places(int64_t ne, int k, const int64_t *L, const signed char *direct,
                               int64_t nrows, const int32_t *ai, const int32_t *aj, int upper,
                               int32_t *pos, signed char *first, signed char *seen)
{
    int64_t missing = 0;
    for (int64_t e = 0; e < ne; e++) {
        const int64_t *le = L + e * k;
        for (int a = 0; a < k; a++)
            for (int b = 0; b < k; b++) {
                const int64_t o = (e * k + a) * k + b, r = le[a], c = le[b];
                pos[o] = -1;
                first[o] = 0;
                if (!direct[e] || (upper && r > c))
                    continue;
                if (r < 0 || r >= nrows) {
                    missing++;
                    continue;
                }
                int32_t lo = ai[r], hi = ai[r + 1];
                while (lo < hi) {               /* the first column >= c in the row */
                    const int32_t m = lo + (hi - lo) / 2;
                    if (aj[m] < c) lo = m + 1;
                    else hi = m;
                }
                if (lo < ai[r + 1] && aj[lo] == c) {
                    pos[o] = lo;
                    if (!seen[lo]) {
                        seen[lo] = 1;
                        first[o] = 1;
                    }
                } else
                    missing++;
            }
    }
    return missing;
}
