/* cochlea embedded runtime: the Dynamixel bridge (see bridge.h). */
#include "bridge.h"

/* The items the bridge reads and writes. Each ADDR_x names an item of a motor's control table
 * (an index into its dxl_table, dxl.h), not an address: every address and size comes from the
 * model data through the generated drive table (<robot>_drives.h), so nothing here assumes
 * one series' layout. */
#define ADDR_RETURN_DELAY DXL_ITEM_RETURN_DELAY
#define ADDR_OPERATING_MODE DXL_ITEM_OPERATING_MODE
#define ADDR_CURRENT_LIMIT DXL_ITEM_CURRENT_LIMIT
#define ADDR_TORQUE_ENABLE DXL_ITEM_TORQUE_ENABLE
#define ADDR_HARDWARE_ERROR DXL_ITEM_HARDWARE_ERROR
#define ADDR_BUS_WATCHDOG DXL_ITEM_BUS_WATCHDOG
#define ADDR_GOAL_CURRENT DXL_ITEM_GOAL_CURRENT
#define ADDR_HOMING_MARKER DXL_ITEM_HOMING_MARKER
#define ALERT_BIT 0x80
#define MS 1000000LL

static const char *const FAILURE_NAMES[COCHLEA_FAIL_KINDS] = {
    "timeout", "crc", "error-byte", "hardware-alert", "length", "port", "late-traffic",
    "non-finite-command", "not-enabled", "stale-packet"};

const char *cochlea_failure_name(int kind)
{
    return (kind >= 0 && kind < COCHLEA_FAIL_KINDS) ? FAILURE_NAMES[kind] : "unknown";
}

const char *cochlea_instruction_name(int instruction)
{
    switch (instruction) {
    case DXL_SYNC_READ: return "SYNC_READ";
    case DXL_FAST_SYNC_READ: return "FAST_SYNC_READ";
    case DXL_BULK_READ: return "BULK_READ";
    case DXL_SYNC_WRITE: return "SYNC_WRITE";
    case DXL_BULK_WRITE: return "BULK_WRITE";
    default: return "unknown";
    }
}

enum { RESULT_OK, RESULT_TIMEOUT, RESULT_CRC, RESULT_PORT };

/* Motor i's item (its address and size, from its model's data). */
static const dxl_item *item_of(const cochlea_bridge *b, int i, int item)
{
    return &b->bus->tables[i].item[item];
}

/* 0 when every motor has item at one address and size (a SYNC_WRITE can carry it), else -1. */
static int same_item(const cochlea_bridge *b, int item)
{
    int i;
    const dxl_item *first = item_of(b, 0, item);
    if (first->size == 0) {
        return -1;
    }
    for (i = 1; i < b->n; ++i) {
        const dxl_item *it = item_of(b, i, item);
        if (it->address != first->address || it->size != first->size) {
            return -1;
        }
    }
    return 0;
}

/* The block of each period's read: from the Realtime Tick (with the tick check) or from
 * Present Current, to the end of Present Position, of the same length and offsets on every
 * motor (else -1: no single state layout reads them, the Python bridge's choose_transfers
 * refuses such a chain too), and its request as the bus says: a SYNC_READ or a
 * FAST_SYNC_READ (the block at one address on every motor, else -1), or a BULK_READ (each
 * motor's block at its own address: a mixed chain, e.g. 568 on a P-series motor, 120 on an
 * X-series one), the Python bridge's frame byte for byte. */
static int read_frame(cochlea_bridge *b, int tick)
{
    static const int items[4] = {DXL_ITEM_REALTIME_TICK, DXL_ITEM_PRESENT_CURRENT,
                                 DXL_ITEM_PRESENT_VELOCITY, DXL_ITEM_PRESENT_POSITION};
    uint8_t ids[COCHLEA_MAX_DRIVES];
    uint16_t addresses[COCHLEA_MAX_DRIVES], lengths[COCHLEA_MAX_DRIVES];
    unsigned length = 0;
    int same_address = 1;
    int read_at[4] = {0, 0, 0, 0};
    uint8_t read_size[4] = {0, 0, 0, 0};
    int32_t len;
    int i, k;
    for (i = 0; i < b->n; ++i) {
        unsigned lo = 0xFFFFu, hi = 0;
        for (k = tick ? 0 : 1; k < 4; ++k) {
            const dxl_item *it = item_of(b, i, items[k]);
            if (it->size == 0 || it->address == DXL_NO_ADDRESS) {
                return -1;
            }
            lo = it->address < lo ? it->address : lo;
            hi = it->address + it->size > hi ? it->address + it->size : hi;
        }
        if (i == 0) {
            length = hi - lo;
        } else if (hi - lo != length) {
            return -1;
        }
        for (k = 0; k < 4; ++k) {
            const dxl_item *it = item_of(b, i, items[k]);
            const int at = (int)it->address - (int)lo;
            if (i == 0) {
                read_at[k] = at;
                read_size[k] = it->size;
            } else if ((k > 0 || tick) && (at != read_at[k] || it->size != read_size[k])) {
                return -1;
            }
        }
        ids[i] = b->drives[i].id;
        addresses[i] = (uint16_t)lo;
        lengths[i] = (uint16_t)length;
        same_address = same_address && lo == addresses[0];
    }
    if (length > COCHLEA_MAX_READ_LENGTH || read_size[1] > 2) {
        return -1;
    }
    if (b->bus->read_instruction == DXL_BULK_READ) {
        len = dxl_bulk_read(b->read_frame, sizeof b->read_frame, ids, addresses, lengths,
                            (size_t)b->n);
    } else if (!same_address) {
        return -1; /* a mixed chain's blocks: only BULK_READ reads them */
    } else if (b->bus->read_instruction == DXL_FAST_SYNC_READ) {
        len = dxl_fast_sync_read(b->read_frame, sizeof b->read_frame, addresses[0],
                                 (uint16_t)length, ids, (size_t)b->n);
    } else if (b->bus->read_instruction == DXL_SYNC_READ) {
        len = dxl_sync_read(b->read_frame, sizeof b->read_frame, addresses[0],
                            (uint16_t)length, ids, (size_t)b->n);
    } else {
        return -1;
    }
    if (len < 0) {
        return -1;
    }
    for (k = 0; k < 4; ++k) {
        b->read_at[k] = read_at[k];
        b->read_size[k] = read_size[k];
    }
    for (i = 0; i < b->n; ++i) {
        b->read_addresses[i] = addresses[i];
    }
    b->read_len = (size_t)len;
    b->read_address = addresses[0];
    b->read_length = (int)length;
    b->realtime_tick = tick;
    return 0;
}

/* Why the drive table does not fit the bridge (for cochlea_bridge_init's -1), or NULL. */
static const char *check_tables(cochlea_bridge *b)
{
    static const int written[] = {DXL_ITEM_RETURN_DELAY, DXL_ITEM_OPERATING_MODE,
                                  DXL_ITEM_CURRENT_LIMIT, DXL_ITEM_TORQUE_ENABLE,
                                  DXL_ITEM_HARDWARE_ERROR, DXL_ITEM_BUS_WATCHDOG,
                                  DXL_ITEM_GOAL_CURRENT};
    int i, k;
    if (b->bus == 0 || b->bus->tables == 0 || b->bus->n_tables != b->n) {
        return "the drive table has no bus (regenerate it with cochlea-codegen)";
    }
    for (i = 0; i < b->n; ++i) {
        if (b->drives[i].bus != b->bus) {
            return "the drives are not of one chain (their bus differs)";
        }
        for (k = 0; k < (int)(sizeof written / sizeof written[0]); ++k) {
            const dxl_item *it = item_of(b, i, written[k]);
            if (it->size != 1 && it->size != 2 && it->size != 4) {
                return "a motor's control table lacks an item the bridge writes";
            }
        }
    }
    for (i = 0; i < b->n; ++i) { /* every period's frame carries an int16 Goal Current */
        if (item_of(b, i, DXL_ITEM_GOAL_CURRENT)->size != 2) {
            return "a motor's Goal Current is not 2 bytes";
        }
    }
    if (!(b->bus->write_instruction == DXL_BULK_WRITE
          || (b->bus->write_instruction == DXL_SYNC_WRITE
              && same_item(b, DXL_ITEM_GOAL_CURRENT) == 0))) {
        return "the motors place Goal Current at different addresses and the table's write is "
               "not BULK_WRITE (a mixed chain's: regenerate the table with cochlea-codegen)";
    }
    if (read_frame(b, 0) != 0 || read_frame(b, 1) != 0) {
        return "the motors place Present Current .. Present Position (and the Realtime Tick) "
               "differently and the table's read is not BULK_READ, or their blocks differ in "
               "length or layout (no single read parses them)";
    }
    return 0;
}

int cochlea_bridge_init(cochlea_bridge *b, const cochlea_hal *hal, const cochlea_drive *drives,
                        int n, int64_t timeout_ns, double watchdog_s)
{
    int i;
    double lsb;
    b->config_problem = "too many drives for the bridge";
    if (n < 1 || n > COCHLEA_MAX_DRIVES) {
        return -1;
    }
    b->hal = hal;
    b->drives = drives;
    b->n = n;
    b->timeout_ns = timeout_ns;
    lsb = watchdog_s / 0.020 - 1e-9;
    lsb = lsb < 1.0 ? 1.0 : (lsb > 127.0 ? 127.0 : lsb);
    b->watchdog_lsb = (uint8_t)lsb;
    if ((double)b->watchdog_lsb < lsb) { /* ceil */
        b->watchdog_lsb = (uint8_t)(b->watchdog_lsb + 1);
    }
    b->position_margin = 2.0 * 3.14159265358979323846 / 180.0;
    b->expected_start = 0;
    b->start_tolerance[0] = 5.0 * 3.14159265358979323846 / 180.0;
    b->start_tolerance[1] = 5e-3;
    b->retries = 3;
    b->bus = drives[0].bus;
    b->homing_drive = -1;
    b->homing_marker = 0;
    b->homing_offset = 0.0;
    b->offset_current = 1;
    b->torque_pending = 0;
    b->torque_failed_id = -1;
    b->active = 0;
    b->suspect = 0;
    b->reads = b->good_reads = b->writes = 0;
    b->unexpected_packets = b->garbage_packets = 0;
    for (i = 0; i < COCHLEA_FAIL_KINDS; ++i) {
        b->failures[i] = 0;
    }
    b->last_failure = -1;
    b->last_failure_id = -1;
    b->alert_id = -1;
    b->confirmed_off = 0;
    for (i = 0; i < n; ++i) {
        b->position_offset[i] = drives[i].q_offset;
        cochlea_drive_real_init(&b->conv[i], &drives[i], b->position_offset[i]);
        b->present_position[i] = b->present_velocity[i] = 0;
        b->present_current[i] = 0;
        b->joint_current[i] = COCHLEA_R(0.0);
        b->goal[i] = 0;
        b->last_tick[i] = -1;
        b->tick_seen_ns[i] = 0;
    }
    dxl_parser_init(&b->parser, 1);
    b->config_problem = check_tables(b);
    if (b->config_problem) {
        return -1;
    }
    return read_frame(b, 0);
}

void cochlea_bridge_expect_homing(cochlea_bridge *b, int drive, uint16_t marker, double offset)
{
    b->homing_drive = drive >= 0 && drive < b->n ? drive : -1;
    b->homing_marker = marker;
    b->homing_offset = offset;
}

int cochlea_bridge_use_realtime_tick(cochlea_bridge *b)
{
    return read_frame(b, 1);
}

/* ---- the wire ------------------------------------------------------------------------------ */

static int64_t now(const cochlea_bridge *b)
{
    return b->hal->now_ns(b->hal->ctx);
}

static int send(cochlea_bridge *b, const uint8_t *frame, size_t len)
{
    const cochlea_hal *hal = b->hal;
    long sent;
    if (hal->rs485_direction) {
        hal->rs485_direction(hal->ctx, 1);
    }
    sent = hal->serial_write(hal->ctx, frame, len);
    if (hal->rs485_direction) {
        hal->rs485_direction(hal->ctx, 0);
    }
    return sent == (long)len;
}

static void discard(cochlea_bridge *b)
{
    if (b->hal->serial_discard_input) {
        b->hal->serial_discard_input(b->hal->ctx);
    }
    dxl_parser_reset(&b->parser);
}

/* 1 once deadline has passed. */
static int past(const cochlea_bridge *b, int64_t deadline)
{
    return now(b) - deadline >= 0;
}

/* Bytes into the parser until deadline: the count, 0 at the deadline, -1 on a port error.
 * Once the deadline has passed it takes one last look, without waiting, at what has already
 * arrived (a reply that came in time but was not yet read), the first time (*drained 0);
 * after that it reads nothing and returns 0, whatever the line holds: a line that always has
 * a byte ready (babble, noise, a stuck transmitter) cannot keep a wait alive past its
 * deadline. Every wait of the bridge ends through here or past(); each starts with
 * *drained = 0. */
static long receive(cochlea_bridge *b, int64_t deadline, int *drained)
{
    size_t room;
    uint8_t *space = dxl_parser_space(&b->parser, &room);
    int64_t left = deadline - now(b);
    long got;
    if (left <= 0) {
        if (*drained) {
            return 0;
        }
        *drained = 1;
        left = 0;
    }
    if (room == 0) { /* full of garbage: start over rather than stall */
        dxl_parser_reset(&b->parser);
        space = dxl_parser_space(&b->parser, &room);
    }
    got = b->hal->serial_read(b->hal->ctx, space, room, left);
    if (got > 0) {
        dxl_parser_commit(&b->parser, (size_t)got); /* clamped to the room */
    }
    return got < 0 ? -1 : got;
}

/* A unicast instruction and its status packet. */
static int transact(cochlea_bridge *b, const uint8_t *frame, size_t len, uint8_t id,
                    int64_t timeout, int tries, uint8_t *error)
{
    int result = RESULT_TIMEOUT, attempt;
    for (attempt = 0; attempt < tries; ++attempt) {
        const int64_t deadline = now(b) + timeout;
        int drained = 0;
        discard(b);
        if (!send(b, frame, len)) {
            return RESULT_PORT;
        }
        for (;;) {
            const int code = dxl_parser_parse(&b->parser);
            long got;
            if (code == DXL_OK && b->parser.id == id) {
                *error = b->parser.error;
                return RESULT_OK;
            }
            if (code == DXL_CRC_FAILURE) {
                result = RESULT_CRC;
            }
            if (code != DXL_NEED_MORE) { /* not our reply: ends at the deadline too */
                if (past(b, deadline)) {
                    break;
                }
                continue;
            }
            got = receive(b, deadline, &drained);
            if (got < 0) {
                return RESULT_PORT;
            }
            if (got == 0) {
                break;
            }
        }
    }
    return result;
}

static int64_t setup_timeout(const cochlea_bridge *b)
{
    const int64_t four = 4 * b->timeout_ns;
    return four > 20 * MS ? four : 20 * MS;
}

static int fail_start(cochlea_start_report *r, int error, int step, int drive, int detail)
{
    r->error = error;
    r->step = step;
    r->drive = drive;
    r->detail = detail;
    return 0;
}

/* One start-up instruction to drive i, confirmed. On success the reply's parameters are in the
 * parser (b->parser.params). */
static int command(cochlea_bridge *b, int step, int i, const uint8_t *frame, int32_t len,
                   cochlea_start_report *r)
{
    uint8_t error = 0;
    int result;
    if (len < 0) {
        return fail_start(r, COCHLEA_START_BAD_CONFIG, step, i, 0);
    }
    result = transact(b, frame, (size_t)len, b->drives[i].id, setup_timeout(b), b->retries,
                      &error);
    if (result == RESULT_TIMEOUT) {
        return fail_start(r, COCHLEA_START_NO_ANSWER, step, i, 0);
    }
    if (result == RESULT_CRC) {
        return fail_start(r, COCHLEA_START_CRC, step, i, 0);
    }
    if (result == RESULT_PORT) {
        return fail_start(r, COCHLEA_START_PORT, step, i, 0);
    }
    if (error & ALERT_BIT) {
        int status = -1;
        const dxl_item *it = item_of(b, i, ADDR_HARDWARE_ERROR);
        const int32_t n = dxl_read(b->scratch, sizeof b->scratch, b->drives[i].id,
                                   it->address, it->size);
        uint8_t ignored;
        if (n > 0 && transact(b, b->scratch, (size_t)n, b->drives[i].id, setup_timeout(b), 1,
                              &ignored) == RESULT_OK && b->parser.params_len == it->size) {
            status = b->parser.params[0];
        }
        return fail_start(r, COCHLEA_START_ALERT, step, i, status);
    }
    if (error & 0x7F) {
        return fail_start(r, COCHLEA_START_REFUSED, step, i, error);
    }
    return 1;
}

/* An item's value in the item's own size, little-endian. */
static void put_value(uint8_t *data, int size, int32_t v)
{
    if (size == 1) {
        data[0] = (uint8_t)v;
    } else if (size == 2) {
        dxl_put_u16(data, (uint16_t)(int16_t)v);
    } else {
        dxl_put_u32(data, (uint32_t)v);
    }
}

/* The start-up's WRITE of item (ADDR_x) to every motor, each at the address and in the size
 * of its own table, confirmed. size is what the caller's values are meant for: a table whose
 * item has another size is a bad configuration (the value might not fit), never a guess. */
static int write_all(cochlea_bridge *b, int step, int item, int size, const int32_t *values,
                     int32_t same, cochlea_start_report *r)
{
    int i;
    for (i = 0; i < b->n; ++i) {
        uint8_t data[4];
        const dxl_item *it = item_of(b, i, item);
        const int32_t v = values ? values[i] : same;
        int32_t len;
        if (it->size != size) {
            return fail_start(r, COCHLEA_START_BAD_CONFIG, step, i, 0);
        }
        put_value(data, it->size, v);
        len = dxl_write(b->scratch, sizeof b->scratch, b->drives[i].id, it->address, data,
                        it->size);
        if (!command(b, step, i, b->scratch, len, r)) {
            return 0;
        }
    }
    return 1;
}

/* ---- each period ---------------------------------------------------------------------------- */

static int fail(cochlea_bridge *b, int kind, int id)
{
    b->failures[kind] += 1;
    b->last_failure = kind;
    b->last_failure_id = id;
    if (kind < COCHLEA_FAIL_NON_FINITE) {
        b->suspect = 1;
    }
    return 0;
}

/* After a failed read, replies may still be on their way: Protocol 2.0 has no sequence
 * numbers, so a late one would pass for the next period's. Wait until the line has been quiet
 * for one timeout, dropping what arrives; give up at twice that. */
static int quiet(cochlea_bridge *b, int64_t t0)
{
    const int64_t give_up = t0 + 2 * b->timeout_ns;
    int64_t quiet_until = t0 + b->timeout_ns;
    int drained = 0;
    for (;;) {
        const long got = receive(b, quiet_until < give_up ? quiet_until : give_up, &drained);
        const int64_t t = now(b);
        dxl_parser_reset(&b->parser);
        if (got < 0) {
            return 0;
        }
        if (got == 0 && t >= quiet_until) {
            b->suspect = 0;
            return 1;
        }
        if (t >= give_up) {
            return 0;
        }
        if (got > 0) {
            quiet_until = t + b->timeout_ns;
        }
    }
}

static int slot_of(const cochlea_bridge *b, uint8_t id)
{
    int i;
    for (i = 0; i < b->n; ++i) {
        if (b->drives[i].id == id) {
            return i;
        }
    }
    return -1;
}

/* A register of size bytes (1, 2, 4), little-endian, as stored and as two's complement. */
static uint32_t get_unsigned(const uint8_t *p, int size)
{
    return size == 1 ? p[0] : size == 2 ? dxl_get_u16(p) : dxl_get_u32(p);
}

static int32_t get_signed(const uint8_t *p, int size)
{
    return size == 1 ? (int32_t)p[0] - (p[0] >= 0x80u ? 256 : 0)
           : size == 2 ? (int32_t)dxl_get_i16(p) : dxl_get_i32(p);
}

/* The Realtime Tick check of a read whose packets all came (asked: when the request was
 * sent; arrived: when the last reply was in): 0, a stale-packet failure, if a motor's tick has
 * not moved since a reply that was in more than COCHLEA_STALE_AFTER_NS before this request.
 * A tick that has not moved can only be a repeat: the motor sampled it no later than the
 * reply that first carried it arrived, whatever the host's or the bus's delays. */
static int fresh(cochlea_bridge *b, int64_t asked, int64_t arrived)
{
    int j;
    for (j = 0; j < b->n; ++j) {
        const int32_t tick = (int32_t)get_unsigned(
            b->raw + (size_t)j * (size_t)b->read_length + b->read_at[0], b->read_size[0]);
        if (tick != b->last_tick[j]) {
            b->last_tick[j] = tick;
            b->tick_seen_ns[j] = arrived;
        } else if (asked - b->tick_seen_ns[j] > COCHLEA_STALE_AFTER_NS) {
            return fail(b, COCHLEA_FAIL_STALE, b->drives[j].id);
        }
    }
    return 1;
}

/* The ID of the first motor whose reply has not come, else -1. */
static int missing(const cochlea_bridge *b)
{
    int i;
    for (i = 0; i < b->n; ++i) {
        if (b->slots[i] == 0) {
            return b->drives[i].id;
        }
    }
    return -1;
}

/* The status packets of a SYNC_READ, one per motor, into b->raw: 1, or 0 on a failure
 * (counted). */
static int collect_sync(cochlea_bridge *b, int64_t deadline)
{
    const size_t length = (size_t)b->read_length;
    int pending = b->n, failure = -1, failure_id = -1, i, drained = 0;
    for (i = 0; i < b->n; ++i) {
        b->slots[i] = 0;
    }
    while (pending) {
        const int code = dxl_parser_parse(&b->parser);
        if (code == DXL_NEED_MORE) {
            const long got = receive(b, deadline, &drained);
            if (got > 0) {
                continue;
            }
            if (got < 0) {
                return fail(b, COCHLEA_FAIL_PORT, -1);
            }
            if (failure < 0) {
                failure = COCHLEA_FAIL_TIMEOUT;
                failure_id = missing(b);
            }
            break;
        }
        if (code == DXL_OK) {
            const int j = slot_of(b, b->parser.id);
            const uint8_t error = b->parser.error;
            size_t k;
            if (j < 0 || b->slots[j]) {
                b->unexpected_packets += 1;
                if (past(b, deadline)) { /* a flood of packets for no one */
                    return fail(b, failure >= 0 ? failure : COCHLEA_FAIL_TIMEOUT,
                                failure >= 0 ? failure_id : missing(b));
                }
                continue;
            }
            --pending;
            if (error & ALERT_BIT) {
                b->alert_id = b->parser.id;
                failure = COCHLEA_FAIL_ALERT; /* outranks every other cause */
                failure_id = b->parser.id;
            }
            if (b->parser.params_len != length || (error & 0x7F)) {
                b->slots[j] = 2;
                if (failure < 0) {
                    failure = b->parser.params_len != length
                                  ? COCHLEA_FAIL_LENGTH : COCHLEA_FAIL_ERROR_BYTE;
                    failure_id = b->parser.id;
                }
                continue;
            }
            b->slots[j] = 1;
            for (k = 0; k < length; ++k) {
                b->raw[(size_t)j * length + k] = b->parser.params[k];
            }
        } else if (code == DXL_CRC_FAILURE) {
            const int j = slot_of(b, b->parser.id);
            if (failure < 0) {
                failure = COCHLEA_FAIL_CRC;
                failure_id = b->parser.id;
            }
            if (j >= 0 && b->slots[j] == 0) {
                b->slots[j] = 2;
                --pending;
            }
        } else {
            b->garbage_packets += 1;
        }
        if (pending && code != DXL_OK && past(b, deadline)) {
            return fail(b, failure >= 0 ? failure : COCHLEA_FAIL_TIMEOUT,
                        failure >= 0 ? failure_id : missing(b));
        }
    }
    if (failure >= 0) {
        return fail(b, failure, failure_id);
    }
    return 1;
}

/* The reply to a FAST_SYNC_READ: one combined status packet (ID 0xFE) holding every motor's
 * block, checked by dxl_fast_sync_check and copied into b->raw: 1, or 0 on a failure,
 * through the same counters and kinds as the SYNC_READ's (the Python bridge's
 * _fast_sync_read, case for case): nothing whole in time timeout (the first motor); a
 * packet whose CRC fails crc (its motor when the ID is one of ours, else unknown: -1); a
 * motor missing from the packet, another ID where its block belongs, or a short or overlong
 * packet length (that motor); a block's running CRC wrong crc (that motor); the alert bit in
 * a block hardware-alert (that motor; it outranks an error byte), an error byte error-byte; a
 * motor answering alone (a model or firmware without FAST_SYNC_READ refuses it with an
 * Instruction Error) error-byte, or its alert. Other motors' packets and garbage are counted
 * and skipped until the deadline. */
static int collect_fast(cochlea_bridge *b, int64_t deadline)
{
    const size_t length = (size_t)b->read_length;
    uint8_t ids[COCHLEA_MAX_DRIVES];
    int drained = 0, failure = -1, failure_id = -1, i;
    size_t at = 0;
    int check;
    for (;;) {
        const int code = dxl_parser_parse(&b->parser);
        if (code == DXL_NEED_MORE) {
            const long got = receive(b, deadline, &drained);
            if (got > 0) {
                continue;
            }
            if (got < 0) {
                return fail(b, COCHLEA_FAIL_PORT, -1);
            }
            return fail(b, COCHLEA_FAIL_TIMEOUT, b->drives[0].id);
        }
        if (code == DXL_CRC_FAILURE) {
            return fail(b, COCHLEA_FAIL_CRC,
                        slot_of(b, b->parser.id) >= 0 ? b->parser.id : -1);
        }
        if (code == DXL_OK && b->parser.id == DXL_BROADCAST_ID) {
            break;
        }
        if (code == DXL_OK && slot_of(b, b->parser.id) >= 0) {
            /* a motor answering on its own: it refused the instruction (or its alert) */
            if (b->parser.error & ALERT_BIT) {
                b->alert_id = b->parser.id;
                return fail(b, COCHLEA_FAIL_ALERT, b->parser.id);
            }
            return fail(b, (b->parser.error & 0x7F) ? COCHLEA_FAIL_ERROR_BYTE
                                                     : COCHLEA_FAIL_LENGTH, b->parser.id);
        }
        if (code == DXL_OK) {
            b->unexpected_packets += 1;
        } else {
            b->garbage_packets += 1;
        }
        if (past(b, deadline)) { /* a flood of packets or garbage: no reply in time */
            return fail(b, COCHLEA_FAIL_TIMEOUT, b->drives[0].id);
        }
    }
    for (i = 0; i < b->n; ++i) {
        ids[i] = b->drives[i].id;
    }
    check = dxl_fast_sync_check(&b->parser, ids, (size_t)b->n, length, &at);
    if (check == DXL_FAST_BLOCK_CRC) {
        return fail(b, COCHLEA_FAIL_CRC, ids[at]);
    }
    if (check != DXL_FAST_OK) {
        return fail(b, COCHLEA_FAIL_LENGTH, ids[at < (size_t)b->n ? at : 0]);
    }
    for (i = 0; i < b->n; ++i) {
        const uint8_t *block = dxl_fast_block(&b->parser, (size_t)i, length);
        const uint8_t error = block[0];
        size_t k;
        if (error & ALERT_BIT) {
            b->alert_id = ids[i];
            failure = COCHLEA_FAIL_ALERT;
            failure_id = ids[i];
        } else if ((error & 0x7F) && failure < 0) {
            failure = COCHLEA_FAIL_ERROR_BYTE;
            failure_id = ids[i];
        }
        for (k = 0; k < length; ++k) {
            b->raw[(size_t)i * length + k] = block[2 + k];
        }
    }
    if (failure >= 0) {
        return fail(b, failure, failure_id);
    }
    return 1;
}

/* The period's read (SYNC_READ or FAST_SYNC_READ, as the bus says): each motor's Present
 * Position, Velocity and Current as read (integers: present_*), converted by the caller. */
static int sync_read(cochlea_bridge *b)
{
    const int64_t t0 = now(b);
    const size_t length = (size_t)b->read_length;
    int64_t deadline, asked;
    int i;
    b->reads += 1;
    discard(b);
    if (b->suspect && !quiet(b, t0)) {
        return fail(b, COCHLEA_FAIL_LATE, -1);
    }
    /* From the request, as the Python bridge: quiet() takes a whole timeout, and a deadline
     * from t0 would fail every read after the first failed one. */
    asked = now(b);
    deadline = asked + b->timeout_ns;
    if (!send(b, b->read_frame, b->read_len)) {
        return fail(b, COCHLEA_FAIL_PORT, -1);
    }
    if (!(b->bus->read_instruction == DXL_FAST_SYNC_READ ? collect_fast(b, deadline)
                                                          : collect_sync(b, deadline))) {
        return 0;
    }
    if (b->realtime_tick && !fresh(b, asked, now(b))) {
        return 0;
    }
    for (i = 0; i < b->n; ++i) {
        /* each item where the model data put it within the block */
        const uint8_t *raw = b->raw + (size_t)i * length;
        b->present_current[i] = (int16_t)get_signed(raw + b->read_at[1], b->read_size[1]);
        b->present_velocity[i] = get_signed(raw + b->read_at[2], b->read_size[2]);
        b->present_position[i] = get_signed(raw + b->read_at[3], b->read_size[3]);
    }
    b->good_reads += 1;
    return 1;
}

int cochlea_bridge_read(cochlea_bridge *b, cochlea_real *q, cochlea_real *qd)
{
    int i;
    if (!b->active) {
        return fail(b, COCHLEA_FAIL_NOT_ENABLED, -1);
    }
    if (b->torque_failed_id >= 0) { /* the torque did not come on: stop the run safely */
        return fail(b, COCHLEA_FAIL_NOT_ENABLED, b->torque_failed_id);
    }
    if (!sync_read(b)) {
        return 0;
    }
    for (i = 0; i < b->n; ++i) { /* the period's conversions, in the working precision */
        const cochlea_drive_real *c = &b->conv[i];
        b->joint_current[i] = cochlea_drive_current_real(c, b->present_current[i]);
        qd[i] = cochlea_drive_velocity_real(c, b->present_velocity[i]);
        q[i] = cochlea_drive_position_real(c, b->present_position[i]);
    }
    return 1;
}

/* A write of item (ADDR_x) of size bytes to every motor, no reply: values[i] per motor, or
 * same to all. bulk 0: one SYNC_WRITE, the item at one address on every motor (DXL_E_ARG
 * otherwise); bulk 1: one BULK_WRITE, each motor's item at its own address (a mixed chain).
 * DXL_E_ARG when a motor's item has another size. The Python bridge's frames byte for byte. */
static int32_t goal_frame(cochlea_bridge *b, int item, int size, const int16_t *values,
                          int32_t same, int bulk)
{
    uint8_t ids[COCHLEA_MAX_DRIVES];
    uint16_t addresses[COCHLEA_MAX_DRIVES], lengths[COCHLEA_MAX_DRIVES];
    uint8_t data[4 * COCHLEA_MAX_DRIVES];
    int i;
    if (!bulk && same_item(b, item) != 0) {
        return DXL_E_ARG;
    }
    for (i = 0; i < b->n; ++i) {
        const dxl_item *it = item_of(b, i, item);
        if (it->size != size) {
            return DXL_E_ARG;
        }
        ids[i] = b->drives[i].id;
        addresses[i] = it->address;
        lengths[i] = (uint16_t)size;
        put_value(data + (size_t)size * (size_t)i, size, values ? values[i] : same);
    }
    if (bulk) {
        return dxl_bulk_write(b->write_frame, sizeof b->write_frame, ids, addresses, lengths,
                              data, (size_t)b->n);
    }
    return dxl_sync_write(b->write_frame, sizeof b->write_frame, addresses[0], (uint16_t)size,
                          ids, data, (size_t)b->n);
}

/* Whether a frame of item to every motor is a BULK one: where the models place it
 * differently (Torque Enable: 64 on the X series, 512 on the P series), as the Python
 * bridge's _write_all chooses. */
static int bulk_item(const cochlea_bridge *b, int item)
{
    return same_item(b, item) != 0;
}

/* Start-up step 9 at the first nonzero command, its Goal Current already sent: two
 * transactions, one SYNC_WRITE of Torque Enable 1 to every motor, then one SYNC_READ of Torque
 * Enable confirming each (BULK_WRITE and BULK_READ, each motor at its own address, where the
 * models place it differently) (asked again, up to b->retries times in all, only while a reply is
 * missing or corrupted), as the Python bridge's _torque_on, the same bytes on the wire. The ID
 * of the first motor (drive order) that did not answer, answered with an error or its alert,
 * or reads back anything but 1; 254 when the port failed; -1 when every motor confirmed. */
static int torque_on(cochlea_bridge *b)
{
    uint8_t ids[COCHLEA_MAX_DRIVES], got[COCHLEA_MAX_DRIVES], error[COCHLEA_MAX_DRIVES];
    int value[COCHLEA_MAX_DRIVES];
    int i, tries;
    const int bulk = bulk_item(b, ADDR_TORQUE_ENABLE);
    int32_t len = goal_frame(b, ADDR_TORQUE_ENABLE, 1, 0, 1, bulk);
    if (len < 0 || !send(b, b->write_frame, (size_t)len)) {
        return 254;
    }
    for (i = 0; i < b->n; ++i) {
        ids[i] = b->drives[i].id;
        got[i] = 0; /* 0 no reply yet, 2 only corrupted ones, 1 answered */
        error[i] = 0;
        value[i] = -1;
    }
    { /* read back where each motor's model keeps it: one SYNC_READ where all alike, else
       * one BULK_READ, each at its own address (the Python bridge's frames) */
        uint16_t addresses[COCHLEA_MAX_DRIVES], lengths[COCHLEA_MAX_DRIVES];
        for (i = 0; i < b->n; ++i) {
            const dxl_item *it = item_of(b, i, ADDR_TORQUE_ENABLE);
            addresses[i] = it->address;
            lengths[i] = it->size;
            if (it->size != 1) {
                return 254; /* not a frame this bridge can read back */
            }
        }
        len = bulk ? dxl_bulk_read(b->scratch, sizeof b->scratch, ids, addresses, lengths,
                                   (size_t)b->n)
                   : dxl_sync_read(b->scratch, sizeof b->scratch, addresses[0], 1, ids,
                                   (size_t)b->n);
    }
    if (len < 0) {
        return 254;
    }
    for (tries = 0; tries < b->retries; ++tries) {
        const int64_t deadline = now(b) + setup_timeout(b);
        int pending = 0, drained = 0;
        for (i = 0; i < b->n; ++i) {
            pending += got[i] != 1;
        }
        if (!pending) {
            break;
        }
        discard(b);
        if (!send(b, b->scratch, (size_t)len)) {
            return 254;
        }
        while (pending) {
            const int code = dxl_parser_parse(&b->parser);
            int j;
            if (code == DXL_NEED_MORE) {
                const long n = receive(b, deadline, &drained);
                if (n < 0) {
                    return 254;
                }
                if (n == 0) {
                    break;
                }
                continue;
            }
            j = slot_of(b, b->parser.id);
            if (code == DXL_OK && j >= 0 && got[j] != 1) {
                got[j] = 1;
                error[j] = b->parser.error;
                value[j] = b->parser.params_len == 1 ? b->parser.params[0] : -1;
                --pending;
            } else if (code == DXL_CRC_FAILURE && j >= 0 && got[j] == 0) {
                got[j] = 2;
                --pending;
            } else if (past(b, deadline)) { /* a flood of packets for no one */
                break;
            }
        }
    }
    for (i = 0; i < b->n; ++i) {
        if (got[i] != 1 || error[i] != 0 || value[i] != 1) {
            return b->drives[i].id;
        }
    }
    return -1;
}

int cochlea_bridge_write(cochlea_bridge *b, const cochlea_real *tau)
{
    int i, finite = 1;
    int32_t len;
    if (!b->active) {
        return fail(b, COCHLEA_FAIL_NOT_ENABLED, -1);
    }
    b->writes += 1;
    for (i = 0; i < b->n; ++i) {
        finite = finite && cochlea_finite_real(tau[i]);
    }
    for (i = 0; i < b->n; ++i) { /* a NaN or infinite command: zero current, and report it */
        b->goal[i] = finite ? cochlea_drive_goal_current_real(&b->conv[i], tau[i],
                                                              b->offset_current)
                            : 0;
    }
    len = goal_frame(b, ADDR_GOAL_CURRENT, 2, b->goal, 0,
                     b->bus->write_instruction == DXL_BULK_WRITE);
    if (len < 0 || !send(b, b->write_frame, (size_t)len)) {
        return fail(b, COCHLEA_FAIL_PORT, -1);
    }
    if (!finite) {
        return fail(b, COCHLEA_FAIL_NON_FINITE, -1);
    }
    if (b->torque_pending) { /* start-up step 9, with the first nonzero command */
        int any = 0;
        for (i = 0; i < b->n; ++i) {
            any = any || b->goal[i] != 0;
        }
        if (any) {
            b->torque_pending = 0;
            b->torque_failed_id = torque_on(b);
            if (b->torque_failed_id >= 0) {
                return fail(b, COCHLEA_FAIL_NOT_ENABLED, b->torque_failed_id);
            }
        }
    }
    return 1;
}

/* ---- start-up and shut-down ----------------------------------------------------------------- */

int cochlea_bridge_stop(cochlea_bridge *b)
{
    int i, round, confirmed = 0;
    /* The Python bridge's frames: BULK_WRITEs both when the period's write is one, else a
     * SYNC_WRITE of Goal Current and Torque Enable's where the models place it alike. */
    const int bulk = b->bus->write_instruction == DXL_BULK_WRITE;
    for (round = 0; round < 2; ++round) {
        int32_t len = goal_frame(b, ADDR_GOAL_CURRENT, 2, 0, 0, bulk);
        if (len > 0) {
            (void)send(b, b->write_frame, (size_t)len);
        }
        len = goal_frame(b, ADDR_TORQUE_ENABLE, 1, 0, 0,
                         bulk || bulk_item(b, ADDR_TORQUE_ENABLE));
        if (len > 0) {
            (void)send(b, b->write_frame, (size_t)len);
        }
    }
    b->active = 0;
    /* After a failed read, its late replies may still come: one from a motor would pass for
     * that motor's confirmation. The motors already have their orders; wait for a quiet line
     * (at most two read timeouts) before asking them. */
    if (b->suspect) {
        (void)quiet(b, now(b));
    }
    for (i = 0; i < b->n; ++i) {
        uint8_t error = 0;
        b->off_confirmed[i] = 0;
        const dxl_item *it = item_of(b, i, ADDR_TORQUE_ENABLE);
        const int32_t len = dxl_read(b->scratch, sizeof b->scratch, b->drives[i].id,
                                     it->address, it->size);
        const int64_t timeout = b->timeout_ns > 10 * MS ? b->timeout_ns : 10 * MS;
        if (len > 0 && transact(b, b->scratch, (size_t)len, b->drives[i].id, timeout, 2,
                                &error) == RESULT_OK && b->parser.params_len == it->size &&
            b->parser.params[0] == 0) {
            ++confirmed;
            b->off_confirmed[i] = 1;
            if (error & ALERT_BIT) {
                b->alert_id = b->drives[i].id;
            }
        }
    }
    b->alert_status = -1;
    if (b->alert_id >= 0 && slot_of(b, (uint8_t)b->alert_id) >= 0) { /* what the alert was */
        const dxl_item *it = item_of(b, slot_of(b, (uint8_t)b->alert_id), ADDR_HARDWARE_ERROR);
        const int32_t len = dxl_read(b->scratch, sizeof b->scratch, (uint8_t)b->alert_id,
                                     it->address, it->size);
        uint8_t error = 0;
        if (len > 0 && transact(b, b->scratch, (size_t)len, (uint8_t)b->alert_id,
                                b->timeout_ns > 10 * MS ? b->timeout_ns : 10 * MS, 1,
                                &error) == RESULT_OK && b->parser.params_len == 1) {
            b->alert_status = b->parser.params[0];
        }
    }
    b->confirmed_off = confirmed;
    return confirmed;
}

static int start(cochlea_bridge *b, cochlea_start_report *r)
{
    int32_t limits[COCHLEA_MAX_DRIVES], modes[COCHLEA_MAX_DRIVES];
    double q[COCHLEA_MAX_DRIVES];
    int i, tries, read_ok = 0;
    for (i = 0; i < b->n; ++i) { /* 1. every motor there, of the model the table names */
        const int32_t len = dxl_ping(b->scratch, sizeof b->scratch, b->drives[i].id);
        int number;
        if (!command(b, COCHLEA_STEP_PING, i, b->scratch, len, r)) {
            return 0;
        }
        number = b->parser.params_len >= 2 ? dxl_get_u16(b->parser.params) : -1;
        if (number != b->drives[i].model_number) {
            return fail_start(r, COCHLEA_START_WRONG_MODEL, COCHLEA_STEP_PING, i, number);
        }
    }
    if (b->homing_drive >= 0) { /* before any write: the slider still holds its homing */
        const int h = b->homing_drive;
        const dxl_item *it = item_of(b, h, ADDR_HOMING_MARKER);
        const int32_t len = it->size == 2 ? dxl_read(b->scratch, sizeof b->scratch,
                                                     b->drives[h].id, it->address, 2)
                                          : DXL_E_ARG; /* no such item: a bad configuration */
        int marker;
        if (!command(b, COCHLEA_STEP_HOMING, h, b->scratch, len, r)) {
            return 0;
        }
        marker = b->parser.params_len == 2 ? dxl_get_u16(b->parser.params) : -1;
        if (marker != b->homing_marker) {
            return fail_start(r, COCHLEA_START_NOT_HOMED, COCHLEA_STEP_HOMING, h, marker);
        }
        b->position_offset[h] = b->homing_offset;
    }
    for (i = 0; i < b->n; ++i) {
        limits[i] = b->drives[i].current_limit_lsb;
        modes[i] = b->bus->tables[i].current_mode;
    }
    if (!write_all(b, COCHLEA_STEP_TORQUE_OFF, ADDR_TORQUE_ENABLE, 1, 0, 0, r) ||
        !write_all(b, COCHLEA_STEP_WATCHDOG_CLEAR, ADDR_BUS_WATCHDOG, 1, 0, 0, r) ||
        !write_all(b, COCHLEA_STEP_MODE, ADDR_OPERATING_MODE, 1, modes, 0, r) ||
        !write_all(b, COCHLEA_STEP_RETURN_DELAY, ADDR_RETURN_DELAY, 1, 0, 0, r) ||
        !write_all(b, COCHLEA_STEP_CURRENT_LIMIT, ADDR_CURRENT_LIMIT, 2, limits, 0, r) ||
        !write_all(b, COCHLEA_STEP_GOAL_ZERO, ADDR_GOAL_CURRENT, 2, 0, 0, r) ||
        !write_all(b, COCHLEA_STEP_WATCHDOG, ADDR_BUS_WATCHDOG, 1, 0, b->watchdog_lsb, r)) {
        return 0;
    }
    if (b->homing_drive >= 0) {
        /* The token back after the configuration: should a firmware reset its gains on the
         * Operating Mode write, the next start-up in this power cycle still finds it. */
        uint8_t data[2];
        int32_t len;
        dxl_put_u16(data, b->homing_marker);
        len = dxl_write(b->scratch, sizeof b->scratch, b->drives[b->homing_drive].id,
                        item_of(b, b->homing_drive, ADDR_HOMING_MARKER)->address, data, 2);
        if (!command(b, COCHLEA_STEP_HOMING, b->homing_drive, b->scratch, len, r)) {
            return 0;
        }
    }
    for (tries = 0; tries < 3 * b->retries && !read_ok; ++tries) { /* 8. the first good read */
        read_ok = sync_read(b);
    }
    if (!read_ok) {
        return fail_start(r, COCHLEA_START_NO_READ, COCHLEA_STEP_FIRST_READ, -1, b->last_failure);
    }
    for (i = 0; i < b->n; ++i) { /* in double: the start-up is no period */
        const cochlea_drive *d = &b->drives[i];
        double offset;
        b->joint_current[i] = (cochlea_real)cochlea_drive_current(d, b->present_current[i]);
        q[i] = cochlea_drive_position(d, b->present_position[i], b->position_offset[i]);
        offset = cochlea_drive_unwrap(d, q[i], b->position_offset[i]);
        q[i] += offset - b->position_offset[i];
        b->position_offset[i] = offset;
        cochlea_drive_real_init(&b->conv[i], d, offset);
        if (!(q[i] >= d->position_lo - b->position_margin &&
              q[i] <= d->position_hi + b->position_margin)) {
            r->value = q[i];
            return fail_start(r, COCHLEA_START_OUTSIDE_LIMITS, COCHLEA_STEP_LIMITS, i, 0);
        }
    }
    /* The controller and its path start from the scenario's initial pose: a robot standing
     * elsewhere would meet an initial error the study never had, at the gains' full
     * authority. Refused before the torque comes on (cochlea-run's _check_start). */
    for (i = 0; b->expected_start && i < b->n; ++i) {
        const double tolerance = b->start_tolerance[b->drives[i].revolute ? 0 : 1];
        const double away = q[i] - b->expected_start[i];
        if (!(away <= tolerance && -away <= tolerance)) { /* NaN too */
            r->value = q[i];
            r->expected = b->expected_start[i];
            return fail_start(r, COCHLEA_START_AWAY_FROM_START, COCHLEA_STEP_LIMITS, i, 0);
        }
    }
    /* 9. Torque on: with the first nonzero command (cochlea_bridge_write), after its Goal
     * Current, so that no motor is powered at zero current while the loop gets ready. */
    b->torque_pending = 1;
    b->torque_failed_id = -1;
    return 1;
}

int cochlea_bridge_start(cochlea_bridge *b, cochlea_start_report *report)
{
    report->error = COCHLEA_START_OK;
    report->step = 0;
    report->drive = -1;
    report->detail = 0;
    report->value = report->expected = 0.0;
    if (start(b, report)) {
        int k;
        /* The counters cover the run from here; the start-up's reads are kept apart. */
        b->startup_reads = b->reads;
        b->reads = b->good_reads = b->writes = 0;
        for (k = 0; k < COCHLEA_FAIL_KINDS; ++k) {
            b->failures[k] = 0;
        }
        b->active = 1;
        return 1;
    }
    (void)cochlea_bridge_stop(b);
    return 0;
}

static int backend_read(void *ctx, cochlea_real *q, cochlea_real *qd)
{
    return cochlea_bridge_read((cochlea_bridge *)ctx, q, qd);
}

static int backend_write(void *ctx, const cochlea_real *tau)
{
    return cochlea_bridge_write((cochlea_bridge *)ctx, tau);
}

static int backend_shutdown(void *ctx)
{
    return cochlea_bridge_stop((cochlea_bridge *)ctx);
}

cochlea_backend cochlea_bridge_backend(cochlea_bridge *b)
{
    cochlea_backend backend;
    backend.ctx = b;
    backend.read = backend_read;
    backend.write = backend_write;
    backend.shutdown = backend_shutdown;
    backend.current = b->joint_current;
    return backend;
}
