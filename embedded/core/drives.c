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
