/* STM32F4 port of the firmware core: fw_tick() runs in the TIM2 interrupt, so the main loop's
 * accesses to state shared with it mask interrupts (for well under a microsecond). */
#ifndef FW_PORT_STM32F4_H
#define FW_PORT_STM32F4_H
#define FW_CRITICAL_BEGIN() __asm volatile("cpsid i" ::: "memory")
#define FW_CRITICAL_END() __asm volatile("cpsie i" ::: "memory")
#define FW_BOARD_CHANNELS 3u
#define FW_FIFO_DEPTH 8192u /* 117 ms at 70 kS/s: the 100 ms lead plus slack */
#define FW_SENSOR_RING 1024u
#endif
