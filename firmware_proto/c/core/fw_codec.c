#include "fw_codec.h"

#include <string.h>

static uint32_t crc_table[256];
static bool crc_ready;

static void crc_init(void) {
    for (uint32_t i = 0; i < 256u; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++) c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        crc_table[i] = c;
    }
    crc_ready = true;
}

uint32_t fw_crc32_update(uint32_t crc, const uint8_t *data, size_t n) {
    if (!crc_ready) crc_init();
    crc = ~crc;
    for (size_t i = 0; i < n; i++) crc = crc_table[(crc ^ data[i]) & 0xFFu] ^ (crc >> 8);
    return ~crc;
}

size_t fw_cobs_encode(const uint8_t *in, size_t n, uint8_t *out) {
    size_t code_at = 0, o = 1;
    uint8_t code = 1;
    for (size_t i = 0; i < n; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = in[i];
            if (++code == 0xFFu) {
                out[code_at] = code;
                code = 1;
                if (i + 1 == n) return o; /* a frame ending with a full block: nothing follows */
                code_at = o++;
            }
        }
    }
    out[code_at] = code;
    return o;
}

long fw_cobs_decode(uint8_t *buf, size_t n) {
    size_t i = 0, o = 0;
    while (i < n) {
        uint8_t code = buf[i];
        if (code == 0) return -1;
        if (i + code > n) return -1;
        i++;
        for (uint8_t k = 1; k < code; k++) buf[o++] = buf[i++];
        if (code != 0xFFu && i < n) buf[o++] = 0;
    }
    return (long)o;
}

float fw_get_f32(const uint8_t *p) {
    uint32_t u = fw_get_u32(p);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

void fw_put_f32(uint8_t *p, float v) {
    uint32_t u;
    memcpy(&u, &v, sizeof u);
    fw_put_u32(p, u);
}

bool fw_type_known(uint8_t t) {
    return (t >= FW_HELLO && t <= FW_HEARTBEAT) || (t >= FW_SAMPLES && t <= FW_SYNC);
}

static bool f32_finite(const uint8_t *p) { return (fw_get_u32(p) & 0x7F800000u) != 0x7F800000u; }

/* Payload checks of one type: FW_DEC_OK, FW_DEC_BAD_LENGTH or FW_DEC_BAD_VALUE. */
static enum fw_decode_error check_payload(uint8_t type, const uint8_t *pl, size_t len) {
    size_t fixed;
    switch (type) {
    case FW_HELLO: case FW_STOP: case FW_HEARTBEAT: case FW_ACK: fixed = 8; break;
    case FW_NAK: fixed = 12; break;
    case FW_START: case FW_FAULT: fixed = 16; break;
    case FW_RAMP_TO_SAFE: fixed = 0; break;
    case FW_STATUS: fixed = 56; break;
    case FW_CAPABILITIES: {
        if (len < 36) return FW_DEC_BAD_LENGTH;
        uint8_t c = pl[10];
        if (len != 36u + 8u * c) return FW_DEC_BAD_LENGTH;
        if (c < 1 || c > FW_MAX_CHANNELS) return FW_DEC_BAD_VALUE;
        return FW_DEC_OK;
    }
    case FW_CONFIGURE: {
        if (len < 16) return FW_DEC_BAD_LENGTH;
        uint8_t c = pl[12];
        if (len != 16u + 32u * c) return FW_DEC_BAD_LENGTH;
        if (c < 1 || c > FW_MAX_CHANNELS) return FW_DEC_BAD_VALUE;
        for (unsigned i = 0; i < c; i++) {
            const uint8_t *ch = pl + 16 + 32 * i;
            static const uint8_t floats[] = {0, 4, 16, 20, 24};
            for (unsigned k = 0; k < sizeof floats; k++)
                if (!f32_finite(ch + floats[k])) return FW_DEC_BAD_VALUE;
        }
        return FW_DEC_OK;
    }
    case FW_SAMPLES: case FW_SENSOR: {
        size_t head = type == FW_SAMPLES ? 12u : 16u;
        if (len < head) return FW_DEC_BAD_LENGTH;
        uint8_t c = pl[8];
        if (c < 1 || c > FW_MAX_CHANNELS) return FW_DEC_BAD_VALUE;
        uint16_t n = fw_get_u16(pl + 10);
        if (len != head + 2u * c * (size_t)n) return FW_DEC_BAD_LENGTH;
        if (n < 1) return FW_DEC_BAD_VALUE;
        uint64_t first = fw_get_u64(pl);
        if (first + (uint64_t)(n - 1) >= FW_NO_INDEX || first + (uint64_t)(n - 1) < first) return FW_DEC_BAD_VALUE;
        if (type == FW_SENSOR && fw_get_u16(pl + 12) < 1) return FW_DEC_BAD_VALUE;
        return FW_DEC_OK;
    }
    case FW_SYNC: {
        if (len < 12) return FW_DEC_BAD_LENGTH;
        uint16_t n = fw_get_u16(pl + 8);
        if (len != 12u + 8u * (size_t)n) return FW_DEC_BAD_LENGTH;
        if (n < 1) return FW_DEC_BAD_VALUE;
        uint32_t prev = 0;
        for (unsigned j = 0; j < n; j++) {
            uint32_t off = fw_get_u32(pl + 12 + 8 * j);
            if (off < prev) return FW_DEC_BAD_VALUE;
            prev = off;
        }
        uint64_t first = fw_get_u64(pl);
        if (first + prev >= FW_NO_INDEX || first + prev < first) return FW_DEC_BAD_VALUE;
        return FW_DEC_OK;
    }
    default: return FW_DEC_UNKNOWN_TYPE;
    }
    return len == fixed ? FW_DEC_OK : FW_DEC_BAD_LENGTH;
}

enum fw_decode_error fw_check_frame(const uint8_t *f, size_t n) {
    if (n < FW_HEADER_SIZE + FW_CRC_SIZE) return FW_DEC_TOO_SHORT;
    if (fw_crc32_update(0, f, n - 4) != fw_get_u32(f + n - 4)) return FW_DEC_BAD_CRC;
    uint8_t version = f[0], type = f[1];
    if (!fw_type_known(type)) return FW_DEC_UNKNOWN_TYPE;
    if (version != FW_PROTOCOL_VERSION && type != FW_HELLO && type != FW_NAK) return FW_DEC_BAD_VERSION;
    return check_payload(type, f + FW_HEADER_SIZE, n - FW_HEADER_SIZE - FW_CRC_SIZE);
}

size_t fw_finish_frame(uint8_t *frame, size_t payload_len, uint8_t *wire) {
    size_t n = FW_HEADER_SIZE + payload_len;
    fw_put_u32(frame + n, fw_crc32_update(0, frame, n));
    size_t w = fw_cobs_encode(frame, n + FW_CRC_SIZE, wire);
    wire[w++] = 0;
    return w;
}
