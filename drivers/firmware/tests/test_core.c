/* Unit tests of the core: the worked examples of drivers/protocol.md byte for byte, the
 * kinematics checks of docs/conventions.md, the limit check, and the controller's duties on
 * a test board with a clock the test sets. Exit 0 when every check passes. */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "mh_core.h"
#include "test_board.h"

static int failures = 0;
static int checks = 0;

#define CHECK(cond)                                                                       \
    do {                                                                                  \
        checks++;                                                                         \
        if (!(cond)) {                                                                    \
            failures++;                                                                   \
            fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond);     \
        }                                                                                 \
    } while (0)

/* "02 01 00" -> bytes; returns the count. */
static size_t hex(const char *text, uint8_t *out)
{
    size_t n = 0;
    unsigned v;
    int used;
    while (sscanf(text, " %2x%n", &v, &used) == 1) {
        out[n++] = (uint8_t)v;
        text += used;
    }
    return n;
}

static bool same(const uint8_t *a, size_t na, const char *expected_hex)
{
    uint8_t e[256];
    size_t ne = hex(expected_hex, e);
    size_t i;
    if (na != ne || memcmp(a, e, ne) != 0) {
        fprintf(stderr, "  got:      ");
        for (i = 0; i < na; i++) {
            fprintf(stderr, "%02x ", a[i]);
        }
        fprintf(stderr, "\n  expected: %s\n", expected_hex);
        return false;
    }
    return true;
}

/* ---- the worked examples ------------------------------------------------------------------ */

typedef struct example {
    const char *raw;
    const char *wire;
} example;

/* drivers/protocol.md, "Worked examples" (serial) */
static const example EXAMPLES[] = {
    {"02 01 00 00 98 5e", "00 03 02 01 01 03 98 5e 00"},
    {"02 81 00 00 64 00 fa 00 00 00 02 43 73 69 6d 3e 57",
     "00 03 02 81 01 02 64 02 fa 01 01 08 02 43 73 69 6d 3e 57 00"},
    {"02 02 01 00 00 00 70 42 00 00 00 00 00 00 b4 42 ab e0",
     "00 04 02 02 01 01 01 03 70 42 01 01 01 01 01 05 b4 42 ab e0 00"},
    {"02 82 02 00 20 4e 00 00 00 00 48 41 00 00 48 41 00 00 48 41 00 00 48 41 00 00 01 00 0c 5c",
     "00 04 02 82 02 03 20 4e 01 01 01 03 48 41 01 03 48 41 01 03 48 41 01 03 48 41 01 02 01 03 "
     "0c 5c 00"},
    {"02 03 02 00 9a 56", "00 04 02 03 02 03 9a 56 00"},
    {"02 04 03 00 3b e0", "00 04 02 04 03 03 3b e0 00"},
    {"02 05 04 00 07 00 00 00 b3 90", "00 04 02 05 04 02 07 01 01 03 b3 90 00"},
    {"02 06 05 00 fd 24", "00 04 02 06 05 03 fd 24 00"},
    {"02 85 03 00 07 00 00 00 0b f3", "00 04 02 85 03 02 07 01 01 03 0b f3 00"},
    {"02 8f 04 00 02 6e 20 6e 6f 74 20 66 69 6e 69 74 65 8b 29",
     "00 04 02 8f 04 10 02 6e 20 6e 6f 74 20 66 69 6e 69 74 65 8b 29 00"},
};

static void test_crc(void)
{
    const uint8_t check[] = "123456789";
    CHECK(mh_crc16(check, 9, 0xFFFFu) == 0x29B1u);
    CHECK(mh_crc16(check, 0, 0xFFFFu) == 0xFFFFu);
}

static void test_examples(void)
{
    size_t i;
    for (i = 0; i < sizeof EXAMPLES / sizeof EXAMPLES[0]; i++) {
        uint8_t raw[64];
        uint8_t wire[MH_MAX_WIRE];
        uint8_t back[MH_MAX_ENCODED];
        size_t nraw = hex(EXAMPLES[i].raw, raw);
        size_t nback = 0;
        size_t n;
        /* the CRC at the end of raw is the CRC of what comes before it */
        CHECK(mh_crc16(raw, nraw - 2, 0xFFFFu) == mh_get_u16(raw + nraw - 2));
        /* header and body framed give the wire bytes */
        n = mh_frame_encode(raw[0], raw[1], mh_get_u16(raw + 2), raw + 4, nraw - 6, wire);
        CHECK(same(wire, n, EXAMPLES[i].wire));
        /* and the wire bytes decode back to raw */
        CHECK(mh_cobs_decode(wire + 1, n - 2, back, sizeof back, &nback));
        CHECK(same(back, nback, EXAMPLES[i].raw));
    }
}

static void test_cobs_edges(void)
{
    uint8_t in[300];
    uint8_t enc[310];
    uint8_t dec[300];
    size_t n;
    size_t m = 0;
    size_t i;
    /* a 254-byte run without zeros: code 0xFF, then the trailing 01 */
    for (i = 0; i < 254; i++) {
        in[i] = (uint8_t)(i % 255 + 1);
    }
    n = mh_cobs_encode(in, 254, enc);
    CHECK(n == 256 && enc[0] == 0xFF && enc[255] == 0x01);
    CHECK(mh_cobs_decode(enc, n, dec, sizeof dec, &m) && m == 254 && memcmp(dec, in, m) == 0);
    /* not COBS: a code byte of 0, a code past the end, more than the buffer holds */
    enc[0] = 0x00;
    CHECK(!mh_cobs_decode(enc, 3, dec, sizeof dec, &m));
    enc[0] = 0x05;
    CHECK(!mh_cobs_decode(enc, 3, dec, sizeof dec, &m));
    CHECK(!mh_cobs_decode((const uint8_t *)"\x03\x01\x01\x03\x01\x01", 6, dec, 4, &m));
    /* one zero byte is 01 01 */
    in[0] = 0;
    n = mh_cobs_encode(in, 1, enc);
    CHECK(n == 2 && enc[0] == 1 && enc[1] == 1);
}

/* ---- kinematics and the limit check --------------------------------------------------------- */

static const float K = 0.465f / 0.102f;

static bool near4(const float w[4], float a, float b, float c, float d, float tol)
{
    return fabsf(w[0] - a) < tol && fabsf(w[1] - b) < tol && fabsf(w[2] - c) < tol
           && fabsf(w[3] - d) < tol;
}

static void test_kinematics(void)
{
    float w[4];
    float s;
    float c;
    int deg;
    /* docs/conventions.md's checks */
    mh_command_to_wheels(100.0f, 0.0f, 0.0f, K, w);
    CHECK(near4(w, 100.0f, -100.0f, -100.0f, 100.0f, 1e-4f));
    mh_command_to_wheels(100.0f, 0.0f, 45.0f, K, w);
    CHECK(near4(w, 100.0f, 0.0f, 0.0f, 100.0f, 1e-4f));
    mh_command_to_wheels(0.0f, 60.0f, 0.0f, K, w);
    CHECK(near4(w, -45.59f, 45.59f, -45.59f, 45.59f, 0.005f));
    /* n = 60 ahead (theta 90): every wheel at 60 */
    mh_command_to_wheels(60.0f, 0.0f, 90.0f, K, w);
    CHECK(near4(w, 60.0f, 60.0f, 60.0f, 60.0f, 1e-4f));
    /* sin and cos against libm over the whole theta range */
    for (deg = -720; deg <= 720; deg++) {
        float x = (float)deg * 0.9101f;
        mh_sincos_deg(x, &s, &c);
        CHECK(fabs(s - sin(x * 3.14159265358979 / 180.0)) < 2e-6);
        CHECK(fabs(c - cos(x * 3.14159265358979 / 180.0)) < 2e-6);
    }
    /* the peak is the largest |w_i| */
    for (deg = -655; deg <= 655; deg += 7) {
        float peak = mh_wheel_peak(37.0f, -21.0f, K);
        float m = 0.0f;
        int i;
        mh_command_to_wheels(37.0f, -21.0f, (float)deg, K, w);
        for (i = 0; i < 4; i++) {
            m = fabsf(w[i]) > m ? fabsf(w[i]) : m;
        }
        CHECK(fabsf(m - peak) < 1e-4f);
    }
}

static void test_limit_check(void)
{
    const float L = 130.0f;
    CHECK(mh_check_command(130.0f, 0.0f, 90.0f, K, L) == MH_CMD_OK); /* exactly at it */
    CHECK(mh_check_command(-130.0f, 0.0f, 270.0f, K, L) == MH_CMD_OK);
    CHECK(mh_check_command(130.0f * 1.0000005f, 0.0f, 90.0f, K, L) == MH_CMD_OK);
    CHECK(mh_check_command(130.0f * 1.000002f, 0.0f, 90.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    /* conformance's cases beyond the limit */
    CHECK(mh_check_command(1.01f * L, 0.0f, 90.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(-1.01f * L, 0.0f, 270.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(0.0f, 1.01f * L * 6.0f / K, 90.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(0.8f * L, 0.5f * L * 6.0f / K, 45.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(5000.0f, 0.0f, 90.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(1e30f, 0.0f, 90.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(3.4e38f, 3.4e38f, 90.0f, K, L) == MH_CMD_BEYOND_LIMIT);
    CHECK(mh_check_command(0.0f, 0.0f, 700.0f, K, L) == MH_CMD_THETA_RANGE);
    CHECK(mh_check_command(0.0f, 0.0f, 655.36f, K, L) == MH_CMD_OK);
    CHECK(mh_check_command(0.0f, 0.0f, -655.37f, K, L) == MH_CMD_THETA_RANGE);
    /* not finite, field by field, in order */
    CHECK(mh_check_command(NAN, INFINITY, NAN, K, L) == MH_CMD_N_NOT_FINITE);
    CHECK(mh_check_command(0.0f, -INFINITY, NAN, K, L) == MH_CMD_OMEGA_NOT_FINITE);
    CHECK(mh_check_command(0.0f, 0.0f, INFINITY, K, L) == MH_CMD_THETA_NOT_FINITE);
    /* subnormals and -0.0 are valid */
    CHECK(mh_check_command(1e-45f, -0.0f, -1e-40f, K, L) == MH_CMD_OK);
    CHECK(strcmp(mh_cmd_check_text(MH_CMD_N_NOT_FINITE), "n not finite") == 0);
}

/* ---- the controller on a test board ------------------------------------------------------- */

static mh_core core;
static test_board tb;

static void feed_hex(const char *wire)
{
    uint8_t b[256];
    size_t n = hex(wire, b);
    mh_feed(&core, b, n);
}

static void feed_frame(uint8_t version, uint8_t type, uint16_t seq, const uint8_t *body,
                       size_t len)
{
    uint8_t wire[MH_MAX_WIRE];
    size_t n = mh_frame_encode(version, type, seq, body, len, wire);
    mh_feed(&core, wire, n);
}

static void feed_command(uint16_t seq, float n, float omega, float theta)
{
    uint8_t body[12];
    mh_put_f32(body, n);
    mh_put_f32(body + 4, omega);
    mh_put_f32(body + 8, theta);
    feed_frame(2, MH_COMMAND, seq, body, 12);
}

/* What the core wrote since the last call; clears it. */
static size_t take(uint8_t *out)
{
    size_t n = tb.out_len;
    memcpy(out, tb.out, n);
    tb.out_len = 0;
    return n;
}

/* The frames written since the last call, decoded: types, seqs and raw bodies. */
typedef struct frame_seen {
    uint8_t type;
    uint16_t seq;
    uint8_t body[64];
    size_t body_len;
} frame_seen;

static size_t take_frames(frame_seen *f, size_t cap)
{
    uint8_t out[TB_OUT_CAP];
    size_t n = take(out);
    size_t i = 0;
    size_t count = 0;
    while (i < n && count < cap) {
        size_t start;
        uint8_t raw[MH_MAX_ENCODED];
        size_t nraw = 0;
        while (i < n && out[i] == 0) {
            i++;
        }
        start = i;
        while (i < n && out[i] != 0) {
            i++;
        }
        if (i > start && mh_cobs_decode(out + start, i - start, raw, sizeof raw, &nraw)) {
            f[count].type = raw[1];
            f[count].seq = mh_get_u16(raw + 2);
            f[count].body_len = nraw - 6;
            memcpy(f[count].body, raw + 4, nraw - 6);
            count++;
        }
    }
    return count;
}

static uint16_t tlm_status(const frame_seen *f)
{
    return mh_get_u16(f->body + 20);
}

static uint16_t tlm_ack(const frame_seen *f)
{
    return mh_get_u16(f->body + 22);
}

static void reset_board(void)
{
    memset(&tb, 0, sizeof tb);
}

static void test_worked_session(void)
{
    uint8_t out[TB_OUT_CAP];
    size_t n;
    uint8_t body[12];
    frame_seen f[8];

    /* the HELLO_ACK of the worked example, byte for byte */
    reset_board();
    tb_start(&core, &tb, 100, 130.0f, K, "sim");
    tb.now_us = 1234567u;
    feed_hex("00 03 02 01 01 03 98 5e 00");
    n = take(out);
    CHECK(n > 20 && same(out, 20, "00 03 02 81 01 02 64 02 fa 01 01 08 02 43 73 69 6d 3e 57 00"));

    /* a session at 50 Hz whose wheels read 12.5 rpm: the TELEMETRY, PONG and ERROR examples */
    reset_board();
    tb.wheels[0] = tb.wheels[1] = tb.wheels[2] = tb.wheels[3] = 12.5f;
    tb_start(&core, &tb, 50, 130.0f, K, "sim");
    tb.now_us = 4000000000u; /* the clock wraps during the session */
    feed_hex("00 03 02 01 01 03 98 5e 00");
    CHECK(take_frames(f, 8) == 2 && f[0].type == MH_HELLO_ACK && f[0].seq == 0
          && f[1].type == MH_TELEMETRY && f[1].seq == 1 && mh_get_u32(f[1].body) == 0
          && tlm_status(&f[1]) == MH_ST_STOPPED && tlm_ack(&f[1]) == 0);
    tb.now_us += 5000u;
    feed_hex("00 04 02 02 01 01 01 03 70 42 01 01 01 01 01 05 b4 42 ab e0 00"); /* COMMAND */
    CHECK(tb.out_len == 0);
    CHECK(near4(tb.targets, 60.0f, 60.0f, 60.0f, 60.0f, 1e-4f));
    tb.now_us += 14999u;
    mh_poll(&core);
    CHECK(tb.out_len == 0); /* the second sample is due at 20000 us */
    tb.now_us += 1u;
    mh_poll(&core);
    n = take(out);
    CHECK(same(out, n, "00 04 02 82 02 03 20 4e 01 01 01 03 48 41 01 03 48 41 01 03 48 41 01 03 "
                       "48 41 01 02 01 03 0c 5c 00"));
    feed_hex("00 04 02 03 02 03 9a 56 00");        /* STOP, seq 2 */
    feed_hex("00 04 02 04 03 03 3b e0 00");        /* HEARTBEAT, seq 3 */
    feed_hex("00 04 02 05 04 02 07 01 01 03 b3 90 00"); /* PING 7, seq 4 */
    n = take(out);
    CHECK(same(out, n, "00 04 02 85 03 02 07 01 01 03 0b f3 00")); /* PONG 7, seq 3 */
    feed_hex("00 04 02 06 05 03 fd 24 00"); /* ESTOP_RESET, seq 5: nothing latched */
    CHECK(tb.out_len == 0);
    mh_put_f32(body, NAN);
    mh_put_f32(body + 4, 0.0f);
    mh_put_f32(body + 8, 90.0f);
    feed_frame(2, MH_COMMAND, 6, body, 12);
    n = take(out);
    CHECK(same(out, n, "00 04 02 8f 04 10 02 6e 20 6e 6f 74 20 66 69 6e 69 74 65 8b 29 00"));
    tb.now_us += 20000u;
    mh_poll(&core);
    CHECK(take_frames(f, 8) == 1 && f[0].seq == 5 && mh_get_u32(f[0].body) == 40000u
          && tlm_status(&f[0]) == MH_ST_STOPPED && tlm_ack(&f[0]) == 5);
    CHECK(core.counters.received == 7 && core.counters.lost == 0
          && core.counters.refused_commands == 1 && core.counters.malformed == 0);
}

static void hello(void)
{
    feed_hex("00 03 02 01 01 03 98 5e 00");
}

static void test_before_hello(void)
{
    frame_seen f[8];
    uint8_t tok[4] = {1, 2, 3, 4};
    uint8_t short_body[8] = {0};
    reset_board();
    tb_start(&core, &tb, 100, 130.0f, K, "t");
    /* a COMMAND, a short COMMAND, STOP: ignored, no telemetry, no ERROR */
    feed_command(1, 10.0f, 0.0f, 90.0f);
    feed_frame(2, MH_COMMAND, 2, short_body, 8);
    feed_frame(2, MH_STOP, 3, NULL, 0);
    tb.now_us += 1000000u;
    mh_poll(&core);
    CHECK(tb.out_len == 0 && tb.targets[0] == 0.0f);
    /* PING: PONG, carrying the seq counted since power-up */
    feed_frame(2, MH_PING, 4, tok, 4);
    CHECK(take_frames(f, 8) == 1 && f[0].type == MH_PONG && f[0].seq == 0
          && memcmp(f[0].body, tok, 4) == 0);
    /* a HELLO of version 3: ERROR 1, seq 1 */
    feed_frame(3, MH_HELLO, 0, NULL, 0);
    CHECK(take_frames(f, 8) == 1 && f[0].type == MH_ERROR && f[0].body[0] == MH_E_VERSION
          && f[0].seq == 1);
    /* the HELLO_ACK restarts the count */
    hello();
    CHECK(take_frames(f, 8) == 2 && f[0].type == MH_HELLO_ACK && f[0].seq == 0);
}

static void test_watchdog_and_stop(void)
{
    frame_seen f[64];
    size_t n;
    reset_board();
    tb.wheels_follow_targets = true;
    tb_start(&core, &tb, 100, 130.0f, K, "t");
    hello();
    take_frames(f, 64);
    feed_command(1, 50.0f, 0.0f, 90.0f);
    CHECK(near4(tb.targets, 50.0f, 50.0f, 50.0f, 50.0f, 1e-4f));
    tb.now_us += 249999u;
    mh_poll(&core);
    n = take_frames(f, 64);
    CHECK(n == 24 && tlm_status(&f[n - 1]) == 0 && tlm_ack(&f[n - 1]) == 1);
    tb.now_us += 1u;
    mh_poll(&core);
    n = take_frames(f, 64);
    CHECK(n == 1 && tlm_status(&f[0]) == MH_ST_WATCHDOG && tb.targets[0] == 0.0f);
    /* HEARTBEAT feeds but does not release; the next COMMAND does */
    feed_frame(2, MH_HEARTBEAT, 2, NULL, 0);
    tb.now_us += 10000u;
    mh_poll(&core);
    n = take_frames(f, 64);
    CHECK(n == 1 && tlm_status(&f[0]) == MH_ST_WATCHDOG && tlm_ack(&f[0]) == 2);
    feed_command(3, 20.0f, 0.0f, 90.0f);
    tb.now_us += 10000u;
    mh_poll(&core);
    n = take_frames(f, 64);
    CHECK(n == 1 && tlm_status(&f[0]) == 0 && tlm_ack(&f[0]) == 3 && tb.targets[0] > 19.0f);
    /* a refused command does not feed: the watchdog fires 250 ms after seq 3 */
    tb.now_us += 100000u;
    feed_command(4, 500.0f, 0.0f, 90.0f);
    n = take_frames(f, 64);
    CHECK(f[n - 1].type == MH_ERROR && f[n - 1].body[0] == MH_E_BAD_COMMAND);
    tb.now_us += 139999u;
    mh_poll(&core);
    take_frames(f, 64);
    CHECK(!(mh_status(&core) & MH_ST_WATCHDOG));
    tb.now_us += 1u;
    mh_poll(&core);
    CHECK(mh_status(&core) & MH_ST_WATCHDOG);
    /* STOP: STOPPED until the next COMMAND, wheels to zero */
    feed_command(5, 20.0f, 0.0f, 90.0f);
    feed_frame(2, MH_STOP, 6, NULL, 0);
    CHECK(mh_status(&core) == MH_ST_STOPPED && tb.targets[0] == 0.0f);
    /* a command of the wrong length in a session: ERROR 2, malformed, not acknowledged */
    {
        uint8_t body[8] = {0};
        feed_frame(2, MH_COMMAND, 7, body, 8);
        n = take_frames(f, 64);
        CHECK(f[n - 1].type == MH_ERROR && f[n - 1].body[0] == MH_E_BAD_COMMAND);
        CHECK(core.ack_seq == 6 && core.counters.malformed == 1);
    }
}

static void test_estop(void)
{
    frame_seen f[16];
    size_t n;
    reset_board();
    tb.estop = true;
    tb_start(&core, &tb, 100, 130.0f, K, "t");
    hello();
    take_frames(f, 16);
    CHECK(mh_status(&core) == (MH_ST_ESTOP | MH_ST_STOPPED));
    /* a valid COMMAND is acknowledged, the wheels stay at zero */
    feed_command(1, 50.0f, 0.0f, 90.0f);
    CHECK(core.ack_seq == 1 && tb.targets[0] == 0.0f && mh_status(&core) == MH_ST_ESTOP);
    /* a HELLO does not clear it */
    hello();
    take_frames(f, 16);
    CHECK(mh_status(&core) & MH_ST_ESTOP);
    /* ESTOP_RESET while held: ERROR 3, not acknowledged */
    feed_frame(2, MH_ESTOP_RESET, 1, NULL, 0);
    n = take_frames(f, 16);
    CHECK(n == 1 && f[0].type == MH_ERROR && f[0].body[0] == MH_E_ESTOP_HELD && core.ack_seq == 0);
    /* released: cleared, STOPPED until the next COMMAND */
    tb.estop = false;
    feed_frame(2, MH_ESTOP_RESET, 2, NULL, 0);
    CHECK(core.ack_seq == 2 && mh_status(&core) == MH_ST_STOPPED);
    feed_command(3, 50.0f, 0.0f, 90.0f);
    CHECK(mh_status(&core) == 0 && tb.targets[0] > 49.0f);
    /* pressed during a session: latched at the next poll, wheels to zero */
    tb.estop = true;
    mh_poll(&core);
    tb.estop = false;
    mh_poll(&core);
    CHECK((mh_status(&core) & MH_ST_ESTOP) && tb.targets[0] == 0.0f);
    /* the drive fault is reported as it is */
    tb.fault = true;
    mh_poll(&core);
    CHECK(mh_status(&core) & MH_ST_FAULT);
}

static void test_framing_counters(void)
{
    uint8_t junk[200];
    uint8_t wire[MH_MAX_WIRE];
    size_t n;
    size_t i;
    frame_seen f[16];
    reset_board();
    tb_start(&core, &tb, 0, 130.0f, K, "t");
    hello();
    take_frames(f, 16);
    /* a run of 200 bytes without a delimiter: one malformed frame, 200 garbage bytes */
    for (i = 0; i < sizeof junk; i++) {
        junk[i] = 0x55;
    }
    mh_feed(&core, junk, sizeof junk);
    feed_hex("00");
    CHECK(core.counters.malformed == 1 && core.counters.garbage_bytes == 200);
    /* a run of exactly 66 bytes is decoded (and is not COBS here): malformed, 66 bytes */
    mh_feed(&core, junk, 66);
    feed_hex("00");
    CHECK(core.counters.malformed == 2 && core.counters.garbage_bytes == 266);
    /* a bad CRC */
    n = mh_frame_encode(2, MH_HEARTBEAT, 1, NULL, 0, wire);
    wire[n - 2] ^= 0x01;
    mh_feed(&core, wire, n);
    CHECK(core.counters.crc == 1);
    /* an unknown type, a wrong version, an echo of our own telemetry */
    feed_frame(2, 0x07, 2, NULL, 0);
    feed_frame(1, MH_HEARTBEAT, 3, NULL, 0);
    feed_frame(2, MH_TELEMETRY, 9, junk, 24);
    CHECK(core.counters.unknown_types == 1 && core.counters.version_errors == 1
          && core.counters.echoes == 1);
    /* the next valid frame: seq 4 after 1 (three dropped frames explain the gap) */
    feed_frame(2, MH_HEARTBEAT, 4, NULL, 0);
    CHECK(core.ack_seq == 4 && core.counters.lost == 0);
    /* seq 10 after 4: five lost */
    feed_frame(2, MH_HEARTBEAT, 10, NULL, 0);
    CHECK(core.counters.lost == 5);
    /* a HELLO with a body: malformed, no answer */
    feed_frame(2, MH_HELLO, 0, junk, 1);
    CHECK(core.counters.malformed == 3 && tb.out_len == 0);
    /* rate 0: no telemetry ever */
    tb.now_us += 5000000u;
    mh_poll(&core);
    CHECK(take_frames(f, 16) == 0);
    /* seq across 65535 -> 0 is acknowledged */
    feed_frame(2, MH_HEARTBEAT, 65535, NULL, 0);
    feed_frame(2, MH_HEARTBEAT, 0, NULL, 0);
    CHECK(core.ack_seq == 0);
}

static void test_stall_and_slow_writer(void)
{
    frame_seen f[128];
    size_t n;
    reset_board();
    tb_start(&core, &tb, 100, 130.0f, K, "t");
    hello();
    take_frames(f, 128);
    /* a stall of 10 s: skip ahead, send the last sample due with its own time, seq + 1 */
    tb.now_us += 10000000u;
    mh_poll(&core);
    n = take_frames(f, 128);
    CHECK(n == 1 && f[0].seq == 2 && mh_get_u32(f[0].body) == 10000000u);
    CHECK(core.counters.telemetry_skipped == 999);
    /* a stall of 30 samples: each sent late with its own time */
    tb.now_us += 300000u;
    mh_poll(&core);
    n = take_frames(f, 128);
    CHECK(n == 30 && mh_get_u32(f[0].body) == 10010000u && mh_get_u32(f[29].body) == 10300000u);
    /* a writer that takes 5 bytes at a time: frames stay whole, in order */
    tb.write_budget = 5;
    tb.now_us += 20000u;
    mh_poll(&core);
    while (mh_tx_pending(&core) > 0) {
        mh_poll(&core);
    }
    n = take_frames(f, 128);
    CHECK(n == 2 && f[0].seq == 33 && f[1].seq == 34);
    /* 1/3 s periods (3 Hz) round to the microsecond */
    reset_board();
    tb_start(&core, &tb, 3, 130.0f, K, "t");
    hello();
    take_frames(f, 128);
    tb.now_us = 1000000u;
    mh_poll(&core);
    n = take_frames(f, 128);
    CHECK(n == 3 && mh_get_u32(f[0].body) == 333333u && mh_get_u32(f[1].body) == 666667u
          && mh_get_u32(f[2].body) == 1000000u);
}

int main(void)
{
    test_crc();
    test_examples();
    test_cobs_edges();
    test_kinematics();
    test_limit_check();
    test_worked_session();
    test_before_hello();
    test_watchdog_and_stop();
    test_estop();
    test_framing_counters();
    test_stall_and_slow_writer();
    printf("%d checks, %d failed\n", checks, failures);
    return failures == 0 ? 0 : 1;
}
