/* A board for tests: a clock the test sets, an output buffer the test reads, wheels that
 * report what the test sets (or the targets), an e-stop button the test presses. */
#ifndef MH_TEST_BOARD_H
#define MH_TEST_BOARD_H

#include "mh_core.h"

#define TB_OUT_CAP 65536u

typedef struct test_board {
    uint32_t now_us;
    uint8_t out[TB_OUT_CAP];
    size_t out_len;
    size_t write_budget; /* bytes write() takes per call; 0: all */
    float wheels[4];
    bool wheels_follow_targets;
    float targets[4];
    unsigned target_calls;
    bool estop;
    bool fault;
} test_board;

static uint32_t tb_now_us(void *ctx)
{
    return ((test_board *)ctx)->now_us;
}

static size_t tb_write(void *ctx, const uint8_t *data, size_t len)
{
    test_board *b = ctx;
    size_t i;
    if (b->write_budget > 0 && len > b->write_budget) {
        len = b->write_budget;
    }
    if (len > TB_OUT_CAP - b->out_len) {
        len = TB_OUT_CAP - b->out_len;
    }
    for (i = 0; i < len; i++) {
        b->out[b->out_len + i] = data[i];
    }
    b->out_len += len;
    return len;
}

static void tb_read_wheels(void *ctx, float rpm[4])
{
    test_board *b = ctx;
    int i;
    for (i = 0; i < 4; i++) {
        rpm[i] = b->wheels_follow_targets ? b->targets[i] : b->wheels[i];
    }
}

static void tb_set_targets(void *ctx, const float rpm[4])
{
    test_board *b = ctx;
    int i;
    for (i = 0; i < 4; i++) {
        b->targets[i] = rpm[i];
    }
    b->target_calls++;
}

static bool tb_estop(void *ctx)
{
    return ((test_board *)ctx)->estop;
}

static bool tb_fault(void *ctx)
{
    return ((test_board *)ctx)->fault;
}

static void tb_start(mh_core *core, test_board *b, uint16_t rate_hz, float limit, float k,
                     const char *name)
{
    mh_board board;
    mh_config cfg;
    board.ctx = b;
    board.now_us = tb_now_us;
    board.write = tb_write;
    board.read_wheels = tb_read_wheels;
    board.set_targets = tb_set_targets;
    board.estop_pressed = tb_estop;
    board.drive_fault = tb_fault;
    cfg.telemetry_rate_hz = rate_hz;
    cfg.wheel_limit_rpm = limit;
    cfg.k = k;
    cfg.name = name;
    mh_init(core, &board, &cfg);
}

#endif
