/* The few STM32F405/407 and Cortex-M4 registers the port touches, at the register level (no
 * vendor library: no Debian package ships the STM32 CMSIS headers). Each block names the
 * section of the reference it comes from:
 *   RM0090, "STM32F405/415, STM32F407/417, STM32F427/437 and STM32F429/439 advanced
 *   Arm-based 32-bit MCUs", and PM0214, "STM32 Cortex-M4 MCUs and MPUs programming
 *   manual" (the core's System Control Block, SysTick, NVIC, FPU).
 * Addresses are the memory map of RM0090 section 2.3 (table 1). */
#ifndef COCHLEA_STM32F4_REGS_H
#define COCHLEA_STM32F4_REGS_H

#include <stdint.h>

#define REG32(address) (*(volatile uint32_t *)(uintptr_t)(address))

/* ---- RCC, reset and clock control: RM0090 section 7.3 (register map 7.3.24) --------------- */
#define RCC_BASE 0x40023800u
#define RCC_CR REG32(RCC_BASE + 0x00u)      /* 7.3.1 */
#define RCC_CR_HSION (1u << 0)
#define RCC_CR_HSIRDY (1u << 1)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_PLLCFGR REG32(RCC_BASE + 0x04u) /* 7.3.2: PLLM 5:0, PLLN 14:6, PLLP 17:16,
                                             * PLLSRC 22, PLLQ 27:24 */
#define RCC_PLLCFGR_PLLSRC_HSE (1u << 22)
#define RCC_CFGR REG32(RCC_BASE + 0x08u)    /* 7.3.3: SW 1:0, SWS 3:2, HPRE 7:4, PPRE1 12:10,
                                             * PPRE2 15:13 */
#define RCC_CFGR_SW_PLL 2u
#define RCC_CFGR_SWS_PLL (2u << 2)
#define RCC_CFGR_PPRE1_DIV4 (5u << 10)
#define RCC_CFGR_PPRE2_DIV2 (4u << 13)
#define RCC_AHB1ENR REG32(RCC_BASE + 0x30u) /* 7.3.10 */
#define RCC_AHB1ENR_GPIOAEN (1u << 0)
#define RCC_AHB1ENR_GPIOBEN (1u << 1)
#define RCC_APB1ENR REG32(RCC_BASE + 0x40u) /* 7.3.13 */
#define RCC_APB1ENR_TIM2EN (1u << 0)
#define RCC_APB1ENR_USART2EN (1u << 17)
#define RCC_APB1ENR_USART3EN (1u << 18)
#define RCC_APB2ENR REG32(RCC_BASE + 0x44u) /* 7.3.14 */
#define RCC_APB2ENR_USART1EN (1u << 4)
#define RCC_CSR REG32(RCC_BASE + 0x74u)     /* 7.3.21 */
#define RCC_CSR_LSION (1u << 0)
#define RCC_CSR_RMVF (1u << 24)
#define RCC_CSR_IWDGRSTF (1u << 29)
#define RCC_CSR_WWDGRSTF (1u << 30)

/* ---- Flash interface: RM0090 section 3.9.1 (FLASH_ACR) ------------------------------------ */
#define FLASH_ACR REG32(0x40023C00u)
#define FLASH_ACR_LATENCY_5WS 5u /* 168 MHz at 2.7-3.6 V (section 3.5.1) */
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_ACR_DCEN (1u << 10)

/* ---- GPIO: RM0090 section 8.4 (register map 8.4.11) --------------------------------------- */
#define GPIOA_BASE 0x40020000u
#define GPIOA_MODER REG32(GPIOA_BASE + 0x00u)   /* 8.4.1: 2 bits a pin, 01 output, 10 AF */
#define GPIOA_OSPEEDR REG32(GPIOA_BASE + 0x08u) /* 8.4.3: 11 very high speed */
#define GPIOA_PUPDR REG32(GPIOA_BASE + 0x0Cu)   /* 8.4.4: 01 pull-up */
#define GPIOA_BSRR REG32(GPIOA_BASE + 0x18u)    /* 8.4.7: set 15:0, reset 31:16 */
#define GPIOA_AFRL REG32(GPIOA_BASE + 0x20u)    /* 8.4.9: pins 0-7, 4 bits each */
#define GPIOA_AFRH REG32(GPIOA_BASE + 0x24u)    /* 8.4.10: pins 8-15 */
#define GPIOB_BASE 0x40020400u
#define GPIOB_MODER REG32(GPIOB_BASE + 0x00u)
#define GPIOB_AFRH REG32(GPIOB_BASE + 0x24u)
#define GPIO_AF7_USART 7u                       /* USART1..3: AF7 (datasheet DS8626 table 9) */

/* ---- USART: RM0090 section 30.6 (register map 30.6.8) ------------------------------------- */
#define USART1_BASE 0x40011000u /* APB2 */
#define USART2_BASE 0x40004400u /* APB1 */
#define USART3_BASE 0x40004800u /* APB1 */
#define USART_SR(base) REG32((base) + 0x00u)   /* 30.6.1 */
#define USART_SR_ORE (1u << 3)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TC (1u << 6)
#define USART_SR_TXE (1u << 7)
#define USART_DR(base) REG32((base) + 0x04u)   /* 30.6.2 */
#define USART_BRR(base) REG32((base) + 0x08u)  /* 30.6.3: mantissa 15:4, fraction 3:0 */
#define USART_CR1(base) REG32((base) + 0x0Cu)  /* 30.6.4 */
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_UE (1u << 13)
#define USART_CR1_OVER8 (1u << 15)
#define USART_CR2(base) REG32((base) + 0x10u)  /* 30.6.5: 0 = 1 stop bit */
#define USART_CR3(base) REG32((base) + 0x14u)  /* 30.6.6 */

/* ---- TIM2, a 32-bit general-purpose timer: RM0090 section 18.4 (register map 18.4.21) ---- */
#define TIM2_BASE 0x40000000u
#define TIM2_CR1 REG32(TIM2_BASE + 0x00u) /* 18.4.1: CEN 0 */
#define TIM2_EGR REG32(TIM2_BASE + 0x14u) /* 18.4.6: UG 0 loads the prescaler */
#define TIM2_CNT REG32(TIM2_BASE + 0x24u) /* 18.4.10 */
#define TIM2_PSC REG32(TIM2_BASE + 0x28u) /* 18.4.11 */
#define TIM2_ARR REG32(TIM2_BASE + 0x2Cu) /* 18.4.12 */

/* ---- IWDG, the independent watchdog: RM0090 section 21.4 ---------------------------------- */
#define IWDG_KR REG32(0x40003000u)  /* 21.4.1: 0x5555 unlock, 0xAAAA reload, 0xCCCC start */
#define IWDG_PR REG32(0x40003004u)  /* 21.4.2: prescaler /4 << PR */
#define IWDG_RLR REG32(0x40003008u) /* 21.4.3: 12-bit reload */
#define IWDG_SR REG32(0x4000300Cu)  /* 21.4.4: PVU 0, RVU 1 (an update in progress) */

/* ---- Interrupt numbers: RM0090 section 12.2, the vector table ------------------------------------- */
#define IRQ_USART1 37
#define IRQ_USART3 39
#define IRQ_COUNT 82 /* the vector table's external interrupts (0..81, FPU last) */

/* ---- Cortex-M4 core: PM0214 section 4 ----------------------------------------------------- */
#define SYST_CSR REG32(0xE000E010u) /* 4.5.1: ENABLE 0, TICKINT 1, CLKSOURCE 2 (processor) */
#define SYST_RVR REG32(0xE000E014u) /* 4.5.2: 24-bit reload */
#define SYST_CVR REG32(0xE000E018u) /* 4.5.3: counts down */
#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n))          /* 4.2.2 */
#define NVIC_IPR_BYTE(irq) (*(volatile uint8_t *)(uintptr_t)(0xE000E400u + (irq))) /* 4.2.7 */
#define SCB_ICSR REG32(0xE000ED04u) /* 4.4.3: PENDSTSET 26 */
#define SCB_ICSR_PENDSTSET (1u << 26)
#define SCB_SHPR3 REG32(0xE000ED20u) /* 4.4.8: SysTick priority 31:24 */
#define SCB_CPACR REG32(0xE000ED88u) /* 4.6.1: CP10, CP11 full access 23:20 */

#endif /* COCHLEA_STM32F4_REGS_H */
