/* cochlea's HAL (embedded/core/cochlea_rt.h) on an STM32F405/407 at the register level:
 * the clocks, SysTick as the period timer and the 64-bit nanosecond clock, USART1 as the
 * Dynamixel bus (an interrupt receive ring; writes wait for transmission complete), USART2
 * as a polled console, the RS-485 direction pin and the independent watchdog.
 * docs/embedded.md, "STM32F4 port", says what each does on a board and under QEMU. */
#ifndef COCHLEA_HAL_STM32F4_H
#define COCHLEA_HAL_STM32F4_H

#include <stdint.h>

#include "cochlea_rt.h"

/* The core clock the port runs at (Hz): the PLL's 168 MHz from an HSE of STM32_HSE_HZ, the
 * rate QEMU's netduinoplus2 machine also gives its STM32F405. */
#ifndef STM32_SYSCLK_HZ
#define STM32_SYSCLK_HZ 168000000u
#endif
#ifndef STM32_HSE_HZ
#define STM32_HSE_HZ 8000000u /* the crystal (STM32F4-Discovery: 8 MHz) */
#endif
#define STM32_APB1_HZ (STM32_SYSCLK_HZ / 4u) /* USART2 */
/* TIM2's counting clock (Hz): APB1's timer clock, twice APB1 when APB1 is divided (RM0090
 * section 7.2): 84 MHz. QEMU's model counts at a fixed 1 GHz of its virtual clock instead
 * (measured; its "clock-frequency"), so a build for QEMU sets 1000000000. */
#ifndef STM32_TIMER_HZ
#define STM32_TIMER_HZ (2u * STM32_APB1_HZ)
#endif
#define STM32_APB2_HZ (STM32_SYSCLK_HZ / 2u) /* USART1 */
/* The receive ring (bytes, a power of two): several periods of status packets. */
#define STM32_RX_RING 1024u

/* What stm32f4_clock_init found. */
enum stm32f4_clock {
    STM32F4_CLOCK_PLL = 0,        /* HSE and PLL locked, 168 MHz */
    STM32F4_CLOCK_UNMODELLED = 1, /* RCC reads 0 (impossible on silicon, where HSION and
                                   * HSIRDY are 1 while the HSI clocks the core): an emulator
                                   * without an RCC model, whose clock is the machine's */
    STM32F4_CLOCK_NO_HSE = 2,     /* the crystal did not start: nothing may run */
    STM32F4_CLOCK_NO_PLL = 3      /* the PLL did not lock or was not selected */
};

typedef struct {
    volatile uint8_t ring[STM32_RX_RING];
    volatile uint32_t head;      /* written by the interrupt only */
    volatile uint32_t tail;      /* written by the loop only */
    volatile uint32_t overflows; /* bytes dropped on a full ring */
    uint32_t baud;
} stm32f4_uart;

/* Clocks (bounded waits: a part that does not lock is reported, never waited on for ever). */
int stm32f4_clock_init(void);
/* The clock (TIM2, 64-bit), SysTick's period, the sleep and the independent watchdog are the
 * STM32 ports' shared ones: embedded/ports/common/stm32_timebase.c (board.h). */
/* USART1 on PA9 (TX) / PA10 (RX), 8N1 at baud, its receive interrupt on, PA8 the RS-485
 * direction pin (low: receive). */
void stm32f4_bus_init(stm32f4_uart *u, uint32_t baud);
/* The HAL over it (ctx = u). rs485 0: rs485_direction NULL (an adapter that switches by
 * itself). */
void stm32f4_hal(cochlea_hal *hal, stm32f4_uart *u, int rs485);
/* USART2 on PA2 / PA3 at 115200 8N1, polled: whole lines, outside the periods. */
void stm32f4_console_init(void);
void stm32f4_console_write(const char *text);

#endif /* COCHLEA_HAL_STM32F4_H */
