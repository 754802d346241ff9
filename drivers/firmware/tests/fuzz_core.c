/* A fuzz target for the core: the input is split into steps that advance the clock, press or
 * release the e-stop, or feed bytes. libFuzzer calls LLVMFuzzerTestOneInput; built with
 * -DMH_FUZZ_STANDALONE it is a program of its own that runs N pseudo-random inputs (the
 * inputs mix valid frames of every type with random bytes). Every run checks what the core
 * wrote: whole frames of at most 67 bytes between delimiters, valid COBS and CRC, version 2. */
#include <stdlib.h>
#include <string.h>

#include "mh_core.h"
#include "test_board.h"

static mh_core core;
static test_board tb;
static unsigned long frames_checked = 0;
static unsigned long frame_types[256];

/* Checks the frames written whole so far and keeps a frame still being written. */
static void check_output(void)
{
    size_t i = 0;
    size_t end = tb.out_len;
    while (end > 0 && tb.out[end - 1] != 0) {
        end--;
    }
    while (i < end) {
        size_t start;
        uint8_t raw[MH_MAX_ENCODED];
        size_t n = 0;
        while (i < end && tb.out[i] == 0) {
            i++;
        }
        start = i;
        while (i < end && tb.out[i] != 0) {
            i++;
        }
        if (i == start) {
            break;
        }
        if (i - start > MH_MAX_ENCODED || !mh_cobs_decode(tb.out + start, i - start, raw,
                                                          sizeof raw, &n)
            || n < MH_OVERHEAD || raw[0] != MH_PROTOCOL_VERSION
            || mh_crc16(raw, n - 2, 0xFFFFu) != mh_get_u16(raw + n - 2)) {
            abort();
        }
        frames_checked++;
        frame_types[raw[1]]++;
    }
    memmove(tb.out, tb.out + end, tb.out_len - end);
    tb.out_len -= end;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    size_t i = 0;
    memset(&tb, 0, sizeof tb);
    tb.wheels_follow_targets = true;
    tb.write_budget = size > 0 ? (size_t)(data[0] % 8u) : 0u;
    tb_start(&core, &tb, 100, 130.0f, 0.465f / 0.102f, "fuzz");
    while (i < size) {
        uint8_t op = data[i++];
        size_t len = (size_t)(op & 0x3Fu) + 1u;
        switch (op >> 6) {
        case 0: /* advance the clock by up to 2^16 * 8 us */
            if (i + 2 <= size) {
                tb.now_us += (uint32_t)mh_get_u16(data + i) * 8u;
                i += 2;
            }
            mh_poll(&core);
            break;
        case 1:
            tb.estop = (op & 1u) != 0;
            mh_poll(&core);
            break;
        default: /* bytes */
            if (len > size - i) {
                len = size - i;
            }
            mh_feed(&core, data + i, len);
            i += len;
            break;
        }
        if (tb.out_len > TB_OUT_CAP / 2) {
            check_output();
        }
    }
    check_output();
    return 0;
}

#ifdef MH_FUZZ_STANDALONE
#include <stdio.h>

static uint32_t rng_state = 12345u;

static uint32_t rng(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

/* Appends a feed step holding one frame of a host type, a random body and seq. */
static size_t add_frame(uint8_t *buf, size_t at)
{
    static const uint8_t types[] = {MH_HELLO, MH_COMMAND, MH_STOP, MH_HEARTBEAT, MH_PING,
                                    MH_ESTOP_RESET, MH_TELEMETRY, 0x07};
    static const size_t lens[] = {0, 12, 0, 0, 4, 0, 24, 0};
    uint8_t body[24];
    uint8_t wire[MH_MAX_WIRE];
    size_t t = rng() % 8u;
    size_t len = lens[t];
    size_t n;
    size_t j;
    for (j = 0; j < len; j++) {
        body[j] = (uint8_t)rng();
    }
    if (types[t] == MH_COMMAND && rng() % 2u == 0) {
        /* a plausible command: small floats */
        mh_put_f32(body, (float)(rng() % 400u) - 200.0f);
        mh_put_f32(body + 4, (float)(rng() % 400u) - 200.0f);
        mh_put_f32(body + 8, (float)(rng() % 1400u) - 700.0f);
    }
    if (rng() % 16u == 0) {
        len = rng() % 20u; /* a wrong length */
    }
    n = mh_frame_encode(rng() % 8u == 0 ? (uint8_t)(rng() % 4u) : 2u, types[t],
                        (uint16_t)(rng() % 8u), body, len, wire);
    if (rng() % 16u == 0) {
        wire[1 + rng() % (n - 2)] ^= (uint8_t)(1u << (rng() % 8u)); /* damaged */
    }
    buf[at++] = (uint8_t)(0xC0u | (n - 1u));
    memcpy(buf + at, wire, n);
    return at + n;
}

int main(int argc, char **argv)
{
    long runs = argc > 1 ? atol(argv[1]) : 10000;
    long r;
    static uint8_t buf[4096];
    for (r = 0; r < runs; r++) {
        size_t at = 0;
        while (at < sizeof buf - 80u) {
            uint32_t pick = rng() % 10u;
            if (pick < 5u) {
                at = add_frame(buf, at);
            } else if (pick < 7u) {
                buf[at++] = (uint8_t)(rng() % 64u); /* clock */
                buf[at++] = (uint8_t)rng();
                buf[at++] = (uint8_t)rng();
            } else if (pick < 8u) {
                buf[at++] = (uint8_t)(0x40u | (rng() % 2u)); /* e-stop */
            } else {
                buf[at++] = (uint8_t)rng(); /* raw bytes */
            }
            if (rng() % 64u == 0) {
                break;
            }
        }
        LLVMFuzzerTestOneInput(buf, at);
    }
    printf("%ld fuzz inputs, no failure; %lu frames written: %lu HELLO_ACK, %lu TELEMETRY, "
           "%lu PONG, %lu ERROR\n", runs, frames_checked, frame_types[MH_HELLO_ACK],
           frame_types[MH_TELEMETRY], frame_types[MH_PONG], frame_types[MH_ERROR]);
    return 0;
}
#endif
