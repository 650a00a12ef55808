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

/* The working precision of everything a period computes: the loop's q, qd, tau, errors and
 * row, the supervisor's checks, the drives' per-period conversions, the scenario's interface.
 * float with COCHLEA_FLOAT (a single-precision FPU: a Cortex-M4F has no double instruction,
 * so a double there is a library routine), double otherwise. Configuration, start-up and the
 * run's report stay double (outside the period). The generated <name>_real is the same type. */
#ifdef COCHLEA_FLOAT
typedef float cochlea_real;
/* A literal in the working precision (COCHLEA_R(1.0) is 1.0f in float). */
#define COCHLEA_R(x) x##f
#else
typedef double cochlea_real;
#define COCHLEA_R(x) x
#endif

/* cochlea_finite in the working precision: on the float's own bits in the float build (a
 * float converted to double would be a library call on a Cortex-M4F). */
static inline int cochlea_finite_real(cochlea_real x)
{
#ifdef COCHLEA_FLOAT
    union {
        float f;
        uint32_t u;
    } bits;
    bits.f = x;
    return (bits.u & 0x7F800000UL) != 0x7F800000UL;
#else
    return cochlea_finite(x);
#endif
}

#endif /* COCHLEA_FP_H */
