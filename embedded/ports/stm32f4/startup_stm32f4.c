/* Start-up of the STM32F4 firmware: the vector table (the core's 16 entries and the
 * STM32F405/407's 82 interrupts, RM0090 section 12.2) and the reset handler: the FPU on
 * before any floating-point instruction (CPACR, PM0214 section 4.6.1), .data copied, .bss
 * zeroed, the stack painted for the high-water mark, then main (the last steps and the fault
 * handler are the STM32 ports' shared ones: embedded/ports/common/stm32_startup.c). A fault
 * prints one line on the console and parks the core with interrupts off: the motors' own Bus
 * Watchdog stops them, and the independent watchdog, if the run had started it, resets the
 * core (which then parks: firmware.c refuses to start after a watchdog reset). */
#include <stdint.h>

#include "board.h"
#include "hal_stm32f4.h"
#include "stm32f4_regs.h"

extern uint32_t _estack;

void USART1_IRQHandler(void);
void USART3_IRQHandler(void);

void Reset_Handler(void)
{
    SCB_CPACR |= 0xFu << 20; /* CP10, CP11: full access */
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    stm32_start(); /* .data, .bss, the stack painted, main (stm32_startup.c) */
}

/* The core's exceptions, then every external interrupt: the bus's receive (37, USART1), the
 * row stream's transmit (39, USART3; stream.c) and Default_Handler (a fault line) for the
 * others, which the firmware never enables. */
__attribute__((section(".isr_vector"), used)) const vector vectors[16 + IRQ_COUNT] = {
    STM32_CORE_VECTORS(&_estack),
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 0-3 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 4-7 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 8-11 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 12-15 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 16-19 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 20-23 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 24-27 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 28-31 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 32-35 */
    Default_Handler, USART1_IRQHandler, Default_Handler, USART3_IRQHandler, /* 36-39 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 40-43 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 44-47 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 48-51 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 52-55 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 56-59 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 60-63 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 64-67 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 68-71 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 72-75 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 76-79 */
    Default_Handler, Default_Handler, /* 80-81 */
};
