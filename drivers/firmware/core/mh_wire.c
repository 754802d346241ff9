#include "mh_wire.h"

uint16_t mh_crc16(const uint8_t *data, size_t len, uint16_t crc)
{
    size_t i;
    int bit;
    for (i = 0; i < len; i++) {
        crc = (uint16_t)(crc ^ ((uint16_t)data[i] << 8));
        for (bit = 0; bit < 8; bit++) {
            if (crc & 0x8000u) {
                crc = (uint16_t)((crc << 1) ^ 0x1021u);
            } else {
                crc = (uint16_t)(crc << 1);
            }
        }
    }
    return crc;
}

size_t mh_cobs_encode(const uint8_t *in, size_t len, uint8_t *out)
{
    size_t code_at = 0; /* where the current block's code byte goes */
    size_t o = 1;
    uint8_t code = 1;
    size_t i;
    for (i = 0; i < len; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = in[i];
            code++;
            if (code == 0xFF) {
                out[code_at] = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return o;
}

bool mh_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap, size_t *out_len)
{
    size_t i = 0;
    size_t o = 0;
    while (i < len) {
        uint8_t code = in[i];
        size_t j;
        if (code == 0 || i + code > len) {
            return false;
        }
        for (j = 1; j < code; j++) {
            if (o >= cap) {
                return false;
            }
            out[o++] = in[i + j];
        }
        i += code;
        if (code < 0xFF && i < len) {
            if (o >= cap) {
                return false;
            }
            out[o++] = 0;
        }
    }
    *out_len = o;
    return true;
}

size_t mh_frame_encode(uint8_t version, uint8_t type, uint16_t seq, const uint8_t *body,
                       size_t body_len, uint8_t *out)
{
    uint8_t raw[MH_MAX_FRAME];
    size_t n;
    size_t i;
    uint16_t crc;
    if (body_len > MH_MAX_FRAME - MH_OVERHEAD) {
        return 0;
    }
    raw[0] = version;
    raw[1] = type;
    mh_put_u16(raw + 2, seq);
    for (i = 0; i < body_len; i++) {
        raw[MH_HEADER + i] = body[i];
    }
    n = MH_HEADER + body_len;
    crc = mh_crc16(raw, n, 0xFFFFu);
    mh_put_u16(raw + n, crc);
    n += 2;
    out[0] = 0;
    n = mh_cobs_encode(raw, n, out + 1) + 1;
    out[n] = 0;
    return n + 1;
}

void mh_put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

void mh_put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

/* float <-> its IEEE-754 binary32 bits through a union (defined behaviour in C99 TC3). */
typedef union {
    float f;
    uint32_t u;
} mh_f32_bits;

void mh_put_f32(uint8_t *p, float v)
{
    mh_f32_bits b;
    b.f = v;
    mh_put_u32(p, b.u);
}

uint16_t mh_get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

uint32_t mh_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16)
           | ((uint32_t)p[3] << 24);
}

float mh_get_f32(const uint8_t *p)
{
    mh_f32_bits b;
    b.u = mh_get_u32(p);
    return b.f;
}
