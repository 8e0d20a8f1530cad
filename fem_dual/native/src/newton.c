/* One slab's Newton on the pointwise assembly (fem_dual.slab.native_newton.NativeNewton). */
#include <math.h>
#include <string.h>

#include "internal.h"

struct slab {
    kernel_t kernel;
    int cells, nq, ncols, wsize, nw, nd, bs, N, kd;
    double *packed, *out, *r, *B;
    const double *c, *coords, *Tg, *initial, *scale, *PT;
    const int64_t *wslot, *wfree, *r_keep, *r_rows, *start_rows;
    int64_t nkeep, entries;
    int nstart, npairs, ngroups, nd2;
    const int64_t *cols, *lo, *hi, *start, *flat, *source;
    fem_dual_dtp *dtp;
    double *sums;  /* N doubles of work (the trial state's buffer: free while the band is
                      made) */
};

static double dot(int n, const double *a, const double *b)
{
    double s = 0.0;
    int i;
    for (i = 0; i < n; ++i) s += a[i] * b[i];
    return s;
}

/* R at x into F (the implicit DtP map solved there first); returns |R| (2-norm), NaN
   where the map hands back */
static double slab_evaluate(const struct slab *S, const double *x, double *F)
{
    const int local = 0;
    const uint8_t perm = 0;
    const int nq2 = 2 * S->nq;
    int e, a, c, j;
    int64_t k;
    fem_dual_put_state(S->cells, S->wsize, S->nw, S->packed, S->wslot, S->wfree, x);
    if (S->dtp != NULL && fem_dual_dtp_solve(S->dtp, S->cells, x, S->packed, S->wsize) != 0)
        return NAN;
    memset(S->out, 0, (int64_t)S->cells * S->nq * S->ncols * sizeof(double));
    for (e = 0; e < S->cells; ++e)
        S->kernel(S->out + (int64_t)e * S->nq * S->ncols, S->packed + (int64_t)e * S->wsize,
                  S->c, S->coords + (int64_t)e * 6, &local, &perm);
    for (e = 0; e < S->cells; ++e) {
        const double *o = S->out + (int64_t)e * S->nq * S->ncols;
        for (a = 0; a < S->nd; ++a) {
            const double *t = S->Tg + ((int64_t)e * S->nd + a) * nq2;
            double *ra = S->r + ((int64_t)e * S->nd + a) * S->bs;
            for (c = 0; c < S->bs; ++c) {
                double s = 0.0;
                for (j = 0; j < nq2; ++j) s += t[j] * o[(j / 2) * S->ncols + (j % 2) * S->bs + c];
                ra[c] = s;
            }
        }
    }
    memset(F, 0, S->N * sizeof(double));
    for (k = 0; k < S->nkeep; ++k) F[S->r_rows[k]] += S->r[S->r_keep[k]];
    for (j = 0; j < S->nstart; ++j) F[S->start_rows[j]] += S->initial[j];
    return sqrt(dot(S->N, F, F));
}

/* The Jacobian at the last evaluation (its Hessian in S->out) into chol, its upper band in
   LAPACK's storage (Fortran, (kd + 1) x N: flat and source are the entries on and above the
   diagonal); returns its 1-norm (the largest column sum of the symmetric matrix: a column's
   entries on and above the diagonal, and its row's right of it). */
static double slab_band(const struct slab *S, double *chol)
{
    const int N = S->N, kd = S->kd, ldab = kd + 1;
    double largest = 0.0;
    int i, j;
    fem_dual_band(S->cells, S->nq, S->ncols, S->out, S->npairs, S->cols, S->scale, S->ngroups,
                  S->lo, S->hi, S->start, S->PT, S->nd2, S->entries, S->flat, S->source, S->B,
                  chol, (int64_t)ldab * N);
    memset(S->sums, 0, N * sizeof(double));
    for (j = 0; j < N; ++j)
        for (i = 0; i <= kd; ++i) {  /* chol[i + j ldab] = J(j - kd + i, j) */
            const int r = j - kd + i;
            const double v = fabs(chol[(int64_t)j * ldab + i]);
            if (r < 0) continue;
            S->sums[j] += v;
            if (r != j) S->sums[r] += v;
        }
    for (j = 0; j < N; ++j)
        if (S->sums[j] > largest) largest = S->sums[j];
    return largest;
}

/* One slab's Newton on the pointwise assembly of fem_dual.slab.local_action.LocalAction (an
   explicit DtP map): the iteration of fem_dual.slab.pointwise_newton.PointwiseNewtonSolver.solve
   while every full step lowers the residual enough. Each evaluation puts the free unknowns x
   into the dual state's columns of the packed rows (wslot, wfree: -1 keeps the packed value,
   a Dirichlet one), calls the kernel of the density's gradient and Hessian on every cell into
   `out`, assembles R (the residual of LocalAction._residual: r_e = Tg_e g_e, scattered to rows
   r_rows, plus the initial rows); where a step is factored, the band (fem_dual_band, its
   entries on and above the diagonal only, straight into `chol`: LAPACK's upper storage,
   Fortran order, (kd + 1) x N), factored there by fem_dual_band_cholesky; row: kd + 1
   doubles of work.
   Returns 0 when Newton ended (*reason: 1 CONVERGED_FNORM_ABS, 2 CONVERGED_FNORM_RELATIVE,
   3 CONVERGED_SNORM_RELATIVE, -1 DIVERGED_MAX_IT; x the last iterate, F its residual, out
   its evaluation, chol the last step's factors, *last_step that step relative to x,
   history[0 .. *iterations], *backward the backward floor at the last factored iterate; where
   `final` is not NULL and Newton's last step exceeded kept_step (relative: else chol serves
   as the factors at x), the Jacobian at x factored into it, Fortran (kd + 1) x N, and
   *final_factored 1 where it is positive definite), 1 where the numpy iteration must decide (a
   residual that is not finite, a Jacobian that is not positive definite, a step that is not
   finite or that the line search would shorten): x is then undefined. */
int fem_dual_slab_newton(uintptr_t kernel, int cells, int nq, int ncols, int wsize,
                         double *packed, const double *c, const double *coords, int nw,
                         const int64_t *wslot, const int64_t *wfree, int nd, int bs,
                         const double *Tg, int64_t nkeep, const int64_t *r_keep,
                         const int64_t *r_rows, int nstart, const int64_t *start_rows,
                         const double *initial, int npairs, const int64_t *cols,
                         const double *scale, int ngroups, const int64_t *lo,
                         const int64_t *hi, const int64_t *start, const double *PT, int nd2,
                         int64_t entries, const int64_t *flat, const int64_t *source,
                         double *B, int N, int kd, double *chol,
                         double *row, double *x, double *F,
                         double *step, double *trial, double *Fnew, double *r, double *out,
                         double atol, int check_start, double rtol, double stol, int max_it,
                         int patience, double no_progress, double decrease,
                         double *history, int *iterations, double *backward, double *last_step,
                         int *reason, fem_dual_dtp *dtp, double *final,
                         double kept_step, int *final_factored)
{
    struct slab S;
    double fnorm, first, gnorm;
    int it = 0, j, ldab = kd + 1;
    S.kernel = (kernel_t)kernel; S.cells = cells; S.nq = nq; S.ncols = ncols;
    S.wsize = wsize; S.nw = nw; S.nd = nd; S.bs = bs; S.N = N; S.kd = kd;
    S.packed = packed; S.out = out; S.r = r; S.B = B; S.c = c;
    S.coords = coords; S.Tg = Tg; S.initial = initial; S.scale = scale; S.PT = PT;
    S.wslot = wslot; S.wfree = wfree; S.r_keep = r_keep; S.r_rows = r_rows;
    S.start_rows = start_rows; S.nkeep = nkeep; S.entries = entries; S.nstart = nstart;
    S.npairs = npairs; S.ngroups = ngroups; S.nd2 = nd2; S.cols = cols; S.lo = lo; S.hi = hi;
    S.start = start; S.flat = flat; S.source = source; S.dtp = dtp; S.sums = trial;

    *backward = 0.0;
    *last_step = INFINITY;
    *final_factored = 0;
    fnorm = slab_evaluate(&S, x, F);
    history[0] = first = fnorm;
    *iterations = 0;
    if (!isfinite(fnorm)) return 1;
    if (check_start && fnorm < atol) {
        *reason = 1;
        return 0;
    }
    for (;;) {
        double largest = slab_band(&S, chol), xmax = 0.0, ynorm, xnorm, bw;
        for (j = 0; j < N; ++j)
            if (fabs(x[j]) > xmax) xmax = fabs(x[j]);
        bw = 8.0 * 2.220446049250313e-16 * largest * xmax;
        *backward = isfinite(bw) ? bw : 0.0;
        if (fem_dual_band_cholesky(N, kd, chol, ldab, row) != 0) return 1;
        memcpy(step, F, N * sizeof(double));
        fem_dual_band_solve(N, kd, chol, ldab, 1, step);
        for (j = 0; j < N; ++j) {
            if (!isfinite(step[j])) return 1;
            trial[j] = x[j] - step[j];
        }
        gnorm = slab_evaluate(&S, trial, Fnew);
        if (!(isfinite(gnorm) && gnorm <= (1.0 - decrease) * fnorm)) return 1;
        ++it;
        ynorm = sqrt(dot(N, step, step));
        memcpy(x, trial, N * sizeof(double));
        memcpy(F, Fnew, N * sizeof(double));
        fnorm = gnorm;
        history[it] = fnorm;
        *iterations = it;
        xnorm = sqrt(dot(N, x, x));
        *last_step = ynorm / xnorm;
        if (fnorm < atol) *reason = 1;
        else if (fnorm <= rtol * first) *reason = 2;
        else if (ynorm < stol * xnorm) *reason = 3;
        else if ((patience >= 0 && it >= (max_it < patience ? max_it : patience)
                  && fnorm > no_progress * first) || it >= max_it) *reason = -1;
        else continue;
        if (final != NULL && *last_step > kept_step) {  /* the Jacobian at x, factored */
            slab_band(&S, final);
            *final_factored = fem_dual_band_cholesky(N, kd, final, ldab, row) == 0;
        }
        return 0;
    }
}
