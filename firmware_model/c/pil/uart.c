/*
 * uart.c -- CMSDK APB UART0 of mps2-an386 (0x40004000) and the SysTick counter of the PIL target.
 *
 * Receiving sleeps: the UART's RX interrupt (IRQ 0) is enabled in the NVIC but masked by PRIMASK,
 * so a received byte only wakes the core from WFI (a pending interrupt ends WFI whatever its
 * masking) -- the emulated core does not spin while the drive process computes, which matters
 * with four drives' QEMUs on a few host cores.
 */
#include "pil_target.h"

typedef struct {
    volatile uint32_t data;      /* 0x000 */
    volatile uint32_t state;     /* 0x004: bit 0 TX buffer full, bit 1 RX buffer full */
    volatile uint32_t ctrl;      /* 0x008: bit 0 TX enable, 1 RX enable, 3 RX interrupt enable */
    volatile uint32_t intstatus; /* 0x00C: bit 1 RX interrupt (write 1 to clear) */
    volatile uint32_t bauddiv;   /* 0x010 */
} cmsdk_uart_t;

#define UART0 ((cmsdk_uart_t *)0x40004000u)
#define UART_STATE_TXFULL 1u
#define UART_STATE_RXFULL 2u
#define UART_CTRL_TXEN 1u
#define UART_CTRL_RXEN 2u
#define UART_CTRL_RXINTEN 8u
#define UART_INT_RX 2u

#define NVIC_ISER0 (*(volatile uint32_t *)0xE000E100u)
#define NVIC_ICPR0 (*(volatile uint32_t *)0xE000E280u)
#define UART0_RX_IRQ_BIT 1u /* IRQ 0 */

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)

void uart_init(void)
{
    __asm__ __volatile__("cpsid i" ::: "memory"); /* interrupts wake WFI, never run a handler */
    UART0->bauddiv = 16;                    /* the smallest valid divider (QEMU does not pace) */
    UART0->ctrl = UART_CTRL_TXEN | UART_CTRL_RXEN | UART_CTRL_RXINTEN;
    NVIC_ISER0 = UART0_RX_IRQ_BIT;
}

uint8_t uart_getc(void)
{
    for (;;) {
        if (UART0->state & UART_STATE_RXFULL) {
            return (uint8_t)UART0->data;
        }
        /* clear the RX interrupt and its pending bit, look again (a byte may have come in
           between), then sleep: a byte arriving after the look pends the interrupt, and a
           pending interrupt ends WFI at once */
        UART0->intstatus = UART_INT_RX;
        NVIC_ICPR0 = UART0_RX_IRQ_BIT;
        if (UART0->state & UART_STATE_RXFULL) {
            return (uint8_t)UART0->data;
        }
        __asm__ __volatile__("wfi" ::: "memory");
    }
}

void uart_write(const uint8_t *data, uint32_t n)
{
    while (n--) {
        while (UART0->state & UART_STATE_TXFULL) {
        }
        UART0->data = *data++;
    }
}

void systick_start(void)
{
    SYST_RVR = 0x00FFFFFFu;
    SYST_CVR = 0;
    SYST_CSR = 5u; /* ENABLE, CLKSOURCE = processor clock, no interrupt */
}
