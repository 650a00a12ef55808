/* What a board port gives the shared firmware (firmware.c) and row stream (stream.c).
 *
 * Both STM32 ports (embedded/ports/stm32f4: an STM32F405/407; embedded/ports/opencr: the
 * OpenCR board's STM32F746) implement these at the register level; the run (the start-up,
 * the periods, the safe stop, the console's lines) and the stream's framing are written once,
 * in this folder. Every wait here ends at a deadline on the clock or after a bounded count of
 * polls (cochlea_rt.h's contract). docs/embedded.md, "STM32F4 port" and "OpenCR (STM32F746)
 * port". */
#ifndef COCHLEA_PORTS_BOARD_H
#define COCHLEA_PORTS_BOARD_H

#include <stdint.h>

#include "cochlea_rt.h"

/* The board's name in the console's first line and the stream's header
 * ("cochlea-<name>", "cochlea-<name>-stream"). */
extern const char board_name[];

/* What board_clock_init found: the same four answers on both ports. */
enum board_clock {
    BOARD_CLOCK_PLL = 0,        /* crystal and PLL locked: the board's rate */
    BOARD_CLOCK_UNMODELLED = 1, /* RCC reads 0 (impossible on silicon): an emulator's */
    BOARD_CLOCK_NO_HSE = 2,     /* the crystal did not start: nothing may run */
    BOARD_CLOCK_NO_PLL = 3      /* the PLL did not lock or was not selected */
};
int board_clock_init(void);
/* The free-running timer: its raw 32-bit count (board_timer_hz() a second), and the 64-bit
 * nanosecond clock made from it (monotonic, never wraps). */
void board_clock_start(void);
uint32_t board_timer_count(void);
uint32_t board_timer_hz(void);
int64_t board_now_ns(void);
/* The period timer (SysTick): tick(ctx) once a period from its interrupt. 0, or -1 for a
 * period it cannot make. */
int board_tick_start(int64_t period_ns, void (*tick)(void *), void *ctx);
uint32_t board_ticks(void);
/* Sleep until the next interrupt (WFI). */
void board_idle(void);
/* The console: whole lines, outside the periods, polled with a bound. */
void board_console_init(void);
void board_console_write(const char *text);
/* The Dynamixel bus: its UART at baud and the HAL over it (rs485 0: no direction pin). */
void board_bus_init(uint32_t baud);
void board_bus_hal(cochlea_hal *hal, int rs485);
/* Bytes the receive ring lost (it was full, or the DMA lapped the reader). */
uint32_t board_bus_rx_overflows(void);
/* The bus's power: 1 on, 0 off (OpenCR's Dynamixel power switch; a no-op where the board
 * has none). The firmware switches it on just before the bus starts and off at every end,
 * after the safe stop (torque off). board_bus_power_settle_ms: the motors' boot time to wait
 * after switching on (0: none). */
void board_bus_power(int on);
uint32_t board_bus_power_settle_ms(void);
/* The independent watchdog: started (it cannot be stopped), kicked, given a new timeout. */
void board_iwdg_start(uint32_t timeout_ms);
void board_iwdg_kick(void *ctx);
void board_iwdg_timeout(uint32_t timeout_ms);
/* Whether the last reset was a watchdog's; clears the flags. */
int board_reset_by_watchdog(void);
/* Stack bytes ever used (the reset handler painted it). */
uint32_t board_stack_used(void);

/* Shared by the STM32 ports (stm32_timebase.c, with TIM2 and SysTick): sleep (WFI) only when
 * an interrupt is due before deadline_ns, and not when *wake (a count the bus's interrupt
 * moves; NULL: none) is no longer seen; and a wait until a deadline made of such sleeps. */
void stm32_sleep_before(int64_t deadline_ns, const volatile uint32_t *wake, uint32_t seen);
void stm32_wait_until(int64_t deadline_ns);
/* The HAL's now_ns and wait_until_ns over these (ctx unused). */
int64_t stm32_hal_now(void *ctx);
void stm32_hal_wait_until(void *ctx, int64_t deadline_ns);
/* A clock's ready bit: 1 once (*reg & mask) == value, 0 after a bounded count of polls. */
int stm32_wait_bits(volatile uint32_t *reg, uint32_t mask, uint32_t value);
#ifdef BOARD_HOST_MODEL
void model_idle(void); /* the register model's WFI */
#endif

/* The start-up (stm32_startup.c): the rest of a port's Reset_Handler, after its own first
 * steps (the FPU on, ...): .data, .bss, the stack painted, main; never returns. The vector
 * table's 16 core entries, the same on both ports (STM32_CORE_VECTORS; vector is a handler's
 * type), and their handlers. */
void stm32_start(void);
void Reset_Handler(void);
void Fault_Handler(void);
void Default_Handler(void);
void SysTick_Handler(void);
typedef void (*vector)(void);
#define STM32_CORE_VECTORS(stack_top)                                                        \
    (vector)(uintptr_t)(stack_top), Reset_Handler, Fault_Handler /* NMI */,                \
        Fault_Handler /* HardFault */, Fault_Handler /* MemManage */,                      \
        Fault_Handler /* BusFault */, Fault_Handler /* UsageFault */, 0, 0, 0, 0,          \
        Default_Handler /* SVCall */, Default_Handler /* DebugMonitor */, 0,               \
        Default_Handler /* PendSV */, SysTick_Handler

/* The row stream's UART (stream.c frames, the board moves bytes): set up at baud (transmit
 * only); whether it takes a byte now; one byte; its "transmit register empty" interrupt on
 * or off. The board's interrupt handler for it calls stream_tx_interrupt(). */
void board_stream_uart_init(uint32_t baud);
int board_stream_tx_ready(void);
void board_stream_tx_byte(uint8_t byte);
void board_stream_tx_interrupt(int on);
void stream_tx_interrupt(void);

/* Interrupts masked and restored (PRIMASK), shared by the ports. A host build of a port's
 * HAL against a register model (tests/test_embedded_opencr.py) has no PRIMASK. */
#ifdef BOARD_HOST_MODEL
static inline uint32_t board_irq_save(void)
{
    return 0;
}

static inline void board_irq_restore(uint32_t primask)
{
    (void)primask;
}
#else
static inline uint32_t board_irq_save(void)
{
    uint32_t primask;
    __asm__ volatile("mrs %0, primask\n\tcpsid i" : "=r"(primask) : : "memory");
    return primask;
}

static inline void board_irq_restore(uint32_t primask)
{
    __asm__ volatile("msr primask, %0" : : "r"(primask) : "memory");
}
#endif

#endif /* COCHLEA_PORTS_BOARD_H */
