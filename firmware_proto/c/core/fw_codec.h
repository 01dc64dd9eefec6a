/* piezod board protocol (firmware_proto/PROTOCOL.md), version 1: constants and the wire codec.
 * C11, no dynamic allocation, no I/O. */
#ifndef FW_CODEC_H
#define FW_CODEC_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define FW_PROTOCOL_VERSION 1u
#define FW_HEADER_SIZE 8u
#define FW_CRC_SIZE 4u
#define FW_MAX_FRAME 8192u
#define FW_MAX_WIRE 8226u /* MAX_FRAME + ceil(8192/254) + delimiter */
#define FW_MAX_STUFFED (FW_MAX_WIRE - 1u)
#define FW_MAX_CHANNELS 8u
#define FW_NO_INDEX UINT64_MAX
#define FW_NO_CHANNEL 0xFFu
#define FW_FLAG_ACK_REQ 0x01u

enum fw_type {
    FW_HELLO = 0x01, FW_CAPABILITIES = 0x02, FW_CONFIGURE = 0x03, FW_ACK = 0x04, FW_NAK = 0x05,
    FW_START = 0x06, FW_STOP = 0x07, FW_RAMP_TO_SAFE = 0x08, FW_HEARTBEAT = 0x09,
    FW_SAMPLES = 0x10, FW_STATUS = 0x11, FW_SENSOR = 0x12, FW_FAULT = 0x13, FW_SYNC = 0x14
};

enum fw_state { FW_UNCONFIGURED = 0, FW_IDLE = 1, FW_ARMED = 2, FW_RUNNING = 3, FW_RAMPING = 4 };

enum fw_nak_reason {
    FW_NAK_VERSION_MISMATCH = 1, FW_NAK_UNKNOWN_TYPE = 2, FW_NAK_BAD_LENGTH = 3,
    FW_NAK_BAD_VALUE = 4, FW_NAK_BAD_STATE = 5, FW_NAK_UNSUPPORTED = 6
};

enum fw_fault_code {
    FW_FAULT_UNDERRUN = 1, FW_FAULT_LIMIT_VIOLATION = 2, FW_FAULT_CRC_ERRORS = 3,
    FW_FAULT_WATCHDOG = 4, FW_FAULT_CONFIG_REJECTED = 5, FW_FAULT_OVERFLOW = 6,
    FW_FAULT_INDEX_GAP = 7, FW_FAULT_HARDWARE = 8
};
#define FW_N_FAULT_CODES 8u

/* Why a received frame was dropped (PROTOCOL.md 2.3, in check order). */
enum fw_decode_error {
    FW_DEC_OK = 0, FW_DEC_OVERSIZE, FW_DEC_BAD_COBS, FW_DEC_TOO_SHORT, FW_DEC_BAD_CRC,
    FW_DEC_UNKNOWN_TYPE, FW_DEC_BAD_VERSION, FW_DEC_BAD_LENGTH, FW_DEC_BAD_VALUE
};

/* CRC-32/ISO-HDLC (zlib): crc = fw_crc32_update(0, data, n) gives the CRC of data. */
uint32_t fw_crc32_update(uint32_t crc, const uint8_t *data, size_t n);

/* Canonical COBS encoding of in[0..n) into out (no delimiter); returns the stuffed length
 * (<= n + n/254 + 1). out must not overlap in. */
size_t fw_cobs_encode(const uint8_t *in, size_t n, uint8_t *out);

/* COBS-decode buf[0..n) in place (no delimiter inside); returns the decoded length, or -1. */
long fw_cobs_decode(uint8_t *buf, size_t n);

/* Checks 3..8 of PROTOCOL.md 2.3 on a decoded frame. */
enum fw_decode_error fw_check_frame(const uint8_t *frame, size_t n);

/* Encode a frame whose header and payload are in frame[0..8+len): sets the CRC, stuffs it into
 * wire and appends the delimiter. Returns the wire length. */
size_t fw_finish_frame(uint8_t *frame, size_t payload_len, uint8_t *wire);

static inline void fw_put_u16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static inline void fw_put_u32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}
static inline void fw_put_u64(uint8_t *p, uint64_t v) {
    fw_put_u32(p, (uint32_t)v); fw_put_u32(p + 4, (uint32_t)(v >> 32));
}
static inline uint16_t fw_get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static inline uint32_t fw_get_u32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
static inline uint64_t fw_get_u64(const uint8_t *p) {
    return (uint64_t)fw_get_u32(p) | ((uint64_t)fw_get_u32(p + 4) << 32);
}
static inline int16_t fw_get_i16(const uint8_t *p) {
    uint16_t u = fw_get_u16(p);
    return (int16_t)(u >= 0x8000u ? (int32_t)u - 65536 : (int32_t)u);
}
float fw_get_f32(const uint8_t *p);
void fw_put_f32(uint8_t *p, float v);

/* Payload length of a type given the frame (-1: unknown type; also validates the block sizes). */
bool fw_type_known(uint8_t type);

#endif
