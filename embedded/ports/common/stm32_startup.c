/* What the STM32 ports' start-up shares (each port's startup_*.c has its vector table and
 * its Reset_Handler's first steps, then calls stm32_start): .data copied, .bss zeroed, the
 * free stack painted for the high-water mark (board_stack_used), the constructors, main;
 * and the fault handler: the bus's power off (a no-op on a board without a switch; the motors
 * stop), one line on the console, the core parked with interrupts off. The motors' own Bus
 * Watchdog stops them too, and the independent watchdog, if the run had started it, resets
 * the core, which then refuses to start (firmware.c). */
#include <stdint.h>

#include "board.h"

#define STACK_PAINT 0x5afe57acu

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern void (*__init_array_start[])(void);
extern void (*__init_array_end[])(void);

int main(void);

void stm32_start(void)
{
    uint32_t *src = &_sidata, *dst = &_sdata, *sp;
    long i, n;
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
uint32_t board_stack_used(void)
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
    board_bus_power(0);
    line[16] = (char)('0' + (ipsr / 10) % 10);
    line[17] = (char)('0' + ipsr % 10);
    board_console_write(line);
    for (;;) {
        __asm__ volatile("wfi");
    }
}

void Default_Handler(void)
{
    Fault_Handler();
}
