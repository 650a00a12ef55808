/* cochlea-embedded: a scenario's controller on the Dynamixel motors, with no Python.
 *
 *   build/cochlea-embedded --scenario NAME --port PATH [--baud B] [--duration S] --out DIR
 *                          [--watchdog-misses N] [--watchdog-errors N] [--mlockall on|off]
 *                          [--cpu N] [--sched fifo|rr|other] [--priority N]
 *                          [--homing auto|required] [--homing-record FILE] [--list]
 *                          [--start-tolerance-deg DEG] [--start-tolerance-mm MM]
 *
 * The POSIX program around the portable core (embedded/core/): it opens the port (termios, any
 * Dynamixel baud rate up to 4.5 Mbaud), starts the motors as cochlea-run's bridge does, runs
 * the loop at absolute deadlines (clock_nanosleep) with cochlea-run's overrun rule, under
 * SCHED_FIFO 40 with its memory locked (or the --sched/--priority/--cpu/--mlockall asked for)
 * when the system permits, and streams every period's row to DIR/log.bin from a writer thread,
 * outside the period. After the run, whatever ended it: log.csv, log.columns.json and
 * summary.json, the same files and schema as cochlea-run's (figures aside), and the same exit
 * codes: 0 completed or user stop (SIGINT), 2 a wrong option, 5 the motors could not be
 * started (nothing moved), 10..17 the supervisor's rules (16: SIGTERM, or SIGHUP: a hang-up of
 * the terminal or session is SIGTERM's safe stop), and before the start (nothing moved) the
 * shell's code of the signal: 130 SIGINT, 143 SIGTERM, 129 SIGHUP. SIGPIPE is ignored: a
 * closed standard output (a pipe, a terminal that hung up) fails its writes, never the run.
 * Every scenario cochlea-codegen generated is linked in; --list prints them.
 * Units: SI inside and in every file (rad, m, rad/s, m/s, N m, N, s); degrees only in messages.
 */
#define _GNU_SOURCE /* pthread_setschedparam, mlockall, clock_gettime on glibc */

#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <dirent.h>
#include <fcntl.h>
#include <time.h>
#include <unistd.h>
#include <ctype.h>
#include <limits.h>
#include <pwd.h>

#include "bridge.h"
#include "cochlea_rt.h"
#include "hal_posix.h"
#include "loop.h"
#include "scenarios.h"

#ifdef COCHLEA_FLOAT
#define PRECISION "float"
#else
#define PRECISION "double"
#endif

#define EXIT_USER_ERROR 2
/* Before the start (nothing moved): the shell's code of the signal, as cochlea-run's. */
#define EXIT_INTERRUPTED 130 /* SIGINT */
#define EXIT_TERMINATED 143  /* SIGTERM */
#define EXIT_HUNG_UP 129     /* SIGHUP */
/* The disk's estimate (cochlea/apps/outputs.py's): bytes a log.csv value takes at most
 * ("%.10g" and its comma), and room for log.columns.json and summary.json. */
#define CSV_VALUE_BYTES 17
#define REPORT_MARGIN_BYTES (1L << 20)
#define MAX_WATCHDOG_MISSES 1000
#define FIFO_PRIORITY 40
/* The bus budget (cochlea/dynamixel/budget.py): 10 bit times a byte, a motor's turnaround,
 * the FTDI adapter's best latency timer, and the read timeout's margin over that. */
#define BITS_PER_BYTE 10.0
#define TURNAROUND_S 20e-6
#define ADAPTER_LATENCY_S 1e-3
#define TIMEOUT_MARGIN_S 3e-3
#define WATCHDOG_S 0.1
/* Convergence: cochlea/apps/report.py's rule, word for word, with its encoder-count floor
 * (measurement_resolution: one count of the drives on every joint). */
#define CONVERGENCE_RATIO 0.05
#define TAIL_FRACTION 0.2
#define CONVERGENCE_RULE                                                                      \
    "final RMS over the last 20% <= 5% of the initial absolute error, or below 1e-05 rad, "   \
    "1e-06 m (with encoder counts, of the plant or of a hardware run's drives: below the "     \
    "coordinate's measurement_resolution, one count on every joint; each coordinate's "        \
    "convergence_floor), on the tracking error judged_error names; converged overall only if " \
    "every coordinate converged, nothing diverged and no supervisor rule stopped the run (real " \
    "time) or would have (as fast as possible: supervisor)"
/* On the motors the program knows only what it measures: judged_error and logged_state say so,
 * and each coordinate's measured_* numbers are its judged ones, as cochlea-run writes them. */
#define LOGGED_STATE                                                                          \
    "measured only: a hardware run knows the robot only through its encoders and velocity "    \
    "registers (q, qd, pose, error)"

/* ---- options ------------------------------------------------------------------------------ */

typedef struct {
    const char *scenario, *port, *out;
    long baud;
    double duration; /* NaN: the scenario's */
    double rate;     /* Hz; NaN: the scenario's */
    int watchdog_misses;
    int watchdog_errors;
    /* The loop thread's real-time settings, cochlea-run's options (RealtimeOptions). */
    int mlockall;         /* 1: lock memory while the loop runs (this program's default) */
    int cpu;              /* pin the loop's thread to this CPU; -1: the CPUs given */
    const char *sched;    /* "fifo", "rr" or "other" */
    int priority_given;   /* --priority given */
    int priority;         /* fifo and rr: 1..99 (default FIFO_PRIORITY); other: none */
    const char *homing;   /* "auto" or "required" (cochlea-run's --homing) */
    const char *homing_record; /* the record cochlea-dxl home wrote; 0: the default */
    double start_tolerance_deg, start_tolerance_mm; /* cochlea-run's: 5 deg, 5 mm */
} options;

static int fail_usage(const char *fmt, ...)
{
    va_list args;
    fputs("cochlea-embedded: ", stderr);
    va_start(args, fmt);
    vfprintf(stderr, fmt, args);
    va_end(args);
    fputs("\n", stderr);
    return EXIT_USER_ERROR;
}

static void usage(FILE *to)
{
    fprintf(to,
            "usage: cochlea-embedded --scenario NAME --port PATH [--baud B] [--duration S]\n"
            "                        [--rate HZ] --out DIR [--watchdog-misses N]\n"
            "                        [--watchdog-errors N] [--mlockall on|off] [--cpu N]\n"
            "                        [--sched fifo|rr|other] [--priority N]\n"
            "                        [--homing auto|required] [--homing-record FILE]\n"
            "                        [--start-tolerance-deg DEG] [--start-tolerance-mm MM] | --list\n"
            "Runs a generated scenario's controller on the Dynamixel motors of PATH (real ones,\n"
            "or the pseudo-terminal cochlea-emulator prints) in real time, " PRECISION
            " precision.\n"
            "  --baud B             the motors' baud rate (default 4000000)\n"
            "  --duration S         seconds to run (default: the scenario's; at most a day, and\n"
            "                       as long as the disk holds log.bin and log.csv: checked\n"
            "                       before the start; memory does not grow with it)\n"
            "  --rate HZ            the control rate (default: the scenario's)\n"
            "  --out DIR            a new or empty folder for log.bin, log.csv, summary.json\n"
            "  --watchdog-misses N  consecutive overrunning periods tolerated; one period stuck\n"
            "                       for longer than N periods stops at once (default 20)\n"
            "  --watchdog-errors N  consecutive failed reads tolerated (default 5)\n"
            "  --start-tolerance-deg DEG, --start-tolerance-mm MM\n"
            "                       how far a revolute (prismatic) joint may stand from the\n"
            "                       scenario's initial pose at the start (default 5 deg, 5 mm);\n"
            "                       farther is refused before the torque comes on (exit 5)\n"
            "  --mlockall on|off    lock the memory while the loop runs, so no page fault stalls\n"
            "                       a period (default on; needs CAP_IPC_LOCK or a memlock limit)\n"
            "  --cpu N              pin the loop's thread to CPU N (default: the CPUs given)\n"
            "  --sched P            the loop's scheduling policy: fifo (default), rr or other\n"
            "  --priority N         --sched fifo or rr: the real-time priority, 1..99 (default\n"
            "                       40: above normal processes, below the kernel's threads)\n"
            "  A real-time setting the system refuses is one warning and the run goes on with\n"
            "  what it got; summary.json's realtime entry records both.\n"
            "  --homing auto|required  a prismatic joint (the parallel robot's slider): check\n"
            "                       its homing record (cochlea-dxl home) on a real port and not\n"
            "                       on the emulator's pseudo-terminal (auto, default), or always\n"
            "  --homing-record FILE the record cochlea-dxl home wrote (default\n"
            "                       ~/.cochlea/homing/ROBOT.json, the shipped description's;\n"
            "                       a user's description: the path cochlea-dxl home printed)\n"
            "  --list               the scenarios linked into this program\n"
            "Exit codes: 0 completed or stopped by the user, 2 wrong option, 5 motors not "
            "started,\n10 position-limit, 11 velocity-limit, 12 keep-out, 13 non-finite, "
            "14 estimate-bound,\n15 watchdog, 16 terminated (SIGTERM, or SIGHUP: a hang-up), "
            "17 log-failure (the log\ncould not be written); before the start, nothing moved: "
            "130 SIGINT, 143 SIGTERM,\n129 SIGHUP.\n");
}

static int parse_number(const char *text, double *value)
{
    char *end;
    errno = 0;
    *value = strtod(text, &end);
    return errno == 0 && end != text && *end == '\0' && isfinite(*value);
}

static const cochlea_scenario *find_scenario(const char *name)
{
    int i;
    for (i = 0; cochlea_scenarios[i]; ++i) {
        if (strcmp(cochlea_scenarios[i]->name, name) == 0) {
            return cochlea_scenarios[i];
        }
    }
    return 0;
}

/* ---- real-time settings (cochlea/runtime/loop.py's RealtimeOptions and apply_realtime) ---- */

/* The policy named by --sched ("fifo", "rr", "other"), or 0 for another name. */
static const char *policy_of(const char *name)
{
    if (strcmp(name, "fifo") == 0) {
        return "SCHED_FIFO";
    }
    if (strcmp(name, "rr") == 0) {
        return "SCHED_RR";
    }
    return strcmp(name, "other") == 0 ? "SCHED_OTHER" : 0;
}

static int policy_value(const char *name)
{
    return strcmp(name, "fifo") == 0 ? SCHED_FIFO
           : strcmp(name, "rr") == 0 ? SCHED_RR : SCHED_OTHER;
}

/* The priority asked for: SCHED_OTHER's is 0. */
static int priority_level(const options *o)
{
    if (strcmp(o->sched, "other") == 0) {
        return 0;
    }
    return o->priority;
}

/* The CPUs this process may use, "0, 1, 3", into buf. */
static const char *cpu_list(char *buf, size_t n)
{
    cpu_set_t set;
    size_t used = 0;
    int c;
    buf[0] = '\0';
    if (sched_getaffinity(0, sizeof set, &set) != 0) {
        snprintf(buf, n, "unknown");
        return buf;
    }
    for (c = 0; c < CPU_SETSIZE && used < n; ++c) {
        if (CPU_ISSET(c, &set)) {
            used += (size_t)snprintf(buf + used, n - used, "%s%d", used ? ", " : "", c);
        }
    }
    return buf;
}

/* The user's mistakes in the real-time options, refused before anything moves. */
static int check_realtime_options(const options *o)
{
    if (strcmp(o->sched, "other") == 0) {
        if (o->priority_given) {
            return fail_usage("--priority goes with --sched fifo or rr (SCHED_OTHER has no "
                              "real-time priority)");
        }
    } else {
        /* Linux's range where the OS cannot say, as cochlea-run */
        int lo = sched_get_priority_min(policy_value(o->sched));
        int hi = sched_get_priority_max(policy_value(o->sched));
        lo = lo < 0 ? 1 : lo;
        hi = hi < 0 ? 99 : hi;
        if (priority_level(o) < lo || priority_level(o) > hi) {
            return fail_usage("--priority must be between %d and %d for --sched %s, got %d", lo,
                              hi, o->sched, priority_level(o));
        }
    }
    if (o->cpu >= 0) {
        cpu_set_t set;
        if (sched_getaffinity(0, sizeof set, &set) == 0
            && (o->cpu >= CPU_SETSIZE || !CPU_ISSET(o->cpu, &set))) {
            char list[512];
            return fail_usage("--cpu %d is not a CPU this process may use: expected one of %s",
                              o->cpu, cpu_list(list, sizeof list));
        }
    }
    return 0;
}

static int parse(int argc, char **argv, options *o)
{
    int i;
    double v;
    o->scenario = o->port = o->out = 0;
    o->baud = 4000000;
    o->duration = NAN;
    o->rate = NAN;
    o->watchdog_misses = 20;
    o->watchdog_errors = 5;
    o->mlockall = 1;
    o->cpu = -1;
    o->sched = "fifo";
    o->priority_given = 0;
    o->priority = FIFO_PRIORITY;
    o->homing = "auto";
    o->start_tolerance_deg = 5.0;
    o->start_tolerance_mm = 5.0;
    o->homing_record = 0;
    for (i = 1; i < argc; ++i) {
        const char *a = argv[i];
        const char *value = i + 1 < argc ? argv[i + 1] : 0;
        if (strcmp(a, "--help") == 0 || strcmp(a, "-h") == 0) {
            usage(stdout);
            exit(0);
        }
        if (strcmp(a, "--list") == 0) {
            int k;
            for (k = 0; cochlea_scenarios[k]; ++k) {
                printf("%s (%s robot, %s space, controller %s)\n", cochlea_scenarios[k]->name,
                       cochlea_scenarios[k]->robot, cochlea_scenarios[k]->space,
                       cochlea_scenarios[k]->controller);
            }
            exit(0);
        }
        if (!value) {
            usage(stderr);
            return fail_usage("%s needs a value", a);
        }
        ++i;
        if (strcmp(a, "--scenario") == 0) {
            o->scenario = value;
        } else if (strcmp(a, "--port") == 0) {
            o->port = value;
        } else if (strcmp(a, "--out") == 0) {
            o->out = value;
        } else if (strcmp(a, "--baud") == 0) {
            /* Only the rates the motors have (Baud Rate, address 8): at any other the port
             * would find no motor, and 0 is the termios "hang up" rate. */
            static const long rates[] = {9600, 57600, 115200, 1000000, 2000000, 3000000,
                                         4000000, 4500000};
            size_t k, found = 0;
            for (k = 0; k < sizeof rates / sizeof rates[0]; ++k) {
                found |= parse_number(value, &v) && v == (double)rates[k];
            }
            if (!found) {
                return fail_usage("--baud must be a whole number of baud the motors have: "
                                  "9600, 57600, 115200, 1000000, 2000000, 3000000, 4000000 or "
                                  "4500000, got %s", value);
            }
            o->baud = (long)v;
        } else if (strcmp(a, "--duration") == 0) {
            /* At most a day, for sanity rather than memory (the log goes to disk through a
             * fixed ring): a lab session is hours, a day at 1 kHz is tens of GB of log (the
             * free-space check weighs the actual need), and inf or 1e300 s would overflow the
             * period count. */
            if (!parse_number(value, &v) || !(v > 0 && v <= 86400.0)) {
                return fail_usage("--duration must be positive and at most 86400 s, got %s",
                                  value);
            }
            o->duration = v;
        } else if (strcmp(a, "--rate") == 0) {
            if (!parse_number(value, &v) || !(v >= 1.0 && v <= 20000.0)) {
                return fail_usage("--rate must be between 1 and 20000 Hz, got %s", value);
            }
            o->rate = v;
        } else if (strcmp(a, "--watchdog-misses") == 0) {
            if (!parse_number(value, &v) || v != floor(v) || v < 1 || v > MAX_WATCHDOG_MISSES) {
                return fail_usage("--watchdog-misses must be between 1 and %d periods, got %s",
                                  MAX_WATCHDOG_MISSES, value);
            }
            o->watchdog_misses = (int)v;
        } else if (strcmp(a, "--watchdog-errors") == 0) {
            if (!parse_number(value, &v) || v != floor(v) || v < 1 || v > MAX_WATCHDOG_MISSES) {
                return fail_usage("--watchdog-errors must be between 1 and %d reads, got %s",
                                  MAX_WATCHDOG_MISSES, value);
            }
            o->watchdog_errors = (int)v;
        } else if (strcmp(a, "--start-tolerance-deg") == 0
                   || strcmp(a, "--start-tolerance-mm") == 0) {
            /* NaN, inf, zero and negative refused, as cochlea-run refuses them. */
            if (!parse_number(value, &v) || !(v > 0 && v < 1e300)) {
                return fail_usage("%s must be a positive number, got %s", a, value);
            }
            *(strcmp(a, "--start-tolerance-deg") == 0 ? &o->start_tolerance_deg
                                                       : &o->start_tolerance_mm) = v;
        } else if (strcmp(a, "--homing") == 0) {
            if (strcmp(value, "auto") != 0 && strcmp(value, "required") != 0) {
                return fail_usage("--homing: expected auto or required, got %s", value);
            }
            o->homing = value;
        } else if (strcmp(a, "--homing-record") == 0) {
            o->homing_record = value;
        } else if (strcmp(a, "--mlockall") == 0) {
            if (strcmp(value, "on") != 0 && strcmp(value, "off") != 0) {
                return fail_usage("--mlockall: expected on or off, got %s", value);
            }
            o->mlockall = strcmp(value, "on") == 0;
        } else if (strcmp(a, "--cpu") == 0) {
            if (!parse_number(value, &v) || v != floor(v) || v < -1e6 || v > 1e6) {
                return fail_usage("--cpu must be a whole number, got %s", value);
            }
            o->cpu = (int)v;
            if (o->cpu < 0) { /* -1 is "none" inside: a negative CPU is never one to use */
                char list[512];
                return fail_usage("--cpu %s is not a CPU this process may use: expected one of %s",
                                  value, cpu_list(list, sizeof list));
            }
        } else if (strcmp(a, "--sched") == 0) {
            if (!policy_of(value)) {
                return fail_usage("--sched: expected one of fifo, rr, other, got '%s'", value);
            }
            o->sched = value;
        } else if (strcmp(a, "--priority") == 0) {
            if (!parse_number(value, &v) || v != floor(v) || v < -1e6 || v > 1e6) {
                return fail_usage("--priority must be a whole number, got %s", value);
            }
            o->priority = (int)v;
            o->priority_given = 1;
        } else {
            usage(stderr);
            return fail_usage("unknown option %s", a);
        }
    }
    if (!o->scenario || !o->port || !o->out) {
        usage(stderr);
        return fail_usage("--scenario, --port and --out are needed");
    }
    return check_realtime_options(o);
}

/* ---- the output folder --------------------------------------------------------------------- */

/* Where the outermost folder this run created ends in --out's text (0: none, --out existed):
 * a start that fails removes what it made, so the identical retry is not refused for a
 * folder that is "not empty". */
static size_t out_created_from;

static int make_folders(const char *path)
{
    char buf[4096];
    size_t i, n = strlen(path);
    if (n == 0 || n >= sizeof buf) {
        errno = ENAMETOOLONG;
        return -1;
    }
    memcpy(buf, path, n + 1);
    for (i = 1; i <= n; ++i) {
        if (buf[i] == '/' || buf[i] == '\0') {
            const char keep = buf[i];
            buf[i] = '\0';
            if (mkdir(buf, 0777) == 0) {
                if (!out_created_from) {
                    out_created_from = i;
                }
            } else if (errno != EEXIST) {
                return -1;
            }
            buf[i] = keep;
        }
    }
    return 0;
}

static int folder_is_empty(const char *path)
{
    DIR *d = opendir(path);
    struct dirent *e;
    int empty = 1;
    if (!d) {
        return errno == ENOENT;
    }
    while ((e = readdir(d)) != 0) {
        if (strcmp(e->d_name, ".") != 0 && strcmp(e->d_name, "..") != 0) {
            empty = 0;
            break;
        }
    }
    closedir(d);
    return empty;
}

/* Bytes an unprivileged user may still write on the file system that holds, or would hold,
 * path (its nearest existing ancestor); -1 when that cannot be known. */
static double free_bytes(const char *path)
{
    char buf[4096];
    struct statvfs fs;
    size_t n = strlen(path);
    if (n >= sizeof buf) {
        return -1.0;
    }
    memcpy(buf, path, n + 1);
    for (;;) {
        if (statvfs(n ? buf : ".", &fs) == 0) { /* "." : a relative path's base */
            return (double)fs.f_bavail * (double)fs.f_frsize;
        }
        if ((errno != ENOENT && errno != ENOTDIR) || n == 0) {
            return -1.0;
        }
        const size_t before = n;
        while (n > 1 && buf[n - 1] == '/') { /* "a/b/" -> "a/b" */
            buf[--n] = '\0';
        }
        while (n > 0 && buf[n - 1] != '/') { /* "a/b" -> "a/", "/a" -> "/" */
            buf[--n] = '\0';
        }
        if (n == before) {
            return -1.0;
        }
    }
}

static void size_text(char *buf, size_t n, double bytes)
{
    static const char *const units[] = {"bytes", "KiB", "MiB", "GiB", "TiB"};
    int u = 0;
    while (bytes >= 1024.0 && u < 4) {
        bytes /= 1024.0;
        ++u;
    }
    snprintf(buf, n, u ? "%.1f %s" : "%.0f %s", bytes, units[u]);
}

static FILE *open_in(const char *folder, const char *name, const char *mode)
{
    char path[4352];
    snprintf(path, sizeof path, "%s/%s", folder, name);
    return fopen(path, mode);
}

/* Close a report file written under its temporary name ".NAME.tmp" and, if every byte
 * reached the disk, rename it to NAME: a reader (or a crash) sees the whole file or none. */
static int finish_atomic(FILE *f, const char *out, const char *name)
{
    char tmp[4352], final[4352];
    int failed = ferror(f) != 0 || fflush(f) != 0 || fsync(fileno(f)) != 0;
    int error = failed ? errno : 0;
    if (fclose(f) != 0 && !failed) {
        failed = 1;
        error = errno;
    }
    snprintf(tmp, sizeof tmp, "%s/.%s.tmp", out, name);
    snprintf(final, sizeof final, "%s/%s", out, name);
    if (!failed && rename(tmp, final) != 0) {
        failed = 1;
        error = errno;
    }
    if (failed) {
        unlink(tmp);
        errno = error ? error : EIO;
        return -1;
    }
    return 0;
}

/* Undo a start that failed before the first period: the two files it wrote (the folder was
 * new or empty, so they are this run's) and the folders it created, innermost first. */
static void undo_start(const char *out)
{
    char path[4352];
    size_t i, n = strlen(out);
    snprintf(path, sizeof path, "%s/log.bin", out);
    unlink(path);
    snprintf(path, sizeof path, "%s/log.columns.json", out);
    unlink(path);
    if (!out_created_from || n >= sizeof path) {
        return;
    }
    memcpy(path, out, n + 1);
    for (i = n; i >= out_created_from; --i) {
        if (path[i] == '/' || path[i] == '\0') {
            const char keep = path[i];
            path[i] = '\0';
            rmdir(path); /* only if empty: never what others put there */
            path[i] = keep;
        }
    }
}

/* ---- names of things, as cochlea-run spells them -------------------------------------------- */

static const char *model_name(int model_number)
{
    switch (model_number) {
    case 311: return "MX-64";
    case 1120: return "XM540-W270";
    default: return "unknown model";
    }
}

static void who(char *buf, size_t n, const cochlea_drive *d)
{
    snprintf(buf, n, "ID %d (%s, %s)", d->id, d->name, model_name(d->model_number));
}

/* The joint j of the scenario as "unit.joint", and its unit (rad or m). */
static const char *joint_of(const cochlea_scenario *sc, int j, char *buf, size_t n)
{
    int u;
    for (u = 0; u < sc->n_units; ++u) {
        const cochlea_unit_info *unit = &sc->units[u];
        if (j >= unit->q0 && j < unit->q0 + unit->nq) {
            snprintf(buf, n, "%s.%s", unit->name, unit->joint_names[j - unit->q0]);
            return unit->joint_units[j - unit->q0];
        }
    }
    snprintf(buf, n, "joint %d", j);
    return "rad";
}

static void show(char *buf, size_t n, double value, const char *unit)
{
    if (strcmp(unit, "rad") == 0) {
        snprintf(buf, n, "%.2f deg", value * 180.0 / M_PI);
    } else {
        snprintf(buf, n, "%.4f m", value);
    }
}

static void vector_text(char *buf, size_t n, const cochlea_real *v, int count)
{
    size_t used = 0;
    int i;
    used += (size_t)snprintf(buf, n, "[");
    for (i = 0; i < count && used < n; ++i) {
        used += (size_t)snprintf(buf + used, n - used, "%s%.4g", i ? ", " : "", (double)v[i]);
    }
    if (used < n) {
        snprintf(buf + used, n - used, "]");
    }
}

/* The stop's time (s): the float build's period forms it in float; here, after the run, it
 * is the exact k h of the stop's period, as the double build's. */
static double stop_time_s(const cochlea_loop *loop)
{
#ifdef COCHLEA_FLOAT
    if (loop->stop.period >= 0) {
        return cochlea_loop_time(loop, loop->stop.period);
    }
#endif
    return (double)loop->stop.time_s;
}

/* The first stop signal received (0: none); set by on_signal. */
static volatile sig_atomic_t interrupted;

/* The supervisor's message for a stop, as cochlea/runtime/supervisor.py words it. */
static void stop_detail(char *buf, size_t n, const cochlea_loop *loop, const cochlea_real *row)
{
    const cochlea_stop *s = &loop->stop;
    const cochlea_scenario *sc = loop->scenario;
    char name[128], a[64], b[64], c[64], vec[1024];
    const char *unit;
    buf[0] = '\0';
    switch (s->rule) {
    case COCHLEA_USER_STOP:
    case COCHLEA_TERMINATED: /* supervisor.py's SIGNAL_STOPS */
        snprintf(buf, n, "%s", interrupted == SIGINT ? "SIGINT received (Ctrl-C)"
                 : interrupted == SIGTERM ? "SIGTERM received"
                 : interrupted == SIGHUP ? "SIGHUP received: the terminal or session hung up"
                 : "signal received");
        break;
    case COCHLEA_POSITION_LIMIT:
        unit = joint_of(sc, s->joint, name, sizeof name);
        show(a, sizeof a, s->value, unit);
        show(b, sizeof b, sc->position_lo[s->joint], unit);
        show(c, sizeof c, sc->position_hi[s->joint], unit);
        snprintf(buf, n, "%s = %s outside [%s, %s]", name, a, b, c);
        break;
    case COCHLEA_VELOCITY_LIMIT:
        unit = strcmp(joint_of(sc, s->joint, name, sizeof name), "rad") == 0 ? "rad/s" : "m/s";
        snprintf(buf, n, "%s speed = %.4g %s, limit %.4g %s", name, s->value, unit, s->limit,
                 unit);
        break;
    case COCHLEA_KEEP_OUT: {
        int u, first = 0;
        const char *label = "?", *owner = "?";
        for (u = 0; u < sc->n_units; ++u) {
            if (s->unit < first + sc->units[u].n_points) {
                owner = sc->units[u].name;
                label = sc->units[u].point_labels[s->unit - first];
                break;
            }
            first += sc->units[u].n_points;
        }
        snprintf(buf, n,
                 "%s %s at (%.4f, %.4f) m is %.1f mm from the centre (%.4f, %.4f) m, inside "
                 "the keep-out radius %.1f mm",
                 owner, label, s->point[0], s->point[1], s->value * 1000.0, s->centre[0],
                 s->centre[1], s->limit * 1000.0);
        break;
    }
    case COCHLEA_NON_FINITE:
        if (s->what == 0) {
            vector_text(vec, sizeof vec, row + 1, 2 * sc->nq);
            snprintf(buf, n, "state = %s", vec);
        } else if (s->what == 1) {
            vector_text(vec, sizeof vec, loop->tau, sc->nq);
            snprintf(buf, n, "command = %s", vec);
        } else {
            snprintf(buf, n, "%s estimate is not finite",
                     s->unit >= 0 ? sc->units[s->unit].name : "the next");
        }
        break;
    case COCHLEA_ESTIMATE_BOUND:
        snprintf(buf, n, "%s |p_hat| = %.4g, bound %.4g", sc->units[s->unit].name, s->value,
                 s->limit);
        break;
    case COCHLEA_WATCHDOG:
        /* cochlea/runtime/supervisor.py's OverrunWatch words, to the digit */
        if (s->reason == COCHLEA_WATCHDOG_READS) {
            snprintf(buf, n, "%d consecutive backend read failures", s->count);
        } else if (s->reason == COCHLEA_WATCHDOG_LATE) {
            snprintf(buf, n, "the loop fell %.1f ms behind its deadlines (at most %g ms: "
                     "max(%d periods, %g ms)); it did not catch up", s->value * 1e3,
                     s->limit * 1e3, loop->limits.watchdog_misses, COCHLEA_MAX_LATENESS_S * 1e3);
        } else if (s->reason == COCHLEA_WATCHDOG_STALL) {
            snprintf(buf, n, "the loop stalled: one period took %.1f ms, more than %d periods "
                     "of %g ms", s->value * 1e3, loop->limits.watchdog_misses,
                     loop->period_s * 1e3);
        } else {
            snprintf(buf, n, "%d consecutive deadline misses: each period's own work overran "
                     "its %g ms (the last took %.3f ms)", s->count, loop->period_s * 1e3,
                     s->value * 1e3);
        }
        break;
    default:
        break;
    }
}

/* ---- the slider's homing record (cochlea/dynamixel/homing.py) -------------------------------- */

/* What cochlea-dxl home writes: one entry per prismatic joint in "joints"; the flat one-joint
 * records of before issue 25 are still read. This program homes one joint (its bridge checks
 * one marker): a record of one entry, whose keys then occur once each. */
#define HOMING_FORMAT "cochlea-homing/2"
#define HOMING_FORMAT_1 "cochlea-homing/1"

/* What the homing check found before the start: summary.json's timing.bus.homing. */
static struct {
    char report[4608];       /* "no slider", "not checked (...)", "homed DATE (PATH)" */
    char date[64];
    const char *robot;
    int drive;               /* the slider's drive index, -1: no check */
    uint16_t marker;
    double offset;
} homing = {"no slider", "", "", -1, 0, 0.0};

/* The raw text of "key"'s value in the record (a flat JSON object, as cochlea-dxl home writes
 * it): a string with its quotes, or a number, true, false, null. 0 when the key is absent. */
static const char *record_value(const char *text, const char *key, char *out, size_t n)
{
    char quoted[64];
    const char *p = text;
    snprintf(quoted, sizeof quoted, "\"%s\"", key);
    while ((p = strstr(p, quoted)) != 0) {
        const char *v = p + strlen(quoted);
        size_t k = 0;
        while (isspace((unsigned char)*v)) {
            ++v;
        }
        if (*v != ':') {
            p += 1;
            continue;
        }
        ++v;
        while (isspace((unsigned char)*v)) {
            ++v;
        }
        if (*v == '"') {
            out[k++] = *v++;
            while (*v && *v != '"' && k + 4 < n) {
                if (*v == '\\' && v[1]) {
                    out[k++] = *v++;
                }
                out[k++] = *v++;
            }
            if (*v != '"') {
                return 0;
            }
            out[k++] = '"';
        } else {
            while (*v && *v != ',' && *v != '}' && !isspace((unsigned char)*v) && k + 1 < n) {
                out[k++] = *v++;
            }
        }
        out[k] = '\0';
        return k ? out : 0;
    }
    return 0;
}

/* A whole number (JSON's int, not a float or a bool). */
/* How many times "key" occurs as a key (followed by a colon) in the record. */
static int record_count(const char *text, const char *key)
{
    char quoted[64];
    const char *p = text;
    int count = 0;
    snprintf(quoted, sizeof quoted, "\"%s\"", key);
    while ((p = strstr(p, quoted)) != 0) {
        const char *v = p + strlen(quoted);
        while (isspace((unsigned char)*v)) {
            ++v;
        }
        count += *v == ':';
        p += 1;
    }
    return count;
}

static int record_int(const char *text, const char *key, long *value)
{
    char token[64], *end;
    size_t i;
    if (!record_value(text, key, token, sizeof token)) {
        return 0;
    }
    for (i = token[0] == '-' ? 1 : 0; token[i]; ++i) {
        if (!isdigit((unsigned char)token[i])) {
            return 0;
        }
    }
    errno = 0;
    *value = strtol(token, &end, 10);
    return errno == 0 && *end == '\0' && end != token;
}

static int record_number(const char *text, const char *key, double *value)
{
    char token[64];
    return record_value(text, key, token, sizeof token) && parse_number(token, value);
}

/* The homing check as cochlea-run's bridge makes it, before the port opens: which slider, and
 * the offset and token of its record; 0, or a message (exit 5: nothing moved) in msg. */
static int check_homing(const options *o, const cochlea_scenario *sc, char *msg, size_t n)
{
    char path[4096], resolved[PATH_MAX];
    static char text[65536];
    const cochlea_drive *d = 0;
    FILE *f;
    size_t got;
    long motor_id, raw_counts, marker, direction;
    double stop_m, ratio;
    char value[128];
    int i, slider = -1, sliders = 0, v2;
    homing.robot = sc->robot;
    for (i = 0; i < sc->nq; ++i) {
        if (!sc->drives[i].revolute) {
            slider = slider < 0 ? i : slider;
            ++sliders;
        }
    }
    if (slider < 0) {
        return 0; /* "no slider" */
    }
    if (strcmp(o->homing, "auto") == 0 && (strncmp(o->port, "unix:", 5) == 0
                                            || strncmp(o->port, "socket://", 9) == 0)) {
        /* only cochlea-emulator --listen is reached over a socket */
        snprintf(homing.report, sizeof homing.report,
                 "not checked (a socket: the virtual chain)");
        return 0;
    }
    if (strcmp(o->homing, "auto") == 0 && realpath(o->port, resolved)
        && strncmp(resolved, "/dev/pts/", 9) == 0) {
        snprintf(homing.report, sizeof homing.report,
                 "not checked (a pseudo-terminal: the virtual chain)");
        return 0;
    }
    if (sliders > 1) { /* its bridge counts one joint from a homing: the others would not be */
        snprintf(msg, n, "the robot has %d prismatic joints and this program checks the homing "
                 "of one: run it with cochlea-run --backend dynamixel, which checks each",
                 sliders);
        return -1;
    }
    if (o->homing_record) {
        snprintf(path, sizeof path, "%s", o->homing_record);
    } else {
        const char *home = getenv("HOME");
        const struct passwd *pw = home ? 0 : getpwuid(getuid());
        snprintf(path, sizeof path, "%s/.cochlea/homing/%s.json",
                 home ? home : pw ? pw->pw_dir : ".", sc->robot);
    }
    f = fopen(path, "r");
    if (!f) {
        if (errno == ENOENT) {
            if (o->homing_record) {
                snprintf(msg, n, "the slider is not homed: no homing record %s; run cochlea-dxl "
                         "home --robot %s [--description FILE] --port PORT first, and pass "
                         "the record it writes", path, sc->robot);
            } else { /* a user description's record is not this default: say where it is */
                snprintf(msg, n, "the slider is not homed: no homing record %s; run cochlea-dxl "
                         "home --robot %s --port PORT first (a description of your own: "
                         "cochlea-dxl home --robot %s --description FILE --port PORT, then "
                         "--homing-record with the record it names)", path, sc->robot,
                         sc->robot);
            }
        } else {
            snprintf(msg, n, "homing record %s: cannot read it (%s); run cochlea-dxl home "
                     "again", path, strerror(errno));
        }
        return -1;
    }
    got = fread(text, 1, sizeof text - 1, f);
    fclose(f);
    text[got] = '\0';
    d = &sc->drives[slider];
    v2 = record_value(text, "format", value, sizeof value)
         && strcmp(value, "\"" HOMING_FORMAT "\"") == 0;
    if (v2 && record_count(text, "motor_id") != 1) {
        snprintf(msg, n, "homing record %s holds %d joints; this robot has one prismatic joint: "
                 "run cochlea-dxl home --robot %s --port PORT again", path,
                 record_count(text, "motor_id"), sc->robot);
        return -1;
    }
    if (record_value(text, "robot", value, sizeof value)
        && (value[0] != '"' || strlen(value) != strlen(sc->robot) + 2
            || strncmp(value + 1, sc->robot, strlen(sc->robot)) != 0)) {
        const int quoted = value[0] == '"' && strlen(value) >= 2;
        snprintf(msg, n, "homing record %s was made for the %.*s robot, not the %s one: run "
                 "cochlea-dxl home --robot %s --port PORT again", path,
                 (int)strlen(value) - (quoted ? 2 : 0), value + (quoted ? 1 : 0), sc->robot,
                 sc->robot);
        return -1;
    }
    if (!((v2 || (record_value(text, "format", value, sizeof value)
                  && strcmp(value, "\"" HOMING_FORMAT_1 "\"") == 0))
          && record_int(text, "motor_id", &motor_id) && record_int(text, "raw_counts", &raw_counts)
          && record_int(text, "marker", &marker) && record_number(text, "stop_m", &stop_m)
          && record_number(text, "ratio_m_per_rad", &ratio)
          && record_int(text, "direction", &direction) && (direction == 1 || direction == -1)
          && marker >= 0 && marker <= 65535)) {
        snprintf(msg, n, "homing record %s: not a " HOMING_FORMAT " record (nor a "
                 HOMING_FORMAT_1 " one); run cochlea-dxl home again", path);
        return -1;
    }
    if (record_value(text, "date", value, sizeof value) && value[0] == '"') {
        snprintf(homing.date, sizeof homing.date, "%.*s", (int)strlen(value) - 2, value + 1);
    }
    { /* the description's direction and pinion ratio: the drive's torque_per_effort is
       * direction * ratio (m/rad), whatever the motor's counts per turn (4096 on the X
       * series, 607500 on a PH42: no model's resolution assumed here) */
        const double per_rad = d->torque_per_effort;
        const long dir = per_rad < 0 ? -1 : 1;
        if (motor_id != d->id || direction != dir || fabs(ratio - fabs(per_rad)) > 1e-12) {
            snprintf(msg, n, "homing record %s was made for motor ID %ld, direction %+ld, ratio "
                     "%g m/rad; the description has ID %d, %+ld, %g: run cochlea-dxl home again",
                     path, motor_id, direction, ratio, d->id, dir, fabs(per_rad));
            return -1;
        }
    }
    homing.drive = slider;
    homing.marker = (uint16_t)marker;
    homing.offset = stop_m - d->q_per_count * (double)raw_counts;
    snprintf(homing.report, sizeof homing.report, "homed %s (%s)", homing.date, path);
    return 0;
}

static void start_failure(char *buf, size_t n, const cochlea_bridge *b,
                          const cochlea_start_report *r, const options *o)
{
    /* each step, and the item it writes (its address is the motor's, from its table) */
    static const char *const steps[] = {
        "", "PING", "Torque Enable 0 (WRITE %d = 0)", "Bus Watchdog 0 (WRITE %d = 0)",
        "Operating Mode %d (WRITE %d)", "Return Delay Time 0 (WRITE %d = 0)",
        "the Current Limit (WRITE %d)", "Goal Current 0 (WRITE %d = 0)",
        "the Bus Watchdog (WRITE %d)", "the first %s", "the joint limits",
        "Torque Enable 1 (WRITE %d = 1)", "the homing marker (READ/WRITE %d)"};
    static const int items[] = {
        -1, -1, DXL_ITEM_TORQUE_ENABLE, DXL_ITEM_BUS_WATCHDOG, DXL_ITEM_OPERATING_MODE,
        DXL_ITEM_RETURN_DELAY, DXL_ITEM_CURRENT_LIMIT, DXL_ITEM_GOAL_CURRENT,
        DXL_ITEM_BUS_WATCHDOG, -1, -1, DXL_ITEM_TORQUE_ENABLE, DXL_ITEM_HOMING_MARKER};
    const char *read_name = cochlea_instruction_name(b->bus->read_instruction);
    char what[96] = "?";
    char name[160] = "the bus";
    char value[64];
    char id_text[32] = "";
    const int drive = r->drive >= 0 && r->drive < b->n ? r->drive : 0;
    if (r->step >= 1 && r->step <= COCHLEA_STEP_HOMING) {
        const int item = items[r->step];
        const int address = item >= 0 ? b->bus->tables[drive].item[item].address : 0;
        if (r->step == COCHLEA_STEP_MODE) {
            snprintf(what, sizeof what, steps[r->step], b->bus->tables[drive].current_mode,
                     address);
        } else if (r->step == COCHLEA_STEP_FIRST_READ) {
            snprintf(what, sizeof what, steps[r->step], read_name);
        } else if (item >= 0) {
            snprintf(what, sizeof what, steps[r->step], address);
        } else {
            snprintf(what, sizeof what, "%s", steps[r->step]);
        }
    }
    if (r->drive >= 0 && r->drive < b->n) {
        who(name, sizeof name, &b->drives[r->drive]);
    }
    if (b->last_failure_id >= 0) {
        snprintf(id_text, sizeof id_text, " (ID %d)", b->last_failure_id);
    }
    switch (r->error) {
    case COCHLEA_START_NO_ANSWER:
        snprintf(buf, n, "%s did not answer %s on %s at %ld baud", name, what, o->port, o->baud);
        break;
    case COCHLEA_START_CRC:
        snprintf(buf, n, "%s answered %s with corrupted packets (CRC) only", name, what);
        break;
    case COCHLEA_START_PORT:
        snprintf(buf, n, "the serial port %s failed during %s", o->port, what);
        break;
    case COCHLEA_START_ALERT:
        snprintf(buf, n, "%s reports a hardware error (Hardware Error Status 0x%02X)", name,
                 (unsigned)r->detail);
        break;
    case COCHLEA_START_REFUSED:
        snprintf(buf, n, "%s refused %s (error byte 0x%02X)", name, what, (unsigned)r->detail);
        break;
    case COCHLEA_START_WRONG_MODEL:
        snprintf(buf, n, "%s is model number %d, not %d (%s)", name, r->detail,
                 b->drives[r->drive].model_number, model_name(b->drives[r->drive].model_number));
        break;
    case COCHLEA_START_NO_READ:
        snprintf(buf, n, "no good %s of the motors' state on %s (last failure: %s%s)",
                 read_name, o->port, cochlea_failure_name(r->detail), id_text);
        break;
    case COCHLEA_START_OUTSIDE_LIMITS:
        show(value, sizeof value, r->value,
             b->drives[r->drive].revolute ? "rad" : "m");
        snprintf(buf, n, "%s reads %s, outside its limits: check zero_offset_deg and direction "
                 "in the description", name, value);
        break;
    case COCHLEA_START_AWAY_FROM_START: {
        char expected[48];
        show(value, sizeof value, r->value, b->drives[r->drive].revolute ? "rad" : "m");
        show(expected, sizeof expected, r->expected, b->drives[r->drive].revolute ? "rad" : "m");
        snprintf(buf, n, "the robot is not at the scenario's initial pose: %s is at %s, the "
                 "scenario starts it at %s (tolerance %g deg, %g mm): move the joints there by "
                 "hand with the power off, or run a scenario whose initial state is where the "
                 "robot stands (--start-tolerance-deg, --start-tolerance-mm widen it)", name,
                 value, expected, o->start_tolerance_deg, o->start_tolerance_mm);
        break;
    }
    case COCHLEA_START_NOT_HOMED:
        snprintf(buf, n, "the slider (ID %d) was power-cycled or rebooted since it was homed "
                 "(%s): its encoder lost its turns; run cochlea-dxl home --robot %s --port "
                 "PORT again", b->drives[r->drive].id, homing.date[0] ? homing.date
                 : "date unknown", homing.robot);
        break;
    default:
        snprintf(buf, n, "the drive table does not fit the bridge (%d drives)", b->n);
    }
}

/* ---- the log: a ring between the loop and a writer thread ------------------------------------ */

/* Rows travel from the loop to log.bin through a ring of RING_SECONDS of periods (Python's
 * RING_SECONDS): the writer wakes every WRITER_PAUSE_NS and writes what the loop finished, so
 * a disk that stalls for less than the ring loses nothing, and the memory is the ring's
 * whatever the run's length. The loop never overwrites a row the writer has not written: at
 * the start of each period log_ready() says whether the period's slot is free, and a full ring
 * or a failed write ends the run with the log-failure rule (safe stop, exit 17). */
#define RING_SECONDS 4.0
#define WRITER_PAUSE_NS 20000000L
#define WRITER_STACK_BYTES (256 * 1024)

typedef struct {
    double *ring;        /* ring_rows x row_length: row k in slot k % ring_rows */
    double period_s;     /* the loop's period: the float build's t column is k period_s */
    int row_length;
    long ring_rows;
    long done;           /* rows the loop has finished (atomic; the loop's only) */
    long written;        /* rows handed to log.bin (atomic; the writer's only) */
    int finished;        /* the loop has ended (atomic) */
    int failed;          /* a write or the close failed (atomic); error is its errno */
    int error;
    int overrun;         /* a row came for a slot not yet written and was dropped (atomic) */
    FILE *file;
#ifdef COCHLEA_TEST_HOOKS
    /* Test builds only (make ... CC="cc -DCOCHLEA_TEST_HOOKS"): the writer fails with ENOSPC
     * once fail_after rows are in the file, or stops writing for good (a hung disk) once
     * stall_after are; -1: never. */
    long fail_after, stall_after;
#endif
} run_log;

/* In the period (the loop's log_ready): two atomic loads, no lock, no syscall. */
static int log_ready(void *ctx)
{
    run_log *log = (run_log *)ctx;
    const long next = __atomic_load_n(&log->done, __ATOMIC_RELAXED);
    return !__atomic_load_n(&log->failed, __ATOMIC_ACQUIRE)
           && !__atomic_load_n(&log->overrun, __ATOMIC_RELAXED)
           && next - __atomic_load_n(&log->written, __ATOMIC_ACQUIRE) < log->ring_rows;
}

/* In the period (the loop's on_row): one copy into the ring. */
static void log_row(void *ctx, const cochlea_real *row, int row_length)
{
    run_log *log = (run_log *)ctx;
    const long k = __atomic_load_n(&log->done, __ATOMIC_RELAXED);
#ifdef COCHLEA_FLOAT
    double *slot = log->ring + (size_t)(k % log->ring_rows) * (size_t)row_length;
    int j;
#endif
    if (k - __atomic_load_n(&log->written, __ATOMIC_ACQUIRE) >= log->ring_rows) {
        /* log_ready() rules this out; should it ever happen, drop rather than overwrite. */
        __atomic_store_n(&log->overrun, 1, __ATOMIC_RELAXED);
        return;
    }
#ifdef COCHLEA_FLOAT
    /* log.bin is double: the float row widened, and its t the exact k h (row k is period
     * k's), which a float t cannot carry past a few hours */
    for (j = 1; j < row_length; ++j) {
        slot[j] = (double)row[j];
    }
    slot[0] = (double)k * log->period_s;
#else
    memcpy(log->ring + (size_t)(k % log->ring_rows) * (size_t)row_length, row,
           (size_t)row_length * sizeof(double));
#endif
    __atomic_store_n(&log->done, k + 1, __ATOMIC_RELEASE);
}

static void log_failed(run_log *log, int error)
{
    log->error = error ? error : EIO;
    __atomic_store_n(&log->failed, 1, __ATOMIC_RELEASE);
}

/* The writer's work: every finished row to the file, up to the ring's end and then from its
 * start; `written` moves only past rows the file has taken. */
static void write_rows(run_log *log)
{
    const long done = __atomic_load_n(&log->done, __ATOMIC_ACQUIRE);
    long written = log->written;
    while (written < done && !log->failed) {
        const long first = written % log->ring_rows;
        size_t count = (size_t)(done - written < log->ring_rows - first
                                    ? done - written : log->ring_rows - first);
        int full = 0;
#ifdef COCHLEA_TEST_HOOKS
        if (log->stall_after >= 0 && written + (long)count > log->stall_after) {
            if (written >= log->stall_after) {
                return;
            }
            count = (size_t)(log->stall_after - written);
        }
        if (log->fail_after >= 0 && written + (long)count >= log->fail_after) {
            count = (size_t)(log->fail_after - written);
            full = 1;
        }
#endif
        errno = 0;
        if ((count && fwrite(log->ring + (size_t)first * (size_t)log->row_length,
                             sizeof(double) * (size_t)log->row_length, count, log->file) != count)
            || fflush(log->file) != 0) {
            log_failed(log, errno);
            return;
        }
        written += (long)count;
        __atomic_store_n(&log->written, written, __ATOMIC_RELEASE);
        if (full) {
            log_failed(log, ENOSPC);
            return;
        }
    }
}

static void *writer(void *arg)
{
    run_log *log = (run_log *)arg;
    const struct timespec pause = {0, WRITER_PAUSE_NS};
    while (!__atomic_load_n(&log->finished, __ATOMIC_ACQUIRE)) {
        write_rows(log);
        nanosleep(&pause, 0);
    }
    write_rows(log);
    return 0;
}

/* ---- statistics of log.bin read back in chunks (fixed memory) ------------------------------ */

/* The timing columns' percentiles are numpy's (linear interpolation) of the finite values,
 * found in two passes over log.bin: the first counts the values in a histogram of HIST_BINS
 * logarithmic bins from HIST_LO to HIST_HI s (each bin 2.1e-4 wide relative to its values;
 * one more bin below, one above), the second gathers the values of the bins that hold the
 * order statistics wanted and selects them exactly. A bin of more than GATHER_MAX values (in
 * all, over the bins wanted) is not gathered: its geometric centre stands for the value, within
 * 1.1e-4 relative (at 1 kHz an hour puts a few thousand periods in the fullest bin). */
#define HIST_BINS 65536
#define HIST_LO 1e-9
#define HIST_HI 1e3
#define GATHER_MAX (1L << 19)
#define PERCENTS 2
#define TIMING_COLUMNS 3

static const double percents[PERCENTS] = {50.0, 99.0};

typedef struct {
    double *values;  /* gathered (or 0) */
    long count, cap;
    int bin;
} gathered;

typedef struct {
    int column;      /* in the row */
    long first_row;  /* rows before it have no value (the first period has no wall period) */
    long n;          /* finite values */
    double sum, min, max, mean, m2;
    uint32_t *bins;  /* HIST_BINS + 2 */
    long rank[2 * PERCENTS];     /* order statistics wanted (-1: none) */
    int slot[2 * PERCENTS];      /* their gathered bin */
    long in_bin[2 * PERCENTS];   /* their rank inside it */
    gathered bins_wanted[2 * PERCENTS];
    int n_wanted;
    double percentile[PERCENTS];
} timing_column;

static int hist_bin(double x)
{
    static double scale = 0.0;
    double b;
    if (scale == 0.0) {
        scale = (double)HIST_BINS / log(HIST_HI / HIST_LO);
    }
    if (!(x >= HIST_LO)) {
        return 0;
    }
    if (x >= HIST_HI) {
        return HIST_BINS + 1;
    }
    b = floor(log(x / HIST_LO) * scale);
    return 1 + (b < 0 ? 0 : b >= HIST_BINS ? HIST_BINS - 1 : (int)b);
}

static double bin_centre(const timing_column *c, int bin)
{
    if (bin == 0) {
        return c->min;
    }
    if (bin == HIST_BINS + 1) {
        return c->max;
    }
    return HIST_LO * exp(((double)bin - 0.5) * log(HIST_HI / HIST_LO) / (double)HIST_BINS);
}

static int compare(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* numpy's "linear" virtual index of percentile p of n values, term for term. */
static double virtual_index(long n, double p)
{
    const double q = p / 100.0;
    return (double)n * q + (1.0 + q * (1.0 - 1.0 - 1.0)) - 1.0;
}

/* After the first pass: the order statistics each percentile needs, their bins, and room to
 * gather those bins' values within *budget. 0, or -1 when out of memory. */
static int plan_percentiles(timing_column *c, long *budget)
{
    int p, w, j;
    c->n_wanted = 0;
    for (p = 0; p < 2 * PERCENTS; ++p) {
        c->rank[p] = -1;
    }
    if (c->n == 0) {
        return 0;
    }
    for (p = 0; p < PERCENTS; ++p) {
        const double v = virtual_index(c->n, percents[p]);
        const long i = (long)floor(v);
        c->rank[2 * p] = v >= (double)(c->n - 1) ? c->n - 1 : (i < 0 ? 0 : i);
        c->rank[2 * p + 1] = v >= (double)(c->n - 1) ? c->n - 1 : (i < 0 ? 0 : i + 1);
    }
    for (j = 0; j < 2 * PERCENTS; ++j) {
        long below = 0;
        int bin = 0;
        while (below + (long)c->bins[bin] <= c->rank[j]) {
            below += (long)c->bins[bin++];
        }
        c->in_bin[j] = c->rank[j] - below;
        for (w = 0; w < c->n_wanted && c->bins_wanted[w].bin != bin; ++w) {
        }
        if (w == c->n_wanted) {
            gathered *g = &c->bins_wanted[c->n_wanted++];
            g->bin = bin;
            g->count = 0;
            g->cap = (long)c->bins[bin];
            g->values = 0;
            if (g->cap <= *budget) {
                g->values = malloc(sizeof(double) * (size_t)g->cap);
                if (!g->values) {
                    return -1;
                }
                *budget -= g->cap;
            }
        }
        c->slot[j] = w;
    }
    return 0;
}

/* After the second pass: the percentiles, numpy's _lerp of the two order statistics. */
static void finish_percentiles(timing_column *c)
{
    double order[2 * PERCENTS];
    int p, j;
    for (j = 0; j < c->n_wanted; ++j) {
        gathered *g = &c->bins_wanted[j];
        if (g->values) {
            qsort(g->values, (size_t)g->count, sizeof(double), compare);
        }
    }
    for (j = 0; j < 2 * PERCENTS; ++j) {
        const gathered *g = c->n ? &c->bins_wanted[c->slot[j]] : 0;
        order[j] = !g ? NAN
                   : g->values && c->in_bin[j] < g->count ? g->values[c->in_bin[j]]
                                                          : bin_centre(c, g->bin);
    }
    for (p = 0; p < PERCENTS; ++p) {
        const double v = c->n ? virtual_index(c->n, percents[p]) : NAN;
        const double gamma = v - floor(v);
        const double a = order[2 * p], b = order[2 * p + 1], diff = b - a;
        c->percentile[p] = !c->n ? NAN : gamma >= 0.5 ? b - diff * (1.0 - gamma)
                                                     : a + diff * gamma;
    }
    for (j = 0; j < c->n_wanted; ++j) {
        free(c->bins_wanted[j].values);
        c->bins_wanted[j].values = 0;
    }
}

/* What the report needs of the whole log, gathered row by row: the timing columns (wall
 * period, compute, backend i/o), per tracked coordinate the tail's sum of squares, per joint
 * the largest |tau|, per unit the largest |p_hat| and whether every one was finite, and the
 * first and last rows. */
typedef struct {
    long rows, tail;
    timing_column timing[TIMING_COLUMNS];
    double tail_sq[COCHLEA_MAX_UNITS][COCHLEA_MAX_ERRORS];
    double torque_max[COCHLEA_MAX_JOINTS];
    double estimate_max[COCHLEA_MAX_UNITS];
    int estimate_finite[COCHLEA_MAX_UNITS];
    double first[COCHLEA_MAX_ROW], last[COCHLEA_MAX_ROW];
    int have_first; /* first: the first row with a measured state (a failed first read
                     * logs NaN until the first good one, as cochlea-run's report) */
} log_stats;

/* ---- JSON ------------------------------------------------------------------------------------ */

static void json_number(FILE *f, double v)
{
    if (isnan(v)) {
        fputs("NaN", f); /* as Python's json writes it */
    } else if (isinf(v)) {
        fputs(v > 0 ? "Infinity" : "-Infinity", f);
    } else {
        fprintf(f, "%.17g", v);
    }
}

static void json_string(FILE *f, const char *s)
{
    fputc('"', f);
    for (; *s; ++s) {
        const unsigned char ch = (unsigned char)*s;
        if (ch == '"' || ch == '\\') {
            fprintf(f, "\\%c", ch);
        } else if (ch < 0x20) {
            fprintf(f, "\\u%04x", ch);
        } else {
            fputc(ch, f);
        }
    }
    fputc('"', f);
}

static void key(FILE *f, int indent, const char *name)
{
    fprintf(f, "%*s", indent, "");
    json_string(f, name);
    fputs(": ", f);
}

/* ---- the run's files --------------------------------------------------------------------- */

/* log.columns.json: how to read log.bin, cochlea-run's raw columns. The names are the
 * scenario's, generated from the one schema of every log (cochlea/log_schema.py). */
static int write_columns(const char *out, const cochlea_scenario *sc, int row_length)
{
    FILE *f;
    int i;
    if (sc->n_raw_columns != row_length) {
        fprintf(stderr, "cochlea-embedded: the scenario names %d log.bin columns but a row "
                "holds %d values: regenerate generated_c/ (cochlea-codegen)\n",
                sc->n_raw_columns, row_length);
        return -1;
    }
    f = open_in(out, "log.columns.json", "w");
    if (!f) {
        return -1;
    }
    fprintf(f, "{\n \"schema_version\": %d,\n \"dtype\": \"float64\",\n \"row_length\": %d,\n"
            " \"columns\": [\n", sc->schema_version, row_length);
    for (i = 0; i < sc->n_raw_columns; ++i) {
        fputs(i ? ",\n  " : "  ", f);
        json_string(f, sc->raw_columns[i]);
    }
    fputs("\n ]\n}\n", f);
    return fclose(f);
}

/* Offsets in a row of unit u's errors and estimate. */
static int unit_offset(const cochlea_scenario *sc, int u)
{
    int k, off = 1 + 3 * sc->nq;
    for (k = 0; k < u; ++k) {
        off += sc->units[k].ne + sc->units[k].np;
    }
    return off;
}

/* log.csv's header: cochlea-run's columns (its pose columns aside), SI: the scenario's,
 * generated from the one schema of every log (cochlea/log_schema.py). */
static void csv_header(FILE *f, const cochlea_scenario *sc)
{
    int i;
    for (i = 0; i < sc->n_log_columns; ++i) {
        if (i) {
            fputc(',', f);
        }
        fputs(sc->log_columns[i], f);
    }
    fputc('\n', f);
}

/* The number of values in a log.csv row (for the disk's estimate). */
static long csv_columns(const cochlea_scenario *sc)
{
    return sc->n_log_columns;
}

/* One log.csv row from a log.bin row; the desired path is evaluated again at the row's time. */
static void csv_row(FILE *f, const cochlea_scenario *sc, const double *row)
{
    double xd[64], xd_dot[64], xd_ddot[64];
    const int n = sc->nq;
    const double *timing = row + cochlea_loop_timing_at(sc);
    const double *current = timing + COCHLEA_TIMING_COLUMNS;
    int u, i;
    if (sc->desired(row[0], xd, xd_dot, xd_ddot) != 0) {
        for (i = 0; i < sc->nd; ++i) {
            xd[i] = xd_dot[i] = NAN;
        }
    }
    fprintf(f, "%.10g", row[0]);
    for (u = 0; u < sc->n_units; ++u) {
        const cochlea_unit_info *t = &sc->units[u];
        const double *e = row + unit_offset(sc, u);
        for (i = 0; i < t->nq; ++i) fprintf(f, ",%.10g", row[1 + t->q0 + i]);
        for (i = 0; i < t->nq; ++i) fprintf(f, ",%.10g", row[1 + n + t->q0 + i]);
        for (i = 0; i < t->nd; ++i) fprintf(f, ",%.10g", xd[t->d0 + i]);
        for (i = 0; i < t->nd; ++i) fprintf(f, ",%.10g", xd_dot[t->d0 + i]);
        for (i = 0; i < t->nd; ++i) fprintf(f, ",%.10g", t->tracking_sign * e[i]);
        for (i = t->nd; i < t->ne; ++i) fprintf(f, ",%.10g", e[i]);
        for (i = 0; i < t->nq; ++i) fprintf(f, ",%.10g", row[1 + 2 * n + t->q0 + i]);
        for (i = 0; i < t->nq; ++i) fprintf(f, ",%.10g", current[t->q0 + i]);
        for (i = 0; i < t->np; ++i) fprintf(f, ",%.10g", e[t->ne + i]);
    }
    for (i = 0; i < COCHLEA_TIMING_COLUMNS; ++i) {
        fprintf(f, ",%.10g", timing[i]);
    }
    fputc('\n', f);
}

/* ---- reading log.bin back ------------------------------------------------------------------- */

/* The first pass's work on row k: statistics that need one look at each value. */
static void first_pass_row(log_stats *st, const cochlea_scenario *sc, const double *row, long k,
                           int row_length)
{
    int u, i, c;
    if (!st->have_first) {
        for (i = 0; i < sc->nq && isfinite(row[1 + i]); ++i) {
        }
        if (i == sc->nq) {
            memcpy(st->first, row, sizeof(double) * (size_t)row_length);
            st->have_first = 1;
        }
    }
    if (k == st->rows - 1) {
        memcpy(st->last, row, sizeof(double) * (size_t)row_length);
    }
    for (c = 0; c < TIMING_COLUMNS; ++c) {
        timing_column *t = &st->timing[c];
        const double v = row[t->column];
        if (k >= t->first_row && isfinite(v)) {
            t->n += 1;
            t->sum += v;
            t->min = t->n == 1 || v < t->min ? v : t->min;
            t->max = t->n == 1 || v > t->max ? v : t->max;
            t->bins[hist_bin(v)] += 1;
        }
    }
    for (i = 0; i < sc->nq; ++i) {
        const double v = fabs(row[1 + 2 * sc->nq + i]);
        const double max = st->torque_max[i];
        st->torque_max[i] = (isnan(v) || isnan(max)) ? NAN : (v > max ? v : max);
    }
    for (u = 0; u < sc->n_units; ++u) {
        const cochlea_unit_info *t = &sc->units[u];
        const double *e = row + unit_offset(sc, u);
        double s = 0.0;
        if (k >= st->tail) {
            for (i = 0; i < t->nd; ++i) {
                st->tail_sq[u][i] += e[i] * e[i];
            }
        }
        for (i = 0; i < t->np; ++i) {
            s += e[t->ne + i] * e[t->ne + i];
        }
        st->estimate_finite[u] = st->estimate_finite[u] && isfinite(s);
        if (!(sqrt(s) <= st->estimate_max[u])) {
            st->estimate_max[u] = sqrt(s);
        }
    }
}

/* The second pass's work on row k: the spread about the mean, and the values of the bins the
 * percentiles are in. */
static void second_pass_row(log_stats *st, const double *row, long k)
{
    int c, w;
    for (c = 0; c < TIMING_COLUMNS; ++c) {
        timing_column *t = &st->timing[c];
        const double v = row[t->column];
        if (k >= t->first_row && isfinite(v)) {
            const int bin = hist_bin(v);
            t->m2 += (v - t->mean) * (v - t->mean);
            for (w = 0; w < t->n_wanted; ++w) {
                gathered *g = &t->bins_wanted[w];
                if (g->bin == bin && g->values && g->count < g->cap) {
                    g->values[g->count++] = v;
                }
            }
        }
    }
}

/* Reads DIR/log.bin (rows of row_length) back through chunk (chunk_rows rows): the first pass
 * writes log.csv (unless csv is 0) and gathers what needs one look, the second what needs the
 * mean and the percentiles' bins. 0, or -1 with errno when log.bin cannot be read or memory
 * is short. */
static int read_back(const char *out, const cochlea_scenario *sc, int row_length, long rows,
                     double *chunk, long chunk_rows, FILE *csv, log_stats *st)
{
    FILE *f;
    long k, got, budget = GATHER_MAX;
    int pass, c, u, i;
#ifdef COCHLEA_TEST_HOOKS
    if (getenv("COCHLEA_TEST_GATHER_MAX")) {
        budget = atol(getenv("COCHLEA_TEST_GATHER_MAX"));
    }
#endif
    st->rows = rows;
    st->have_first = 0;
    st->tail = (long)((double)rows * (1.0 - TAIL_FRACTION));
    for (c = 0; c < TIMING_COLUMNS; ++c) {
        timing_column *t = &st->timing[c];
        t->column = cochlea_loop_timing_at(sc) + 1 + c; /* wall period, compute, i/o */
        t->first_row = c == 0 ? 1 : 0;
        t->n = 0;
        t->sum = t->m2 = t->mean = 0.0;
        t->min = t->max = NAN;
        t->n_wanted = 0;
        t->bins = 0;
        for (i = 0; i < PERCENTS; ++i) {
            t->percentile[i] = NAN;
        }
    }
    for (u = 0; u < COCHLEA_MAX_UNITS; ++u) {
        st->estimate_max[u] = 0.0;
        st->estimate_finite[u] = 1;
        for (i = 0; i < COCHLEA_MAX_ERRORS; ++i) {
            st->tail_sq[u][i] = 0.0;
        }
    }
    for (i = 0; i < COCHLEA_MAX_JOINTS; ++i) {
        st->torque_max[i] = 0.0;
    }
    if (rows == 0) {
        return 0;
    }
    for (c = 0; c < TIMING_COLUMNS; ++c) {
        /* calloc: only the pages of bins that are used become resident */
        st->timing[c].bins = calloc(HIST_BINS + 2, sizeof(uint32_t));
        if (!st->timing[c].bins) {
            return -1;
        }
    }
    if (!(f = open_in(out, "log.bin", "rb"))) {
        return -1;
    }
    for (pass = 0; pass < 2; ++pass) {
        if (pass == 1) {
            for (c = 0; c < TIMING_COLUMNS; ++c) {
                timing_column *t = &st->timing[c];
                t->mean = t->n ? t->sum / (double)t->n : NAN;
                if (plan_percentiles(t, &budget) != 0) {
                    fclose(f);
                    return -1;
                }
            }
            rewind(f);
        }
        for (k = 0; k < rows; k += got) {
            const long want = rows - k < chunk_rows ? rows - k : chunk_rows;
            long j;
            got = (long)fread(chunk, sizeof(double) * (size_t)row_length, (size_t)want, f);
            if (got != want) {
                fclose(f);
                errno = errno ? errno : EIO;
                return -1;
            }
            for (j = 0; j < got; ++j) {
                const double *row = chunk + (size_t)j * (size_t)row_length;
                if (pass == 0) {
                    first_pass_row(st, sc, row, k + j, row_length);
                    if (csv) {
                        csv_row(csv, sc, row);
                    }
                } else {
                    second_pass_row(st, row, k + j);
                }
            }
        }
    }
    fclose(f);
    for (c = 0; c < TIMING_COLUMNS; ++c) {
        finish_percentiles(&st->timing[c]);
        free(st->timing[c].bins);
        st->timing[c].bins = 0;
    }
    return 0;
}

/* Per tracked coordinate of unit u, what one encoder count on every joint moves it at the
 * run's last pose (cochlea/apps/report.py's measurement_resolution): the joint's count in joint
 * space; in task space sum_j |fk(q + count_j) - fk(q)|, the change of the tracking error (the
 * first nd errors, desired - fk(q)) that the controller computes from a fresh state at the
 * last row's time. 1 and res[nd] filled, or 0 when there is no last row (or no memory). */
static int measurement_resolution(const cochlea_scenario *sc, int u, const log_stats *st,
                                  double period, double *res)
{
    const cochlea_unit_info *t = &sc->units[u];
    cochlea_real q[COCHLEA_MAX_JOINTS], qd[COCHLEA_MAX_JOINTS], tau[COCHLEA_MAX_JOINTS];
    cochlea_real base[COCHLEA_MAX_ERRORS], moved[COCHLEA_MAX_ERRORS];
    void *state;
    int i, j;
    if (st->rows == 0) {
        return 0;
    }
    if (strcmp(sc->space, "joint") == 0) {
        for (i = 0; i < t->nd; ++i) {
            res[i] = fabs(sc->drives[t->q0 + i].q_per_count);
        }
        return 1;
    }
    state = malloc(sc->state_size);
    if (!state || sc->init(state, period) != 0) {
        free(state);
        return 0;
    }
    for (j = 0; j < sc->nq; ++j) {
        q[j] = (cochlea_real)st->last[1 + j];
        qd[j] = (cochlea_real)st->last[1 + sc->nq + j];
    }
    (void)sc->step(state, st->last[0], q, qd, tau, base);
    for (i = 0; i < t->nd; ++i) {
        res[i] = 0.0;
    }
    for (j = t->q0; j < t->q0 + t->nq; ++j) {
        const cochlea_real keep = q[j];
        q[j] = (cochlea_real)(q[j] + fabs(sc->drives[j].q_per_count));
        (void)sc->step(state, st->last[0], q, qd, tau, moved);
        q[j] = keep;
        for (i = 0; i < t->nd; ++i) {
            res[i] += fabs((double)moved[t->e0 + i] - (double)base[t->e0 + i]);
        }
    }
    sc->terminate(state);
    free(state);
    return 1;
}

/* summary.json's "units" entry of unit u; whether every tracked coordinate converged. res: the
 * unit's measurement_resolution, or 0 (the numeric floor alone). */
static int unit_summary(FILE *f, const cochlea_scenario *sc, int u, const log_stats *st,
                        const double *res)
{
    const cochlea_unit_info *t = &sc->units[u];
    const int off = unit_offset(sc, u);
    const long rows = st->rows, tail = st->tail;
    int i, all = 1;
    const double max_norm = st->estimate_max[u];
    const int finite = st->estimate_finite[u];
    key(f, 4, t->name);
    fputs("{\n", f);
    key(f, 6, "tracked");
    fputs("{\n", f);
    for (i = 0; i < t->nd; ++i) {
        const double numeric = strcmp(t->tracked_units[i], "rad") == 0 ? 1e-5 : 1e-6;
        const double floor_ = res && res[i] > numeric ? res[i] : numeric;
        key(f, 8, t->tracked_names[i]);
        fputs("{\n", f);
        key(f, 10, "unit");
        json_string(f, t->tracked_units[i]);
        fputs(",\n", f);
        if (rows == 0 || !st->have_first) {
            fputs("          \"initial_abs_error\": null,\n          \"final_rms_error\": null,\n"
                  "          \"converged\": false,\n", f);
            key(f, 10, "convergence_floor");
            json_number(f, floor_);
            fputs(",\n          \"measured_initial_abs_error\": null,\n"
                  "          \"measured_final_rms_error\": null,\n"
                  "          \"measured_converged\": false\n", f);
            all = 0;
        } else {
            const double initial = fabs(st->first[off + i]);
            const double rms = sqrt(st->tail_sq[u][i] / (double)(rows - tail));
            int ok;
            ok = isfinite(rms) && (rms <= CONVERGENCE_RATIO * initial || rms <= floor_);
            all = all && ok;
            key(f, 10, "initial_abs_error");
            json_number(f, initial);
            fputs(",\n", f);
            key(f, 10, "final_rms_error");
            json_number(f, rms);
            fputs(",\n", f);
            key(f, 10, "converged");
            fputs(ok ? "true,\n" : "false,\n", f);
            /* the floor it was judged on: the numeric one, or one count on every joint */
            key(f, 10, "convergence_floor");
            json_number(f, floor_);
            fputs(",\n", f);
            /* the error the controller measured: on the motors, the one judged */
            key(f, 10, "measured_initial_abs_error");
            json_number(f, initial);
            fputs(",\n", f);
            key(f, 10, "measured_final_rms_error");
            json_number(f, rms);
            fputs(",\n", f);
            key(f, 10, "measured_converged");
            fputs(ok ? "true" : "false", f);
            if (res) {
                fputs(",\n", f);
                key(f, 10, "measurement_resolution");
                json_number(f, res[i]);
            }
            fputs("\n", f);
        }
        fprintf(f, "        }%s\n", i + 1 < t->nd ? "," : "");
    }
    fputs("      },\n", f);
    /* the count each joint's position is measured in: the drives' encoders */
    key(f, 6, "position_quantum");
    fputs("{\"source\": \"drives\", \"joints\": {", f);
    for (i = 0; i < t->nq; ++i) {
        fputs(i ? ", " : "", f);
        json_string(f, t->joint_names[i]);
        fputs(": {\"value\": ", f);
        json_number(f, fabs(sc->drives[t->q0 + i].q_per_count));
        fputs(", \"unit\": ", f);
        json_string(f, t->joint_units[i]);
        fputs("}", f);
    }
    fputs("}},\n", f);
    key(f, 6, "torque");
    fputs("{\n", f);
    for (i = 0; i < t->nq; ++i) {
        const double max = st->torque_max[t->q0 + i];
        key(f, 8, t->joint_names[i]);
        fputs("{\n", f);
        key(f, 10, "unit");
        json_string(f, strcmp(t->joint_units[i], "rad") == 0 ? "N m" : "N");
        fputs(",\n", f);
        key(f, 10, "max_abs");
        json_number(f, max);
        fprintf(f, "\n        }%s\n", i + 1 < t->nq ? "," : "");
    }
    fputs("      },\n", f);
    key(f, 6, "estimates");
    fputs("{\n", f);
    key(f, 8, "names");
    fputs("[", f);
    for (i = 0; i < t->np; ++i) {
        fputs(i ? ", " : "", f);
        json_string(f, t->param_names[i]);
    }
    fputs("],\n", f);
    key(f, 8, "units");
    fputs("[", f);
    for (i = 0; i < t->np; ++i) {
        fputs(i ? ", " : "", f);
        json_string(f, t->param_units[i]);
    }
    fputs("],\n", f);
    key(f, 8, "bound_norm");
    json_number(f, t->bound);
    fputs(",\n", f);
    key(f, 8, "max_norm");
    json_number(f, max_norm);
    fputs(",\n", f);
    key(f, 8, "bounded");
    fputs(finite && max_norm <= t->bound * (1 + 1e-9) ? "true" : "false", f);
    fputs(",\n", f);
    key(f, 8, "final");
    if (rows == 0) {
        fputs("null", f);
    } else {
        const double *p = st->last + off + t->ne;
        fputs("[", f);
        for (i = 0; i < t->np; ++i) {
            fputs(i ? ", " : "", f);
            json_number(f, p[i]);
        }
        fputs("]", f);
    }
    fputs(",\n", f);
    key(f, 8, "nominal");
    fputs("[", f);
    for (i = 0; i < t->np; ++i) {
        fputs(i ? ", " : "", f);
        json_number(f, t->p_nominal[i]);
    }
    fputs("]\n      }\n", f);
    fprintf(f, "    }%s\n", u + 1 < sc->n_units ? "," : "");
    return all;
}

typedef struct {
    const char *scheduling, *memory;
    double wall_s;
    char detail[2048];
    char shutdown[2048];
    char last_failure[256];
    double budget_bytes, wire_s, bus_s, cycle_s, timeout_s, watchdog_s;
} run_facts;

static void timing_summary(FILE *f, const cochlea_loop *loop, const log_stats *st,
                           const run_facts *facts, const cochlea_bridge *b, const options *o)
{
    const double h = loop->period_s;
    const timing_column *wall = &st->timing[0], *compute = &st->timing[1],
                        *backend = &st->timing[2];
    const long rows = st->rows;
    long k;
    int i;
    fputs("{\n", f);
    key(f, 4, "unit");
    fputs("\"s\",\n", f);
    key(f, 4, "nominal_period");
    json_number(f, h);
    fputs(",\n", f);
    /* the wall period of every row but the first */
    key(f, 4, "period_mean");
    json_number(f, wall->n ? wall->mean : NAN);
    fputs(",\n", f);
    key(f, 4, "period_std");
    json_number(f, wall->n ? sqrt(wall->m2 / (double)wall->n) : NAN);
    fputs(",\n", f);
    key(f, 4, "period_p50");
    json_number(f, wall->percentile[0]);
    fputs(",\n", f);
    key(f, 4, "period_p99");
    json_number(f, wall->percentile[1]);
    fputs(",\n", f);
    key(f, 4, "period_max");
    json_number(f, wall->n ? wall->max : NAN);
    fputs(",\n", f);
    key(f, 4, "deadline_misses");
    fprintf(f, "%u,\n", loop->deadline_misses);
    key(f, 4, "deadline_miss_fraction");
    json_number(f, (double)loop->deadline_misses / (double)(rows > 1 ? rows : 1));
    fputs(",\n", f);
    key(f, 4, "compute_p50");
    json_number(f, compute->percentile[0]);
    fputs(",\n", f);
    key(f, 4, "compute_p99");
    json_number(f, compute->percentile[1]);
    fputs(",\n", f);
    key(f, 4, "compute_max");
    json_number(f, compute->n ? compute->max : NAN);
    fputs(",\n", f);
    key(f, 4, "backend_mean");
    json_number(f, backend->n ? backend->mean : NAN);
    fputs(",\n", f);
    key(f, 4, "backend_p99");
    json_number(f, backend->percentile[1]);
    fputs(",\n", f);
    /* the overrun rule (loop.h), cochlea-run's keys */
    fprintf(f, "    \"overruns\": %u,\n", loop->overruns);
    /* issue 28: periods still running at a tick of the port's period timer
     * (cochlea_loop_tick); this program's periods wait on the clock, not on a timer
     * interrupt, so nothing ticks here and it stays 0 (a board port's timer counts it) */
    fprintf(f, "    \"tick_overruns\": %u,\n", (unsigned)loop->tick_overruns);
    key(f, 4, "lateness_max");
    json_number(f, (double)loop->lateness_max_ns * 1e-9);
    fputs(",\n", f);
    key(f, 4, "overrun_policy");
    json_string(f, COCHLEA_OVERRUN_POLICY);
    fputs(",\n", f);
    key(f, 4, "stall_limit");
    json_number(f, (double)loop->stall_ns * 1e-9);
    fputs(",\n", f);
    key(f, 4, "lateness_limit");
    json_number(f, (double)loop->lateness_limit_ns * 1e-9);
    fputs(",\n", f);
    key(f, 4, "scheduling");
    json_string(f, facts->scheduling);
    fputs(",\n", f);
    key(f, 4, "memory");
    json_string(f, facts->memory);
    fputs(",\n", f);
    key(f, 4, "watchdog_misses_allowed");
    fprintf(f, "%d,\n", loop->limits.watchdog_misses);
    key(f, 4, "watchdog_errors_allowed");
    fprintf(f, "%d,\n", loop->limits.watchdog_errors);
    key(f, 4, "bus");
    fputs("{\n", f);
    key(f, 6, "port");
    json_string(f, o->port);
    fprintf(f, ",\n      \"baud\": %ld,\n      \"motors\": [", o->baud);
    for (i = 0; i < b->n; ++i) {
        fprintf(f, "%s%d", i ? ", " : "", b->drives[i].id);
    }
    fputs("],\n", f);
    key(f, 6, "bus_budget");
    fprintf(f, "{\"bytes_per_period\": %d, \"wire_s\": ", (int)facts->budget_bytes);
    json_number(f, facts->wire_s);
    fputs(", \"bus_s\": ", f);
    json_number(f, facts->bus_s);
    fputs(", \"with_adapter_latency_s\": ", f);
    json_number(f, facts->cycle_s);
    /* the transfers sent, chosen from the models' data by cochlea-run's rule */
    fputs(", \"read_instruction\": ", f);
    json_string(f, cochlea_instruction_name(b->bus->read_instruction));
    fputs(", \"write_instruction\": ", f);
    json_string(f, cochlea_instruction_name(b->bus->write_instruction));
    fputs(", \"read_choice\": ", f);
    json_string(f, b->bus->read_choice);
    fputs("},\n", f);
    key(f, 6, "read_timeout_s");
    json_number(f, facts->timeout_s);
    fputs(",\n", f);
    key(f, 6, "watchdog_s");
    json_number(f, facts->watchdog_s);
    fprintf(f, ",\n      \"realtime_tick_check\": %s", b->realtime_tick ? "true" : "false");
    fprintf(f, ",\n      \"friction_compensated_by\": \"%s\"",
            b->offset_current ? "bridge" : "controller");
    fprintf(f, ",\n      \"reads\": %u,\n      \"good_reads\": %u,\n      \"writes\": %u,\n",
            b->reads, b->good_reads, b->writes);
    key(f, 6, "failures");
    fputs("{", f);
    for (i = 0, k = 0; i < COCHLEA_FAIL_KINDS; ++i) {
        if (b->failures[i]) {
            fprintf(f, "%s\"%s\": %u", k++ ? ", " : "", cochlea_failure_name(i), b->failures[i]);
        }
    }
    fprintf(f, "},\n      \"garbage_packets\": %u,\n      \"unexpected_packets\": %u,\n",
            b->garbage_packets, b->unexpected_packets);
    key(f, 6, "last_failure");
    json_string(f, facts->last_failure);
    fputs(",\n      \"low_latency\": null,\n", f);
    key(f, 6, "homing");
    json_string(f, homing.report);
    fputs(",\n", f);
    key(f, 6, "shutdown");
    json_string(f, facts->shutdown);
    fputs("\n    }\n  }", f);
}

static void realtime_summary(FILE *f, const options *o); /* with the real-time settings */

static int write_summary(const char *out, const cochlea_loop *loop, const log_stats *st,
                         const run_facts *facts, const cochlea_bridge *b, const options *o,
                         int *converged_out)
{
    const long rows = st->rows;
    const cochlea_scenario *sc = loop->scenario;
    FILE *f = open_in(out, ".summary.json.tmp", "w");
    int u, converged = 1;
    long pos;
    if (!f) {
        return -1;
    }
    fputs("{\n", f);
    key(f, 2, "schema_version"); /* the log's column names: cochlea/log_schema.py */
    fprintf(f, "%d,\n", sc->schema_version);
    key(f, 2, "scenario");
    json_string(f, sc->name);
    fputs(",\n", f);
    key(f, 2, "scenario_file");
    fprintf(f, "\"compiled in: generated_c/embedded/%s_scenario.c\",\n", sc->name);
    key(f, 2, "robot");
    json_string(f, sc->robot);
    fputs(",\n", f);
    key(f, 2, "space");
    json_string(f, sc->space);
    fputs(",\n", f);
    key(f, 2, "controller");
    json_string(f, sc->controller);
    fputs(",\n", f);
    key(f, 2, "variant");
    json_string(f, sc->variant);
    fputs(",\n", f);
    key(f, 2, "parameterisation");
    json_string(f, sc->parameterisation);
    fputs(",\n", f);
    /* cochlea-run's [control] mirror: the generator refuses "measured" (the followers' desired
     * paths are compiled in, functions of time), so every compiled-in scenario has "desired". */
    key(f, 2, "mirror");
    fputs("\"desired\",\n", f);
    key(f, 2, "program");
    fputs("\"cochlea-embedded (" PRECISION ")\",\n", f);
    /* cochlea-run's statement of the kernels it ran: here, always the C compiled in. */
    key(f, 2, "kernels");
    fputs("{\"used\": \"c\", \"requested\": \"c\", \"library\": \"compiled in: "
          "cochlea-embedded (" PRECISION ")\", \"fallback_reason\": null},\n", f);
    key(f, 2, "rate_Hz");
    json_number(f, 1.0 / loop->period_s);
    fputs(",\n", f);
    key(f, 2, "duration_s");
    json_number(f, (double)rows * loop->period_s);
    fprintf(f, ",\n  \"periods\": %ld,\n", rows);
    key(f, 2, "convergence_rule");
    json_string(f, CONVERGENCE_RULE);
    fputs(",\n", f);
    key(f, 2, "judged_error");
    json_string(f, "measured");
    fputs(",\n", f);
    key(f, 2, "logged_state");
    json_string(f, LOGGED_STATE);
    fputs(",\n", f);
    /* "converged" needs the units: written last-but-known, so leave room and come back. */
    key(f, 2, "converged");
    pos = ftell(f);
    fputs("false,\n", f);
    fputs("  \"diverged\": {},\n", f);
    key(f, 2, "stop");
    fputs("{\n", f);
    key(f, 4, "rule");
    json_string(f, cochlea_rule_name(loop->stop.rule));
    fputs(",\n", f);
    key(f, 4, "time_s");
    json_number(f, stop_time_s(loop));
    fputs(",\n", f);
    key(f, 4, "detail");
    json_string(f, facts->detail);
    fprintf(f, ",\n    \"exit_code\": %d\n  },\n", cochlea_exit_code(loop->stop.rule));
    fputs("  \"supervisor\": null,\n", f);
    key(f, 2, "timing");
    timing_summary(f, loop, st, facts, b, o);
    fputs(",\n", f);
    /* The loop thread's settings, asked for and obtained (cochlea-run's RealtimeOptions). */
    key(f, 2, "realtime");
    realtime_summary(f, o);
    fputs(",\n", f);
    key(f, 2, "wall_time_s");
    json_number(f, facts->wall_s);
    fputs(",\n", f);
    key(f, 2, "units");
    fputs("{\n", f);
    for (u = 0; u < sc->n_units; ++u) {
        double res[COCHLEA_MAX_ERRORS];
        const int known = measurement_resolution(sc, u, st, loop->period_s, res);
        converged = unit_summary(f, sc, u, st, known ? res : 0) && converged;
    }
    fputs("  }\n}\n", f);
    converged = converged && loop->stop.rule == COCHLEA_COMPLETED;
    if (converged && pos >= 0 && fseek(f, pos, SEEK_SET) == 0) {
        fputs("true, ", f); /* "false," and "true, " have the same length */
    }
    *converged_out = converged;
    return finish_atomic(f, out, "summary.json");
}

/* ---- signals and real-time settings --------------------------------------------------------- */

static cochlea_loop the_loop;

/* SIGINT: the user's stop; SIGTERM and SIGHUP (a hang-up): terminated. The first one names
 * the stop. */
static void on_signal(int signum)
{
    if (!interrupted) {
        interrupted = signum;
        the_loop.stop_request = signum == SIGINT ? COCHLEA_USER_STOP : COCHLEA_TERMINATED;
    }
}

/* What apply_realtime asked for, obtained and changed (summary.json's "realtime"). */
typedef struct {
    int locked;                    /* mlockall succeeded */
    int affinity_saved;            /* --cpu applied: the CPUs before, to restore */
    cpu_set_t affinity_before;
    int policy_changed;            /* the policy before, to restore */
    int policy_before;
    struct sched_param param_before;
    int n_problems;
    char problems[3][384];
    const char *policy;            /* obtained: "fifo", "rr", "other" or "unknown" */
    int priority;                  /* obtained */
    char cpus[512];                /* obtained: "0, 1" */
    int cpus_known;                /* the OS said which (else null, as cochlea-run) */
    char scheduling[96];           /* timing.scheduling */
    const char *memory;            /* timing.memory */
} realtime_facts;

static realtime_facts rt;

static void problem(const char *fmt, ...)
{
    va_list args;
    if (rt.n_problems >= 3) {
        return;
    }
    va_start(args, fmt);
    vsnprintf(rt.problems[rt.n_problems++], sizeof rt.problems[0], fmt, args);
    va_end(args);
}

/* The options on the calling thread (and mlockall on the process), as cochlea-run's
 * apply_realtime: a setting the OS refuses (no permission, a locked-memory limit) is a problem,
 * not an error; the run goes on with what it got, and rt says what. */
static void apply_realtime(const options *o)
{
    const int want = policy_value(o->sched), level = priority_level(o);
    struct sched_param p;
    int policy, error;
    memset(&rt, 0, sizeof rt);
    if (o->mlockall) {
        if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) {
            rt.locked = 1;
        } else {
            char limit[96] = "";
            error = errno;
            if (error == ENOMEM || error == EPERM) {
                struct rlimit r;
                if (getrlimit(RLIMIT_MEMLOCK, &r) == 0) {
                    if (r.rlim_cur == RLIM_INFINITY) {
                        snprintf(limit, sizeof limit, "; RLIMIT_MEMLOCK is unlimited");
                    } else {
                        snprintf(limit, sizeof limit, "; RLIMIT_MEMLOCK is %g MiB",
                                 (double)r.rlim_cur / 1048576.0);
                    }
                }
            }
            problem("mlockall failed (%s%s: raise memlock in /etc/security/limits.conf or run "
                    "with CAP_IPC_LOCK)", strerror(error), limit);
        }
    }
    if (o->cpu >= 0) {
        cpu_set_t one;
        const int saved = pthread_getaffinity_np(pthread_self(), sizeof rt.affinity_before,
                                                 &rt.affinity_before) == 0;
        CPU_ZERO(&one);
        CPU_SET(o->cpu, &one);
        error = pthread_setaffinity_np(pthread_self(), sizeof one, &one);
        if (error != 0) {
            problem("CPU affinity %d refused (%s)", o->cpu, strerror(error));
        } else {
            rt.affinity_saved = saved;
        }
    }
    if (pthread_getschedparam(pthread_self(), &policy, &p) == 0) {
        if (policy != want || p.sched_priority != level) {
            struct sched_param asked;
            memset(&asked, 0, sizeof asked);
            asked.sched_priority = level;
            error = pthread_setschedparam(pthread_self(), want, &asked);
            if (error == 0) {
                rt.policy_changed = 1;
                rt.policy_before = policy;
                rt.param_before = p;
            } else {
                problem("%s %d not permitted (%s: run as root, with CAP_SYS_NICE or an rtprio "
                        "limit)", policy_of(o->sched), level, strerror(error));
            }
        }
    }
    rt.policy = "unknown";
    if (pthread_getschedparam(pthread_self(), &policy, &p) == 0) {
        rt.policy = policy == SCHED_FIFO ? "fifo" : policy == SCHED_RR ? "rr"
                    : policy == SCHED_OTHER ? "other" : "unknown";
        rt.priority = p.sched_priority;
    }
    rt.cpus_known = strcmp(cpu_list(rt.cpus, sizeof rt.cpus), "unknown") != 0;
    if (strcmp(rt.policy, "fifo") == 0 || strcmp(rt.policy, "rr") == 0) {
        snprintf(rt.scheduling, sizeof rt.scheduling, "%s %d", policy_of(rt.policy),
                 rt.priority);
    } else if (strcmp(o->sched, "other") != 0) {
        snprintf(rt.scheduling, sizeof rt.scheduling, "normal (%s not permitted)",
                 policy_of(o->sched));
    } else {
        snprintf(rt.scheduling, sizeof rt.scheduling, "normal");
    }
    rt.memory = rt.locked ? "locked" : o->mlockall ? "not locked (mlockall not permitted)"
                                                   : "not locked";
    if (rt.n_problems) { /* once, before the start: the run goes on with what it got */
        int i;
        fputs("cochlea-embedded: warning: real-time settings not all obtained: ", stderr);
        for (i = 0; i < rt.n_problems; ++i) {
            fprintf(stderr, "%s%s", i ? "; " : "", rt.problems[i]);
        }
        fprintf(stderr, "; running %s, memory %s, CPUs %s\n", rt.scheduling,
                rt.locked ? "locked" : "not locked", rt.cpus);
    }
}

/* What apply_realtime changed, undone: the report runs as a normal thread. */
static void undo_realtime(void)
{
    if (rt.policy_changed) {
        (void)pthread_setschedparam(pthread_self(), rt.policy_before, &rt.param_before);
        rt.policy_changed = 0;
    }
    if (rt.affinity_saved) {
        (void)pthread_setaffinity_np(pthread_self(), sizeof rt.affinity_before,
                                     &rt.affinity_before);
        rt.affinity_saved = 0;
    }
    if (rt.locked) {
        munlockall();
    }
}

/* summary.json's "realtime": the loop thread's settings, asked for and obtained. */
static void realtime_summary(FILE *f, const options *o)
{
    int i;
    fputs("{\n    \"requested\": {\"mlockall\": ", f);
    fputs(o->mlockall ? "true" : "false", f);
    if (o->cpu >= 0) {
        fprintf(f, ", \"cpu\": %d", o->cpu);
    } else {
        fputs(", \"cpu\": null", f);
    }
    fprintf(f, ", \"policy\": \"%s\", \"priority\": %d},\n", o->sched, priority_level(o));
    fprintf(f, "    \"obtained\": {\"mlockall\": %s, \"cpu\": %s%s%s, \"policy\": \"%s\", "
            "\"priority\": %d},\n", rt.locked ? "true" : "false", rt.cpus_known ? "[" : "",
            rt.cpus_known ? rt.cpus : "null", rt.cpus_known ? "]" : "", rt.policy, rt.priority);
    fputs("    \"problems\": [", f);
    for (i = 0; i < rt.n_problems; ++i) {
        fputs(i ? ", " : "", f);
        json_string(f, rt.problems[i]);
    }
    fputs("]\n  }", f);
}

/* The writer thread, with a small stack: locked memory (mlockall) makes the default 8 MiB
 * resident, most of the program's, for a thread that only calls fwrite. */
static int start_writer(pthread_t *thread, run_log *log)
{
    pthread_attr_t attr;
    int failed;
    if (pthread_attr_init(&attr) != 0) {
        return -1;
    }
    (void)pthread_attr_setstacksize(&attr, WRITER_STACK_BYTES); /* else the default */
    failed = pthread_create(thread, &attr, writer, log);
    pthread_attr_destroy(&attr);
    return failed;
}

/* Back to normal priority and unlocked memory; the writer flushes what is left and the log
 * file is closed (a failed close counts as a failed log). */
static void leave_realtime(run_log *log, pthread_t writer_thread)
{
    undo_realtime();
    __atomic_store_n(&log->finished, 1, __ATOMIC_RELEASE);
    pthread_join(writer_thread, 0);
    if (fclose(log->file) != 0 && !log->failed) {
        log_failed(log, errno);
    }
}

/* The whole rows log.bin holds once closed (at most the loop's), with a partial last row (a
 * write cut short by a full disk) cut off, so log.bin stays rows of row_length. */
static long rows_kept(const char *out, const run_log *log, long logged)
{
    char path[4352];
    struct stat st;
    const off_t row_bytes = (off_t)sizeof(double) * (off_t)log->row_length;
    long rows;
    snprintf(path, sizeof path, "%s/log.bin", out);
    if (stat(path, &st) != 0) {
        return 0;
    }
    rows = (long)(st.st_size / row_bytes);
    rows = rows < logged ? rows : logged;
    if (st.st_size != (off_t)rows * row_bytes) {
        (void)truncate(path, (off_t)rows * row_bytes);
    }
    return rows;
}

#ifdef COCHLEA_TEST_HOOKS
/* Test builds only: COCHLEA_TEST_SLOW_READS="FIRST:COUNT:MS" makes the reads of periods
 * FIRST..FIRST+COUNT-1 (COUNT -1: every one from FIRST on) take MS milliseconds more, so the
 * overrun rule can be driven through the real program (a stall, or a loop slower than its
 * rate). */
static struct {
    cochlea_backend inner;
    long first, count, k;
    double ms;
} slow;

static int slow_read(void *ctx, double *q, double *qd)
{
    const int ok = slow.inner.read(ctx, q, qd);
    const long k = slow.k++;
    if (k >= slow.first && (slow.count < 0 || k < slow.first + slow.count)) {
        struct timespec t;
        t.tv_sec = (time_t)(slow.ms / 1000.0);
        t.tv_nsec = (long)((slow.ms - 1000.0 * (double)t.tv_sec) * 1e6);
        while (nanosleep(&t, &t) != 0 && errno == EINTR) {
        }
    }
    return ok;
}
#endif

/* ---- main ----------------------------------------------------------------------------------- */

int main(int argc, char **argv)
{
    options o;
    const cochlea_scenario *sc;
    cochlea_posix_port port;
    cochlea_hal hal;
    static cochlea_bridge bridge;
    cochlea_start_report report;
    cochlea_backend backend;
    run_log log;
    run_facts facts;
    pthread_t writer_thread;
    struct sigaction action;
    void *controller;
    double duration, period;
    int n, rule, code, converged = 0, i, loop_error;
    int64_t started, ended;
    long steps;
    char text[512];

    if ((code = parse(argc, argv, &o)) != 0) {
        return code;
    }
    sc = find_scenario(o.scenario);
    if (!sc) {
        fprintf(stderr, "cochlea-embedded: no scenario %s in this program (--list shows them). "
                "Scenarios are compiled in: add a scenario to kernels.toml's [embedded] "
                "scenarios, run cochlea-codegen, then make embedded\n", o.scenario);
        return EXIT_USER_ERROR;
    }
    n = sc->nq;
    period = isnan(o.rate) ? sc->period_s : 1.0 / o.rate;
    duration = isnan(o.duration) ? sc->duration_s : o.duration;
    steps = (long)nearbyint(duration / period);
    if (steps < 1) {
        return fail_usage("--duration %g s is shorter than one period (%g s)", duration, period);
    }
    memset(&log, 0, sizeof log);
    log.row_length = cochlea_loop_row_length(sc);
    if (!folder_is_empty(o.out)) {
        return fail_usage("--out %s exists and is not empty: choose a new folder (runs never "
                          "overwrite a log)", o.out);
    }
    { /* the disk must hold the whole log: refused now rather than a log-failure stop later */
        const double need = (double)steps * (double)log.row_length * 8.0
                            + (double)(steps + 1) * (double)csv_columns(sc) * CSV_VALUE_BYTES
                            + (double)REPORT_MARGIN_BYTES;
        double free_ = free_bytes(o.out);
        char a[32], b[32];
#ifdef COCHLEA_TEST_HOOKS
        if (getenv("COCHLEA_TEST_FREE_BYTES")) {
            free_ = atof(getenv("COCHLEA_TEST_FREE_BYTES"));
        }
#endif
        if (free_ >= 0.0 && need > free_) {
            size_text(a, sizeof a, need);
            size_text(b, sizeof b, free_);
            return fail_usage("--out %s: the run's log needs about %s (log.bin and log.csv, "
                              "%ld periods) but only %s are free on that disk: free some "
                              "space, choose another --out or a shorter --duration", o.out, a,
                              steps, b);
        }
    }
    /* The bridge reads its addresses, sizes and transfers from the drive table (the model
     * data): a table it cannot drive is refused here, before anything opens. It keeps &hal,
     * filled once the port is open. */
    if (cochlea_bridge_init(&bridge, &hal, sc->drives, n, 0, WATCHDOG_S) != 0 ||
        cochlea_bridge_use_realtime_tick(&bridge) != 0) { /* the tick always, as cochlea-run */
        return fail_usage("the drive table of %s does not fit the bridge: %s", sc->name,
                          bridge.config_problem ? bridge.config_problem : "its read frame "
                          "does not fit");
    }
    { /* the bus budget, cochlea/dynamixel/budget.py's, of the transfers the bridge sends */
        /* The write of Goal Current: SYNC_WRITE 14 + 3 n bytes, or BULK_WRITE 10 + 7 n (per
         * motor ID, address, length, 2 bytes); the read's request: 14 + n, or BULK_READ's
         * 10 + 5 n; then a status packet of 11 bytes and the block (Realtime Tick .. Present
         * Position) per motor (SYNC_READ, BULK_READ), or FAST_SYNC_READ's one combined packet
         * of 8 bytes and ERR ID block CRC per motor, after one return delay and turnaround
         * instead of n */
        const double block = (double)bridge.read_length;
        const int fast = bridge.bus->read_instruction == DXL_FAST_SYNC_READ;
        const int bulk_read = bridge.bus->read_instruction == DXL_BULK_READ;
        const int bulk_write = bridge.bus->write_instruction == DXL_BULK_WRITE;
        const double replies = fast ? 8.0 + (block + 4.0) * n : (11.0 + block) * n;
        const double bytes = (bulk_write ? 10.0 + 7.0 * n : 14.0 + 3.0 * n)
                             + (bulk_read ? 10.0 + 5.0 * n : 14.0 + n) + replies;
        facts.budget_bytes = bytes;
        facts.wire_s = bytes * BITS_PER_BYTE / (double)o.baud;
        facts.bus_s = facts.wire_s + (fast ? 1 : n) * TURNAROUND_S;
        facts.cycle_s = facts.bus_s + ADAPTER_LATENCY_S;
        facts.timeout_s = facts.cycle_s + TIMEOUT_MARGIN_S;
        snprintf(text, sizeof text,
                 "bus budget for %d motors at %ld baud: %.0f bytes per period = %.0f us on the "
                 "bus, %.0f us with the adapter's 1 ms latency; the period is %.0f us", n,
                 o.baud, bytes, facts.bus_s * 1e6, facts.cycle_s * 1e6, period * 1e6);
        if (facts.bus_s > period) {
            return fail_usage("%s: the bus cannot meet the loop rate; use a higher baud rate "
                              "(4 Mbaud) or a lower rate (--rate)", text);
        }
        if (facts.cycle_s > period) {
            fprintf(stderr, "cochlea-embedded: warning: %s: the bus fits but the adapter's "
                    "latency does not, so periods will overrun now and then\n", text);
        }
    }
    if (sc->nd > 64) {
        return fail_usage("the scenario %s tracks %d coordinates, more than this program's 64",
                          sc->name, sc->nd);
    }
#ifdef COCHLEA_TEST_HOOKS
    log.fail_after = getenv("COCHLEA_TEST_LOG_FAIL_AFTER")
                         ? atol(getenv("COCHLEA_TEST_LOG_FAIL_AFTER")) : -1;
    log.stall_after = getenv("COCHLEA_TEST_LOG_STALL_AFTER")
                          ? atol(getenv("COCHLEA_TEST_LOG_STALL_AFTER")) : -1;
#endif
    /* The ring, touched now so that no period takes a page fault in it (mlockall, when
     * permitted, would too). A short run needs no more rows than it has. */
    log.period_s = period;
    log.ring_rows = (long)ceil(RING_SECONDS / period - 1e-9); /* 4 / 0.001 is 4000 */
    log.ring_rows = log.ring_rows < steps ? log.ring_rows : steps;
    log.ring = malloc(sizeof(double) * (size_t)log.ring_rows * (size_t)log.row_length);
    controller = malloc(sc->state_size);
    if (!log.ring || !controller) {
        return fail_usage("not enough memory for the log's ring (%g s of periods)",
                          RING_SECONDS);
    }
    memset(log.ring, 0, sizeof(double) * (size_t)log.ring_rows * (size_t)log.row_length);
    /* The slider's homing record, checked before anything is created or opened (the bridge
     * checks its token after the PINGs, before any write). */
    {
        static char why[9000]; /* two paths of up to 4 KiB */
        if (check_homing(&o, sc, why, sizeof why) != 0) {
            fprintf(stderr, "cochlea-embedded: the backend could not start, nothing moved: "
                    "%s\n", why);
            return COCHLEA_EXIT_BACKEND;
        }
    }
    if (make_folders(o.out) != 0) {
        const int error = errno;
        undo_start(o.out);
        return fail_usage("cannot create --out %s: %s", o.out, strerror(error));
    }
    if (write_columns(o.out, sc, log.row_length) != 0
        || !(log.file = open_in(o.out, "log.bin", "wb"))) {
        const int error = errno;
        undo_start(o.out);
        return fail_usage("cannot write to %s: %s", o.out, strerror(error));
    }

    /* Signals first: a Ctrl-C during the start-up still ends in the safe stop. */
    memset(&action, 0, sizeof action);
    action.sa_handler = on_signal;
    sigemptyset(&action.sa_mask);
    sigaction(SIGINT, &action, 0);
    sigaction(SIGTERM, &action, 0);
    sigaction(SIGHUP, &action, 0);
    /* A reader that went away (a closed pipe, ssh's end of a closed session) fails a write
     * with EPIPE instead of killing the program between the motors' start and their stop. */
    action.sa_handler = SIG_IGN;
    sigaction(SIGPIPE, &action, 0);

    printf("cochlea-embedded: %s (controller %s, %s variant), Dynamixel motors on %s, real time "
           "at %g Hz, %s precision -> %s\n", sc->name, sc->controller, sc->variant, o.port,
           1.0 / period, PRECISION, o.out);
    printf("cochlea-embedded: bus: %s + %s per period (%s)\n",
           cochlea_instruction_name(bridge.bus->read_instruction),
           cochlea_instruction_name(bridge.bus->write_instruction), bridge.bus->read_choice);
    fflush(stdout);
    if (cochlea_posix_open(&port, o.port, o.baud) != 0) {
        const int socket_port = strncmp(o.port, "unix:", 5) == 0
                                || strncmp(o.port, "socket://", 9) == 0;
        fprintf(stderr, "cochlea-embedded: the backend could not start, nothing moved: cannot "
                "%s %s: %s\n", socket_port ? "connect to the socket" : "open the serial port",
                o.port, strerror(errno));
        undo_start(o.out);
        return COCHLEA_EXIT_BACKEND;
    }
    cochlea_posix_hal(&hal, &port);
    bridge.timeout_ns = (int64_t)nearbyint(facts.timeout_s * 1e9);
    facts.watchdog_s = bridge.watchdog_lsb * 0.02;
    /* Friction compensated once: by the bridge's offset current or by the controller. */
    bridge.offset_current = sc->bridge_offset_current;
    if (homing.drive >= 0) {
        cochlea_bridge_expect_homing(&bridge, homing.drive, homing.marker, homing.offset);
    }
    backend = cochlea_bridge_backend(&bridge);
#ifdef COCHLEA_TEST_HOOKS
    if (getenv("COCHLEA_TEST_SLOW_READS")
        && sscanf(getenv("COCHLEA_TEST_SLOW_READS"), "%ld:%ld:%lf", &slow.first, &slow.count,
                  &slow.ms) == 3) {
        slow.inner = backend;
        slow.k = 0;
        backend.read = slow_read;
    }
#endif
    /* The controller before the motors: a configuration it refuses moves nothing. */
    loop_error = cochlea_loop_init(&the_loop, sc, &hal, &backend, controller, period, duration,
                                   o.watchdog_misses, o.watchdog_errors, 1);
    if (loop_error != COCHLEA_LOOP_OK) {
        cochlea_posix_close(&port);
        undo_start(o.out);
        return fail_usage("the loop refused the scenario (error %d)", loop_error);
    }
    the_loop.on_row = log_row;
    the_loop.log_ready = log_ready;
    the_loop.row_ctx = &log;

    /* Everything the run needs is ready before the motors' torque goes on, so the first period
     * follows it at once: the writer (started before the real-time priority, so it does not
     * inherit it), the locked memory and the priority. */
    if (start_writer(&writer_thread, &log) != 0) {
        cochlea_posix_close(&port);
        undo_start(o.out);
        return fail_usage("cannot start the log writer");
    }
    apply_realtime(&o);
    facts.scheduling = rt.scheduling;
    facts.memory = rt.memory;
    bridge.expected_start = sc->initial_q;
    bridge.start_tolerance[0] = o.start_tolerance_deg * M_PI / 180.0;
    bridge.start_tolerance[1] = o.start_tolerance_mm * 1e-3;
    if (!cochlea_bridge_start(&bridge, &report)) {
        leave_realtime(&log, writer_thread);
        start_failure(text, sizeof text, &bridge, &report, &o);
        fprintf(stderr, "cochlea-embedded: the backend could not start, nothing moved: %s\n",
                text);
        cochlea_posix_close(&port);
        undo_start(o.out);
        return COCHLEA_EXIT_BACKEND;
    }
    if (interrupted) {
        cochlea_bridge_stop(&bridge);
        leave_realtime(&log, writer_thread);
        cochlea_posix_close(&port);
        undo_start(o.out);
        fprintf(stderr, "cochlea-embedded: %s before the run started; drives disabled, "
                "nothing moved\n", interrupted == SIGTERM ? "terminated"
                : interrupted == SIGHUP ? "hung up (SIGHUP)" : "interrupted");
        return interrupted == SIGTERM ? EXIT_TERMINATED
               : interrupted == SIGHUP ? EXIT_HUNG_UP : EXIT_INTERRUPTED;
    }
    started = hal.now_ns(hal.ctx);
    rule = cochlea_loop_run(&the_loop); /* ends with the motors' safe stop, always */
    ended = hal.now_ns(hal.ctx);
    leave_realtime(&log, writer_thread);
    cochlea_posix_close(&port);
    facts.wall_s = (double)(ended - started) * 1e-9;

    /* The reports, from the rows log.bin holds. */
    {
        static log_stats stats;
        const long logged = the_loop.rows;
        const long kept = rows_kept(o.out, &log, logged);
        int report_error = 0, csv_written = 0, summary_written = 0;
        FILE *csv;
        size_t used;
        /* the loop's last row is the stop's own */
        stop_detail(facts.detail, sizeof facts.detail, &the_loop, the_loop.row);
        if (rule == COCHLEA_LOG_FAILURE || log.failed || log.overrun || kept < logged) {
            /* A log lost at the end (the last flush, the close) is a log failure too, as in
             * cochlea-run; the rule the run ended by, if another, is kept in the detail. */
            char before[sizeof facts.detail], what[512];
            snprintf(before, sizeof before, "%s", facts.detail);
            if (log.failed) {
                snprintf(what, sizeof what, "the log writer failed: %s (%s/log.bin)",
                         strerror(log.error), o.out);
            } else if (log.overrun || rule != COCHLEA_LOG_FAILURE) {
                snprintf(what, sizeof what, "the log writer lost rows");
            } else {
                snprintf(what, sizeof what, "the log writer fell %ld periods (%g s) behind the "
                         "loop", log.ring_rows, (double)log.ring_rows * period);
            }
            snprintf(facts.detail, sizeof facts.detail, "%s; log.bin holds the first %ld of %ld "
                     "periods: free the disk or choose another --out", what, kept, logged);
            if (rule != COCHLEA_LOG_FAILURE && rule != COCHLEA_COMPLETED) {
                const size_t at = strlen(facts.detail);
                snprintf(facts.detail + at, sizeof facts.detail - at, " (the run had ended by "
                         "rule %s%s%s)", cochlea_rule_name(rule), before[0] ? ": " : "", before);
            }
            rule = the_loop.stop.rule = COCHLEA_LOG_FAILURE;
        }
        if (bridge.last_failure < 0) {
            snprintf(facts.last_failure, sizeof facts.last_failure, "no failure");
        } else {
            int slot = -1;
            for (i = 0; i < bridge.n; ++i) {
                if (bridge.drives[i].id == bridge.last_failure_id) {
                    slot = i;
                }
            }
            if (slot >= 0) {
                snprintf(facts.last_failure, sizeof facts.last_failure, "%s (ID %d, %s)",
                         cochlea_failure_name(bridge.last_failure), bridge.last_failure_id,
                         bridge.drives[slot].name);
            } else {
                snprintf(facts.last_failure, sizeof facts.last_failure, "%s",
                         cochlea_failure_name(bridge.last_failure));
            }
        }
        if (bridge.confirmed_off == bridge.n) {
            used = (size_t)snprintf(facts.shutdown, sizeof facts.shutdown,
                                    "goal current 0 and torque off sent; torque off confirmed "
                                    "by all %d", bridge.n);
        } else {
            used = (size_t)snprintf(facts.shutdown, sizeof facts.shutdown,
                                    "goal current 0 and torque off sent; not confirmed by ");
            for (i = 0, code = 0; i < bridge.n && used < sizeof facts.shutdown; ++i) {
                if (!bridge.off_confirmed[i]) {
                    who(text, sizeof text, &bridge.drives[i]);
                    used += (size_t)snprintf(facts.shutdown + used, sizeof facts.shutdown - used,
                                             "%s%s", code++ ? ", " : "", text);
                }
            }
            if (used < sizeof facts.shutdown) {
                used += (size_t)snprintf(facts.shutdown + used, sizeof facts.shutdown - used,
                                         " (its Bus Watchdog, %.0f ms, stops it)",
                                         facts.watchdog_s * 1e3);
            }
        }
        if (bridge.alert_id >= 0) {
            const cochlea_drive *d = 0;
            static const char *const bits[8] = {"input voltage", 0, "overheating",
                                                "motor encoder", "electrical shock", "overload",
                                                0, 0};
            char what[128] = "";
            for (i = 0; i < bridge.n; ++i) {
                if (bridge.drives[i].id == bridge.alert_id) {
                    d = &bridge.drives[i];
                }
            }
            if (bridge.alert_status < 0) {
                snprintf(what, sizeof what, "Hardware Error Status unreadable");
            } else {
                size_t w = 0;
                int bit;
                for (bit = 0; bit < 8; ++bit) {
                    if ((bridge.alert_status >> bit & 1) && bits[bit] && w < sizeof what) {
                        w += (size_t)snprintf(what + w, sizeof what - w, "%s%s", w ? ", " : "",
                                              bits[bit]);
                    }
                }
                if (w == 0) {
                    snprintf(what, sizeof what, bridge.alert_status ? "0x%02X" : "none",
                             (unsigned)bridge.alert_status);
                }
            }
            if (d) {
                who(text, sizeof text, d);
                if (used < sizeof facts.shutdown) {
                    snprintf(facts.shutdown + used, sizeof facts.shutdown - used,
                             "; %s: hardware error (%s)", text, what);
                }
                /* The stop line names the motor and its alert, as cochlea-run's does. */
                if (the_loop.stop.rule == COCHLEA_WATCHDOG && the_loop.stop.reason == 1) {
                    const size_t at = strlen(facts.detail);
                    snprintf(facts.detail + at, sizeof facts.detail - at,
                             ": %s: hardware error (%s)", text, what);
                }
            }
        } else if (the_loop.stop.rule == COCHLEA_WATCHDOG && the_loop.stop.reason == 1
                   && bridge.last_failure >= 0) {
            const size_t at = strlen(facts.detail);
            snprintf(facts.detail + at, sizeof facts.detail - at, ": last failure %s",
                     cochlea_failure_name(bridge.last_failure));
            for (i = 0; i < bridge.n; ++i) {
                if (bridge.drives[i].id == bridge.last_failure_id) {
                    const size_t end = strlen(facts.detail);
                    who(text, sizeof text, &bridge.drives[i]);
                    snprintf(facts.detail + end, sizeof facts.detail - end, " from %s", text);
                }
            }
        }
        /* log.csv as log.bin is read back; summary.json last, from what was read. */
        errno = 0;
        csv = open_in(o.out, ".log.csv.tmp", "w");
        if (!csv) {
            report_error = errno;
        } else {
            csv_header(csv, sc);
        }
        if (read_back(o.out, sc, log.row_length, kept, log.ring, log.ring_rows, csv, &stats)
            != 0) {
            report_error = report_error ? report_error : (errno ? errno : EIO);
            (void)read_back(o.out, sc, log.row_length, 0, log.ring, log.ring_rows, 0, &stats);
            if (csv) { /* part of log.csv: removed, never renamed into place as if whole */
                char tmp[4352];
                fclose(csv);
                csv = 0;
                snprintf(tmp, sizeof tmp, "%s/.log.csv.tmp", o.out);
                unlink(tmp);
            }
        }
        if (csv) {
            if (finish_atomic(csv, o.out, "log.csv") == 0) {
                csv_written = 1;
            } else if (!report_error) {
                report_error = errno ? errno : EIO;
            }
        }
        errno = 0;
        if (write_summary(o.out, &the_loop, &stats, &facts, &bridge, &o, &converged) == 0) {
            summary_written = 1;
        } else if (!report_error) {
            report_error = errno ? errno : EIO;
        }
        if (report_error) {
            fprintf(stderr, "cochlea-embedded: writing the report to %s failed: %s (log.bin "
                    "keeps what was written; %s)\n", o.out, strerror(report_error),
                    csv_written ? (summary_written ? "log.csv and summary.json written"
                                   : "log.csv written, summary.json not")
                    : summary_written ? "summary.json written, log.csv not"
                    : "neither log.csv nor summary.json was written");
        }
        printf("  ran %.2f s in %.2f s (%.1fx real time)\n", (double)logged * period,
               facts.wall_s,
               (double)logged * period / (facts.wall_s > 1e-9 ? facts.wall_s : 1e-9));
        /* Only the files that were written are named. */
        printf("  converged: %s\n", converged ? "yes" : "no");
        if (csv_written) {
            printf("  log: %s/log.csv\n", o.out);
        } else {
            printf("  log: log.csv not written (log.bin keeps the rows written)\n");
        }
        if (summary_written) {
            printf("  summary: %s/summary.json\n", o.out);
        } else {
            printf("  summary: summary.json not written\n");
        }
        printf("  bus: %.0f bytes per period, budget %.0f us; %u of %u reads good; shut-down: "
               "%s\n", facts.budget_bytes, facts.bus_s * 1e6, bridge.good_reads, bridge.reads,
               facts.shutdown);
        printf("  timing: deadline misses %u, overruns %u, lateness max %.3f ms; %s; memory "
               "%s\n", the_loop.deadline_misses, the_loop.overruns,
               (double)the_loop.lateness_max_ns * 1e-6, facts.scheduling, facts.memory);
        fflush(stdout);
    }
    free(log.ring);
    free(controller);
    if (rule == COCHLEA_COMPLETED) {
        return 0;
    }
    if (rule == COCHLEA_USER_STOP) {
        fprintf(stderr, "cochlea-embedded: stopped by the user at t = %.3f s; zero effort "
                "commanded, drives disabled, log complete\n", stop_time_s(&the_loop));
    } else {
        /* A failed log is the one stop whose log is not whole: the detail says how much is. */
        fprintf(stderr, "cochlea-embedded: stopped by rule %s at t = %.3f s: %s; zero effort "
                "commanded, drives disabled, %s\n", cochlea_rule_name(rule),
                stop_time_s(&the_loop), facts.detail,
                rule == COCHLEA_LOG_FAILURE ? "log kept up to the failure" : "log complete");
    }
    return cochlea_exit_code(rule);
}
