#include "mh_core.h"

/* Deliberate bugs, each off unless defined at compile time; the conformance tests build
 * them to show that a rule fails on each:
 *   MH_BUG_PING_FEEDS_WATCHDOG         a PING feeds the watchdog
 *   MH_BUG_WATCHDOG_ONLY_WHILE_MOVING  the watchdog runs only while a command is in force
 *   MH_BUG_ESTOP_ERROR_FEEDS_WATCHDOG  an ESTOP_RESET answered with ERROR 3 feeds it
 *   MH_BUG_BYTES_FEED_WATCHDOG         every received byte feeds it */

/* in 32 bits also where int has 16 */
#define MH_WATCHDOG_US ((uint32_t)MH_WATCHDOG_MS * 1000u)

/* Body lengths of the host's types. */
static int mh_host_body_len(uint8_t type)
{
    switch (type) {
    case MH_COMMAND:
        return 12;
    case MH_PING:
        return 4;
    case MH_HELLO:
    case MH_STOP:
    case MH_HEARTBEAT:
    case MH_ESTOP_RESET:
        return 0;
    default:
        return -1;
    }
}

static bool mh_is_controller_type(uint8_t type)
{
    return type == MH_HELLO_ACK || type == MH_TELEMETRY || type == MH_PONG || type == MH_ERROR;
}

static uint32_t mh_now(const mh_core *c)
{
    return c->board.now_us(c->board.ctx);
}

/* ---- output ------------------------------------------------------------------------------ */

static void mh_flush(mh_core *c)
{
    while (c->tx_len > 0) {
        size_t chunk = MH_TX_BUFFER - c->tx_head;
        size_t took;
        if (chunk > c->tx_len) {
            chunk = c->tx_len;
        }
        took = c->board.write(c->board.ctx, c->tx + c->tx_head, chunk);
        if (took > chunk) {
            took = chunk;
        }
        c->tx_head = (c->tx_head + took) % MH_TX_BUFFER;
        c->tx_len -= took;
        if (took < chunk) {
            return;
        }
    }
}

/* Queues one frame (with the next seq), or drops it whole when it does not fit. */
static void mh_send(mh_core *c, uint8_t type, const uint8_t *body, size_t body_len)
{
    uint8_t wire[MH_MAX_WIRE];
    size_t n = mh_frame_encode(MH_PROTOCOL_VERSION, type, c->tx_seq, body, body_len, wire);
    size_t i;
    size_t at;
    c->tx_seq = (uint16_t)(c->tx_seq + 1u);
    if (n > MH_TX_BUFFER - c->tx_len) {
        mh_flush(c); /* make room if the board takes bytes now */
    }
    if (n == 0 || n > MH_TX_BUFFER - c->tx_len) {
        c->counters.dropped_output++;
        return;
    }
    at = (c->tx_head + c->tx_len) % MH_TX_BUFFER;
    for (i = 0; i < n; i++) {
        c->tx[at] = wire[i];
        at = (at + 1u) % MH_TX_BUFFER;
    }
    c->tx_len += n;
}

static void mh_send_error(mh_core *c, uint8_t code, const char *text)
{
    uint8_t body[41];
    size_t n = 1;
    body[0] = code;
    while (text[n - 1] != '\0' && n < sizeof body) {
        body[n] = (uint8_t)text[n - 1];
        n++;
    }
    mh_send(c, MH_ERROR, body, n);
}

/* ---- state -------------------------------------------------------------------------------- */

uint16_t mh_status(const mh_core *c)
{
    uint16_t st = 0;
    if (c->estop) {
        st |= MH_ST_ESTOP;
    }
    if (c->watchdog) {
        st |= MH_ST_WATCHDOG;
    }
    if (c->stopped) {
        st |= MH_ST_STOPPED;
    }
    if (c->fault) {
        st |= MH_ST_FAULT;
    }
    return st;
}

/* Sets the wheel targets the state asks for and tells the board when they changed. */
static void mh_apply_targets(mh_core *c)
{
    float w[4];
    int i;
    bool changed = false;
    w[0] = w[1] = w[2] = w[3] = 0.0f;
    if (c->session && !c->estop && !c->stopped && !c->watchdog && c->have_command) {
        mh_command_to_wheels(c->command[0], c->command[1], c->command[2], c->cfg.k, w);
    }
    for (i = 0; i < 4; i++) {
        /* compared as bits would also catch -0.0; the board needs only value changes */
        if (w[i] < c->targets[i] || w[i] > c->targets[i]) {
            changed = true;
        }
        c->targets[i] = w[i];
    }
    if (changed) {
        c->board.set_targets(c->board.ctx, c->targets);
    }
}

static void mh_feed_watchdog(mh_core *c, uint32_t now)
{
    c->last_feed_us = now;
}

/* Time of telemetry sample k after the HELLO [us], k * 10^6 / rate rounded, modulo 2^32,
 * in 32-bit arithmetic: with m = k mod rate < 2^16, m * (10^6 mod rate) + rate / 2 < 2^32. */
static uint32_t mh_sample_time_us(uint32_t k, uint32_t rate)
{
    uint32_t q = 1000000u / rate;
    uint32_t r = 1000000u % rate;
    uint32_t m = k % rate;
    return (k / rate) * 1000000u + m * q + (m * r + rate / 2u) / rate;
}

/* Sample k is due at elapsed time e (both modulo 2^32, within 2^31 us of each other). */
static bool mh_sample_due(const mh_core *c, uint32_t k, uint32_t elapsed)
{
    return (int32_t)(elapsed - mh_sample_time_us(k, c->cfg.telemetry_rate_hz)) >= 0;
}

static void mh_send_telemetry(mh_core *c)
{
    uint8_t body[24];
    float wheels[4];
    int i;
    c->board.read_wheels(c->board.ctx, wheels);
    mh_put_u32(body, mh_sample_time_us(c->sample, c->cfg.telemetry_rate_hz));
    for (i = 0; i < 4; i++) {
        mh_put_f32(body + 4 + 4 * i, wheels[i]);
    }
    mh_put_u16(body + 20, mh_status(c));
    mh_put_u16(body + 22, c->ack_seq);
    mh_send(c, MH_TELEMETRY, body, sizeof body);
    c->counters.telemetry_sent++;
    c->sample++;
}

static void mh_telemetry_due(mh_core *c, uint32_t now)
{
    uint32_t rate = c->cfg.telemetry_rate_hz;
    uint32_t elapsed = now - c->t0_us;
    uint32_t skipped = 0;
    if (rate == 0) {
        return;
    }
    if (mh_sample_due(c, c->sample + MH_SKIP_AHEAD, elapsed)) {
        /* a long stall: skip to the last sample due (a second of samples at a time first) */
        while (mh_sample_due(c, c->sample + rate + 1u, elapsed)) {
            c->sample += rate;
            skipped += rate;
        }
        while (mh_sample_due(c, c->sample + 1u, elapsed)) {
            c->sample++;
            skipped++;
        }
        c->counters.telemetry_skipped += skipped;
    }
    while (mh_sample_due(c, c->sample, elapsed)) {
        mh_send_telemetry(c);
    }
}

static void mh_tick(mh_core *c, uint32_t now)
{
    bool fault = c->board.drive_fault != 0 && c->board.drive_fault(c->board.ctx);
    c->fault = fault;
    if (!c->estop && c->board.estop_pressed != 0 && c->board.estop_pressed(c->board.ctx)) {
        c->estop = true;
        mh_apply_targets(c);
    }
    if (!c->session) {
        return;
    }
#ifdef MH_BUG_WATCHDOG_ONLY_WHILE_MOVING
    if (!c->have_command || c->stopped) {
        mh_feed_watchdog(c, now);
    }
#endif
    if (!c->watchdog && now - c->last_feed_us >= MH_WATCHDOG_US) {
        c->watchdog = true;
        c->have_command = false;
        mh_apply_targets(c);
    }
    mh_telemetry_due(c, now);
}

/* ---- input -------------------------------------------------------------------------------- */

static void mh_drop(mh_core *c, uint32_t *counter, size_t encoded_len)
{
    (*counter)++;
    c->counters.garbage_bytes += (uint32_t)encoded_len;
    c->rx_dropped_since_valid++;
}

/* A valid frame's seq: frames missing from the host's count that no dropped frame explains
 * are lost; a jump backwards is the host restarting. */
static void mh_account_seq(mh_core *c, uint16_t seq)
{
    if (c->rx_have_seq) {
        uint16_t gap = (uint16_t)(seq - c->rx_expected_seq);
        if (gap < 0x8000u && gap > c->rx_dropped_since_valid) {
            c->counters.lost += gap - c->rx_dropped_since_valid;
        }
    }
    c->rx_have_seq = true;
    c->rx_expected_seq = (uint16_t)(seq + 1u);
    c->rx_dropped_since_valid = 0;
}

static void mh_on_hello(mh_core *c, uint16_t seq, uint32_t now)
{
    uint8_t body[8 + MH_NAME_MAX];
    size_t n = 8;
    c->session = true;
    c->t0_us = now;
    c->sample = 0;
    c->tx_seq = 0;
    c->stopped = true;
    c->watchdog = false;
    c->have_command = false;
    mh_feed_watchdog(c, now);
    c->ack_seq = seq;
    mh_apply_targets(c);
    mh_put_u16(body, c->cfg.telemetry_rate_hz);
    mh_put_u16(body + 2, (uint16_t)MH_WATCHDOG_MS);
    mh_put_f32(body + 4, c->cfg.wheel_limit_rpm);
    if (c->cfg.name != 0) {
        while (n < sizeof body && c->cfg.name[n - 8] != '\0') {
            body[n] = (uint8_t)c->cfg.name[n - 8];
            n++;
        }
    }
    mh_send(c, MH_HELLO_ACK, body, n);
    mh_telemetry_due(c, now); /* the first sample, seq 1, time_us 0 */
}

static void mh_on_command(mh_core *c, uint16_t seq, const uint8_t *body, uint32_t now)
{
    float n = mh_get_f32(body);
    float omega = mh_get_f32(body + 4);
    float theta = mh_get_f32(body + 8);
    mh_cmd_check why = mh_check_command(n, omega, theta, c->cfg.k, c->cfg.wheel_limit_rpm);
    if (why != MH_CMD_OK) {
        c->counters.refused_commands++;
        mh_send_error(c, MH_E_BAD_COMMAND, mh_cmd_check_text(why));
        return;
    }
    c->ack_seq = seq;
    mh_feed_watchdog(c, now);
    c->command[0] = n;
    c->command[1] = omega;
    c->command[2] = theta;
    c->have_command = true;
    c->stopped = false;
    c->watchdog = false;
    mh_apply_targets(c);
}

static void mh_on_estop_reset(mh_core *c, uint16_t seq, uint32_t now)
{
    if (c->estop && c->board.estop_pressed != 0 && c->board.estop_pressed(c->board.ctx)) {
#ifdef MH_BUG_ESTOP_ERROR_FEEDS_WATCHDOG
        mh_feed_watchdog(c, now);
#endif
        mh_send_error(c, MH_E_ESTOP_HELD, "e-stop still held");
        return;
    }
    c->ack_seq = seq;
    mh_feed_watchdog(c, now);
    if (c->estop) {
        c->estop = false;
        c->have_command = false;
        c->stopped = true;
        mh_apply_targets(c);
    }
}

/* One piece between two delimiters. */
static void mh_on_piece(mh_core *c, const uint8_t *piece, size_t len, uint32_t now)
{
    uint8_t raw[MH_MAX_ENCODED];
    size_t n = 0;
    uint8_t version;
    uint8_t type;
    uint16_t seq;
    size_t body_len;
    int want;
    /* checked in the document's order: malformed, crc, type, version, body length */
    if (!mh_cobs_decode(piece, len, raw, sizeof raw, &n) || n < MH_OVERHEAD) {
        mh_drop(c, &c->counters.malformed, len);
        return;
    }
    if (mh_crc16(raw, n - 2u, 0xFFFFu) != mh_get_u16(raw + n - 2u)) {
        mh_drop(c, &c->counters.crc, len);
        return;
    }
    version = raw[0];
    type = raw[1];
    seq = mh_get_u16(raw + 2);
    body_len = n - MH_OVERHEAD;
    if (mh_is_controller_type(type)) {
        c->counters.echoes++; /* a frame of our own heard back: counted nowhere else */
        return;
    }
    want = mh_host_body_len(type);
    if (want < 0) {
        mh_drop(c, &c->counters.unknown_types, len);
        return;
    }
    if (version != MH_PROTOCOL_VERSION && type != MH_HELLO) {
        mh_drop(c, &c->counters.version_errors, len);
        return;
    }
    if (n > MH_MAX_FRAME || body_len != (size_t)want) {
        /* the CRC is right, so type and seq can be trusted: a session answers a COMMAND */
        c->counters.malformed++;
        c->counters.garbage_bytes += (uint32_t)len;
        if (type == MH_COMMAND && c->session) {
            mh_account_seq(c, seq);
            c->counters.refused_commands++;
            mh_send_error(c, MH_E_BAD_COMMAND, "COMMAND body not 12 bytes");
        } else {
            c->rx_dropped_since_valid++;
        }
        return;
    }
    c->counters.received++;
    c->last_type = type;
    mh_account_seq(c, seq);
    if (type == MH_HELLO) {
        if (version != MH_PROTOCOL_VERSION) {
            mh_send_error(c, MH_E_VERSION, "controller speaks protocol version 2");
        } else {
            mh_on_hello(c, seq, now);
        }
        return;
    }
    if (type == MH_PING) {
#ifdef MH_BUG_PING_FEEDS_WATCHDOG
        if (c->session) {
            mh_feed_watchdog(c, now);
        }
#endif
        mh_send(c, MH_PONG, raw + MH_HEADER, 4);
        return;
    }
    if (!c->session) {
        return; /* before the first HELLO only HELLO and PING are answered */
    }
    switch (type) {
    case MH_COMMAND:
        mh_on_command(c, seq, raw + MH_HEADER, now);
        break;
    case MH_STOP:
        c->ack_seq = seq;
        mh_feed_watchdog(c, now);
        c->have_command = false;
        c->stopped = true;
        mh_apply_targets(c);
        break;
    case MH_HEARTBEAT:
        c->ack_seq = seq;
        mh_feed_watchdog(c, now);
        break;
    case MH_ESTOP_RESET:
        mh_on_estop_reset(c, seq, now);
        break;
    default:
        break;
    }
}

void mh_feed(mh_core *c, const uint8_t *data, size_t len)
{
    uint32_t now = mh_now(c);
    size_t i;
    /* what was due before these bytes came happens first */
    mh_tick(c, now);
#ifdef MH_BUG_BYTES_FEED_WATCHDOG
    if (c->session && len > 0) {
        mh_feed_watchdog(c, now);
    }
#endif
    for (i = 0; i < len; i++) {
        uint8_t b = data[i];
        if (b == 0) {
            if (!c->rx_discarding && c->rx_len > 0) {
                mh_on_piece(c, c->rx, c->rx_len, now);
            }
            c->rx_len = 0;
            c->rx_discarding = false;
        } else if (c->rx_discarding) {
            c->counters.garbage_bytes++;
        } else if (c->rx_len == MH_MAX_ENCODED) {
            /* longer than any frame: one malformed frame up to the next delimiter */
            mh_drop(c, &c->counters.malformed, (size_t)c->rx_len + 1u);
            c->rx_len = 0;
            c->rx_discarding = true;
        } else {
            c->rx[c->rx_len++] = b;
        }
    }
    mh_flush(c);
}

void mh_poll(mh_core *c)
{
    mh_tick(c, mh_now(c));
    mh_flush(c);
}

uint32_t mh_idle_us(const mh_core *c)
{
    uint32_t now = mh_now(c);
    uint32_t idle = MH_IDLE_MAX_US;
    if (c->session && !c->watchdog) {
        uint32_t fed_for = now - c->last_feed_us;
        uint32_t left = fed_for >= MH_WATCHDOG_US ? 0u : MH_WATCHDOG_US - fed_for;
        if (left < idle) {
            idle = left;
        }
    }
    if (c->session && c->cfg.telemetry_rate_hz > 0) {
        uint32_t next = mh_sample_time_us(c->sample, c->cfg.telemetry_rate_hz);
        int32_t left = (int32_t)(next - (now - c->t0_us));
        if (left <= 0) {
            idle = 0;
        } else if ((uint32_t)left < idle) {
            idle = (uint32_t)left;
        }
    }
    return idle;
}

size_t mh_tx_pending(const mh_core *c)
{
    return c->tx_len;
}

void mh_init(mh_core *c, const mh_board *board, const mh_config *cfg)
{
    /* volatile: the compiler must not turn the loop into a call of memset */
    volatile uint8_t *p = (volatile uint8_t *)c;
    size_t i;
    for (i = 0; i < sizeof *c; i++) {
        p[i] = 0;
    }
    c->board = *board;
    c->cfg = *cfg;
    c->stopped = true;
    c->board.set_targets(c->board.ctx, c->targets);
    if (c->board.estop_pressed != 0 && c->board.estop_pressed(c->board.ctx)) {
        c->estop = true;
    }
}
