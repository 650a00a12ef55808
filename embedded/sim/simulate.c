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
 * --log FILE writes one row of doubles (native byte order) per period:
 *   t (s), x[NX], p_hat[NP], tau[NQ], errors[NE], pose[NPOSE], xd[ND], xd_dot[ND]
 * each block unit after unit (x: per unit [q, qd]). The loop writes its rows into a ring of
 * blocks of about 256 KB; a second thread evaluates each row's poses from its x and writes the
 * block to the file while the loop fills the next (the poses and the page cache's copy were a
 * quarter of a serial study's time). Without --log the pose, which only the log needs, is not
 * evaluated.
 *
 * Prints one line of JSON on stdout: the scenario, the sizes, the rows run, the status, the
 * wall time (s) of the loop (loop_s) and of the whole program from main() on (main_s), the
 * loop's own CPU time (loop_cpu_s: its thread's, the log's writer not included; on a busy
 * machine the measure of the loop's work) and each unit's sizes.
 * Exit status: 0 completed, 1 diverged or step-failed, 2 bad arguments or an unwritable log. */
#define _POSIX_C_SOURCE 200112L
#include "sim_scenario.h"
/* The controller in this translation unit: the loop evaluates the desired trajectory once per
 * period and hands it to the step (<scenario>_step is <scenario>_desired at t, then
 * <scenario>_step_desired on that sample), and the log writes the same sample. */
#include SIM_CONTROLLER_SOURCE

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
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

/* Each unit's [q, qd] (the first 2 nq of its plant's state: the encoders are on the links)
 * into x, unit after unit. */
static void measured_state(const double *plant_x, double *x)
{
    int u, i = 0, j = 0;
    for (u = 0; u < SIM_UNITS; ++u) {
        memcpy(x + j, plant_x + i, (size_t)(2 * sim_units[u].nq) * sizeof(double));
        i += sim_units[u].nxp;
        j += 2 * sim_units[u].nq;
    }
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

/* The log: rows in SIM_BLOCKS blocks of about 256 KB, a ring; the writer thread fills in each
 * handed block's poses and writes it while the loop fills the next ones (several, so that a
 * writer held up by other work on the machine does not stop the loop at once). */
#define SIM_BLOCKS 4
#define SIM_BLOCK_ROWS ((1 << 18) / (8 * SIM_COLUMNS) + 1)

typedef struct {
    int fd;
    pthread_t thread;
    pthread_mutex_t lock;
    pthread_cond_t changed;
    long rows[SIM_BLOCKS]; /* rows of each handed block */
    int next;              /* the block the writer writes next */
    int queued;            /* blocks handed and not yet written (the one being written too) */
    int stop;              /* no more blocks */
    int failed;            /* 1: a write failed, 2: a pose kernel did; the log is incomplete */
} sim_writer;

static double sim_blocks[SIM_BLOCKS][SIM_BLOCK_ROWS * SIM_COLUMNS];

#define SIM_POSE_COLUMN (1 + SIM_NX + SIM_NP + SIM_NQ + SIM_NE)

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

static void *writer_main(void *arg)
{
    sim_writer *w = arg;
    pthread_mutex_lock(&w->lock);
    for (;;) {
        while (!w->queued && !w->stop) pthread_cond_wait(&w->changed, &w->lock);
        if (!w->queued) break; /* stopped, every block written */
        {
            double *block = sim_blocks[w->next];
            const long rows = w->rows[w->next];
            int failed;
            pthread_mutex_unlock(&w->lock);
            failed = fill_poses(block, rows) ? 2
                     : write_all(w->fd, (const char *)block,
                                 (size_t)rows * SIM_COLUMNS * sizeof(double)) ? 1 : 0;
            pthread_mutex_lock(&w->lock);
            if (!w->failed) w->failed = failed;
            w->next = (w->next + 1) % SIM_BLOCKS;
            w->queued -= 1;
            pthread_cond_broadcast(&w->changed);
        }
    }
    pthread_mutex_unlock(&w->lock);
    return NULL;
}

/* Hand the first rows of block *block (rows > 0) to the writer and move *block on to the next
 * one, once the writer has written it; 0, or the writer's failure so far (sim_writer.failed). */
static int writer_hand(sim_writer *w, int *block, long rows)
{
    int failed;
    pthread_mutex_lock(&w->lock);
    w->rows[*block] = rows;
    w->queued += 1;
    pthread_cond_broadcast(&w->changed);
    while (w->queued == SIM_BLOCKS) pthread_cond_wait(&w->changed, &w->lock);
    failed = w->failed;
    pthread_mutex_unlock(&w->lock);
    *block = (*block + 1) % SIM_BLOCKS;
    return failed;
}

static int writer_start(sim_writer *w, const char *path)
{
    w->fd = open(path, O_WRONLY | O_CREAT | O_TRUNC, 0666);
    w->next = w->queued = w->stop = w->failed = 0;
    if (w->fd < 0) return -1;
    if (pthread_mutex_init(&w->lock, NULL) != 0) return -1;
    if (pthread_cond_init(&w->changed, NULL) != 0) return -1;
    return pthread_create(&w->thread, NULL, writer_main, w) != 0 ? -1 : 0;
}

/* The last rows of block (rows >= 0), then the writer stopped and the file closed; 0, or the
 * writer's failure (1 also when the close failed). */
static int writer_finish(sim_writer *w, int block, long rows)
{
    if (rows > 0) writer_hand(w, &block, rows);
    pthread_mutex_lock(&w->lock);
    w->stop = 1;
    pthread_cond_broadcast(&w->changed);
    pthread_mutex_unlock(&w->lock);
    pthread_join(w->thread, NULL);
    if (close(w->fd) != 0 && !w->failed) w->failed = 1;
    return w->failed;
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

int main(int argc, char **argv)
{
    static double history[SIM_RING][SIM_NX]; /* x of the last SIM_RING periods */
    sim_writer writer;
    int block = 0;     /* the block the loop fills */
    long in_block = 0; /* its rows */
    const double start = now_s();
    const double h = SIM_PERIOD;
    double duration = SIM_DURATION, x[SIM_NX], tau[SIM_NQ], torque[SIM_NQ], loop_start, end;
    double loop_cpu; /* s: the loop's thread's CPU time over the loop */
    double plant_x[SIM_NXP], plant_next[SIM_NXP]; /* the plants' states; x is their [q, qd] */
    sim_real measurement[SIM_NX], command[SIM_NQ], errors[SIM_NE];
    sim_real xd[SIM_ND], xd_dot[SIM_ND], xd_ddot[SIM_ND];
    SIM_C(_config) config;
    SIM_C(_state) state;
    const char *log_path = NULL, *status = "completed";
    int log = 0;
    long steps, k, rows = 0;
    int i, u, qi, code = 0;
#if SIM_JITTER > 0
    sim_pcg64 jitter;
#endif
#if SIM_ENCODER_COUNTS > 0
    sim_pcg64 encoder;
    double counts[SIM_NQ]; /* this period's encoder counts of noise, joint after joint */
#endif

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
    steps = lround(duration / h); /* as the simulation's int(round(duration / h)) */

    SIM_C(_default_config)(&config);
    if (config.h != h || SIM_C(_init)(&state, &config) != 0) {
        fprintf(stderr, "simulate: the default configuration of %s is refused\n", SIM_NAME);
        return 2;
    }
    if (log_path) {
        log = 1;
        if (writer_start(&writer, log_path) != 0) {
            fprintf(stderr, "simulate: cannot write %s\n", log_path);
            return 2;
        }
    }
    for (u = 0, i = 0; u < SIM_UNITS; i += sim_units[u].nxp, ++u)
        memcpy(plant_x + i, sim_units[u].x0, (size_t)sim_units[u].nxp * sizeof(double));
    measured_state(plant_x, x);

#if SIM_JITTER > 0
    sim_pcg64_start(&jitter, sim_jitter_seed);
#endif
#if SIM_ENCODER_COUNTS > 0
    sim_pcg64_start(&encoder, sim_encoder_seed);
#endif
    loop_cpu = clock_s(CLOCK_THREAD_CPUTIME_ID);
    loop_start = now_s();
    for (k = 0; k < steps; ++k) {
        const double t = (double)k * h; /* as the simulation's time grid, arange(N) * h */
        long age = SIM_DELAY; /* periods: how old this period's measurement is */
        const double *seen;
        double *slot = history[k % SIM_RING];
        const sim_real *p_hat = state.p_hat; /* the estimate used in this period */
        double *r = sim_blocks[block] + in_block * SIM_COLUMNS;

#if SIM_JITTER > 0
        age += (long)sim_integer(&jitter, 0, SIM_JITTER);
#endif
        seen = history[k >= age ? (k - age) % SIM_RING : 0];
#if SIM_ENCODER_COUNTS > 0
        for (i = 0; i < SIM_NQ; ++i)
            counts[i] = sim_integer(&encoder, -SIM_ENCODER_COUNTS, SIM_ENCODER_COUNTS);
#endif

        for (i = 0; i < SIM_NX; ++i) slot[i] = x[i];
        if (log) {
            *r++ = t;
            for (i = 0; i < SIM_NX; ++i) *r++ = x[i];
            for (i = 0; i < SIM_NP; ++i) *r++ = p_hat[i];
        }

        /* The measurement, its encoder counts of noise, on each unit's grid */
        for (u = 0, i = 0, qi = 0; u < SIM_UNITS; qi += sim_units[u].nq, ++u) {
            const sim_unit *s = &sim_units[u];
            int j;
            for (j = 0; j < 2 * s->nq; ++j, ++i) {
                double m = seen[i];
#if SIM_ENCODER_COUNTS > 0
                if (j < s->nq) m += counts[qi + j] * s->quantum[j];
#endif
                if (s->quantum && s->quantum[j] > 0) {
                    const double q = s->quantum[j], o = s->offset[j];
                    m = o + q * nearbyint((m - o) / q);
                }
                measurement[i] = (sim_real)m;
            }
        }

        /* <scenario>_step(&state, t, ...), its desired sample kept for the log */
        code = SIM_C(_desired)(t, xd, xd_dot, xd_ddot) != 0 ? -1
               : SIM_C(_step_desired)(&state, xd, xd_dot, xd_ddot, measurement, command, errors);
        if (code != 0) {
            status = "step-failed";
            break;
        }

        /* The drives: each command on its joint's effort grid */
        for (u = 0, i = 0; u < SIM_UNITS; ++u) {
            const sim_unit *s = &sim_units[u];
            int j;
            for (j = 0; j < s->nq; ++j, ++i) {
                double e = (double)command[i];
                if (s->effort_offset)
                    e += s->effort_offset[j] * fmin(fmax(e / s->effort_ramp[j], -1.0), 1.0);
                if (s->effort_quantum) {
                    if (s->effort_quantum[j] > 0)
                        e = s->effort_quantum[j] * nearbyint(e / s->effort_quantum[j]);
                    e = fmin(fmax(e, -s->effort_bound[j]), s->effort_bound[j]);
                }
                tau[i] = e;
                torque[i] = s->torque_scale ? s->torque_scale[j] * e : e;
            }
        }

        /* The plants, unit after unit */
        for (u = 0, i = 0, qi = 0; u < SIM_UNITS; ++u) {
            const sim_unit *s = &sim_units[u];
            const double *arg[6]; /* a plant without a 6th input reads the first 5 */
            double *res[1];
            arg[0] = plant_x + i;
            arg[1] = torque + qi;
            arg[2] = s->plant_p;
            arg[3] = s->friction;
            arg[4] = &h;
            arg[5] = s->coulomb;
            res[0] = plant_next + i;
            code = s->plant(arg, res, NULL, NULL, 0);
            if (code != 0) {
                fprintf(stderr, "simulate: the plant of %s returned %d\n", s->name, code);
                return 2;
            }
            i += s->nxp;
            qi += s->nq;
        }

        if (log) {
            for (i = 0; i < SIM_NQ; ++i) *r++ = tau[i];
            for (i = 0; i < SIM_NE; ++i) *r++ = (double)errors[i];
            r += SIM_NPOSE; /* the writer thread evaluates the poses from the row's x */
            for (i = 0; i < SIM_ND; ++i) *r++ = (double)xd[i];
            for (i = 0; i < SIM_ND; ++i) *r++ = (double)xd_dot[i];
            if (++in_block == SIM_BLOCK_ROWS) {
                const int failed = writer_hand(&writer, &block, in_block);
                if (failed) return cannot_write(log_path, failed);
                in_block = 0;
            }
        }
        rows = k + 1;
        memcpy(plant_x, plant_next, sizeof plant_x);
        measured_state(plant_x, x);
        if (!all_finite(plant_x, SIM_NXP) || !all_finite_real(state.p_hat, SIM_NP)) {
            status = "diverged";
            break;
        }
    }
    end = now_s();
    loop_cpu = clock_s(CLOCK_THREAD_CPUTIME_ID) - loop_cpu;
    SIM_C(_terminate)(&state);
    if (log) {
        const int failed = writer_finish(&writer, block, in_block);
        if (failed) return cannot_write(log_path, failed);
    }
    printf("{\"scenario\": \"%s\", \"precision\": \"%s\", \"period_s\": %.17g, "
           "\"duration_s\": %.17g, \"periods\": %ld, \"rows\": %ld, \"status\": \"%s\", "
           "\"step_code\": %d, \"units\": %d, \"nx\": %d, \"np\": %d, \"nq\": %d, \"ne\": %d, "
           "\"npose\": %d, \"nd\": %d, \"columns\": %d, \"log\": %s, \"loop_s\": %.9f, "
           "\"loop_cpu_s\": %.9f, \"main_s\": %.9f, \"unit_sizes\": [",
           SIM_NAME, SIM_PRECISION, h, duration, steps, rows, status, code, SIM_UNITS, SIM_NX,
           SIM_NP, SIM_NQ, SIM_NE, SIM_NPOSE, SIM_ND, SIM_COLUMNS, log ? "true" : "false",
           end - loop_start, loop_cpu, now_s() - start);
    for (u = 0; u < SIM_UNITS; ++u) {
        const sim_unit *s = &sim_units[u];
        printf("%s{\"name\": \"%s\", \"nq\": %d, \"np\": %d, \"nd\": %d, \"ne\": %d, "
               "\"npose\": %d}", u ? ", " : "", s->name, s->nq, s->np, s->nd, s->ne, s->npose);
    }
    printf("]}\n");
    return strcmp(status, "completed") == 0 ? 0 : 1;
}
