/* Start-up of the STM32F4 firmware: the vector table (the core's 16 entries and the
 * STM32F405/407's 82 interrupts, RM0090 section 12.2) and the reset handler: the FPU on
 * before any floating-point instruction (CPACR, PM0214 section 4.6.1), .data copied, .bss
 * zeroed, the stack painted for the high-water mark, then main. A fault prints one line on
 * the console and parks the core with interrupts off: the motors' own Bus Watchdog stops
 * them, and the independent watchdog, if the run had started it, resets the core (which then
 * parks: firmware.c refuses to start after a watchdog reset). */
#include <stdint.h>

#include "board.h"
#include "hal_stm32f4.h"
#include "stm32f4_regs.h"

#define STACK_PAINT 0x5afe57acu

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern void (*__init_array_start[])(void);
extern void (*__init_array_end[])(void);

int main(void);
void Reset_Handler(void);
void Fault_Handler(void);
void Default_Handler(void);
void SysTick_Handler(void);
void USART1_IRQHandler(void);
void USART3_IRQHandler(void);

void Reset_Handler(void)
{
    uint32_t *src = &_sidata, *dst = &_sdata, *sp;
    long i, n;
    SCB_CPACR |= 0xFu << 20; /* CP10, CP11: full access */
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    while (dst < &_edata) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0;
    }
    /* Paint the free stack up to 64 bytes under this frame. */
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    for (dst = &_ebss; dst < sp - 16;) {
        *dst++ = STACK_PAINT;
    }
    n = __init_array_end - __init_array_start;
    for (i = 0; i < n; ++i) {
        __init_array_start[i]();
    }
    main();
    for (;;) {
        board_idle();
    }
}

/* Bytes of stack ever used: from the top down to the deepest word not still painted. */
uint32_t stm32f4_stack_used(void);
uint32_t stm32f4_stack_used(void)
{
    const uint32_t *p = &_ebss;
    while (p < &_estack && *p == STACK_PAINT) {
        ++p;
    }
    return (uint32_t)((uintptr_t)&_estack - (uintptr_t)p);
}

void Fault_Handler(void)
{
    uint32_t ipsr;
    char line[] = "fault exception=00\r\n";
    __asm__ volatile("cpsid i\n\tmrs %0, ipsr" : "=r"(ipsr));
    line[16] = (char)('0' + (ipsr / 10) % 10);
    line[17] = (char)('0' + ipsr % 10);
    stm32f4_console_write(line);
    for (;;) {
        __asm__ volatile("wfi");
    }
}

void Default_Handler(void)
{
    Fault_Handler();
}

typedef void (*vector)(void);

/* The core's exceptions, then every external interrupt: the bus's receive (37, USART1), the
 * row stream's transmit (39, USART3; stream.c) and Default_Handler (a fault line) for the
 * others, which the firmware never enables. */
__attribute__((section(".isr_vector"), used)) const vector vectors[16 + IRQ_COUNT] = {
    (vector)(uintptr_t)&_estack, Reset_Handler,
    Fault_Handler,   /* NMI */
    Fault_Handler,   /* HardFault */
    Fault_Handler,   /* MemManage */
    Fault_Handler,   /* BusFault */
    Fault_Handler,   /* UsageFault */
    0, 0, 0, 0,      /* reserved */
    Default_Handler, /* SVCall */
    Default_Handler, /* DebugMonitor */
    0,               /* reserved */
    Default_Handler, /* PendSV */
    SysTick_Handler,
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
