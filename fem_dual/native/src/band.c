/* The band of a slab's Jacobian from the density's Hessian at the quadrature points
   (fem_dual.slab.local_action.LocalAction._band). */
#include <string.h>

#include "fem_dual_native.h"

/* The band of LocalAction._band: for each Hessian group g (pairs lo[g] .. hi[g] - 1, basis
   table P_g (nd2, nq), given transposed: PT_g (nq, nd2) at PT + g nq nd2),
   B[start[g] + (ab cells + e) members + m - lo[g]] = sum_q P_g[ab, q] out[e, q, cols[m]]
   scale[e, m]; then band[flat[k]] += B[source[k]]. band (zeroed here) and B are the
   caller's. */
void fem_dual_band(int cells, int nq, int ncols, const double *out, int npairs,
                   const int64_t *cols, const double *scale, int ngroups, const int64_t *lo,
                   const int64_t *hi, const int64_t *start, const double *PT, int nd2,
                   int64_t entries, const int64_t *flat, const int64_t *source, double *B,
                   double *band, int64_t band_size)
{
    int g, e, m, q, ab;
    int64_t k;
    double acc[1024];
    for (g = 0; g < ngroups; ++g) {
        const double *Pg = PT + (int64_t)g * nd2 * nq;
        int members = (int)(hi[g] - lo[g]);
        for (e = 0; e < cells; ++e) {
            for (m = (int)lo[g]; m < hi[g]; ++m) {
                const double sc = scale[(int64_t)e * npairs + m];
                double *Bm = B + start[g] + (int64_t)e * members + (m - lo[g]);
                for (ab = 0; ab < nd2; ++ab) acc[ab] = 0.0;
                for (q = 0; q < nq; ++q) {
                    const double h = out[((int64_t)e * nq + q) * ncols + cols[m]] * sc;
                    const double *row = Pg + (int64_t)q * nd2;
                    for (ab = 0; ab < nd2; ++ab) acc[ab] += row[ab] * h;
                }
                for (ab = 0; ab < nd2; ++ab) Bm[(int64_t)ab * cells * members] = acc[ab];
            }
        }
    }
    memset(band, 0, band_size * sizeof(double));
    for (k = 0; k < entries; ++k) band[flat[k]] += B[source[k]];
}
