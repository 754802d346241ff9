#include "mh_kinematics.h"

static float mh_fabs(float x)
{
    return x < 0.0f ? -x : x;
}

bool mh_is_finite(float x)
{
    union {
        float f;
        uint32_t u;
    } b;
    b.f = x;
    /* an exponent of all ones is an infinity or a NaN */
    return (b.u & 0x7F800000u) != 0x7F800000u;
}

float mh_wheel_peak(float n_rpm, float omega_dps, float k)
{
    return mh_fabs(n_rpm) + k * mh_fabs(omega_dps) / 6.0f;
}

mh_cmd_check mh_check_command(float n_rpm, float omega_dps, float theta_deg, float k,
                              float wheel_limit_rpm)
{
    float peak;
    if (!mh_is_finite(n_rpm)) {
        return MH_CMD_N_NOT_FINITE;
    }
    if (!mh_is_finite(omega_dps)) {
        return MH_CMD_OMEGA_NOT_FINITE;
    }
    if (!mh_is_finite(theta_deg)) {
        return MH_CMD_THETA_NOT_FINITE;
    }
    if (mh_fabs(theta_deg) > MH_THETA_LIMIT_DEG) {
        return MH_CMD_THETA_RANGE;
    }
    peak = mh_wheel_peak(n_rpm, omega_dps, k);
    /* "not <=" so that an overflow to infinity is refused too */
    if (!(peak <= wheel_limit_rpm + wheel_limit_rpm * MH_LIMIT_SLACK)) {
        return MH_CMD_BEYOND_LIMIT;
    }
    return MH_CMD_OK;
}

const char *mh_cmd_check_text(mh_cmd_check why)
{
    switch (why) {
    case MH_CMD_N_NOT_FINITE:
        return "n not finite";
    case MH_CMD_OMEGA_NOT_FINITE:
        return "omega not finite";
    case MH_CMD_THETA_NOT_FINITE:
        return "theta not finite";
    case MH_CMD_THETA_RANGE:
        return "theta out of range";
    case MH_CMD_BEYOND_LIMIT:
        return "wheel target beyond the limit";
    case MH_CMD_OK:
    default:
        return "";
    }
}

#define MH_DEG_TO_RAD 0.017453292519943295f

void mh_sincos_deg(float deg, float *s, float *c)
{
    float x = deg;
    float r;
    float r2;
    float sr;
    float cr;
    int q = 0;
    int i;
    /* to [-180, 180]: at most two turns for a validated theta (exact: Sterbenz) */
    for (i = 0; i < 2 && x > 180.0f; i++) {
        x -= 360.0f;
    }
    for (i = 0; i < 2 && x < -180.0f; i++) {
        x += 360.0f;
    }
    /* to [-45, 45] and the quarter turn q it lies in */
    if (x > 135.0f) {
        q = 2;
    } else if (x > 45.0f) {
        q = 1;
    } else if (x < -135.0f) {
        q = -2;
    } else if (x < -45.0f) {
        q = -1;
    }
    r = (x - 90.0f * (float)q) * MH_DEG_TO_RAD;
    r2 = r * r;
    /* Taylor series to r^9 and r^10: below 2e-9 on |r| <= pi/4 */
    sr = r * (1.0f - r2 / 6.0f * (1.0f - r2 / 20.0f * (1.0f - r2 / 42.0f
                                                       * (1.0f - r2 / 72.0f))));
    cr = 1.0f - r2 / 2.0f * (1.0f - r2 / 12.0f * (1.0f - r2 / 30.0f
                                                  * (1.0f - r2 / 56.0f * (1.0f - r2 / 90.0f))));
    switch (q) {
    case 1:
        *s = cr;
        *c = -sr;
        break;
    case -1:
        *s = -cr;
        *c = sr;
        break;
    case 2:
    case -2:
        *s = -sr;
        *c = -cr;
        break;
    default:
        *s = sr;
        *c = cr;
        break;
    }
}

void mh_command_to_wheels(float n_rpm, float omega_dps, float theta_deg, float k, float w[4])
{
    float s;
    float c;
    float v;
    float vx;
    float vy;
    float kwz;
    mh_sincos_deg(theta_deg, &s, &c);
    v = n_rpm / (mh_fabs(s) + mh_fabs(c));
    vx = v * s;
    vy = -v * c;
    kwz = k * omega_dps / 6.0f;
    w[0] = vx - vy - kwz;
    w[1] = vx + vy + kwz;
    w[2] = vx + vy - kwz;
    w[3] = vx - vy + kwz;
}
