/* Start-up of the OpenCR firmware: the vector table (the core's 16 entries and the
 * STM32F746's 98 interrupts) and the reset handler: the FPU on before any floating-point
 * instruction (CPACR CP10/CP11, PM0253 section 4.6.1: the M7's double-precision FPv5),
 * VTOR at the table, the instruction cache on; then the STM32 ports' shared start-up
 * (embedded/ports/common/stm32_startup.c): .data copied, .bss zeroed, the stack painted for
 * the high-water mark, main; and its fault handler.
 *
 * Caches and MPU: the instruction cache is on (code and constants in flash over AXIM; nothing
 * writes code). The data cache stays off and the MPU is not used: .data, .bss and the stack
 * are in the DTCM (0x20000000, 64 KB: zero wait states, never cached), and the one buffer a
 * DMA writes, the bus's receive ring, is in SRAM1 (0x20010000), which with the data cache off
 * the core reads as the DMA wrote it: no cache maintenance, no non-cacheable MPU region to
 * get wrong. The cost is uncached reads of flash constants and of the ring.
 *
 * Two vector tables. The core (or OpenCR's bootloader, which jumps here with VTOR already on
 * this image and with its SysTick still interrupting: ROBOTIS's jump_to_fw) starts on
 * boot_vectors, at the image's first word: the initial stack pointer, Reset_Handler, the
 * fault handlers, and for every other exception Boot_Quiet_Handler, which silences what
 * interrupted. Reset_Handler then masks interrupts, stops SysTick, disables and clears every
 * NVIC line, moves VTOR to vectors (the firmware's handlers) and unmasks, as at a reset: no
 * handler of the firmware runs before .data and .bss are set up, whoever started the core.
 *
 * A fault switches the Dynamixel power off (the motors stop; a torque-off packet cannot be
 * trusted from a faulted core), prints one line on the console and parks with interrupts off;
 * the independent watchdog, if the run had started it, resets the core, which then refuses to
 * start (firmware.c). */
#include <stdint.h>

#include "board.h"
#include "hal_opencr.h"
#include "stm32f746_regs.h"

extern uint32_t _estack;
extern const vector vectors[];
extern const vector boot_vectors[];

void DMA1_Stream1_IRQHandler(void);
void USART2_IRQHandler(void);
void USART3_IRQHandler(void);

/* An exception taken while boot_vectors is the table (before Reset_Handler quietens the core:
 * a bootloader's SysTick or a line it left enabled): stopped or disabled, then back. */
static void Boot_Quiet_Handler(void)
{
    uint32_t ipsr;
    __asm__ volatile("mrs %0, ipsr" : "=r"(ipsr));
    SYST_CSR = 0u;
    SCB_ICSR = SCB_ICSR_PENDSTCLR;
    if (ipsr >= 16u) {
        NVIC_ICER((ipsr - 16u) / 32u) = 1u << ((ipsr - 16u) % 32u);
    }
}

void Reset_Handler(void)
{
    uint32_t n;
    __asm__ volatile("cpsid i" ::: "memory");
    SYST_CSR = 0u; /* a bootloader's SysTick (reset value: off) */
    for (n = 0; n < NVIC_REGISTERS; ++n) {
        NVIC_ICER(n) = 0xFFFFFFFFu;
        NVIC_ICPR(n) = 0xFFFFFFFFu;
    }
    SCB_ICSR = SCB_ICSR_PENDSTCLR | SCB_ICSR_PENDSVCLR;
    SCB_CPACR |= 0xFu << 20; /* CP10, CP11: full access */
    SCB_VTOR = (uint32_t)(uintptr_t)vectors;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    __asm__ volatile("cpsie i" ::: "memory"); /* PRIMASK as a reset leaves it */
    /* The instruction cache: invalidated, then on (PM0253 section 4.8). */
    SCB_ICIALLU = 0;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    SCB_CCR |= SCB_CCR_IC;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    stm32_start(); /* .data, .bss, the stack painted, main (stm32_startup.c) */
}

/* The core's exceptions, then every external interrupt: the bus's DMA receive (12, DMA1
 * stream 1: its laps) and IDLE (39, USART3), the row stream's transmit (38, USART2; stream.c)
 * and Default_Handler (a fault line) for the others, which the firmware never enables. */
/* The table the core starts on (above): first in flash, at the image's load address. */
__attribute__((section(".isr_vector"), used)) const vector boot_vectors[16 + IRQ_COUNT] = {
    (vector)(uintptr_t)&_estack, Reset_Handler, Fault_Handler /* NMI */,
    Fault_Handler /* HardFault */, Fault_Handler /* MemManage */, Fault_Handler /* BusFault */,
    Fault_Handler /* UsageFault */, 0, 0, 0, 0, Boot_Quiet_Handler /* SVCall */,
    Boot_Quiet_Handler /* DebugMonitor */, 0, Boot_Quiet_Handler /* PendSV */,
    Boot_Quiet_Handler /* SysTick */, [16 ... 16 + IRQ_COUNT - 1] = Boot_Quiet_Handler,
};

/* The firmware's table, from Reset_Handler on. VTOR takes a table aligned to its size rounded
 * up to a power of two (PM0253 section 4.3.4): 114 words, 512 bytes. */
__attribute__((aligned(512), used)) const vector vectors[16 + IRQ_COUNT] = {
    STM32_CORE_VECTORS(&_estack),
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 0-3 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 4-7 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 8-11 */
    DMA1_Stream1_IRQHandler, Default_Handler, Default_Handler, Default_Handler, /* 12-15 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 16-19 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 20-23 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 24-27 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 28-31 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 32-35 */
    Default_Handler, Default_Handler, USART2_IRQHandler, USART3_IRQHandler, /* 36-39 */
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
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 80-83 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 84-87 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 88-91 */
    Default_Handler, Default_Handler, Default_Handler, Default_Handler, /* 92-95 */
    Default_Handler, Default_Handler, /* 96-97 */
};
