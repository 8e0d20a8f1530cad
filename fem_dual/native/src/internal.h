/* What the sources share beyond the library's interface (fem_dual_native.h): the signature of an
   FFCx kernel (ufcx.h's tabulate_tensor_float64, for a cell without permutations) and helpers
   of the slab's Newton that live with their concept. Not read by cffi. */
#ifndef FEM_DUAL_INTERNAL_H
#define FEM_DUAL_INTERNAL_H

#include "fem_dual_native.h"

/* The helpers below are the library's own, not part of its interface. */
#if defined(__GNUC__)
#define FEM_DUAL_HIDDEN __attribute__((visibility("hidden")))
#else
#define FEM_DUAL_HIDDEN
#endif

typedef void (*kernel_t)(double *, const double *, const double *, const double *,
                         const int *, const uint8_t *);

/* pack.c */
FEM_DUAL_HIDDEN void fem_dual_put_state(int cells, int wsize, int nw, double *packed,
                                        const int64_t *wslot, const int64_t *wfree,
                                        const double *x);

/* dtp.c */
FEM_DUAL_HIDDEN int fem_dual_dtp_solve(fem_dual_dtp *D, int cells, const double *x,
                                       double *packed, int wsize);

#endif
