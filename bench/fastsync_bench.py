"""One period's bus transaction for 6 X-series motors at 4 Mbaud: FAST_SYNC_READ against the
plain SYNC_READ, and both against their wire time (issue 27, item 5; issue 30, item 2).

The chain: the shipped serial robot's description with its six motors made XM540-W270s (an
X-series model, whose data say it answers FAST_SYNC_READ), served by the emulator with its
wire timing (every byte takes 10 bit times at the baud rate, each status packet follows its
request and the packets before it; Return Delay Time 0, as the bridge sets it). The emulator
runs either as ``cochlea-emulator`` in its own process (``--emulator process``, the default:
SCHED_FIFO 30 when permitted, as cochlea-run meets it) or as a ``VirtualChain`` thread in this
process (``--emulator thread``: the two then share one interpreter lock, the set-up of the
figures measured before issue 30's work). ``--emulator-path DIR`` runs another tree's emulator
(e.g. a ``git archive`` of main) against this tree's bridge.

Measured per transfer: the bridge's read() (request, replies, parse; median and p90 over
``--periods`` periods, the torque off so that nothing moves) and its read+write, next to the
budget's wire time of the same bytes (request + replies, and with the write). The wire time is
a floor: the pseudo-terminal (the kernel passes its bytes on in worker threads) and Python at
both ends add their own latency on top; ``--floor`` measures that latency alone (the same
bytes to and fro between two processes that do nothing else, sent when their wire time is
over). Not a timed test: run by hand (``python bench/fastsync_bench.py``), on a quiet machine
for numbers to keep.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import multiprocessing
import os
import re
import select
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path

import numpy as np

from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.emulator import VirtualChain, precise_timers
from cochlea.sim import load_scenario

ROOT = Path(__file__).resolve().parents[1]
BAUD = 4_000_000


def x_series_scenario(folder: Path) -> Path:
    """serial_joint with the six MX-64s made XM540-W270s (the bus traffic is what counts)."""
    text = (ROOT / "models" / "robots" / "serial.toml").read_text()
    text = re.sub(r'model = "MX-64"', 'model = "XM540-W270"', text)
    (folder / "serial_x.toml").write_text(text)
    scenario = (ROOT / "models" / "scenarios" / "serial_joint.toml").read_text()
    scenario = re.sub(r'^description = .*$', 'description = "serial_x.toml"', scenario,
                      flags=re.M)
    if 'description = "serial_x.toml"' not in scenario:
        scenario = scenario.replace('robot = "serial"',
                                    'robot = "serial"\ndescription = "serial_x.toml"', 1)
    path = folder / "serial_x_joint.toml"
    path.write_text(scenario)
    return path


@contextlib.contextmanager
def emulator(scenario: Path | str, mode: str, path: Path | None, robot: str = "serial",
             baud: int = BAUD, wire_timing: bool = True, quiet: bool = False):
    """The chain's pseudo-terminal, served as ``mode`` says (see the module docstring)."""
    if mode == "thread":
        with VirtualChain(robot, scenario, baud=baud, wire_timing=wire_timing) as chain:
            yield chain.path
        return
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(p) for p in (path, ROOT) if p)}
    proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                             robot, "--scenario", str(scenario), "--baud", str(baud)]
                            + (["--wire-timing"] if wire_timing else []), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        if not port.startswith("/dev/"):
            raise SystemExit(f"fastsync_bench: the emulator did not start: "
                             f"{proc.stderr.read().strip()[-300:]}")
        started = proc.stdout.readline().strip()
        if not quiet:
            print(f"  {started}", flush=True)
        yield port
    finally:
        proc.terminate()
        proc.communicate(timeout=20)


#: The rows of docs/dynamixel.md's measured bus table ("The bus budget"): robot, baud, wire
#: timing.
BUS_TABLE = [("serial", 4_000_000, False), ("serial", 4_000_000, True),
             ("serial", 2_000_000, True), ("serial", 1_000_000, True),
             ("parallel", 4_000_000, False), ("parallel", 4_000_000, True),
             ("parallel", 2_000_000, True), ("parallel", 1_000_000, True)]


def bus_table(periods: int, path: Path | None) -> list[dict]:
    """The shipped robots (MX-64s, SYNC_READ + SYNC_WRITE) over ``cochlea-emulator`` in its own
    process, at 500 Hz: read + write time per period, median and 99th percentile, against
    the budget's bus time (docs/dynamixel.md, "The bus budget")."""
    rows = []
    for robot, baud, wire in BUS_TABLE:
        scenario = f"{robot}_joint"
        with emulator(scenario, "process", path, robot, baud, wire, quiet=True) as port:
            backend = DynamixelBackend(robot, port, baud, realtime_tick=True)
            backend.enable()
            n = len(backend.drives)
            x, tau, cycles = np.zeros(2 * n), np.zeros(n), []
            try:
                gc.disable()
                for _ in range(periods):
                    t0 = time.perf_counter()
                    backend.read(x)
                    backend.write(tau)
                    cycles.append(time.perf_counter() - t0)
                    time.sleep(max(0.0, 0.002 - (time.perf_counter() - t0)))
            finally:
                gc.enable()
                backend.disable()
        b = backend.budget
        rows.append({"robot": robot, "baud": baud, "wire_timing": wire,
                     "budget_ms": b.bus_s * 1e3,
                     "median_ms": float(np.median(cycles)) * 1e3,
                     "p99_ms": float(np.percentile(cycles, 99)) * 1e3})
        r = rows[-1]
        print(f"| {robot} | {baud // 1_000_000} M | {'on' if wire else 'off'} | "
              f"{r['budget_ms']:.3f} ms | {r['median_ms']:.2f} / {r['p99_ms']:.2f} ms |",
              flush=True)
    return rows


def measure(scenario: Path, read: str, periods: int, mode: str = "process",
            path: Path | None = None) -> dict:
    description = load_scenario(scenario).description
    with emulator(scenario, mode, path) as port:
        backend = DynamixelBackend("serial", port, BAUD, description=description,
                                   timeout_s=0.02, read_instruction=read, realtime_tick=True)
        backend.enable()
        reads, cycles, fails = [], [], 0
        x, tau = np.zeros(12), np.zeros(6)
        try:
            gc.disable()
            for _ in range(periods):
                t0 = time.perf_counter()
                ok = backend.read(x)
                t1 = time.perf_counter()
                backend.write(tau)
                t2 = time.perf_counter()
                if ok:
                    reads.append(t1 - t0)
                    cycles.append(t2 - t0)
                else:
                    fails += 1
                time.sleep(0.001)
        finally:
            gc.enable()
            backend.disable()
    b = backend.budget
    read_bytes = b.sync_read_bytes + (b.combined_reply_bytes if read == "fast"
                                      else b.motors * b.reply_bytes)
    return {
        "read_instruction": backend.summary()["bus_budget"]["read_instruction"],
        "models": sorted({d.spec.name for d in backend.drives}),
        "emulator": mode, "periods": periods, "failed_reads": fails,
        "read_bytes": read_bytes, "read_wire_us": read_bytes * b.byte_time_s * 1e6,
        "period_bytes": b.total_bytes, "period_wire_us": b.wire_s * 1e6,
        "read_median_us": float(np.median(reads)) * 1e6,
        "read_p90_us": float(np.percentile(reads, 90)) * 1e6,
        "read_write_median_us": float(np.median(cycles)) * 1e6,
    }


def _echo(master: int, request: int, reply: int, wire_s: float) -> None:
    """The floor's other end: a reply of ``reply`` bytes ``wire_s`` after each request of
    ``request`` bytes arrived (slept, then waited on the clock), nothing else."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(30))  # as the emulator
    except (AttributeError, PermissionError, OSError):
        pass
    precise_timers()
    got = 0
    while True:
        select.select([master], [], [])
        data = os.read(master, 4096)
        if data == b"q":
            return
        got += len(data)
        if got < request:
            continue
        got = 0
        due = time.perf_counter() + wire_s
        time.sleep(max(0.0, due - time.perf_counter() - 100e-6))
        while time.perf_counter() < due:
            pass
        os.write(master, b"x" * reply)


def pty_floor(request: int, reply: int, periods: int) -> dict:
    """One transaction's bytes between two processes over a pseudo-terminal, the reply sent
    when the wire time of the request and the reply from the request's arrival is over (as
    the emulator does): the time above that wire time is the pseudo-terminal's and Python's
    (this process's read), what no emulator can remove."""
    wire_s = (request + reply) * 10.0 / BAUD
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    echo = multiprocessing.Process(target=_echo, args=(master, request, reply, wire_s),
                                   daemon=True)
    echo.start()
    times = []
    try:
        time.sleep(0.2)
        for _ in range(periods):
            t = time.perf_counter()
            os.write(slave, b"y" * request)
            got = 0
            while got < reply and select.select([slave], [], [], 0.05)[0]:
                got += len(os.read(slave, 4096))
            if got >= reply:
                times.append(time.perf_counter() - t)
            time.sleep(0.001)
    finally:
        os.write(slave, b"q")
        echo.join(timeout=5)
        os.close(master)
        os.close(slave)
    return {"wire_us": wire_s * 1e6, "median_us": float(np.median(times)) * 1e6,
            "p90_us": float(np.percentile(times, 90)) * 1e6, "lost": periods - len(times)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--periods", type=int, default=2000)
    p.add_argument("--emulator", choices=["process", "thread"], default="process",
                   help="cochlea-emulator in its own process (default) or a VirtualChain "
                        "thread in this one")
    p.add_argument("--emulator-path", type=Path, metavar="DIR",
                   help="with --emulator process: the emulator's package from DIR (another "
                        "tree's cochlea/, e.g. a git archive of main)")
    p.add_argument("--floor", action="store_true",
                   help="also measure the pseudo-terminal's floor for each transfer")
    p.add_argument("--bus-table", action="store_true",
                   help="instead: the read + write table of docs/dynamixel.md's \"The bus "
                        "budget\" (the shipped robots at 1-4 Mbaud, 500 Hz)")
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)
    if args.bus_table:
        print("| robot | baud | wire timing | budget (bus) | measured median / p99 |")
        rows = bus_table(args.periods, args.emulator_path)
        print(f"(load average {os.getloadavg()[0]:.1f})")
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1) + "\n")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        scenario = x_series_scenario(Path(tmp))
        rows = [measure(scenario, read, args.periods, args.emulator, args.emulator_path)
                for read in ("sync", "fast")]
    for r in rows:
        if args.floor:
            replies = r["read_bytes"] - (14 + 6)  # the request: 14 + n bytes
            r["floor"] = pty_floor(14 + 6, replies, args.periods)
        print(f"{r['read_instruction']:>15}: {r['read_bytes']} bytes read "
              f"({r['read_wire_us']:.0f} us of wire), {r['period_bytes']} per period "
              f"({r['period_wire_us']:.0f} us); read() median {r['read_median_us']:.0f} us "
              f"({r['read_median_us'] / r['read_wire_us']:.2f}x the wire), "
              f"p90 {r['read_p90_us']:.0f} us; read+write median "
              f"{r['read_write_median_us']:.0f} us; {r['failed_reads']} of {r['periods']} "
              f"reads failed ({', '.join(r['models'])}, {BAUD} baud, emulator wire timing, "
              f"emulator {r['emulator']})")
        if args.floor:
            f = r["floor"]
            print(f"{'':>15}  pseudo-terminal floor of the same bytes: median "
                  f"{f['median_us']:.0f} us ({f['median_us'] / f['wire_us']:.2f}x), p90 "
                  f"{f['p90_us']:.0f} us")
    s, f = rows
    print(f"FAST_SYNC_READ saves {s['read_bytes'] - f['read_bytes']} bytes "
          f"({s['read_wire_us'] - f['read_wire_us']:.0f} us of wire) per read; measured "
          f"median read {s['read_median_us'] - f['read_median_us']:.0f} us shorter "
          f"(load average {os.getloadavg()[0]:.1f})")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
