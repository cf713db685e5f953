/*
 * pil_protocol.h -- the framed binary protocol between a drive process and its PIL target.
 *
 * The drive's Python side (firmware_model/pil_link.py mirrors these numbers; a test checks that
 * they agree) talks to the firmware on the emulated Cortex-M4 over the board's UART0, one
 * request and one reply per control period.  The target keeps the drive's st[] (parameters and
 * loop state), the tables and the recorder in its RAM; a request carries only what changed since
 * the last one, a reply only what the step changed.
 *
 * Frame (both directions):
 *     SYNC (0xA5) | TYPE (1 byte) | LEN (varint) | payload (LEN bytes) | CHECK (1 byte)
 * CHECK = (TYPE + the bytes of LEN + the payload bytes) mod 256.
 * Integers in a payload are LEB128 varints (7 bits a byte, least significant group first, bit 7
 * set on every byte but the last); signed values are zigzag-coded first ((v << 1) ^ (v >> 63):
 * 0, -1, 1, -2 ... -> 0, 1, 2, 3 ...), so small magnitudes take one or two bytes.
 *
 * Host -> target:
 *   'H' HELLO  (no payload)                                        -> 'h'
 *   'T' TICK   n_writes, n_writes x (slot u8, zz value)    st[slot] = value before the step
 *              flags u8 (PIL_TICK_COLUMN: table column idx follows)
 *              zz (idx - previous idx)                     the table column to play
 *              rec (0: none, 1: = idx, else rec_idx + 2)   the recorder column to write
 *              zz (count - previous count)                 the encoder count
 *              [PIL_TICK_COLUMN: 3 x zz (value - the value last sent in that row):
 *               reference position, reference velocity, feed-forward of column idx]
 *                                                                  -> 't'
 *   "previous" values start at 0 and are updated by every TICK the target executed, on both ends;
 *   differences are taken modulo 2^64 (int64).  Only column idx is ever sent: the step reads no
 *   other, and the host knows which columns the target holds.
 *
 * Target -> host:
 *   'h' HELLO reply: version, ILC_N_STATE, table columns, recorder columns, SysTick clock [Hz]
 *   't' TICK reply:  zz tau [µN·m], status, n_changed, n_changed x (slot u8, zz (new - old
 *                    value)) -- the st words the step changed --, then if rec_idx >= 0 the
 *                    recorder column as 4 x zz (value - its st word after the step: REC_POS -
 *                    S_POS, REC_VEL - S_VEST, REC_TAU - S_TAU, REC_TAU_FB - S_TAU_FB; 0 when the
 *                    recorder holds what the state says), then the SysTick ticks the call of
 *                    ilc_control_tick took (see below).
 *   'E' ERROR:       code (PIL_ERR_*), detail -- the request was not executed
 *   'F' FAULT:       exception number, CFSR, HFSR, stacked PC -- sent once by the fault handler,
 *                    the target then sleeps for ever
 *
 * Time: SysTick counts the processor clock (25 MHz on mps2-an386, reported in HELLO).  QEMU runs
 * with -icount shift=0: virtual time advances 1 ns per guest instruction, so one SysTick tick is
 * 40 instructions -- an instruction count at a 40-instruction resolution, not a cycle count of
 * real silicon (QEMU models no pipeline, wait states or caches).
 */
#ifndef PIL_PROTOCOL_H
#define PIL_PROTOCOL_H

#define PIL_PROTOCOL_VERSION 1
#define PIL_SYNC 0xA5u
#define PIL_MAX_PAYLOAD 1024u

#define PIL_HELLO 'H'
#define PIL_HELLO_REPLY 'h'
#define PIL_TICK 'T'
#define PIL_TICK_REPLY 't'
#define PIL_ERROR 'E'
#define PIL_FAULT 'F'

/* TICK flags */
#define PIL_TICK_COLUMN 1u

/* columns the target holds: a trial's tables (capacity 60,000 + the hold slot) fit */
#define PIL_TABLE_COLS 65537
#define PIL_REC_COLS 65536

/* PIL_ERROR codes */
#define PIL_ERR_CHECK 1     /* CHECK mismatch (detail: the check computed) */
#define PIL_ERR_LENGTH 2    /* LEN above PIL_MAX_PAYLOAD (detail: LEN) */
#define PIL_ERR_TYPE 3      /* unknown TYPE (detail: TYPE) */
#define PIL_ERR_FORMAT 4    /* payload shorter or longer than its fields (detail: offset) */
#define PIL_ERR_SLOT 5      /* st slot >= ILC_N_STATE (detail: slot) */
#define PIL_ERR_COLUMN 6    /* table column or idx >= PIL_TABLE_COLS (detail: column) */
#define PIL_ERR_RECORD 7    /* rec_idx >= PIL_REC_COLS (detail: rec_idx) */

#endif /* PIL_PROTOCOL_H */
