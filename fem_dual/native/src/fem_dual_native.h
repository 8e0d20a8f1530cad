/* The compiled loops of fem_dual.native: what Python calls (through cffi) and what the sources
   share. cffi reads this file with its preprocessor lines removed
   (fem_dual.native.build.declarations), so below the include guard it holds plain
   declarations only: no macros, no further includes. Each function is described where it is
   defined. Arrays are C-contiguous (row-major) unless said otherwise; int64_t arrays are
   indices, uintptr_t values addresses (an FFCx kernel's tabulate_tensor_float64, arrays). */
#ifndef FEM_DUAL_NATIVE_H
#define FEM_DUAL_NATIVE_H

#include <stdint.h>

/* An implicit DtP map (fem_dual.slab.pointwise_dtp.PointwiseDtP) solved inside each evaluation
   of fem_dual_slab_newton: the dual state's values into its packed rows (wslot, wfree), its
   Newton (fem_dual_dtp_newton) from the last root X, the branch test and G_x^-1 into Ginv, then
   X's and Ginv's values into the density's rows (both_*: nx and ng columns a row, from
   X[both_xindex], Ginv[...]). */
typedef struct {
    uintptr_t kernel;
    int points, n, wsize, nw, max_it, nx, ng, iterations;
    double last_step, branch_tol;
    double *packed, *out, *step, *X, *Ginv, *work;
    const double *c, *coords;
    const int64_t *xslot, *wslot, *wfree, *xdofs;
    const int64_t *both_xslot, *both_xindex, *both_gslot, *both_gindex;
} fem_dual_dtp;

/* rk4.c */
int fem_dual_rk4(uintptr_t kernel, const double *c, int n, int steps, double h, double scale,
                 const double *minv, const double *z0, double *states, double *rates,
                 double *work);
void fem_dual_hermite(int m, int n2, int steps, double h, const int64_t *rows, const double *w,
                      const double *states, const double *rates, double *out);

/* band.c */
void fem_dual_band(int cells, int nq, int ncols, const double *out, int npairs,
                   const int64_t *cols, const double *scale, int ngroups, const int64_t *lo,
                   const int64_t *hi, const int64_t *start, const double *PT, int nd2,
                   int64_t entries, const int64_t *flat, const int64_t *source, double *B,
                   double *band, int64_t band_size);

/* cholesky.c */
int fem_dual_band_cholesky(int n, int kd, double *ab, int ldab, double *row);
void fem_dual_band_solve(int n, int kd, const double *ab, int ldab, int nrhs, double *b);

/* dtp.c */
int fem_dual_dtp_newton(uintptr_t kernel, int cells, int points, int n, int wsize,
                        double *packed, const int64_t *xslot, const double *c,
                        const double *coords, int max_it, double last_step, double *out,
                        double *step, double *X, const int64_t *xdofs, double *work,
                        int *iterations);

/* newton.c */
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
                         double kept_step, int *final_factored);

/* tangents.c */
void fem_dual_tangents(int cells, int nq, int nd, int bs, int n, int k1, const double *T,
                       const double *Tg, const double *out, int ncols, int npairs,
                       const int64_t *cols, const int64_t *pk, const int64_t *pl,
                       const double *dw, const int64_t *rows, const double *sign,
                       const double *minv, double *dm, double *work);

/* estimate.c */
int fem_dual_estimate(int S, int V, int n, const double *z, const double *zc,
                      const double *alg, const double *psi, const double *lost,
                      double safety, double roundoff, double atol, double rtol,
                      double scale_x, double scale_v, double per_time,
                      const double *per_slab, double *local, double *glob, double *scales,
                      double *floor, double *err_local, double *err_global);
int fem_dual_summary(int S, int V, int n, int first, const double *glob,
                     const double *local, const double *floor, const double *H, double tiny,
                     double *rows, double *peak, double *final, double *glob_peak,
                     double *local_peak, double *low, double *high, double *drift);

/* pack.c */
void fem_dual_pack(int cells, int ncoef, int wsize, const int64_t *width,
                   const int64_t *offset, const uintptr_t *values, const uintptr_t *index,
                   double *packed);

#endif
