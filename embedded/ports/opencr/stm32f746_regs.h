/* The few STM32F746 and Cortex-M7 registers the OpenCR port touches, at the register level
 * (no vendor library: no Debian package ships the STM32 CMSIS headers). Each block names the
 * section of the reference it comes from:
 *   RM0385, "STM32F75xxx and STM32F74xxx advanced Arm-based 32-bit MCUs" (reference manual),
 *   and PM0253, "STM32F7 Series and STM32H7 Series Cortex-M7 processor programming manual"
 *   (the core's System Control Block, SysTick, NVIC, FPU, caches).
 * Addresses are the memory map of RM0385 section 2.2.2. The section numbers are RM0385's as
 * remembered, not checked against the PDF here: where unsure, the chapter is named instead.
 * The names that the shared files (embedded/ports/common/stm32_timebase.c) use are spelled
 * as in the STM32F4 port's stm32f4_regs.h: TIM2, the IWDG, RCC_CSR's flags, SysTick and the
 * SCB sit at the same addresses with the same bits on both chips.
 *
 * A host build against a register model (BOARD_HOST_MODEL, tests/test_embedded_opencr.py)
 * routes every register through model_reg(address), which returns the model's word. */
#ifndef COCHLEA_STM32F746_REGS_H
#define COCHLEA_STM32F746_REGS_H

#include <stdint.h>

#ifdef BOARD_HOST_MODEL
volatile uint32_t *model_reg(uint32_t address);
#define REG32(address) (*model_reg((uint32_t)(address)))
#define REG8(address) (*(volatile uint8_t *)model_reg((uint32_t)(address)))
#else
#define REG32(address) (*(volatile uint32_t *)(uintptr_t)(address))
#define REG8(address) (*(volatile uint8_t *)(uintptr_t)(address))
#endif

/* ---- RCC, reset and clock control: RM0385 section 5.3 (register map 5.3.28) -------------- */
#define RCC_BASE 0x40023800u
#define RCC_CR REG32(RCC_BASE + 0x00u)      /* 5.3.1 */
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_PLLCFGR REG32(RCC_BASE + 0x04u) /* 5.3.2: PLLM 5:0, PLLN 14:6, PLLP 17:16,
                                             * PLLSRC 22, PLLQ 27:24 */
#define RCC_PLLCFGR_PLLSRC_HSE (1u << 22)
#define RCC_CFGR REG32(RCC_BASE + 0x08u)    /* 5.3.3: SW 1:0, SWS 3:2, HPRE 7:4, PPRE1 12:10,
                                             * PPRE2 15:13 */
#define RCC_CFGR_SW_PLL 2u
#define RCC_CFGR_SWS_PLL (2u << 2)
#define RCC_CFGR_PPRE1_DIV4 (5u << 10)
#define RCC_CFGR_PPRE2_DIV2 (4u << 13)
#define RCC_AHB1ENR REG32(RCC_BASE + 0x30u) /* 5.3.10 */
#define RCC_AHB1ENR_GPIOCEN (1u << 2)
#define RCC_AHB1ENR_GPIODEN (1u << 3)
#define RCC_AHB1ENR_GPIOFEN (1u << 5)
#define RCC_AHB1ENR_DMA1EN (1u << 21)
#define RCC_APB1ENR REG32(RCC_BASE + 0x40u) /* 5.3.13 */
#define RCC_APB1ENR_TIM2EN (1u << 0)
#define RCC_APB1ENR_USART2EN (1u << 17)
#define RCC_APB1ENR_USART3EN (1u << 18)
#define RCC_APB1ENR_PWREN (1u << 28)
#define RCC_APB2ENR REG32(RCC_BASE + 0x44u) /* 5.3.14 */
#define RCC_APB2ENR_USART6EN (1u << 5)
#define RCC_CSR REG32(RCC_BASE + 0x74u)     /* 5.3.21 */
#define RCC_CSR_RMVF (1u << 24)
#define RCC_CSR_IWDGRSTF (1u << 29)
#define RCC_CSR_WWDGRSTF (1u << 30)

/* ---- PWR, the regulator's over-drive for 216 MHz: RM0385 sections 4.1.4, 4.4 -------------- */
#define PWR_CR1 REG32(0x40007000u)  /* 4.4.1: VOS 15:14 (11: scale 1), ODEN 16, ODSWEN 17 */
#define PWR_CR1_VOS_SCALE1 (3u << 14)
#define PWR_CR1_ODEN (1u << 16)
#define PWR_CR1_ODSWEN (1u << 17)
#define PWR_CSR1 REG32(0x40007004u) /* 4.4.2: ODRDY 16, ODSWRDY 17 */
#define PWR_CSR1_ODRDY (1u << 16)
#define PWR_CSR1_ODSWRDY (1u << 17)

/* ---- Flash interface: RM0385 section 3.7.1 (FLASH_ACR) ------------------------------------ */
#define FLASH_ACR REG32(0x40023C00u)
#define FLASH_ACR_LATENCY_7WS 7u /* 210-216 MHz at 2.7-3.6 V (section 3.3.2) */
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ARTEN (1u << 9)

/* ---- GPIO: RM0385 section 6.4 (register map 6.4.11) --------------------------------------- */
#define GPIOC_BASE 0x40020800u
#define GPIOD_BASE 0x40020C00u
#define GPIOF_BASE 0x40021400u
#define GPIO_MODER(base) REG32((base) + 0x00u)   /* 6.4.1: 2 bits a pin, 01 output, 10 AF */
#define GPIO_OSPEEDR(base) REG32((base) + 0x08u) /* 6.4.3: 11 very high speed */
#define GPIO_PUPDR(base) REG32((base) + 0x0Cu)   /* 6.4.4: 01 pull-up */
#define GPIO_ODR(base) REG32((base) + 0x14u)     /* 6.4.6 */
#define GPIO_BSRR(base) REG32((base) + 0x18u)    /* 6.4.7: set 15:0, reset 31:16 */
#define GPIO_AFRL(base) REG32((base) + 0x20u)    /* 6.4.9: pins 0-7, 4 bits each */
#define GPIO_AFRH(base) REG32((base) + 0x24u)    /* 6.4.10: pins 8-15 */
#define GPIO_AF7 7u /* USART1..3 (datasheet DS10916, table 12) */
#define GPIO_AF8 8u /* USART6, UART4/5/7/8 */

/* ---- USART, the newer layout (ISR/ICR/RDR/TDR): RM0385 section 31.8 (map 31.8.12) --------- */
#define USART2_BASE 0x40004400u /* APB1 */
#define USART3_BASE 0x40004800u /* APB1 */
#define USART6_BASE 0x40011400u /* APB2 */
#define USART_CR1(base) REG32((base) + 0x00u) /* 31.8.1 */
#define USART_CR1_UE (1u << 0)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_IDLEIE (1u << 4)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_OVER8 (1u << 15)
#define USART_CR2(base) REG32((base) + 0x04u) /* 31.8.2: 0 = 1 stop bit */
#define USART_CR3(base) REG32((base) + 0x08u) /* 31.8.3 */
#define USART_CR3_DMAR (1u << 6)
#define USART_BRR(base) REG32((base) + 0x0Cu) /* 31.8.4: OVER8 = 1: BRR[15:4] = USARTDIV[15:4],
                                               * BRR[2:0] = USARTDIV[3:0] >> 1 */
#define USART_ISR(base) REG32((base) + 0x1Cu) /* 31.8.8 */
#define USART_ISR_ORE (1u << 3)
#define USART_ISR_IDLE (1u << 4)
#define USART_ISR_TC (1u << 6)
#define USART_ISR_TXE (1u << 7)
#define USART_ICR(base) REG32((base) + 0x20u) /* 31.8.9: write 1 to clear */
#define USART_ICR_ORECF (1u << 3)
#define USART_ICR_IDLECF (1u << 4)
#define USART_ICR_TCCF (1u << 6)
#define USART_RDR(base) REG32((base) + 0x24u) /* 31.8.10 */
#define USART_TDR(base) REG32((base) + 0x28u) /* 31.8.11 */

/* ---- DMA1: RM0385 section 8.5 (register map 8.5.11) --------------------------------------- */
#define DMA1_BASE 0x40026000u
#define DMA_LISR(base) REG32((base) + 0x00u)  /* 8.5.1: stream 1's flags are bits 6-11 */
#define DMA_LIFCR(base) REG32((base) + 0x08u) /* 8.5.3: write 1 to clear */
#define DMA_S1_TCIF (1u << 11)
#define DMA_S1_ALL_FLAGS (0x3Du << 6) /* FEIF, DMEIF, TEIF, HTIF, TCIF of stream 1 */
#define DMA_SCR(base, s) REG32((base) + 0x10u + 0x18u * (s))   /* 8.5.5 */
#define DMA_SCR_EN (1u << 0)
#define DMA_SCR_TCIE (1u << 4)
#define DMA_SCR_CIRC (1u << 8)
#define DMA_SCR_MINC (1u << 10)
#define DMA_SCR_PL_HIGH (2u << 16)
#define DMA_SCR_CHSEL(c) ((uint32_t)(c) << 25)
#define DMA_SNDTR(base, s) REG32((base) + 0x14u + 0x18u * (s)) /* 8.5.6: counts down */
#define DMA_SPAR(base, s) REG32((base) + 0x18u + 0x18u * (s))  /* 8.5.7 */
#define DMA_SM0AR(base, s) REG32((base) + 0x1Cu + 0x18u * (s)) /* 8.5.8 */
#define DMA_SFCR(base, s) REG32((base) + 0x24u + 0x18u * (s))  /* 8.5.10: 0: direct mode */
/* USART3_RX: DMA1 stream 1, channel 4 (RM0385's DMA1 request mapping table, section 8.3.4;
 * OpenCR's own drv_uart.c uses the same). */
#define BUS_DMA_STREAM 1
#define BUS_DMA_CHANNEL 4

/* ---- TIM2, a 32-bit timer: RM0385, "General-purpose timers (TIM2/TIM3/TIM4/TIM5)" ------ */
#define TIM2_BASE 0x40000000u
#define TIM2_CR1 REG32(TIM2_BASE + 0x00u) /* TIMx_CR1: CEN 0 */
#define TIM2_EGR REG32(TIM2_BASE + 0x14u) /* TIMx_EGR: UG 0 loads PSC */
#define TIM2_CNT REG32(TIM2_BASE + 0x24u) /* TIMx_CNT */
#define TIM2_PSC REG32(TIM2_BASE + 0x28u) /* TIMx_PSC */
#define TIM2_ARR REG32(TIM2_BASE + 0x2Cu) /* TIMx_ARR */

/* ---- IWDG: RM0385, "Independent watchdog (IWDG)", its registers (as RM0090 21.4) -------- */
#define IWDG_KR REG32(0x40003000u)  /* IWDG_KR: 0x5555 unlock, 0xAAAA reload, 0xCCCC start */
#define IWDG_PR REG32(0x40003004u)  /* IWDG_PR: prescaler /4 << PR */
#define IWDG_RLR REG32(0x40003008u) /* IWDG_RLR: 12-bit reload */
#define IWDG_SR REG32(0x4000300Cu)  /* IWDG_SR: PVU 0, RVU 1, WVU 2 (an update in progress) */

/* ---- Interrupt numbers: RM0385, "NVIC", the STM32F74x vector table ---------------------- */
#define IRQ_DMA1_STREAM1 12
#define IRQ_USART2 38
#define IRQ_USART3 39
#define IRQ_COUNT 98 /* the vector table's external interrupts (0..97, SPDIF_RX last) */

/* ---- Cortex-M7 core: PM0253 section 4 ----------------------------------------------------- */
#define SYST_CSR REG32(0xE000E010u) /* 4.4.1: ENABLE 0, TICKINT 1, CLKSOURCE 2 (processor) */
#define SYST_RVR REG32(0xE000E014u) /* 4.4.2: 24-bit reload */
#define SYST_CVR REG32(0xE000E018u) /* 4.4.3: counts down */
#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n))          /* 4.2.2 */
#define NVIC_ICER(n) REG32(0xE000E180u + 4u * (n))          /* 4.2.3: a 1 disables */
#define NVIC_ICPR(n) REG32(0xE000E280u + 4u * (n))          /* 4.2.5: a 1 clears pending */
#define NVIC_REGISTERS 8u /* ICER/ICPR words: 256 interrupt lines, more than the 98 used */
#define NVIC_IPR_BYTE(irq) REG8(0xE000E400u + (uint32_t)(irq)) /* 4.2.7 */
#define SCB_ICSR REG32(0xE000ED04u)  /* 4.3.3: PENDSTSET 26 */
#define SCB_ICSR_PENDSTSET (1u << 26)
#define SCB_ICSR_PENDSTCLR (1u << 25)
#define SCB_ICSR_PENDSVCLR (1u << 27)
#define SCB_VTOR REG32(0xE000ED08u)  /* 4.3.4 */
#define SCB_CCR REG32(0xE000ED14u)   /* 4.3.7: DC 16, IC 17 */
#define SCB_CCR_IC (1u << 17)
#define SCB_SHPR3 REG32(0xE000ED20u) /* 4.3.9: SysTick priority 31:24 */
#define SCB_CPACR REG32(0xE000ED88u) /* 4.6.1 (FPU): CP10, CP11 full access 23:20 */
#define SCB_ICIALLU REG32(0xE000EF50u) /* 4.8.4 (caches): invalidate the I-cache */

#endif /* COCHLEA_STM32F746_REGS_H */
