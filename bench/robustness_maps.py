"""The robustness maps of docs/robustness_maps.md (issue 16): each spec in docs/robustness/*.toml
swept with ``cochlea-sweep`` and published beside it.

    .venv/bin/python bench/robustness_maps.py [--workers N] [--only NAME ...]

(`make robustness-maps`.)

Each sweep runs into ``runs/robustness-NAME`` (the same command resumes an interrupted one);
its samples are then published in ``docs/robustness/NAME/`` as a sweep folder of its own:
``sweep.json`` and ``spec.toml`` as the sweep wrote them, the rows in ONE part file (a few
hundred samples; the sweep's hundreds of one-batch files would be megabytes of Parquet
headers), and the report written there by ``cochlea-sweep report``, so its replay commands
(``cochlea-sweep replay docs/robustness/NAME SAMPLE``) work from a clone. The index,
docs/robustness_maps.md, tabulates every map.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from cochlea.sweep import results

ROOT = Path(__file__).resolve().parents[1]
SPECS = ROOT / "docs" / "robustness"
RUNS = ROOT / "runs"
SWEEP = [sys.executable, "-m", "cochlea.apps.cochlea_sweep"]


def sweep(name: str, workers: int) -> Path:
    out = RUNS / f"robustness-{name}"
    subprocess.run([*SWEEP, str(SPECS / f"{name}.toml"), "--out", str(out), "--workers",
                    str(workers)], cwd=ROOT, check=True)
    return out


def publish(name: str, out: Path) -> dict:
    """The sweep folder ``out`` as ``docs/robustness/NAME`` with one part file; its report."""
    target = SPECS / name
    if target.exists():
        shutil.rmtree(target)
    (target / "parts").mkdir(parents=True)
    manifest = json.loads((out / "sweep.json").read_text())
    # Paths relative to the repository, as a clone has them.
    for key in ("spec_path", "scenario_path"):
        path = Path(manifest[key])
        if path.is_relative_to(ROOT):
            manifest[key] = str(path.relative_to(ROOT))
    (target / "sweep.json").write_text(json.dumps(manifest, indent=1) + "\n")
    shutil.copy(out / "spec.toml", target / "spec.toml")
    table = results.read(out)  # every part, the result columns by the log schema
    samples = table["sample"].to_pylist()
    assert samples == list(range(manifest["total"])), f"{out}: the sweep is not complete"
    pq.write_table(table, target / "parts" / f"part-{0:09d}-{samples[-1]:09d}.parquet")
    subprocess.run([*SWEEP, "report", str(target.relative_to(ROOT))], cwd=ROOT, check=True)
    return row(name, manifest, table)


def row(name: str, manifest: dict, table: pa.Table) -> dict:
    import numpy as np

    from cochlea.sweep.report import wilson

    success = np.array(table["success"].to_pylist(), bool)
    ratio = np.array(table["convergence_ratio"].to_pylist(), float)
    torque = max(max(table[c].to_pylist())
                 for c in results.columns(table.column_names, results.RATIO))
    lo, hi = wilson(int(success.sum()), len(success))
    return {"name": name, "robot": manifest["robot"], "space": manifest["space"],
            "samples": len(success), "success": int(success.sum()), "lo": lo, "hi": hi,
            "ratio_p50": float(np.median(ratio)), "ratio_p95": float(np.percentile(ratio, 95)),
            "ratio_max": float(ratio.max()), "torque_max": float(torque)}


def index(rows: list[dict]) -> None:
    lines = ["| map | robot, space | samples | success (95 % interval) | convergence ratio "
             "median / 95th pct / max | largest peak torque / limit |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| [{r['name']}](robustness/{r['name']}/summary.md) | {r['robot']}, "
                     f"{r['space']} | {r['samples']} | {r['success']} "
                     f"({r['lo']:.1%}-{r['hi']:.1%}) | {r['ratio_p50']:.3g} / "
                     f"{r['ratio_p95']:.3g} / {r['ratio_max']:.3g} | {r['torque_max']:.3g} |")
    path = ROOT / "docs" / "robustness_maps.md"
    text = path.read_text()
    begin, end = "<!-- maps: begin -->", "<!-- maps: end -->"
    head, rest = text.split(begin)
    _, tail = rest.split(end)
    path.write_text(head + begin + "\n" + "\n".join(lines) + "\n" + end + tail)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--only", nargs="*", metavar="NAME", help="these maps only (the index keeps "
                   "the others' published rows)")
    args = p.parse_args()
    names = sorted(f.stem for f in SPECS.glob("*.toml"))
    chosen = args.only or names
    rows = []
    for name in names:
        if name in chosen:
            rows.append(publish(name, sweep(name, args.workers)))
        elif (SPECS / name / "sweep.json").exists():
            folder = SPECS / name
            rows.append(row(name, json.loads((folder / "sweep.json").read_text()),
                            results.read(folder)))
    index(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
