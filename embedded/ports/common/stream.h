/* The row stream of the board ports (STM32F4: USART3; OpenCR: USART2; board.h's
 * board_stream_*): the loop's log rows (cochlea-run's log.bin rows), every
 * STM32_STREAM_EVERY-th, framed and sent on the board's stream UART to a host command
 * (cochlea-embedded-host) that writes log.bin, log.columns.json and summary.json as
 * cochlea-run does. docs/embedded.md, "The row stream", has the frame format.
 *
 * Outside the period's critical path: stream_row (the loop's on_row, inside the
 * period) only copies a row into a ring of slots, or counts it dropped when the ring is full;
 * the framing and CRC-32 are done by stream_pump, called from the idle wait before
 * each period's deadline, and the bytes leave through the UART's TXE interrupt (and the same
 * pump where the interrupt is not raised, as on QEMU 7.2). Nothing here ever waits in a
 * period. */
#ifndef COCHLEA_PORTS_STREAM_H
#define COCHLEA_PORTS_STREAM_H

#include <stdint.h>

#include "cochlea_fp.h" /* cochlea_real: the working precision */

/* Frame: sync 0xC5 0x7E, type (u8), flags (u8, 0), payload length (u16 LE), sequence
 * (u32 LE, 0 for the header, one more per frame), payload, CRC-32 (IEEE, zlib's; u32 LE) of
 * type .. payload. */
#define STREAM_SYNC0 0xC5u
#define STREAM_SYNC1 0x7Eu
#define STREAM_HEADER 'H' /* key=value text, the columns last */
#define STREAM_ROW 'R'    /* period index (i64 LE), then row_length doubles (LE) */
#define STREAM_END 'E'    /* key=value text: the console's end line and the stream's counts */
#define STREAM_OVERHEAD 14u
#define STREAM_MAX_PAYLOAD 4096u
/* The longest row streamed (values); a longer scenario's stream says so and sends no rows. */
#define STREAM_MAX_ROW 96
/* Row slots between the period and the pump. */
#define STREAM_SLOTS 8u
/* Bytes between the pump and the USART (a power of two, above the largest frame: the header,
 * at most the firmware's 2 KB line). */
#define STREAM_TX_RING 4096u

typedef struct {
    uint32_t every;          /* decimation: every N-th period's row */
    int row_length;          /* values a row (0: rows not streamed) */
    uint32_t rows_seen;      /* rows the loop produced */
    uint32_t rows_queued;    /* taken into a slot */
    uint32_t rows_dropped;   /* a full ring of slots: counted, never waited on */
    uint32_t rows_sent;      /* framed into the TX ring */
    uint32_t rows_crc;       /* CRC-32 of the sent row frames' CRCs (4 bytes LE each), in
                              * order: the host's log holds exactly what was sent when its
                              * own equals it (one CRC pass a row, not two) */
    uint32_t frames;         /* frames framed (the next sequence number) */
    uint32_t bytes_dropped;  /* header or end bytes a stuck line did not take */
} stream_counts;

/* The board's stream UART at baud, 8N1; every-th row streamed; row_length values a row;
 * period_s the loop's period (the float build's frames carry t = k period_s, exact). */
void stream_init(uint32_t baud, uint32_t every, int row_length, double period_s);
/* The header frame (text, key=value; NUL-terminated), before the periods. */
void stream_header(const char *text);
/* The loop's on_row (inside the period: a copy or a count, nothing else). The row is in the
 * working precision (float in the float build); the frame is always doubles: the float row
 * is widened when it is framed, between periods, its t formed as k period_s. */
void stream_row(void *ctx, const cochlea_real *row, int row_length);
/* Frames queued rows and moves bytes to the USART while it takes them (idle context). */
void stream_pump(void);
/* After the run: every queued row framed (until deadline_ns), so the counts are final. */
void stream_flush_rows(int64_t deadline_ns);
/* Then the end frame (text), its bytes sent before deadline_ns. */
void stream_end(const char *text, int64_t deadline_ns);
const stream_counts *stream_counts_now(void);

#endif /* COCHLEA_PORTS_STREAM_H */
