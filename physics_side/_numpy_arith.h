/* What makes the physics side's C fast paths bit-identical to their numpy bodies (included by
 * _pathkernel.c, _worldkernel.c, _controlkernel.c and policies/_*kernel.c; change it here, once).
 *
 * - Each product rounded on its own, as numpy does: no fused multiply-add (compilers
 *   contract by default on FMA hardware, e.g. every arm64).
 * - No x87 extended-precision intermediates: such a build stops here (the extensions are
 *   optional, the numpy bodies then run).
 * - numpy's maximum / minimum on float64: a NaN in either argument is the result, and of two
 *   equal values the second (as the SIMD instructions it uses: maximum(-0.0, 0.0) is 0.0,
 *   maximum(0.0, -0.0) is -0.0); a reduction along an axis is the same, row after row.
 * - protocol.frames.wrap_pi with its constants' exact bits.
 */
#ifndef SUMOCO_NUMPY_ARITH_H
#define SUMOCO_NUMPY_ARITH_H

#include <float.h>
#include <math.h>

#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#elif defined(_MSC_VER)
#pragma fp_contract(off)
#endif

#if defined(FLT_EVAL_METHOD) && FLT_EVAL_METHOD != 0 && FLT_EVAL_METHOD != -1
#error "the physics kernels need double evaluation (FLT_EVAL_METHOD 0)"
#endif

static inline double np_max(double a, double b) { return (a > b || a != a) ? a : b; }
static inline double np_min(double a, double b) { return (a < b || a != a) ? a : b; }

/* protocol.frames.wrap_pi: a - _TWO_PI * ceil((a - np.pi) * _INV_TWO_PI), _TWO_PI = 2 * np.pi,
 * _INV_TWO_PI = 1 / _TWO_PI */
static inline double wrap_pi(double a) {
    const double pi = 0x1.921fb54442d18p+1, two_pi = 0x1.921fb54442d18p+2, inv_two_pi = 0x1.45f306dc9c883p-3;
    return a - two_pi * ceil((a - pi) * inv_two_pi);
}

#endif
