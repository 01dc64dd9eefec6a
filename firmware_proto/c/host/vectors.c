/* Checks the C codec and core against the test vectors of PROTOCOL.md section 10.
 * stdin: one vector per line, "NAME FRAME_HEX WIRE_HEX" (tests/test_firmware_c.py parses
 * PROTOCOL.md and writes them). stdout: "ok NAME CHECK" or "FAIL NAME CHECK: why"; exit 1 on
 * any failure. Built with FW_FIFO_DEPTH=16384 to match the CAPABILITIES vector. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fw_core.h"

#define MAXV 64
typedef struct vec {
    char name[48];
    uint8_t frame[FW_MAX_FRAME];
    size_t frame_len;
    uint8_t wire[FW_MAX_WIRE];
    size_t wire_len;
} vec;

static vec vecs[MAXV];
static int n_vecs, failures;
static uint8_t out[1 << 16];
static size_t out_len;
static fw_board board;

static void result(const char *name, const char *check, int ok, const char *why) {
    if (ok) printf("ok %s %s\n", name, check);
    else printf("FAIL %s %s: %s\n", name, check, why), failures++;
}

static size_t unhex(const char *s, uint8_t *dst, size_t cap) {
    size_t n = 0;
    while (s[0] && s[1] && n < cap) {
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1) break;
        dst[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static const vec *find(const char *name) {
    for (int i = 0; i < n_vecs; i++)
        if (!strcmp(vecs[i].name, name)) return &vecs[i];
    return NULL;
}

static void tx(void *ctx, const uint8_t *d, size_t n) {
    (void)ctx;
    if (out_len + n <= sizeof out) memcpy(out + out_len, d, n), out_len += n;
}
static void dac(void *ctx, const int16_t *c, unsigned n) { (void)ctx, (void)c, (void)n; }
static void adc(void *ctx, int16_t *c, unsigned n) { (void)ctx, memset(c, 0, 2 * n); }
static void timer(void *ctx, uint32_t r) { (void)ctx, (void)r; }

static uint64_t sync_at[16];
static uint8_t sync_to[16];
static unsigned n_sync;
static void sync_out(void *ctx, uint8_t lines) {
    (void)ctx;
    if (n_sync < 16) sync_at[n_sync] = board.last_played, sync_to[n_sync++] = lines;
}

static void new_board(float ch1_lo) {
    fw_caps caps = {.fw_major = 1, .fw_minor = 2, .fw_patch = 3, .n_channels = 3, .dac_bits = 16,
                    .adc_bits = 16, .max_samples_per_frame = 1024, .sample_rate_min_hz = 1000,
                    .sample_rate_max_hz = 200000, .sample_clock_hz = 0, .board_serial = 12648430,
                    .amp_v_min = {-150.0f, ch1_lo, -10.0f}, .amp_v_max = {150.0f, 150.0f, 150.0f}};
    fw_hal hal = {.tx = tx, .dac_write = dac, .adc_read = adc, .timer = timer, .sync_out = sync_out};
    fw_init(&board, &caps, &hal, 0);
    out_len = 0;
}

/* Revision 1: SYNC events drive the outputs at their sample's tick (PROTOCOL.md 4.14). */
static void sync_check(void) {
    const vec *hello = find("HELLO"), *conf = find("CONFIGURE"), *start = find("START"), *sync = find("SYNC");
    if (!hello || !conf || !start || !sync) {
        result("SYNC", "outputs-follow-events", 0, "vector missing");
        return;
    }
    new_board(-150.0f);
    board.caps.sync_outputs = 3;
    fw_rx(&board, hello->wire, hello->wire_len, 1000);
    fw_rx(&board, conf->wire, conf->wire_len, 2000);
    const vec *hb = find("HEARTBEAT");
    uint64_t t = 3000;
    for (; t < 3000000 && board.state != FW_IDLE; t += 1000)
        hb ? fw_rx(&board, hb->wire, hb->wire_len, t) : fw_poll(&board, t);
    /* START at 20000 with prefill 20 (the START vector starts at 0: build our own frame) */
    static uint8_t f[FW_MAX_FRAME], w[FW_MAX_WIRE];
    memset(f, 0, 8 + 16);
    f[0] = 1, f[1] = FW_START, f[2] = 1, f[4] = 40;
    fw_put_u64(f + 8, 20000);
    fw_put_u32(f + 16, 20);
    fw_rx(&board, w, fw_finish_frame(f, 16, w), t + 1);
    fw_rx(&board, sync->wire, sync->wire_len, t + 2);
    memset(f, 0, sizeof f);
    f[0] = 1, f[1] = FW_SAMPLES, f[4] = 41;
    fw_put_u64(f + 8, 20000);
    f[16] = 3;
    fw_put_u16(f + 18, 20);
    fw_rx(&board, w, fw_finish_frame(f, 12 + 6 * 20, w), t + 3);
    n_sync = 0;
    for (int k = 0; k < 21; k++) fw_tick(&board); /* the 21st underruns */
    fw_poll(&board, t + 4);
    static const uint64_t want_at[] = {20000, 20005, 20010, 20015};
    static const uint8_t want_to[] = {7, 0, 1, 0};
    int ok = board.state == FW_IDLE && n_sync == 4;
    for (unsigned k = 0; ok && k < 4; k++) ok = sync_at[k] == want_at[k] && sync_to[k] == want_to[k];
    if (!ok) fprintf(stderr, "sync: state %u n %u first %llu->%u\n", (unsigned)board.state, n_sync, (unsigned long long)sync_at[0], sync_to[0]);
    result("SYNC", "outputs-follow-events", ok, "sync transitions differ from the vector's events");
}

/* Feed vector `in` to the board (tx_seq preset) and compare the first frame out with `want`. */
static void reply_check(const char *in, const char *want, uint32_t tx_seq) {
    const vec *a = find(in), *b = find(want);
    char check[64];
    snprintf(check, sizeof check, "reply-to-%s", in);
    if (!a || !b) {
        result(want, check, 0, "vector missing from PROTOCOL.md");
        return;
    }
    board.tx_seq = tx_seq;
    out_len = 0;
    fw_rx(&board, a->wire, a->wire_len, 1000);
    size_t first = 0;
    while (first < out_len && out[first] != 0) first++;
    int ok = out_len > first && first + 1 == b->wire_len && !memcmp(out, b->wire, b->wire_len);
    result(want, check, ok, "the core's reply differs from the vector");
}

int main(void) {
    static char line[3 * FW_MAX_WIRE + 3 * FW_MAX_FRAME + 128];
    while (n_vecs < MAXV && fgets(line, sizeof line, stdin)) {
        char *name = strtok(line, " \n"), *f = strtok(NULL, " \n"), *w = strtok(NULL, " \n");
        if (!name || !f || !w) continue;
        vec *v = &vecs[n_vecs++];
        snprintf(v->name, sizeof v->name, "%s", name);
        v->frame_len = unhex(f, v->frame, sizeof v->frame);
        v->wire_len = unhex(w, v->wire, sizeof v->wire);
    }
    result("CRC", "check-value", fw_crc32_update(0, (const uint8_t *)"123456789", 9) == 0xCBF43926u, "crc");
    for (int i = 0; i < n_vecs; i++) {
        vec *v = &vecs[i];
        static uint8_t buf[FW_MAX_WIRE];
        size_t n = fw_cobs_encode(v->frame, v->frame_len, buf);
        buf[n++] = 0;
        result(v->name, "cobs-encode", n == v->wire_len && !memcmp(buf, v->wire, n), "stuffed bytes differ");
        memcpy(buf, v->wire, v->wire_len);
        long d = fw_cobs_decode(buf, v->wire_len - 1);
        result(v->name, "cobs-decode", d == (long)v->frame_len && !memcmp(buf, v->frame, v->frame_len),
               "decoded bytes differ");
        result(v->name, "frame-checks", fw_check_frame(v->frame, v->frame_len) == FW_DEC_OK, "a check failed");
        uint32_t crc = fw_crc32_update(0, v->frame, v->frame_len - 4);
        result(v->name, "crc", crc == fw_get_u32(v->frame + v->frame_len - 4), "CRC differs");
    }
    new_board(-150.0f);
    reply_check("HELLO", "CAPABILITIES", 0);
    reply_check("CONFIGURE", "ACK", 1);
    new_board(-150.0f);
    reply_check("HELLO_V2", "NAK_VERSION_MISMATCH", 3);
    new_board(-150.0f);
    board.caps.sync_outputs = 3;
    reply_check("HELLO", "CAPABILITIES_SYNC", 0);
    sync_check();
    new_board(-150.0f);
    board.caps.no_position_sensor = 1;
    reply_check("HELLO", "CAPABILITIES_NO_SENSOR", 0);
    new_board(-100.0f); /* channel 1's amplifier starts above the vector's code_min: refused at 64 */
    const vec *hello = find("HELLO");
    if (hello) fw_rx(&board, hello->wire, hello->wire_len, 500);
    reply_check("CONFIGURE", "NAK_BAD_VALUE", 2);
    return failures ? 1 : 0;
}
