/* The reference firmware on a real board: STM32F405 (Cortex-M4F, 168 MHz) with
 *  - 3 x AD5791 20-bit DACs on SPI1 (daisy-chained, one /SYNC, common /LDAC) -> HV amplifiers,
 *  - an AD7606B simultaneous-sampling 16-bit ADC on SPI2 (CONVST from TIM2, BUSY, /CS) <- sensors,
 *  - USART1 at 6 Mbaud to an FT232H-class USB bridge (the link),
 *  - the HV amplifier's /ENABLE output and /FAULT input, three sync outputs (pixel, line, frame).
 * Pin map and wiring: docs/hardware.md. Register-level code (no vendor HAL), so it builds with
 * Debian's gcc-arm-none-eabi alone.
 *
 * Timing per sample (TIM2 update interrupt, priority 0): write the three DAC words for this tick
 * (the /LDAC pulse of the previous tick applied them at the tick edge), read the ADC conversion
 * that TIM2's CONVST started at this tick edge, hand both to fw_tick(). USART1 RX is an interrupt
 * into a ring; the main loop runs fw_rx / fw_poll and drains TX with the USART's TXE interrupt. */
#include <stdint.h>

#include "fw_core.h"

#define SYSCLK_HZ 168000000u
#define REG(addr) (*(volatile uint32_t *)(addr))

/* RCC */
#define RCC_CR REG(0x40023800u)
#define RCC_PLLCFGR REG(0x40023804u)
#define RCC_CFGR REG(0x40023808u)
#define RCC_AHB1ENR REG(0x40023830u)
#define RCC_APB1ENR REG(0x40023840u)
#define RCC_APB2ENR REG(0x40023844u)
#define FLASH_ACR REG(0x40023C00u)
/* GPIO A, B, C */
#define GPIO(port, off) REG(0x40020000u + 0x400u * (port) + (off))
#define MODER 0x00u
#define OSPEEDR 0x08u
#define IDR 0x10u
#define BSRR 0x18u
#define AFRL 0x20u
#define AFRH 0x24u
#define PA 0u
#define PB 1u
#define PC 2u
/* SPI1 (DACs), SPI2 (ADC) */
#define SPI_CR1(n) REG((n) == 1 ? 0x40013000u : 0x40003800u)
#define SPI_SR(n) REG(((n) == 1 ? 0x40013000u : 0x40003800u) + 0x08u)
#define SPI_DR(n) REG(((n) == 1 ? 0x40013000u : 0x40003800u) + 0x0Cu)
/* USART1 */
#define USART1_SR REG(0x40011000u)
#define USART1_DR REG(0x40011004u)
#define USART1_BRR REG(0x40011008u)
#define USART1_CR1 REG(0x4001100Cu)
/* TIM2 (sample clock, CONVST on CH1 = PA0... see docs/hardware.md) */
#define TIM2_CR1 REG(0x40000000u)
#define TIM2_DIER REG(0x4000000Cu)
#define TIM2_SR REG(0x40000010u)
#define TIM2_CCMR1 REG(0x40000018u)
#define TIM2_CCER REG(0x40000020u)
#define TIM2_PSC REG(0x40000028u)
#define TIM2_ARR REG(0x4000002Cu)
#define TIM2_CCR1 REG(0x40000034u)
/* SysTick: 1 ms, and DWT cycle counter for the cycle budget */
#define SYST_CSR REG(0xE000E010u)
#define SYST_RVR REG(0xE000E014u)
#define DWT_CTRL REG(0xE0001000u)
#define DWT_CYCCNT REG(0xE0001004u)
#define DEMCR REG(0xE000EDFCu)
#define NVIC_ISER0 REG(0xE000E100u)
#define NVIC_ISER1 REG(0xE000E104u)
#define IRQ_TIM2 28u
#define IRQ_USART1 37u

/* pins (docs/hardware.md): */
#define PIN_DAC_SYNC 4u   /* PA4  AD5791 /SYNC (daisy chain)    */
#define PIN_DAC_LDAC 3u   /* PA3  AD5791 /LDAC (all three)      */
#define PIN_ADC_CS 12u    /* PB12 AD7606B /CS                    */
#define PIN_ADC_BUSY 1u   /* PB1  AD7606B BUSY (input)           */
#define PIN_AMP_EN 6u     /* PC6  HV amplifier /ENABLE (low = on) */
#define PIN_AMP_FAULT 7u  /* PC7  HV amplifier /FAULT (input)     */
#define PIN_SYNC0 8u      /* PC8..PC10: pixel, line, frame clocks */

static fw_board board;
static volatile uint64_t ms;
static uint8_t rx_ring[4096], tx_ring[16384];
static volatile uint32_t rx_head, rx_tail, tx_head, tx_tail;
static int16_t dac_pending[3];
static volatile uint32_t tick_cycles_max, tick_cycles_last;

void systick_handler(void);
void tim2_handler(void);
void usart1_handler(void);

void systick_handler(void) { ms++; }

extern uint32_t _estack;
void reset_handler(void);
void default_handler(void);
/* Cortex-M4 system vectors + STM32F405 IRQs 0..81 (TIM2 = 28, USART1 = 37) */
__attribute__((section(".vectors"), used)) static void (*const vectors[16 + 82])(void) = {
    [0] = (void (*)(void))(&_estack), [1] = reset_handler, [2 ... 14] = default_handler,
    [15] = systick_handler, [16 ... 16 + 27] = default_handler, [16 + 28] = tim2_handler,
    [16 + 29 ... 16 + 36] = default_handler, [16 + 37] = usart1_handler, [16 + 38 ... 97] = default_handler,
};

static uint64_t now_us(void) {
    uint64_t a;
    FW_CRITICAL_BEGIN();
    a = ms;
    FW_CRITICAL_END();
    return a * 1000u;
}

static uint32_t spi_xfer16(unsigned n, uint16_t v) {
    while (!(SPI_SR(n) & 2u)) {
    }
    SPI_DR(n) = v;
    while (!(SPI_SR(n) & 1u)) {
    }
    return SPI_DR(n);
}

/* AD5791 write: 24-bit word 0b0001 (DAC register) + 20-bit two's-complement code; the i16
 * code is left-justified: code << 4. Daisy chain: the last DAC's word goes first. */
static void hal_dac(void *ctx, const int16_t *codes, unsigned C) {
    (void)ctx;
    for (unsigned c = 0; c < C && c < 3; c++) dac_pending[c] = codes[c];
    GPIO(PA, BSRR) = 1u << (PIN_DAC_SYNC + 16u);
    for (int c = 2; c >= 0; c--) {
        uint32_t w = (1u << 20) | (((uint32_t)(int32_t)dac_pending[c] << 4) & 0xFFFFFu);
        spi_xfer16(1, (uint16_t)(w >> 8));
        spi_xfer16(1, (uint16_t)((w & 0xFFu) << 8)); /* 8 bits used, 8 padding (DACs ignore after /SYNC) */
    }
    GPIO(PA, BSRR) = 1u << PIN_DAC_SYNC;
    GPIO(PA, BSRR) = 1u << (PIN_DAC_LDAC + 16u); /* /LDAC pulse: all three outputs update together */
    GPIO(PA, BSRR) = 1u << PIN_DAC_LDAC;
}

/* AD7606B: CONVST was started by TIM2 CH1 at the tick edge; wait for BUSY low, read V1..V3. */
static void hal_adc(void *ctx, int16_t *dst, unsigned C) {
    (void)ctx;
    while (GPIO(PB, IDR) & (1u << PIN_ADC_BUSY)) {
    }
    GPIO(PB, BSRR) = 1u << (PIN_ADC_CS + 16u);
    for (unsigned c = 0; c < C; c++) dst[c] = (int16_t)spi_xfer16(2, 0);
    GPIO(PB, BSRR) = 1u << PIN_ADC_CS;
}

static void hal_sync(void *ctx, uint8_t lines) {
    (void)ctx;
    GPIO(PC, BSRR) = ((uint32_t)(lines & 7u) << PIN_SYNC0) | ((uint32_t)(~lines & 7u) << (PIN_SYNC0 + 16u));
}

static void hal_timer(void *ctx, uint32_t rate) {
    (void)ctx;
    TIM2_CR1 = 0;
    if (!rate) return;
    TIM2_PSC = 0;
    TIM2_ARR = SYSCLK_HZ / 2u / rate - 1u; /* TIM2 runs at 84 MHz; exact rates divide it */
    TIM2_CCR1 = 1u;                         /* CONVST pulse right after the update */
    TIM2_SR = 0;
    TIM2_CR1 = 1u;
}

static void hal_tx(void *ctx, const uint8_t *d, size_t n) {
    (void)ctx;
    if (sizeof tx_ring - (tx_head - tx_tail) < n) return; /* counted by the host as lost frames */
    for (size_t i = 0; i < n; i++) tx_ring[(tx_head + i) % sizeof tx_ring] = d[i];
    tx_head += (uint32_t)n;
    USART1_CR1 |= 1u << 7; /* TXEIE */
}

void tim2_handler(void) {
    uint32_t t0 = DWT_CYCCNT;
    TIM2_SR = 0;
    fw_tick(&board);
    tick_cycles_last = DWT_CYCCNT - t0;
    if (tick_cycles_last > tick_cycles_max) tick_cycles_max = tick_cycles_last;
}

void usart1_handler(void) {
    uint32_t sr = USART1_SR;
    if (sr & (1u << 5)) { /* RXNE */
        uint8_t b = (uint8_t)USART1_DR;
        if (rx_head - rx_tail < sizeof rx_ring) rx_ring[rx_head++ % sizeof rx_ring] = b;
    }
    if ((sr & (1u << 7)) && (USART1_CR1 & (1u << 7))) { /* TXE */
        if (tx_tail != tx_head) USART1_DR = tx_ring[tx_tail++ % sizeof tx_ring];
        else USART1_CR1 &= ~(1u << 7);
    }
}

static void clocks(void) {
    RCC_CR |= 1u << 16; /* HSE 8 MHz */
    while (!(RCC_CR & (1u << 17))) {
    }
    /* PLL: 8 MHz / 8 * 336 / 2 = 168 MHz, /7 = 48 MHz (USB) */
    RCC_PLLCFGR = 8u | (336u << 6) | (0u << 16) | (1u << 22) | (7u << 24);
    RCC_CR |= 1u << 24;
    while (!(RCC_CR & (1u << 25))) {
    }
    FLASH_ACR = 5u | (1u << 8) | (1u << 9) | (1u << 10); /* 5 wait states, prefetch, caches */
    RCC_CFGR = (5u << 10) | (4u << 13) | 2u;              /* APB1 /4, APB2 /2, SYSCLK = PLL */
    while ((RCC_CFGR & 0xCu) != 0x8u) {
    }
}

static void gpio_mode(uint32_t port, unsigned pin, uint32_t mode, uint32_t af) {
    GPIO(port, MODER) = (GPIO(port, MODER) & ~(3u << (2 * pin))) | (mode << (2 * pin));
    GPIO(port, OSPEEDR) |= 3u << (2 * pin);
    if (mode == 2u) {
        volatile uint32_t *afr = pin < 8 ? &GPIO(port, AFRL) : &GPIO(port, AFRH);
        *afr = (*afr & ~(0xFu << (4 * (pin % 8)))) | (af << (4 * (pin % 8)));
    }
}

int main(void) {
    clocks();
    RCC_AHB1ENR |= 7u;                       /* GPIOA..C */
    RCC_APB2ENR |= (1u << 4) | (1u << 12);   /* USART1, SPI1 */
    RCC_APB1ENR |= (1u << 0) | (1u << 14);   /* TIM2, SPI2 */
    DEMCR |= 1u << 24;
    DWT_CYCCNT = 0;
    DWT_CTRL |= 1u;
    /* SPI1: PA5 SCK, PA7 MOSI, PA6 MISO (AF5); SPI2: PB13 SCK, PB14 MISO, PB15 MOSI (AF5) */
    gpio_mode(PA, 5, 2, 5), gpio_mode(PA, 6, 2, 5), gpio_mode(PA, 7, 2, 5);
    gpio_mode(PB, 13, 2, 5), gpio_mode(PB, 14, 2, 5), gpio_mode(PB, 15, 2, 5);
    gpio_mode(PA, 9, 2, 7), gpio_mode(PA, 10, 2, 7); /* USART1 TX, RX */
    gpio_mode(PA, 0, 2, 1);                           /* TIM2_CH1 -> AD7606B CONVST */
    gpio_mode(PA, PIN_DAC_SYNC, 1, 0), gpio_mode(PA, PIN_DAC_LDAC, 1, 0);
    gpio_mode(PB, PIN_ADC_CS, 1, 0), gpio_mode(PB, PIN_ADC_BUSY, 0, 0);
    gpio_mode(PC, PIN_AMP_EN, 1, 0), gpio_mode(PC, PIN_AMP_FAULT, 0, 0);
    for (unsigned k = 0; k < 3; k++) gpio_mode(PC, PIN_SYNC0 + k, 1, 0);
    GPIO(PA, BSRR) = (1u << PIN_DAC_SYNC) | (1u << PIN_DAC_LDAC);
    GPIO(PB, BSRR) = 1u << PIN_ADC_CS;
    GPIO(PC, BSRR) = 1u << PIN_AMP_EN; /* amplifier disabled until the DACs hold a valid code */
    /* SPI1: master, CPHA=1 (AD5791 samples on the falling edge), 16-bit, 84 MHz / 4 = 21 MHz */
    SPI_CR1(1) = (1u << 0) | (1u << 2) | (1u << 3) | (1u << 8) | (1u << 9) | (1u << 11) | (1u << 6);
    /* SPI2: master, CPOL=1, 16-bit, 42 MHz / 2 = 21 MHz (AD7606B: 50 MHz max) */
    SPI_CR1(2) = (1u << 1) | (1u << 2) | (1u << 8) | (1u << 9) | (1u << 11) | (1u << 6);
    /* AD5791 control register (address 0b0010): RBUF=1, OPGND=0, DACTRI=0, BIN/2sC=0, SDODIS=1 */
    GPIO(PA, BSRR) = 1u << (PIN_DAC_SYNC + 16u);
    for (int c = 0; c < 3; c++) spi_xfer16(1, (uint16_t)((2u << 12) | 0x0022u >> 8)), spi_xfer16(1, 0x2200u);
    GPIO(PA, BSRR) = 1u << PIN_DAC_SYNC;
    USART1_BRR = (7u << 4) | 0u; /* 84 MHz / (8 * 1.75) = 6 Mbaud with OVER8 */
    USART1_CR1 = (1u << 15) | (1u << 13) | (1u << 5) | (1u << 3) | (1u << 2); /* OVER8 UE RXNEIE TE RE */
    /* TIM2 CH1 PWM1: CONVST high for one timer count after each update */
    TIM2_CCMR1 = 6u << 4;
    TIM2_CCER = 1u;
    TIM2_DIER = 1u;
    NVIC_ISER0 = 1u << IRQ_TIM2;
    NVIC_ISER1 = 1u << (IRQ_USART1 - 32u);
    SYST_RVR = SYSCLK_HZ / 1000u - 1u;
    SYST_CSR = 7u;
    static const fw_caps caps = {
        .fw_major = 1, .fw_minor = 0, .fw_patch = 0, .n_channels = 3, .dac_bits = 16, .adc_bits = 16, .sync_outputs = 3,
        .max_samples_per_frame = 500, .sample_rate_min_hz = 100, .sample_rate_max_hz = 100000,
        .sample_clock_hz = SYSCLK_HZ / 2u, .board_serial = 0x51A0F405u,
        .amp_v_min = {-150.0f, -150.0f, -10.0f}, .amp_v_max = {150.0f, 150.0f, 150.0f},
    };
    fw_hal hal = {.tx = hal_tx, .dac_write = hal_dac, .adc_read = hal_adc, .timer = hal_timer,
                  .sync_out = hal_sync};
    fw_init(&board, &caps, &hal, now_us());
    GPIO(PC, BSRR) = 1u << (PIN_AMP_EN + 16u); /* DACs at code 0 (0 V): enable the amplifier */
    static uint8_t chunk[256];
    for (;;) {
        size_t n = 0;
        while (n < sizeof chunk && rx_tail != rx_head) chunk[n++] = rx_ring[rx_tail++ % sizeof rx_ring];
        uint64_t t = now_us();
        if (n) fw_rx(&board, chunk, n, t);
        else fw_poll(&board, t);
        if (!(GPIO(PC, IDR) & (1u << PIN_AMP_FAULT))) GPIO(PC, BSRR) = 1u << PIN_AMP_EN; /* latch off */
    }
}
