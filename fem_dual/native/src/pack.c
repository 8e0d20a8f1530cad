/* Rows of packed kernel coefficients: the gather of a compiled expression's coefficients
   (fem_dual.native.force.PackedExpression.pack) and the scatter of a slab's free unknowns into
   them (fem_dual_put_state). */
#include "internal.h"

/* PackedExpression.pack: the row of every cell, packed[e, offset[k] + j] =
   values_k[index_k[e, j]], j < width[k], for the coefficients k (the addresses of their values
   and of their (cells, width[k]) indices in `values` and `index`). */
void fem_dual_pack(int cells, int ncoef, int wsize, const int64_t *width,
                   const int64_t *offset, const uintptr_t *values, const uintptr_t *index,
                   double *packed)
{
    int k, e, j;
    for (k = 0; k < ncoef; ++k) {
        const double *v = (const double *)values[k];
        const int64_t *ix = (const int64_t *)index[k];
        const int64_t m = width[k];
        for (e = 0; e < cells; ++e) {
            double *row = packed + (int64_t)e * wsize + offset[k];
            const int64_t *at = ix + e * m;
            for (j = 0; j < m; ++j) row[j] = v[at[j]];
        }
    }
}

/* The free unknowns x into the dual state's columns of packed rows (cells x wsize): column
   wslot[e nw + j] of row e from x[wfree[e nw + j]]; -1 keeps the packed (Dirichlet) value. */
void fem_dual_put_state(int cells, int wsize, int nw, double *packed, const int64_t *wslot,
                        const int64_t *wfree, const double *x)
{
    int e, j;
    for (e = 0; e < cells; ++e) {
        double *row = packed + (int64_t)e * wsize;
        for (j = 0; j < nw; ++j) {
            int64_t f = wfree[(int64_t)e * nw + j];
            if (f >= 0) row[wslot[(int64_t)e * nw + j]] = x[f];
        }
    }
}
