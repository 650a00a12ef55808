/* The STM32F4 port's registers and rates for the shared STM32 files (board.h,
 * stm32_timebase.c). */
#ifndef COCHLEA_STM32F4_BOARD_CONFIG_H
#define COCHLEA_STM32F4_BOARD_CONFIG_H

#include "hal_stm32f4.h"
#include "stm32f4_regs.h"

#endif /* COCHLEA_STM32F4_BOARD_CONFIG_H */
