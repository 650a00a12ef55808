/* Times a scenario's generated embedded controller (<scenario>_step), in C, on recorded
 * measurements. Compiled with the scenario's source into a shared library, once per precision:
 *
 *   cc -shared -fPIC -DSCENARIO_HEADER='"serial_task.h"' -DSCENARIO=serial_task \
 *      -DSCENARIO_UPPER=SERIAL_TASK [-DCOCHLEA_FLOAT] time_embedded_step.c serial_task.c -lm
 *
 * bench/embedded_bench.py loads both precisions into one process and calls bench_time on each in
 * turn. Units: times in s, measurements in rad, m, rad/s, m/s, commands in N m, N. */
#define _POSIX_C_SOURCE 199309L
#include SCENARIO_HEADER

#include <stdlib.h>
#include <time.h>

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define FN(x) CAT(SCENARIO, x)
#define SIZE(x) CAT(SCENARIO_UPPER, x)

typedef FN(_real) real;

static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return 1e9 * (double)t.tv_sec + (double)t.tv_nsec;
}

/* out: NX, NQ, NE; returns sizeof(real) (4: the float build, 8: double). */
int bench_sizes(int *out)
{
    out[0] = SIZE(_NX);
    out[1] = SIZE(_NQ);
    out[2] = SIZE(_NE);
    return (int)sizeof(real);
}

/* From a fresh init, `rows` periods on measurements[rows][NX] at times[rows], `reps` times:
 * ns_out[r] is the time per step of repetition r (ns). commands_out[rows][NQ] gets the commands
 * of one more, untimed run first. Returns 0, -2 if out of memory, or the first nonzero step
 * code. */
int bench_time(const double *times, const double *measurements, long rows, long reps,
               double *ns_out, double *commands_out)
{
    FN(_config) config;
    FN(_state) state;
    real command[SIZE(_NQ)], errors[SIZE(_NE)];
    real *m = malloc((size_t)(rows * SIZE(_NX)) * sizeof(real));
    long k, r;
    int i, code = 0;
    if (!m) return -2;
    for (k = 0; k < rows * SIZE(_NX); ++k) m[k] = (real)measurements[k];
    FN(_default_config)(&config);
    if ((code = FN(_init)(&state, &config)) != 0) goto done;
    for (k = 0; k < rows; ++k) {
        if ((code = FN(_step)(&state, times[k], m + k * SIZE(_NX), command, errors)) != 0)
            goto done;
        for (i = 0; i < SIZE(_NQ); ++i) commands_out[k * SIZE(_NQ) + i] = (double)command[i];
    }
    for (r = 0; r < reps; ++r) {
        double start;
        if ((code = FN(_init)(&state, &config)) != 0) goto done;
        start = now_ns();
        for (k = 0; k < rows; ++k)
            if ((code = FN(_step)(&state, times[k], m + k * SIZE(_NX), command, errors)) != 0)
                goto done;
        ns_out[r] = (now_ns() - start) / (double)rows;
    }
done:
    free(m);
    return code;
}
