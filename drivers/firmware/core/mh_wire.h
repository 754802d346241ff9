/* Serial framing of the mecanum-hil controller protocol, version 2 (drivers/protocol.md):
 * CRC-16/CCITT-FALSE, COBS, little-endian fields and whole frames. No heap, no libc. */
#ifndef MH_WIRE_H
#define MH_WIRE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define MH_PROTOCOL_VERSION 2u
/* Longest frame before COBS (header + body + CRC) [bytes]. */
#define MH_MAX_FRAME 64u
/* Longest run between delimiters a receiver buffers: 64 + 1 COBS byte + 1 to spare. */
#define MH_MAX_ENCODED 66u
/* Longest frame on the wire: 00 + 65 COBS bytes + 00. */
#define MH_MAX_WIRE 67u
/* Header (version, type, seq) and CRC [bytes]. */
#define MH_HEADER 4u
#define MH_OVERHEAD 6u

/* Message types. */
enum {
    MH_HELLO = 0x01, MH_COMMAND = 0x02, MH_STOP = 0x03, MH_HEARTBEAT = 0x04, MH_PING = 0x05,
    MH_ESTOP_RESET = 0x06,
    MH_HELLO_ACK = 0x81, MH_TELEMETRY = 0x82, MH_PONG = 0x85, MH_ERROR = 0x8F
};

/* CRC-16/CCITT-FALSE (poly 0x1021, no reflection, no final XOR); start with crc = 0xFFFF. */
uint16_t mh_crc16(const uint8_t *data, size_t len, uint16_t crc);

/* COBS-encodes len bytes (len <= 254) into out (len + 1 bytes); returns the length written. */
size_t mh_cobs_encode(const uint8_t *in, size_t len, uint8_t *out);

/* Decodes one COBS piece into out (at most cap bytes). Returns false when the piece is not
 * valid COBS or decodes to more than cap bytes; *out_len is the decoded length. */
bool mh_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap, size_t *out_len);

/* A whole wire frame, 00 COBS(version type seq body crc) 00, into out (MH_MAX_WIRE bytes).
 * Returns its length, or 0 when the body is longer than a frame carries. */
size_t mh_frame_encode(uint8_t version, uint8_t type, uint16_t seq, const uint8_t *body,
                       size_t body_len, uint8_t *out);

/* Little-endian fields. */
void mh_put_u16(uint8_t *p, uint16_t v);
void mh_put_u32(uint8_t *p, uint32_t v);
void mh_put_f32(uint8_t *p, float v);
uint16_t mh_get_u16(const uint8_t *p);
uint32_t mh_get_u32(const uint8_t *p);
float mh_get_f32(const uint8_t *p);

#ifdef __cplusplus
}
#endif

#endif
