"""Benchmark rows of ``build/cochlea-embedded`` (issue 12) against ``cochlea-emulator``: the C
loop's own compute per period against the Python loop's on the same scenario and emulator, the
bus time of one period at 1-4 Mbaud with the emulator's wire timing, and the deadline misses of
a 20 s run. Every number comes from the runs' own log.bin (per-period timing columns, s), so
the rows of one table are taken in one bench run on the same machine.

A row that cannot be measured (the program refuses the run, or it stops early on every
attempt) says why in its place; the other rows are still taken.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from cochlea.dynamixel.bridge import TICK_READ_LENGTH
from cochlea.dynamixel.budget import bus_budget

ROOT = Path(__file__).resolve().parent.parent
PROGRAM = ROOT / "build" / "cochlea-embedded"
#: cochlea-emulator serves at full pace a moment after it prints its port (see
#: tests/test_embedded_program.py).
SETTLE_S = 2.0
#: The exit code of a refused option or run (EXIT_USER_ERROR of embedded/posix/main.c,
#: cochlea-run's too): the run cannot happen as asked, so it is not repeated.
EXIT_REFUSED = 2
#: The heading of this part of results.md.
TITLE = "## The embedded program (build/cochlea-embedded) against cochlea-emulator"


class NotRun(RuntimeError):
    """A row that could not be measured; the message says why (one line)."""


def build() -> Path:
    subprocess.run(["make", "--no-print-directory", "embedded"], cwd=ROOT, check=True,
                   capture_output=True)
    return PROGRAM


def with_rotors(scenario: str, folder: Path) -> str:
    """The scenario the emulator serves for study ``scenario``: for the serial system a copy
    in ``folder`` whose plant has the drives' rotors (``[plant] armature = true``), as the HIL
    tests serve it. The thesis's serial gains leave no margin for a late period on its rigid
    links (6e-6 kg m^2 distal links; docs/dynamixel.md, "serial_task on the rigid plant has no
    margin for a late period"), so over a real-time chain, and at 400 Hz, the rigid plant
    measured the host's scheduling and then stopped at a velocity limit; these rows measure the
    bus and the loop. The controller's scenario stays the study."""
    from cochlea.resources import SCENARIOS_DIR

    source = SCENARIOS_DIR / f"{scenario}.toml"
    if not scenario.startswith("serial") or not source.is_file():
        return scenario
    text = source.read_text()
    if "[plant]" in text:  # a plant of its own: served as it is
        return scenario
    path = folder / f"{scenario}_with_rotors.toml"
    path.write_text(text + "\n[plant]\narmature = true\n")
    return str(path)


@contextmanager
def emulator(robot: str, scenario: str, *options: str):
    """``cochlea-emulator`` serving ``scenario`` (with the serial drives' rotors:
    :func:`with_rotors`) on a Unix-domain socket, as the HIL tests do: a pseudo-terminal's
    bytes wait for the kernel's worker threads, which a loaded machine delays (docs/dynamixel.md,
    "Does the virtual chain keep up"). Yields the ``--port`` to give a loop."""
    with tempfile.TemporaryDirectory(prefix="cochlea-emu-") as folder:  # short: a socket path
        served = with_rotors(scenario, Path(folder))
        proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                                 robot, "--scenario", served, "--listen",
                                 f"unix:{folder}/chain.sock", *options],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            port = proc.stdout.readline().strip()
            if not port.startswith("unix:"):
                raise RuntimeError(f"cochlea-emulator did not start: {proc.stderr.read()}")
            time.sleep(SETTLE_S)
            yield port
        finally:
            proc.terminate()
            proc.communicate(timeout=20)


def timing(out: Path) -> dict[str, np.ndarray]:
    """The per-period timing columns of a run's log.bin (s), rows that have them."""
    columns = json.loads((out / "log.columns.json").read_text())
    rows = np.fromfile(out / "log.bin").reshape(-1, columns["row_length"])
    names = columns["columns"]
    table = {n: rows[:, names.index(n)] for n in ("compute_s", "backend_io_s", "wall_period_s",
                                                  "start_lateness_s")}
    keep = np.isfinite(table["compute_s"])
    return {k: v[keep] for k, v in table.items()}


def _stats(values: np.ndarray) -> dict:
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99)),
            "max": float(values.max())}


#: A run is repeated (on a fresh emulator) at most this often when it does not complete: the
#: Python emulator now and then falls tens of milliseconds behind on a shared machine (see
#: tests/test_embedded_program.py), which can stop a run on the failed-read watchdog.
ATTEMPTS = 3


def _last_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[-1] if lines else "(nothing on stderr)"


def _attempts(what: str, emulator_args: tuple, command) -> dict:
    """``command(port, attempt)`` on a fresh emulator until it completes (exit 0): its
    summary. The failures before it are kept in the result (``failed_attempts``). A refusal
    (exit 2: the program will not run as asked, e.g. the bus cannot carry the rate) is not
    the emulator's lag and is not repeated. Raises :class:`NotRun` saying why."""
    failures = []
    for attempt in range(ATTEMPTS):
        with emulator(*emulator_args) as port:
            done, out = command(port, attempt)
        if done.returncode == 0:
            summary = json.loads((out / "summary.json").read_text())
            summary["failed_attempts"] = failures
            summary["out"] = str(out)
            return summary
        if done.returncode == EXIT_REFUSED:
            raise NotRun(f"{what} refused the run: {_last_line(done.stderr)}")
        failures.append(f"exit {done.returncode}: {done.stderr.strip()[-300:]}")
    raise NotRun(f"{what} stopped early {ATTEMPTS} times (last: "
                 f"{_last_line(failures[-1])})")


def run_c(scenario: str, emulator_args: tuple, out: Path, seconds: float, *options: str
          ) -> dict:
    """``build/cochlea-embedded`` on a fresh emulator; the read watchdog allows 100 failed
    reads in a row (the runs measure time, not faults)."""
    def command(port: str, attempt: int):
        folder = out.with_name(f"{out.name}-{attempt}")
        return subprocess.run([str(PROGRAM), "--scenario", scenario, "--port", port,
                               "--duration", str(seconds), "--out", str(folder),
                               "--watchdog-errors", "100", *options], capture_output=True,
                              text=True, timeout=seconds + 60), folder
    return _attempts("cochlea-embedded", emulator_args, command)


def run_python(robot: str, space: str, out: Path, seconds: float) -> dict:
    def command(port: str, attempt: int):
        folder = out.with_name(f"{out.name}-{attempt}")
        return subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot",
                               robot, "--space", space, "--backend", "dynamixel", "--port",
                               port, "--duration", str(seconds), "--out", str(folder),
                               "--status", "off", "--watchdog-misses", "300"],
                              capture_output=True, text=True, timeout=seconds + 120), folder
    return _attempts("cochlea-run", (robot, f"{robot}_{space}"), command)


def loop_compute(studies=(("serial", "task"), ("parallel", "task")), seconds: float = 5.0
                 ) -> list[dict]:
    """Per period, the loop's own work (its compute less the bus transaction), C against
    Python, each against its own fresh emulator of the same scenario."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for robot, space in studies:
            name = f"{robot}_{space}"
            try:
                runs = {"c": run_c(name, (robot, name), Path(tmp) / f"c-{name}", seconds,
                                   "--watchdog-misses", "300"),
                        "py": run_python(robot, space, Path(tmp) / f"py-{name}", seconds)}
            except NotRun as why:
                rows.append({"scenario": name, "not_run": str(why)})
                continue
            own = {}
            for who, summary in runs.items():
                t = timing(Path(summary["out"]))
                own[who] = _stats(t["compute_s"] - t["backend_io_s"])
                own[who + "_bus"] = _stats(t["backend_io_s"])
            rows.append({"scenario": name, "unit": "s", "c_loop": own["c"],
                         "python_loop": own["py"], "c_bus": own["c_bus"],
                         "python_bus": own["py_bus"],
                         "python_over_c_p50": own["py"]["p50"] / own["c"]["p50"],
                         "repeated_runs": len(runs["c"]["failed_attempts"])
                         + len(runs["py"]["failed_attempts"])})
    return rows


def carried_rate(motors: int, baud: int, rates=(1000, 500, 400, 250, 200, 100)) -> int:
    """The highest control rate (Hz) whose period holds the bus time of one period as the
    program counts it (cochlea/dynamixel/budget.py with the program's read: the Realtime
    Tick's block of TICK_READ_LENGTH bytes per motor, measured current included; the adapter's
    latency aside, as the emulator has none). The program refuses a rate the bus cannot carry,
    so a budget of the 10-byte state read alone picked 500 Hz at 1 Mbaud, which it refused."""
    budget = bus_budget(motors, baud, read_length=TICK_READ_LENGTH)
    return next(r for r in rates if budget.bus_s <= 1.0 / r)


def wire_times(bauds=(1_000_000, 2_000_000, 3_000_000, 4_000_000), seconds: float = 3.0
               ) -> list[dict]:
    """The bus transaction of one period (SYNC_WRITE, SYNC_READ and the six status packets of
    the serial system) with the emulator holding each byte for its time on the wire, at the
    highest rate the bus carries at each baud (:func:`carried_rate`)."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for baud in bauds:
            rate = carried_rate(6, baud)
            try:
                summary = run_c("serial_joint", ("serial", "serial_joint", "--wire-timing",
                                                 "--baud", str(baud)),
                                Path(tmp) / f"w{baud}", seconds, "--baud", str(baud),
                                "--rate", str(rate), "--watchdog-misses", "300")
            except NotRun as why:
                rows.append({"baud": baud, "rate_Hz": rate, "not_run": str(why)})
                continue
            t = timing(Path(summary["out"]))
            budget = summary["timing"]["bus"]["bus_budget"]
            rows.append({"baud": baud, "rate_Hz": rate, "unit": "s",
                         "repeated_runs": len(summary["failed_attempts"]),
                         "bus_io": _stats(t["backend_io_s"]), "budget_bus_s": budget["bus_s"],
                         "budget_wire_s": budget["wire_s"],
                         "good_reads": summary["timing"]["bus"]["good_reads"],
                         "reads": summary["timing"]["bus"]["reads"]})
    return rows


def deadline_misses(seconds: float = 20.0) -> dict:
    """The C program's serial task study for 20 s at 4 Mbaud: its missed deadlines and period."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            summary = run_c("serial_task", ("serial", "serial_task"), Path(tmp) / "m", seconds,
                            "--watchdog-misses", "1000")
        except NotRun as why:
            return {"scenario": "serial_task", "seconds": seconds, "not_run": str(why)}
    t = summary["timing"]
    return {"scenario": "serial_task", "seconds": seconds, "periods": summary["periods"],
            "deadline_misses": t["deadline_misses"],
            "deadline_miss_fraction": t["deadline_miss_fraction"],
            "period_p99_s": t["period_p99"], "period_max_s": t["period_max"],
            "scheduling": t["scheduling"], "memory": t["memory"],
            "repeated_runs": len(summary["failed_attempts"])}


def bench() -> dict:
    build()
    return {"loop_compute": loop_compute(), "wire": wire_times(),
            "deadline_misses": deadline_misses()}


def us(seconds: float) -> str:
    return f"{seconds * 1e6:.0f} us" if seconds >= 1e-5 else f"{seconds * 1e6:.1f} us"


def markdown(results: dict) -> str:
    lines = [TITLE, "",
             "The loop's own work per period (its compute less the bus transaction), C against "
             "Python on the same scenario, each against a fresh emulator (5 s). Every emulator "
             "here serves on its Unix-domain socket, and the serial system's chain has its "
             "drives' rotors in the plant (`[plant] armature = true`: the thesis's rigid links "
             "leave its gains no margin for a late period; see `with_rotors`):", "",
             "| scenario | C p50 | C p99 | C max | Python p50 | Python p99 | Python max | "
             "Python / C (p50) |", "|---|---|---|---|---|---|---|---|"]
    for r in results["loop_compute"]:
        if "not_run" in r:
            lines.append(f"| {r['scenario']} | not measured: {r['not_run']} |")
            continue
        c, p = r["c_loop"], r["python_loop"]
        lines.append(f"| {r['scenario']} | {us(c['p50'])} | {us(c['p99'])} | {us(c['max'])} | "
                     f"{us(p['p50'])} | {us(p['p99'])} | {us(p['max'])} | "
                     f"{r['python_over_c_p50']:.0f}x |")
    lines += ["", "The bus transaction of one period (6 motors, serial_joint) with the emulator's "
              "wire timing:", "",
              "| baud | rate | bus i/o p50 | p99 | max | budget (wire + turnaround) | good reads |",
              "|---|---|---|---|---|---|---|"]
    for r in results["wire"]:
        if "not_run" in r:
            lines.append(f"| {r['baud'] / 1e6:g} M | {r['rate_Hz']} Hz | not measured: "
                         f"{r['not_run']} |")
            continue
        b = r["bus_io"]
        lines.append(f"| {r['baud'] / 1e6:g} M | {r['rate_Hz']} Hz | {us(b['p50'])} | "
                     f"{us(b['p99'])} | {us(b['max'])} | {us(r['budget_bus_s'])} | "
                     f"{r['good_reads']} of {r['reads']} |")
    m = results["deadline_misses"]
    repeated = sum(r.get("repeated_runs", 0) for r in results["loop_compute"]) \
        + sum(r.get("repeated_runs", 0) for r in results["wire"]) + m.get("repeated_runs", 0)
    if "not_run" in m:
        lines += ["", f"Deadline misses of the C program over {m['seconds']:g} s "
                  f"({m['scenario']}): not measured: {m['not_run']}."]
    else:
        lines += ["", f"Deadline misses of the C program over {m['seconds']:g} s "
                  f"({m['scenario']}, 4 Mbaud, {m['scheduling']}, memory {m['memory']}): "
                  f"{m['deadline_misses']} of {m['periods']} periods "
                  f"({100 * m['deadline_miss_fraction']:.2f} %); period p99 "
                  f"{m['period_p99_s'] * 1e3:.3f} ms, max {m['period_max_s'] * 1e3:.3f} ms."]
    lines += ["", f"Runs repeated because one stopped early (the emulator's lag, see "
              f"bench/embedded_program.py): {repeated}.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    results = bench()
    print(markdown(results))
