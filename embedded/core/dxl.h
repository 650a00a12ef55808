/*
 * dxl.h - a portable C99 codec for Dynamixel Protocol 2.0: CRC-16, instruction builders with
 * byte stuffing, little-endian helpers and a streaming packet parser.
 *
 * It is the C twin of cochlea/dynamixel/protocol.py (same frames byte for byte, same parser
 * result codes and resynchronisation), written for microcontrollers: no malloc, no stdio, no
 * libc at all (only <stddef.h> and <stdint.h>), every buffer provided by the caller. It builds
 * with `-std=c99 -pedantic -ffreestanding -fno-builtin -Wall -Wextra -Wconversion`.
 *
 * Frame layout (little-endian):
 *   instruction:  FF FF FD 00 | ID | LEN_L LEN_H | INST | params...       | CRC_L CRC_H
 *   status:       FF FF FD 00 | ID | LEN_L LEN_H | 0x55 | ERR | params... | CRC_L CRC_H
 * LEN counts the bytes after it after byte stuffing (every FF FF FD from INST on gets an extra
 * FD); the CRC covers the stuffed frame from the header on.
 */
#ifndef DXL_H
#define DXL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Largest frame a motor sends or accepts (the official SDK's bound). */
#define DXL_MAX_FRAME 1024
/* The parser holds two frames, so a frame split across reads never waits for room. */
#define DXL_PARSER_CAPACITY (2 * DXL_MAX_FRAME)
/* Header (4), ID, LEN_L, LEN_H: the bytes before the instruction. */
#define DXL_PREFIX 7
/* Room that always holds a frame of n parameters, however much of it needs stuffing. */
#define DXL_FRAME_SIZE(n_params) (DXL_PREFIX + 2 * (1 + (size_t)(n_params)) + 2)

#define DXL_BROADCAST_ID 0xFE
#define DXL_MAX_ID 252

/* Instruction codes (ROBOTIS e-Manual, Protocol 2.0). */
#define DXL_PING 0x01
#define DXL_READ 0x02
#define DXL_WRITE 0x03
#define DXL_REG_WRITE 0x04
#define DXL_ACTION 0x05
#define DXL_FACTORY_RESET 0x06
#define DXL_REBOOT 0x08
#define DXL_CLEAR 0x10
#define DXL_STATUS 0x55
#define DXL_SYNC_READ 0x82
#define DXL_SYNC_WRITE 0x83
#define DXL_BULK_READ 0x92
#define DXL_BULK_WRITE 0x93
#define DXL_FAST_SYNC_READ 0x8A

/* Builder errors (negative, so they never look like a frame length). */
#define DXL_E_SPACE (-1) /* the frame does not fit in the caller's buffer */
#define DXL_E_ARG (-2)   /* an impossible packet: ID 253 or 255, NULL data, LEN over 65535 */

/*
 * Result codes of dxl_parser_parse, the same numbers as protocol.py's PacketParser. They are
 * plain ints rather than an enum so that the ABI does not depend on -fshort-enums.
 */
#define DXL_OK 0          /* a whole packet with a good CRC: see id, instruction, error, params */
#define DXL_NEED_MORE 1   /* no whole packet in the buffer yet: feed more bytes */
#define DXL_CRC_FAILURE 2 /* a packet whose CRC does not match (id is its maybe-corrupted ID) */
#define DXL_BAD_LENGTH 3  /* a header with an impossible length (one byte dropped to resync) */
#define DXL_BAD_ID 4      /* a header with an impossible ID (one byte dropped) */
#define DXL_WRONG_KIND 5  /* a good packet of the other kind (an instruction among statuses) */
#define DXL_SHORT 6       /* a good packet too short for its kind */

/* CRC-16 of data[0..n) continuing from crc (start with 0). dxl_crc16(0, "123456789", 9) is
 * 0xFEE8. */
uint16_t dxl_crc16(uint16_t crc, const uint8_t *data, size_t n);

/*
 * Builders: each writes a whole stuffed frame into out[0..cap) and returns its length, or
 * DXL_E_SPACE / DXL_E_ARG (out may then hold a partial frame). DXL_FRAME_SIZE(n) is always
 * enough room for n parameters. IDs inside parameters (sync_read, sync_write) are sent as
 * given, as protocol.py does.
 */
int32_t dxl_instruction(uint8_t *out, size_t cap, uint8_t id, uint8_t instruction,
                        const uint8_t *params, size_t n_params);
/* A status packet (what a motor answers): 0x55, the error byte, then the parameters. */
int32_t dxl_status(uint8_t *out, size_t cap, uint8_t id, uint8_t error, const uint8_t *params,
                   size_t n_params);
int32_t dxl_ping(uint8_t *out, size_t cap, uint8_t id);
int32_t dxl_read(uint8_t *out, size_t cap, uint8_t id, uint16_t address, uint16_t length);
int32_t dxl_write(uint8_t *out, size_t cap, uint8_t id, uint16_t address, const uint8_t *data,
                  size_t n);
int32_t dxl_reboot(uint8_t *out, size_t cap, uint8_t id);
/* To the broadcast ID: read length bytes at address from each of ids[0..n_ids). */
int32_t dxl_sync_read(uint8_t *out, size_t cap, uint16_t address, uint16_t length,
                      const uint8_t *ids, size_t n_ids);
/* FAST_SYNC_READ (0x8A): the SYNC_READ request with another instruction code; the motors
 * answer with one combined status packet (see dxl_fast_sync_check). */
int32_t dxl_fast_sync_read(uint8_t *out, size_t cap, uint16_t address, uint16_t length,
                           const uint8_t *ids, size_t n_ids);
/* To the broadcast ID: data holds n_ids blocks of length bytes, block k for ids[k]. */
int32_t dxl_sync_write(uint8_t *out, size_t cap, uint16_t address, uint16_t length,
                       const uint8_t *ids, const uint8_t *data, size_t n_ids);

/* BULK_READ (0x92), to the broadcast ID: per motor k its ID ids[k], then the address and
 * length of the block it answers with (addresses[k], lengths[k]); each motor answers with its
 * own status packet, as for SYNC_READ (protocol.py's bulk_read). */
int32_t dxl_bulk_read(uint8_t *out, size_t cap, const uint8_t *ids, const uint16_t *addresses,
                      const uint16_t *lengths, size_t n_ids);
/* BULK_WRITE (0x93), to the broadcast ID, no reply: per motor k its ID, address, length, then
 * lengths[k] bytes of data, the blocks back to back in data (protocol.py's bulk_write). */
int32_t dxl_bulk_write(uint8_t *out, size_t cap, const uint8_t *ids, const uint16_t *addresses,
                       const uint16_t *lengths, const uint8_t *data, size_t n_ids);

/* Little-endian fields of the control table; the signed getters are two's complement. */
void dxl_put_u16(uint8_t *p, uint16_t value);
void dxl_put_u32(uint8_t *p, uint32_t value);
uint16_t dxl_get_u16(const uint8_t *p);
uint32_t dxl_get_u32(const uint8_t *p);
int16_t dxl_get_i16(const uint8_t *p);
int32_t dxl_get_i32(const uint8_t *p);

/*
 * Streaming parser. Bytes go in with dxl_parser_feed (a copy) or dxl_parser_space +
 * dxl_parser_commit (a UART driver or DMA writes straight into the buffer). Each
 * dxl_parser_parse call returns one result code; on DXL_OK the packet is in id, instruction,
 * error (status packets) and params[0..params_len), valid until the next call on the parser.
 * Every call either consumes at least one byte or returns DXL_NEED_MORE, so a loop of calls
 * ends, whatever the bytes.
 *
 * The fields are public for reading; only the functions below change them. buf is last so that
 * a bounds checker placed after the struct guards it.
 */
typedef struct dxl_parser {
    size_t start;        /* first unparsed byte in buf */
    size_t end;          /* one past the last byte received */
    const uint8_t *params; /* the last OK packet's unstuffed parameters, inside buf */
    size_t params_len;
    size_t frame_len;    /* stuffed length of the last packet returned (OK or CRC failure) */
    uint32_t dropped;    /* garbage bytes skipped since dxl_parser_init (wraps around) */
    uint8_t status_mode; /* 1: parse status packets (a master), 0: instructions (a motor) */
    uint8_t id;
    uint8_t instruction;
    uint8_t error;
    uint8_t buf[DXL_PARSER_CAPACITY];
} dxl_parser;

/* status_mode nonzero: expect status packets; zero: instruction packets. */
void dxl_parser_init(dxl_parser *p, int status_mode);
/* Forget buffered bytes (the start of a new transaction). */
void dxl_parser_reset(dxl_parser *p);
/* Bytes received but not yet parsed. */
size_t dxl_parser_pending(const dxl_parser *p);
/* Free room at the end of the buffer: *room bytes at the returned pointer (then commit). */
uint8_t *dxl_parser_space(dxl_parser *p, size_t *room);
/* Declare n bytes written at dxl_parser_space (clamped to the room there was). */
void dxl_parser_commit(dxl_parser *p, size_t n);
/* Copy up to n bytes in; returns how many fitted (feed the rest again after parsing). */
size_t dxl_parser_feed(dxl_parser *p, const uint8_t *data, size_t n);
/* One step of parsing: a DXL_* result code. */
int dxl_parser_parse(dxl_parser *p);

/*
 * The combined status packet of a FAST_SYNC_READ (protocol.py's fast_sync_status, the format
 * the official SDK's GroupSyncRead.fastSyncRead parses): one header with ID 0xFE and 0x55,
 * then per motor ERR ID DATA[length] CRC, where each motor's CRC is the running CRC of the
 * packet from its header to the end of that motor's data and the last motor's CRC is the
 * packet's own. The parser returns it as one DXL_OK packet with id DXL_BROADCAST_ID; then
 * dxl_fast_sync_check says whether it holds every motor ids[0..n) in order, length data bytes
 * each, every running CRC right: DXL_FAST_OK, or the first motor at fault (*at, an index
 * into ids) with DXL_FAST_MISSING (fewer blocks than motors), DXL_FAST_WRONG_ID (another ID
 * where its block belongs, more blocks than asked, or a length that is no whole number of
 * blocks) or DXL_FAST_BLOCK_CRC (its running CRC is wrong). The running CRCs are checked over
 * the unstuffed bytes: when the body needed stuffing only the packet's own CRC (checked by
 * the parser) is relied on, as check_fast_sync does. dxl_fast_block gives motor k's block:
 * its error byte, then its ID, then its data.
 */
#define DXL_FAST_OK 0
#define DXL_FAST_MISSING 1
#define DXL_FAST_WRONG_ID 2
#define DXL_FAST_BLOCK_CRC 3
int dxl_fast_sync_check(const dxl_parser *p, const uint8_t *ids, size_t n_ids, size_t length,
                        size_t *at);
const uint8_t *dxl_fast_block(const dxl_parser *p, size_t k, size_t length);

/*
 * Where a motor keeps what the bridge reads and writes: its control table's items, generated
 * from the model data (cochlea/dynamixel/models, through cochlea/dynamixel/embedded_drives.py
 * into generated_c/embedded/<robot>_drives.h), so that no code assumes one series' addresses.
 * An item a model does not have is {DXL_NO_ADDRESS, 0}.
 */
enum dxl_item_name {
    DXL_ITEM_RETURN_DELAY = 0,   /* Return Delay Time */
    DXL_ITEM_OPERATING_MODE,     /* Operating Mode */
    DXL_ITEM_CURRENT_LIMIT,      /* Current Limit */
    DXL_ITEM_TORQUE_ENABLE,      /* Torque Enable */
    DXL_ITEM_HARDWARE_ERROR,     /* Hardware Error Status */
    DXL_ITEM_BUS_WATCHDOG,       /* Bus Watchdog */
    DXL_ITEM_GOAL_CURRENT,       /* Goal Current */
    DXL_ITEM_HOMING_MARKER,      /* Feedforward 2nd Gain: the slider's homing token */
    DXL_ITEM_REALTIME_TICK,      /* Realtime Tick */
    DXL_ITEM_PRESENT_CURRENT,    /* Present Current */
    DXL_ITEM_PRESENT_VELOCITY,   /* Present Velocity */
    DXL_ITEM_PRESENT_POSITION,   /* Present Position */
    DXL_N_ITEMS
};
#define DXL_NO_ADDRESS 0xFFFFu

typedef struct {
    uint16_t address;
    uint8_t size; /* bytes: 1, 2 or 4; 0 when the model has no such item */
} dxl_item;

/* One motor's items (indexed by enum dxl_item_name) and the Operating Mode value of current
 * control. */
typedef struct {
    const char *model;  /* the model's name, e.g. "MX-64" */
    dxl_item item[DXL_N_ITEMS];
    uint8_t current_mode;
} dxl_table;

/* A chain's transfers, chosen by the generator from the models' data with the Python bridge's
 * rule (cochlea.dynamixel.bridge.choose_transfers): the per-period read (DXL_BULK_READ when the
 * models place the block at different addresses, DXL_FAST_SYNC_READ when every model's data
 * says it answers it, DXL_SYNC_READ otherwise) and write (DXL_BULK_WRITE when they place Goal
 * Current at different addresses, DXL_SYNC_WRITE otherwise),
 * why (the same text cochlea-run writes as read_choice), and each drive's table in the drive
 * table's order. */
typedef struct dxl_bus {
    uint8_t read_instruction;
    uint8_t write_instruction;
    const char *read_choice;
    int n_tables;
    const dxl_table *tables;
} dxl_bus;

#ifdef __cplusplus
}
#endif

#endif /* DXL_H */
