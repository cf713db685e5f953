/*
 * pil_target.h -- the board support of the PIL target (QEMU mps2-an386, Cortex-M4F): UART0, the
 * SysTick instruction counter, the fault report.
 */
#ifndef PIL_TARGET_H
#define PIL_TARGET_H

#include <stdint.h>

/* SysTick clock of mps2-an386 (the board's SYSCLK) [Hz] */
#define PIL_SYSTICK_HZ 25000000u

/* CMSDK APB UART0 (0x40004000): enable TX and RX; RX wakes the core from WFI (IRQ 0, masked). */
void uart_init(void);
/* Next received byte; sleeps (WFI) until one arrives. */
uint8_t uart_getc(void);
/* Send n bytes (waits while the transmit buffer is full). */
void uart_write(const uint8_t *data, uint32_t n);

/* SysTick as a free-running 24-bit down counter on the processor clock. */
void systick_start(void);
/* Its current value (counts down). */
static inline uint32_t systick_now(void)
{
    return *(volatile uint32_t *)0xE000E018u;
}
/* Ticks elapsed from an earlier systick_now() reading to a later one. */
static inline uint32_t systick_elapsed(uint32_t earlier, uint32_t later)
{
    return (earlier - later) & 0x00FFFFFFu;
}

/* The fault handler's report to the host (a PIL_FAULT frame): exception number, stacked PC. */
void pil_report_fault(uint32_t exception, uint32_t pc);

#endif /* PIL_TARGET_H */
