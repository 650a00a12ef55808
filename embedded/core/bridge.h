/* cochlea embedded runtime: the Dynamixel bridge, cochlea/dynamixel/bridge.py in C.
 *
 * Start-up (cochlea_bridge_start), each step on every motor before the next, every write
 * confirmed by its status packet; a failure shuts down safely and reports which step and which
 * motor, before anything moved:
 *   1. PING every motor and check its model number (and the alert bit); with a homing check
 *      (cochlea_bridge_expect_homing), READ the slider's homing marker;
 *   2. Torque Enable 0, Bus Watchdog 0 (clears a watchdog error latched by an earlier run);
 *   3. Operating Mode 0 (current control);  4. Return Delay Time 0;
 *   5. Current Limit from the drive table;  6. Goal Current 0;
 *   7. Bus Watchdog: the motors stop by themselves if the loop stops talking;
 *   8. SYNC_READ until the first good read; unwrap the single-turn encoders to the turn nearest
 *      the middle of each joint's limits, and refuse a joint outside its limits;
 *   9. Torque Enable 1, deferred to the first nonzero command (cochlea_bridge_write): its Goal
 *      Current first, then one SYNC_WRITE of Torque Enable 1 to every motor and one SYNC_READ
 *      of Torque Enable confirming each, so that no motor is powered at zero current while the
 *      loop gets ready (the parallel robot's slider fell
 *      meanwhile on the emulator). A refusal fails that write and every read after it
 *      (not-enabled), so the loop's read watchdog stops the run.
 * Each period: cochlea_bridge_read is one read of Present Current, Velocity and Position
 * (with the Realtime Tick check, from the Realtime Tick: on the X series 126..135 and
 * 120..135; on the P series 568..583), cochlea_bridge_write one SYNC_WRITE of Goal Current.
 * The read is a BULK_READ (each motor's block at its own address) when the models place it at
 * different addresses (a mixed chain: an X-series arm with a P-series joint), a
 * FAST_SYNC_READ (one combined status packet) when every motor's model data says it answers
 * it, a SYNC_READ otherwise; the write a BULK_WRITE where the models place Goal Current
 * differently: the generator's choice (dxl_bus), by the Python bridge's rule, and the Python
 * bridge's frames byte for byte. Every address and size comes from the generated drive
 * table's control tables (the model data), none from this code. Failures (timeout, CRC, error byte, hardware alert, length, port, late
 * traffic, non-finite command, stale packet) are a 0 return and counters, never a stop of
 * their own: the loop's watchdog decides.
 * The Realtime Tick check (cochlea_bridge_use_realtime_tick; the Python bridge's
 * realtime_tick, which cochlea-run sets): a motor's millisecond counter, read with the state,
 * that has not moved since a reply which had already arrived more than 1.1 ms (a tick and a
 * tenth for the motor's clock) before this request is a stale packet (a motor repeating old
 * data), and the read fails as stale-packet. It costs 6 bytes per motor and period.
 * Shut-down (cochlea_bridge_stop, also after a failed start-up and on every fault): SYNC_WRITE
 * Goal Current 0 and Torque Enable 0, each twice (no reply needed, so one dead motor cannot hold
 * up the others), then a READ of Torque Enable per motor to confirm. These and the torque-on
 * (and its read-back) are BULK_WRITE / BULK_READ where the models place the item differently
 * (Torque Enable 64 and 512), as the Python bridge sends them; the rest of this text says
 * SYNC_READ / SYNC_WRITE for any of them.
 */
#ifndef COCHLEA_BRIDGE_H
#define COCHLEA_BRIDGE_H

#include "cochlea_rt.h"
#include "drives.h"
#include "dxl.h"

#ifdef __cplusplus
extern "C" {
#endif

#define COCHLEA_MAX_DRIVES 16
/* The longest block a period may read per motor (bytes): the X series' Realtime Tick ..
 * Present Position is 16. */
#define COCHLEA_MAX_READ_LENGTH 32
#define COCHLEA_STALE_AFTER_NS 1100000

/* Failure kinds of a period (indices into cochlea_bridge.failures), the Python bridge's. */
enum cochlea_failure {
    COCHLEA_FAIL_TIMEOUT = 0, COCHLEA_FAIL_CRC, COCHLEA_FAIL_ERROR_BYTE, COCHLEA_FAIL_ALERT,
    COCHLEA_FAIL_LENGTH, COCHLEA_FAIL_PORT, COCHLEA_FAIL_LATE, COCHLEA_FAIL_NON_FINITE,
    COCHLEA_FAIL_NOT_ENABLED, COCHLEA_FAIL_STALE, COCHLEA_FAIL_KINDS
};
const char *cochlea_failure_name(int kind);
/* The name cochlea-run writes of a transfer (dxl.h's DXL_SYNC_READ .. DXL_BULK_WRITE), e.g.
 * "BULK_READ"; "unknown" for another code. */
const char *cochlea_instruction_name(int instruction);

/* Why a start-up failed. */
enum cochlea_start_error {
    COCHLEA_START_OK = 0,
    COCHLEA_START_NO_ANSWER,      /* a motor did not answer (motor, step) */
    COCHLEA_START_CRC,            /* it answered with corrupted packets only */
    COCHLEA_START_PORT,           /* the port itself failed */
    COCHLEA_START_ALERT,          /* it reports a hardware error (detail: Hardware Error) */
    COCHLEA_START_REFUSED,        /* it refused an instruction (detail: its error byte) */
    COCHLEA_START_WRONG_MODEL,    /* detail: the model number it answered */
    COCHLEA_START_NO_READ,        /* no good SYNC_READ in 3 x retries tries */
    COCHLEA_START_OUTSIDE_LIMITS, /* a joint reads outside its limits (value: q, SI) */
    COCHLEA_START_BAD_CONFIG,     /* too many drives, a frame that does not fit */
    COCHLEA_START_NOT_HOMED,      /* the slider's homing marker is not the record's (detail:
                                   * the value it holds): power-cycled or rebooted since */
    COCHLEA_START_AWAY_FROM_START /* a joint stands farther from the scenario's initial pose
                                   * than the tolerance (value: q, expected: the pose's, SI) */
};

/* Start-up steps, for messages. */
enum cochlea_start_step {
    COCHLEA_STEP_PING = 1, COCHLEA_STEP_TORQUE_OFF, COCHLEA_STEP_WATCHDOG_CLEAR,
    COCHLEA_STEP_MODE, COCHLEA_STEP_RETURN_DELAY, COCHLEA_STEP_CURRENT_LIMIT,
    COCHLEA_STEP_GOAL_ZERO, COCHLEA_STEP_WATCHDOG, COCHLEA_STEP_FIRST_READ,
    COCHLEA_STEP_LIMITS, COCHLEA_STEP_TORQUE_ON, COCHLEA_STEP_HOMING
};

typedef struct {
    int error;        /* enum cochlea_start_error */
    int step;         /* enum cochlea_start_step */
    int drive;        /* index into the drive table, or -1 */
    int detail;       /* model number, error byte, Hardware Error Status, failure kind */
    double value;     /* the joint's position (SI) for COCHLEA_START_OUTSIDE_LIMITS and
                       * COCHLEA_START_AWAY_FROM_START */
    double expected;  /* the scenario's initial position of that joint (SI), for the latter */
} cochlea_start_report;

typedef struct {
    /* Configuration (cochlea_bridge_init). */
    const cochlea_hal *hal;
    const cochlea_drive *drives;
    int n;
    const dxl_bus *bus;         /* the drives' bus: transfers and control tables (dxl.h) */
    const char *config_problem; /* why cochlea_bridge_init refused the drive table, or NULL */
    int64_t timeout_ns;         /* a period's transaction: the bus budget plus margin */
    uint8_t watchdog_lsb;       /* Bus Watchdog, 20 ms per LSB */
    double position_margin;     /* start-up: how far outside its limits a joint may read (SI) */
    const double *expected_start; /* start-up: where the scenario starts the joints (n, SI),
                                   * or NULL (cochlea_bridge_init): no check */
    double start_tolerance[2];  /* how far from it a revolute (rad), a prismatic joint (m) may
                                 * stand: 5 deg, 5 mm by default */
    int retries;
    int realtime_tick;          /* read the Realtime Tick and refuse stale packets */
    int read_length;            /* bytes per motor of the period's read */
    uint16_t read_address;      /* where that block starts on the first motor */
    uint16_t read_addresses[COCHLEA_MAX_DRIVES]; /* and on each motor (its model's data: they
                                 * differ on a mixed chain, read by BULK_READ) */
    int read_at[4];             /* offsets in it of the Realtime Tick, Present Current,
                                 * Velocity, Position (the tick's only with realtime_tick) */
    uint8_t read_size[4];       /* and their sizes (bytes), from the model data */
    int homing_drive;           /* the homed slider's drive index, -1: no homing check */
    uint16_t homing_marker;     /* the token it must hold (the homing record's) */
    double homing_offset;       /* its position offset from the record (m) */
    int offset_current;         /* 1 (the default): each command gets the fit's offset current,
                                 * the gearbox's friction; 0: the controller compensates it
                                 * (the scenario's bridge_offset_current) */
    /* State. */
    int active;                 /* between a successful start and the stop */
    int torque_pending;         /* Torque Enable 1 still to come, with the first nonzero command */
    int torque_failed_id;       /* the motor that refused it (every read then fails), or -1 */
    int suspect;                /* a failed read: wait for a quiet line before the next */
    double position_offset[COCHLEA_MAX_DRIVES];
    /* each drive's per-period conversions in the working precision (drives.h), set up with
     * its position offset at init and again at the start (the unwrap, the homing) */
    cochlea_drive_real conv[COCHLEA_MAX_DRIVES];
    int32_t present_position[COCHLEA_MAX_DRIVES]; /* counts, last good read */
    int32_t present_velocity[COCHLEA_MAX_DRIVES]; /* LSB, last good read */
    int16_t present_current[COCHLEA_MAX_DRIVES];  /* LSB, last good read */
    cochlea_real joint_current[COCHLEA_MAX_DRIVES]; /* the same in A at the joint's sign */
    int16_t goal[COCHLEA_MAX_DRIVES];             /* LSB, last written */
    /* Counters. */
    uint32_t reads, good_reads, writes, unexpected_packets, garbage_packets;  /* of the run */
    uint32_t startup_reads;     /* SYNC_READs of the start-up, kept apart */
    uint32_t failures[COCHLEA_FAIL_KINDS];
    int last_failure, last_failure_id;
    int alert_id;               /* a motor that raised the alert bit, or -1 */
    int confirmed_off;          /* motors that confirmed torque off at the last stop */
    uint8_t off_confirmed[COCHLEA_MAX_DRIVES];  /* per drive: 1 if it confirmed */
    int alert_status;           /* the alert motor's Hardware Error Status, -1 unreadable */
    /* Buffers. */
    dxl_parser parser;
    /* room for BULK_READ's request (5 bytes per motor) and BULK_WRITE's Goal Current (7) */
    uint8_t read_frame[DXL_FRAME_SIZE(5 * COCHLEA_MAX_DRIVES)];
    size_t read_len;
    uint8_t write_frame[DXL_FRAME_SIZE(7 * COCHLEA_MAX_DRIVES)];
    uint8_t scratch[DXL_FRAME_SIZE(4 + 5 * COCHLEA_MAX_DRIVES)];
    uint8_t raw[COCHLEA_MAX_DRIVES * COCHLEA_MAX_READ_LENGTH];
    int32_t last_tick[COCHLEA_MAX_DRIVES];        /* the last Realtime Tick seen, -1 none */
    int64_t tick_seen_ns[COCHLEA_MAX_DRIVES];     /* when the reply first carrying it was in */
    uint8_t slots[COCHLEA_MAX_DRIVES];
} cochlea_bridge;

/* 0, or -1 when the drive table does not fit the bridge (b->config_problem says why, one
 * line): more than COCHLEA_MAX_DRIVES drives, no bus, a motor without an item the bridge
 * writes, a Goal Current not of 2 bytes, or transfers that do not fit the motors (a SYNC_READ
 * or SYNC_WRITE where they place the items at different addresses, blocks of different
 * lengths or layouts: a table written by hand; the generator never writes one).
 * watchdog_s is rounded up to whole 20 ms, within 20..2540 ms. */
int cochlea_bridge_init(cochlea_bridge *b, const cochlea_hal *hal, const cochlea_drive *drives,
                        int n, int64_t timeout_ns, double watchdog_s);
/* Read the Realtime Tick with the state and refuse stale packets (before the start). 0, or -1
 * when the frame does not fit. */
int cochlea_bridge_use_realtime_tick(cochlea_bridge *b);
/* The homing check of a joint whose encoder loses its turns at power-on (the parallel robot's
 * slider), cochlea-run's: after the PINGs and before any write, drive must hold marker at
 * its homing-marker item, else the start fails (COCHLEA_START_NOT_HOMED); its position
 * is then q_per_count counts + offset (the homing record's stop), and the marker is written
 * back after the configuration. The marker's item is the drive's Feedforward 2nd Gain (RAM,
 * unused in current control, 0 after power-on and REBOOT: cochlea/dynamixel/homing.py), at
 * the address of its model's table. Call before cochlea_bridge_start. */
void cochlea_bridge_expect_homing(cochlea_bridge *b, int drive, uint16_t marker, double offset);
/* Steps 1-8, step 9 armed for the first nonzero command; 1 on success, else 0 with *report
 * filled, after the safe stop. */
int cochlea_bridge_start(cochlea_bridge *b, cochlea_start_report *report);
/* One SYNC_READ into q[n], qd[n] (SI, the working precision: integer counts to float by the
 * drives' _real conversions in the float build); 1, or 0 on a failure (counted). */
int cochlea_bridge_read(cochlea_bridge *b, cochlea_real *q, cochlea_real *qd);
/* One SYNC_WRITE of Goal Current for the joint efforts tau[n] (SI); a non-finite effort sends
 * zero current to every motor and counts as a failure. 1, or 0 on a failure. */
int cochlea_bridge_write(cochlea_bridge *b, const cochlea_real *tau);
/* The safe shut-down; the number of motors that confirmed torque off. */
int cochlea_bridge_stop(cochlea_bridge *b);
/* The bridge as the loop's backend (read, write, the safe shut-down as its shutdown, and
 * joint_current as its measured current). */
cochlea_backend cochlea_bridge_backend(cochlea_bridge *b);

#ifdef __cplusplus
}
#endif

#endif /* COCHLEA_BRIDGE_H */
