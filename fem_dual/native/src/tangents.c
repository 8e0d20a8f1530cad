/* The exact tangents of a solved slab after their banded solve
   (fem_dual.slab.local_action.LocalAction._tangent_matrix). */
#include <string.h>

#include "fem_dual_native.h"

/* The tangents of LocalAction._tangent_matrix after its banded solve: from the solved
   unknowns dw ((N + 1) x k1, row N zero for the fixed unknowns; rows (cells, nd, bs): the row
   of each cell unknown) to the change of the momenta at the cell ends, dm (cells, 2, 2n, k1).
   At each point, dZ = T dw (the values and derivatives of the cell's unknowns: T (cells, nq,
   2, nd)), dg = H dZ with H the density's Hessian from its upper pairs (pk, pl; entries cols
   of out (cells, nq, ncols)), summed against the weighted table Tg (cells, nd, nq 2) of the
   two end basis functions; then signed by the cell's orientation (sign (cells, 2)), the
   velocity rows times M^-1 (minv, n x n). work: 4 bs k1 doubles. */
void fem_dual_tangents(int cells, int nq, int nd, int bs, int n, int k1, const double *T,
                       const double *Tg, const double *out, int ncols, int npairs,
                       const int64_t *cols, const int64_t *pk, const int64_t *pl,
                       const double *dw, const int64_t *rows, const double *sign,
                       const double *minv, double *dm, double *work)
{
    const int m = 2 * bs, K = 2 * n;
    double *dZ = work, *dg = work + (int64_t)m * k1;
    int c, q, s, a, b, k, p, i, j;
    memset(dm, 0, (size_t)cells * 2 * K * k1 * sizeof(double));
    for (c = 0; c < cells; ++c) {
        double *dmc = dm + (int64_t)c * 2 * K * k1;
        for (q = 0; q < nq; ++q) {
            const double *oq = out + ((int64_t)c * nq + q) * ncols;
            for (s = 0; s < 2; ++s) {
                const double *Tq = T + (((int64_t)c * nq + q) * 2 + s) * nd;
                for (b = 0; b < bs; ++b) {
                    double *z = dZ + (int64_t)(s * bs + b) * k1;
                    for (k = 0; k < k1; ++k) z[k] = 0.0;
                    for (a = 0; a < nd; ++a) {
                        const double t = Tq[a];
                        const double *w = dw + rows[((int64_t)c * nd + a) * bs + b] * k1;
                        for (k = 0; k < k1; ++k) z[k] += t * w[k];
                    }
                }
            }
            memset(dg, 0, (size_t)m * k1 * sizeof(double));
            for (p = 0; p < npairs; ++p) {
                const double h = oq[cols[p]];
                const int64_t r = pk[p], l = pl[p];
                for (k = 0; k < k1; ++k) dg[r * k1 + k] += h * dZ[l * k1 + k];
                if (r != l)
                    for (k = 0; k < k1; ++k) dg[l * k1 + k] += h * dZ[r * k1 + k];
            }
            for (a = 0; a < 2; ++a)
                for (s = 0; s < 2; ++s) {
                    const double t = Tg[((int64_t)c * nd + a) * (nq * 2) + q * 2 + s];
                    for (b = 0; b < K; ++b) {
                        double *d = dmc + ((int64_t)a * K + b) * k1;
                        const double *g = dg + (int64_t)(s * bs + b) * k1;
                        for (k = 0; k < k1; ++k) d[k] += t * g[k];
                    }
                }
        }
        for (a = 0; a < 2; ++a) {
            double *d = dmc + (int64_t)a * K * k1;
            for (i = 0; i < K * k1; ++i) d[i] *= sign[c * 2 + a];
            for (k = 0; k < k1; ++k) {  /* the velocity rows: M^-1 (M v)' (dZ as scratch) */
                for (i = 0; i < n; ++i) {
                    double acc = 0.0;
                    for (j = 0; j < n; ++j) acc += minv[i * n + j] * d[(n + j) * k1 + k];
                    dZ[i] = acc;
                }
                for (i = 0; i < n; ++i) d[(n + i) * k1 + k] = dZ[i];
            }
        }
    }
}
