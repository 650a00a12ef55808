/* The bare-metal port of replay.c for QEMU's mps2 boards: mps2-an386 (Cortex-M4F) and
 * mps2-an500 (Cortex-M7). The vector table, the reset handler (the FPU on, .data copied,
 * .bss zeroed) and the output through ARM semihosting: SYS_WRITE0 for each line, SYS_EXIT
 * (the extended form, with the status) at the end. Run it with
 *   qemu-system-arm -M mps2-an386 -cpu cortex-m4 -nographic -monitor none -serial none \
 *       -semihosting-config enable=on,target=native -kernel replay.elf
 * Add -icount shift=0 for an instruction count (replay.c's C line).
 * A fault prints one line ("F <vector>") and exits with status 3. */
#include <stdint.h>

int replay_main(void);

/* ---- semihosting ------------------------------------------------------------------------ */

#define SYS_WRITE0 0x04
#define SYS_EXIT 0x18
#define SYS_EXIT_EXTENDED 0x20
#define ADP_STOPPED_APPLICATION_EXIT 0x20026

static uintptr_t semihost(uintptr_t op, const void *arg)
{
    register uintptr_t r0 __asm__("r0") = op;
    register uintptr_t r1 __asm__("r1") = (uintptr_t)arg;
    __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void port_line(const char *text)
{
    semihost(SYS_WRITE0, text);
    semihost(SYS_WRITE0, "\n");
}

void port_exit(int status)
{
    uintptr_t block[2];
    block[0] = ADP_STOPPED_APPLICATION_EXIT;
    block[1] = (uintptr_t)status;
    semihost(SYS_EXIT_EXTENDED, block);
    /* A host without the extended call: the plain exit (status 0 only). */
    semihost(SYS_EXIT, (const void *)(uintptr_t)ADP_STOPPED_APPLICATION_EXIT);
    for (;;) {
    }
}

/* ---- ticks: SysTick on the processor clock -------------------------------------------- */

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)

static void ticks_start(void)
{
    SYST_RVR = 0xffffffu;
    SYST_CVR = 0;
    SYST_CSR = 5u; /* enabled, the processor clock, no interrupt */
}

uint32_t port_ticks(void)
{
    return (0u - SYST_CVR) & 0xffffffu; /* SysTick counts down */
}

/* 2 n instructions (subs, bne) and the counter's reads around them. */
uint32_t port_calibrate(uint32_t *instructions)
{
    uint32_t n = 1u << 20, start = port_ticks();
    __asm__ volatile("1: subs %0, %0, #1\n\tbne 1b" : "+r"(n) : : "cc");
    *instructions = 2u << 20;
    return (port_ticks() - start) & 0xffffffu;
}

/* ---- startup ---------------------------------------------------------------------------- */

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern void (*__init_array_start[])(void);
extern void (*__init_array_end[])(void);

void Reset_Handler(void);
void Fault_Handler(void);

void Reset_Handler(void)
{
    volatile uint32_t *const cpacr = (volatile uint32_t *)0xE000ED88u;
    uint32_t *src = &_sidata, *dst = &_sdata;
    long i, n;
    /* CP10 and CP11 (the FPU) full access, before any floating-point instruction. */
    *cpacr |= (0xFu << 20);
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    while (dst < &_edata) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0;
    }
    n = __init_array_end - __init_array_start;
    for (i = 0; i < n; ++i) {
        __init_array_start[i]();
    }
    ticks_start();
    port_exit(replay_main());
}

void Fault_Handler(void)
{
    uint32_t ipsr;
    char line[] = "F 00";
    __asm__ volatile("mrs %0, ipsr" : "=r"(ipsr));
    line[2] = (char)('0' + (ipsr / 10) % 10);
    line[3] = (char)('0' + ipsr % 10);
    port_line(line);
    port_exit(3);
}

/* Cortex-M: the initial stack pointer, then the handlers (reset, NMI, the four faults, ...). */
__attribute__((section(".isr_vector"), used)) void *const vectors[16] = {
    &_estack,       (void *)Reset_Handler, (void *)Fault_Handler, (void *)Fault_Handler,
    (void *)Fault_Handler, (void *)Fault_Handler, (void *)Fault_Handler, 0,
    0,              0,                     0,                     (void *)Fault_Handler,
    (void *)Fault_Handler, 0,              (void *)Fault_Handler, (void *)Fault_Handler,
};
