/* cochlea embedded runtime: joint <-> motor conversions (see drives.h). The floating-point
 * operations are the Python bridge's (cochlea/dynamixel/bridge.py), in the same order, on the
 * same constants, so both give the same values bit for bit. */
#include "drives.h"

#include <math.h>

double cochlea_drive_position(const cochlea_drive *d, int32_t counts, double position_offset)
{
    return (double)counts * d->q_per_count + position_offset;
}

double cochlea_drive_velocity(const cochlea_drive *d, int32_t velocity_lsb)
{
    return (double)velocity_lsb * d->qd_per_lsb;
}

double cochlea_drive_current(const cochlea_drive *d, int16_t present_lsb)
{
    return (double)present_lsb * d->ampere_per_lsb;
}

double cochlea_drive_unwrap(const cochlea_drive *d, double q, double position_offset)
{
    const double two_pi = 2.0 * 3.14159265358979323846;
    double turns;
    if (!d->revolute) {
        return position_offset;
    }
    /* Python's round(): half to even, as nearbyint in the default rounding mode. */
    turns = nearbyint(((d->position_lo + d->position_hi) / 2.0 - q) / two_pi);
    return position_offset + two_pi * turns;
}

int16_t cochlea_drive_goal_current(const cochlea_drive *d, double effort, int offset_current)
{
    const double torque = effort * d->torque_per_effort;
    const double limit = (double)d->current_limit_lsb;
    double blend, amps;
    if (!cochlea_finite(torque)) {
        return 0;
    }
    blend = torque * d->inv_ramp;
    blend = blend < -1.0 ? -1.0 : (blend > 1.0 ? 1.0 : blend);
    blend = offset_current ? blend * d->i0 : 0.0;
    amps = torque * d->inv_a + blend;
    amps = nearbyint(amps * d->lsb_per_ampere);
    amps = amps < -limit ? -limit : (amps > limit ? limit : amps);
    return (int16_t)amps;
}

void cochlea_drive_real_init(cochlea_drive_real *c, const cochlea_drive *d,
                             double position_offset)
{
    double mid = ((d->position_lo + d->position_hi) / 2.0 - position_offset) / d->q_per_count;
    c->drive = d;
    c->position_offset = position_offset;
    /* within +-2^30 counts (and 0 for a NaN): an int32 difference from it cannot overflow */
    mid = mid == mid ? nearbyint(mid) : 0.0;
    mid = mid < -1073741824.0 ? -1073741824.0 : (mid > 1073741824.0 ? 1073741824.0 : mid);
    c->count0 = (int32_t)mid;
    c->q0 = (cochlea_real)((double)c->count0 * d->q_per_count + position_offset);
    c->q_per_count = (cochlea_real)d->q_per_count;
    c->qd_per_lsb = (cochlea_real)d->qd_per_lsb;
    c->ampere_per_lsb = (cochlea_real)d->ampere_per_lsb;
    c->torque_per_effort = (cochlea_real)d->torque_per_effort;
    c->inv_a = (cochlea_real)d->inv_a;
    c->inv_ramp = (cochlea_real)d->inv_ramp;
    c->i0 = (cochlea_real)d->i0;
    c->lsb_per_ampere = (cochlea_real)d->lsb_per_ampere;
    c->current_limit = (cochlea_real)d->current_limit_lsb;
}

#ifdef COCHLEA_FLOAT

cochlea_real cochlea_drive_position_real(const cochlea_drive_real *c, int32_t counts)
{
    /* the difference in 64 bits, then held within +-2^24 (a float's exact integers): a
     * reading that far off is far outside the joint's limits either way */
    int64_t diff = (int64_t)counts - (int64_t)c->count0;
    diff = diff < -16777216 ? -16777216 : (diff > 16777216 ? 16777216 : diff);
    return (float)(int32_t)diff * c->q_per_count + c->q0;
}

cochlea_real cochlea_drive_velocity_real(const cochlea_drive_real *c, int32_t velocity_lsb)
{
    return (float)velocity_lsb * c->qd_per_lsb;
}

cochlea_real cochlea_drive_current_real(const cochlea_drive_real *c, int16_t present_lsb)
{
    return (float)present_lsb * c->ampere_per_lsb;
}

int16_t cochlea_drive_goal_current_real(const cochlea_drive_real *c, cochlea_real effort,
                                        int offset_current)
{
    const float torque = effort * c->torque_per_effort;
    const float limit = c->current_limit;
    float blend, amps;
    if (!cochlea_finite_real(torque)) {
        return 0;
    }
    blend = torque * c->inv_ramp;
    blend = blend < -1.0f ? -1.0f : (blend > 1.0f ? 1.0f : blend);
    blend = offset_current ? blend * c->i0 : 0.0f;
    amps = (torque * c->inv_a + blend) * c->lsb_per_ampere;
    /* the clip first (the limit is an integer, so it commutes with the rounding), then half
     * to even: |amps| <= 32767 < 2^22, and 1.5 2^23 + amps lies where the float's spacing
     * is 1, so the addition rounds it to an integer in the FPU's mode (to nearest, even) */
    amps = amps < -limit ? -limit : (amps > limit ? limit : amps);
    amps = (amps + 12582912.0f) - 12582912.0f;
    return (int16_t)(int32_t)amps;
}

#else

cochlea_real cochlea_drive_position_real(const cochlea_drive_real *c, int32_t counts)
{
    return cochlea_drive_position(c->drive, counts, c->position_offset);
}

cochlea_real cochlea_drive_velocity_real(const cochlea_drive_real *c, int32_t velocity_lsb)
{
    return cochlea_drive_velocity(c->drive, velocity_lsb);
}

cochlea_real cochlea_drive_current_real(const cochlea_drive_real *c, int16_t present_lsb)
{
    return cochlea_drive_current(c->drive, present_lsb);
}

int16_t cochlea_drive_goal_current_real(const cochlea_drive_real *c, cochlea_real effort,
                                        int offset_current)
{
    return cochlea_drive_goal_current(c->drive, effort, offset_current);
}

#endif
