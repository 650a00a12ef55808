"""Does the virtual chain keep up? ``cochlea-emulator``'s per-period work and the 1 kHz loops'
deadline misses against it, for this tree's emulator and a baseline revision's, in one run
(issue 30, item 2).

Measurements per emulator version (the versions take turns, so the machine's load hits both
alike):

* **micro**: one period's requests (a SYNC_WRITE of Goal Current to every motor, then a
  SYNC_READ of 120..135: what ``cochlea-run --backend dynamixel`` sends) written to the chain's
  pseudo-terminal, and the chain's own work on them timed in-process (``_receive`` + ``_flush``:
  read, parse, plant up to the arrival, replies built and written), median and p90 in us, and
  the system calls the chain makes per period (``os.read``/``os.write`` counted).
* **hil**: ``cochlea-emulator`` (its default SCHED_FIFO 30) and a 1 kHz loop on its
  pseudo-terminal for ``--duration`` s (serial_joint): ``cochlea-run --backend dynamixel`` and
  ``build/cochlea-embedded`` (when built), with ``--hogs`` busy Python processes beside them
  (one per core by default: a ``make test-fast``-like load). Reported: the loop's deadline-miss
  fraction, its failed reads (timeouts), its stop rule.
* **pty floor** (once, with the hogs): a period's bytes to and fro between two processes under
  SCHED_FIFO that do nothing else, at 1 kHz: what the pseudo-terminal alone costs, the floor
  no emulator can beat (the kernel moves a pseudo-terminal's bytes in worker threads of
  ordinary priority); the same over a Unix-domain socket pair (**socket floor**), whose bytes
  the writer's own system call delivers.
* **transports** (``--transports``, default ``pty,unix``): the hil runs of this tree's emulator
  on its pseudo-terminal and on a socket (``cochlea-emulator --listen unix:PATH`` or
  ``socket://127.0.0.1:0``); the baseline's on the pseudo-terminal only.

The baseline (``--baseline REV``, default ``main``; ``none``: this tree alone) is that
revision's package (``cochlea/`` and its data) exported with ``git archive`` into the output
folder, its plant on this tree's ``build/libcochlea.so`` (an export has no build);
``--baseline python`` is this tree with the C lane switched off at both ends
(``COCHLEA_EMULATOR_LANE=0``: the emulator's period requests and the bridge's SYNC_READ replies
in Python), on every transport. The loops are always this tree's. Nothing is written outside
``--out`` (default: a new temporary folder, printed). Run
by hand, not a test:
``python bench/emulator_speed.py --out /tmp/emuspeed`` (numbers in docs/dynamixel.md, "Does
the virtual chain keep up").

Exit codes: 0 measured; 2 a bad option (one line); 3 a run could not be made (one line).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MICRO = r"""
import gc, json, os, select, sys, time, tty
from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.emulator import VirtualChain
robot, periods = sys.argv[1], int(sys.argv[2])
chain = VirtualChain(robot, robot + "_joint_realistic")
fd = os.open(chain.open(), os.O_RDWR | os.O_NOCTTY)
tty.setraw(fd)
ids = [m.id for m in chain.motors]
def serve_once():
    chain._receive(); chain._flush(float("inf"))
for frame in [proto.write(i, 11, bytes([0])) for i in ids] + \
        [proto.write(i, 64, bytes([1])) for i in ids]:  # current control, torque on
    os.write(fd, frame); time.sleep(0.002); serve_once(); os.read(fd, 4096)
period = proto.sync_write(102, 2, [(i, proto.le(5, 2)) for i in ids]) + \
    proto.sync_read(120, 16, ids)
reply = 11 + 16  # bytes of one motor's status packet: 11 + its 16 data (no stuffing here)
calls = {"read": 0, "write": 0}
real_read, real_write = os.read, os.write
def counted_read(f, n):
    if f == chain.master: calls["read"] += 1
    return real_read(f, n)
def counted_write(f, b):
    if f == chain.master: calls["write"] += 1
    return real_write(f, b)
gc.disable()
times, cpus = [], []
for k in range(periods + 200):
    real_write(fd, period)
    if k == 200:
        os.read, os.write = counted_read, counted_write
    d, cpu, got = 0.0, 0.0, b""
    while len(got) < len(ids) * reply:  # the request may reach the chain in pieces
        ready = select.select([chain.master, fd], [], [], 1.0)[0]
        if not ready:
            raise SystemExit("no reply in 1 s")
        if chain.master in ready:
            t, c = time.perf_counter(), time.thread_time()
            serve_once()
            d += time.perf_counter() - t
            cpu += time.thread_time() - c
        if fd in ready:
            got += real_read(fd, 4096)
    if k >= 200:
        times.append(d)
        cpus.append(cpu)
os.read, os.write = real_read, real_write
print(json.dumps({"times": times, "cpus": cpus, "reads": calls["read"],
                  "writes": calls["write"], "periods": periods}))
"""


def hog() -> None:
    while True:
        pass


def _echo(master: int, reply: int) -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(30))  # as the emulator
    except (AttributeError, PermissionError, OSError):
        pass
    while True:
        select.select([master], [], [])
        if os.read(master, 4096) == b"q":
            return
        os.write(master, b"x" * reply)


def pty_floor(periods: int, request: int = 20 + 29, reply: int = 6 * 27,
              transport: str = "pty") -> dict:
    """The pseudo-terminal alone: a 1 kHz round trip of a period's bytes (the loop's SYNC_WRITE
    and SYNC_READ, six replies) between two processes under SCHED_FIFO (40 and 30, as the loop
    and the emulator) that do no other work: the floor that no emulator can beat. The kernel
    passes a pseudo-terminal's bytes on in its own worker threads (ordinary priority), so a
    loaded machine delays them whatever the two ends' priority. ``transport="unix"``: the same
    over a Unix-domain socket pair (delivered in the writer's own system call)."""
    import socket
    import tty

    if transport == "pty":
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
    else:
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        master, slave = a.detach(), b.detach()
    echo = multiprocessing.Process(target=_echo, args=(master, reply), daemon=True)
    echo.start()
    rtts, lost = [], 0
    old = None
    try:
        old = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
    except (AttributeError, PermissionError, OSError):
        old = None
    try:
        for _ in range(periods):
            t = time.perf_counter()
            os.write(slave, b"y" * request)
            got = 0
            while got < reply:
                if not select.select([slave], [], [], 0.05)[0]:
                    lost += 1
                    break
                got += len(os.read(slave, 4096))
            rtts.append(time.perf_counter() - t)
            time.sleep(max(0.0, 0.001 - (time.perf_counter() - t)))
    finally:
        if old is not None:
            os.sched_setscheduler(0, old[0], old[1])
        os.write(slave, b"q")
        echo.join(timeout=5)
        os.close(master)
        os.close(slave)
    rtts.sort()
    n = len(rtts)
    return {"median_us": rtts[n // 2] * 1e6, "p99_us": rtts[int(0.99 * n)] * 1e6,
            "max_ms": rtts[-1] * 1e3, "over_1ms_fraction": sum(r > 1e-3 for r in rtts) / n,
            "lost": lost}


def export(rev: str, folder: Path) -> Path:
    """``rev``'s package, as a checkout (``cochlea/``, ``models/``, ``codegen/``,
    ``generated_c/``: the package finds its data beside it), under ``folder`` (PYTHONPATH)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "cochlea", "models",
                              "codegen", "generated_c"], capture_output=True)
    if archive.returncode != 0:
        raise RuntimeError(f"--baseline {rev}: git archive failed: "
                           f"{archive.stderr.decode().strip()}")
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return folder


def micro_stats(raw: dict) -> dict:
    times, cpus = sorted(raw["times"]), sorted(raw["cpus"])
    n = len(times)
    return {"median_us": times[n // 2] * 1e6, "cpu_median_us": cpus[n // 2] * 1e6,
            "p90_us": times[int(0.9 * n)] * 1e6, "p99_us": times[int(0.99 * n)] * 1e6,
            "reads_per_period": raw["reads"] / raw["periods"],
            "writes_per_period": raw["writes"] / raw["periods"], "periods": n}


def cpu_seconds(pid: int) -> float:
    """User + system processor time of process ``pid`` so far (Linux /proc), seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


#: ``--baseline python``: this tree with the emulator's C lane switched off (its period
#: requests answered in Python, cochlea/dynamixel/lane.py).
PYTHON_PATH_BASELINE = "python"


def env_for(tree: Path, lane: bool = True) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{tree}{os.pathsep}{ROOT}"}
    if tree != ROOT:  # an exported revision has no build/: the plant on this tree's kernels
        env["COCHLEA_LIB"] = str(ROOT / "build" / "libcochlea.so")
    if not lane:
        env["COCHLEA_EMULATOR_LANE"] = "0"
    return env


def micro(tree: Path, robot: str, periods: int, lane: bool = True) -> dict:
    done = subprocess.run([sys.executable, "-c", MICRO, robot, str(periods)],
                          env=env_for(tree, lane),
                          capture_output=True, text=True, timeout=120, cwd=tree)
    if done.returncode != 0:
        raise RuntimeError(f"micro ({tree}): {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout)


#: ``--transports``: the emulator's ``--listen`` for each (the pseudo-terminal: none).
LISTEN = {"pty": None, "unix": "unix:{out}/chain.sock", "tcp": "socket://127.0.0.1:0"}


def hil(tree: Path, loop: str, out: Path, duration: float, program: Path,
        transport: str = "pty", lane: bool = True) -> dict:
    """One run of ``loop`` (``python`` or ``c``) against the emulator of ``tree``, on its
    pseudo-terminal or a socket (``transport``: a key of :data:`LISTEN`)."""
    log = out / "emulator.log"
    listen = LISTEN[transport]
    emu = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                            "serial", "--scenario", "serial_joint", "--log", str(log),
                            *(() if listen is None else ("--listen", listen.format(out=out)))],
                           env=env_for(tree, lane), cwd=out, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        port = emu.stdout.readline().strip()
        if not port.startswith(("/dev/", "unix:", "socket://")):
            raise RuntimeError(f"the emulator did not start: {emu.stderr.read().strip()}")
        time.sleep(2.0)  # as tests/test_embedded_program.py: the emulator settles
        cpu_before = cpu_seconds(emu.pid)
        run_out = out / "run"
        # Deadline misses do not stop a run (their count is the result); failed reads do, as
        # by default (cochlea-run has no --watchdog-errors: 6 in a row stop it).
        common = ["--port", port, "--duration", str(duration), "--out", str(run_out),
                  "--watchdog-misses", "500"]
        if loop == "python":
            cmd = [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial",
                   "--space", "joint", "--backend", "dynamixel", *common]
        else:
            cmd = [str(program), "--scenario", "serial_joint", *common]
        done = subprocess.run(cmd, env=env_for(ROOT, lane), cwd=out, capture_output=True,
                              text=True, timeout=duration + 120)
        emulator_cpu = cpu_seconds(emu.pid) - cpu_before
    finally:
        emu.terminate()
        emu.communicate(timeout=20)
    try:
        summary = json.loads((run_out / "summary.json").read_text())
    except (OSError, ValueError):
        raise RuntimeError(f"{loop} run: no summary (exit {done.returncode}): "
                           f"{done.stderr.strip()[-300:]}") from None
    timing = summary["timing"]
    bus = timing["bus"]
    return {"stop": summary["stop"]["rule"], "periods": summary["periods"],
            "deadline_miss_fraction": timing["deadline_miss_fraction"],
            "lateness_max_ms": timing.get("lateness_max", float("nan")) * 1e3,
            "failed_reads": bus["reads"] - bus["good_reads"],
            # The emulator's processor time while the loop ran (its start-up and the loop's
            # own start-up included: an upper bound), per period of the run.
            "emulator_cpu_us_per_period": emulator_cpu / max(summary["periods"], 1) * 1e6,
            "failures": bus.get("failures", {})}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2, as every other bad option
        self.exit(2, f"emulator_speed: {message}\n")


def main(argv: list[str] | None = None) -> int:
    p = _Parser(description=__doc__.split("\n\n")[0])
    p.add_argument("--baseline", default="main",
                   help="git revision to compare with (main); 'python': this tree with the "
                        "emulator's C lane off; 'none': this tree alone")
    p.add_argument("--duration", type=float, default=20.0, help="seconds per HIL run (20)")
    p.add_argument("--hogs", type=int, default=os.cpu_count() or 2,
                   help="busy processes beside the runs (default: one per core)")
    p.add_argument("--periods", type=int, default=3000,
                   help="micro: periods timed per version (3000)")
    p.add_argument("--rounds", type=int, default=4,
                   help="micro: the versions take this many turns each (4)")
    p.add_argument("--loops", default="python,c", help="python, c or both (python,c)")
    p.add_argument("--transports", default="pty,unix",
                   help="the emulator's line for this tree's hil runs: pty, unix, tcp "
                        "(pty,unix; the baseline's: pty)")
    p.add_argument("--program", type=Path, default=ROOT / "build" / "cochlea-embedded",
                   help="the C program (default build/cochlea-embedded)")
    p.add_argument("--out", type=Path, help="output folder (default: a new temporary one)")
    args = p.parse_args(argv)
    loops = [x for x in args.loops.split(",") if x]
    transports = [x for x in args.transports.split(",") if x]
    if not 0 < args.duration <= 600 or args.hogs < 0 or args.periods < 10 or \
            not 1 <= args.rounds <= 100 or \
            not set(loops) <= {"python", "c"} or not transports or \
            not set(transports) <= set(LISTEN):
        print("emulator_speed: expected --duration in (0, 600] s, --hogs >= 0, --periods >= 10, "
              "--rounds 1..100, --loops of python,c, --transports of pty,unix,tcp",
              file=sys.stderr)
        return 2
    if "c" in loops and not args.program.is_file():
        print(f"emulator_speed: {args.program} is not built (make embedded), or --loops python",
              file=sys.stderr)
        return 2
    try:
        out = args.out or Path(tempfile.mkdtemp(prefix="emulator_speed_"))
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"emulator_speed: --out {args.out}: cannot make the folder ({exc.strerror or exc})",
              file=sys.stderr)
        return 2
    print(f"output in {out}", flush=True)
    trees = {}
    try:
        if args.baseline == "none":
            trees = {"this": ROOT}
        elif args.baseline == PYTHON_PATH_BASELINE:
            trees = {"baseline": ROOT, "this": ROOT}
        else:
            trees = {"baseline": export(args.baseline, out / "baseline"), "this": ROOT}
        # The baseline's emulator without the C lane when it is this tree's.
        lanes = {name: not (name == "baseline" and args.baseline == PYTHON_PATH_BASELINE)
                 for name in trees}
        results = {name: {"micro": {}, "hil": {}} for name in trees}
        for robot in ("serial", "parallel"):
            # The versions take turns, in alternating order, so a change of the machine's load
            # (other processes come and go) hits both alike; the samples are pooled.
            raw = {name: {"times": [], "cpus": [], "reads": 0, "writes": 0, "periods": 0}
                   for name in trees}
            names = list(trees)
            for k in range(args.rounds):
                for name in names if k % 2 == 0 else names[::-1]:
                    got = micro(trees[name], robot, max(args.periods // args.rounds, 10),
                                lanes[name])
                    for key in raw[name]:
                        raw[name][key] += got[key]
            for name in trees:
                results[name]["micro"][robot] = r = micro_stats(raw[name])
                print(f"micro {name:8s} {robot:8s} median {r['median_us']:7.1f} us (CPU "
                      f"{r['cpu_median_us']:6.1f} us)  p90 "
                      f"{r['p90_us']:7.1f} us  p99 {r['p99_us']:7.1f} us  syscalls/period "
                      f"read {r['reads_per_period']:.2f} write {r['writes_per_period']:.2f}",
                      flush=True)
        hogs = [multiprocessing.Process(target=hog, daemon=True) for _ in range(args.hogs)]
        for h in hogs:
            h.start()
        try:
            results["pty_floor"] = pty_floor(args.periods * 3)
            results["socket_floor"] = pty_floor(args.periods * 3, transport="unix")
            for what in ("pty", "socket"):
                r = results[f"{what}_floor"]
                print(f"{what} floor ({args.hogs} hogs): round trip median "
                      f"{r['median_us']:.0f} us  p99 {r['p99_us']:.0f} us  max "
                      f"{r['max_ms']:.1f} ms  over 1 ms {100 * r['over_1ms_fraction']:.2f} %",
                      flush=True)
            for loop in loops:
                for transport in transports:
                    for name, tree in trees.items():
                        if name == "baseline" and transport != "pty" and lanes[name]:
                            continue  # an older revision may have no --listen
                        folder = out / f"hil_{loop}_{name}_{transport}"
                        folder.mkdir(exist_ok=True)
                        results[name]["hil"][f"{loop}_{transport}"] = r = hil(
                            tree, loop, folder, args.duration, args.program, transport,
                            lanes[name])
                        print(f"hil   {name:8s} {loop:6s} {transport:4s} ({args.hogs} hogs) "
                              f"misses {100 * r['deadline_miss_fraction']:.2f} %  failed "
                              f"reads {r['failed_reads']}  lateness max "
                              f"{r['lateness_max_ms']:.1f} ms  emulator CPU "
                              f"{r['emulator_cpu_us_per_period']:.0f} us/period  stop "
                              f"{r['stop']}", flush=True)
        finally:
            for h in hogs:
                h.terminate()
    except (RuntimeError, subprocess.SubprocessError, OSError) as exc:
        print(f"emulator_speed: {exc}", file=sys.stderr)
        return 3
    results["settings"] = {"baseline": args.baseline, "duration_s": args.duration,
                           "hogs": args.hogs, "cpus": os.cpu_count(),
                           "load_before": os.getloadavg()}
    (out / "emulator_speed.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
