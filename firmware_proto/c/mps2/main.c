/* The reference firmware on an emulated Cortex-M3: QEMU's mps2-an385 (CMSDK UART0 = the link,
 * CMSDK TIMER0 = the time base: a free-running 32-bit counter at 25 MHz, read in the main loop,
 * so that ticks the emulator delays are caught up rather than lost, as interrupts would be). The sample clock is paced from SysTick in the main loop, as in the
 * host build; a simulated first-order stage (0.1 um/V, 1 ms lag) stands behind the DAC/ADC. */
#include <stdint.h>

#include "fw_core.h"

#define SYSCLK_HZ 25000000u
#define UART0_BASE 0x40004000u
#define UART_DATA (*(volatile uint32_t *)(UART0_BASE + 0x00u))
#define UART_STATE (*(volatile uint32_t *)(UART0_BASE + 0x04u))
#define UART_CTRL (*(volatile uint32_t *)(UART0_BASE + 0x08u))
#define UART_BAUDDIV (*(volatile uint32_t *)(UART0_BASE + 0x10u))
#define TIMER0_CTRL (*(volatile uint32_t *)0x40000000u)
#define TIMER0_VALUE (*(volatile uint32_t *)0x40000004u)
#define TIMER0_RELOAD (*(volatile uint32_t *)0x40000008u)

#define TX_RING 65536u

static fw_board board;
static uint64_t clock_ticks;
static uint32_t clock_last;
static uint8_t tx_ring[TX_RING];
static uint32_t tx_head, tx_tail, tx_dropped;
static uint32_t rate_hz;
static uint64_t t0_us, ticks_done;
static float volts[FW_BOARD_CHANNELS], pos_um[FW_BOARD_CHANNELS];
static float lag_alpha = 1.0f;

void systick_handler(void);
void systick_handler(void) {}

static uint64_t now_us(void) {
    uint32_t v = TIMER0_VALUE; /* counts down */
    clock_ticks += (uint32_t)(clock_last - v);
    clock_last = v;
    return clock_ticks / (SYSCLK_HZ / 1000000u);
}

static void hal_tx(void *ctx, const uint8_t *d, size_t n) {
    (void)ctx;
    if (TX_RING - (tx_head - tx_tail) < n) {
        tx_dropped++;
        return;
    }
    for (size_t i = 0; i < n; i++) tx_ring[(tx_head + i) & (TX_RING - 1u)] = d[i];
    tx_head += (uint32_t)n;
}

static void hal_dac(void *ctx, const int16_t *codes, unsigned C) {
    (void)ctx;
    for (unsigned c = 0; c < C; c++) {
        const fw_channel *ch = &board.conf.ch[c];
        volts[c] = board.configured ? ch->dac_offset_v + ch->dac_v_per_code * (float)codes[c] : 0.0f;
    }
}

static void hal_adc(void *ctx, int16_t *dst, unsigned C) {
    (void)ctx;
    for (unsigned c = 0; c < C; c++) {
        const fw_channel *ch = &board.conf.ch[c];
        pos_um[c] += (0.1f * volts[c] - pos_um[c]) * lag_alpha;
        float code = (pos_um[c] - ch->adc_offset_um) / ch->adc_um_per_code;
        dst[c] = (int16_t)(code > 32767.0f ? 32767 : code < -32768.0f ? -32768 : (int32_t)code);
    }
}

static void hal_timer(void *ctx, uint32_t rate) {
    (void)ctx;
    rate_hz = rate;
    t0_us = now_us();
    ticks_done = 0;
    if (rate) lag_alpha = 1000.0f / (float)rate > 1.0f ? 1.0f : 1000.0f / (float)rate;
}

int main(void) {
    UART_BAUDDIV = 16u;
    UART_CTRL = 3u; /* TX and RX enabled */
    TIMER0_RELOAD = 0xFFFFFFFFu;
    TIMER0_VALUE = 0xFFFFFFFFu;
    TIMER0_CTRL = 1u;
    clock_last = TIMER0_VALUE;
    static const fw_caps caps = {
        .fw_major = 1, .fw_minor = 0, .fw_patch = 0, .n_channels = FW_BOARD_CHANNELS, .dac_bits = 16,
        .adc_bits = 16, .sync_outputs = 3, .max_samples_per_frame = 500, .sample_rate_min_hz = 100,
        .sample_rate_max_hz = 100000, .sample_clock_hz = 1000000, .board_serial = 0x51A0E385u,
        .amp_v_min = {-230.0f, -230.0f, -230.0f}, .amp_v_max = {230.0f, 230.0f, 230.0f},
    };
    fw_hal hal = {.ctx = 0, .tx = hal_tx, .dac_write = hal_dac, .adc_read = hal_adc, .timer = hal_timer};
    fw_init(&board, &caps, &hal, now_us());
    static uint8_t rx[256];
    for (;;) {
        size_t n = 0;
        while (n < sizeof rx && (UART_STATE & 2u)) rx[n++] = (uint8_t)UART_DATA;
        uint64_t t = now_us();
        if (n) fw_rx(&board, rx, n, t);
        if (rate_hz && board.state == FW_RUNNING && t > t0_us) {
            uint64_t due = (t - t0_us) * rate_hz / 1000000u;
            while (ticks_done < due && board.state == FW_RUNNING) {
                fw_tick(&board);
                ticks_done++;
            }
        }
        fw_poll(&board, t);
        while (tx_tail != tx_head && !(UART_STATE & 1u)) {
            UART_DATA = tx_ring[tx_tail & (TX_RING - 1u)];
            tx_tail++;
        }
    }
}
