/* cochlea's HAL on the OpenCR board (hal_opencr.h). Register level; RM0385 and PM0253 in
 * stm32f746_regs.h. Every wait here ends at a deadline on the clock or after a bounded count
 * of polls (cochlea_rt.h's contract). */
#include "hal_opencr.h"

#include "board.h"
#include "stm32f746_regs.h"

const char board_name[] = "opencr";

/* A peripheral's clock, enabled and read back: the first access must wait two cycles after
 * the enable (ST's errata for the STM32F74x, "delay after an RCC peripheral clock enabling";
 * their HAL reads the register back, as here). */
static void clock_on(volatile uint32_t *enr, uint32_t bits)
{
    *enr |= bits;
    (void)*enr;
}

/* ---- clocks: HSE 25 MHz -> PLL 216 MHz, AHB 216, APB1 54, APB2 108 (RM0385 section 5.2) -- */

int board_clock_init(void)
{
    const uint32_t pllm = STM32_HSE_HZ / 1000000u; /* 1 MHz at the VCO's input */
    const uint32_t plln = 432u, pllp = 2u, pllq = 9u; /* VCO 432 MHz; /2: 216; /9: 48 */
    if (RCC_CR == 0u) {
        /* No RCC behind this address (silicon always reads HSION and HSIRDY here while the
         * HSI runs the core): an emulator's, whose clock is the machine's. */
        return BOARD_CLOCK_UNMODELLED;
    }
    clock_on(&RCC_APB1ENR, RCC_APB1ENR_PWREN);
    PWR_CR1 |= PWR_CR1_VOS_SCALE1; /* scale 1 (its reset value): needed for 216 MHz */
    RCC_CR |= RCC_CR_HSEON;
    if (!stm32_wait_bits(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY)) {
        return BOARD_CLOCK_NO_HSE;
    }
    RCC_PLLCFGR = pllm | (plln << 6) | (((pllp / 2u) - 1u) << 16) | RCC_PLLCFGR_PLLSRC_HSE
                  | (pllq << 24);
    RCC_CR |= RCC_CR_PLLON;
    if (!stm32_wait_bits(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        return BOARD_CLOCK_NO_PLL;
    }
    /* Over 180 MHz the regulator's over-drive: ODEN, then the switch (section 4.1.4). A part
     * that does not come up is reported as the PLL's failure: nothing runs. */
    PWR_CR1 |= PWR_CR1_ODEN;
    if (!stm32_wait_bits(&PWR_CSR1, PWR_CSR1_ODRDY, PWR_CSR1_ODRDY)) {
        return BOARD_CLOCK_NO_PLL;
    }
    PWR_CR1 |= PWR_CR1_ODSWEN;
    if (!stm32_wait_bits(&PWR_CSR1, PWR_CSR1_ODSWRDY, PWR_CSR1_ODSWRDY)) {
        return BOARD_CLOCK_NO_PLL;
    }
    /* Wait states before the faster clock, read back (section 3.3.2); the ART accelerator. */
    FLASH_ACR = FLASH_ACR_LATENCY_7WS | FLASH_ACR_PRFTEN | FLASH_ACR_ARTEN;
    if ((FLASH_ACR & 0xFu) != FLASH_ACR_LATENCY_7WS) {
        return BOARD_CLOCK_NO_PLL;
    }
    RCC_CFGR = RCC_CFGR_PPRE1_DIV4 | RCC_CFGR_PPRE2_DIV2; /* AHB /1 */
    RCC_CFGR = (RCC_CFGR & ~3u) | RCC_CFGR_SW_PLL;
    if (!stm32_wait_bits(&RCC_CFGR, 3u << 2, RCC_CFGR_SWS_PLL)) {
        return BOARD_CLOCK_NO_PLL;
    }
    return BOARD_CLOCK_PLL;
}

uint32_t opencr_brr_over8(uint32_t clock_hz, uint32_t baud)
{
    const uint32_t div = (2u * clock_hz + baud / 2u) / baud;
    return (div & 0xFFF0u) | ((div & 0xFu) >> 1);
}

/* Output, push-pull, very high speed, at level (set before the pin drives: no glitch). */
static void gpio_output(uint32_t base, uint32_t pin, int level)
{
    GPIO_BSRR(base) = level ? (1u << pin) : (1u << (pin + 16u));
    GPIO_OSPEEDR(base) |= 3u << (2u * pin);
    GPIO_MODER(base) = (GPIO_MODER(base) & ~(3u << (2u * pin))) | (1u << (2u * pin));
}

/* Alternate function af on pin (pins 0-15). */
static void gpio_alternate(uint32_t base, uint32_t pin, uint32_t af)
{
    if (pin < 8u) {
        GPIO_AFRL(base) = (GPIO_AFRL(base) & ~(0xFu << (4u * pin))) | (af << (4u * pin));
    } else {
        GPIO_AFRH(base) = (GPIO_AFRH(base) & ~(0xFu << (4u * (pin - 8u))))
                          | (af << (4u * (pin - 8u)));
    }
    GPIO_OSPEEDR(base) |= 3u << (2u * pin);
    GPIO_MODER(base) = (GPIO_MODER(base) & ~(3u << (2u * pin))) | (2u << (2u * pin));
}

/* ---- the Dynamixel power switch (PF15, high: on) ---------------------------------------- */

void board_bus_power(int on)
{
    clock_on(&RCC_AHB1ENR, RCC_AHB1ENR_GPIOFEN);
    gpio_output(GPIOF_BASE, OPENCR_DXL_POWER_PIN, on);
}

uint32_t board_bus_power_settle_ms(void)
{
    return OPENCR_POWER_SETTLE_MS;
}

/* ---- USART3: the Dynamixel bus, DMA receive into a circular ring ---------------------- */

/* The ring lives in SRAM1 (the linker's .sram1, 0x20010000): the DMA reaches it through the
 * bus matrix, and with the data cache left off (startup_opencr.c) the core reads what the DMA
 * wrote without cache maintenance. */
static volatile uint8_t rx_ring[OPENCR_RX_RING] __attribute__((section(".sram1"), aligned(4)));
static volatile uint32_t dma_laps; /* transfer-complete interrupts: the DMA wrapped */
static volatile uint32_t bus_idles; /* IDLE interrupts: a burst ended (wakes a read) */
static uint32_t rx_tail;            /* bytes taken, since the start (the loop's only) */
static uint32_t rx_seen;            /* the DMA's position last read, since the start */
static uint32_t rx_overflows;       /* bytes lost: the DMA lapped the reader, or an overrun */
static uint32_t bus_baud;

volatile uint8_t *opencr_bus_ring(void)
{
    return rx_ring;
}

uint32_t opencr_bus_dma_laps(void)
{
    return dma_laps;
}

uint32_t opencr_bus_idles(void)
{
    return bus_idles;
}

uint32_t board_bus_rx_overflows(void)
{
    return rx_overflows;
}

void DMA1_Stream1_IRQHandler(void);
void DMA1_Stream1_IRQHandler(void)
{
    const uint32_t flags = DMA_LISR(DMA1_BASE) & DMA_S1_ALL_FLAGS;
    DMA_LIFCR(DMA1_BASE) = flags;
    if (flags & DMA_S1_TCIF) {
        dma_laps = dma_laps + 1u;
    }
}

void USART3_IRQHandler(void);
void USART3_IRQHandler(void)
{
    if (USART_ISR(USART3_BASE) & USART_ISR_IDLE) {
        USART_ICR(USART3_BASE) = USART_ICR_IDLECF;
        bus_idles = bus_idles + 1u;
    }
}

/* Bytes the DMA has written since the start: the laps (its transfer-complete interrupts)
 * times the ring, plus the ring less NDTR (which counts down from the ring's size and
 * reloads). Read until the laps did not move in between; a position behind the last one
 * means the lap's interrupt is still pending (masked, or not yet taken): one more lap. */
static uint32_t rx_written(void)
{
    uint32_t laps, ndtr, written;
    unsigned tries = 0;
    do {
        laps = dma_laps;
        ndtr = DMA_SNDTR(DMA1_BASE, BUS_DMA_STREAM) & 0xFFFFu;
    } while (laps != dma_laps && ++tries < 4u);
    written = laps * OPENCR_RX_RING + (OPENCR_RX_RING - ndtr);
    if ((int32_t)(written - rx_seen) < 0) {
        written += OPENCR_RX_RING;
    }
    rx_seen = written;
    return written;
}

/* The unread bytes up to written: more than the ring means the DMA overwrote the oldest ones
 * (counted lost; reading resumes at the oldest byte still in the ring). An overrun (a byte
 * the DMA did not take in time) is counted the same. */
static void rx_account(uint32_t written)
{
    if (written - rx_tail > OPENCR_RX_RING) {
        rx_overflows += written - rx_tail - OPENCR_RX_RING;
        rx_tail = written - OPENCR_RX_RING;
    }
    if (USART_ISR(USART3_BASE) & USART_ISR_ORE) {
        USART_ICR(USART3_BASE) = USART_ICR_ORECF;
        rx_overflows += 1u;
    }
}

void board_bus_init(uint32_t baud)
{
    uint32_t polls;
    bus_baud = baud;
    clock_on(&RCC_AHB1ENR, RCC_AHB1ENR_GPIOCEN | RCC_AHB1ENR_DMA1EN);
    clock_on(&RCC_APB1ENR, RCC_APB1ENR_USART3EN);
    /* PC9 the direction, low (receive); PC10 TX, PC11 RX (pulled up): AF7 */
    gpio_output(GPIOC_BASE, OPENCR_DXL_DIR_PIN, 0);
    gpio_alternate(GPIOC_BASE, 10u, GPIO_AF7);
    gpio_alternate(GPIOC_BASE, 11u, GPIO_AF7);
    GPIO_PUPDR(GPIOC_BASE) = (GPIO_PUPDR(GPIOC_BASE) & ~(3u << 22)) | (1u << 22);
    USART_CR1(USART3_BASE) = 0;
    USART_CR2(USART3_BASE) = 0;
    USART_CR3(USART3_BASE) = USART_CR3_DMAR;
    USART_BRR(USART3_BASE) = opencr_brr_over8(STM32_APB1_HZ, baud);
    /* DMA1 stream 1, channel 4: USART3's RDR into the ring, circular, bytes, direct mode;
     * its transfer-complete interrupt counts the laps. Disabled first (bounded). */
    DMA_SCR(DMA1_BASE, BUS_DMA_STREAM) = 0;
    for (polls = 0; polls < 100000u && (DMA_SCR(DMA1_BASE, BUS_DMA_STREAM) & DMA_SCR_EN);
         ++polls) {
    }
    DMA_LIFCR(DMA1_BASE) = DMA_S1_ALL_FLAGS;
    DMA_SPAR(DMA1_BASE, BUS_DMA_STREAM) = USART3_BASE + 0x24u; /* USART_RDR */
    DMA_SM0AR(DMA1_BASE, BUS_DMA_STREAM) = (uint32_t)(uintptr_t)rx_ring;
    DMA_SNDTR(DMA1_BASE, BUS_DMA_STREAM) = OPENCR_RX_RING;
    DMA_SFCR(DMA1_BASE, BUS_DMA_STREAM) = 0;
    DMA_SCR(DMA1_BASE, BUS_DMA_STREAM) = DMA_SCR_CHSEL(BUS_DMA_CHANNEL) | DMA_SCR_PL_HIGH
                                         | DMA_SCR_MINC | DMA_SCR_CIRC | DMA_SCR_TCIE;
    dma_laps = 0;
    bus_idles = 0;
    rx_tail = rx_seen = rx_overflows = 0;
    DMA_SCR(DMA1_BASE, BUS_DMA_STREAM) |= DMA_SCR_EN;
    USART_CR1(USART3_BASE) = USART_CR1_OVER8 | USART_CR1_UE | USART_CR1_TE | USART_CR1_RE
                             | USART_CR1_IDLEIE;
    NVIC_IPR_BYTE(IRQ_USART3) = 0x20u; /* above SysTick */
    NVIC_IPR_BYTE(IRQ_DMA1_STREAM1) = 0x20u;
    NVIC_ISER(IRQ_USART3 / 32) = 1u << (IRQ_USART3 % 32);
    NVIC_ISER(IRQ_DMA1_STREAM1 / 32) = 1u << (IRQ_DMA1_STREAM1 % 32);
}

long opencr_bus_write(void *ctx, const uint8_t *data, size_t n)
{
    /* The bytes' wire time (10 bits each) twice over, and 1 ms (integers: no soft double). */
    const int64_t deadline = board_now_ns() + 1000000
                             + (int64_t)((uint64_t)n * 20000000000u / bus_baud);
    size_t i;
    (void)ctx;
    USART_ICR(USART3_BASE) = USART_ICR_TCCF;
    for (i = 0; i < n; ++i) {
        while (!(USART_ISR(USART3_BASE) & USART_ISR_TXE)) {
            if (board_now_ns() >= deadline) {
                return -1;
            }
        }
        USART_TDR(USART3_BASE) = data[i];
    }
    /* Transmission complete: the last stop bit has left the shift register, so the
     * direction pin may go back to receive (cochlea_rt.h). A write to TDR clears TC. */
    while (!(USART_ISR(USART3_BASE) & USART_ISR_TC)) {
        if (board_now_ns() >= deadline) {
            return -1;
        }
    }
    return (long)n;
}

long opencr_bus_read(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns)
{
    const int64_t deadline = board_now_ns() + (timeout_ns > 0 ? timeout_ns : 0);
    (void)ctx;
    for (;;) {
        const uint32_t idles = bus_idles;
        const uint32_t written = rx_written();
        size_t got = 0;
        rx_account(written);
        while (got < n && rx_tail != written) {
            data[got++] = rx_ring[rx_tail % OPENCR_RX_RING];
            rx_tail += 1u;
        }
        if (got > 0) {
            return (long)got;
        }
        if (board_now_ns() >= deadline) {
            return 0;
        }
        /* a reply's end (IDLE) or the next tick wakes it, never past the deadline */
        stm32_sleep_before(deadline, &bus_idles, idles);
    }
}

static void bus_discard(void *ctx)
{
    (void)ctx;
    rx_tail = rx_written();
}

void opencr_bus_direction(void *ctx, int transmit)
{
    (void)ctx;
    GPIO_BSRR(GPIOC_BASE) = transmit ? (1u << OPENCR_DXL_DIR_PIN)
                                     : (1u << (OPENCR_DXL_DIR_PIN + 16u));
}

void board_bus_hal(cochlea_hal *hal, int rs485)
{
    hal->ctx = 0;
    hal->serial_write = opencr_bus_write;
    hal->serial_read = opencr_bus_read;
    hal->serial_discard_input = bus_discard;
    hal->rs485_direction = rs485 ? opencr_bus_direction : 0;
    hal->now_ns = stm32_hal_now;
    hal->wait_until_ns = stm32_hal_wait_until;
}

/* ---- USART6: the console (PC6 TX, PC7 RX: AF8), 115200 8N1, polled --------------------- */

void board_console_init(void)
{
    clock_on(&RCC_AHB1ENR, RCC_AHB1ENR_GPIOCEN);
    clock_on(&RCC_APB2ENR, RCC_APB2ENR_USART6EN);
    gpio_alternate(GPIOC_BASE, 6u, GPIO_AF8);
    gpio_alternate(GPIOC_BASE, 7u, GPIO_AF8);
    USART_CR1(USART6_BASE) = 0;
    USART_BRR(USART6_BASE) = opencr_brr_over8(STM32_APB2_HZ, 115200u);
    USART_CR1(USART6_BASE) = USART_CR1_OVER8 | USART_CR1_UE | USART_CR1_TE;
}

void board_console_write(const char *text)
{
    /* A bounded count of polls a byte (about 1 ms at 216 MHz; a byte takes 87 us at 115200
     * baud): a console that does not drain loses characters, never hangs the firmware. */
    for (; *text; ++text) {
        uint32_t polls;
        for (polls = 0; polls < STM32_SYSCLK_HZ / 10000u; ++polls) {
            if (USART_ISR(USART6_BASE) & USART_ISR_TXE) {
                break;
            }
        }
        USART_TDR(USART6_BASE) = (uint8_t)*text;
    }
}

/* ---- USART2: the row stream (PD5 TX: AF7), transmit only --------------------------------- */

void board_stream_uart_init(uint32_t baud)
{
    clock_on(&RCC_AHB1ENR, RCC_AHB1ENR_GPIODEN);
    clock_on(&RCC_APB1ENR, RCC_APB1ENR_USART2EN);
    gpio_alternate(GPIOD_BASE, 5u, GPIO_AF7);
    USART_CR1(USART2_BASE) = 0;
    USART_CR2(USART2_BASE) = 0;
    USART_CR3(USART2_BASE) = 0;
    USART_BRR(USART2_BASE) = opencr_brr_over8(STM32_APB1_HZ, baud);
    USART_CR1(USART2_BASE) = USART_CR1_OVER8 | USART_CR1_UE | USART_CR1_TE;
    NVIC_IPR_BYTE(IRQ_USART2) = 0x80u; /* below SysTick and the bus */
    NVIC_ISER(IRQ_USART2 / 32) = 1u << (IRQ_USART2 % 32);
}

int board_stream_tx_ready(void)
{
    return (USART_ISR(USART2_BASE) & USART_ISR_TXE) != 0u;
}

void board_stream_tx_byte(uint8_t byte)
{
    USART_TDR(USART2_BASE) = byte;
}

void board_stream_tx_interrupt(int on)
{
    if (on) {
        USART_CR1(USART2_BASE) |= USART_CR1_TXEIE;
    } else {
        USART_CR1(USART2_BASE) &= ~USART_CR1_TXEIE;
    }
}

void USART2_IRQHandler(void);
void USART2_IRQHandler(void)
{
    stream_tx_interrupt();
}
