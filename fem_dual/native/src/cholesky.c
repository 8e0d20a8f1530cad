/* The banded Cholesky factorisation in LAPACK's upper band storage and its solves
   (fem_dual.slab.banded.BandedLU). */
#include <math.h>

#include "fem_dual_native.h"

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
