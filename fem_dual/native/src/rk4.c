/* Classical RK4 in Nystrom form with the force from its FFCx kernel, and the cubic Hermite of
   its step ends (fem_dual.slab.base_state.FlowPredictor). */
#include <math.h>
#include <string.h>

#include "internal.h"

/* The one-cell mesh of fem_dual.native.force.CompiledForce: the kernel's coordinate dofs. */
static const double CELL[6] = {0.0, 0.0, 0.0, 1.0, 0.0, 0.0};

/* a = S F(x): S = scale I, or the matrix minv (n x n, row-major) where it is not NULL */
static void accel(kernel_t F, const double *c, int n, double scale, const double *minv,
                  const double *x, double *f, double *a)
{
    int i, j;
    const int local = 0;
    const uint8_t perm = 0;
    memset(f, 0, n * sizeof(double));
    F(f, x, c, CELL, &local, &perm);
    if (minv == NULL) {
        for (i = 0; i < n; ++i) a[i] = scale * f[i];
        return;
    }
    for (i = 0; i < n; ++i) {
        double s = 0.0;
        for (j = 0; j < n; ++j) s += minv[i * n + j] * f[j];
        a[i] = s;
    }
}

/* Classical RK4 of x' = v, v' = a(x) in Nystrom form over `steps` steps of length h from z0 =
   (x, v): states and rates (steps + 1, 2n), rates = (v, a(x)). work: 7 n doubles. Returns 0, or
   1 where a value is not finite (the loop stops there). */
int fem_dual_rk4(uintptr_t kernel, const double *c, int n, int steps, double h, double scale,
                 const double *minv, const double *z0, double *states, double *rates,
                 double *work)
{
    kernel_t F = (kernel_t)kernel;
    double *k1 = work, *k2 = work + n, *k3 = work + 2 * n, *k4 = work + 3 * n;
    double *y = work + 4 * n, *ahead = work + 5 * n, *f = work + 6 * n;
    const double half = 0.5 * h, h2 = 0.25 * h * h, hh2 = 0.5 * h * h;
    const double hh6 = h * h / 6.0, h6 = h / 6.0;
    int s, i, m = 2 * n;
    double *x, *v;
    memcpy(states, z0, m * sizeof(double));
    accel(F, c, n, scale, minv, states, f, k1);
    memcpy(rates, states + n, n * sizeof(double));
    memcpy(rates + n, k1, n * sizeof(double));
    for (s = 0; s < steps; ++s) {
        x = states + s * m;
        v = x + n;
        for (i = 0; i < n; ++i) y[i] = x[i] + half * v[i];
        accel(F, c, n, scale, minv, y, f, k2);
        for (i = 0; i < n; ++i) y[i] += h2 * k1[i];
        accel(F, c, n, scale, minv, y, f, k3);
        for (i = 0; i < n; ++i) {
            ahead[i] = x[i] + h * v[i];
            y[i] = ahead[i] + hh2 * k2[i];
        }
        accel(F, c, n, scale, minv, y, f, k4);
        for (i = 0; i < n; ++i) {
            x[m + i] = ahead[i] + hh6 * (k1[i] + k2[i] + k3[i]);
            x[m + n + i] = v[i] + h6 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]);
        }
        accel(F, c, n, scale, minv, x + m, f, k1);
        for (i = 0; i < n; ++i) {
            rates[(s + 1) * m + i] = x[m + n + i];
            rates[(s + 1) * m + n + i] = k1[i];
        }
        for (i = 0; i < m; ++i)
            if (!isfinite(x[m + i]) || !isfinite(rates[(s + 1) * m + i])) return 1;
    }
    return 0;
}

/* The cubic Hermite of an rk4 run at m times (FlowPredictor.along): out[i] = sum_j w[i, j]
   [states; h rates][rows[i, j]], j < 4, for states and rates (steps + 1, n2) each. */
void fem_dual_hermite(int m, int n2, int steps, double h, const int64_t *rows, const double *w,
                      const double *states, const double *rates, double *out)
{
    int i, j, c;
    for (i = 0; i < m; ++i) {
        double *o = out + (int64_t)i * n2;
        for (c = 0; c < n2; ++c) o[c] = 0.0;
        for (j = 0; j < 4; ++j) {
            const int64_t r = rows[i * 4 + j];
            const double wt = w[i * 4 + j];
            if (r <= steps) {
                const double *s = states + r * n2;
                for (c = 0; c < n2; ++c) o[c] += wt * s[c];
            } else {
                const double *s = rates + (r - steps - 1) * n2;
                for (c = 0; c < n2; ++c) o[c] += wt * (h * s[c]);
            }
        }
    }
}
