/* The OpenCR port's registers and rates for the shared STM32 files (board.h,
 * stm32_timebase.c). */
#ifndef COCHLEA_OPENCR_BOARD_CONFIG_H
#define COCHLEA_OPENCR_BOARD_CONFIG_H

#include "hal_opencr.h"
#include "stm32f746_regs.h"

#endif /* COCHLEA_OPENCR_BOARD_CONFIG_H */
