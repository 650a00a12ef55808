/* cochlea: sin and cos of one angle at once, inline (cochlea_sincos).
 * Source: codegen/cochlea_trig.h; cochlea-codegen copies it beside the kernels that use it
 * (generated_c/cochlea_trig.h, or a user's --out folder): edit the source, then regenerate.
 *
 * Where it is used: the ideal plants' RK4 steps in generated_c/ (<unit>_plant_step[_coulomb],
 * <unit>_armature_plant_step[_coulomb]: cochlea-codegen takes each sin(a) and cos(a) of one
 * value of a from one cochlea_sincos at the first of them, cochlea/kernels/trig.py), and the
 * all-in-C simulation's specialised plants and controller (embedded/sim/sim_trig.h: sim_sincos
 * is this function). libm's sincos and its call were a quarter of a sweep worker's CPU time;
 * inline, the compiler keeps the work in registers and interleaves it with the plant's.
 * It is not libm: a result may differ from libm's by an ulp, so an ideal study's log differs
 * from what the same code gave on libm by rounding (docs/codegen.md gives the measured
 * difference). The geared plant (<unit>_gear_plant_step, whose backlash grows an ulp to
 * 1e-2 rad over a study), the controllers and the model, pose and Jacobian kernels keep
 * libm: the realistic studies are bit for bit what they were.
 *
 * Method (x in rad):
 *  1. n = x 2/pi rounded to the nearest integer and r = x - n pi/2, with pi/2 as
 *     P1 + P2 + P3: P1 and P2 hold 33 bits each, so n P1 and n P2 are exact for |n| < 2^20;
 *     x - n P1 is exact (Sterbenz); the subtraction of n P2 keeps its rounding error (Knuth's
 *     two-sum), n P3 is the rest. r = r0 + r1, a double and its tail, |r| <= pi/4 (a hair
 *     over), to about 2^-119 relative even where x is the double nearest a multiple of pi/2.
 *  2. sin r and cos r from their Taylor series to r^17 and r^18: on |r| <= pi/4 the first
 *     term left out is below 1.1e-19 of the result; the tail r1 enters to first order
 *     (sin: + r1 (1 - r^2/2), cos: - r1 r); 1 - r^2/2 is formed with its rounding error
 *     (Dekker), so the last addition is the only rounding of size: < 1 ulp.
 *  3. The quadrant n mod 4 picks +-sin r or +-cos r.
 * Outside |x| < 2^19 (n P1 no longer exact), and for NaN and infinities, libm's sin and cos.
 * cochlea_sin and cochlea_cos are cochlea_sincos's halves.
 * Measured against a 50-digit reference (tests/test_embedded_sim.py, tests/test_codegen_trig.py):
 * at most 1 ulp.
 *
 * Rounding: round to nearest, and no contraction of a * b + c into a fused multiply-add. The
 * exactness of steps 1 and 2 does not depend on it (every product the two-sum and Dekker's step
 * use, n P1, n P2, z/2, is exact, so a fused form rounds the same), but a contracted polynomial
 * rounds differently, and one build should give the results of another. So:
 *  - C99's own pragma below turns contraction off in this function for every compiler that
 *    implements it (clang, and so zig cc, whose default -ffp-contract=on contracts within an
 *    expression; -ffp-contract=fast ignores pragmas);
 *  - GCC does not implement it (it warns: not given to GCC) and contracts only with
 *    -ffp-contract=fast, its default in the GNU modes (-std=gnu99) where the target has an FMA:
 *    cochlea builds with -std=c99, where GCC's default is off. A GNU-mode build for an FMA
 *    target still gets results within 1 ulp (tests/test_codegen_trig.py builds it so), not
 *    always the same last bit. */
#ifndef COCHLEA_TRIG_H
#define COCHLEA_TRIG_H

#include <math.h>

/* Inline wherever it is called, so that the compiler interleaves it with the plant's other
 * work (GCC otherwise splits it and calls the larger part) */
#ifdef __GNUC__
#define COCHLEA_TRIG_INLINE static inline __attribute__((always_inline))
#else
#define COCHLEA_TRIG_INLINE static inline
#endif

COCHLEA_TRIG_INLINE void cochlea_sincos(double x, double *sin_x, double *cos_x)
{
#if !defined(__GNUC__) || defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#endif
    /* pi/2 = P1 + P2 + P3 + 1e-37 (P1, P2: 33 bits each) */
    const double P1 = 0x1.921fb544p+0, P2 = 0x1.0b4611a6p-34, P3 = 0x1.3198a2e037073p-69;
    const double TWO_OVER_PI = 0x1.45f306dc9c883p-1;
    const double ROUND = 0x1.8p52; /* adding and subtracting it rounds to an integer */
    const int reduced = fabs(x) < 0x1p19; /* 0 also for NaN */
    double n, a, b, r0, e, r1, z, z2, z4, s, c, hz, w, sin_r, cos_r;
    int quadrant;
    /* Computed for every x, then replaced by libm's where x is out of range: straight-line
     * code, so that a sin and a cos of one angle inlined apart compute it once (the compiler
     * finds the second copy's work done by the first). */
    n = (x * TWO_OVER_PI + ROUND) - ROUND;
    a = x - n * P1;               /* exact */
    b = n * P2;                   /* exact */
    r0 = a - b;                   /* two-sum: r0 + e == a - b */
    {
        const double bb = r0 - a, aa = r0 - bb;
        e = (a - aa) + (-b - bb);
    }
    r1 = e - n * P3;              /* the tail, off the critical path: it enters to first order */
    z = r0 * r0;
    z2 = z * z;
    z4 = z2 * z2;
    /* sin r0 = r0 + r0 z (-1/3! + z (1/5! - ...)), to r0^17 (Estrin's scheme: short chains) */
    s = ((-0.16666666666666666 + z * 0.008333333333333333)
         + z2 * (-0.0001984126984126984 + z * 2.7557319223985893e-06))
        + z4 * ((-2.505210838544172e-08 + z * 1.6059043836821613e-10)
                + z2 * (-7.647163731819816e-13 + z * 2.8114572543455206e-15));
    s = r0 + ((r0 * z) * s + r1 * (1.0 - 0.5 * z));
    /* cos r0 = 1 - z/2 + z^2 (1/4! - z (1/6! - ...)), to r0^18 */
    c = ((0.041666666666666664 + z * -0.001388888888888889)
         + z2 * (2.48015873015873e-05 + z * -2.755731922398589e-07))
        + z4 * ((2.08767569878681e-09 + z * -1.1470745597729725e-11)
                + z2 * (4.779477332387385e-14 + z * -1.5619206968586225e-16));
    hz = 0.5 * z;
    w = 1.0 - hz;
    c = w + (((1.0 - w) - hz) + (z2 * c - r0 * r1));
    /* the quadrant: sin x = s, c, -s, -c and cos x = c, -s, -c, s */
    quadrant = (int)(reduced ? n : 0.0) & 3;
    sin_r = quadrant & 1 ? c : s;
    cos_r = quadrant & 1 ? s : c;
    *sin_x = quadrant & 2 ? -sin_r : sin_r;
    *cos_x = (quadrant + 1) & 2 ? -cos_r : cos_r;
    if (!reduced) {
        *sin_x = sin(x);
        *cos_x = cos(x);
    }
}

COCHLEA_TRIG_INLINE double cochlea_sin(double x)
{
    double s, c;
    cochlea_sincos(x, &s, &c);
    return s;
}

COCHLEA_TRIG_INLINE double cochlea_cos(double x)
{
    double s, c;
    cochlea_sincos(x, &s, &c);
    return c;
}

#endif
