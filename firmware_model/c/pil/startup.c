/*
 * startup.c -- reset and exception vectors of the PIL target (QEMU mps2-an386, Cortex-M4F).
 *
 * Owns the vector table (the initial stack pointer, Reset_Handler, the system exceptions and the
 * first 32 external interrupts), Reset_Handler (copies .data from its load address, zeroes
 * .bss, turns the FPU on -- CP10/CP11 full access -- and calls main), the fault handler (reports
 * the fault and the stacked PC to the host over UART0, pil_report_fault, then sleeps for ever) and the three memory
 * functions the compiler may emit calls to in a freestanding build (memcpy, memset, memmove).
 * No libc is linked.
 */
#include <stddef.h>
#include <stdint.h>

#include "pil_target.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;

int main(void);
void Reset_Handler(void);
void Fault_Handler(void);
void pil_fault_entry(const uint32_t *frame);

#define SCB_CPACR (*(volatile uint32_t *)0xE000ED88u)

void Reset_Handler(void)
{
    uint32_t *src = &_sidata;
    uint32_t *dst = &_sdata;
    while (dst < &_edata) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss; ++dst) {
        *dst = 0;
    }
    SCB_CPACR |= (0xFu << 20); /* CP10, CP11: full access (the M4F's FPU) */
    __asm__ __volatile__("dsb\n\tisb" ::: "memory");
    (void)main();
    for (;;) {
        __asm__ __volatile__("wfi");
    }
}

/* the exception frame (r0-r3, r12, lr, pc, xPSR) is on the main stack: pass it on */
__attribute__((naked)) void Fault_Handler(void)
{
    __asm__ __volatile__("mrs r0, msp\n\tb pil_fault_entry");
}

__attribute__((used)) void pil_fault_entry(const uint32_t *frame)
{
    uint32_t ipsr;
    __asm__ __volatile__("mrs %0, ipsr" : "=r"(ipsr));
    pil_report_fault(ipsr & 0x1FFu, frame[6]);
    for (;;) {
        __asm__ __volatile__("wfi");
    }
}

/* a vector: the initial stack pointer (entry 0) or a handler */
typedef union {
    void (*handler)(void);
    const uint32_t *stack;
} vector_t;

#define F {Fault_Handler}
/* 16 system vectors + 32 external interrupts (UART0 RX is IRQ 0; interrupts stay masked: the
   target waits for its UART with WFI, PRIMASK set, and no interrupt handler ever runs) */
__attribute__((section(".isr_vector"), used)) const vector_t pil_vectors[48] = {
    {.stack = &_estack},
    {Reset_Handler},
    F, /* NMI */
    F, /* HardFault */
    F, /* MemManage */
    F, /* BusFault */
    F, /* UsageFault */
    {0}, {0}, {0}, {0},
    F, /* SVCall */
    F, /* DebugMonitor */
    {0},
    F, /* PendSV */
    F, /* SysTick */
    F, F, F, F, F, F, F, F, F, F, F, F, F, F, F, F,
    F, F, F, F, F, F, F, F, F, F, F, F, F, F, F, F,
};
#undef F

void *memcpy(void *dst, const void *src, size_t n)
{
    uint8_t *d = dst;
    const uint8_t *s = src;
    while (n--) {
        *d++ = *s++;
    }
    return dst;
}

void *memmove(void *dst, const void *src, size_t n)
{
    uint8_t *d = dst;
    const uint8_t *s = src;
    if (d < s) {
        while (n--) {
            *d++ = *s++;
        }
    } else {
        while (n--) {
            d[n] = s[n];
        }
    }
    return dst;
}

void *memset(void *dst, int c, size_t n)
{
    uint8_t *d = dst;
    while (n--) {
        *d++ = (uint8_t)c;
    }
    return dst;
}
