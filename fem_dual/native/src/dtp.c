/* The implicit DtP map (fem_dual.slab.pointwise_dtp.PointwiseDtP): its pointwise Newton on all
   cells at once, alone or inside a slab's compiled Newton (fem_dual_dtp_solve). */
#include <math.h>
#include <string.h>

#include "internal.h"

/* x = A^-1 b for one n x n matrix (row-major; n = 2 by the closed form of
   fem_dual.slab.pointwise_dtp._solve, else Gaussian elimination with partial pivoting). A is
   kept. */
static void small_solve(int n, const double *A, const double *b, double *x, double *work)
{
    int i, j, k, piv;
    if (n == 2) {
        double det = A[0] * A[3] - A[1] * A[2];
        x[0] = (A[3] * b[0] - A[1] * b[1]) / det;
        x[1] = (A[0] * b[1] - A[2] * b[0]) / det;
        return;
    }
    memcpy(work, A, n * n * sizeof(double));
    memcpy(x, b, n * sizeof(double));
    for (k = 0; k < n; ++k) {
        piv = k;
        for (i = k + 1; i < n; ++i)
            if (fabs(work[i * n + k]) > fabs(work[piv * n + k])) piv = i;
        if (piv != k) {
            double t;
            for (j = 0; j < n; ++j) {
                t = work[k * n + j]; work[k * n + j] = work[piv * n + j]; work[piv * n + j] = t;
            }
            t = x[k]; x[k] = x[piv]; x[piv] = t;
        }
        for (i = k + 1; i < n; ++i) {
            double f = work[i * n + k] / work[k * n + k];
            for (j = k; j < n; ++j) work[i * n + j] -= f * work[k * n + j];
            x[i] -= f * x[k];
        }
    }
    for (i = n - 1; i >= 0; --i) {
        double s = x[i];
        for (j = i + 1; j < n; ++j) s -= work[i * n + j] * x[j];
        x[i] = s / work[i * n + i];
    }
}

/* The Newton iteration of PointwiseDtP.solve on all cells at once: evaluate (G, G_x, t) at
   every point (kernel of the packed expression: `packed` (cells, wsize) holds its
   coefficients, X's values at columns xslot[p n + k] of a cell's row), step = G_x^-1 G, stop
   on a step that is not finite (returns 1) or after the step at which max |step| <=
   last_step (1 + max |X|) (returns 0), else 2 after max_it + 1 evaluations. X (the point
   function's values, block index xdofs[e points + p]) and the packed rows follow every step;
   `out` keeps the last evaluation, `step` the last step, *iterations the last iteration. */
int fem_dual_dtp_newton(uintptr_t kernel, int cells, int points, int n, int wsize,
                        double *packed, const int64_t *xslot, const double *c,
                        const double *coords, int max_it, double last_step, double *out,
                        double *step, double *X, const int64_t *xdofs, double *work,
                        int *iterations)
{
    kernel_t K = (kernel_t)kernel;
    const int local = 0;
    const uint8_t perm = 0;
    const int width = n + n * n + 1;
    const int64_t total = (int64_t)cells * points;
    int it, e, p, k;
    int64_t i;
    for (it = 0; it <= max_it; ++it) {
        double largest = 0.0, current = 0.0;
        int finite = 1;
        *iterations = it;
        memset(out, 0, total * width * sizeof(double));
        for (e = 0; e < cells; ++e)
            K(out + (int64_t)e * points * width, packed + (int64_t)e * wsize, c,
              coords + (int64_t)e * 6, &local, &perm);
        for (i = 0; i < total; ++i) {
            const double *o = out + i * width;
            small_solve(n, o + n, o, step + i * n, work);
            for (k = 0; k < n; ++k) {
                double s = step[i * n + k];
                if (!isfinite(s)) finite = 0;
                else if (fabs(s) > largest) largest = fabs(s);
            }
        }
        if (!finite) return 1;
        for (e = 0; e < cells; ++e)
            for (p = 0; p < points; ++p) {
                int64_t block = xdofs[(int64_t)e * points + p];
                for (k = 0; k < n; ++k) {
                    double x = X[block * n + k];
                    if (fabs(x) > current) current = fabs(x);
                    x -= step[((int64_t)e * points + p) * n + k];
                    X[block * n + k] = x;
                    packed[(int64_t)e * wsize + xslot[p * n + k]] = x;
                }
            }
        if (largest <= last_step * (1.0 + current)) return 0;
    }
    return 2;
}

/* Whether the symmetric part S of the n x n matrix A is positive definite with its smallest
   eigenvalue above tol |S|_F (so above tol times its largest magnitude: the branch test of
   PointwiseDtP._branch holds; a pass here implies one there). work: n n doubles. */
static int on_branch(int n, const double *A, double tol, double *work)
{
    int i, j, k;
    double frob = 0.0;
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {
            double v = 0.5 * (A[i * n + j] + A[j * n + i]);
            work[i * n + j] = v;
            frob += v * v;
        }
    frob = sqrt(frob);
    if (!isfinite(frob)) return 0;
    for (i = 0; i < n; ++i) work[i * n + i] -= tol * frob;
    for (k = 0; k < n; ++k) {  /* Cholesky in place */
        double d = work[k * n + k];
        for (j = 0; j < k; ++j) d -= work[k * n + j] * work[k * n + j];
        if (!(d > 0.0)) return 0;
        d = sqrt(d);
        work[k * n + k] = d;
        for (i = k + 1; i < n; ++i) {
            double v = work[i * n + k];
            for (j = 0; j < k; ++j) v -= work[i * n + j] * work[k * n + j];
            work[i * n + k] = v / d;
        }
    }
    return 1;
}

/* inv = A^-1 (n x n, row-major): the closed form of fem_dual.slab.pointwise_dtp._inverse for n = 2,
   else Gauss-Jordan with partial pivoting. work: 2 n n doubles. */
static void small_inverse(int n, const double *A, double *inv, double *work)
{
    int i, j, k, piv;
    if (n == 2) {
        double det = A[0] * A[3] - A[1] * A[2];
        inv[0] = A[3] / det; inv[3] = A[0] / det;
        inv[1] = -A[1] / det; inv[2] = -A[2] / det;
        return;
    }
    memcpy(work, A, n * n * sizeof(double));
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) inv[i * n + j] = i == j ? 1.0 : 0.0;
    for (k = 0; k < n; ++k) {
        piv = k;
        for (i = k + 1; i < n; ++i)
            if (fabs(work[i * n + k]) > fabs(work[piv * n + k])) piv = i;
        for (j = 0; j < n; ++j) {
            double t = work[k * n + j]; work[k * n + j] = work[piv * n + j];
            work[piv * n + j] = t;
            t = inv[k * n + j]; inv[k * n + j] = inv[piv * n + j]; inv[piv * n + j] = t;
        }
        for (i = 0; i < n; ++i) {
            double f;
            if (i == k) continue;
            f = work[i * n + k] / work[k * n + k];
            for (j = 0; j < n; ++j) {
                work[i * n + j] -= f * work[k * n + j];
                inv[i * n + j] -= f * inv[k * n + j];
            }
        }
    }
    for (k = 0; k < n; ++k) {
        double d = work[k * n + k];
        for (j = 0; j < n; ++j) inv[k * n + j] /= d;
    }
}

/* The implicit DtP map at a slab's free unknowns x (see fem_dual_dtp), its X and G_x^-1 then
   put into the density's packed rows (cells x wsize); 0, or 1 where the numpy iteration must
   decide (Newton failed, a root off the branch). */
int fem_dual_dtp_solve(fem_dual_dtp *D, int cells, const double *x, double *packed, int wsize)
{
    const int n = D->n, width = n + n * n + 1;
    int e, j, q, status;
    fem_dual_put_state(cells, D->wsize, D->nw, D->packed, D->wslot, D->wfree, x);
    status = fem_dual_dtp_newton(D->kernel, cells, D->points, n, D->wsize, D->packed,
                                 D->xslot, D->c, D->coords, D->max_it, D->last_step, D->out,
                                 D->step, D->X, D->xdofs, D->work, &D->iterations);
    if (status != 0) return 1;
    for (e = 0; e < cells; ++e)
        for (q = 0; q < D->points; ++q) {
            const double *Gx = D->out + ((int64_t)e * D->points + q) * width + n;
            int64_t block = D->xdofs[(int64_t)e * D->points + q];
            if (!on_branch(n, Gx, D->branch_tol, D->work)) return 1;
            small_inverse(n, Gx, D->Ginv + block * n * n, D->work);
        }
    for (e = 0; e < cells; ++e) {
        double *row = packed + (int64_t)e * wsize;
        for (j = 0; j < D->nx; ++j)
            row[D->both_xslot[j]] = D->X[D->both_xindex[(int64_t)e * D->nx + j]];
        for (j = 0; j < D->ng; ++j)
            row[D->both_gslot[j]] = D->Ginv[D->both_gindex[(int64_t)e * D->ng + j]];
    }
    return 0;
}
