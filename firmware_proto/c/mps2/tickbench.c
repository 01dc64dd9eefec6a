/* Instructions per sample of the firmware core, measured under QEMU with -icount shift=0 (one
 * instruction per nanosecond of virtual time, read from the 25 MHz CMSDK timer): a configured
 * board with a full FIFO runs N ticks (DAC write + ADC read through a minimal HAL, sensor rows,
 * SENSOR frames built by fw_poll every 64 ticks). Prints one line on UART0 and halts. */
#include <stdint.h>
#include <string.h>

#include "fw_core.h"

#define UART_DATA (*(volatile uint32_t *)0x40004000u)
#define UART_STATE (*(volatile uint32_t *)0x40004004u)
#define UART_CTRL (*(volatile uint32_t *)0x40004008u)
#define UART_BAUDDIV (*(volatile uint32_t *)0x40004010u)
#define TIMER0_CTRL (*(volatile uint32_t *)0x40000000u)
#define TIMER0_VALUE (*(volatile uint32_t *)0x40000004u)
#define TIMER0_RELOAD (*(volatile uint32_t *)0x40000008u)

void systick_handler(void);
void systick_handler(void) {}

static fw_board board;
static volatile int16_t dac_out[3];
static uint32_t seq;
static uint8_t frame[FW_MAX_FRAME], wire[FW_MAX_WIRE];

static void tx(void *c, const uint8_t *d, size_t n) { (void)c, (void)d, (void)n; }
static void dac(void *c, const int16_t *codes, unsigned n) {
    (void)c;
    for (unsigned k = 0; k < n; k++) dac_out[k] = codes[k];
}
static void adc(void *c, int16_t *dst, unsigned n) {
    (void)c;
    for (unsigned k = 0; k < n; k++) dst[k] = dac_out[k];
}
static void timer(void *c, uint32_t r) { (void)c, (void)r; }

static void put(const char *s) {
    for (; *s; s++) {
        while (UART_STATE & 1u) {
        }
        UART_DATA = (uint8_t)*s;
    }
}

static void put_u(uint32_t v) {
    char b[12];
    int i = 11;
    b[i] = 0;
    do b[--i] = (char)('0' + v % 10u), v /= 10u;
    while (v);
    put(b + i);
}

static void send(uint8_t type, const uint8_t *p, size_t len, uint64_t now) {
    frame[0] = 1, frame[1] = type, frame[2] = 1, frame[3] = 0;
    fw_put_u32(frame + 4, seq++);
    memcpy(frame + 8, p, len);
    size_t w = fw_finish_frame(frame, len, wire);
    fw_rx(&board, wire, w, now);
}

static uint32_t elapsed_insns(uint32_t t0) { return (t0 - TIMER0_VALUE) * 40u; /* 25 MHz, 1 insn/ns */ }

int main(void) {
    UART_BAUDDIV = 16u;
    UART_CTRL = 3u;
    TIMER0_RELOAD = 0xFFFFFFFFu;
    TIMER0_VALUE = 0xFFFFFFFFu;
    TIMER0_CTRL = 1u;
    static const fw_caps caps = {.n_channels = 3, .dac_bits = 16, .adc_bits = 16, .max_samples_per_frame = 500,
                                 .sample_rate_min_hz = 1, .sample_rate_max_hz = 200000,
                                 .amp_v_min = {-150.0f, -150.0f, -150.0f}, .amp_v_max = {150.0f, 150.0f, 150.0f}};
    fw_hal hal = {.tx = tx, .dac_write = dac, .adc_read = adc, .timer = timer};
    fw_init(&board, &caps, &hal, 0);
    static uint8_t p[16 + 3 * 32 + 12 + 6 * 1300];
    memset(p, 0, sizeof p);
    fw_put_u16(p, 1);
    send(FW_HELLO, p, 8, 1);
    memset(p, 0, sizeof p);
    fw_put_u32(p, 100000), fw_put_u32(p + 4, 60000), fw_put_u16(p + 8, 10), fw_put_u16(p + 10, 1);
    p[12] = 3;
    for (unsigned c = 0; c < 3; c++) {
        uint8_t *q = p + 16 + 32 * c;
        fw_put_f32(q, 300.0f / 65536.0f), fw_put_u16(q + 8, (uint16_t)-30000), fw_put_u16(q + 10, 30000);
        fw_put_f32(q + 16, 1e6f), fw_put_f32(q + 20, 0.001f);
    }
    send(FW_CONFIGURE, p, 16 + 3 * 32, 2);
    fw_poll(&board, 100000);
    memset(p, 0, 16);
    fw_put_u32(p + 8, 1000);
    send(FW_START, p, 16, 100001);
    const uint32_t rows = 1300, runs = 12; /* 15600 ticks, FIFO refilled between runs */
    uint32_t tick_insns = 0, rx_insns = 0, poll_insns = 0, ticks = 0;
    for (uint32_t r = 0; r < runs; r++) {
        memset(p, 0, 12);
        fw_put_u64(p, board.write_index);
        p[8] = 3;
        fw_put_u16(p + 10, (uint16_t)rows);
        for (uint32_t j = 0; j < rows * 3u; j++) fw_put_u16(p + 12 + 2 * j, (uint16_t)(int16_t)((j * 37u) % 50000u - 25000));
        uint32_t t0 = TIMER0_VALUE;
        send(FW_SAMPLES, p, 12 + 6 * rows, 100002 + r);
        rx_insns += elapsed_insns(t0);
        for (uint32_t j = 0; j < rows; j++) {
            t0 = TIMER0_VALUE;
            fw_tick(&board);
            tick_insns += elapsed_insns(t0);
            ticks++;
            if (j % 64u == 63u) {
                t0 = TIMER0_VALUE;
                fw_poll(&board, 100100u + ticks * 10u);
                poll_insns += elapsed_insns(t0);
            }
        }
    }
    put("ticks ");
    put_u(ticks);
    put(" insns_per_tick ");
    put_u(tick_insns / ticks);
    put(" insns_per_sample_received ");
    put_u(rx_insns / ticks);
    put(" insns_per_sample_polled ");
    put_u(poll_insns / ticks);
    put(" clamped ");
    put_u(board.cnt.clamped_samples);
    put(" state ");
    put_u(board.state);
    put("\n");
    for (;;) {
    }
}
