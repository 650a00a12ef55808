/* cochlea embedded runtime: the floating-point rules every core file (and the generated
 * controller) relies on, and a finiteness test no optimisation can remove.
 *
 * Included by cochlea_rt.h and drives.h, so every .c file of embedded/core that computes in
 * floating point sees it (dxl.c, the codec, has no floating point and stays standalone).
 * Portable C99: <stdint.h> only.
 */
#ifndef COCHLEA_FP_H
#define COCHLEA_FP_H

#include <stdint.h>

/* The supervisor refuses a NaN or infinite state, command or estimate. Under -ffast-math
 * (GCC, Clang: __FAST_MATH__) or -ffinite-math-only (__FINITE_MATH_ONLY__ nonzero) the
 * compiler may assume no value is ever NaN or infinite and delete those checks: a NaN command
 * would then reach the motors. Such a build is refused here rather than shipped. */
#if defined(__FAST_MATH__)
#error "cochlea: do not build with -ffast-math: it lets the compiler delete the supervisor's NaN and infinity checks (a NaN command would reach the motors); build without it (-O2 is enough)"
#elif defined(__FINITE_MATH_ONLY__) && __FINITE_MATH_ONLY__
#error "cochlea: do not build with -ffinite-math-only: it lets the compiler delete the supervisor's NaN and infinity checks (a NaN command would reach the motors); build without it"
#endif

/* 1 if x is neither NaN nor infinite, decided on its IEEE 754 bits (exponent not all ones),
 * so that no floating-point assumption of the compiler can fold the test away. The union is
 * C99's way to read an object's bytes as another type (6.5.2.3, footnote 82). */
static inline int cochlea_finite(double x)
{
    union {
        double d;
        uint64_t u;
    } bits;
    bits.d = x;
    return (bits.u & 0x7FF0000000000000ULL) != 0x7FF0000000000000ULL;
}

#endif /* COCHLEA_FP_H */
