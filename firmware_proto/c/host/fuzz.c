/* Byte-level fuzz harness of the firmware core: never crash, never hang, never apply a sample
 * outside the configured limits, ramps only towards the safe code.
 *
 *   fw-fuzz --random N [--seed S]   N random cases generated here (xorshift)
 *   fw-fuzz < cases                 cases from stdin: u32 length + bytes, repeated (hypothesis)
 *   libFuzzer: build with -DFW_LIBFUZZER -fsanitize=fuzzer (LLVMFuzzerTestOneInput below)
 *
 * A case is a program of operations on a board that has been through HELLO / CONFIGURE / START:
 *   op & 3 == 0: feed the next k raw bytes (k = next byte)          -- random garbage, cut frames
 *   op & 3 == 1: advance the clock by (next byte) * 0.25 ms and poll -- watchdog, ramps, status
 *   op & 3 == 2: run (next byte) ticks of the sample clock
 *   op & 3 == 3: a well-framed frame (valid COBS + CRC) of type, flags, seq and payload taken from
 *                the next bytes, so the state machine itself is exercised, not only the CRC check
 * Every DAC write is checked; a violation prints the case and aborts (exit status != 0). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fw_core.h"

static fw_board board;
static uint64_t now;
static int in_tick;
static unsigned long long dac_checks, ticks_run;
static int16_t last_code[FW_MAX_CHANNELS];

static void fail(const char *why, unsigned c, int code) {
    fprintf(stderr, "VIOLATION: %s (channel %u, code %d, state %u)\n", why, c, code, (unsigned)board.state);
    abort();
}

static void tx(void *ctx, const uint8_t *d, size_t n) {
    (void)ctx;
    if (n == 0 || d[n - 1] != 0) fail("a frame without its delimiter", 0, (int)n);
}

static void dac(void *ctx, const int16_t *codes, unsigned C) {
    (void)ctx;
    dac_checks++;
    for (unsigned c = 0; c < C; c++) {
        if (!board.configured) {
            if (codes[c] != 0) fail("output moved before any configuration", c, codes[c]);
            continue;
        }
        const fw_channel *ch = &board.conf.ch[c];
        if (in_tick) {
            if (codes[c] < ch->code_min || codes[c] > ch->code_max) fail("sample outside the limits", c, codes[c]);
        } else {
            int before = abs(last_code[c] - ch->safe_code), after = abs(codes[c] - ch->safe_code);
            if (after > before) fail("ramp moved away from the safe code", c, codes[c]);
        }
        last_code[c] = codes[c];
    }
}

static void adc(void *ctx, int16_t *dst, unsigned C) {
    (void)ctx;
    for (unsigned c = 0; c < C; c++) dst[c] = (int16_t)(last_code[c] / 2);
}

static void timer(void *ctx, uint32_t r) { (void)ctx, (void)r; }

static void sync_out(void *ctx, uint8_t lines) {
    (void)ctx;
    if (lines & ~7u) fail("a sync output beyond the three advertised", 0, lines);
    if (!in_tick && lines) fail("sync outputs raised outside a tick", 0, lines);
}

static const fw_caps caps = {.fw_major = 1, .n_channels = 3, .dac_bits = 16, .adc_bits = 16, .sync_outputs = 3,
                             .max_samples_per_frame = 64, .sample_rate_min_hz = 1, .sample_rate_max_hz = 200000,
                             .sample_clock_hz = 0, .board_serial = 1,
                             .amp_v_min = {-150.0f, -150.0f, -10.0f}, .amp_v_max = {150.0f, 150.0f, 150.0f}};

static uint8_t frame[FW_MAX_FRAME], wire[FW_MAX_WIRE];
static uint32_t host_seq;

static void send_frame(uint8_t type, uint8_t flags, uint8_t version, const uint8_t *payload, size_t len) {
    if (len > FW_MAX_FRAME - 12) len = FW_MAX_FRAME - 12;
    frame[0] = version;
    frame[1] = type;
    frame[2] = flags;
    frame[3] = 0;
    fw_put_u32(frame + 4, host_seq++);
    memcpy(frame + 8, payload, len);
    size_t w = fw_finish_frame(frame, len, wire);
    fw_rx(&board, wire, w, now);
}

static void setup(void) {
    fw_hal hal = {.tx = tx, .dac_write = dac, .adc_read = adc, .timer = timer, .sync_out = sync_out};
    now = 1000;
    memset(last_code, 0, sizeof last_code);
    fw_init(&board, &caps, &hal, now);
    host_seq = 0;
    uint8_t p[8 + 16 + 3 * 32] = {0};
    fw_put_u16(p, 1);
    send_frame(FW_HELLO, 1, 1, p, 8);
    memset(p, 0, sizeof p);
    fw_put_u32(p, 10000);
    fw_put_u32(p + 4, 50);
    fw_put_u16(p + 8, 5);
    fw_put_u16(p + 10, 2);
    p[12] = 3;
    for (unsigned c = 0; c < 3; c++) {
        uint8_t *q = p + 16 + 32 * c;
        fw_put_f32(q, 300.0f / 65536.0f);
        fw_put_f32(q + 4, c == 2 ? 70.0f : 0.0f);
        int16_t lim = c == 2 ? 10000 : 20000;
        fw_put_u16(q + 8, (uint16_t)-lim);
        fw_put_u16(q + 10, (uint16_t)lim);
        fw_put_u16(q + 12, (uint16_t)(c == 2 ? -lim : 0));
        fw_put_f32(q + 16, 1000.0f);
        fw_put_f32(q + 20, 0.01f);
    }
    send_frame(FW_CONFIGURE, 1, 1, p, 16 + 3 * 32);
    for (int k = 0; k < 400 && board.state == FW_RAMPING; k++) now += 1000, fw_poll(&board, now);
    memset(p, 0, sizeof p);
    fw_put_u32(p + 8, 16);
    send_frame(FW_START, 1, 1, p, 16);
    if (board.state != FW_ARMED) fail("the harness's setup did not reach ARMED", 0, board.state);
}

static void run_case(const uint8_t *data, size_t n) {
    setup();
    size_t i = 0;
    while (i < n) {
        uint8_t op = data[i++];
        uint8_t arg = i < n ? data[i++] : 0;
        switch (op & 3u) {
        case 0: {
            size_t k = arg <= n - i ? arg : n - i;
            fw_rx(&board, data + i, k, now);
            i += k;
            break;
        }
        case 1:
            now += (uint64_t)arg * 250u;
            fw_poll(&board, now);
            break;
        case 2:
            in_tick = 1;
            for (unsigned t = 0; t < arg; t++) fw_tick(&board), ticks_run++;
            in_tick = 0;
            now += (uint64_t)arg * 100u; /* 10 kS/s */
            fw_poll(&board, now);
            break;
        default: {
            static const uint8_t types[] = {FW_HELLO, FW_CONFIGURE, FW_START, FW_STOP, FW_RAMP_TO_SAFE,
                                            FW_HEARTBEAT, FW_SAMPLES, FW_SAMPLES, FW_SAMPLES, FW_STATUS, FW_SYNC, FW_SYNC, 0x7f};
            uint8_t type = types[arg % sizeof types];
            uint8_t flags = (arg & 0x80u) ? 0 : 1;
            uint8_t version = (arg & 0x40u) && (op & 0x80u) ? 2 : 1;
            size_t len = i < n ? data[i++] : 0;
            if (type == FW_SAMPLES && (op & 0x40u)) {
                /* a plausible SAMPLES header: C = 3, N rows, first index near the write index */
                static uint8_t pl[12 + 2 * 3 * 128];
                uint16_t rows = (uint16_t)(len % 128u + 1u);
                fw_put_u64(pl, board.write_index + (uint64_t)(op >> 5 & 1u) * 3u);
                pl[8] = 3, pl[9] = 0;
                fw_put_u16(pl + 10, rows);
                for (size_t b = 0; b < 6u * rows; b++) pl[12 + b] = i < n ? data[i++] : (uint8_t)b;
                send_frame(type, 0, version, pl, 12u + 6u * rows);
            } else {
                size_t k = len <= n - i ? len : n - i;
                send_frame(type, flags, version, data + i, k);
                i += k;
            }
            break;
        }
        }
    }
}

#ifdef FW_LIBFUZZER
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    run_case(data, size);
    return 0;
}
#else
static uint64_t rng = 0x9E3779B97F4A7C15u;
static uint8_t next_byte(void) {
    rng ^= rng << 13, rng ^= rng >> 7, rng ^= rng << 17;
    return (uint8_t)(rng >> 24);
}

int main(int argc, char **argv) {
    static uint8_t buf[1 << 16];
    unsigned long cases = 0;
    if (argc >= 3 && !strcmp(argv[1], "--random")) {
        unsigned long n = strtoul(argv[2], NULL, 0);
        if (argc >= 5 && !strcmp(argv[3], "--seed")) rng ^= strtoull(argv[4], NULL, 0) * 0x2545F4914F6CDD1Du;
        for (; cases < n; cases++) {
            size_t len = 16u + next_byte() * 4u;
            for (size_t k = 0; k < len; k++) buf[k] = next_byte();
            run_case(buf, len);
        }
    } else {
        uint8_t head[4];
        while (fread(head, 1, 4, stdin) == 4) {
            size_t len = fw_get_u32(head);
            if (len > sizeof buf || fread(buf, 1, len, stdin) != len) return 2;
            run_case(buf, len);
            cases++;
        }
    }
    printf("cases %lu ticks %llu dac_checks %llu violations 0\n", cases, ticks_run, dac_checks);
    return 0;
}
#endif
