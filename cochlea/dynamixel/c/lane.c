/*
 * lane.c - the period's packet work in C, at both ends of the bus: the virtual chain's
 * requests (cochlea-emulator) and the bridge's SYNC_READ replies (cochlea-run).
 *
 * The emulator's side:
 * A 1 kHz loop sends the chain two instructions a period: a SYNC_WRITE of every motor's Goal
 * Current and a SYNC_READ of the per-period block (Realtime Tick .. Present Position). In
 * Python their packet work (parse, CRC, the writes' checks, six status packets built and
 * CRC-checked) cost the emulator about 150 us a period, which kept the loops against it late
 * (issue 30, item 2). Here the same work runs on the motors' own control tables (Python's
 * bytearrays, shared by pointer), and Python keeps what is not packet work: the plant, the
 * publication of the present registers, the event log, the reply queue and its timing.
 *
 * The lane takes a receive only when every byte of it is one of those two requests, whole,
 * with a good CRC and nothing to unstuff, and the chain has nothing the lane does not model
 * (faults, baud checks, ignored writes: emulator.py decides). Anything else -- a partial
 * packet, garbage, another instruction -- goes to the Python path, byte for byte as before:
 * lane_scan() decides that without changing anything. The semantics are emulator.py's
 * (VirtualMotor.write/_check, VirtualChain._instruction/_reply), checked against it by
 * tests/test_emulator_lane.py on the same bytes.
 */
#include <stddef.h>
#include <stdint.h>

#include "dxl.h"

#define LANE_MAX_MOTORS 64
#define LANE_MAX_PACKETS 16
/* The most motors one lane request may list, and the longest read it may ask: a request past
 * either (a hostile or broken host's) goes to the Python path, so that a packet's actions and
 * status packets always fit the buffers Python made (lane_sizes). */
#define LANE_MAX_LISTED 256
#define LANE_MAX_READ 1024
#define LANE_MAX_ACTIONS (1 + LANE_MAX_LISTED)
#define LANE_OUT_SIZE (LANE_MAX_LISTED * DXL_FRAME_SIZE(1 + LANE_MAX_READ))

/* The Protocol 2.0 error numbers of control_table.py. */
#define E_DATA_RANGE 4
#define E_DATA_LIMIT 6
#define E_ACCESS 7
#define ALERT_BIT 0x80

/* What lane_execute reports to Python, four int32 each: kind, motor (index), a, b. */
#define ACT_WRITTEN 1   /* a Goal Current written: a = value */
#define ACT_REFUSED 2   /* a Goal Current refused: a = the error number */
#define ACT_READ 3      /* a SYNC_READ heard: a = address, b = length (its event) */
#define ACT_REPLY 4     /* a motor read: a = offset of its status packet in out, b = length */
#define ACT_CONTACT 5   /* a motor read that does not answer (Status Return Level 0) */

typedef struct {
    uint8_t *table;      /* the motor's control table: VirtualMotor.table */
    uint32_t table_size;
    uint16_t a_goal;     /* Goal Current: 2 bytes, signed, RAM */
    uint16_t a_limit;    /* Current Limit: 2 bytes, unsigned */
    uint16_t a_watchdog; /* Bus Watchdog: 0xFF when tripped */
    uint16_t a_error;    /* Hardware Error Status */
    uint16_t a_level;    /* Status Return Level */
    int32_t goal_lo, goal_hi;
    uint8_t answering;
    uint8_t id;
} lane_motor;

typedef struct {
    uint32_t n_motors;
    int16_t by_id[256]; /* motor index by ID, -1 where none */
    lane_motor motors[LANE_MAX_MOTORS];
} lane_chain;

typedef struct {
    uint32_t offset;      /* of the frame in the receive */
    uint32_t frame_len;   /* its bytes (no stuffing in a lane packet) */
    uint32_t params;      /* offset of its parameters in the receive */
    uint32_t n_params;
    uint32_t instruction; /* DXL_SYNC_WRITE or DXL_SYNC_READ */
} lane_packet;

static uint16_t u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((unsigned)p[1] << 8));
}

static int has_ff_ff_fd(const uint8_t *p, size_t n)
{
    size_t i;
    for (i = 0; i + 2 < n; i++) {
        if (p[i] == 0xFF && p[i + 1] == 0xFF && p[i + 2] == 0xFD) {
            return 1;
        }
    }
    return 0;
}

/*
 * The packets of a receive, if the lane takes every byte of it: their number (1..
 * LANE_MAX_PACKETS), else 0 and Python parses it. Changes nothing.
 */
int32_t lane_scan(const lane_chain *c, const uint8_t *in, size_t n, lane_packet *packets)
{
    size_t o = 0;
    int32_t count = 0;
    while (o < n) {
        size_t length, total, k;
        const uint8_t *p = in + o;
        uint16_t crc;
        lane_packet *pk;
        if (count == LANE_MAX_PACKETS || n - o < DXL_PREFIX + 3) {
            return 0;
        }
        if (p[0] != 0xFF || p[1] != 0xFF || p[2] != 0xFD || p[3] != 0x00 ||
            p[4] != DXL_BROADCAST_ID) {
            return 0;
        }
        length = u16(p + 5);
        total = DXL_PREFIX + length;
        if (length < 3 || total > n - o || total > DXL_MAX_FRAME * 2) {
            return 0;
        }
        crc = dxl_crc16(0, p, total - 2);
        if (crc != u16(p + total - 2)) {
            return 0;
        }
        if (has_ff_ff_fd(p + DXL_PREFIX, total - 2 - DXL_PREFIX)) {
            return 0; /* a stuffed byte to take out: Python's parser does it */
        }
        pk = &packets[count];
        pk->offset = (uint32_t)o;
        pk->frame_len = (uint32_t)total;
        pk->instruction = p[DXL_PREFIX];
        pk->params = (uint32_t)(o + DXL_PREFIX + 1);
        pk->n_params = (uint32_t)(length - 3);
        if (pk->n_params < 4) {
            return 0;
        }
        if (pk->instruction == DXL_SYNC_WRITE) {
            const uint8_t *q = in + pk->params;
            uint16_t address = u16(q);
            if (u16(q + 2) != 2 || (pk->n_params - 4) / 3 > LANE_MAX_LISTED) {
                return 0;
            }
            /* Every motor the write reaches must take it as its Goal Current. */
            for (k = 4; k + 3 <= pk->n_params; k += 3) {
                int16_t m = c->by_id[q[k]];
                if (m >= 0 && c->motors[m].answering && c->motors[m].a_goal != address) {
                    return 0;
                }
            }
        } else if (pk->instruction != DXL_SYNC_READ || pk->n_params - 4 > LANE_MAX_LISTED ||
                   u16(in + pk->params + 2) > LANE_MAX_READ) {
            return 0;
        }
        o += total;
        count++;
    }
    return count;
}

static void act(int32_t *a, size_t *k, int32_t kind, int32_t motor, int32_t x, int32_t y)
{
    a[4 * *k] = kind;
    a[4 * *k + 1] = motor;
    a[4 * *k + 2] = x;
    a[4 * *k + 3] = y;
    (*k)++;
}

/* VirtualMotor.write of one whole Goal Current (VirtualMotor._check's rules for it). */
static int32_t write_goal(lane_motor *m, const uint8_t *data, int32_t *value)
{
    uint8_t *t = m->table;
    int32_t v = (int16_t)u16(data);
    int32_t limit = u16(t + m->a_limit);
    *value = v;
    if (v < m->goal_lo || v > m->goal_hi) {
        return E_DATA_RANGE;
    }
    if (t[m->a_watchdog] == 0xFF) {
        return E_DATA_RANGE; /* goal values are read-only after a watchdog error */
    }
    if ((v < 0 ? -v : v) > limit) {
        return E_DATA_LIMIT;
    }
    t[m->a_goal] = data[0];
    t[m->a_goal + 1] = data[1];
    return 0;
}

/*
 * One packet lane_scan returned, applied to the tables: its actions (at most LANE_MAX_ACTIONS)
 * into actions, the status packets into out (at most LANE_OUT_SIZE bytes). Returns the number
 * of actions, or -1 when the caller's buffers are smaller than that (checked before anything
 * is changed).
 */
int32_t lane_execute(lane_chain *c, const uint8_t *in, const lane_packet *pk, int32_t *actions,
                     size_t cap_actions, uint8_t *out, size_t cap_out)
{
    const uint8_t *q = in + pk->params;
    size_t k, n_act = 0, w = 0;
    uint16_t address = u16(q), length = u16(q + 2);
    if (cap_actions < LANE_MAX_ACTIONS || cap_out < LANE_OUT_SIZE) {
        return -1;
    }
    if (pk->instruction == DXL_SYNC_WRITE) {
        for (k = 4; k + 3 <= pk->n_params && n_act < cap_actions; k += 3) {
            int16_t i = c->by_id[q[k]];
            int32_t value, error;
            if (i < 0 || !c->motors[i].answering) {
                continue;
            }
            error = write_goal(&c->motors[i], q + k + 1, &value);
            act(actions, &n_act, error ? ACT_REFUSED : ACT_WRITTEN, i, error ? error : value, 0);
        }
        return (int32_t)n_act;
    }
    act(actions, &n_act, ACT_READ, -1, address, length);
    for (k = 4; k < pk->n_params && n_act < cap_actions; k++) {
        int16_t i = c->by_id[q[k]];
        lane_motor *m;
        uint8_t error = 0;
        const uint8_t *data = NULL;
        size_t n_data = 0;
        int32_t got;
        if (i < 0 || !c->motors[i].answering) {
            continue;
        }
        m = &c->motors[i];
        if (m->table[m->a_level] != 1 && m->table[m->a_level] != 2) {
            act(actions, &n_act, ACT_CONTACT, i, 0, 0);
            continue;
        }
        if (length < 1 || (size_t)address + length > m->table_size) {
            error = E_ACCESS;
        } else {
            data = m->table + address;
            n_data = length;
        }
        if (m->table[m->a_error]) {
            error |= ALERT_BIT;
        }
        got = dxl_status(out + w, cap_out - w, m->id, error, data, n_data);
        if (got < 0) {
            return -1;
        }
        act(actions, &n_act, ACT_REPLY, i, (int32_t)w, got);
        w += (size_t)got;
    }
    return (int32_t)n_act;
}

/*
 * The bridge's side: the replies to a SYNC_READ of n motors, length data bytes each, as a
 * healthy chain sends them -- status packets back to back in the order asked, each with its
 * motor's ID, no error, the length asked, a good CRC and nothing stuffed. In Python their
 * parse (header search, CRC, a packet at a time) was a tenth of cochlea-run's period
 * (cochlea/dynamixel/bridge.py). Returns 1 and copies each motor's data into
 * raw[k * length ..] when the first n * (11 + length) bytes of buf are exactly that; else 0,
 * raw untouched, and the bridge parses the same bytes in Python (whatever is wrong is
 * reported as before).
 */
int32_t lane_status_block(const uint8_t *buf, size_t n_bytes, const uint8_t *ids, size_t n,
                          size_t length, uint8_t *raw)
{
    size_t k, i, frame = DXL_PREFIX + 2 + length + 2;
    if (n == 0 || length == 0 || length > DXL_MAX_FRAME || n_bytes < n * frame) {
        return 0;
    }
    for (k = 0; k < n; k++) {
        const uint8_t *p = buf + k * frame;
        if (p[0] != 0xFF || p[1] != 0xFF || p[2] != 0xFD || p[3] != 0x00 || p[4] != ids[k] ||
            u16(p + 5) != length + 4 || p[7] != DXL_STATUS || p[8] != 0) {
            return 0;
        }
        if (dxl_crc16(0, p, frame - 2) != u16(p + frame - 2) ||
            has_ff_ff_fd(p + DXL_PREFIX, frame - 2 - DXL_PREFIX)) {
            return 0;
        }
    }
    for (k = 0; k < n; k++) {
        const uint8_t *data = buf + k * frame + DXL_PREFIX + 2;
        for (i = 0; i < length; i++) {
            raw[k * length + i] = data[i];
        }
    }
    return 1;
}

/* The layout Python's ctypes structures must match (checked when the lane is loaded). */
int32_t lane_sizes(uint32_t *sizes)
{
    sizes[0] = (uint32_t)sizeof(lane_motor);
    sizes[1] = (uint32_t)sizeof(lane_chain);
    sizes[2] = (uint32_t)sizeof(lane_packet);
    sizes[3] = LANE_MAX_MOTORS;
    sizes[4] = LANE_MAX_PACKETS;
    sizes[5] = LANE_MAX_ACTIONS;
    sizes[6] = (uint32_t)LANE_OUT_SIZE;
    return 0;
}
