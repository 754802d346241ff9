/* The core on a test board, as a shared library for Python (ctypes): one controller per
 * process, a clock the caller sets, the output read back by the caller. */
#include <string.h>

#include "mh_core.h"
#include "test_board.h"

static mh_core core;
static test_board tb;

void h_start(uint16_t rate_hz, float limit, float k, int estop_pressed)
{
    memset(&tb, 0, sizeof tb);
    tb.wheels_follow_targets = true;
    tb.estop = estop_pressed != 0;
    tb_start(&core, &tb, rate_hz, limit, k, "harness");
}

void h_set_time(uint32_t now_us)
{
    tb.now_us = now_us;
}

void h_set_estop(int pressed)
{
    tb.estop = pressed != 0;
}

void h_feed(const uint8_t *data, size_t len)
{
    mh_feed(&core, data, len);
}

void h_poll(void)
{
    mh_poll(&core);
}

/* What the core wrote since the last call (at most cap bytes); clears it. */
size_t h_take(uint8_t *out, size_t cap)
{
    size_t n = tb.out_len < cap ? tb.out_len : cap;
    memcpy(out, tb.out, n);
    memmove(tb.out, tb.out + n, tb.out_len - n);
    tb.out_len -= n;
    return n;
}

void h_targets(float out[4])
{
    memcpy(out, tb.targets, sizeof tb.targets);
}

uint16_t h_status(void)
{
    return mh_status(&core);
}

uint16_t h_ack_seq(void)
{
    return core.ack_seq;
}

/* The counters in mh_counters' order. */
void h_counters(uint32_t out[12])
{
    memcpy(out, &core.counters, sizeof core.counters);
}

int h_check_command(float n, float omega, float theta, float k, float limit)
{
    return (int)mh_check_command(n, omega, theta, k, limit);
}

void h_command_to_wheels(float n, float omega, float theta, float k, float out[4])
{
    mh_command_to_wheels(n, omega, theta, k, out);
}
