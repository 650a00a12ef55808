/* cochlea's HAL on an STM32F405/407 (hal_stm32f4.h). Register level; RM0090 and PM0214
 * sections in stm32f4_regs.h. Every wait here ends at a deadline on the clock or after a
 * bounded count of polls (cochlea_rt.h's contract). */
#include "hal_stm32f4.h"

#include "board.h"
#include "stm32f4_regs.h"

/* ---- interrupts ------------------------------------------------------------------------- */

/* ---- clocks: HSE -> PLL 168 MHz, AHB 168, APB1 42, APB2 84 (RM0090 section 7.2) ---------- */

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
    if (!stm32_wait_bits(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY)) {
        return STM32F4_CLOCK_NO_HSE;
    }
    /* Wait states before the faster clock (section 3.5.1), the caches on. */
    FLASH_ACR = FLASH_ACR_LATENCY_5WS | FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN;
    RCC_CFGR = RCC_CFGR_PPRE1_DIV4 | RCC_CFGR_PPRE2_DIV2; /* AHB /1 */
    RCC_PLLCFGR = pllm | (plln << 6) | (((pllp / 2u) - 1u) << 16) | RCC_PLLCFGR_PLLSRC_HSE
                  | (pllq << 24);
    RCC_CR |= RCC_CR_PLLON;
    if (!stm32_wait_bits(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        return STM32F4_CLOCK_NO_PLL;
    }
    RCC_CFGR = (RCC_CFGR & ~3u) | RCC_CFGR_SW_PLL;
    if (!stm32_wait_bits(&RCC_CFGR, 3u << 2, RCC_CFGR_SWS_PLL)) {
        return STM32F4_CLOCK_NO_PLL;
    }
    return STM32F4_CLOCK_PLL;
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
    const int64_t deadline = board_now_ns() + 1000000
                             + (int64_t)((uint64_t)n * 20000000000u / u->baud);
    size_t i;
    for (i = 0; i < n; ++i) {
        while (!(USART_SR(USART1_BASE) & USART_SR_TXE)) {
            if (board_now_ns() >= deadline) {
                return -1;
            }
        }
        USART_DR(USART1_BASE) = data[i];
    }
    /* Transmission complete: the last stop bit has left the shift register, so the
     * direction pin may go back to receive (cochlea_rt.h). */
    while (!(USART_SR(USART1_BASE) & USART_SR_TC)) {
        if (board_now_ns() >= deadline) {
            return -1;
        }
    }
    return (long)n;
}

static long bus_read(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns)
{
    stm32f4_uart *u = (stm32f4_uart *)ctx;
    const int64_t deadline = board_now_ns() + (timeout_ns > 0 ? timeout_ns : 0);
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
        if (board_now_ns() >= deadline) {
            return 0;
        }
        stm32_sleep_before(deadline, &u->head, head);
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

void stm32f4_hal(cochlea_hal *hal, stm32f4_uart *u, int rs485)
{
    hal->ctx = u;
    hal->serial_write = bus_write;
    hal->serial_read = bus_read;
    hal->serial_discard_input = bus_discard;
    hal->rs485_direction = rs485 ? bus_direction : 0;
    hal->now_ns = stm32_hal_now;
    hal->wait_until_ns = stm32_hal_wait_until;
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
