/* The controller's side of the mecanum-hil protocol, version 2 (drivers/protocol.md, serial).
 *
 * Portable C99 without heap or OS calls. A board gives the core its I/O through mh_board,
 * owns one mh_core (a static variable: the core allocates nothing), and from its main loop
 * calls mh_feed() with the bytes it received and mh_poll() often enough for the telemetry
 * period (mh_idle_us() says how long it may wait). */
#ifndef MH_CORE_H
#define MH_CORE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "mh_kinematics.h"
#include "mh_wire.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Watchdog time, announced in HELLO_ACK [ms]. */
#define MH_WATCHDOG_MS 250u
/* Bytes queued towards the host; a frame that does not fit is dropped whole. */
#ifndef MH_TX_BUFFER
#define MH_TX_BUFFER 256u
#endif
/* Longest name in HELLO_ACK [bytes]. */
#define MH_NAME_MAX 32u
/* After a stall of more than this many telemetry periods the core skips ahead. */
#define MH_SKIP_AHEAD 50u
/* Longest wait mh_idle_us() returns [us] (the e-stop button is read at least this often). */
#define MH_IDLE_MAX_US 10000u

/* Status word bits. */
#define MH_ST_ESTOP 0x0001u
#define MH_ST_WATCHDOG 0x0002u
#define MH_ST_STOPPED 0x0004u
#define MH_ST_FAULT 0x0008u

/* Error codes. */
#define MH_E_VERSION 1u
#define MH_E_BAD_COMMAND 2u
#define MH_E_ESTOP_HELD 3u

/* The board seam: what the board implements. ctx is passed back unchanged. */
typedef struct mh_board {
    void *ctx;
    /* A free-running microsecond clock; wraps at 2^32. */
    uint32_t (*now_us)(void *ctx);
    /* Takes up to len bytes towards the host without blocking; returns how many it took. */
    size_t (*write)(void *ctx, const uint8_t *data, size_t len);
    /* The four measured wheel speeds [rpm] (1 FL, 2 FR, 3 RL, 4 RR). */
    void (*read_wheels)(void *ctx, float rpm[4]);
    /* New wheel speed targets [rpm]; called at every change. */
    void (*set_targets)(void *ctx, const float rpm[4]);
    /* The e-stop button is pressed; NULL when the board has none. */
    bool (*estop_pressed)(void *ctx);
    /* The drive reports a fault (status FAULT); NULL when the board has no such report. */
    bool (*drive_fault)(void *ctx);
} mh_board;

/* The robot and the announcement. */
typedef struct mh_config {
    uint16_t telemetry_rate_hz; /* 0: no telemetry */
    float wheel_limit_rpm;      /* the robot profile's wheel_speed_max_rpm */
    float k;                    /* the robot profile's lx_plus_ly_m / wheel_radius_m */
    const char *name;           /* HELLO_ACK's name, cut at MH_NAME_MAX bytes */
} mh_config;

/* What the controller received and sent [frames, bytes for garbage_bytes]. */
typedef struct mh_counters {
    uint32_t received;
    uint32_t malformed;
    uint32_t crc;
    uint32_t unknown_types;
    uint32_t version_errors;
    uint32_t echoes;
    uint32_t lost;
    uint32_t garbage_bytes;
    uint32_t refused_commands;
    uint32_t dropped_output;
    uint32_t telemetry_sent;
    uint32_t telemetry_skipped;
} mh_counters;

/* The state of one controller. Its fields are the core's own. */
typedef struct mh_core {
    mh_board board;
    mh_config cfg;
    mh_counters counters;
    /* receiving */
    uint8_t rx[MH_MAX_ENCODED];
    uint8_t rx_len;
    bool rx_discarding;
    bool rx_have_seq;
    uint16_t rx_expected_seq;
    uint32_t rx_dropped_since_valid;
    uint8_t last_type; /* type of the last valid frame received (0: none yet) */
    /* sending */
    uint8_t tx[MH_TX_BUFFER];
    size_t tx_head;
    size_t tx_len;
    uint16_t tx_seq;
    /* session */
    bool session;
    bool stopped;
    bool watchdog;
    bool estop;
    bool fault;
    bool have_command;
    float command[3];
    float targets[4];
    uint16_t ack_seq;
    uint32_t t0_us;
    uint32_t last_feed_us;
    uint32_t sample;
} mh_core;

/* Starts a controller: no session, wheels stopped. board and cfg are copied. */
void mh_init(mh_core *c, const mh_board *board, const mh_config *cfg);
/* Bytes received from the host, any chunking. Call from the main loop, not an interrupt. */
void mh_feed(mh_core *c, const uint8_t *data, size_t len);
/* Watchdog, e-stop, telemetry due by now, and what waits to be written. */
void mh_poll(mh_core *c);
/* How long the board may wait before the next mh_poll() [us] (at most MH_IDLE_MAX_US). */
uint32_t mh_idle_us(const mh_core *c);
/* Bytes waiting for the board's write(). */
size_t mh_tx_pending(const mh_core *c);
/* The status word as the next telemetry sample carries it. */
uint16_t mh_status(const mh_core *c);

#ifdef __cplusplus
}
#endif

#endif
