"""Compiled loops around FFCx kernels: the inner loops that Python would run step by step.

UFL stays the single source: FFCx compiles the scene's force as a `fem.Expression` (its C
kernel is `tabulate_tensor_float64`), and a small C library, compiled here once per machine with
the compiler the FFCx JIT uses and kept in the user's cache (`$XDG_CACHE_HOME/fem-dual`, by
default `~/.cache/fem-dual`), calls that kernel inside its loops. Where no compiler is found,
`library()` returns None and the callers keep their numpy loops (`reason()` says why).

What it holds:
- `rk4`: classical Runge-Kutta in Nystrom form, the loop of
  fem_dual.slab.base_state.FlowPredictor (the same stages and sums), with the force from its kernel,
  and (`hermite`) its cubic Hermite read at the slab's nodes.
- `band`: the Jacobian's band of fem_dual.slab.local_action.LocalAction from the Hessian of the
  density at the quadrature points: the products of each Hessian group with its basis table and
  their scatter into the band, in one pass (numpy: a gather, a matrix product per group, a
  gather and a bincount).
- `dtp_newton`: the Newton iteration of fem_dual.slab.pointwise_dtp.PointwiseDtP (an implicit DtP map
  solved at every point), the same steps and stopping rule, with G and G_x from the kernel of
  its expression (`PackedExpression` packs that kernel's coefficients as DOLFINx does).
- `slab_newton`: a slab's Newton of fem_dual.slab.pointwise_newton (the residual and band of
  fem_dual.slab.local_action from the kernel of the density's gradient and Hessian, the implicit
  DtP map solved inside each evaluation, the step by the banded Cholesky below), while every
  full step is taken; the numpy iteration decides the rest (line search, failures), so those
  rules live in one place.
- `band_cholesky`, `band_solve`: the banded Cholesky factorisation in LAPACK's storage (dpbtrf's
  with uplo = 'U') and its solves, for every banded Jacobian (fem_dual.slab.local_action.BandedLU):
  twice the reference LAPACK's speed on these bands.
- `tangents`: the exact tangents of a solved slab after their banded solve
  (fem_dual.slab.local_action.LocalAction._tangent_matrix): the solved unknowns through the
  density's Hessian to the momenta at the cell ends (numpy: a dozen batched products).
- `estimate`: a slab's error estimate from the answer's and the companion's vertex values
  (fem_dual.integrate.simulation._estimates; numpy: some twenty array operations a slab).
- `summary`: what the run's accumulator keeps of accepted slabs (fem_dual.integrate.sinks.Accumulator:
  their reported errors, peaks, the drift of H_d; numpy: some twenty array operations).
- `pack`: the gather of a compiled expression's coefficients into its kernel's rows
  (`PackedExpression.pack`; numpy: a gather and a copy per coefficient).
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Dict, Optional

import numpy as np

__all__ = ["library", "reason", "CompiledForce", "PackedExpression", "pointer"]

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>

typedef void (*kernel_t)(double *, const double *, const double *, const double *,
                         const int *, const uint8_t *);

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

/* x = A^-1 b for one n x n matrix (row-major; n = 2 by the closed form of
   fem_dual.slab.pointwise_dtp._solve, else Gaussian elimination with partial pivoting). A is kept. */
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
/* An implicit DtP map (fem_dual.slab.pointwise_dtp.PointwiseDtP) solved inside each evaluation: the
   dual state's values into its packed rows (wslot, wfree), its Newton (fem_dual_dtp_newton)
   from the last root X, the branch test and G_x^-1 into Ginv, then X's and Ginv's values into
   the density's rows (both_*: nx and ng columns a row, from X[both_xindex], Ginv[...]). */
typedef struct {
    uintptr_t kernel;
    int points, n, wsize, nw, max_it, nx, ng, iterations;
    double last_step, branch_tol;
    double *packed, *out, *step, *X, *Ginv, *work;
    const double *c, *coords;
    const int64_t *xslot, *wslot, *wfree, *xdofs;
    const int64_t *both_xslot, *both_xindex, *both_gslot, *both_gindex;
} fem_dual_dtp;

/* The Cholesky factor U (A = U^T U) of a symmetric positive definite band matrix in LAPACK's
   upper band storage, in place: ab[(kd + i - j) + j ldab] = A(i, j) for j - kd <= i <= j, as
   dpbtrf with uplo = 'U' leaves it (scipy's dpbtrs solves with it). Right-looking, a column at
   a time: twice as fast as the reference LAPACK's blocked dpbtrf on these bands (N = 384, kd =
   53: 150 against 330 us). row: kd + 1 doubles. Returns 0, or j + 1 where the pivot of column
   j is not positive (the matrix is not positive definite). */
int fem_dual_band_cholesky(int n, int kd, double *ab, int ldab, double *row)
{
    int j, l, i, m;
    for (j = 0; j < n; ++j) {
        double d = ab[kd + (int64_t)j * ldab];
        if (!(d > 0.0)) return j + 1;
        d = sqrt(d);
        ab[kd + (int64_t)j * ldab] = d;
        m = kd < n - 1 - j ? kd : n - 1 - j;
        for (l = 1; l <= m; ++l) {  /* row j of U right of the diagonal */
            double *u = ab + (kd - l) + (int64_t)(j + l) * ldab;
            *u /= d;
            row[l] = *u;
        }
        for (l = 1; l <= m; ++l) {  /* A(j + i, j + l) -= U(j, j + i) U(j, j + l), i <= l */
            double *column = ab + (kd - l) + (int64_t)(j + l) * ldab;
            const double r = row[l];
            for (i = 1; i <= l; ++i) column[i] -= row[i] * r;
        }
    }
    return 0;
}

/* x = A^-1 b with A = U^T U from fem_dual_band_cholesky, for nrhs right-hand sides b (n x nrhs,
   row-major), in place. */
void fem_dual_band_solve(int n, int kd, const double *ab, int ldab, int nrhs, double *b)
{
    int i, j, k;
    for (j = 0; j < n; ++j) {  /* U^T y = b */
        const double *column = ab + (int64_t)j * ldab + kd - j;  /* U(i, j) at column[i] */
        const int first = j - kd > 0 ? j - kd : 0;
        for (k = 0; k < nrhs; ++k) {
            double s = b[(int64_t)j * nrhs + k];
            for (i = first; i < j; ++i) s -= column[i] * b[(int64_t)i * nrhs + k];
            b[(int64_t)j * nrhs + k] = s / column[j];
        }
    }
    for (j = n - 1; j >= 0; --j) {  /* U x = y */
        const double *column = ab + (int64_t)j * ldab + kd - j;
        const int first = j - kd > 0 ? j - kd : 0;
        for (k = 0; k < nrhs; ++k) {
            const double x = b[(int64_t)j * nrhs + k] / column[j];
            b[(int64_t)j * nrhs + k] = x;
            for (i = first; i < j; ++i) b[(int64_t)i * nrhs + k] -= column[i] * x;
        }
    }
}

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

/* The free unknowns x into the dual state's columns of packed rows (cells x wsize): column
   wslot[e nw + j] of row e from x[wfree[e nw + j]]; -1 keeps the packed (Dirichlet) value. */
static void put_state(int cells, int wsize, int nw, double *packed, const int64_t *wslot,
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

/* The implicit DtP map at the free unknowns x (see fem_dual_dtp); 0, or 1 where the numpy
   iteration must decide (Newton failed, a root off the branch). */
static int dtp_solve(const struct slab *S, const double *x)
{
    fem_dual_dtp *D = S->dtp;
    const int n = D->n, width = n + n * n + 1;
    int e, j, q, status;
    put_state(S->cells, D->wsize, D->nw, D->packed, D->wslot, D->wfree, x);
    status = fem_dual_dtp_newton(D->kernel, S->cells, D->points, n, D->wsize, D->packed,
                                 D->xslot, D->c, D->coords, D->max_it, D->last_step, D->out,
                                 D->step, D->X, D->xdofs, D->work, &D->iterations);
    if (status != 0) return 1;
    for (e = 0; e < S->cells; ++e)
        for (q = 0; q < D->points; ++q) {
            const double *Gx = D->out + ((int64_t)e * D->points + q) * width + n;
            int64_t block = D->xdofs[(int64_t)e * D->points + q];
            if (!on_branch(n, Gx, D->branch_tol, D->work)) return 1;
            small_inverse(n, Gx, D->Ginv + block * n * n, D->work);
        }
    for (e = 0; e < S->cells; ++e) {
        double *row = S->packed + (int64_t)e * S->wsize;
        for (j = 0; j < D->nx; ++j)
            row[D->both_xslot[j]] = D->X[D->both_xindex[(int64_t)e * D->nx + j]];
        for (j = 0; j < D->ng; ++j)
            row[D->both_gslot[j]] = D->Ginv[D->both_gindex[(int64_t)e * D->ng + j]];
    }
    return 0;
}

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
    put_state(S->cells, S->wsize, S->nw, S->packed, S->wslot, S->wfree, x);
    if (S->dtp != NULL && dtp_solve(S, x) != 0) return NAN;
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

/* Classical RK4 of x' = v, v' = a(x) in Nystrom form over `steps` steps of length h from z0 =
   (x, v): states and rates (steps + 1, 2n), rates = (v, a(x)). work: 7 n doubles. Returns 0, or
   1 where a value is not finite (the loop stops there). */
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

/* fem_dual.integrate.simulation._estimates of S slabs of V vertices (states of m = 2n components, x then
   v; z, zc the answer's and the companion's, contiguous): local = ((zc - z) + alg) safety, plus
   lost from the second vertex on; glob = local + psi (written only where psi is given); the
   error weights' running scales (the largest |x| and |v| so far, from scale_x and scale_v; a
   part that has not moved takes the other's scale), the round-off floor, the weighted local
   error per unit of time (dt / T: per_time, or per_slab[s] where that is given) and the
   weighted global error. alg, psi and lost may be NULL. Returns 1 where a value is not finite
   or a weight is not positive (the numpy code judges those), else 0. */
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

/* fem_dual.integrate.sinks.Accumulator's summaries of S accepted slabs of V vertices (m = 2n state
   components; glob, local (S, V, m), H (S, V) and floor (S, 2) contiguous): the reported
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
"""

_SYMBOLS = ("fem_dual_rk4", "fem_dual_band", "fem_dual_dtp_newton",
            "fem_dual_slab_newton", "fem_dual_band_cholesky", "fem_dual_band_solve",
            "fem_dual_tangents", "fem_dual_hermite", "fem_dual_pack", "fem_dual_estimate",
            "fem_dual_summary")


def _declarations(source: str, names) -> str:
    """What cffi must know of the library, read off its source: the struct typedefs and the
    prototypes of the functions `names`, as written there."""
    parts = [m.group(0) for m in re.finditer(r"^typedef struct \{.*?\} \w+;", source,
                                             re.S | re.M)]
    for name in names:
        m = re.search(r"^(?:int|void) " + name + r"\(.*?\)\n\{", source, re.S | re.M)
        parts.append(m.group(0)[:-1].rstrip() + ";")
    return "\n".join(parts) + "\n"


_CDEF = _declarations(_SOURCE, _SYMBOLS)

_FLAGS = ("-O3", "-fPIC", "-shared")  # no -march=native: the same code on every machine
_loaded: Dict[str, object] = {}


def _cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "fem-dual"


def _fingerprint(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _compile(target: Path) -> None:
    """Compile the library into `target`, and its fingerprint (sha256) beside it. Both are
    written under other names, then renamed: processes that compile at once each leave whole
    files, and a library whose fingerprint does not match is not loaded (a truncated one that
    dlopen accepts kills the process with SIGBUS when a function is called)."""
    import sysconfig

    compiler = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(compiler) is None:
        compiler = shutil.which("cc") or shutil.which("gcc") or ""
        if not compiler:
            raise OSError("no C compiler (cc, gcc) on PATH")
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        source = Path(tmp) / "fem_dual_native.c"
        source.write_text(_SOURCE)
        built = Path(tmp) / target.name
        subprocess.run([compiler, *_FLAGS, "-o", str(built), str(source), "-lm"], check=True,
                       capture_output=True, timeout=120)
        stamp = Path(tmp) / "fingerprint"
        stamp.write_text(_fingerprint(built))
        os.replace(built, target)
        os.replace(stamp, _stamp(target))


def _stamp(target: Path) -> Path:
    return target.with_suffix(".sha256")


def _intact(target: Path) -> bool:
    """Whether `target` is the library its fingerprint was taken of."""
    try:
        return _stamp(target).read_text() == _fingerprint(target)
    except OSError:
        return False


def library():
    """(ffi, lib) of the compiled loops, compiled on first use and kept; None where it cannot
    be built or loaded (`reason()` says why). A library in the cache that is not the one
    compiled there (damaged, truncated, replaced) is compiled again."""
    if "lib" in _loaded:
        return _loaded["lib"]
    result = None
    try:
        import cffi

        digest = hashlib.sha256((_SOURCE + _CDEF + " ".join(_FLAGS)).encode()).hexdigest()[:16]
        target = _cache_dir() / f"native-{digest}.so"
        if not _intact(target):
            _compile(target)
        ffi = cffi.FFI()
        ffi.cdef(_CDEF)
        lib = ffi.dlopen(str(target))
        for name in _SYMBOLS:  # (AttributeError where one is missing)
            getattr(lib, name)
        result = (ffi, lib)
    except (ImportError, OSError, AttributeError, subprocess.SubprocessError) as exc:
        _loaded["reason"] = f"{type(exc).__name__}: {exc}"
    _loaded["lib"] = result
    return result


def reason() -> Optional[str]:
    """Why the compiled loops are not in use (None: they are, or were not asked for yet)."""
    return _loaded.get("reason")  # type: ignore[return-value]


def pointer(ffi, array: Optional[np.ndarray], kind: str = "double *"):
    """A C pointer to a C-contiguous array of the C type `kind` points to (NULL for None); the
    pointer keeps the array alive while it lives (a temporary array passed to a call stays
    valid through the call)."""
    if array is None:
        return ffi.NULL
    return ffi.from_buffer(kind.replace("*", "[]"), array)


class CompiledForce:
    """A scene's UFL force F(x) compiled by FFCx (a `fem.Expression` of x, a DG0 vector on a
    mesh of one cell), for the compiled loops: `kernel` is its tabulate_tensor_float64's
    address, `pack(scene)` the constants it reads, in its order, for the scene's values.

    Args:
        scene: a nonlinear scene (its forms give `force(x, c)`).

    Raises:
        ValueError: the force is a number (no expression to compile: `of` gives None).
    """

    @classmethod
    def of(cls, scene) -> Optional["CompiledForce"]:
        """The compiled force of `scene`; None for a force that is a number (F = 1)."""
        try:
            return cls(scene)
        except ValueError:
            return None

    def __init__(self, scene):
        import ufl
        from dolfinx import fem, mesh
        from mpi4py import MPI

        from fem_dual.compat import CellPointEvaluator, constant, quiet_jit_logging, vector_space

        n = scene.n
        msh = mesh.create_unit_interval(MPI.COMM_SELF, 1)
        self.x = fem.Function(vector_space(msh, 0, n, "DG"))
        self.c = {k: constant(msh, v) for k, v in scene.constants().items()}
        force = ufl.as_vector([scene.forms.force(self.x, self.c)[i] for i in range(n)])
        if force.ufl_domain() is None:  # depends on neither x nor a constant
            raise ValueError("the force is a number")
        with quiet_jit_logging():
            expr = CellPointEvaluator(force, np.zeros(1)).compiled
        self._packed = PackedExpression(expr, np.zeros(1, dtype=np.int32))
        self.kernel = self._packed.kernel
        self.n = n

    def pack(self, scene) -> np.ndarray:
        """The kernel's constants for `scene`'s parameter values."""
        for key, value in scene.constants().items():
            self.c[key].value = value
        return self._packed.constants()


class PackedExpression:
    """A compiled `fem.Expression` with its coefficients packed as DOLFINx packs them for its
    kernel (a row per cell: each coefficient's cell values, dof by dof and component by
    component, in the kernel's order), for the compiled loops that call the kernel themselves.
    Elements on an interval need no dof transformation (Lagrange, DG, Quadrature).

    Args:
        expr: the expression (0.5.2's fem.Expression).
        cells: the cells (int32) whose rows are packed.
    """

    def __init__(self, expr, cells: np.ndarray):
        import cffi
        import ufl
        from dolfinx import cpp

        ufcx = expr.ufcx_expression
        original = ufl.algorithms.extract_coefficients(expr.ufl_expression)
        self.coefficients = [original[ufcx.original_coefficient_positions[i]]
                             for i in range(ufcx.num_coefficients)]
        self.cells = np.asarray(cells, dtype=np.int32)
        columns, self._slots = [], {}
        offset = 0
        for f in self.coefficients:
            V = f.function_space
            bs = V.dofmap.index_map_bs
            dofs = V.dofmap.list.array.reshape(len(V.dofmap.list.offsets) - 1, -1)[self.cells]
            index = (dofs[:, :, None] * bs + np.arange(bs)).reshape(len(self.cells), -1)
            columns.append((f, f.x.array, index))  # (a view of f's vector: stays valid)
            self._slots[id(f)] = offset + np.arange(index.shape[1])
            offset += index.shape[1]
        self._columns = columns
        self.packed = np.zeros((len(self.cells), max(offset, 1)))
        self._compiled = self._compiled_pack()
        msh = expr.ufl_expression.ufl_domain().ufl_cargo()
        geometry = msh.geometry.dofmap.array.reshape(-1, 2)[self.cells]
        self.coords = np.ascontiguousarray(msh.geometry.x[geometry].reshape(len(self.cells), 6))
        self._constants = lambda: cpp.fem.pack_constants(expr._cpp_object)
        self.kernel = int(cffi.FFI().cast("uintptr_t", ufcx.tabulate_tensor_float64))

    def _compiled_pack(self) -> Optional[tuple]:
        """(the `pack` function, its arguments) of the compiled gather where the library is
        available (the coefficients' value arrays are views of their vectors: they stay
        valid), else None."""
        built = library()
        if built is None or not self._columns:
            return None
        ffi, lib = built
        kept = [np.ascontiguousarray(index, dtype=np.int64) for _, _, index in self._columns]
        views = [ffi.from_buffer("double[]", values) for _, values, _ in self._columns]
        views += [ffi.from_buffer("int64_t[]", index) for index in kept]
        address = (lambda view: int(ffi.cast("uintptr_t", view)))
        count = len(kept)
        width = np.array([index.shape[1] for index in kept], dtype=np.int64)
        offset = np.concatenate([[0], np.cumsum(width)[:-1]]).astype(np.int64)
        values = ffi.new("uintptr_t[]", [address(v) for v in views[:count]])
        index = ffi.new("uintptr_t[]", [address(v) for v in views[count:]])
        args = (len(self.cells), count, self.packed.shape[1], pointer(ffi, width, "int64_t *"),
                pointer(ffi, offset, "int64_t *"), values, index, pointer(ffi, self.packed))
        self._keep_alive = (kept, views, width, offset)
        return lib.fem_dual_pack, args

    def pack(self) -> np.ndarray:
        """The rows of the coefficients' current values."""
        if self._compiled is not None:
            self._compiled[0](*self._compiled[1])
            return self.packed
        start = 0
        for _, values, index in self._columns:
            self.packed[:, start:start + index.shape[1]] = values[index]
            start += index.shape[1]
        return self.packed

    def index(self, f) -> np.ndarray:
        """(cells, columns): where in `f.x.array` each of its columns of a row is packed from."""
        return next(index for g, _, index in self._columns if g is f)

    def slot(self, f) -> np.ndarray:
        """The columns of a row that hold the coefficient `f`'s cell values."""
        return self._slots[id(f)]

    def constants(self) -> np.ndarray:
        """The kernel's constants at their current values."""
        return np.ascontiguousarray(self._constants(), dtype=np.float64)
