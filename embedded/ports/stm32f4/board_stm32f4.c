/* The STM32F405/407 as the shared firmware's board (embedded/ports/common/board.h): the
 * console, the bus and the clocks are the port's own (hal_stm32f4.c); TIM2's clock, SysTick's
 * period, the sleep and the watchdog are the STM32 ports' shared ones
 * (embedded/ports/common/stm32_timebase.c). The board has no bus power switch: the motors'
 * supply is the user's. */
#include "board.h"
#include "hal_stm32f4.h"

const char board_name[] = "stm32f4";

static stm32f4_uart bus;

int board_clock_init(void)
{
    return stm32f4_clock_init(); /* enum stm32f4_clock: the same four values as board_clock */
}

void board_console_init(void)
{
    stm32f4_console_init();
}

void board_console_write(const char *text)
{
    stm32f4_console_write(text);
}

void board_bus_init(uint32_t baud)
{
    stm32f4_bus_init(&bus, baud);
}

void board_bus_hal(cochlea_hal *hal, int rs485)
{
    stm32f4_hal(hal, &bus, rs485);
}

uint32_t board_bus_rx_overflows(void)
{
    return bus.overflows;
}

void board_bus_power(int on)
{
    (void)on;
}

uint32_t board_bus_power_settle_ms(void)
{
    return 0;
}

/* stm32f4_clock_init's answers are board_clock_init's. */
typedef char clock_answers_agree[((int)STM32F4_CLOCK_PLL == (int)BOARD_CLOCK_PLL
                                  && (int)STM32F4_CLOCK_UNMODELLED == (int)BOARD_CLOCK_UNMODELLED
                                  && (int)STM32F4_CLOCK_NO_HSE == (int)BOARD_CLOCK_NO_HSE
                                  && (int)STM32F4_CLOCK_NO_PLL == (int)BOARD_CLOCK_NO_PLL)
                                 ? 1 : -1];
