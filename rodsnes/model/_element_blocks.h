/* Element blocks added into the value array of a PETSc BAIJ or SBAIJ matrix: shared by
 * _assembly_kernel.c (tangents made elsewhere) and _elastic_kernel.c (the elastic tangents
 * added as they are made, rodsnes_elastic_tangents_into).
 *
 * V (ne, k bs, k bs), row-major: the tangents of ne groups of k nodes, bs unknowns a node.
 * pos (ne, k, k): the place of each node pair's block in the matrix's block CSR (its blocks'
 * values a[pos bs^2 ...], bs x bs column by column, PETSc's storage), or -1: not added here.
 * add_element_blocks adds V's blocks there (ADD_VALUES) and returns 0, or 1 for a block size
 * it is not made for (3 and 6).  first (ne, k, k) or NULL: where it is 1 the block is stored,
 * not added (its first addition since the matrix was zeroed: v + 0.0, the same bits as
 * 0.0 + v, a zero's sign included), so the matrix need not be zeroed there first. */
#include <stdint.h>

#define ADD_BLOCKS(BS)                                                                     \
    for (int64_t e = 0; e < ne; e++) {                                                     \
        const int64_t ld = (int64_t)k * BS;                     /* V's row length */       \
        const double *Ve = V + e * ld * ld;                                                \
        const int32_t *pe = pos + e * (int64_t)k * k;                                      \
        const signed char *fe = first ? first + e * (int64_t)k * k : 0;                    \
        for (int i = 0; i < k; i++)                                                        \
            for (int j = 0; j < k; j++) {                                                  \
                const int64_t p = pe[i * k + j];                                           \
                if (p < 0)                                                                 \
                    continue;                                                              \
                double *blk = a + p * (BS * BS);                                           \
                const double *v = Ve + (int64_t)i * BS * ld + (int64_t)j * BS;             \
                if (fe && fe[i * k + j])                                                   \
                    for (int c = 0; c < BS; c++)                                           \
                        for (int r = 0; r < BS; r++)                                       \
                            blk[c * BS + r] = v[r * ld + c] + 0.0;                         \
                else                                                                       \
                    for (int c = 0; c < BS; c++)                                           \
                        for (int r = 0; r < BS; r++)                                       \
                            blk[c * BS + r] += v[r * ld + c];                              \
            }                                                                              \
    }

static inline int add_element_blocks(double *a, const int32_t *pos, const signed char *first,
                                     const double *V, int64_t ne, int k, int bs)
{
    switch (bs) {
    case 3:
        ADD_BLOCKS(3)
        return 0;
    case 6:
        ADD_BLOCKS(6)
        return 0;
    default:
        return 1;
    }
}

#undef ADD_BLOCKS
