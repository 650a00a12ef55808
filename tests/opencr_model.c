/* A register model of the few STM32F746 peripherals the OpenCR port touches, for
 * tests/test_embedded_opencr.py: the port's HAL (embedded/ports/opencr/hal_opencr.c), the
 * shared clock (embedded/ports/common/stm32_timebase.c) and, for the "firmware" cases, the
 * whole shared firmware with the core, compiled for the host with BOARD_HOST_MODEL, so that
 * every register access comes here (stm32f746_regs.h: model_reg).
 *
 * What the model does: TIM2's counter advances STEP counts at each read (the clock moves as
 * the code polls it); USART3's TXE is always set and TC only TC_POLLS reads of the status
 * register after the last byte written to TDR (never, with --tc-stuck); its DMA (stream 1)
 * is a ring the test fills (dma_put), NDTR counting down and reloading, the transfer-complete
 * flag and its interrupt handler; GPIOC's and GPIOF's BSRR move their ODR. Every write to
 * TDR, BSRR (the direction pin PC9, the power switch PF15) and the console's TDR is an event
 * with the model's time, printed for the test:
 *   event <t_ns> <what> <value>
 * then the case's own "key value" lines. No Dynamixel answers on the bus.
 *
 * With "emulator PTY" the model's line is a pseudo-terminal (cochlea-emulator's): the bytes
 * written to TDR go out when TC is reported, the bytes that come in are the DMA's (and an
 * IDLE interrupt), TIM2 counts the host's monotonic clock and SysTick fires from the model's
 * WFI at its period: the whole firmware runs in real time against the virtual chain. Each
 * power event then also prints the bus's bytes so far: power_at <on> <sent> <received>.
 *
 * Usage: opencr_model CASE [--tc-stuck] [--watchdog-reset]; CASE: ring, overflow, pending,
 * timeout, write, power, firmware, emulator PTY. */
#define _DEFAULT_SOURCE /* cfmakeraw, nanosleep, clock_gettime */
#include <fcntl.h>
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "board.h"
#include "hal_opencr.h"
#include "stm32f746_regs.h"

void SysTick_Handler(void);

#define STEP 100u          /* TIM2 counts a read (0.93 us at 108 MHz) */
#define TC_POLLS 20u       /* status reads from the last TDR write until TC */
#define SENTINEL 0xA5A5A5A5u

static uint32_t periph[0x30000u / 4u]; /* 0x40000000 .. 0x4002FFFF */
static uint32_t core[0x1000u / 4u];    /* 0xE000E000 .. 0xE000EFFF */
static uint64_t counts;                /* TIM2 */
static uint32_t tc_polls = 0xFFFFFFFFu; /* status reads since the last TDR write */
static int tc_stuck, tc_seen_after_write;
static uint32_t ndtr = OPENCR_RX_RING, dma_pos, lisr;
static volatile uint32_t *pending;
static uint32_t pending_address;
static char console[8192];
static size_t console_n;
static int ended;
static jmp_buf parked;
static uint32_t bus_bytes;
static int line_fd = -1; /* the pseudo-terminal, in the emulator case */
static uint8_t tx_pending[4096];
static size_t tx_n;
static uint32_t rx_bytes, idle_pending;
static int64_t clock_start_ns, next_tick_ns;

static int64_t host_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

void DMA1_Stream1_IRQHandler(void);
void USART3_IRQHandler(void);
static void dma_put(const uint8_t *bytes, size_t n, int isr);

/* The line's bytes in: into the DMA's ring, then the IDLE interrupt (the burst ended). */
static void pump(void)
{
    uint8_t buf[512];
    ssize_t n;
    if (line_fd < 0) {
        return;
    }
    while ((n = read(line_fd, buf, sizeof buf)) > 0) {
        dma_put(buf, (size_t)n, 1);
        rx_bytes += (uint32_t)n;
        idle_pending = 1;
    }
    if (idle_pending) {
        USART3_IRQHandler();
    }
}

/* The bytes written to TDR out on the line, once the model says they left (TC). */
static void flush_line(void)
{
    size_t done = 0;
    while (line_fd >= 0 && done < tx_n) {
        const ssize_t n = write(line_fd, tx_pending + done, tx_n - done);
        if (n > 0) {
            done += (size_t)n;
        }
    }
    tx_n = 0;
}

static int64_t now_ns(void)
{
    return (int64_t)(counts * 1000000000u / STM32_TIMER_HZ);
}

static void event(const char *what, long value)
{
    printf("event %lld %s %ld\n", (long long)now_ns(), what, value);
}

static volatile uint32_t *raw(uint32_t a)
{
    if (a >= 0x40000000u && a < 0x40030000u) {
        return &periph[(a - 0x40000000u) / 4u];
    }
    if (a >= 0xE000E000u && a < 0xE000F000u) {
        return &core[(a - 0xE000E000u) / 4u];
    }
    fprintf(stderr, "unmodelled register %08x\n", (unsigned)a);
    exit(90);
}

static int write_only(uint32_t a)
{
    return a == USART3_BASE + 0x28u || a == USART6_BASE + 0x28u || a == USART2_BASE + 0x28u
           || a == GPIOC_BASE + 0x18u || a == GPIOF_BASE + 0x18u || a == USART3_BASE + 0x20u
           || a == DMA1_BASE + 0x08u;
}

static void written(uint32_t a, uint32_t v)
{
    if (a == GPIOC_BASE + 0x18u || a == GPIOF_BASE + 0x18u) {
        uint32_t *odr = (uint32_t *)raw(a - 0x18u + 0x14u);
        const uint32_t pin = a == GPIOC_BASE + 0x18u ? OPENCR_DXL_DIR_PIN : OPENCR_DXL_POWER_PIN;
        *odr = (*odr | (v & 0xFFFFu)) & ~(v >> 16);
        if (v & ((1u << pin) | (1u << (pin + 16u)))) {
            event(pin == OPENCR_DXL_DIR_PIN ? "direction" : "power", (v >> pin) & 1u);
            if (pin == OPENCR_DXL_POWER_PIN) {
                printf("power_at %u %u %u\n", (unsigned)((v >> pin) & 1u), (unsigned)bus_bytes,
                       (unsigned)rx_bytes);
            }
        }
    } else if (a == USART3_BASE + 0x28u) {
        tc_polls = 0;
        tc_seen_after_write = 0;
        bus_bytes += 1u;
        if (line_fd >= 0) {
            if (tx_n < sizeof tx_pending) {
                tx_pending[tx_n++] = (uint8_t)v;
            }
        } else {
            event("bus", (long)(v & 0xFFu));
        }
    } else if (a == USART6_BASE + 0x28u) {
        if (console_n + 1 < sizeof console) {
            console[console_n++] = (char)v;
            console[console_n] = '\0';
        }
        if ((char)v == '\n') {
            const char *line = console_n >= 2 ? console + console_n - 2 : console;
            while (line > console && line[-1] != '\n') {
                --line;
            }
            if (strncmp(line, "end ", 4) == 0) {
                ended = 1;
            }
        }
    } else if (a == DMA1_BASE + 0x08u) {
        lisr &= ~v;
    } else if (a == USART3_BASE + 0x20u && (v & USART_ICR_IDLECF)) {
        idle_pending = 0;
    }
}

static void settle(void)
{
    if (pending != 0) {
        if (*pending != SENTINEL) {
            written(pending_address, *pending);
        }
        pending = 0;
    }
}

volatile uint32_t *model_reg(uint32_t a)
{
    volatile uint32_t *p;
    settle();
    a &= ~3u;
    p = raw(a);
    if (a == TIM2_BASE + 0x24u) {
        if (line_fd >= 0) {
            counts = (uint64_t)(host_ns() - clock_start_ns) * STM32_TIMER_HZ / 1000000000u;
        } else {
            counts += STEP;
        }
        *p = (uint32_t)counts;
    } else if (a == USART3_BASE + 0x1Cu) {
        uint32_t isr = USART_ISR_TXE;
        if (tc_polls != 0xFFFFFFFFu && !tc_stuck && ++tc_polls >= TC_POLLS) {
            isr |= USART_ISR_TC;
            if (!tc_seen_after_write) {
                tc_seen_after_write = 1;
                if (line_fd >= 0) {
                    flush_line();
                } else {
                    event("tc", 1);
                }
            }
        }
        if (idle_pending) {
            isr |= USART_ISR_IDLE;
        }
        *p = isr;
    } else if (a == USART6_BASE + 0x1Cu || a == USART2_BASE + 0x1Cu) {
        *p = USART_ISR_TXE | USART_ISR_TC;
    } else if (a == DMA1_BASE + 0x14u + 0x18u * BUS_DMA_STREAM) {
        pump();
        *p = ndtr;
    } else if (a == DMA1_BASE + 0x00u) {
        *p = lisr;
    }
    if (write_only(a)) {
        *p = SENTINEL;
        pending = p;
        pending_address = a;
    }
    return p;
}

/* The DMA takes n bytes off the line into the ring; at the ring's end NDTR reloads, the
 * transfer-complete flag is set and (isr) its interrupt runs. */
static void dma_put(const uint8_t *bytes, size_t n, int isr)
{
    size_t i;
    for (i = 0; i < n; ++i) {
        opencr_bus_ring()[dma_pos] = bytes[i];
        dma_pos = (dma_pos + 1u) % OPENCR_RX_RING;
        if (--ndtr == 0u) {
            ndtr = OPENCR_RX_RING;
            lisr |= 1u << 11; /* TCIF1 */
            if (isr) {
                DMA1_Stream1_IRQHandler();
            }
        }
    }
}

void model_idle(void)
{
    if (ended) {
        longjmp(parked, 1);
    }
    if (line_fd >= 0) {
        /* asleep until the next interrupt: a byte on the line, or SysTick's tick */
        const struct timespec nap = {0, 20000};
        pump();
        nanosleep(&nap, 0);
        if ((SYST_CSR & 1u) && SYST_RVR != 0u) {
            const int64_t period = ((int64_t)SYST_RVR + 1) * 1000000000 / STM32_SYSCLK_HZ;
            const int64_t now = host_ns();
            if (next_tick_ns == 0) {
                next_tick_ns = now + period;
            }
            if (now >= next_tick_ns) {
                next_tick_ns += period;
                SysTick_Handler();
            }
        }
        return;
    }
    counts += STM32_TIMER_HZ / 10000u; /* 100 us asleep */
    if ((SYST_CSR & 1u) && SYST_RVR != 0u) {
        SysTick_Handler();
    }
}

uint32_t board_stack_used(void)
{
    return 0;
}

int opencr_firmware_main(void);

static uint8_t pattern(uint32_t i)
{
    return (uint8_t)(i * 7u + 3u);
}

/* Reads until n bytes came or a read returns 0; checks them against pattern from first. */
static long read_check(size_t n, uint32_t first, int64_t timeout_ns)
{
    uint8_t buf[4096];
    size_t got = 0, i;
    while (got < n) {
        const long r = opencr_bus_read(0, buf + got, n - got, timeout_ns);
        if (r <= 0) {
            break;
        }
        got += (size_t)r;
    }
    for (i = 0; i < got; ++i) {
        if (buf[i] != pattern(first + (uint32_t)i)) {
            printf("mismatch %u\n", (unsigned)i);
            return -1;
        }
    }
    return (long)got;
}

static void put_pattern(uint32_t first, size_t n, int isr)
{
    uint8_t buf[4096];
    size_t i;
    for (i = 0; i < n; ++i) {
        buf[i] = pattern(first + (uint32_t)i);
    }
    dma_put(buf, n, isr);
}

int main(int argc, char **argv)
{
    const char *what = argc > 1 ? argv[1] : "";
    int i;
    for (i = 2; i < argc; ++i) {
        tc_stuck |= strcmp(argv[i], "--tc-stuck") == 0;
        if (strcmp(argv[i], "--watchdog-reset") == 0) {
            *raw(0x40023874u) = RCC_CSR_IWDGRSTF;
        }
    }
    setvbuf(stdout, 0, _IOLBF, 0);
    if (strcmp(what, "emulator") == 0) {
        struct termios t;
        line_fd = argc > 2 ? open(argv[2], O_RDWR | O_NOCTTY | O_NONBLOCK) : -1;
        if (line_fd < 0 || tcgetattr(line_fd, &t) != 0) {
            fprintf(stderr, "opencr_model: cannot open the line %s\n", argc > 2 ? argv[2] : "");
            return 2;
        }
        cfmakeraw(&t);
        tcsetattr(line_fd, TCSANOW, &t);
        clock_start_ns = host_ns();
        what = "firmware";
    }
    board_clock_start();
    if (strcmp(what, "firmware") == 0) {
        if (setjmp(parked) == 0) {
            opencr_firmware_main();
        }
        settle();
        printf("console_begin\n%s\nconsole_end\n", console);
        printf("power_pin %u\n", (unsigned)((periph[(GPIOF_BASE + 0x14u - 0x40000000u) / 4u]
                                            >> OPENCR_DXL_POWER_PIN) & 1u));
        printf("bus_bytes %u\n", (unsigned)bus_bytes);
        printf("rx_bytes %u\n", (unsigned)rx_bytes);
        printf("laps %u\n", (unsigned)opencr_bus_dma_laps());
        return 0;
    }
    board_bus_init(4000000u);
    printf("brr %u\n", (unsigned)USART_BRR(USART3_BASE));
    printf("dma_scr %u\n", (unsigned)DMA_SCR(DMA1_BASE, BUS_DMA_STREAM));
    printf("dma_par %u\n", (unsigned)DMA_SPAR(DMA1_BASE, BUS_DMA_STREAM));
    printf("cr3 %u\n", (unsigned)USART_CR3(USART3_BASE));
    if (strcmp(what, "ring") == 0) {
        /* 1000 bytes, read; then 100 more across the ring's end, read */
        put_pattern(0, 1000, 1);
        printf("first %ld\n", read_check(1000, 0, 1000000));
        put_pattern(1000, 100, 1);
        printf("second %ld\n", read_check(100, 1000, 1000000));
        printf("laps %u\n", (unsigned)opencr_bus_dma_laps());
        printf("overflows %u\n", (unsigned)board_bus_rx_overflows());
    } else if (strcmp(what, "pending") == 0) {
        /* the lap's interrupt not yet run when the read looks at NDTR */
        put_pattern(0, 1000, 1);
        printf("first %ld\n", read_check(1000, 0, 1000000));
        put_pattern(1000, 100, 0);
        printf("second %ld\n", read_check(100, 1000, 1000000));
        DMA1_Stream1_IRQHandler(); /* taken late */
        put_pattern(1100, 10, 1);
        printf("third %ld\n", read_check(10, 1100, 1000000));
        printf("overflows %u\n", (unsigned)board_bus_rx_overflows());
    } else if (strcmp(what, "overflow") == 0) {
        /* the ring and 50 bytes more before any read: the 50 oldest are lost */
        put_pattern(0, OPENCR_RX_RING + 50u, 1);
        printf("got %ld\n", read_check(OPENCR_RX_RING, 50, 1000000));
        printf("overflows %u\n", (unsigned)board_bus_rx_overflows());
    } else if (strcmp(what, "timeout") == 0) {
        const int64_t before = now_ns();
        uint8_t b;
        printf("got %ld\n", opencr_bus_read(0, &b, 1, 2000000));
        printf("waited_ns %lld\n", (long long)(now_ns() - before));
    } else if (strcmp(what, "write") == 0) {
        static const uint8_t frame[] = {0xFF, 0xFF, 0xFD, 0x00, 0xFE, 0x03};
        int64_t before;
        opencr_bus_direction(0, 1);
        before = now_ns();
        printf("wrote %ld\n", opencr_bus_write(0, frame, sizeof frame));
        printf("write_ns %lld\n", (long long)(now_ns() - before));
        opencr_bus_direction(0, 0);
        settle();
    } else if (strcmp(what, "power") == 0) {
        board_bus_power(1);
        settle();
        printf("moder_f %u\n", (unsigned)periph[(GPIOF_BASE - 0x40000000u) / 4u]);
        board_bus_power(0);
        settle();
        printf("power_pin %u\n", (unsigned)((periph[(GPIOF_BASE + 0x14u - 0x40000000u) / 4u]
                                            >> OPENCR_DXL_POWER_PIN) & 1u));
    } else {
        fprintf(stderr, "unknown case %s\n", what);
        return 2;
    }
    return 0;
}
