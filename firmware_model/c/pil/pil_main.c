/*
 * pil_main.c -- the drive's control period on the PIL target: receive a period's inputs, run
 * ilc_control_tick (firmware_model/c/ilc_control.c, the same source the host build uses), send
 * the outputs back, with the step's instruction count (protocol: pil_protocol.h).
 *
 * The target keeps the drive's st[] (parameters and loop state), the tables (3 x PIL_TABLE_COLS)
 * and the recorder (4 x PIL_REC_COLS) in its RAM.  st[] starts all zero; the host brings it to
 * its own values with the writes of its first TICK request and keeps a copy of what the target
 * holds to send only what changed.
 */
#include <stdint.h>

#include "../ilc_drive.h"
#include "pil_protocol.h"
#include "pil_target.h"

static int64_t st[ILC_N_STATE];
static int64_t st_before[ILC_N_STATE];
static int32_t tables[3 * PIL_TABLE_COLS];
static int32_t rec[4 * PIL_REC_COLS];
static uint8_t rx[PIL_MAX_PAYLOAD];
static uint8_t tx[PIL_MAX_PAYLOAD + 8];

/* ---------------------------------------------------------------- varints */

typedef struct {
    const uint8_t *p;
    uint32_t n;
    uint32_t at;
    int bad;
} reader_t;

typedef struct {
    uint8_t *p;
    uint32_t at;
} writer_t;

static uint64_t get_u(reader_t *r)
{
    uint64_t v = 0;
    unsigned shift = 0;
    for (;;) {
        uint8_t b;
        if (r->at >= r->n || shift > 63u) {
            r->bad = 1;
            return 0;
        }
        b = r->p[r->at++];
        v |= (uint64_t)(b & 0x7Fu) << shift;
        if (!(b & 0x80u)) {
            return v;
        }
        shift += 7u;
    }
}

static int64_t get_s(reader_t *r)
{
    const uint64_t u = get_u(r);
    return (int64_t)((u >> 1) ^ (0u - (u & 1u)));
}

static uint8_t get_byte(reader_t *r)
{
    if (r->at >= r->n) {
        r->bad = 1;
        return 0;
    }
    return r->p[r->at++];
}

static void put_u(writer_t *w, uint64_t v)
{
    while (v >= 0x80u) {
        w->p[w->at++] = (uint8_t)(v | 0x80u);
        v >>= 7;
    }
    w->p[w->at++] = (uint8_t)v;
}

static void put_s(writer_t *w, int64_t v)
{
    const uint64_t sign = v < 0 ? ~(uint64_t)0 : 0u;
    put_u(w, ((uint64_t)v << 1) ^ sign);
}

/* ---------------------------------------------------------------- frames */

static void send_frame(uint8_t type, const uint8_t *payload, uint32_t len)
{
    uint8_t head[8];
    writer_t w = {head, 0};
    uint32_t sum = type;
    uint32_t i;
    head[w.at++] = PIL_SYNC;
    head[w.at++] = type;
    put_u(&w, len);
    for (i = 2; i < w.at; ++i) {
        sum += head[i];
    }
    for (i = 0; i < len; ++i) {
        sum += payload[i];
    }
    uart_write(head, w.at);
    uart_write(payload, len);
    head[0] = (uint8_t)sum;
    uart_write(head, 1);
}

static void send_error(uint32_t code, uint64_t detail)
{
    uint8_t buf[16];
    writer_t w = {buf, 0};
    put_u(&w, code);
    put_u(&w, detail);
    send_frame(PIL_ERROR, buf, w.at);
}

void pil_report_fault(uint32_t exception, uint32_t pc)
{
    uint8_t buf[24];
    writer_t w = {buf, 0};
    put_u(&w, exception);
    put_u(&w, *(volatile uint32_t *)0xE000ED28u); /* CFSR */
    put_u(&w, *(volatile uint32_t *)0xE000ED2Cu); /* HFSR */
    put_u(&w, pc);
    send_frame(PIL_FAULT, buf, w.at);
}

/* Receive one frame into rx; returns its type, or 0 after an error reply (bad frame). */
static uint8_t receive_frame(uint32_t *len)
{
    uint8_t type, b;
    uint32_t sum, n = 0, i;
    unsigned shift = 0;
    while (uart_getc() != PIL_SYNC) {
    }
    type = uart_getc();
    sum = type;
    do {
        b = uart_getc();
        sum += b;
        n |= (uint32_t)(b & 0x7Fu) << shift;
        shift += 7u;
    } while ((b & 0x80u) && shift < 28u);
    if (n > PIL_MAX_PAYLOAD) {
        send_error(PIL_ERR_LENGTH, n);
        return 0;
    }
    for (i = 0; i < n; ++i) {
        rx[i] = uart_getc();
        sum += rx[i];
    }
    if (uart_getc() != (uint8_t)sum) {
        send_error(PIL_ERR_CHECK, sum & 0xFFu);
        return 0;
    }
    *len = n;
    return type;
}

/* ---------------------------------------------------------------- requests */

static void hello(void)
{
    writer_t w = {tx, 0};
    put_u(&w, PIL_PROTOCOL_VERSION);
    put_u(&w, ILC_N_STATE);
    put_u(&w, PIL_TABLE_COLS);
    put_u(&w, PIL_REC_COLS);
    put_u(&w, PIL_SYSTICK_HZ);
    send_frame(PIL_HELLO_REPLY, tx, w.at);
}

/* the "previous" values of the TICK coding (pil_protocol.h) */
static uint64_t prev_idx, prev_count;
static uint64_t prev_col[3];
static const int rec_state_slot[4] = {ILC_S_POS, ILC_S_VEST, ILC_S_TAU, ILC_S_TAU_FB};

static void tick(uint32_t len)
{
    reader_t r = {rx, len, 0, 0};
    writer_t w = {tx, 0};
    uint64_t n, k, idx, rec_code, count, col[3];
    int64_t rec_idx;
    int32_t tau, status = 0;
    uint32_t t0, t1, n_changed = 0, i;
    uint8_t flags, changed[ILC_N_STATE];

    n = get_u(&r);
    for (k = 0; k < n && !r.bad; ++k) {
        const uint8_t slot = get_byte(&r);
        const int64_t value = get_s(&r);
        if (slot >= ILC_N_STATE) {
            send_error(PIL_ERR_SLOT, slot);
            return;
        }
        st[slot] = value;
    }
    flags = get_byte(&r);
    idx = prev_idx + (uint64_t)get_s(&r);
    rec_code = get_u(&r);
    count = prev_count + (uint64_t)get_s(&r);
    if (flags & PIL_TICK_COLUMN) {
        for (i = 0; i < 3u; ++i) {
            col[i] = prev_col[i] + (uint64_t)get_s(&r);
        }
    }
    if (r.bad || r.at != r.n) {
        send_error(PIL_ERR_FORMAT, r.at);
        return;
    }
    if (idx >= PIL_TABLE_COLS) {
        send_error(PIL_ERR_COLUMN, idx);
        return;
    }
    rec_idx = rec_code == 0 ? -1 : (rec_code == 1 ? (int64_t)idx : (int64_t)(rec_code - 2u));
    if (rec_idx >= PIL_REC_COLS) {
        send_error(PIL_ERR_RECORD, (uint64_t)rec_idx);
        return;
    }
    prev_idx = idx;
    prev_count = count;
    if (flags & PIL_TICK_COLUMN) {
        for (i = 0; i < 3u; ++i) {
            prev_col[i] = col[i];
            tables[i * PIL_TABLE_COLS + idx] = (int32_t)col[i];
        }
    }
    for (i = 0; i < ILC_N_STATE; ++i) {
        st_before[i] = st[i];
    }

    __asm__ __volatile__("" ::: "memory");
    t0 = systick_now();
    __asm__ __volatile__("" ::: "memory");
    tau = ilc_control_tick((int64_t)count, (int64_t)idx, rec_idx, st, tables, PIL_TABLE_COLS, rec,
                           PIL_REC_COLS, &status);
    __asm__ __volatile__("" ::: "memory");
    t1 = systick_now();
    __asm__ __volatile__("" ::: "memory");

    for (i = 0; i < ILC_N_STATE; ++i) {
        if (st[i] != st_before[i]) {
            changed[n_changed++] = (uint8_t)i;
        }
    }
    put_s(&w, tau);
    put_u(&w, (uint32_t)status);
    put_u(&w, n_changed);
    for (i = 0; i < n_changed; ++i) {
        w.p[w.at++] = changed[i];
        put_s(&w, (int64_t)((uint64_t)st[changed[i]] - (uint64_t)st_before[changed[i]]));
    }
    if (rec_idx >= 0) {
        for (i = 0; i < 4u; ++i) {
            put_s(&w, (int64_t)rec[i * PIL_REC_COLS + (uint32_t)rec_idx] - st[rec_state_slot[i]]);
        }
    }
    put_u(&w, systick_elapsed(t0, t1));
    send_frame(PIL_TICK_REPLY, tx, w.at);
}

int main(void)
{
    uart_init();
    systick_start();
    for (;;) {
        uint32_t len = 0;
        const uint8_t type = receive_frame(&len);
        if (type == PIL_HELLO) {
            hello();
        } else if (type == PIL_TICK) {
            tick(len);
        } else if (type != 0) {
            send_error(PIL_ERR_TYPE, type);
        }
    }
}
