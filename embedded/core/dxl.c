/*
 * dxl.c - the Dynamixel Protocol 2.0 codec declared in dxl.h: CRC-16, frame builders, and the
 * streaming parser, a line-by-line port of cochlea/dynamixel/protocol.py so that both give the
 * same frames and the same result codes on the same bytes.
 */
#include "dxl.h"

/* Parser in status mode: 0x55, error, CRC; in instruction mode: instruction, CRC. */
#define SHORTEST_STATUS 4u
#define SHORTEST_INSTRUCTION 3u
/* space() compacts only when the tail is nearly full, as protocol.py does, so that feed()
 * accepts the same number of bytes as the Python parser at every step. */
#define COMPACT_MARGIN 64u
#define MAX_LEN_FIELD 0xFFFFu

/* Polynomial 0x8005, MSB first: a table costs 512 bytes of flash but makes the CRC of a
 * 1 kHz status frame a few hundred cycles rather than a few thousand. */
static const uint16_t crc_table[256] = {
    0x0000, 0x8005, 0x800F, 0x000A, 0x801B, 0x001E, 0x0014, 0x8011, 0x8033, 0x0036, 0x003C,
    0x8039, 0x0028, 0x802D, 0x8027, 0x0022, 0x8063, 0x0066, 0x006C, 0x8069, 0x0078, 0x807D,
    0x8077, 0x0072, 0x0050, 0x8055, 0x805F, 0x005A, 0x804B, 0x004E, 0x0044, 0x8041, 0x80C3,
    0x00C6, 0x00CC, 0x80C9, 0x00D8, 0x80DD, 0x80D7, 0x00D2, 0x00F0, 0x80F5, 0x80FF, 0x00FA,
    0x80EB, 0x00EE, 0x00E4, 0x80E1, 0x00A0, 0x80A5, 0x80AF, 0x00AA, 0x80BB, 0x00BE, 0x00B4,
    0x80B1, 0x8093, 0x0096, 0x009C, 0x8099, 0x0088, 0x808D, 0x8087, 0x0082, 0x8183, 0x0186,
    0x018C, 0x8189, 0x0198, 0x819D, 0x8197, 0x0192, 0x01B0, 0x81B5, 0x81BF, 0x01BA, 0x81AB,
    0x01AE, 0x01A4, 0x81A1, 0x01E0, 0x81E5, 0x81EF, 0x01EA, 0x81FB, 0x01FE, 0x01F4, 0x81F1,
    0x81D3, 0x01D6, 0x01DC, 0x81D9, 0x01C8, 0x81CD, 0x81C7, 0x01C2, 0x0140, 0x8145, 0x814F,
    0x014A, 0x815B, 0x015E, 0x0154, 0x8151, 0x8173, 0x0176, 0x017C, 0x8179, 0x0168, 0x816D,
    0x8167, 0x0162, 0x8123, 0x0126, 0x012C, 0x8129, 0x0138, 0x813D, 0x8137, 0x0132, 0x0110,
    0x8115, 0x811F, 0x011A, 0x810B, 0x010E, 0x0104, 0x8101, 0x8303, 0x0306, 0x030C, 0x8309,
    0x0318, 0x831D, 0x8317, 0x0312, 0x0330, 0x8335, 0x833F, 0x033A, 0x832B, 0x032E, 0x0324,
    0x8321, 0x0360, 0x8365, 0x836F, 0x036A, 0x837B, 0x037E, 0x0374, 0x8371, 0x8353, 0x0356,
    0x035C, 0x8359, 0x0348, 0x834D, 0x8347, 0x0342, 0x03C0, 0x83C5, 0x83CF, 0x03CA, 0x83DB,
    0x03DE, 0x03D4, 0x83D1, 0x83F3, 0x03F6, 0x03FC, 0x83F9, 0x03E8, 0x83ED, 0x83E7, 0x03E2,
    0x83A3, 0x03A6, 0x03AC, 0x83A9, 0x03B8, 0x83BD, 0x83B7, 0x03B2, 0x0390, 0x8395, 0x839F,
    0x039A, 0x838B, 0x038E, 0x0384, 0x8381, 0x0280, 0x8285, 0x828F, 0x028A, 0x829B, 0x029E,
    0x0294, 0x8291, 0x82B3, 0x02B6, 0x02BC, 0x82B9, 0x02A8, 0x82AD, 0x82A7, 0x02A2, 0x82E3,
    0x02E6, 0x02EC, 0x82E9, 0x02F8, 0x82FD, 0x82F7, 0x02F2, 0x02D0, 0x82D5, 0x82DF, 0x02DA,
    0x82CB, 0x02CE, 0x02C4, 0x82C1, 0x8243, 0x0246, 0x024C, 0x8249, 0x0258, 0x825D, 0x8257,
    0x0252, 0x0270, 0x8275, 0x827F, 0x027A, 0x826B, 0x026E, 0x0264, 0x8261, 0x0220, 0x8225,
    0x822F, 0x022A, 0x823B, 0x023E, 0x0234, 0x8231, 0x8213, 0x0216, 0x021C, 0x8219, 0x0208,
    0x820D, 0x8207, 0x0202};

/* Shifts go through unsigned int: where int has 16 bits, a uint16_t or uint8_t promotes to
 * signed int and 0xFF << 8 would overflow it. */
static uint16_t crc_step(uint16_t crc, uint8_t x)
{
    return (uint16_t)(((unsigned)crc << 8) ^ crc_table[(((unsigned)crc >> 8) ^ x) & 0xFFu]);
}

uint16_t dxl_crc16(uint16_t crc, const uint8_t *data, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++) {
        crc = crc_step(crc, data[i]);
    }
    return crc;
}

/* ------------------------------------------------------------------------------------------
 * Builders
 * ------------------------------------------------------------------------------------------ */

/* A frame written byte by byte, so that a builder whose parameters come in pieces (address,
 * length, then data) needs no scratch buffer. Once the frame overflows, nothing more is
 * written and the rest of the input is not read. */
typedef struct {
    uint8_t *out;
    size_t cap;
    size_t w;
    uint8_t last1, last2;
    int full;
} encoder;

static void put(encoder *e, uint8_t x)
{
    if (e->w >= e->cap) {
        e->full = 1;
        return;
    }
    e->out[e->w] = x;
    e->w++;
}

/* The stuffing window starts at the instruction (or 0x55) byte, as the specification and
 * protocol.py define it: the LEN bytes before it never count towards an FF FF FD. */
static void begin(encoder *e, uint8_t *out, size_t cap, uint8_t id, uint8_t first)
{
    e->out = out;
    e->cap = cap;
    e->w = 0;
    e->full = 0;
    put(e, 0xFF);
    put(e, 0xFF);
    put(e, 0xFD);
    put(e, 0x00);
    put(e, id);
    put(e, 0x00); /* LEN, filled in by finish() */
    put(e, 0x00);
    put(e, first);
    e->last1 = first;
    e->last2 = 0;
}

static void param(encoder *e, uint8_t x)
{
    put(e, x);
    if (x == 0xFD && e->last1 == 0xFF && e->last2 == 0xFF) {
        put(e, 0xFD);
    }
    e->last2 = e->last1;
    e->last1 = x;
}

static void params(encoder *e, const uint8_t *data, size_t n)
{
    size_t i;
    for (i = 0; i < n && !e->full; i++) {
        param(e, data[i]);
    }
}

static void param_u16(encoder *e, uint16_t v)
{
    param(e, (uint8_t)(v & 0xFFu));
    param(e, (uint8_t)(v >> 8));
}

static int32_t finish(encoder *e)
{
    size_t length;
    uint16_t crc;
    if (e->full || e->cap - e->w < 2) {
        return DXL_E_SPACE;
    }
    length = e->w - DXL_PREFIX + 2;
    if (length > MAX_LEN_FIELD) {
        return DXL_E_ARG;
    }
    e->out[5] = (uint8_t)(length & 0xFFu);
    e->out[6] = (uint8_t)(length >> 8);
    crc = dxl_crc16(0, e->out, e->w);
    e->out[e->w] = (uint8_t)(crc & 0xFFu);
    e->out[e->w + 1] = (uint8_t)(crc >> 8);
    return (int32_t)(e->w + 2);
}

/* 253 (0xFD) would make the header itself look like a stuffed FF FF FD; 255 is no ID. */
static int bad_id(uint8_t id)
{
    return id == 0xFD || id == 0xFF;
}

int32_t dxl_instruction(uint8_t *out, size_t cap, uint8_t id, uint8_t instruction,
                        const uint8_t *params_, size_t n_params)
{
    encoder e;
    if (bad_id(id) || (params_ == NULL && n_params != 0) || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, id, instruction);
    params(&e, params_, n_params);
    return finish(&e);
}

int32_t dxl_status(uint8_t *out, size_t cap, uint8_t id, uint8_t error, const uint8_t *params_,
                   size_t n_params)
{
    encoder e;
    if ((params_ == NULL && n_params != 0) || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, id, DXL_STATUS);
    param(&e, error);
    params(&e, params_, n_params);
    return finish(&e);
}

int32_t dxl_ping(uint8_t *out, size_t cap, uint8_t id)
{
    return dxl_instruction(out, cap, id, DXL_PING, NULL, 0);
}

int32_t dxl_reboot(uint8_t *out, size_t cap, uint8_t id)
{
    return dxl_instruction(out, cap, id, DXL_REBOOT, NULL, 0);
}

int32_t dxl_read(uint8_t *out, size_t cap, uint8_t id, uint16_t address, uint16_t length)
{
    encoder e;
    if (bad_id(id) || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, id, DXL_READ);
    param_u16(&e, address);
    param_u16(&e, length);
    return finish(&e);
}

int32_t dxl_write(uint8_t *out, size_t cap, uint8_t id, uint16_t address, const uint8_t *data,
                  size_t n)
{
    encoder e;
    if (bad_id(id) || (data == NULL && n != 0) || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, id, DXL_WRITE);
    param_u16(&e, address);
    params(&e, data, n);
    return finish(&e);
}

int32_t dxl_sync_read(uint8_t *out, size_t cap, uint16_t address, uint16_t length,
                      const uint8_t *ids, size_t n_ids)
{
    encoder e;
    if ((ids == NULL && n_ids != 0) || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, DXL_BROADCAST_ID, DXL_SYNC_READ);
    param_u16(&e, address);
    param_u16(&e, length);
    params(&e, ids, n_ids);
    return finish(&e);
}

int32_t dxl_fast_sync_read(uint8_t *out, size_t cap, uint16_t address, uint16_t length,
                           const uint8_t *ids, size_t n_ids)
{
    encoder e;
    if ((ids == NULL && n_ids != 0) || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, DXL_BROADCAST_ID, DXL_FAST_SYNC_READ);
    param_u16(&e, address);
    param_u16(&e, length);
    params(&e, ids, n_ids);
    return finish(&e);
}

int32_t dxl_sync_write(uint8_t *out, size_t cap, uint16_t address, uint16_t length,
                       const uint8_t *ids, const uint8_t *data, size_t n_ids)
{
    encoder e;
    size_t k;
    const uint8_t *block = data;
    if ((n_ids != 0 && (ids == NULL || (data == NULL && length != 0)))
        || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, DXL_BROADCAST_ID, DXL_SYNC_WRITE);
    param_u16(&e, address);
    param_u16(&e, length);
    /* Stop at the first overflow: the blocks past it may not even exist in the caller's
     * memory if n_ids was a mistake. */
    for (k = 0; k < n_ids && !e.full; k++) {
        param(&e, ids[k]);
        params(&e, block, length);
        block += length;
    }
    return finish(&e);
}

int32_t dxl_bulk_read(uint8_t *out, size_t cap, const uint8_t *ids, const uint16_t *addresses,
                      const uint16_t *lengths, size_t n_ids)
{
    encoder e;
    size_t k;
    if ((n_ids != 0 && (ids == NULL || addresses == NULL || lengths == NULL))
        || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    begin(&e, out, cap, DXL_BROADCAST_ID, DXL_BULK_READ);
    for (k = 0; k < n_ids && !e.full; k++) {
        param(&e, ids[k]);
        param_u16(&e, addresses[k]);
        param_u16(&e, lengths[k]);
    }
    return finish(&e);
}

int32_t dxl_bulk_write(uint8_t *out, size_t cap, const uint8_t *ids, const uint16_t *addresses,
                       const uint16_t *lengths, const uint8_t *data, size_t n_ids)
{
    encoder e;
    size_t k;
    const uint8_t *block = data;
    if ((n_ids != 0 && (ids == NULL || addresses == NULL || lengths == NULL))
        || (out == NULL && cap != 0)) {
        return DXL_E_ARG;
    }
    for (k = 0; k < n_ids; k++) { /* data may be NULL only when every block is empty */
        if (data == NULL && lengths[k] != 0) {
            return DXL_E_ARG;
        }
    }
    begin(&e, out, cap, DXL_BROADCAST_ID, DXL_BULK_WRITE);
    /* Stop at the first overflow, as dxl_sync_write does. */
    for (k = 0; k < n_ids && !e.full; k++) {
        param(&e, ids[k]);
        param_u16(&e, addresses[k]);
        param_u16(&e, lengths[k]);
        if (lengths[k] != 0) { /* no arithmetic on a NULL data */
            params(&e, block, lengths[k]);
            block += lengths[k];
        }
    }
    return finish(&e);
}

/* ------------------------------------------------------------------------------------------
 * Little-endian helpers
 * ------------------------------------------------------------------------------------------ */

void dxl_put_u16(uint8_t *p, uint16_t value)
{
    p[0] = (uint8_t)(value & 0xFFu);
    p[1] = (uint8_t)(value >> 8);
}

void dxl_put_u32(uint8_t *p, uint32_t value)
{
    p[0] = (uint8_t)(value & 0xFFu);
    p[1] = (uint8_t)((value >> 8) & 0xFFu);
    p[2] = (uint8_t)((value >> 16) & 0xFFu);
    p[3] = (uint8_t)(value >> 24);
}

uint16_t dxl_get_u16(const uint8_t *p)
{
    return (uint16_t)((unsigned)p[0] | (unsigned)p[1] << 8);
}

uint32_t dxl_get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16)
           | ((uint32_t)p[3] << 24);
}

/* Converting an out-of-range unsigned value to a signed type is implementation-defined in
 * C99, so the negative half is computed in arithmetic rather than by a cast. */
int16_t dxl_get_i16(const uint8_t *p)
{
    uint16_t u = dxl_get_u16(p);
    if (u < 0x8000u) {
        return (int16_t)u;
    }
    return (int16_t)((int32_t)u - 65536);
}

int32_t dxl_get_i32(const uint8_t *p)
{
    uint32_t u = dxl_get_u32(p);
    if (u < 0x80000000u) {
        return (int32_t)u;
    }
    /* 0xFFFFFFFF - u is at most 0x7FFFFFFF, so neither step overflows. */
    return -(int32_t)(0xFFFFFFFFu - u) - 1;
}

/* ------------------------------------------------------------------------------------------
 * Streaming parser
 * ------------------------------------------------------------------------------------------ */

void dxl_parser_init(dxl_parser *p, int status_mode)
{
    size_t i;
    p->start = 0;
    p->end = 0;
    p->params = p->buf;
    p->params_len = 0;
    p->frame_len = 0;
    p->dropped = 0;
    p->status_mode = (uint8_t)(status_mode != 0);
    p->id = 0;
    p->instruction = 0;
    p->error = 0;
    /* Not needed for correctness; it keeps a debugger's view of the buffer deterministic. */
    for (i = 0; i < DXL_PARSER_CAPACITY; i++) {
        p->buf[i] = 0;
    }
}

void dxl_parser_reset(dxl_parser *p)
{
    p->start = 0;
    p->end = 0;
}

size_t dxl_parser_pending(const dxl_parser *p)
{
    return p->end - p->start;
}

static void compact(dxl_parser *p)
{
    size_t n = p->end - p->start;
    size_t i;
    if (n != 0 && p->start != 0) {
        /* Front to back is safe: the destination is always below the source. */
        for (i = 0; i < n; i++) {
            p->buf[i] = p->buf[p->start + i];
        }
    }
    p->start = 0;
    p->end = n;
}

uint8_t *dxl_parser_space(dxl_parser *p, size_t *room)
{
    if (p->start == p->end) {
        p->start = 0;
        p->end = 0;
    } else if (p->end >= DXL_PARSER_CAPACITY - COMPACT_MARGIN) {
        compact(p);
    }
    *room = DXL_PARSER_CAPACITY - p->end;
    return &p->buf[0] + p->end;
}

void dxl_parser_commit(dxl_parser *p, size_t n)
{
    size_t room = DXL_PARSER_CAPACITY - p->end;
    p->end += n < room ? n : room;
}

size_t dxl_parser_feed(dxl_parser *p, const uint8_t *data, size_t n)
{
    size_t room;
    size_t i;
    (void)dxl_parser_space(p, &room);
    if (n > room) {
        n = room;
    }
    for (i = 0; i < n; i++) {
        p->buf[p->end + i] = data[i];
    }
    p->end += n;
    return n;
}

/* The parser indexes p->buf directly (never through a pointer) so that a bounds checker
 * (-fsanitize=bounds) sees every access against the array's declared size. */

/* Removes the stuffing of buf[from..to) in place and returns the new end. A missing stuffing
 * byte (a sender that does not stuff) is tolerated: the data are kept as sent. */
static size_t unstuff(dxl_parser *p, size_t from, size_t to)
{
    size_t r;
    size_t w = from;
    uint8_t last1 = 0, last2 = 0;
    int skip = 0;
    for (r = from; r < to; r++) {
        uint8_t x = p->buf[r];
        if (skip) {
            skip = 0;
            if (x == 0xFD) {
                continue;
            }
        }
        p->buf[w] = x;
        w++;
        if (x == 0xFD && last1 == 0xFF && last2 == 0xFF) {
            skip = 1;
        }
        last2 = last1;
        last1 = x;
    }
    return w;
}

static uint16_t frame_crc(const dxl_parser *p, size_t from, size_t to)
{
    uint16_t crc = 0;
    size_t i;
    for (i = from; i < to; i++) {
        crc = crc_step(crc, p->buf[i]);
    }
    return crc;
}

/* Drops one byte of a header that is not one, so the search resumes inside it. */
static int drop_one(dxl_parser *p, size_t s, int code)
{
    p->start = s + 1;
    p->dropped++;
    return code;
}

int dxl_parser_parse(dxl_parser *p)
{
    size_t s = p->start;
    size_t e = p->end;
    size_t i;
    size_t length, total, crc_end, body, body_end, shortest;
    uint8_t packet_id;

    /* Only a caller writing the fields (or a stray pointer) gets here; the indices below
     * would then run off the buffer, so start again from nothing. */
    if (e > DXL_PARSER_CAPACITY || s > e) {
        dxl_parser_reset(p);
        return DXL_NEED_MORE;
    }
    if (e - s < 4) {
        return DXL_NEED_MORE;
    }
    for (i = s; i + 4 <= e; i++) {
        if (p->buf[i] == 0xFF && p->buf[i + 1] == 0xFF && p->buf[i + 2] == 0xFD
            && p->buf[i + 3] == 0x00) {
            break;
        }
    }
    if (i + 4 > e) {
        /* Keep the last three bytes: a header may be split across reads. */
        size_t keep = e - 3;
        p->dropped += (uint32_t)(keep - s);
        p->start = keep;
        return DXL_NEED_MORE;
    }
    if (i > s) {
        p->dropped += (uint32_t)(i - s);
        s = i;
        p->start = i;
    }
    if (e - s < DXL_PREFIX) {
        return DXL_NEED_MORE;
    }
    packet_id = p->buf[s + 4];
    length = (size_t)p->buf[s + 5] | ((size_t)p->buf[s + 6] << 8);
    if (p->status_mode) {
        /* 0xFE: Fast Sync Read's one combined status packet (the Python parser takes it
         * too); a bridge that did not ask for it drops it as another ID's reply. */
        if (packet_id > DXL_MAX_ID && packet_id != DXL_BROADCAST_ID) {
            return drop_one(p, s, DXL_BAD_ID);
        }
        shortest = SHORTEST_STATUS;
    } else {
        if (packet_id == 0xFD || packet_id == 0xFF) {
            return drop_one(p, s, DXL_BAD_ID);
        }
        shortest = SHORTEST_INSTRUCTION;
    }
    total = DXL_PREFIX + length;
    if (length < shortest || total > DXL_PARSER_CAPACITY) {
        return drop_one(p, s, DXL_BAD_LENGTH);
    }
    if (e - s < total) {
        /* The frame fits the buffer but not from where it starts: make room for the rest. */
        if (total > DXL_PARSER_CAPACITY - s) {
            compact(p);
        }
        return DXL_NEED_MORE;
    }
    crc_end = s + total - 2;
    p->id = packet_id;
    p->frame_len = total;
    if (frame_crc(p, s, crc_end)
        != (uint16_t)((unsigned)p->buf[crc_end] | (unsigned)p->buf[crc_end + 1] << 8)) {
        /* Resynchronise inside the frame: a real header may start in its middle. */
        return drop_one(p, s, DXL_CRC_FAILURE);
    }
    p->start = s + total;
    body = s + DXL_PREFIX;
    body_end = unstuff(p, body, crc_end);
    p->instruction = p->buf[body];
    if (p->status_mode) {
        if (p->instruction != DXL_STATUS) {
            return DXL_WRONG_KIND;
        }
        if (body_end - body < 2) {
            return DXL_SHORT;
        }
        p->error = p->buf[body + 1];
        p->params = &p->buf[body + 2];
        p->params_len = body_end - (body + 2);
    } else {
        if (p->instruction == DXL_STATUS) {
            return DXL_WRONG_KIND;
        }
        p->error = 0;
        p->params = &p->buf[body + 1];
        p->params_len = body_end - (body + 1);
    }
    return DXL_OK;
}

/* ------------------------------------------------------------------------------------------
 * FAST_SYNC_READ's combined status packet
 * ------------------------------------------------------------------------------------------ */

const uint8_t *dxl_fast_block(const dxl_parser *p, size_t k, size_t length)
{
    /* the first block's error byte is the packet's own error byte, just before params */
    return p->params - 1 + k * (length + 4);
}

int dxl_fast_sync_check(const dxl_parser *p, const uint8_t *ids, size_t n_ids, size_t length,
                        size_t *at)
{
    const size_t block = length + 4;
    const size_t body = p->params_len + 3; /* error byte .. the last CRC */
    const size_t params_at = (size_t)(p->params - p->buf);
    size_t present, k;
    int whole, stuffed;
    size_t frame;
    *at = 0;
    if (params_at < 2 + DXL_PREFIX || params_at + p->params_len > DXL_PARSER_CAPACITY) {
        return DXL_FAST_WRONG_ID; /* not a packet this parser returned */
    }
    frame = params_at - 2 - DXL_PREFIX;
    present = body >= block ? body / block : 0;
    whole = body == present * block;
    stuffed = p->frame_len != DXL_PREFIX + 2 + p->params_len + 2;
    for (k = 0; k < n_ids && k < present; ++k) {
        const size_t b = params_at - 1 + k * block;
        if (p->buf[b + 1] != ids[k]) {
            *at = k;
            return DXL_FAST_WRONG_ID;
        }
        if (k + 1 < n_ids && k + 1 < present && !stuffed) {
            const size_t crc_at = b + 2 + length;
            if (frame_crc(p, frame, crc_at)
                != (uint16_t)((unsigned)p->buf[crc_at] | (unsigned)p->buf[crc_at + 1] << 8)) {
                *at = k;
                return DXL_FAST_BLOCK_CRC;
            }
        }
    }
    if (present < n_ids) {
        *at = present;
        return DXL_FAST_MISSING;
    }
    if (present > n_ids || !whole) {
        *at = n_ids > 0 ? n_ids - 1 : 0; /* present >= n_ids here */
        return DXL_FAST_WRONG_ID;
    }
    return DXL_FAST_OK;
}
