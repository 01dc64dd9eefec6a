#include "fw_core.h"

#include <stdarg.h>
#include <stdio.h>
#include <string.h>

_Static_assert((FW_FIFO_DEPTH & (FW_FIFO_DEPTH - 1u)) == 0, "FW_FIFO_DEPTH must be a power of two");
_Static_assert((FW_SENSOR_RING & (FW_SENSOR_RING - 1u)) == 0, "FW_SENSOR_RING must be a power of two");
_Static_assert((FW_SYNC_QUEUE & (FW_SYNC_QUEUE - 1u)) == 0, "FW_SYNC_QUEUE must be a power of two");

#define FIFO_MASK ((uint64_t)FW_FIFO_DEPTH - 1u)
#define DEFAULT_PERIOD_US 10000u

uint16_t fw_max_rows(unsigned c) {
    if (c < 1 || c > FW_MAX_CHANNELS) return 0;
    return (uint16_t)((FW_MAX_FRAME - FW_HEADER_SIZE - FW_CRC_SIZE - 16u) / (2u * c));
}

__attribute__((format(printf, 2, 3))) static void logf_(fw_board *b, const char *fmt, ...) {
#ifdef FW_NO_LOG /* microcontroller builds: no printf in the firmware */
    (void)b, (void)fmt;
    return;
#else
    if (!b->hal.log) return;
    char line[120];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(line, sizeof line, fmt, ap);
    va_end(ap);
    b->hal.log(b->hal.ctx, line);
#endif
}

/* -- sending ----------------------------------------------------------------------------- */

static uint8_t *begin(fw_board *b, uint8_t type) {
    uint8_t *f = b->txf;
    f[0] = FW_PROTOCOL_VERSION;
    f[1] = type;
    f[2] = 0;
    f[3] = 0;
    fw_put_u32(f + 4, b->tx_seq++);
    return f + FW_HEADER_SIZE;
}

static size_t send(fw_board *b, size_t payload_len) {
    size_t w = fw_finish_frame(b->txf, payload_len, b->txw);
    b->hal.tx(b->hal.ctx, b->txw, w);
    return w;
}

static void reply_cached(fw_board *b, uint32_t req_seq, uint8_t req_type, size_t payload_len) {
    size_t w = send(b, payload_len);
    if (w > sizeof b->replies[0].wire) return;
    fw_reply *r = &b->replies[b->reply_next];
    r->seq = req_seq;
    r->type = req_type;
    r->len = (uint8_t)w;
    memcpy(r->wire, b->txw, w);
    b->reply_next = (b->reply_next + 1u) % FW_REPLY_CACHE;
    if (b->reply_count < FW_REPLY_CACHE) b->reply_count++;
}

static void ack(fw_board *b, uint32_t seq, uint8_t type) {
    uint8_t *p = begin(b, FW_ACK);
    fw_put_u32(p, seq);
    p[4] = type;
    p[5] = p[6] = p[7] = 0;
    reply_cached(b, seq, type, 8);
}

static void nak(fw_board *b, uint32_t seq, uint8_t type, uint8_t reason, uint32_t detail) {
    uint8_t *p = begin(b, FW_NAK);
    fw_put_u32(p, seq);
    p[4] = type;
    p[5] = reason;
    p[6] = p[7] = 0;
    fw_put_u32(p + 8, detail);
    reply_cached(b, seq, type, 12);
}

static uint64_t period_us(const fw_board *b) {
    return b->configured ? (uint64_t)b->conf.status_period_ms * 1000u : DEFAULT_PERIOD_US;
}

static void fault(fw_board *b, uint8_t code, uint8_t channel, uint64_t index, uint32_t detail) {
    b->fault_flags |= 1u << (code - 1u);
    if (b->fault_sent_valid[code] && b->now_us - b->fault_sent_us[code] < period_us(b)) return;
    b->fault_sent_valid[code] = true;
    b->fault_sent_us[code] = b->now_us;
    uint8_t *p = begin(b, FW_FAULT);
    p[0] = code;
    p[1] = channel;
    p[2] = p[3] = 0;
    fw_put_u32(p + 4, detail);
    fw_put_u64(p + 8, index);
    send(b, 16);
}

static void clear_faults(fw_board *b) {
    b->fault_flags = 0;
    memset(b->fault_sent_valid, 0, sizeof b->fault_sent_valid);
}

static void send_status(fw_board *b) {
    uint64_t w, p, last;
    uint8_t state;
    FW_CRITICAL_BEGIN();
    w = b->write_index;
    p = b->play_index;
    last = b->last_played;
    state = b->state;
    FW_CRITICAL_END();
    uint8_t *o = begin(b, FW_STATUS);
    memset(o, 0, 56);
    o[0] = state;
    fw_put_u32(o + 4, b->fault_flags);
    fw_put_u64(o + 8, w);
    fw_put_u64(o + 16, last);
    fw_put_u32(o + 24, (uint32_t)(FW_FIFO_DEPTH - (w - p)));
    fw_put_u32(o + 28, b->cnt.crc_errors);
    fw_put_u32(o + 32, b->cnt.frames_dropped);
    fw_put_u32(o + 36, b->cnt.underruns);
    fw_put_u32(o + 40, b->cnt.clamped_samples);
    fw_put_u32(o + 44, b->cnt.index_gaps);
    fw_put_u32(o + 48, b->cnt.overflows);
    send(b, 56);
    b->status_due = false;
    b->next_status_us = b->now_us + period_us(b);
}

static void set_state(fw_board *b, uint8_t s) {
    if (b->state != s) {
        b->state = s;
        b->status_due = true;
    }
}

static void send_capabilities(fw_board *b, uint32_t reply_to) {
    const fw_caps *c = &b->caps;
    uint8_t *p = begin(b, FW_CAPABILITIES);
    memset(p, 0, 36u + 8u * c->n_channels);
    fw_put_u32(p, reply_to);
    fw_put_u16(p + 4, FW_PROTOCOL_VERSION);
    p[6] = c->fw_major;
    p[7] = c->fw_minor;
    fw_put_u16(p + 8, c->fw_patch);
    p[10] = c->n_channels;
    p[11] = c->dac_bits;
    p[12] = c->adc_bits;
    p[13] = (uint8_t)(c->sync_outputs | (c->no_position_sensor ? 0x80u : 0u));
    fw_put_u16(p + 14, c->max_samples_per_frame);
    fw_put_u32(p + 16, c->sample_rate_min_hz);
    fw_put_u32(p + 20, c->sample_rate_max_hz);
    fw_put_u32(p + 24, c->sample_clock_hz);
    fw_put_u32(p + 28, FW_FIFO_DEPTH);
    fw_put_u32(p + 32, c->board_serial);
    for (unsigned i = 0; i < c->n_channels; i++) {
        fw_put_f32(p + 36 + 8 * i, c->amp_v_min[i]);
        fw_put_f32(p + 40 + 8 * i, c->amp_v_max[i]);
    }
    send(b, 36u + 8u * c->n_channels);
}

/* -- outputs outside RUNNING ------------------------------------------------------------ */

static void apply_codes(fw_board *b) {
    b->hal.dac_write(b->hal.ctx, b->out_code, b->caps.n_channels);
}

/* Main loop, with the tick not running (clock stopped or not yet started). */
static void clear_sync(fw_board *b) {
    b->sync_tail = b->sync_head;
    b->sync_any_queued = false;
    if (b->sync_level) {
        b->sync_level = 0;
        if (b->hal.sync_out) b->hal.sync_out(b->hal.ctx, 0);
    }
}

static void stop_clock(fw_board *b) {
    b->hal.timer(b->hal.ctx, 0);
    FW_CRITICAL_BEGIN();
    if (b->state == FW_RUNNING || b->state == FW_ARMED) b->state = FW_IDLE;
    b->play_index = b->write_index;
    b->stop_after = FW_NO_INDEX;
    FW_CRITICAL_END();
    b->status_due = true;
    clear_sync(b);
}

static void begin_ramp(fw_board *b) {
    for (unsigned c = 0; c < b->caps.n_channels; c++) b->ramp_pos[c] = b->out_code[c];
    b->ramp_last_us = b->now_us;
    set_state(b, FW_RAMPING);
}

static void ramp_step(fw_board *b) {
    double dt = (double)(b->now_us - b->ramp_last_us) * 1e-6;
    b->ramp_last_us = b->now_us;
    bool changed = false, done = true;
    for (unsigned c = 0; c < b->conf.n_channels; c++) {
        const fw_channel *ch = &b->conf.ch[c];
        double target = ch->safe_code, pos = b->ramp_pos[c];
        double step = (double)ch->ramp_v_per_s * dt / (double)ch->dac_v_per_code;
        if (pos < target) {
            pos = pos + step >= target ? target : pos + step;
        } else if (pos > target) {
            pos = pos - step <= target ? target : pos - step;
        }
        b->ramp_pos[c] = pos;
        /* round towards where the ramp came from: never faster than the rate, monotonic */
        double code_f = pos < (double)b->out_code[c] ? __builtin_ceil(pos) : __builtin_floor(pos);
        int16_t code = (int16_t)code_f;
        if (code != b->out_code[c]) {
            b->out_code[c] = code;
            changed = true;
        }
        if (code != ch->safe_code) done = false;
    }
    if (changed) apply_codes(b);
    if (done) set_state(b, FW_IDLE);
}

/* -- receiving ---------------------------------------------------------------------------- */

static void on_hello(fw_board *b, const uint8_t *f, uint32_t seq) {
    uint16_t version = fw_get_u16(f + 8);
    if (version != FW_PROTOCOL_VERSION) {
        logf_(b, "HELLO in protocol version %u refused (this board speaks %u)", (unsigned)version,
              FW_PROTOCOL_VERSION);
        nak(b, seq, FW_HELLO, FW_NAK_VERSION_MISMATCH, FW_PROTOCOL_VERSION);
        return;
    }
    b->hello_seen = true;
    logf_(b, "HELLO session %lu (state %u)", (unsigned long)fw_get_u32(f + 12), (unsigned)b->state);
    send_capabilities(b, seq);
    if (b->configured) {
        b->status_due = true;
        if (b->fault_flags & (1u << (FW_FAULT_WATCHDOG - 1u)))
            fault(b, FW_FAULT_WATCHDOG, FW_NO_CHANNEL, b->watchdog_index, 0);
    }
}

/* The acceptance rules of PROTOCOL.md 4.3; returns 0 or the NAK reason, *at = frame offset. */
static uint8_t check_configure(const fw_board *b, const fw_config *c, uint32_t *at) {
    const fw_caps *k = &b->caps;
    uint32_t rmin = k->sample_rate_min_hz > 1 ? k->sample_rate_min_hz : 1;
    if (c->n_channels != k->n_channels) return *at = 20, FW_NAK_BAD_VALUE;
    if (c->sample_rate_hz < rmin || c->sample_rate_hz > k->sample_rate_max_hz) return *at = 8, FW_NAK_UNSUPPORTED;
    if (k->sample_clock_hz && k->sample_clock_hz % c->sample_rate_hz) return *at = 8, FW_NAK_UNSUPPORTED;
    if (c->heartbeat_timeout_ms < 10 || c->heartbeat_timeout_ms > 60000) return *at = 12, FW_NAK_BAD_VALUE;
    if (c->status_period_ms < 1 || c->status_period_ms > 1000) return *at = 16, FW_NAK_BAD_VALUE;
    if (c->sensor_decimation < 1) return *at = 18, FW_NAK_BAD_VALUE;
    for (unsigned i = 0; i < c->n_channels; i++) {
        const fw_channel *ch = &c->ch[i];
        uint32_t o = 24u + 32u * i;
        double vmin = (double)ch->dac_offset_v + (double)ch->dac_v_per_code * ch->code_min;
        double vmax = (double)ch->dac_offset_v + (double)ch->dac_v_per_code * ch->code_max;
        if (!(ch->dac_v_per_code > 0)) return *at = o, FW_NAK_BAD_VALUE;
        if (ch->code_min > ch->code_max) return *at = o + 8, FW_NAK_BAD_VALUE;
        if (ch->safe_code < ch->code_min || ch->safe_code > ch->code_max) return *at = o + 12, FW_NAK_BAD_VALUE;
        if (vmin < (double)k->amp_v_min[i]) return *at = o + 8, FW_NAK_BAD_VALUE;
        if (vmax > (double)k->amp_v_max[i]) return *at = o + 10, FW_NAK_BAD_VALUE;
        if (!(ch->ramp_v_per_s > 0)) return *at = o + 16, FW_NAK_BAD_VALUE;
        if (ch->adc_um_per_code == 0) return *at = o + 20, FW_NAK_BAD_VALUE;
    }
    return 0;
}

static void on_configure(fw_board *b, const uint8_t *f, uint32_t seq, bool req) {
    if (b->state != FW_UNCONFIGURED && b->state != FW_IDLE) {
        if (req) nak(b, seq, FW_CONFIGURE, FW_NAK_BAD_STATE, b->state);
        return;
    }
    fw_config c;
    memset(&c, 0, sizeof c);
    c.sample_rate_hz = fw_get_u32(f + 8);
    c.heartbeat_timeout_ms = fw_get_u32(f + 12);
    c.status_period_ms = fw_get_u16(f + 16);
    c.sensor_decimation = fw_get_u16(f + 18);
    c.n_channels = f[20];
    for (unsigned i = 0; i < c.n_channels; i++) {
        const uint8_t *p = f + 24 + 32 * i;
        fw_channel *ch = &c.ch[i];
        ch->dac_v_per_code = fw_get_f32(p);
        ch->dac_offset_v = fw_get_f32(p + 4);
        ch->code_min = fw_get_i16(p + 8);
        ch->code_max = fw_get_i16(p + 10);
        ch->safe_code = fw_get_i16(p + 12);
        ch->ramp_v_per_s = fw_get_f32(p + 16);
        ch->adc_um_per_code = fw_get_f32(p + 20);
        ch->adc_offset_um = fw_get_f32(p + 24);
    }
    uint32_t at = 0;
    uint8_t reason = check_configure(b, &c, &at);
    if (reason) {
        logf_(b, "CONFIGURE refused: reason %u at frame offset %lu", (unsigned)reason, (unsigned long)at);
        if (req) nak(b, seq, FW_CONFIGURE, reason, at);
        fault(b, FW_FAULT_CONFIG_REJECTED, FW_NO_CHANNEL, FW_NO_INDEX, at);
        return;
    }
    if (req) ack(b, seq, FW_CONFIGURE);
    b->conf = c;
    b->configured = true;
    clear_faults(b);
    logf_(b, "CONFIGURE accepted: %lu Hz, watchdog %lu ms, status every %u ms, decimation %u",
          (unsigned long)c.sample_rate_hz, (unsigned long)c.heartbeat_timeout_ms, (unsigned)c.status_period_ms,
          (unsigned)c.sensor_decimation);
    begin_ramp(b);
    b->status_due = true;
}

static void on_start(fw_board *b, const uint8_t *f, uint32_t seq, bool req) {
    uint64_t index = fw_get_u64(f + 8);
    uint32_t prefill = fw_get_u32(f + 16);
    if (b->state != FW_IDLE) {
        if (req) nak(b, seq, FW_START, FW_NAK_BAD_STATE, b->state);
        return;
    }
    if (index == FW_NO_INDEX) {
        if (req) nak(b, seq, FW_START, FW_NAK_BAD_VALUE, 8);
        return;
    }
    if (prefill > FW_FIFO_DEPTH) {
        if (req) nak(b, seq, FW_START, FW_NAK_BAD_VALUE, 16);
        return;
    }
    if (req) ack(b, seq, FW_START);
    FW_CRITICAL_BEGIN();
    b->write_index = b->play_index = b->start_index = index;
    b->prefill = prefill > 1 ? prefill : 1;
    b->stop_after = FW_NO_INDEX;
    b->sens_countdown = 0;
    FW_CRITICAL_END();
    clear_sync(b);
    clear_faults(b);
    logf_(b, "START at index %llu, prefill %lu", (unsigned long long)index, (unsigned long)b->prefill);
    set_state(b, FW_ARMED);
}

static void on_stop(fw_board *b, const uint8_t *f, uint32_t seq, bool req) {
    uint64_t after = fw_get_u64(f + 8);
    if (req) ack(b, seq, FW_STOP);
    bool deferred = false;
    FW_CRITICAL_BEGIN();
    if (b->state == FW_RUNNING && after != FW_NO_INDEX && after >= b->play_index) {
        b->stop_after = after;
        deferred = true;
    }
    FW_CRITICAL_END();
    if (deferred) {
        logf_(b, "STOP after index %llu", (unsigned long long)after);
        return;
    }
    if (b->state == FW_RUNNING || b->state == FW_ARMED) stop_clock(b);
    set_state(b, FW_IDLE); /* in RAMPING: the ramp stops, the outputs hold */
}

static void on_samples(fw_board *b, const uint8_t *f) {
    uint8_t C = f[16];
    uint16_t N = fw_get_u16(f + 18);
    uint64_t F = fw_get_u64(f + 8);
    uint8_t state = b->state;
    if ((state != FW_ARMED && state != FW_RUNNING) || C != b->conf.n_channels) {
        b->cnt.frames_dropped++;
        return;
    }
    uint64_t W = b->write_index, P;
    FW_CRITICAL_BEGIN();
    P = b->play_index;
    FW_CRITICAL_END();
    uint64_t L = P + FW_FIFO_DEPTH;
    if (F + N <= W) {
        b->cnt.frames_dropped++;
        return;
    }
    if (F > W) {
        b->cnt.frames_dropped++;
        b->cnt.index_gaps++;
        fault(b, FW_FAULT_INDEX_GAP, FW_NO_CHANNEL, W, 0);
        return;
    }
    if (F + N > L) {
        b->cnt.frames_dropped++;
        b->cnt.overflows++;
        fault(b, FW_FAULT_OVERFLOW, FW_NO_CHANNEL, F, 0);
        return;
    }
    bool clamped = false;
    for (uint64_t j = W - F; j < N; j++) {
        const uint8_t *row = f + 20 + 2u * C * j;
        int16_t *slot = b->fifo[(F + j) & FIFO_MASK];
        for (unsigned c = 0; c < C; c++) {
            int16_t v = fw_get_i16(row + 2 * c);
            const fw_channel *ch = &b->conf.ch[c];
#ifndef FW_MUTANT_NO_CLAMP /* only the fuzz test's mutant build defines it: proves the fuzz sees it */
            if (v < ch->code_min || v > ch->code_max) {
#else
            if (0) {
#endif
                b->cnt.clamped_samples++;
                if (!clamped) {
                    clamped = true;
                    fault(b, FW_FAULT_LIMIT_VIOLATION, (uint8_t)c, F + j, (uint16_t)v);
                }
                v = v < ch->code_min ? ch->code_min : ch->code_max;
            }
            slot[c] = v;
        }
    }
    bool start = false;
    FW_CRITICAL_BEGIN();
    b->write_index = F + N;
    if (b->state == FW_ARMED && b->write_index - b->play_index >= b->prefill) {
        b->state = FW_RUNNING;
        start = true;
    }
    FW_CRITICAL_END();
    if (start) {
        b->status_due = true;
        b->sens_flush_us = b->now_us;
        logf_(b, "clock running from index %llu", (unsigned long long)b->start_index);
        b->hal.timer(b->hal.ctx, b->conf.sample_rate_hz);
    }
}

static void on_sync(fw_board *b, const uint8_t *f) {
    uint8_t state = b->state;
    if ((state != FW_ARMED && state != FW_RUNNING) || !b->caps.sync_outputs) {
        b->cnt.frames_dropped++;
        return;
    }
    uint64_t first = fw_get_u64(f + 8), P;
    uint16_t n = fw_get_u16(f + 16);
    FW_CRITICAL_BEGIN();
    P = b->play_index;
    FW_CRITICAL_END();
    uint64_t floor = b->sync_any_queued && b->sync_last_queued + 1u > P ? b->sync_last_queued + 1u : P;
    uint32_t fresh = 0;
    for (unsigned j = 0; j < n; j++)
        if (first + fw_get_u32(f + 20 + 8 * j) >= floor) fresh++;
    uint32_t used = b->sync_head - b->sync_tail;
    if (used + fresh > FW_SYNC_QUEUE) {
        b->cnt.frames_dropped++;
        b->cnt.overflows++;
        fault(b, FW_FAULT_OVERFLOW, FW_NO_CHANNEL, first, 0);
        return;
    }
    uint8_t enabled = (uint8_t)((1u << b->caps.sync_outputs) - 1u);
    uint32_t head = b->sync_head;
    for (unsigned j = 0; j < n; j++) {
        uint64_t index = first + fw_get_u32(f + 20 + 8 * j);
        if (index < floor) continue;
        uint32_t slot = head & (FW_SYNC_QUEUE - 1u);
        b->sync_index[slot] = index;
        b->sync_lines[slot] = f[24 + 8 * j];
        b->sync_mask[slot] = (uint8_t)(f[25 + 8 * j] & enabled);
        head++;
        b->sync_last_queued = index;
        b->sync_any_queued = true;
    }
    b->sync_head = head; /* publish after the slots are written */
}

static const uint8_t nak_for_error[] = {
    [FW_DEC_UNKNOWN_TYPE] = FW_NAK_UNKNOWN_TYPE, [FW_DEC_BAD_VERSION] = FW_NAK_VERSION_MISMATCH,
    [FW_DEC_BAD_LENGTH] = FW_NAK_BAD_LENGTH, [FW_DEC_BAD_VALUE] = FW_NAK_BAD_VALUE,
};

static void process(fw_board *b, uint8_t *buf, size_t n) {
    long len = fw_cobs_decode(buf, n);
    enum fw_decode_error err = len < 0 ? FW_DEC_BAD_COBS : fw_check_frame(buf, (size_t)len);
    if (err != FW_DEC_OK) {
        b->cnt.frames_dropped++;
        if (err == FW_DEC_BAD_CRC) {
            b->cnt.crc_errors++;
            fault(b, FW_FAULT_CRC_ERRORS, FW_NO_CHANNEL, FW_NO_INDEX, b->cnt.crc_errors);
        }
        if (err >= FW_DEC_UNKNOWN_TYPE && (buf[2] & FW_FLAG_ACK_REQ)) {
            uint8_t reason = nak_for_error[err];
            nak(b, fw_get_u32(buf + 4), buf[1], reason, reason == FW_NAK_VERSION_MISMATCH ? FW_PROTOCOL_VERSION : 0);
        }
        return;
    }
    uint8_t type = buf[1];
    uint32_t seq = fw_get_u32(buf + 4);
    bool req = (buf[2] & FW_FLAG_ACK_REQ) != 0;
    b->last_rx_us = b->now_us;
    b->wd_armed = true;
    switch (type) {
    case FW_HELLO: case FW_CONFIGURE: case FW_START: case FW_STOP: case FW_RAMP_TO_SAFE:
    case FW_HEARTBEAT: case FW_SAMPLES: case FW_SYNC:
        break;
    default:
        b->cnt.frames_dropped++; /* a board -> host type */
        return;
    }
    if (req) {
        if (type == FW_HELLO) {
            b->reply_count = 0;
        } else {
            for (unsigned i = 0; i < b->reply_count; i++) {
                const fw_reply *r = &b->replies[i];
                if (r->seq == seq && r->type == type) {
                    b->cnt.duplicate_requests++;
                    b->hal.tx(b->hal.ctx, r->wire, r->len);
                    return;
                }
            }
        }
    }
    if (type == FW_SAMPLES) {
        on_samples(b, buf);
        return;
    }
    if (type == FW_HEARTBEAT) return;
    if (type == FW_SYNC) {
        on_sync(b, buf);
        return;
    }
    if (type == FW_HELLO) {
        on_hello(b, buf, seq);
        return;
    }
    if (!b->hello_seen || (b->state == FW_UNCONFIGURED && type != FW_CONFIGURE)) {
        if (req) nak(b, seq, type, FW_NAK_BAD_STATE, b->state);
        return;
    }
    switch (type) {
    case FW_CONFIGURE: on_configure(b, buf, seq, req); break;
    case FW_START: on_start(b, buf, seq, req); break;
    case FW_STOP: on_stop(b, buf, seq, req); break;
    default: /* RAMP_TO_SAFE */
        if (req) ack(b, seq, FW_RAMP_TO_SAFE);
        if (b->state == FW_RUNNING || b->state == FW_ARMED) stop_clock(b);
        begin_ramp(b);
        break;
    }
}

void fw_rx(fw_board *b, const uint8_t *data, size_t n, uint64_t now_us) {
    fw_poll(b, now_us);
    for (size_t i = 0; i < n; i++) {
        uint8_t byte = data[i];
        if (byte == 0) {
            if (!b->rx_skipping && b->rx_len > 0) process(b, b->rx, b->rx_len);
            b->rx_len = 0;
            b->rx_skipping = false;
        } else if (!b->rx_skipping) {
            if (b->rx_len == FW_MAX_STUFFED) {
                b->cnt.frames_dropped++;
                b->rx_skipping = true;
                b->rx_len = 0;
            } else {
                b->rx[b->rx_len++] = byte;
            }
        }
    }
    fw_poll(b, now_us);
}

/* -- the tick -------------------------------------------------------------------------------- */

void fw_tick(fw_board *b) {
    if (b->state != FW_RUNNING) return;
    if (b->play_index == b->write_index) {
        b->cnt.underruns++;
        b->state = FW_IDLE;
        b->stop_after = FW_NO_INDEX;
        b->ev_underrun = 1;
        return;
    }
    const int16_t *row = b->fifo[b->play_index & FIFO_MASK];
    unsigned C = b->conf.n_channels;
    b->hal.dac_write(b->hal.ctx, row, C);
    memcpy(b->out_code, row, C * sizeof row[0]);
    uint64_t index = b->play_index++;
    b->last_played = index;
    b->cnt.samples_played++;
    uint32_t st = b->sync_tail;
    if (st != b->sync_head) {
        uint8_t level = b->sync_level;
        while (st != b->sync_head && b->sync_index[st & (FW_SYNC_QUEUE - 1u)] <= index) {
            uint32_t slot = st & (FW_SYNC_QUEUE - 1u);
            if (b->sync_index[slot] == index)
                level = (uint8_t)((level & ~b->sync_mask[slot]) | (b->sync_lines[slot] & b->sync_mask[slot]));
            st++;
        }
        b->sync_tail = st;
        if (level != b->sync_level) {
            b->sync_level = level;
            if (b->hal.sync_out) b->hal.sync_out(b->hal.ctx, level);
        }
    }
    if (b->sens_countdown == 0) {
        b->sens_countdown = (uint16_t)(b->conf.sensor_decimation - 1u);
        uint32_t head = b->sens_head;
        if (head - b->sens_tail < FW_SENSOR_RING) {
            uint32_t slot = head & (FW_SENSOR_RING - 1u);
            b->sens_index[slot] = index;
            b->hal.adc_read(b->hal.ctx, b->sens[slot], C);
            b->sens_head = head + 1u;
        } else {
            b->cnt.sensor_rows_lost++;
        }
    } else {
        b->sens_countdown--;
    }
    if (b->stop_after != FW_NO_INDEX && index >= b->stop_after) {
        b->state = FW_IDLE;
        b->play_index = b->write_index;
        b->stop_after = FW_NO_INDEX;
        b->ev_stopped = 1;
    }
}

/* -- the main loop's timers ------------------------------------------------------------------ */

void fw_sensor_done(fw_board *b, uint32_t rows) { b->sens_ready += rows; }

static void flush_sensor(fw_board *b, bool force) {
    uint32_t head = b->sens_deferred ? b->sens_ready : b->sens_head, tail = b->sens_tail;
    uint32_t avail = head - tail;
    uint16_t mspf = b->caps.max_samples_per_frame;
    if (avail == 0) return;
    if (!force && avail < mspf && b->now_us - b->sens_flush_us < period_us(b)) return;
    unsigned C = b->conf.n_channels;
    uint16_t stride = b->conf.sensor_decimation;
    while (tail != head) {
        uint32_t slot0 = tail & (FW_SENSOR_RING - 1u);
        uint64_t first = b->sens_index[slot0];
        uint8_t *p = begin(b, FW_SENSOR);
        uint16_t n = 0;
        while (tail != head && n < mspf) {
            uint32_t slot = tail & (FW_SENSOR_RING - 1u);
            if (b->sens_index[slot] != first + (uint64_t)n * stride) break; /* rows lost between */
            for (unsigned c = 0; c < C; c++) fw_put_u16(p + 16 + 2u * (C * n + c), (uint16_t)b->sens[slot][c]);
            n++;
            tail++;
        }
        fw_put_u64(p, first);
        p[8] = (uint8_t)C;
        p[9] = 0;
        fw_put_u16(p + 10, n);
        fw_put_u16(p + 12, stride);
        p[14] = p[15] = 0;
        send(b, 16u + 2u * C * n);
        b->sens_tail = tail;
    }
    b->sens_flush_us = b->now_us;
}

void fw_poll(fw_board *b, uint64_t now_us) {
    if (now_us > b->now_us) b->now_us = now_us;
    /* deferred conversions of a run that just ended: its last SENSOR rows go out before the
     * STATUS / FAULT that end it, as on a board whose ADC completes within the tick */
    bool hold = b->sens_deferred && b->sens_ready != b->sens_head && b->state != FW_RUNNING;
    if (b->ev_stopped && !hold) {
        b->ev_stopped = 0;
        b->hal.timer(b->hal.ctx, 0);
        clear_sync(b);
        b->status_due = true;
        logf_(b, "stopped after index %lld", (long long)b->last_played);
    }
    if (b->ev_underrun && !hold) {
        b->ev_underrun = 0;
        b->hal.timer(b->hal.ctx, 0);
        clear_sync(b);
        b->status_due = true;
        logf_(b, "underrun (last valid index %lld)", (long long)b->last_played);
        flush_sensor(b, true);
        fault(b, FW_FAULT_UNDERRUN, FW_NO_CHANNEL, b->last_played, 0);
    }
    uint8_t state = b->state;
    if (b->configured && b->wd_armed && (state == FW_IDLE || state == FW_ARMED || state == FW_RUNNING) &&
        b->now_us - b->last_rx_us >= (uint64_t)b->conf.heartbeat_timeout_ms * 1000u) {
        b->cnt.watchdog_trips++;
        b->wd_armed = false;
        if (state == FW_RUNNING || state == FW_ARMED) stop_clock(b);
        b->watchdog_index = b->last_played;
        logf_(b, "watchdog: host silent for %lu ms, ramping to safe", (unsigned long)b->conf.heartbeat_timeout_ms);
        flush_sensor(b, true);
        fault(b, FW_FAULT_WATCHDOG, FW_NO_CHANNEL, b->last_played, 0);
        begin_ramp(b);
    }
    if (b->state == FW_RAMPING && b->now_us > b->ramp_last_us) ramp_step(b);
    if (b->configured) flush_sensor(b, b->state != FW_RUNNING);
    if (b->configured && !hold && (b->status_due || b->now_us >= b->next_status_us)) send_status(b);
}

void fw_init(fw_board *b, const fw_caps *caps, const fw_hal *hal, uint64_t now_us) {
    memset(b, 0, sizeof *b);
    b->caps = *caps;
    if (b->caps.n_channels < 1 || b->caps.n_channels > FW_BOARD_CHANNELS) b->caps.n_channels = 1;
    b->hal = *hal;
    b->state = FW_UNCONFIGURED;
    b->last_played = FW_NO_INDEX;
    b->stop_after = FW_NO_INDEX;
    b->watchdog_index = FW_NO_INDEX;
    b->now_us = now_us;
    b->last_rx_us = now_us;
    apply_codes(b);
}
