/* cochlea's HAL on an STM32F405/407 (hal_stm32f4.h). Register level; RM0090 and PM0214
 * sections in stm32f4_regs.h. Every wait here ends at a deadline on the clock or after a
 * bounded count of polls (cochlea_rt.h's contract). */
#include "hal_stm32f4.h"

#include "board.h"
#include "stm32f4_regs.h"

/* ---- interrupts ------------------------------------------------------------------------- */

#define irq_save board_irq_save
#define irq_restore board_irq_restore

void stm32f4_idle(void)
{
    __asm__ volatile("dsb\n\twfi" ::: "memory");
}

/* ---- clocks: HSE -> PLL 168 MHz, AHB 168, APB1 42, APB2 84 (RM0090 section 7.2) ---------- */

/* Polls of a ready bit before giving up: far beyond the HSE's start-up (a few ms) and the
 * PLL's lock (about 100 us) at the HSI's 16 MHz. */
#define CLOCK_POLLS 2000000u

static int wait_bits(volatile uint32_t *reg, uint32_t mask, uint32_t value)
{
    uint32_t i;
    for (i = 0; i < CLOCK_POLLS; ++i) {
        if ((*reg & mask) == value) {
            return 1;
        }
    }
    return 0;
}

int stm32f4_clock_init(void)
{
    const uint32_t pllm = STM32_HSE_HZ / 1000000u; /* 1 MHz at the VCO's input */
    const uint32_t plln = 336u, pllp = 2u, pllq = 7u; /* VCO 336 MHz; /2: 168; /7: 48 */
    if (RCC_CR == 0u) {
        /* No RCC behind this address (QEMU models none for the STM32F405: its reads are 0).
         * Silicon always reads HSION and HSIRDY here while the HSI runs the core. */
        return STM32F4_CLOCK_UNMODELLED;
    }
    RCC_CR |= RCC_CR_HSEON;
    if (!wait_bits(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY)) {
        return STM32F4_CLOCK_NO_HSE;
    }
    /* Wait states before the faster clock (section 3.5.1), the caches on. */
    FLASH_ACR = FLASH_ACR_LATENCY_5WS | FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN;
    RCC_CFGR = RCC_CFGR_PPRE1_DIV4 | RCC_CFGR_PPRE2_DIV2; /* AHB /1 */
    RCC_PLLCFGR = pllm | (plln << 6) | (((pllp / 2u) - 1u) << 16) | RCC_PLLCFGR_PLLSRC_HSE
                  | (pllq << 24);
    RCC_CR |= RCC_CR_PLLON;
    if (!wait_bits(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        return STM32F4_CLOCK_NO_PLL;
    }
    RCC_CFGR = (RCC_CFGR & ~3u) | RCC_CFGR_SW_PLL;
    if (!wait_bits(&RCC_CFGR, 3u << 2, RCC_CFGR_SWS_PLL)) {
        return STM32F4_CLOCK_NO_PLL;
    }
    return STM32F4_CLOCK_PLL;
}

/* ---- TIM2: the clock ------------------------------------------------------------------ */

/* TIM2's first count: 0 on a board; a test starts it just before a wrap, so that the run
 * crosses one. */
#ifndef STM32_TIMER_START
#define STM32_TIMER_START 0u
#endif

static volatile uint64_t timer_high; /* the wraps, times 2^32 */
static volatile uint32_t timer_last; /* the last reading */

void stm32f4_clock_start(void)
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
 * one), read and updated with interrupts masked so the loop and SysTick's interrupt agree. */
static uint64_t timer_counts(void)
{
    const uint32_t primask = irq_save();
    const uint32_t counter = TIM2_CNT;
    uint64_t high = timer_high;
    if (counter < timer_last) {
        high += (uint64_t)1 << 32;
        timer_high = high;
    }
    timer_last = counter;
    irq_restore(primask);
    return high | counter;
}

static int64_t counts_to_ns(uint64_t counts)
{
    const uint64_t whole = counts / STM32_TIMER_HZ, part = counts % STM32_TIMER_HZ;
    return (int64_t)(whole * 1000000000u + part * 1000000000u / STM32_TIMER_HZ);
}

uint32_t stm32f4_timer_count(void)
{
    return TIM2_CNT;
}

int64_t stm32f4_now_ns(void)
{
    return counts_to_ns(timer_counts());
}

/* ---- SysTick: the period timer ---------------------------------------------------------- */

static volatile uint32_t tick_count;    /* period ticks: written by the interrupt only */
static volatile int64_t tick_ns;        /* the clock at the last tick (0: none yet) */
static int64_t tick_period_ns;
static void (*tick_hook)(void *);
static void *tick_hook_ctx;

int stm32f4_tick_start(int64_t period_ns, void (*tick)(void *), void *tick_ctx)
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

uint32_t stm32f4_ticks(void)
{
    return tick_count;
}

void SysTick_Handler(void);
void SysTick_Handler(void)
{
    tick_ns = stm32f4_now_ns(); /* also keeps the clock's wrap count current */
    tick_count = tick_count + 1u;
    if (tick_hook) {
        tick_hook(tick_hook_ctx);
    }
}

/* Sleep (WFI) only when an interrupt is due by the deadline: the next period tick (a period
 * after the last one) comes before it. Else return and let the caller poll, so a wait outlasts
 * its deadline by no more than a poll (on silicon: SysTick reloads in hardware, exactly).
 * Interrupts are masked around the test, so a byte that arrives in between still ends the WFI
 * (a pending interrupt wakes it; PM0214 section 2.5.2). */
static void sleep_before(int64_t deadline_ns, volatile uint32_t *head, uint32_t seen)
{
    const uint32_t primask = irq_save();
    if (tick_ns != 0 && tick_ns + tick_period_ns <= deadline_ns
        && (head == 0 || *head == seen) && !(SCB_ICSR & SCB_ICSR_PENDSTSET)) {
        __asm__ volatile("dsb\n\twfi" ::: "memory");
    }
    irq_restore(primask);
}

/* ---- USART1: the Dynamixel bus ---------------------------------------------------------- */

static stm32f4_uart *bus_uart;

void USART1_IRQHandler(void);
void USART1_IRQHandler(void)
{
    stm32f4_uart *u = bus_uart;
    /* SR then DR clears RXNE and an overrun (section 30.6.1). */
    while (USART_SR(USART1_BASE) & (USART_SR_RXNE | USART_SR_ORE)) {
        const uint8_t byte = (uint8_t)USART_DR(USART1_BASE);
        if (u == 0) {
            continue;
        }
        if (u->head - u->tail < STM32_RX_RING) {
            u->ring[u->head % STM32_RX_RING] = byte;
            u->head = u->head + 1u;
        } else {
            u->overflows = u->overflows + 1u;
        }
    }
}

static uint32_t brr_over8(uint32_t clock_hz, uint32_t baud)
{
    /* OVER8 = 1: USARTDIV = f / (8 baud) in 1/8ths; mantissa 15:4, fraction 2:0 (30.3.4) */
    const uint32_t div8 = (clock_hz + baud / 2u) / baud;
    return ((div8 >> 3) << 4) | (div8 & 7u);
}

void stm32f4_bus_init(stm32f4_uart *u, uint32_t baud)
{
    u->head = u->tail = u->overflows = 0;
    u->baud = baud;
    bus_uart = u;
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOAEN;
    RCC_APB2ENR |= RCC_APB2ENR_USART1EN;
    /* PA9 TX, PA10 RX: alternate function 7, very high speed, RX pulled up; PA8 output low
     * (the transceiver listens). */
    GPIOA_BSRR = 1u << (8 + 16);
    GPIOA_MODER = (GPIOA_MODER & ~((3u << 16) | (3u << 18) | (3u << 20)))
                  | (1u << 16) | (2u << 18) | (2u << 20);
    GPIOA_OSPEEDR |= (3u << 16) | (3u << 18) | (3u << 20);
    GPIOA_PUPDR = (GPIOA_PUPDR & ~(3u << 20)) | (1u << 20);
    GPIOA_AFRH = (GPIOA_AFRH & ~((0xfu << 4) | (0xfu << 8)))
                 | (GPIO_AF7_USART << 4) | (GPIO_AF7_USART << 8);
    USART_CR1(USART1_BASE) = 0;
    USART_CR2(USART1_BASE) = 0;
    USART_CR3(USART1_BASE) = 0;
    USART_BRR(USART1_BASE) = brr_over8(STM32_APB2_HZ, baud);
    USART_CR1(USART1_BASE) = USART_CR1_OVER8 | USART_CR1_UE | USART_CR1_TE | USART_CR1_RE
                             | USART_CR1_RXNEIE;
    NVIC_IPR_BYTE(IRQ_USART1) = 0x20u; /* above SysTick: a byte is never lost to a tick */
    NVIC_ISER(IRQ_USART1 / 32) = 1u << (IRQ_USART1 % 32);
}

static long bus_write(void *ctx, const uint8_t *data, size_t n)
{
    stm32f4_uart *u = (stm32f4_uart *)ctx;
    /* The bytes' wire time (10 bits each) twice over, and 1 ms (integers: no soft double). */
    const int64_t deadline = stm32f4_now_ns() + 1000000
                             + (int64_t)((uint64_t)n * 20000000000u / u->baud);
    size_t i;
    for (i = 0; i < n; ++i) {
        while (!(USART_SR(USART1_BASE) & USART_SR_TXE)) {
            if (stm32f4_now_ns() >= deadline) {
                return -1;
            }
        }
        USART_DR(USART1_BASE) = data[i];
    }
    /* Transmission complete: the last stop bit has left the shift register, so the
     * direction pin may go back to receive (cochlea_rt.h). */
    while (!(USART_SR(USART1_BASE) & USART_SR_TC)) {
        if (stm32f4_now_ns() >= deadline) {
            return -1;
        }
    }
    return (long)n;
}

static long bus_read(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns)
{
    stm32f4_uart *u = (stm32f4_uart *)ctx;
    const int64_t deadline = stm32f4_now_ns() + (timeout_ns > 0 ? timeout_ns : 0);
    for (;;) {
        const uint32_t head = u->head;
        uint32_t tail = u->tail;
        size_t got = 0;
        while (got < n && tail != head) {
            data[got++] = u->ring[tail % STM32_RX_RING];
            tail += 1u;
        }
        u->tail = tail;
        if (got > 0) {
            return (long)got;
        }
        if (stm32f4_now_ns() >= deadline) {
            return 0;
        }
        sleep_before(deadline, &u->head, head);
    }
}

static void bus_discard(void *ctx)
{
    stm32f4_uart *u = (stm32f4_uart *)ctx;
    u->tail = u->head;
}

static void bus_direction(void *ctx, int transmit)
{
    (void)ctx;
    GPIOA_BSRR = transmit ? (1u << 8) : (1u << (8 + 16));
}

static int64_t hal_now(void *ctx)
{
    (void)ctx;
    return stm32f4_now_ns();
}

static void hal_wait_until(void *ctx, int64_t deadline_ns)
{
    (void)ctx;
    while (stm32f4_now_ns() < deadline_ns) {
        sleep_before(deadline_ns, 0, 0);
    }
}

void stm32f4_hal(cochlea_hal *hal, stm32f4_uart *u, int rs485)
{
    hal->ctx = u;
    hal->serial_write = bus_write;
    hal->serial_read = bus_read;
    hal->serial_discard_input = bus_discard;
    hal->rs485_direction = rs485 ? bus_direction : 0;
    hal->now_ns = hal_now;
    hal->wait_until_ns = hal_wait_until;
}

/* ---- USART2: the console ---------------------------------------------------------------- */

void stm32f4_console_init(void)
{
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOAEN;
    RCC_APB1ENR |= RCC_APB1ENR_USART2EN;
    /* PA2 TX, PA3 RX: alternate function 7 */
    GPIOA_MODER = (GPIOA_MODER & ~((3u << 4) | (3u << 6))) | (2u << 4) | (2u << 6);
    GPIOA_AFRL = (GPIOA_AFRL & ~((0xfu << 8) | (0xfu << 12)))
                 | (GPIO_AF7_USART << 8) | (GPIO_AF7_USART << 12);
    USART_CR1(USART2_BASE) = 0;
    USART_BRR(USART2_BASE) = (STM32_APB1_HZ + 115200u / 2u) / 115200u; /* OVER8 = 0 */
    USART_CR1(USART2_BASE) = USART_CR1_UE | USART_CR1_TE;
}

void stm32f4_console_write(const char *text)
{
    /* A bounded count of polls a byte (about 1 ms at 168 MHz; a byte takes 87 us at 115200
     * baud): a console that does not drain loses characters, never hangs the firmware. */
    for (; *text; ++text) {
        uint32_t polls;
        for (polls = 0; polls < STM32_SYSCLK_HZ / 10000u; ++polls) {
            if (USART_SR(USART2_BASE) & USART_SR_TXE) {
                break;
            }
        }
        USART_DR(USART2_BASE) = (uint8_t)*text;
    }
}

/* ---- the independent watchdog (section 21.3) -------------------------------------------- */

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

void stm32f4_iwdg_start(uint32_t timeout_ms)
{
    IWDG_KR = 0xCCCCu; /* starts the LSI and the watchdog: it cannot be stopped */
    iwdg_set(timeout_ms);
}

void stm32f4_iwdg_kick(void *ctx)
{
    (void)ctx;
    IWDG_KR = 0xAAAAu;
}

int stm32f4_reset_by_watchdog(void)
{
    const uint32_t csr = RCC_CSR;
    RCC_CSR = csr | RCC_CSR_RMVF;
    return (csr & (RCC_CSR_IWDGRSTF | RCC_CSR_WWDGRSTF)) != 0u;
}

void stm32f4_iwdg_timeout(uint32_t timeout_ms)
{
    iwdg_set(timeout_ms);
}
