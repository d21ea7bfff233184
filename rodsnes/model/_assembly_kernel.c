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
