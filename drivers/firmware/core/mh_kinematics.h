/* The project's Mecanum kinematics (docs/conventions.md) and the COMMAND validation of
 * drivers/protocol.md, in float arithmetic without libm. */
#ifndef MH_KINEMATICS_H
#define MH_KINEMATICS_H

#include <stdbool.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Largest |theta_deg| a COMMAND may carry (the CAN signal's range). */
#define MH_THETA_LIMIT_DEG 655.36f
/* Relative slack on the wheel speed limit, so that a command at the limit survives float32. */
#define MH_LIMIT_SLACK 1e-6f

/* Why a COMMAND is refused (MH_CMD_OK: valid). */
typedef enum {
    MH_CMD_OK = 0,
    MH_CMD_N_NOT_FINITE,
    MH_CMD_OMEGA_NOT_FINITE,
    MH_CMD_THETA_NOT_FINITE,
    MH_CMD_THETA_RANGE,
    MH_CMD_BEYOND_LIMIT
} mh_cmd_check;

bool mh_is_finite(float x);

/* The largest wheel speed target |w_i| a command needs [rpm]: |n| + k |omega| / 6.
 * The four targets are (vx -+ vy) -+ k wz with |vx| + |vy| = |n|, so the peak needs no
 * trigonometry. */
float mh_wheel_peak(float n_rpm, float omega_dps, float k);

/* The protocol's COMMAND rule, checked in the document's order. */
mh_cmd_check mh_check_command(float n_rpm, float omega_dps, float theta_deg, float k,
                              float wheel_limit_rpm);

/* ERROR 2's text for a refusal (at most 40 bytes, NUL-terminated). */
const char *mh_cmd_check_text(mh_cmd_check why);

/* sin and cos of an angle in degrees, |deg| <= 720 (a validated theta). */
void mh_sincos_deg(float deg, float *s, float *c);

/* Wheel speed targets [rpm] (1 FL, 2 FR, 3 RL, 4 RR) of a valid command. */
void mh_command_to_wheels(float n_rpm, float omega_dps, float theta_deg, float k, float w[4]);

#ifdef __cplusplus
}
#endif

#endif
