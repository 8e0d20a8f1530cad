/* What cffi's modules include first (cffi/_cffi_include.h, where it uses the limited API),
   precompiled for FFCx's compilations by fem_dual.jit_header. */
#include <pyconfig.h>
#if !defined(Py_DEBUG) && !defined(Py_TRACE_REFS) && !defined(Py_REF_DEBUG)
#  define Py_LIMITED_API
#endif
#include <Python.h>
