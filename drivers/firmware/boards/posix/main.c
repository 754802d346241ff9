/* The POSIX host port of the reference controller: the core on a pseudo-terminal, in real
 * time, with a first-order motor per wheel.
 *
 *   mh-controller [--telemetry-rate HZ] [--limit RPM] [--k K] [--tau-s S] [--name NAME]
 *                 [--estop-pressed [--estop-held-s S]] [--fault-at-s S] [--stall-at-s S
 *                 --stall-s S] [--restart-at-s S] [--nan-at-s S] [--freeze-ack-at-s S]
 *
 * It prints the path of the pseudo-terminal's slave end as the first line of standard output
 * and serves until SIGTERM or SIGINT, then prints its counters as one JSON line on standard
 * error and exits 0. The fault options count from the first HELLO. --restart-at-s plays a
 * power-cycle: the core starts again as at power-up (no session, no telemetry, PING still
 * answered). --nan-at-s makes wheel 2's reading NaN from then on; --freeze-ack-at-s keeps
 * ack_seq at its value of that time (the commands still drive the wheels). */
#define _XOPEN_SOURCE 700

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "mh_core.h"

typedef struct posix_board {
    int master;
    struct timespec start;
    double tau_s;
    float wheels[4];  /* measured speeds [rpm] */
    float targets[4]; /* what the core asks [rpm] */
    uint32_t model_us;
    bool estop_pressed_at_start;
    bool estop_seen;
    double estop_held_s;
    double fault_at_s; /* after the first HELLO; < 0: never */
    double nan_at_s;   /* after the first HELLO; < 0: never */
    double first_hello_s; /* < 0: none yet */
} posix_board;

static volatile sig_atomic_t stop_requested = 0;

static void on_signal(int signum)
{
    (void)signum;
    stop_requested = 1;
}

static double seconds_since_start(const posix_board *b)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (double)(now.tv_sec - b->start.tv_sec) + 1e-9 * (double)(now.tv_nsec - b->start.tv_nsec);
}

static uint32_t board_now_us(void *ctx)
{
    /* modulo 2^32, as a microcontroller's free-running counter */
    return (uint32_t)(uint64_t)(seconds_since_start(ctx) * 1e6);
}

/* Advances every wheel exactly over the time since the last call, the targets held. */
static void advance_model(posix_board *b)
{
    uint32_t now = board_now_us(b);
    double dt = 1e-6 * (double)(uint32_t)(now - b->model_us);
    double a = exp(-dt / b->tau_s);
    int i;
    for (i = 0; i < 4; i++) {
        b->wheels[i] = (float)(b->targets[i] + (b->wheels[i] - b->targets[i]) * a);
    }
    b->model_us = now;
}

static size_t board_write(void *ctx, const uint8_t *data, size_t len)
{
    posix_board *b = ctx;
    ssize_t n = write(b->master, data, len);
    return n > 0 ? (size_t)n : 0u;
}

static void board_read_wheels(void *ctx, float rpm[4])
{
    posix_board *b = ctx;
    advance_model(b);
    memcpy(rpm, b->wheels, sizeof b->wheels);
    if (b->nan_at_s >= 0.0 && b->first_hello_s >= 0.0
        && seconds_since_start(b) - b->first_hello_s >= b->nan_at_s) {
        rpm[1] = (float)NAN; /* fault injection: a sensor that reads no number */
    }
}

static void board_set_targets(void *ctx, const float rpm[4])
{
    posix_board *b = ctx;
    advance_model(b);
    memcpy(b->targets, rpm, sizeof b->targets);
}

static bool board_estop_pressed(void *ctx)
{
    posix_board *b = ctx;
    /* pressed at power-up (the core latches it then), released after --estop-held-s */
    if (b->estop_pressed_at_start && !b->estop_seen) {
        b->estop_seen = true;
        return true;
    }
    return b->estop_pressed_at_start && seconds_since_start(b) < b->estop_held_s;
}

static bool board_drive_fault(void *ctx)
{
    posix_board *b = ctx;
    return b->fault_at_s >= 0.0 && b->first_hello_s >= 0.0
           && seconds_since_start(b) - b->first_hello_s >= b->fault_at_s;
}

static int open_pty(char *path, size_t cap, int *slave)
{
    struct termios t;
    int master = posix_openpt(O_RDWR | O_NOCTTY);
    const char *name;
    if (master < 0 || grantpt(master) != 0 || unlockpt(master) != 0) {
        return -1;
    }
    name = ptsname(master);
    if (name == NULL || strlen(name) + 1 > cap) {
        return -1;
    }
    strcpy(path, name);
    /* kept open, so the master never reads EIO while no host has the port open */
    *slave = open(path, O_RDWR | O_NOCTTY);
    if (*slave < 0 || tcgetattr(*slave, &t) != 0) {
        return -1;
    }
    /* raw: bytes pass unchanged both ways */
    t.c_iflag &= (tcflag_t) ~(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON);
    t.c_oflag &= (tcflag_t) ~OPOST;
    t.c_lflag &= (tcflag_t) ~(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
    t.c_cflag &= (tcflag_t) ~(CSIZE | PARENB);
    t.c_cflag |= CS8;
    t.c_cc[VMIN] = 1;
    t.c_cc[VTIME] = 0;
    if (tcsetattr(*slave, TCSANOW, &t) != 0) {
        return -1;
    }
    if (fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK) != 0) {
        return -1;
    }
    return master;
}

static void usage(const char *prog)
{
    fprintf(stderr,
            "usage: %s [--telemetry-rate HZ] [--limit RPM] [--k K] [--tau-s S] [--name NAME]\n"
            "          [--estop-pressed [--estop-held-s S]] [--fault-at-s S]\n"
            "          [--stall-at-s S --stall-s S] [--restart-at-s S] [--nan-at-s S]\n"
            "          [--freeze-ack-at-s S]\n",
            prog);
}

static bool parse_double(const char *text, double *out)
{
    char *end;
    double v = strtod(text, &end);
    if (end == text || *end != '\0' || !isfinite(v)) {
        return false;
    }
    *out = v;
    return true;
}

static void print_counters(const mh_counters *k, uint8_t last_type)
{
    fprintf(stderr,
            "{\"received\": %lu, \"malformed\": %lu, \"crc\": %lu, \"unknown_types\": %lu, "
            "\"version_errors\": %lu, \"echoes\": %lu, \"lost\": %lu, \"garbage_bytes\": %lu, "
            "\"refused_commands\": %lu, \"dropped_output\": %lu, \"telemetry_sent\": %lu, "
            "\"telemetry_skipped\": %lu, \"last_type\": %u}\n",
            (unsigned long)k->received, (unsigned long)k->malformed, (unsigned long)k->crc,
            (unsigned long)k->unknown_types, (unsigned long)k->version_errors,
            (unsigned long)k->echoes, (unsigned long)k->lost, (unsigned long)k->garbage_bytes,
            (unsigned long)k->refused_commands, (unsigned long)k->dropped_output,
            (unsigned long)k->telemetry_sent, (unsigned long)k->telemetry_skipped,
            (unsigned)last_type);
    fflush(stderr);
}

int main(int argc, char **argv)
{
    static mh_core core;
    static posix_board pb;
    mh_board board;
    mh_config cfg;
    double rate = 100.0;
    double limit = 130.0;
    double k = 0.465 / 0.102; /* drivers/tdam-stm.toml: lx_plus_ly_m / wheel_radius_m */
    double stall_at_s = -1.0;
    double stall_s = 0.0;
    bool stalled = false;
    double restart_at_s = -1.0;
    bool restarted = false;
    double freeze_ack_at_s = -1.0;
    bool frozen = false;
    uint16_t frozen_ack = 0;
    const char *name = "mecanum-hil-c99";
    char path[256];
    int slave = -1;
    int i;
    struct sigaction sa;

    pb.tau_s = 0.05;
    pb.fault_at_s = -1.0;
    pb.nan_at_s = -1.0;
    pb.first_hello_s = -1.0;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        bool ok = true;
        if (strcmp(a, "--estop-pressed") == 0) {
            pb.estop_pressed_at_start = true;
            continue;
        }
        if (v == NULL) {
            ok = false;
        } else if (strcmp(a, "--telemetry-rate") == 0) {
            ok = parse_double(v, &rate) && rate >= 0.0 && rate <= 65535.0 && rate == floor(rate);
        } else if (strcmp(a, "--limit") == 0) {
            ok = parse_double(v, &limit) && limit > 0.0;
        } else if (strcmp(a, "--k") == 0) {
            ok = parse_double(v, &k) && k > 0.0;
        } else if (strcmp(a, "--tau-s") == 0) {
            ok = parse_double(v, &pb.tau_s) && pb.tau_s > 0.0;
        } else if (strcmp(a, "--estop-held-s") == 0) {
            ok = parse_double(v, &pb.estop_held_s) && pb.estop_held_s >= 0.0;
        } else if (strcmp(a, "--fault-at-s") == 0) {
            ok = parse_double(v, &pb.fault_at_s) && pb.fault_at_s >= 0.0;
        } else if (strcmp(a, "--stall-at-s") == 0) {
            ok = parse_double(v, &stall_at_s) && stall_at_s >= 0.0;
        } else if (strcmp(a, "--nan-at-s") == 0) {
            ok = parse_double(v, &pb.nan_at_s) && pb.nan_at_s >= 0.0;
        } else if (strcmp(a, "--freeze-ack-at-s") == 0) {
            ok = parse_double(v, &freeze_ack_at_s) && freeze_ack_at_s >= 0.0;
        } else if (strcmp(a, "--restart-at-s") == 0) {
            ok = parse_double(v, &restart_at_s) && restart_at_s >= 0.0;
        } else if (strcmp(a, "--stall-s") == 0) {
            ok = parse_double(v, &stall_s) && stall_s >= 0.0;
        } else if (strcmp(a, "--name") == 0) {
            name = v;
        } else {
            ok = false;
        }
        if (!ok) {
            usage(argv[0]);
            return 2;
        }
        i++;
    }

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);

    clock_gettime(CLOCK_MONOTONIC, &pb.start);
    pb.master = open_pty(path, sizeof path, &slave);
    if (pb.master < 0) {
        fprintf(stderr, "error: cannot open a pseudo-terminal: %s\n", strerror(errno));
        return 1;
    }
    board.ctx = &pb;
    board.now_us = board_now_us;
    board.write = board_write;
    board.read_wheels = board_read_wheels;
    board.set_targets = board_set_targets;
    board.estop_pressed = board_estop_pressed;
    board.drive_fault = board_drive_fault;
    cfg.telemetry_rate_hz = (uint16_t)rate;
    cfg.wheel_limit_rpm = (float)limit;
    cfg.k = (float)k;
    cfg.name = name;
    mh_init(&core, &board, &cfg);
    printf("%s\n", path);
    fflush(stdout);

    while (!stop_requested) {
        struct pollfd pfd;
        uint32_t idle;
        uint8_t buf[4096];
        if (pb.first_hello_s < 0.0 && core.session) {
            pb.first_hello_s = seconds_since_start(&pb);
        }
        if (!stalled && stall_at_s >= 0.0 && pb.first_hello_s >= 0.0
            && seconds_since_start(&pb) - pb.first_hello_s >= stall_at_s) {
            /* fault injection: the controller reads and sends nothing for a while */
            struct timespec d;
            stalled = true;
            d.tv_sec = (time_t)stall_s;
            d.tv_nsec = (long)((stall_s - (double)d.tv_sec) * 1e9);
            nanosleep(&d, NULL);
        }
        if (!restarted && restart_at_s >= 0.0 && pb.first_hello_s >= 0.0
            && seconds_since_start(&pb) - pb.first_hello_s >= restart_at_s) {
            /* fault injection: a power-cycle, the core as at power-up (counters kept) */
            mh_counters kept = core.counters;
            restarted = true;
            mh_init(&core, &board, &cfg);
            core.counters = kept;
        }
        if (!frozen && freeze_ack_at_s >= 0.0 && pb.first_hello_s >= 0.0
            && seconds_since_start(&pb) - pb.first_hello_s >= freeze_ack_at_s) {
            frozen = true;
            frozen_ack = core.ack_seq;
        }
        if (frozen) {
            core.ack_seq = frozen_ack; /* fault injection: telemetry stops acknowledging */
        }
        mh_poll(&core);
        idle = mh_idle_us(&core);
        pfd.fd = pb.master;
        pfd.events = (short)(POLLIN | (mh_tx_pending(&core) > 0 ? POLLOUT : 0));
        pfd.revents = 0;
        if (poll(&pfd, 1, (int)((idle + 999u) / 1000u)) > 0 && (pfd.revents & POLLIN)) {
            ssize_t n = read(pb.master, buf, sizeof buf);
            if (n > 0) {
                if (frozen) {
                    core.ack_seq = frozen_ack;
                }
                mh_feed(&core, buf, (size_t)n);
            }
        }
    }
    print_counters(&core.counters, core.last_type);
    close(pb.master);
    close(slave);
    return 0;
}
