/* The row stream's UART on the STM32F4 port: USART3 on PB10 (TX, AF7), transmit only; the
 * framing is the shared one (embedded/ports/common/stream.c; docs/embedded.md, "The row
 * stream"). */
#include "board.h"
#include "hal_stm32f4.h"
#include "stm32f4_regs.h"

void board_stream_uart_init(uint32_t baud)
{
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOBEN;
    RCC_APB1ENR |= RCC_APB1ENR_USART3EN;
    /* PB10 TX: alternate function 7 (nothing is received) */
    GPIOB_MODER = (GPIOB_MODER & ~(3u << 20)) | (2u << 20);
    GPIOB_AFRH = (GPIOB_AFRH & ~(0xfu << 8)) | (GPIO_AF7_USART << 8);
    USART_CR1(USART3_BASE) = 0;
    USART_CR2(USART3_BASE) = 0;
    USART_CR3(USART3_BASE) = 0;
    USART_BRR(USART3_BASE) = (STM32_APB1_HZ + baud / 2u) / baud; /* OVER8 = 0 */
    USART_CR1(USART3_BASE) = USART_CR1_UE | USART_CR1_TE;
    NVIC_IPR_BYTE(IRQ_USART3) = 0x80u; /* below SysTick and the bus */
    NVIC_ISER(IRQ_USART3 / 32) = 1u << (IRQ_USART3 % 32);
}

int board_stream_tx_ready(void)
{
    return (USART_SR(USART3_BASE) & USART_SR_TXE) != 0u;
}

void board_stream_tx_byte(uint8_t byte)
{
    USART_DR(USART3_BASE) = byte;
}

void board_stream_tx_interrupt(int on)
{
    if (on) {
        USART_CR1(USART3_BASE) |= USART_CR1_TXEIE;
    } else {
        USART_CR1(USART3_BASE) &= ~USART_CR1_TXEIE;
    }
}

void USART3_IRQHandler(void);
void USART3_IRQHandler(void)
{
    stream_tx_interrupt();
}
