/* A slab's error estimate (fem_dual.integrate.simulation._estimates) and what the run's
   accumulator keeps of accepted slabs (fem_dual.integrate.sinks.Accumulator). */
#include <math.h>
#include <stddef.h>

#include "fem_dual_native.h"

/* fem_dual.integrate.simulation._estimates of S slabs of V vertices (states of m = 2n
   components, x then v; z, zc the answer's and the companion's, contiguous): local = ((zc - z)
   + alg) safety, plus lost from the second vertex on; glob = local + psi (written only where
   psi is given); the error weights' running scales (the largest |x| and |v| so far, from
   scale_x and scale_v; a part that has not moved takes the other's scale), the round-off
   floor, the weighted local error per unit of time (dt / T: per_time, or per_slab[s] where
   that is given) and the weighted global error. alg, psi and lost may be NULL. Returns 1 where
   a value is not finite or a weight is not positive (the numpy code judges those), else 0. */
int fem_dual_estimate(int S, int V, int n, const double *z, const double *zc,
                      const double *alg, const double *psi, const double *lost,
                      double safety, double roundoff, double atol, double rtol,
                      double scale_x, double scale_v, double per_time,
                      const double *per_slab, double *local, double *glob, double *scales,
                      double *floor, double *err_local, double *err_global)
{
    const int m = 2 * n;
    double sx = scale_x, sv = scale_v;
    int s, v, c;
    for (s = 0; s < S; ++s) {
        double peak[2] = {0.0, 0.0}, lpeak[2] = {0.0, 0.0}, gpeak[2] = {0.0, 0.0};
        double scale[2], wx, wv, a, b;
        for (v = 0; v < V; ++v) {
            const int64_t row = ((int64_t)s * V + v) * m;
            for (c = 0; c < m; ++c) {
                const int64_t i = row + c;
                const int part = c >= n;
                double l = zc[i] - z[i], g;
                if (alg != NULL) l = l + alg[i];
                l = l * safety;
                if (lost != NULL && v > 0) l = l + lost[(int64_t)s * m + c];
                g = psi != NULL ? l + psi[i] : l;
                if (!isfinite(l) || !isfinite(g)) return 1;
                local[i] = l;
                if (psi != NULL) glob[i] = g;
                if (fabs(z[i]) > peak[part]) peak[part] = fabs(z[i]);
                if (fabs(l) > lpeak[part]) lpeak[part] = fabs(l);
                if (fabs(g) > gpeak[part]) gpeak[part] = fabs(g);
            }
        }
        if (peak[0] > sx) sx = peak[0];
        if (peak[1] > sv) sv = peak[1];
        scale[0] = sx > 0.0 ? sx : sv;
        scale[1] = sv > 0.0 ? sv : sx;
        wx = atol + rtol * scale[0];
        wv = atol + rtol * scale[1];
        if (!(wx > 0.0) || !(wv > 0.0)) return 1;
        scales[2 * s] = scale[0];
        scales[2 * s + 1] = scale[1];
        floor[2 * s] = roundoff * scale[0];
        floor[2 * s + 1] = roundoff * scale[1];
        a = lpeak[0] - floor[2 * s];
        b = lpeak[1] - floor[2 * s + 1];
        a = (a > 0.0 ? a : 0.0) / wx;
        b = (b > 0.0 ? b : 0.0) / wv;
        err_local[s] = (a >= b ? a : b) / (per_slab != NULL ? per_slab[s] : per_time);
        a = gpeak[0] / wx;
        b = gpeak[1] / wv;
        err_global[s] = a >= b ? a : b;
    }
    return 0;
}

/* fem_dual.integrate.sinks.Accumulator's summaries of S accepted slabs of V vertices (m = 2n
   state components; glob, local (S, V, m), H (S, V) and floor (S, 2) contiguous): the reported
   error of a vertex, max(max |glob| over a part's components, the part's floor), and of it
   rows[r] (the larger part) and peak[part] over the kept vertices (all but each slab's first,
   the run's first vertex kept where `first`), final[part] at the last vertex, glob_peak[s] over
   the slab's vertices; local_peak[s] = max |local| (0 for none); H's low, high and drift,
   (high - low) / max(high, -low, tiny). Returns 1 where a value is not finite (the numpy
   code), else 0. */
int fem_dual_summary(int S, int V, int n, int first, const double *glob,
                     const double *local, const double *floor, const double *H, double tiny,
                     double *rows, double *peak, double *final, double *glob_peak,
                     double *local_peak, double *low, double *high, double *drift)
{
    const int m = 2 * n;
    int s, v, c, r = 0;
    peak[0] = peak[1] = -INFINITY;
    for (s = 0; s < S; ++s) {
        double gp = -INFINITY, lp = 0.0, lo = INFINITY, hi = -INFINITY, size;
        for (v = 0; v < V; ++v) {
            const int64_t row = ((int64_t)s * V + v) * m;
            const double h = H[(int64_t)s * V + v];
            double part[2];
            int k;
            if (!isfinite(h)) return 1;
            if (h < lo) lo = h;
            if (h > hi) hi = h;
            for (k = 0; k < 2; ++k) {
                double g = 0.0;
                for (c = k * n; c < (k + 1) * n; ++c) {
                    const double a = fabs(glob[row + c]), b = fabs(local[row + c]);
                    if (!isfinite(a) || !isfinite(b)) return 1;
                    if (a > g) g = a;
                    if (b > lp) lp = b;
                }
                part[k] = g > floor[2 * s + k] ? g : floor[2 * s + k];
                if (part[k] > gp) gp = part[k];
            }
            if (v > 0 || (s == 0 && first)) {
                rows[r++] = part[0] >= part[1] ? part[0] : part[1];
                for (k = 0; k < 2; ++k)
                    if (part[k] > peak[k]) peak[k] = part[k];
            }
            if (s == S - 1 && v == V - 1) {
                final[0] = part[0];
                final[1] = part[1];
            }
        }
        glob_peak[s] = gp;
        local_peak[s] = lp;
        low[s] = lo;
        high[s] = hi;
        size = hi >= -lo ? hi : -lo;
        drift[s] = (hi - lo) / (size >= tiny ? size : tiny);
    }
    return 0;
}
