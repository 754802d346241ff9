/* The smallest board that links the core for a size measurement (make arm-size): every seam
 * function is a stub, the main loop feeds and polls. Not a port: boards/arduino is one. */
#include "mh_core.h"

static volatile uint32_t fake_clock;
static volatile uint8_t fake_rx;

static uint32_t stub_now_us(void *ctx)
{
    (void)ctx;
    return fake_clock;
}

static size_t stub_write(void *ctx, const uint8_t *data, size_t len)
{
    (void)ctx;
    (void)data;
    return len;
}

static void stub_read_wheels(void *ctx, float rpm[4])
{
    int i;
    (void)ctx;
    for (i = 0; i < 4; i++) {
        rpm[i] = (float)fake_clock;
    }
}

static void stub_set_targets(void *ctx, const float rpm[4])
{
    (void)ctx;
    fake_clock = (uint32_t)rpm[0];
}

static mh_core core;

void arm_board_main(void);

void arm_board_main(void)
{
    static const mh_board board = {0, stub_now_us, stub_write, stub_read_wheels,
                                   stub_set_targets, 0, 0};
    static const mh_config cfg = {100, 130.0f, 4.5588236f, "mecanum-hil-c99"};
    mh_init(&core, &board, &cfg);
    for (;;) {
        uint8_t b = fake_rx;
        mh_feed(&core, &b, 1);
        mh_poll(&core);
    }
}
