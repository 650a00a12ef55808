/* What the STM32 ports share at the register level (board.h): TIM2 as the 64-bit nanosecond
 * clock, SysTick as the period timer, the sleep that never outlasts a deadline, and the
 * independent watchdog; the clocks' bounded wait for a ready bit. TIM2, SysTick, the SCB, the IWDG and RCC_CSR's reset flags have the
 * same addresses and bits on the STM32F405/407 (RM0090, PM0214) and the STM32F746 (RM0385,
 * PM0253); each port's board_config.h gives its registers' names and its rates
 * (STM32_SYSCLK_HZ, STM32_TIMER_HZ). */
#include "board.h"
#include "board_config.h"

/* ---- clocks: a ready bit, polled a bounded number of times ------------------------------- */

/* Polls before giving up: far beyond a crystal's start-up (a few ms), a PLL's lock and the
 * F746's over-drive ramp (about 100 us each) at the HSI's 16 MHz. */
#define CLOCK_POLLS 2000000u

int stm32_wait_bits(volatile uint32_t *reg, uint32_t mask, uint32_t value)
{
    uint32_t i;
    for (i = 0; i < CLOCK_POLLS; ++i) {
        if ((*reg & mask) == value) {
            return 1;
        }
    }
    return 0;
}

/* ---- TIM2: the clock ------------------------------------------------------------------ */

/* TIM2's first count: 0 on a board; a test starts it just before a wrap, so that the run
 * crosses one. */
#ifndef STM32_TIMER_START
#define STM32_TIMER_START 0u
#endif

static volatile uint64_t timer_high; /* the wraps, times 2^32 */
static volatile uint32_t timer_last; /* the last reading */

void board_clock_start(void)
{
    RCC_APB1ENR |= RCC_APB1ENR_TIM2EN;
    TIM2_CR1 = 0;
    TIM2_PSC = 0;
    TIM2_ARR = 0xffffffffu;
    TIM2_EGR = 1u; /* load the prescaler, counter 0 */
    TIM2_CNT = STM32_TIMER_START;
    timer_high = 0;
    timer_last = STM32_TIMER_START;
    TIM2_CR1 = 1u;
}

/* Counts since the start: the counter, plus 2^32 for each wrap seen (a reading below the last
 * one), read and updated with interrupts masked so the loop and SysTick's interrupt agree.
 * SysTick's interrupt reads it every period, so no wrap (51 s at 84 MHz, 40 s at 108 MHz)
 * passes unseen. */
static uint64_t timer_counts(void)
{
    const uint32_t primask = board_irq_save();
    const uint32_t counter = TIM2_CNT;
    uint64_t high = timer_high;
    if (counter < timer_last) {
        high += (uint64_t)1 << 32;
        timer_high = high;
    }
    timer_last = counter;
    board_irq_restore(primask);
    return high | counter;
}

static int64_t counts_to_ns(uint64_t counts)
{
    const uint64_t whole = counts / STM32_TIMER_HZ, part = counts % STM32_TIMER_HZ;
    return (int64_t)(whole * 1000000000u + part * 1000000000u / STM32_TIMER_HZ);
}

uint32_t board_timer_count(void)
{
    return TIM2_CNT;
}

uint32_t board_timer_hz(void)
{
    return STM32_TIMER_HZ;
}

int64_t board_now_ns(void)
{
    return counts_to_ns(timer_counts());
}

/* ---- SysTick: the period timer ---------------------------------------------------------- */

static volatile uint32_t tick_count;    /* period ticks: written by the interrupt only */
static volatile int64_t tick_ns;        /* the clock at the last tick (0: none yet) */
static int64_t tick_period_ns;
static void (*tick_hook)(void *);
static void *tick_hook_ctx;

int board_tick_start(int64_t period_ns, void (*tick)(void *), void *tick_ctx)
{
    const uint64_t cycles = ((uint64_t)period_ns * STM32_SYSCLK_HZ + 500000000u) / 1000000000u;
    if (period_ns <= 0 || cycles < 1000u || cycles > (1u << 24)) {
        return -1;
    }
    tick_period_ns = period_ns;
    tick_hook = tick;
    tick_hook_ctx = tick_ctx;
    tick_count = 0;
    tick_ns = 0;
    SCB_SHPR3 = (SCB_SHPR3 & 0x00ffffffu) | (0x40u << 24); /* below the bus's receive */
    SYST_RVR = (uint32_t)cycles - 1u;
    SYST_CVR = 0;
    SYST_CSR = 7u; /* the processor clock, the interrupt, enabled */
    return 0;
}

uint32_t board_ticks(void)
{
    return tick_count;
}

void SysTick_Handler(void);
void SysTick_Handler(void)
{
    tick_ns = board_now_ns(); /* also keeps the clock's wrap count current */
    tick_count = tick_count + 1u;
    if (tick_hook) {
        tick_hook(tick_hook_ctx);
    }
}

void board_idle(void)
{
#ifdef BOARD_HOST_MODEL
    model_idle();
#else
    __asm__ volatile("dsb\n\twfi" ::: "memory");
#endif
}

/* Sleep (WFI) only when an interrupt is due by the deadline: the next period tick (a period
 * after the last one) comes before it. Else return and let the caller poll, so a wait outlasts
 * its deadline by no more than a poll (on silicon: SysTick reloads in hardware, exactly).
 * Interrupts are masked around the test, so a byte (or a burst's end) that arrives in between
 * still ends the WFI (a pending interrupt wakes it; PM0214 section 2.5.2): wake, when not
 * NULL, is a count the bus's interrupt moves, seen its value before the caller last looked. */
void stm32_sleep_before(int64_t deadline_ns, const volatile uint32_t *wake, uint32_t seen)
{
    const uint32_t primask = board_irq_save();
    if (tick_ns != 0 && tick_ns + tick_period_ns <= deadline_ns
        && (wake == 0 || *wake == seen) && !(SCB_ICSR & SCB_ICSR_PENDSTSET)) {
        board_idle();
    }
    board_irq_restore(primask);
}

void stm32_wait_until(int64_t deadline_ns)
{
    while (board_now_ns() < deadline_ns) {
        stm32_sleep_before(deadline_ns, 0, 0);
    }
}

/* The HAL's clock callbacks (cochlea_rt.h: now_ns, wait_until_ns), the same on both ports. */
int64_t stm32_hal_now(void *ctx)
{
    (void)ctx;
    return board_now_ns();
}

void stm32_hal_wait_until(void *ctx, int64_t deadline_ns)
{
    (void)ctx;
    stm32_wait_until(deadline_ns);
}

/* ---- the independent watchdog (RM0090 section 21.3; RM0385, "Independent watchdog") ------ */

static void iwdg_set(uint32_t timeout_ms)
{
    /* LSI 32 kHz / 4 << pr: the smallest prescaler whose 12-bit reload holds the timeout */
    uint32_t pr = 0, reload;
    while (pr < 6u && (timeout_ms * 32u) / (4u << pr) > 4095u) {
        ++pr;
    }
    reload = (timeout_ms * 32u) / (4u << pr);
    reload = reload < 1u ? 1u : reload > 4095u ? 4095u : reload;
    IWDG_KR = 0x5555u; /* unlock PR and RLR */
    {
        uint32_t polls; /* a previous update still running (PVU, RVU): bounded */
        for (polls = 0; polls < 100000u && (IWDG_SR & 3u); ++polls) {
        }
    }
    IWDG_PR = pr;
    IWDG_RLR = reload;
    IWDG_KR = 0xAAAAu;
}

void board_iwdg_start(uint32_t timeout_ms)
{
    IWDG_KR = 0xCCCCu; /* starts the LSI and the watchdog: it cannot be stopped */
    iwdg_set(timeout_ms);
}

void board_iwdg_kick(void *ctx)
{
    (void)ctx;
    IWDG_KR = 0xAAAAu;
}

void board_iwdg_timeout(uint32_t timeout_ms)
{
    iwdg_set(timeout_ms);
}

int board_reset_by_watchdog(void)
{
    const uint32_t csr = RCC_CSR;
    RCC_CSR = csr | RCC_CSR_RMVF;
    return (csr & (RCC_CSR_IWDGRSTF | RCC_CSR_WWDGRSTF)) != 0u;
}
