/* cochlea all-in-C simulation: one scenario's closed loop with no Python and no CasADi.
 *
 *   simulate [--duration S] [--log FILE]
 *
 * The controller is the scenario's generated embedded controller (generated_c/embedded/), which
 * evaluates the desired trajectory itself at each period's time; the plant is each unit's
 * generated plant period, the same RK4 period as the simulation's, specialised to the
 * scenario's constants (sim.h: sim_plant.c; the geared plant runs its generated_c/ kernel).
 * The scenario is compiled in (sim.h, sim_scenario.h): build it with
 * `python bench/embedded_bench.py build` or `make embedded-sim`.
 *
 * Period k, at t = k h (h = SIM_PERIOD, s), as cochlea.sim.simulate runs it:
 *   1. the state x_k of every unit is logged, and the estimate the controller holds;
 *   2. the controller measures x_{k - delay} (x_0 before that; the delay plus the period's
 *      jitter, if any) of every unit, its positions off by whole encoder counts, if any, put
 *      on the unit's measurement grid, if any;
 *   3. <scenario>_step returns the commands (N m, N), clipped to the effort limits as the
 *      supervisor clips them, the errors, and advances the estimate one period (here as its
 *      two halves: <scenario>_desired at t, then the step on that sample, which the log
 *      keeps);
 *   4. each drive applies its command on its effort grid, if any; the applied effort is logged
 *      and held over the period;
 *   5. each unit's plant integrates the period under the applied effort, times the motors'
 *      torque-constant error (1 + e) where the unit has one: x_{k+1}.
 * The delay's jitter (SIM_JITTER) and the encoder counts of noise (SIM_ENCODER_COUNTS) are
 * drawn as cochlea.sim.setup draws them: numpy's PCG64 from each stream's starting state
 * (sim.h), one double per period for the jitter and one per joint and period for the counts,
 * turned into whole numbers as cochlea.sim.setup.uniform_integers does; the counts times each
 * joint's encoder quantum are added to the measured positions before the grid. (Gaussian
 * noise is not simulated: bench/embedded_bench.py refuses a scenario with it.)
 * The run stops after period k when a state or the estimate is no longer finite ("diverged",
 * k + 1 rows), or before it when the step refuses a non-finite output ("step-failed", k rows).
 *
 * Each unit runs on a thread of its own (the first on the main thread), with its own plant,
 * its own copy of the controller's state and its own measurement history, for the whole run:
 * no synchronisation per period. The units of an embedded controller are independent (each
 * its own desired path, law and estimate: mirror = "desired", the only mode the embedded
 * controller has), so each unit's numbers are those of one loop over all units, bit for bit;
 * the controller's per-unit step (<scenario>_step_desired_unit, COCHLEA_UNIT_STEPS) is its
 * step's work on that unit's entries. The delay's jitter and the encoder counts are drawn by
 * every unit's thread from the same streams (the same numbers; each uses its own). The run
 * ends at the first unit's stop, in the order one loop over the units would meet it (a step
 * refused in period k before a state diverged in it, k rows; diverged in period k, k + 1
 * rows); a unit that runs on past it is cut there.
 *
 * --log FILE writes one row of doubles (native byte order) per period:
 *   t (s), x[NX], p_hat[NP], tau[NQ], errors[NE], pose[NPOSE], xd[ND], xd_dot[ND]
 * each block unit after unit (x: per unit [q, qd]). Each unit's thread writes its part of the
 * rows into a ring of blocks of its own; the units' parts of each block's rows are put
 * together, their poses evaluated from their x and the block written to the file while the
 * units fill the next (the poses and the page cache's copy were a quarter of a serial study's
 * time), by a writer thread where the process has a processor more than its units, else by the
 * units themselves, whichever is ahead (sim_writer; COCHLEA_SIM_LOG_WRITER=thread or units
 * chooses). Without --log the pose, which only the log needs, is not evaluated. An existing
 * regular FILE (one link) is removed and a new one created, not truncated (open_log: 4-5 ms
 * less on ext4 over a previous serial log); anything else (a link, a device, a FIFO, a file
 * that cannot be removed) is opened and truncated as before. The file's blocks are reserved
 * for the whole run at its first write (reserve_blocks) and what a shorter run did not use is
 * given back at its end.
 *
 * Prints one line of JSON on stdout: the scenario, the sizes, the rows run, the status, the
 * wall time (s) of the loop (loop_s: from starting the units' threads to the last one's end)
 * and of the whole program from main() on (main_s), the loop's own CPU time (loop_cpu_s: the
 * busiest unit thread's, a writer thread's not included; on a busy machine the measure of the
 * loop's work; unit_cpu_s: each unit thread's, with what it wrote of the log), the threads the
 * units ran on, the processor each unit's thread ended on (unit_processors: each on its own
 * while the units' and the writer's threads are no more than the processors, place_main; -1
 * where the system does not say), who wrote the log (log_writer: "thread", "units" or "none")
 * and a writer thread's CPU time (writer_cpu_s, 0 without one), and each unit's sizes.
 * Exit status: 0 completed, 1 diverged or step-failed, 2 bad arguments or an unwritable log. */
#ifdef __linux__
#define _GNU_SOURCE /* sched_getcpu, pthread_setaffinity_np: see place_main */
#else
#define _POSIX_C_SOURCE 200112L
#endif
#include "sim_scenario.h"
/* The controller in this translation unit: each unit's thread evaluates its desired sample
 * once per period and hands it to its step (<scenario>_step is <scenario>_desired at t, then
 * <scenario>_step_desired on that sample; per unit <scenario>_desired_unit and
 * <scenario>_step_desired_unit, which COCHLEA_UNIT_STEPS compiles), and the log writes the
 * same sample. */
#define COCHLEA_UNIT_STEPS
#if SIM_INLINE_TRIG && !defined(COCHLEA_FLOAT)
/* The double build's controller takes sin and cos from sim_sincos too (sim_trig.h: inline,
 * within an ulp of libm; the scenario says where that is allowed) */
#include <math.h>
#include "sim_trig.h"
#define sin(x) sim_sin(x)
#define cos(x) sim_cos(x)
#include SIM_CONTROLLER_SOURCE
#undef sin
#undef cos
#else
#include SIM_CONTROLLER_SOURCE
#endif

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <pthread.h>
#ifdef __linux__
#include <sched.h>
#endif
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#ifdef COCHLEA_FLOAT
#define SIM_PRECISION "float"
#else
#define SIM_PRECISION "double"
#endif

#define SIM_COLUMNS (1 + SIM_NX + SIM_NP + SIM_NQ + SIM_NE + SIM_NPOSE + 2 * SIM_ND)

typedef SIM_C(_real) sim_real;

static double clock_s(clockid_t clock)
{
    struct timespec t;
    clock_gettime(clock, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static double now_s(void)
{
    return clock_s(CLOCK_MONOTONIC);
}

static int all_finite(const double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i)
        if (!(v[i] - v[i] == 0.0)) return 0;
    return 1;
}

/* The same for the estimate, in the controller's precision (float in the float build). */
static int all_finite_real(const sim_real *v, int n)
{
    int i;
    for (i = 0; i < n; ++i)
        if (!(v[i] - v[i] == 0)) return 0;
    return 1;
}

#if SIM_JITTER > 0 || SIM_ENCODER_COUNTS > 0
/* numpy's PCG64 (128-bit LCG, XSL-RR output), as np.random.default_rng draws */
__extension__ typedef unsigned __int128 sim_u128;

static sim_u128 sim_u128_of(uint64_t high, uint64_t low)
{
    return ((sim_u128)high << 64) | (sim_u128)low;
}

typedef struct {
    sim_u128 state, inc;
} sim_pcg64;

static void sim_pcg64_start(sim_pcg64 *g, const uint64_t seed[4])
{
    g->state = sim_u128_of(seed[0], seed[1]);
    g->inc = sim_u128_of(seed[2], seed[3]);
}

/* One step, then the output of the new state (numpy's pcg64_next64) */
static uint64_t sim_pcg64_next(sim_pcg64 *g)
{
    const sim_u128 multiplier = sim_u128_of(0x2360ED051FC65DA4ULL, 0x4385DF649FCCF645ULL);
    uint64_t x;
    unsigned r;
    g->state = g->state * multiplier + g->inc;
    x = (uint64_t)(g->state >> 64) ^ (uint64_t)g->state;
    r = (unsigned)(g->state >> 122);
    return (x >> r) | (x << ((64u - r) & 63u));
}

/* Generator.random(): a double in [0, 1), then cochlea.sim.setup.uniform_integers */
static double sim_integer(sim_pcg64 *g, int low, int high)
{
    const double u = (double)(sim_pcg64_next(g) >> 11) * (1.0 / 9007199254740992.0);
    const double count = (double)(high - low + 1);
    return fmin(floor(u * count), count - 1.0) + (double)low;
}
#endif

#define SIM_RING (SIM_DELAY + SIM_JITTER + 1) /* periods of true states kept */

/* Where each unit's entries are in the arrays of the whole scenario, and its part of a row */
typedef struct {
    int xp, x, q, p, e, d, pose; /* first entry in the plants' state, x, tau, p_hat, errors,
                                    xd, pose */
    int width;                   /* its part of a row: x, p_hat, tau, errors, xd, xd_dot */
} sim_offsets;

static sim_offsets sim_offset[SIM_UNITS];

#define SIM_POSE_COLUMN (1 + SIM_NX + SIM_NP + SIM_NQ + SIM_NE)
#define SIM_UNIT_COLUMNS (SIM_COLUMNS - 1 - SIM_NPOSE) /* at most, a unit's part of a row */

/* The column of a row each entry of a unit's part goes to (a scatter, which the compiler
 * does not turn into calls of memcpy as it does loops of a few copies) */
static int sim_column[SIM_UNITS][SIM_UNIT_COLUMNS];

static void find_offsets(void)
{
    sim_offsets o = {0, 0, 0, 0, 0, 0, 0, 0};
    int u, i;
    for (u = 0; u < SIM_UNITS; ++u) {
        const sim_unit *s = &sim_units[u];
        int *to = sim_column[u];
        o.width = 2 * s->nq + s->np + s->nq + s->ne + 2 * s->nd;
        sim_offset[u] = o;
        for (i = 0; i < 2 * s->nq; ++i) *to++ = 1 + o.x + i;
        for (i = 0; i < s->np; ++i) *to++ = 1 + SIM_NX + o.p + i;
        for (i = 0; i < s->nq; ++i) *to++ = 1 + SIM_NX + SIM_NP + o.q + i;
        for (i = 0; i < s->ne; ++i) *to++ = 1 + SIM_NX + SIM_NP + SIM_NQ + o.e + i;
        for (i = 0; i < s->nd; ++i) *to++ = SIM_POSE_COLUMN + SIM_NPOSE + o.d + i;
        for (i = 0; i < s->nd; ++i) *to++ = SIM_POSE_COLUMN + SIM_NPOSE + SIM_ND + o.d + i;
        o.xp += s->nxp;
        o.x += 2 * s->nq;
        o.q += s->nq;
        o.p += s->np;
        o.e += s->ne;
        o.d += s->nd;
        o.pose += s->npose;
    }
}

/* The log: each unit's parts of the rows in SIM_BLOCKS blocks of SIM_BLOCK_ROWS rows (a ring
 * per unit); block n is written once every unit has handed it: its rows put together (with
 * their poses) and written while the units fill the next ones (several, so that a writer held
 * up by other work on the machine does not stop the units at once). Who writes it:
 *
 * - a writer thread of its own, where the process has a processor more than it has units (the
 *   parallel studies' one unit: the writer runs on the other processor);
 * - else the units themselves (units_write): a unit that has handed a block looks at the
 *   oldest block not written and writes it if it is ready and the unit is ahead of it (has
 *   handed a later block), must have its slot back to go on, has handed its last rows, or is
 *   the only unit still running. The unit ahead has time to spare, so the writing goes to
 *   whichever unit is ahead, which then falls behind: on two vCPUs the two arms' threads, each
 *   held on its own processor, share the writing as their loads allow, where a third thread
 *   left one arm a processor to itself and the other arm and the writer the other one (the
 *   scheduler balances threads, not their work: serial_task's arms 6.2 ms of CPU each and the
 *   writer 4 ms, the loop 8-11 ms).
 *
 * One block is written at a time (writing), in order. */
#define SIM_BLOCKS 4
#define SIM_BLOCK_ROWS ((1 << 18) / (8 * SIM_COLUMNS) + 1)

typedef struct {
    int fd;
    int units_write;                  /* 1: no writer thread, the units write (above) */
    pthread_t thread;
    pthread_mutex_t lock;
    pthread_cond_t changed;
    long rows[SIM_UNITS][SIM_BLOCKS]; /* rows of each unit's handed blocks */
    long handed[SIM_UNITS];           /* blocks each unit has handed */
    int done[SIM_UNITS];              /* 1: the unit has handed its last block */
    long written;                     /* blocks written (or being written: then not free) */
    int writing;                      /* 1: block `written` is being written */
    int ended;                        /* the last whole rows are written: the log's end */
    int failed;                       /* 1: a write failed, 2: a pose kernel did */
    long expected;                    /* rows of a whole run: the file's blocks reserved */
    long rows_written;                /* rows in the file */
    int held;                         /* the last run's log, removed (open_log), or -1 */
    int reserved;                     /* 1: the blocks are reserved, the last log let go */
    double cpu_s;                     /* s: the writer thread's CPU time (0: units_write) */
} sim_writer;

static double sim_unit_blocks[SIM_UNITS][SIM_BLOCKS][SIM_BLOCK_ROWS * SIM_UNIT_COLUMNS];
static double sim_rows[SIM_BLOCK_ROWS * SIM_COLUMNS]; /* the writer's rows, put together */

/* Each row's pose[NPOSE], unit after unit, from the row's x (the state logged): 0, or -1 if a
 * pose kernel returned an error. */
static int fill_poses(double *block, long rows)
{
    long k;
    for (k = 0; k < rows; ++k) {
        double *row = block + k * SIM_COLUMNS, *pose = row + SIM_POSE_COLUMN;
        const double *x = row + 1;
        int u;
        for (u = 0; u < SIM_UNITS; ++u) {
            const sim_unit *s = &sim_units[u];
            const double *arg[1];
            double *res[1];
            arg[0] = x;
            res[0] = pose;
            if (s->pose(arg, res, NULL, NULL, 0) != 0) return -1;
            x += 2 * s->nq;
            pose += s->npose;
        }
    }
    return 0;
}

/* Rows [first, first + rows) of the run from the units' block slot: t, then each unit's parts
 * in their places (the poses are filled in after). */
static void put_together(int slot, long first, long rows)
{
    long k;
    int u, i;
    for (k = 0; k < rows; ++k) {
        double *row = sim_rows + k * SIM_COLUMNS;
        row[0] = (double)(first + k) * SIM_PERIOD; /* the units' t of the period */
        for (u = 0; u < SIM_UNITS; ++u) {
            const int width = sim_offset[u].width, *to = sim_column[u];
            const double *part = sim_unit_blocks[u][slot] + k * width;
            for (i = 0; i < width; ++i) row[to[i]] = part[i];
        }
    }
}

static int write_all(int fd, const char *data, size_t bytes)
{
    while (bytes > 0) {
        const ssize_t done = write(fd, data, bytes);
        if (done < 0 && errno == EINTR) continue;
        if (done <= 0) return -1;
        data += done;
        bytes -= (size_t)done;
    }
    return 0;
}

/* The blocks of a whole run's log reserved at once, the file's size left to the writes (so a
 * run that stops early, or a process killed, leaves only its rows): ext4 then allocates no
 * block per page written, which took 1.7 ms of an 8.8 MB log's 20 s run against 0.9 ms
 * reserved (writer_finish gives back what a shorter run did not use). Where the file system
 * or the system cannot, the writes allocate as before. */
static void reserve_blocks(int fd, long rows)
{
#if defined(__linux__) && defined(FALLOC_FL_KEEP_SIZE)
    const off_t row_bytes = (off_t)(SIM_COLUMNS * sizeof(double));
    (void)fallocate(fd, FALLOC_FL_KEEP_SIZE, 0, (off_t)rows * row_bytes);
#else
    (void)fd;
    (void)rows;
#endif
}

/* Under w->lock: whether block w->written can be written: 1 (its rows in *rows: the fewest a
 * unit handed in it), 0 not yet (a unit still filling it), -1 the log ends before it (a unit
 * has handed its last rows before it). */
static int block_ready(const sim_writer *w, long *rows)
{
    const long n = w->written;
    const int slot = (int)(n % SIM_BLOCKS);
    int u, ready = 1;
    *rows = SIM_BLOCK_ROWS;
    for (u = 0; u < SIM_UNITS; ++u) {
        if (w->handed[u] > n) {
            if (w->rows[u][slot] < *rows) *rows = w->rows[u][slot];
        } else if (w->done[u]) {
            return -1; /* this unit's rows end before block n: so do the log's */
        } else {
            ready = 0;
        }
    }
    return ready;
}

/* Under w->lock, block w->written ready with rows rows: written (the lock let go meanwhile),
 * then w->written moved on; a block of fewer rows than a whole one ends the log. The first
 * write lets the last run's log go (its pages freed) and reserves this one's blocks, while
 * the units fill the first blocks. */
static void write_block(sim_writer *w, long rows)
{
    const long n = w->written;
    int failed;
    w->writing = 1;
    pthread_mutex_unlock(&w->lock);
    if (!w->reserved) {
        if (w->held >= 0) close(w->held);
        w->held = -1;
        reserve_blocks(w->fd, w->expected);
        w->reserved = 1;
    }
    put_together((int)(n % SIM_BLOCKS), n * SIM_BLOCK_ROWS, rows);
    failed = fill_poses(sim_rows, rows) ? 2
             : write_all(w->fd, (const char *)sim_rows,
                         (size_t)rows * SIM_COLUMNS * sizeof(double)) ? 1 : 0;
    pthread_mutex_lock(&w->lock);
    w->writing = 0;
    if (!w->failed) w->failed = failed;
    if (!failed) w->rows_written += rows;
    w->written = n + 1;
    if (rows < SIM_BLOCK_ROWS) w->ended = 1; /* a unit's last rows: the log's */
    pthread_cond_broadcast(&w->changed);
}

static void *writer_main(void *arg)
{
    sim_writer *w = arg;
    long rows;
    pthread_mutex_lock(&w->lock);
    while (!w->ended) {
        const int ready = block_ready(w, &rows);
        if (ready < 0) break;
        if (ready) write_block(w, rows);
        else pthread_cond_wait(&w->changed, &w->lock);
    }
    w->ended = 1;
    w->cpu_s = clock_s(CLOCK_THREAD_CPUTIME_ID);
    pthread_cond_broadcast(&w->changed);
    pthread_mutex_unlock(&w->lock);
    return NULL;
}

/* Under w->lock, units_write: unit u (u < 0: the main thread after the units) writes the ready
 * blocks it should (above); with wait, it waits for its next slot while that is not free,
 * writing the blocks it can meanwhile. */
static void units_write(sim_writer *w, int u, int wait)
{
    long rows;
    while (!w->ended) {
        int v, running = 0, ready;
        for (v = 0; v < SIM_UNITS; ++v)
            if (v != u && !w->done[v]) running = 1;
        ready = w->writing ? 0 : block_ready(w, &rows);
        if (ready < 0) {
            w->ended = 1;
            pthread_cond_broadcast(&w->changed);
            break;
        }
        if (ready && (u < 0 || w->done[u] || !running || w->handed[u] > w->written + 1 ||
                      (wait && w->handed[u] - w->written >= SIM_BLOCKS))) {
            write_block(w, rows);
            continue;
        }
        if (!wait || w->handed[u] - w->written < SIM_BLOCKS) break;
        pthread_cond_wait(&w->changed, &w->lock);
    }
}

/* Unit u hands the first rows of its block *slot (rows > 0, or 0 with last) to the writer and
 * moves *slot on to its next block once that one is free; last: the unit's last rows. 0, or
 * the writer's failure so far (sim_writer.failed), or -1 when the log has ended (before this
 * unit's rows: another unit stopped first). */
static int writer_hand(sim_writer *w, int u, int *slot, long rows, int last)
{
    int failed;
    pthread_mutex_lock(&w->lock);
    if (rows > 0) {
        w->rows[u][*slot] = rows;
        w->handed[u] += 1;
    }
    if (last) w->done[u] = 1;
    pthread_cond_broadcast(&w->changed);
    if (w->units_write) {
        units_write(w, u, !last);
    } else {
        while (!last && !w->ended && w->handed[u] - w->written >= SIM_BLOCKS)
            pthread_cond_wait(&w->changed, &w->lock);
    }
    failed = w->failed ? w->failed : w->ended && !last ? -1 : 0;
    pthread_mutex_unlock(&w->lock);
    *slot = (*slot + 1) % SIM_BLOCKS;
    return failed;
}

/* The log's file descriptor: a new file in place of an existing regular file of one link
 * (removed, then created with O_EXCL), else path opened as before, truncated. Truncating the
 * previous run's log (8.8 MB for a serial study) cost 4-5 ms more wall time than writing a new
 * file on ext4 (freeing its blocks, and at close the flush ext4's auto_da_alloc starts for a
 * file truncated and written again). The old file is held open while it is removed, so that
 * freeing its pages (0.8-1.1 ms of an 8.8 MB log) happens when the writer thread closes it
 * (w->held), beside the units' first periods, not before the loop can start; a reader holding
 * it (or a map of it) still reads all of it, as it was. Its pages are not written over: such
 * a map would change under its reader, and fault past a shorter log's end. lstat: a symbolic
 * link, a device (/dev/null, /dev/full), a FIFO or a file with other names is never removed; a
 * file that cannot be removed (its folder not writable) or that another process creates again
 * in between is truncated. The new file has mode 0666 less the umask, not the old one's. -1:
 * not writable. */
static int open_log(sim_writer *w, const char *path)
{
    struct stat st, held;
    w->held = -1;
    if (lstat(path, &st) == 0 && S_ISREG(st.st_mode) && st.st_nlink == 1) {
        w->held = open(path, O_RDONLY | O_NOFOLLOW | O_NONBLOCK);
        if (w->held >= 0 && (fstat(w->held, &held) != 0 || held.st_ino != st.st_ino ||
                             held.st_dev != st.st_dev)) {
            close(w->held); /* another file by now: nothing to hold */
            w->held = -1;
        }
        if (unlink(path) == 0) {
            const int fd = open(path, O_WRONLY | O_CREAT | O_EXCL, 0666);
            if (fd >= 0 || errno != EEXIST) return fd;
        }
    }
    return open(path, O_WRONLY | O_CREAT | O_TRUNC, 0666);
}

/* The removed log let go if the writer has not (its pages freed), and the log closed, a
 * regular file cut to the rows written: the blocks reserved for a longer run given back (a
 * device or a FIFO is left as it is). 0, or 1 if closing failed. */
static int close_log(sim_writer *w)
{
    struct stat st;
    int failed = 0;
    if (w->held >= 0) close(w->held);
    w->held = -1;
    if (fstat(w->fd, &st) == 0 && S_ISREG(st.st_mode) &&
        ftruncate(w->fd, (off_t)w->rows_written * (off_t)(SIM_COLUMNS * sizeof(double))) != 0)
        failed = 1;
    if (close(w->fd) != 0) failed = 1;
    return failed;
}

/* The log's writer for a run of expected rows: the units write it (units_write, 1) or a
 * thread of its own (0). 0, or -1 if the log cannot be opened or the thread started. */
static int writer_start(sim_writer *w, const char *path, long expected, int by_units)
{
    memset(w->rows, 0, sizeof w->rows);
    memset(w->handed, 0, sizeof w->handed);
    memset(w->done, 0, sizeof w->done);
    w->units_write = by_units;
    w->written = 0;
    w->writing = w->ended = w->failed = w->reserved = 0;
    w->expected = expected;
    w->rows_written = 0;
    w->cpu_s = 0.0;
    w->fd = open_log(w, path);
    if (w->fd < 0) return -1;
    if (pthread_mutex_init(&w->lock, NULL) == 0 && pthread_cond_init(&w->changed, NULL) == 0 &&
        (by_units || pthread_create(&w->thread, NULL, writer_main, w) == 0))
        return 0;
    (void)close_log(w);
    return -1;
}

/* Every unit has handed its last rows: the writer's end (units_write: what is left written by
 * this thread), the log closed (close_log); 0, or the writer's failure (1 also when closing
 * failed). */
static int writer_finish(sim_writer *w)
{
    if (w->units_write) {
        pthread_mutex_lock(&w->lock);
        units_write(w, -1, 0);
        w->ended = 1;
        pthread_mutex_unlock(&w->lock);
    } else {
        pthread_join(w->thread, NULL);
    }
    if (close_log(w) && !w->failed) w->failed = 1;
    return w->failed;
}

/* The processors the process may run on (Linux; elsewhere one more than the units: a writer
 * thread, as before). */
static int usable_processors(void)
{
#ifdef __linux__
    cpu_set_t allowed;
    if (sched_getaffinity(0, sizeof allowed, &allowed) == 0) return CPU_COUNT(&allowed);
#endif
    return SIM_UNITS + 1;
}

/* A run that ends without every unit's last rows (a thread not started, a plant's error, the
 * writer's): the writer stops at the first block a unit has not handed, a unit waiting for a
 * free block is let go, and the log is closed with the rows written (writer_finish). */
static void writer_abandon(sim_writer *w)
{
    int u;
    pthread_mutex_lock(&w->lock);
    for (u = 0; u < SIM_UNITS; ++u) w->done[u] = 1;
    pthread_cond_broadcast(&w->changed);
    pthread_mutex_unlock(&w->lock);
}

static int cannot_write(const char *path, int failed)
{
    fprintf(stderr, "simulate: cannot write %s%s\n", path,
            failed == 2 ? " (a pose kernel returned an error)" : "");
    return 2;
}

static int usage(void)
{
    fprintf(stderr, "usage: simulate [--duration S] [--log FILE]   (scenario %s)\n", SIM_NAME);
    return 2;
}

/* One unit's run on its thread: what it is given, and how it ended */
typedef struct {
    int unit;
    long steps;                /* periods to run */
    sim_writer *writer;        /* the log's writer, NULL: no log */
    SIM_C(_state) state;       /* the controller's state as initialised (a copy per unit) */
    pthread_t thread;
    long rows;                 /* rows run */
    const char *status;        /* "completed", "diverged" or "step-failed" */
    int code;                  /* the step's code when it failed, the plant's (plant_failed) */
    int plant_failed;          /* 1: the plant returned an error code */
    int log_failed;            /* the writer's failure seen at a hand */
    double cpu_s;              /* s: the thread's CPU time over its loop */
    int processor;             /* the processor it ended on (Linux; -1 elsewhere) */
    char pad[64];              /* units on other cores: nothing they write shares a line */
} sim_lane;

/* Unit lane->unit's periods, as the loop over all units runs them (the header's steps 1-5) on
 * its entries of the scenario's arrays. */
static void *run_unit(void *arg)
{
    sim_lane *lane = arg;
    const int u = lane->unit;
    const sim_unit *s = &sim_units[u];
    const sim_offsets *o = &sim_offset[u];
    const double h = SIM_PERIOD;
    const int log = lane->writer != NULL;
    /* the plants' states (its entries; x = [q, qd] is the first 2 nq of its plant's) and
     * those of the last SIM_RING periods: copied whole, a size the compiler knows */
    double plant_x[SIM_NXP] = {0}, plant_next[SIM_NXP] = {0}, history[SIM_RING][SIM_NXP];
    const double *x = plant_x + o->xp;
    double tau[SIM_NQ], torque[SIM_NQ];
    sim_real measurement[SIM_NX], command[SIM_NQ], errors[SIM_NE];
    sim_real xd[SIM_ND], xd_dot[SIM_ND], xd_ddot[SIM_ND];
    SIM_C(_state) state = lane->state;
    int slot = 0;      /* its block the thread fills */
    long in_block = 0; /* its rows */
    long k, rows = 0;
    int i, code = 0;
    double cpu;
#if SIM_JITTER > 0
    sim_pcg64 jitter;
#endif
#if SIM_ENCODER_COUNTS > 0
    sim_pcg64 encoder;
    double counts[SIM_NQ]; /* this period's encoder counts of noise, joint after joint */
#endif

    lane->status = "completed";
    memcpy(plant_x + o->xp, s->x0, (size_t)s->nxp * sizeof(double));
#if SIM_JITTER > 0
    sim_pcg64_start(&jitter, sim_jitter_seed);
#endif
#if SIM_ENCODER_COUNTS > 0
    sim_pcg64_start(&encoder, sim_encoder_seed);
#endif
    cpu = clock_s(CLOCK_THREAD_CPUTIME_ID);
    for (k = 0; k < lane->steps; ++k) {
        const double t = (double)k * h; /* as the simulation's time grid, arange(N) * h */
        long age = SIM_DELAY; /* periods: how old this period's measurement is */
        const double *seen;
        double *r = sim_unit_blocks[u][slot] + in_block * o->width;

#if SIM_JITTER > 0
        age += (long)sim_integer(&jitter, 0, SIM_JITTER);
#endif
        seen = history[k >= age ? (k - age) % SIM_RING : 0] + o->xp;
#if SIM_ENCODER_COUNTS > 0
        for (i = 0; i < SIM_NQ; ++i)
            counts[i] = sim_integer(&encoder, -SIM_ENCODER_COUNTS, SIM_ENCODER_COUNTS);
#endif

        memcpy(history[k % SIM_RING], plant_x, sizeof plant_x);
        if (log) {
            for (i = 0; i < 2 * s->nq; ++i) *r++ = x[i];
            for (i = o->p; i < o->p + s->np; ++i) *r++ = state.p_hat[i]; /* used this period */
        }

        /* The measurement, its encoder counts of noise, on the unit's grid */
        for (i = 0; i < 2 * s->nq; ++i) {
            double m = seen[i];
#if SIM_ENCODER_COUNTS > 0
            if (i < s->nq) m += counts[o->q + i] * s->quantum[i];
#endif
            if (s->quantum && s->quantum[i] > 0) {
                const double q = s->quantum[i], off = s->offset[i];
                m = off + q * nearbyint((m - off) / q);
            }
            measurement[o->x + i] = (sim_real)m;
        }

        /* <scenario>_step's work for this unit at t, its desired sample kept for the log */
        code = SIM_C(_desired_unit)(u, t, xd, xd_dot, xd_ddot) != 0 ? -1
               : SIM_C(_step_desired_unit)(&state, u, xd, xd_dot, xd_ddot, measurement,
                                           command, errors);
        if (code != 0) {
            lane->status = "step-failed";
            break;
        }

        /* The drives: each command on its joint's effort grid */
        for (i = 0; i < s->nq; ++i) {
            double e = (double)command[o->q + i];
            if (s->effort_offset)
                e += s->effort_offset[i] * fmin(fmax(e / s->effort_ramp[i], -1.0), 1.0);
            if (s->effort_quantum) {
                if (s->effort_quantum[i] > 0)
                    e = s->effort_quantum[i] * nearbyint(e / s->effort_quantum[i]);
                e = fmin(fmax(e, -s->effort_bound[i]), s->effort_bound[i]);
            }
            tau[o->q + i] = e;
            torque[o->q + i] = s->torque_scale ? s->torque_scale[i] * e : e;
        }

        /* The plant */
        {
            const double *in[6]; /* a plant without a 6th input reads the first 5 */
            double *out[1];
            in[0] = plant_x + o->xp;
            in[1] = torque + o->q;
            in[2] = s->plant_p;
            in[3] = s->friction;
            in[4] = &h;
            in[5] = s->coulomb;
            out[0] = plant_next + o->xp;
            code = s->plant(in, out, NULL, NULL, 0);
            if (code != 0) {
                lane->plant_failed = 1;
                break;
            }
        }

        if (log) {
            for (i = o->q; i < o->q + s->nq; ++i) *r++ = tau[i];
            for (i = o->e; i < o->e + s->ne; ++i) *r++ = (double)errors[i];
            for (i = o->d; i < o->d + s->nd; ++i) *r++ = (double)xd[i];
            for (i = o->d; i < o->d + s->nd; ++i) *r++ = (double)xd_dot[i];
            if (++in_block == SIM_BLOCK_ROWS) {
                const int failed = writer_hand(lane->writer, u, &slot, in_block, 0);
                in_block = 0;
                if (failed > 0) lane->log_failed = failed;
                if (failed) {
                    rows = k + 1; /* the writer has ended: another unit stopped first */
                    break;
                }
            }
        }
        rows = k + 1;
        memcpy(plant_x, plant_next, sizeof plant_x);
        if (!all_finite(plant_x + o->xp, s->nxp) || !all_finite_real(state.p_hat + o->p, s->np)) {
            lane->status = "diverged";
            break;
        }
    }
    lane->cpu_s = clock_s(CLOCK_THREAD_CPUTIME_ID) - cpu;
#ifdef __linux__
    lane->processor = sched_getcpu();
#else
    lane->processor = -1;
#endif
    lane->rows = rows;
    lane->code = code;
    if (log && !lane->plant_failed && !lane->log_failed) {
        const int failed = writer_hand(lane->writer, u, &slot, in_block, 1);
        if (failed > 0) lane->log_failed = failed;
    }
    SIM_C(_terminate)(&state);
    return NULL;
}

/* Where a unit's stop falls in one loop over all units: in period k, the step's refusal
 * (k rows) before the states' divergence (k + 1 rows); completed, after every period. */
static long stop_order(const sim_lane *lane)
{
    if (strcmp(lane->status, "step-failed") == 0) return 2 * lane->rows;
    if (strcmp(lane->status, "diverged") == 0) return 2 * lane->rows - 1;
    return 2 * lane->rows + 1;
}

/* The units' processors (Linux), where the process has a processor for each of its busy
 * threads (the units, and the log's writer thread if any): the main thread's unit stays on the
 * processor it is on and the others go round the processors the process may use from the next
 * one on. Left to the scheduler, a new thread starts on its creator's processor and waits there
 * for a load balancer to move it, and the main thread moves about too: on this project's 2-vCPU
 * machine the two units of a 10 ms run shared one processor for milliseconds of it
 * (serial_task's loop 11.5 ms against 5.8 ms of each unit's CPU time; placed, 15 runs each:
 * 3405x real time against 2230x, serial_joint 2757x against 2081x). With more busy threads
 * than processors nothing is placed: a unit held on its processor could not make way for a
 * writer thread (placed units ran serial_joint with its log at 1590x against 2223x left free;
 * where the units are as many as the processors they write the log themselves, sim_writer). A
 * placement the system refuses is left to the scheduler; the main thread's own set is given
 * back after the run (restore_placement). */
typedef struct {
    int pinned;          /* 1: the main thread is held on cpus[first] */
#ifdef __linux__
    cpu_set_t allowed;   /* the process's processors before the run */
    int cpus[CPU_SETSIZE];
    int count, first;
#endif
} sim_placement;

static void place_main(sim_placement *p, int busy_threads)
{
    p->pinned = 0;
#ifdef __linux__
    {
        const int me = sched_getcpu();
        size_t cpu;
        cpu_set_t one;
        p->count = p->first = 0;
        if (me < 0 || sched_getaffinity(0, sizeof p->allowed, &p->allowed) != 0) return;
        for (cpu = 0; cpu < (size_t)CPU_SETSIZE; ++cpu)
            if (CPU_ISSET(cpu, &p->allowed)) {
                if ((int)cpu == me) p->first = p->count;
                p->cpus[p->count++] = (int)cpu;
            }
        if (p->count < 2 || p->count < busy_threads || p->cpus[p->first] != me) return;
        CPU_ZERO(&one);
        CPU_SET((size_t)me, &one);
        p->pinned = pthread_setaffinity_np(pthread_self(), sizeof one, &one) == 0;
    }
#else
    (void)busy_threads;
#endif
}

static void restore_placement(const sim_placement *p)
{
#ifdef __linux__
    if (p->pinned)
        (void)pthread_setaffinity_np(pthread_self(), sizeof p->allowed, &p->allowed);
#else
    (void)p;
#endif
}

/* Start lane's thread, unit u (>= 1; unit 0 runs on the main thread): on the processor
 * place_main gives it, or where the scheduler puts it if that cannot be had. */
static int start_unit(const sim_placement *p, sim_lane *lane, int u)
{
#ifdef __linux__
    if (p->pinned) {
        pthread_attr_t attr;
        cpu_set_t one;
        int failed = 1;
        if (pthread_attr_init(&attr) == 0) {
            CPU_ZERO(&one);
            CPU_SET((size_t)p->cpus[(p->first + u) % p->count], &one);
            failed = pthread_attr_setaffinity_np(&attr, sizeof one, &one) != 0 ||
                     pthread_create(&lane->thread, &attr, run_unit, lane) != 0;
            pthread_attr_destroy(&attr);
        }
        if (!failed) return 0;
    }
#else
    (void)p;
    (void)u;
#endif
    return pthread_create(&lane->thread, NULL, run_unit, lane) != 0 ? -1 : 0;
}

int main(int argc, char **argv)
{
    static sim_lane lanes[SIM_UNITS];
    sim_writer writer;
    const double start = now_s();
    const double h = SIM_PERIOD;
    double duration = SIM_DURATION, loop_start, end, loop_cpu = 0.0;
    SIM_C(_config) config;
    SIM_C(_state) state;
    const sim_lane *first;
    const char *log_path = NULL, *writer_choice;
    long steps;
    int i, u, threads = 1, by_units;
    sim_placement placement;

    for (i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "--duration") == 0 && i + 1 < argc) {
            char *rest;
            duration = strtod(argv[++i], &rest);
            if (*rest != '\0' || !(duration >= 0.0 && duration < 1e9)) return usage();
        } else if (strcmp(argv[i], "--log") == 0 && i + 1 < argc) {
            log_path = argv[++i];
        } else {
            return usage();
        }
    }
    /* as the simulation's int(round(duration / h)): halves to even (nearbyint in the default
     * rounding mode), where lround took 2.5 periods (--duration 0.0025) to 3 and Python to 2 */
    steps = (long)nearbyint(duration / h);

    SIM_C(_default_config)(&config);
    if (config.h != h || SIM_C(_init)(&state, &config) != 0) {
        fprintf(stderr, "simulate: the default configuration of %s is refused\n", SIM_NAME);
        return 2;
    }
    find_offsets();
    /* who writes the log (sim_writer): COCHLEA_SIM_LOG_WRITER=thread or units chooses (to
     * compare the two), else the units where they are as many as the processors */
    writer_choice = getenv("COCHLEA_SIM_LOG_WRITER");
    if (writer_choice && strcmp(writer_choice, "units") != 0 &&
        strcmp(writer_choice, "thread") != 0) {
        fprintf(stderr, "simulate: COCHLEA_SIM_LOG_WRITER is %s: thread or units\n",
                writer_choice);
        return 2;
    }
    by_units = writer_choice ? strcmp(writer_choice, "units") == 0
                             : SIM_UNITS >= 2 && usable_processors() <= SIM_UNITS;
    if (log_path && writer_start(&writer, log_path, steps, by_units) != 0) {
        fprintf(stderr, "simulate: cannot write %s\n", log_path);
        return 2;
    }
    for (u = 0; u < SIM_UNITS; ++u) {
        lanes[u].unit = u;
        lanes[u].steps = steps;
        lanes[u].writer = log_path ? &writer : NULL;
        lanes[u].state = state;
    }

    loop_start = now_s();
    /* the other units on threads of their own, the first on this one; one loop over all units
     * on this thread if a thread cannot be started */
    place_main(&placement, SIM_UNITS + (log_path != NULL && !by_units));
    for (u = 1; u < SIM_UNITS; ++u)
        if (start_unit(&placement, &lanes[u], u) == 0) ++threads;
        else break;
    if (threads < SIM_UNITS) {
        fprintf(stderr, "simulate: cannot start a thread per unit\n");
        if (log_path) writer_abandon(&writer);
        for (u = 1; u < threads; ++u) pthread_join(lanes[u].thread, NULL);
        if (log_path) (void)writer_finish(&writer);
        restore_placement(&placement);
        return 2;
    }
    run_unit(&lanes[0]);
    for (u = 1; u < SIM_UNITS; ++u) pthread_join(lanes[u].thread, NULL);
    end = now_s();
    restore_placement(&placement);
    SIM_C(_terminate)(&state);

    for (u = 0; u < SIM_UNITS; ++u) {
        if (log_path && (lanes[u].plant_failed || lanes[u].log_failed)) {
            writer_abandon(&writer);
            break;
        }
    }
    for (u = 0; u < SIM_UNITS; ++u) {
        if (lanes[u].plant_failed) {
            fprintf(stderr, "simulate: the plant of %s returned %d\n", sim_units[u].name,
                    lanes[u].code);
            if (log_path) (void)writer_finish(&writer);
            return 2;
        }
        if (lanes[u].log_failed) {
            (void)writer_finish(&writer);
            return cannot_write(log_path, lanes[u].log_failed);
        }
        if (lanes[u].cpu_s > loop_cpu) loop_cpu = lanes[u].cpu_s;
    }
    if (log_path) {
        const int failed = writer_finish(&writer);
        if (failed) return cannot_write(log_path, failed);
    }
    first = &lanes[0]; /* the stop the run makes: the first in one loop over the units */
    for (u = 1; u < SIM_UNITS; ++u)
        if (stop_order(&lanes[u]) < stop_order(first)) first = &lanes[u];
    printf("{\"scenario\": \"%s\", \"precision\": \"%s\", \"period_s\": %.17g, "
           "\"duration_s\": %.17g, \"periods\": %ld, \"rows\": %ld, \"status\": \"%s\", "
           "\"step_code\": %d, \"units\": %d, \"nx\": %d, \"np\": %d, \"nq\": %d, \"ne\": %d, "
           "\"npose\": %d, \"nd\": %d, \"columns\": %d, \"log\": %s, \"threads\": %d, "
           "\"loop_s\": %.9f, \"loop_cpu_s\": %.9f, \"main_s\": %.9f, \"unit_cpu_s\": [",
           SIM_NAME, SIM_PRECISION, h, duration, steps, first->rows, first->status,
           strcmp(first->status, "step-failed") == 0 ? first->code : 0, SIM_UNITS, SIM_NX,
           SIM_NP, SIM_NQ, SIM_NE, SIM_NPOSE, SIM_ND, SIM_COLUMNS, log_path ? "true" : "false",
           threads, end - loop_start, loop_cpu, now_s() - start);
    for (u = 0; u < SIM_UNITS; ++u) printf("%s%.9f", u ? ", " : "", lanes[u].cpu_s);
    printf("], \"unit_processors\": [");
    for (u = 0; u < SIM_UNITS; ++u) printf("%s%d", u ? ", " : "", lanes[u].processor);
    printf("], \"log_writer\": \"%s\", \"writer_cpu_s\": %.9f, \"unit_sizes\": [",
           !log_path ? "none" : by_units ? "units" : "thread", log_path ? writer.cpu_s : 0.0);
    for (u = 0; u < SIM_UNITS; ++u) {
        const sim_unit *s = &sim_units[u];
        printf("%s{\"name\": \"%s\", \"nq\": %d, \"np\": %d, \"nd\": %d, \"ne\": %d, "
               "\"npose\": %d}", u ? ", " : "", s->name, s->nq, s->np, s->nd, s->ne, s->npose);
    }
    printf("]}\n");
    return strcmp(first->status, "completed") == 0 ? 0 : 1;
}
