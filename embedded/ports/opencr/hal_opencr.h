/* cochlea's HAL on ROBOTIS's OpenCR board (an STM32F746ZG, Cortex-M7 with a double-precision
 * FPU) at the register level, as the shared firmware's board (embedded/ports/common/board.h):
 * the clocks (HSE 25 MHz, PLL 216 MHz with the regulator's over-drive), USART3 as the
 * Dynamixel bus with DMA receive into a circular ring, the half-duplex direction pin, the
 * Dynamixel power switch, USART6 as the console and USART2 as the row stream. TIM2's 64-bit
 * clock, SysTick's period and the independent watchdog are the shared STM32 ones
 * (embedded/ports/common/stm32_timebase.c). docs/embedded.md, "OpenCR (STM32F746) port".
 *
 * OpenCR's pins, from ROBOTIS's sources (github.com/ROBOTIS-GIT/OpenCR):
 * - Dynamixel TTL/RS-485 bus: USART3, PC10 TX / PC11 RX, AF7 (Arduino Serial3, its
 *   DYNAMIXEL_SERIAL): arduino/opencr_arduino/opencr/variants/OpenCR/hw/driver/drv_uart.c
 *   (commit 0b4136ffa14b3bdb632e98d876e2727ae9f87c11), huart_inst[DRV_UART_NUM_3] = USART3
 *   and its HAL_UART_MspInit; its receive there is DMA1 stream 1, channel 4, circular;
 * - the half-duplex direction pin: PC9, high = transmit (drv_dxl.c, commit
 *   aee618962039549d42f2663e0339f4d45291c4b6, drv_dxl_tx_enable; variant.cpp, commit
 *   f0a72d446960388f47dadcbc45612ca8609e54be, pin 84 "DXL_DIR_PIN");
 * - the Dynamixel power switch: PF15, high = on (variant.cpp, same commit, pin 32
 *   "BDPIN_DXL_PWR_EN"; libraries/DynamixelSDK/src/dynamixel_sdk/port_handler_arduino.cpp,
 *   commit 185e36be58c4b33bd14d63ac163508aec9ce5fe1: setPowerOn/Off, and 1 s after power-on
 *   before the first packet);
 * - the console: USART6, PC6 TX / PC7 RX, AF8 (variant.cpp's pins 1 and 0, "UART6");
 *   the row stream: USART2, PD5 TX, AF7 (variant.cpp's pin 81, "BDPIN_UART1_TX").
 * The clock tree is ROBOTIS's bsp.c (commit 3efe545bb3299d6a4841fd7a0943fac6972a3150: HSE
 * 25 MHz, SYSCLK 216 MHz). */
#ifndef COCHLEA_HAL_OPENCR_H
#define COCHLEA_HAL_OPENCR_H

#include <stdint.h>

#include "cochlea_rt.h"

#ifndef STM32_HSE_HZ
#define STM32_HSE_HZ 25000000u /* OpenCR's crystal */
#endif
#ifndef STM32_SYSCLK_HZ
#define STM32_SYSCLK_HZ 216000000u /* PLL: M = 25, N = 432, P = 2 (over-drive on) */
#endif
#define STM32_APB1_HZ (STM32_SYSCLK_HZ / 4u) /* 54 MHz: USART2, USART3 */
#define STM32_APB2_HZ (STM32_SYSCLK_HZ / 2u) /* 108 MHz: USART6 */
/* TIM2's counting clock: APB1's timer clock, twice APB1 (its prescaler is not 1; RCC_DCKCFGR1
 * TIMPRE 0): 108 MHz, a count every 9.26 ns, a 32-bit wrap every 39.8 s. */
#ifndef STM32_TIMER_HZ
#define STM32_TIMER_HZ (2u * STM32_APB1_HZ)
#endif
/* The DMA receive ring (bytes, a power of two): several periods of status packets. */
#define OPENCR_RX_RING 1024u
/* The motors' boot time after the power switch closes (ms): ROBOTIS's openPort waits 1 s. */
#ifndef OPENCR_POWER_SETTLE_MS
#define OPENCR_POWER_SETTLE_MS 1000u
#endif

/* Pins: port and number. */
#define OPENCR_DXL_DIR_PIN 9u    /* PC9 */
#define OPENCR_DXL_POWER_PIN 15u /* PF15 */

/* For the register-model test (tests/test_embedded_opencr.py) and the end line: the ring the
 * DMA writes, the bus's receive counts. */
volatile uint8_t *opencr_bus_ring(void);
uint32_t opencr_bus_dma_laps(void);  /* DMA transfer-complete interrupts: ring wraps */
uint32_t opencr_bus_idles(void);     /* USART3 IDLE interrupts: bursts that ended */
/* The HAL's serial calls, for the test (the firmware reaches them through board_bus_hal). */
long opencr_bus_write(void *ctx, const uint8_t *data, size_t n);
long opencr_bus_read(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns);
void opencr_bus_direction(void *ctx, int transmit);

/* The USART's baud-rate register with OVER8 = 1 (RM0385, "USART baud rate generation"):
 * USARTDIV = 2 f / baud, rounded; BRR[15:4] = USARTDIV[15:4], BRR[2:0] = USARTDIV[3:0] >> 1. */
uint32_t opencr_brr_over8(uint32_t clock_hz, uint32_t baud);

#endif /* COCHLEA_HAL_OPENCR_H */
