"""One period's bus transaction for 6 X-series motors at 4 Mbaud: FAST_SYNC_READ against the
plain SYNC_READ, and both against their wire time (issue 27, item 5).

The chain: the shipped serial robot's description with its six motors made XM540-W270s (an
X-series model), served by the emulator with its wire timing (``wire_timing=True``: every
byte takes 10 bit times at the baud rate, each status packet follows its request and the
packets before it; Return Delay Time 0, as the bridge sets it). The emulator answers
FAST_SYNC_READ here by setting (``VirtualChain.fast_sync_read = True``): the models' data do
not source that support yet (docs/dynamixel.md, "Mixed chains and Fast Sync Read").

Measured per transfer: the bridge's read() (request, replies, parse; median and p90 over
``--periods`` periods, the torque off so that nothing moves) and its read+write, next to the
budget's wire time of the same bytes (request + replies, and with the write). The wire time is
a floor: a pseudo-terminal and a Python emulator thread add their own latency on top, so the
measured gap between the two transfers, not their absolute values, is the result. Not a timed
test: run by hand (``python bench/fastsync_bench.py``), on a quiet machine for numbers to keep.
"""

from __future__ import annotations

import argparse
import gc
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.emulator import VirtualChain

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


def measure(scenario: Path, read: str, periods: int) -> dict:
    chain = VirtualChain("serial", scenario, baud=BAUD, wire_timing=True)
    chain.fast_sync_read = read == "fast"
    with chain:
        backend = DynamixelBackend("serial", chain.path, BAUD,
                                   description=chain.scenario.description,
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
        "periods": periods, "failed_reads": fails,
        "read_bytes": read_bytes, "read_wire_us": read_bytes * b.byte_time_s * 1e6,
        "period_bytes": b.total_bytes, "period_wire_us": b.wire_s * 1e6,
        "read_median_us": float(np.median(reads)) * 1e6,
        "read_p90_us": float(np.percentile(reads, 90)) * 1e6,
        "read_write_median_us": float(np.median(cycles)) * 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--periods", type=int, default=2000)
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        scenario = x_series_scenario(Path(tmp))
        rows = [measure(scenario, read, args.periods) for read in ("sync", "fast")]
    for r in rows:
        print(f"{r['read_instruction']:>15}: {r['read_bytes']} bytes read "
              f"({r['read_wire_us']:.0f} us of wire), {r['period_bytes']} per period "
              f"({r['period_wire_us']:.0f} us); read() median {r['read_median_us']:.0f} us, "
              f"p90 {r['read_p90_us']:.0f} us; read+write median "
              f"{r['read_write_median_us']:.0f} us; {r['failed_reads']} of {r['periods']} "
              f"reads failed ({', '.join(r['models'])}, {BAUD} baud, emulator wire timing)")
    s, f = rows
    print(f"FAST_SYNC_READ saves {s['read_bytes'] - f['read_bytes']} bytes "
          f"({s['read_wire_us'] - f['read_wire_us']:.0f} us of wire) per read; measured "
          f"median read {s['read_median_us'] - f['read_median_us']:.0f} us shorter")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
