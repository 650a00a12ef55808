"""Write inputs_<scenario>.h: the measurements a host simulation's controller saw, period by
period, for the firmware of replay.c (the canned sequence both the QEMU and the host builds
replay). The values are C99 hexadecimal literals, so they round-trip exactly.

    python embedded/ports/qemu_mps2/record_inputs.py serial_task [--periods 300]

The simulation is cochlea.sim.simulate with the CasADi kernels, the scenario's own plant
(delay, encoder grid) and the scenario's controller; the logged q and qd of each unit are what
that controller measured (tests/test_embedded_generated.py checks this for every scenario).
Exit codes: 0 written; 2 an unknown scenario or a period count outside 1..5000."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from cochlea.kernels.catalogue import load_config
from cochlea.sim import load_scenario, simulate

HERE = Path(__file__).resolve().parent


def inputs_text(name: str, periods: int) -> str:
    """The header's text for ``periods`` periods of ``name``."""
    sc = load_scenario(name)
    result = simulate(sc, duration=periods * sc.period, kernels="casadi")
    q = np.hstack([u.q for u in result.units])[:periods]
    qd = np.hstack([u.qd for u in result.units])[:periods]
    if len(q) < periods or result.diverged:
        raise SystemExit(f"record_inputs: the simulation of {name} ended early")
    nq = q.shape[1]

    def table(label: str, values) -> list[str]:
        rows = [f"static const double {label}[INPUT_STEPS][INPUT_NQ] = {{"]
        rows += ["    {" + ", ".join(float(v).hex() for v in row) + "}," for row in values]
        return rows + ["};"]

    lines = [
        f"/* The measurements the controller of {name} saw in the first {periods} periods of",
        " * the host simulation (cochlea.sim.simulate, CasADi kernels): joint positions (rad, m)",
        " * and velocities (rad/s, m/s), joints unit after unit. Written by record_inputs.py. */",
        f"#define INPUT_NQ {nq}",
        f"#define INPUT_STEPS {periods}",
        *table("input_q", q),
        *table("input_qd", qd),
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--periods", type=int, default=300)
    parser.add_argument("--out", type=Path, default=None,
                        help="the header to write (default: inputs_<scenario>.h beside this)")
    args = parser.parse_args(argv)
    if args.scenario not in load_config().embedded.scenarios:
        print(f"record_inputs: unknown scenario {args.scenario!r}", file=sys.stderr)
        return 2
    if not 1 <= args.periods <= 5000:
        print(f"record_inputs: --periods {args.periods} is outside 1..5000", file=sys.stderr)
        return 2
    out = args.out or HERE / f"inputs_{args.scenario}.h"
    text = inputs_text(args.scenario, args.periods)
    partial = out.with_name(out.name + ".partial")
    partial.write_text(text)
    os.replace(partial, out)  # never a half-written header under the real name
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
