/* The row stream (stream.h; docs/embedded.md, "The row stream"): the framing, shared by the
 * board ports; the board moves the bytes to its UART (board.h's board_stream_*). */
#include "stream.h"

#include <string.h>

#include "board.h"

#define irq_save board_irq_save
#define irq_restore board_irq_restore

/* CRC-32, IEEE 802.3 (reflected 0xEDB88320, initial and final XOR 0xFFFFFFFF): zlib's crc32,
 * which the host checks with. Table-driven: 1 KB of flash, a few instructions a byte. */
static uint32_t crc_table[256];

static void crc_init(void)
{
    uint32_t i, j;
    for (i = 0; i < 256u; ++i) {
        uint32_t c = i;
        for (j = 0; j < 8u; ++j) {
            c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        }
        crc_table[i] = c;
    }
}

static uint32_t crc_add(uint32_t crc, const uint8_t *data, size_t n)
{
    crc = ~crc;
    while (n--) {
        crc = crc_table[(crc ^ *data++) & 0xffu] ^ (crc >> 8);
    }
    return ~crc;
}

/* Slots: written by the period (stream_row), read by the pump; both in the main
 * context, so plain counters do. */
static struct {
    int64_t k;
    cochlea_real row[STREAM_MAX_ROW];
} slots[STREAM_SLOTS];
static double period_s;
#ifdef COCHLEA_FLOAT
static double wide[STREAM_MAX_ROW]; /* a float row as the frame's doubles (the pump's) */
#endif
static uint32_t slot_head, slot_tail;

/* The TX ring: written by the pump (main context), read by the UART's interrupt and the pump
 * with interrupts masked. */
static volatile uint8_t tx[STREAM_TX_RING];
static volatile uint32_t tx_head, tx_tail;
static stream_counts counts;
static int ready;

static uint32_t tx_free(void)
{
    return STREAM_TX_RING - (tx_head - tx_tail);
}

/* Moves bytes from the ring to the UART while it takes them; its TXE interrupt on while bytes
 * are left (a board's interrupt then carries on), off when the ring is empty. Call with
 * interrupts masked. */
static void tx_move(void)
{
    while (tx_tail != tx_head && board_stream_tx_ready()) {
        board_stream_tx_byte(tx[tx_tail % STREAM_TX_RING]);
        tx_tail = tx_tail + 1u;
    }
    board_stream_tx_interrupt(tx_tail != tx_head);
}

/* The board's stream UART interrupt (TXE). */
void stream_tx_interrupt(void)
{
    tx_move();
}

static void tx_put(const void *data, size_t n)
{
    /* at most two copies (up to the ring's end, then from its start); the bytes are in place
     * before the head moves over them (the interrupt reads only below the head) */
    uint8_t *ring = (uint8_t *)(uintptr_t)tx;
    const uint32_t at = tx_head % STREAM_TX_RING;
    const size_t first = n < STREAM_TX_RING - at ? n : STREAM_TX_RING - at;
    memcpy(ring + at, data, first);
    memcpy(ring, (const uint8_t *)data + first, n - first);
    __asm__ volatile("" ::: "memory");
    tx_head = tx_head + (uint32_t)n;
}

static void put_le(uint8_t *at, uint32_t v, int bytes)
{
    int i;
    for (i = 0; i < bytes; ++i) {
        at[i] = (uint8_t)(v >> (8 * i));
    }
}

/* One frame into the TX ring (the caller has checked the room): payload a then b; its CRC. */
static uint32_t frame(uint8_t type, const uint8_t *a, size_t na, const uint8_t *b, size_t nb)
{
    uint8_t head[10], tail[4];
    uint32_t crc;
    head[0] = STREAM_SYNC0;
    head[1] = STREAM_SYNC1;
    head[2] = type;
    head[3] = 0;
    put_le(head + 4, (uint32_t)(na + nb), 2);
    put_le(head + 6, counts.frames, 4);
    crc = crc_add(0, head + 2, 8);
    crc = crc_add(crc_add(crc, a, na), b, nb);
    put_le(tail, crc, 4);
    tx_put(head, sizeof head);
    tx_put(a, na);
    tx_put(b, nb);
    tx_put(tail, sizeof tail);
    counts.frames += 1u;
    return crc;
}

void stream_init(uint32_t baud, uint32_t every, int row_length, double period)
{
    period_s = period;
    crc_init();
    memset(&counts, 0, sizeof counts);
    counts.every = every > 0u ? every : 1u;
    counts.row_length = row_length <= STREAM_MAX_ROW ? row_length : 0;
    slot_head = slot_tail = tx_head = tx_tail = 0;
    board_stream_uart_init(baud);
    ready = 1;
}

/* Waits (outside the periods only) for room in the TX ring, moving bytes; 0 at the deadline. */
static int room_for(size_t n, int64_t deadline_ns)
{
    for (;;) {
        uint32_t primask;
        if (tx_free() >= n) {
            return 1;
        }
        primask = irq_save();
        tx_move();
        irq_restore(primask);
        if (board_now_ns() >= deadline_ns) {
            return 0;
        }
    }
}

static void text_frame(uint8_t type, const char *text, int64_t deadline_ns)
{
    size_t n = strlen(text);
    uint32_t primask;
    if (!ready) {
        return;
    }
    n = n > STREAM_MAX_PAYLOAD ? STREAM_MAX_PAYLOAD : n;
    if (!room_for(n + STREAM_OVERHEAD, deadline_ns)) {
        counts.bytes_dropped += (uint32_t)(n + STREAM_OVERHEAD);
        counts.frames += 1u; /* the host sees the gap */
        return;
    }
    frame(type, (const uint8_t *)text, n, 0, 0);
    primask = irq_save();
    tx_move();
    irq_restore(primask);
}

void stream_header(const char *text)
{
    text_frame(STREAM_HEADER, text, board_now_ns() + 1000000000);
}

void stream_row(void *ctx, const cochlea_real *row, int row_length)
{
    const uint32_t k = counts.rows_seen;
    (void)ctx;
    counts.rows_seen = k + 1u;
    if (!ready || counts.row_length == 0 || row_length != counts.row_length
        || k % counts.every != 0u) {
        return;
    }
    if (slot_head - slot_tail >= STREAM_SLOTS) {
        counts.rows_dropped += 1u;
        return;
    }
    slots[slot_head % STREAM_SLOTS].k = k;
    memcpy(slots[slot_head % STREAM_SLOTS].row, row, (size_t)row_length * sizeof *row);
    slot_head += 1u;
    counts.rows_queued += 1u;
}

void stream_pump(void)
{
    const size_t bytes = (size_t)counts.row_length * sizeof(double);
    uint32_t primask;
    if (!ready) {
        return;
    }
    /* one row a call: bounded work between two periods (a row is queued per period at most) */
    if (slot_tail != slot_head && tx_free() >= bytes + 8u + STREAM_OVERHEAD) {
        uint8_t k[8];
        const int64_t kk = slots[slot_tail % STREAM_SLOTS].k;
        put_le(k, (uint32_t)kk, 4);
        put_le(k + 4, (uint32_t)((uint64_t)kk >> 32), 4);
        uint8_t crc[4];
#ifdef COCHLEA_FLOAT
        const cochlea_real *row = slots[slot_tail % STREAM_SLOTS].row;
        const uint8_t *payload = (const uint8_t *)wide;
        int j;
        /* widened here, between periods; t exact from k (a float t staircases) */
        for (j = 1; j < counts.row_length; ++j) {
            wide[j] = (double)row[j];
        }
        wide[0] = (double)kk * period_s;
#else
        const uint8_t *payload = (const uint8_t *)slots[slot_tail % STREAM_SLOTS].row;
#endif
        /* little-endian doubles: the Cortex-M's own byte order */
        put_le(crc, frame(STREAM_ROW, k, 8, payload, bytes), 4);
        counts.rows_crc = crc_add(counts.rows_crc, crc, 4);
        slot_tail += 1u;
        counts.rows_sent += 1u;
    }
    primask = irq_save();
    tx_move();
    irq_restore(primask);
}

void stream_flush_rows(int64_t deadline_ns)
{
    while (ready && slot_tail != slot_head && board_now_ns() < deadline_ns) {
        stream_pump();
    }
}

void stream_end(const char *text, int64_t deadline_ns)
{
    if (!ready) {
        return;
    }
    text_frame(STREAM_END, text, deadline_ns);
    while (tx_tail != tx_head && board_now_ns() < deadline_ns) {
        const uint32_t primask = irq_save();
        tx_move();
        irq_restore(primask);
    }
}

const stream_counts *stream_counts_now(void)
{
    return &counts;
}
