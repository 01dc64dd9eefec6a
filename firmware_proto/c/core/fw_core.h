/* The board side of the piezod protocol: a portable core over a small hardware layer.
 *
 * Threading model: fw_tick() is the sample-clock interrupt; everything else (fw_rx, fw_poll)
 * runs in the main loop. The main loop touches state shared with the tick only inside
 * FW_CRITICAL_BEGIN/END, which a port defines (e.g. __disable_irq / __enable_irq); the default
 * is empty, for ports that call fw_tick() from the main loop (the host build, the QEMU build).
 * No dynamic allocation: FW_FIFO_DEPTH and FW_SENSOR_RING size the static buffers. */
#ifndef FW_CORE_H
#define FW_CORE_H

#include "fw_codec.h"

#ifdef FW_PORT_HEADER /* a port's FW_CRITICAL_* and sizes, e.g. -DFW_PORT_HEADER='"stm32f4/port.h"' */
#include FW_PORT_HEADER
#endif

#ifndef FW_FIFO_DEPTH
#define FW_FIFO_DEPTH 16384u
#endif
#ifndef FW_SENSOR_RING
#define FW_SENSOR_RING 4096u
#endif
#ifndef FW_CRITICAL_BEGIN
#define FW_CRITICAL_BEGIN() ((void)0)
#define FW_CRITICAL_END() ((void)0)
#endif
#ifndef FW_BOARD_CHANNELS
#define FW_BOARD_CHANNELS FW_MAX_CHANNELS /* channels this build supports (sizes the buffers) */
#endif
#ifndef FW_SYNC_QUEUE
#define FW_SYNC_QUEUE 1024u /* sync events queued ahead (power of two, >= 1024 per PROTOCOL.md 4.14) */
#endif
#define FW_REPLY_CACHE 16u

/* What the board is: reported in CAPABILITIES. */
typedef struct fw_caps {
    uint8_t fw_major, fw_minor;
    uint16_t fw_patch;
    uint8_t n_channels, dac_bits, adc_bits;
    uint8_t sync_outputs; /* digital sync outputs driven from SYNC frames (0: none) */
    uint8_t no_position_sensor; /* 1: the ADC channels carry no position sensor (revision 2) */
    uint16_t max_samples_per_frame;
    uint32_t sample_rate_min_hz, sample_rate_max_hz, sample_clock_hz;
    uint32_t board_serial;
    float amp_v_min[FW_MAX_CHANNELS], amp_v_max[FW_MAX_CHANNELS];
} fw_caps;

/* The hardware layer. Every function is called from the context stated. */
typedef struct fw_hal {
    void *ctx;
    /* main loop: queue bytes for the host (the port buffers them; it may drop when no host). */
    void (*tx)(void *ctx, const uint8_t *data, size_t n);
    /* tick or main loop: apply one code per channel (left-justified i16) to the DACs. */
    void (*dac_write)(void *ctx, const int16_t *codes, unsigned n_channels);
    /* tick: convert the sensor of every channel into dst; the conversion may complete later
     * (DMA), but before the next fw_poll(). */
    void (*adc_read)(void *ctx, int16_t *dst, unsigned n_channels);
    /* main loop: start the sample timer at rate_hz (0: stop it). The first fw_tick() follows
     * one period after the start. */
    void (*timer)(void *ctx, uint32_t rate_hz);
    /* tick: set the digital sync outputs (bit 0 pixel, 1 line, 2 frame). May be NULL. */
    void (*sync_out)(void *ctx, uint8_t lines);
    /* main loop: one line of log text (may be NULL). */
    void (*log)(void *ctx, const char *text);
} fw_hal;

typedef struct fw_channel {
    float dac_v_per_code, dac_offset_v, ramp_v_per_s, adc_um_per_code, adc_offset_um;
    int16_t code_min, code_max, safe_code;
} fw_channel;

typedef struct fw_config {
    uint32_t sample_rate_hz, heartbeat_timeout_ms;
    uint16_t status_period_ms, sensor_decimation;
    uint8_t n_channels;
    fw_channel ch[FW_MAX_CHANNELS];
} fw_config;

typedef struct fw_counters {
    uint32_t crc_errors, frames_dropped, underruns, clamped_samples, index_gaps, overflows;
    uint32_t watchdog_trips, sensor_rows_lost, duplicate_requests;
    uint64_t samples_played;
} fw_counters;

typedef struct fw_reply {
    uint32_t seq;
    uint8_t type, len;
    uint8_t wire[32];
} fw_reply;

typedef struct fw_board {
    fw_hal hal;
    fw_caps caps;
    fw_config conf;
    bool configured, hello_seen;

    volatile uint8_t state;
    uint32_t fault_flags;
    fw_counters cnt;
    uint32_t tx_seq;

    /* FIFO of [play_index, write_index), C codes per row; clamped when stored */
    int16_t fifo[FW_FIFO_DEPTH][FW_BOARD_CHANNELS];
    uint64_t write_index, play_index, last_played, start_index, stop_after;
    uint32_t prefill;

    /* outputs */
    int16_t out_code[FW_MAX_CHANNELS];
    double ramp_pos[FW_MAX_CHANNELS];
    uint64_t ramp_last_us;

    /* sensor rows converted by the tick, sent by the main loop */
    int16_t sens[FW_SENSOR_RING][FW_BOARD_CHANNELS];
    uint64_t sens_index[FW_SENSOR_RING];
    volatile uint32_t sens_head, sens_tail; /* head: written by tick, tail: main loop */
    bool sens_deferred;             /* the port completes conversions later: fw_sensor_done() */
    volatile uint32_t sens_ready;   /* with sens_deferred: rows [.., sens_ready) are converted */
    uint64_t sens_flush_us;
    uint16_t sens_countdown;

    /* sync events: [sync_tail, sync_head) in index order; written by the main loop, read by the tick */
    uint64_t sync_index[FW_SYNC_QUEUE];
    uint8_t sync_lines[FW_SYNC_QUEUE], sync_mask[FW_SYNC_QUEUE];
    volatile uint32_t sync_head, sync_tail;
    uint64_t sync_last_queued;
    bool sync_any_queued;
    uint8_t sync_level;

    /* events raised in the tick for the main loop */
    volatile uint8_t ev_underrun, ev_stopped;

    /* timers (us of the caller's clock) */
    uint64_t now_us, last_rx_us, next_status_us, fault_sent_us[FW_N_FAULT_CODES + 1];
    bool wd_armed, status_due, fault_sent_valid[FW_N_FAULT_CODES + 1];
    uint64_t watchdog_index;

    /* receive buffer, transmit buffers, reply cache */
    uint8_t rx[FW_MAX_STUFFED];
    size_t rx_len;
    bool rx_skipping;
    uint8_t txf[FW_MAX_FRAME];
    uint8_t txw[FW_MAX_WIRE];
    fw_reply replies[FW_REPLY_CACHE];
    unsigned reply_next, reply_count;
} fw_board;

/* Power-up: state UNCONFIGURED, outputs at code 0 (written once through the HAL).
 * caps->n_channels must lie in [1, FW_BOARD_CHANNELS]. */
void fw_init(fw_board *b, const fw_caps *caps, const fw_hal *hal, uint64_t now_us);
/* The host's bytes (main loop). */
void fw_rx(fw_board *b, const uint8_t *data, size_t n, uint64_t now_us);
/* Timers: watchdog, ramps (>= 1 kHz when called often enough), STATUS, SENSOR, tick events. */
void fw_poll(fw_board *b, uint64_t now_us);
/* One tick of the sample clock (interrupt context). */
void fw_tick(fw_board *b);
/* With b->sens_deferred set (after fw_init), the port's adc_read only names the slot and the
 * port reports conversions complete, in tick order, with this (main loop). */
void fw_sensor_done(fw_board *b, uint32_t rows);
/* Most SENSOR / SAMPLES rows per frame for C channels. */
uint16_t fw_max_rows(unsigned n_channels);

#endif
