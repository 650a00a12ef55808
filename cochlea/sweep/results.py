"""A sweep's folder: ``sweep.json`` (the spec, its base scenario and their hash), ``spec.toml``
(the spec as written) and ``parts/part-FIRST-LAST.parquet``, one Parquet file per finished
batch (one row per sample), each written to a temporary name and renamed: a file in ``parts/``
is always whole, so an interrupted sweep loses at most its unfinished batches and the same
command resumes it with the missing samples only.
"""

from __future__ import annotations

import fcntl
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import CochleaError
from .spec import Spec

MANIFEST = "sweep.json"
PARTS = "parts"
#: Held (flock) by the sweep running in a folder; the kernel drops it when the process dies.
LOCK = ".cochlea-sweep.lock"
MANIFEST_FORMAT = "cochlea-sweep-folder/1"


class SweepFolderError(CochleaError):
    """A sweep folder that cannot be used (another spec's, not a sweep's, unreadable)."""


def flatten(name: str, value: Any) -> dict[str, Any]:
    """One input as columns: a scalar as ``name``, a list as ``name[0]``, ``name[1]``, ..."""
    if isinstance(value, list):
        return {f"{name}[{j}]": v for j, v in enumerate(value)}
    return {name: value}


@dataclass
class Manifest:
    digest: str
    total: int
    robot: str
    space: str
    spec_text: str
    scenario_text: str
    scenario_path: str
    spec_path: str


def write_manifest(out: Path, spec: Spec) -> None:
    data = {"format": MANIFEST_FORMAT, "digest": spec.digest, "total": spec.total,
            "robot": spec.robot, "space": spec.space, "spec_path": str(spec.path.resolve()),
            "scenario_path": str(spec.scenario_path), "spec_text": spec.text,
            "scenario_text": spec.scenario_text}
    tmp = out / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, out / MANIFEST)
    (out / "spec.toml").write_text(spec.text, encoding="utf-8")


def read_manifest(out: Path) -> Manifest:
    path = out / MANIFEST
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if data.get("format") != MANIFEST_FORMAT:
            raise ValueError(data.get("format"))
        return Manifest(data["digest"], int(data["total"]), data["robot"], data["space"],
                        data["spec_text"], data["scenario_text"], data["scenario_path"],
                        data["spec_path"])
    except FileNotFoundError:
        raise SweepFolderError(f"{out}: not a sweep folder (no {MANIFEST}): give the --out "
                               "of a cochlea-sweep run") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SweepFolderError(f"{path}: unreadable sweep manifest ({exc})") from None


def check(out: Path, spec: Spec) -> bool:
    """Whether ``out`` is this spec's sweep folder (to resume); False: new or empty. Any other
    folder is refused. Writes nothing."""
    if out.exists() and not out.is_dir():
        raise SweepFolderError(f"--out {out}: expected a folder, got a file")
    if out.is_dir() and any(out.iterdir()):
        if not (out / MANIFEST).exists():
            raise SweepFolderError(f"--out {out}: expected a new or empty folder, or a sweep "
                                   "folder to resume; it holds other files")
        manifest = read_manifest(out)
        if manifest.digest != spec.digest:
            raise SweepFolderError(f"--out {out}: made by a different spec or scenario (hash "
                                   f"{manifest.digest[:12]}, this one {spec.digest[:12]}): give "
                                   "a new --out, or the spec that made it to resume")
        return True
    return False


def prepare(out: Path, spec: Spec) -> None:
    """A new (or empty) folder becomes this spec's (:func:`check` first); half-written parts of
    a killed run are removed."""
    if not check(out, spec):
        out.mkdir(parents=True, exist_ok=True)
        write_manifest(out, spec)
    parts = out / PARTS
    parts.mkdir(exist_ok=True)
    for tmp in parts.glob("*.tmp"):
        tmp.unlink()


def hold(out: Path, lock: str = LOCK, program: str = "cochlea-sweep",
         error: type[CochleaError] | None = None) -> int:
    """Lock ``out`` for this process (``lock``, a file in it): a second sweep on the same folder
    would run the same missing samples and write them twice (``cochlea-tune`` locks its folder
    the same way). The lock file stays (removing it would let a third process lock a new file
    while a second still holds the old one)."""
    fd = os.open(out / lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise (error or SweepFolderError)(
            f"--out {out}: another {program} is running on this folder; wait for it (the same "
            "command then resumes what is left) or give another --out") from None
    return fd


def release(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)


def write_part(out: Path, rows: list[dict]) -> Path:
    """One batch's rows, renamed into place once whole (and flushed to disk)."""
    samples = [r["sample"] for r in rows]
    name = f"part-{min(samples):09d}-{max(samples):09d}.parquet"
    final = out / PARTS / name
    tmp = final.with_name(name + ".tmp")
    pq.write_table(pa.Table.from_pylist(rows), tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, final)
    return final


def read(out: Path) -> pa.Table:
    """Every finished sample's row, sorted by sample (an empty table when there is none)."""
    files = sorted((out / PARTS).glob("part-*.parquet"))
    if not files:
        return pa.table({"sample": pa.array([], pa.int64())})
    try:
        tables = [pq.read_table(f) for f in files]
    except (OSError, pa.ArrowException) as exc:
        raise SweepFolderError(f"{out / PARTS}: a part file cannot be read ({exc}); remove it "
                               "and resume to run its samples again") from None
    table = pa.concat_tables(tables, promote_options="default")
    return table.sort_by("sample")


def done(out: Path) -> set[int]:
    """The samples already in the folder's part files."""
    if not (out / PARTS).is_dir():
        return set()
    files = sorted((out / PARTS).glob("part-*.parquet"))
    seen: set[int] = set()
    for f in files:
        try:
            seen.update(pq.read_table(f, columns=["sample"])["sample"].to_pylist())
        except (OSError, pa.ArrowException) as exc:
            raise SweepFolderError(f"{f}: unreadable part file ({exc}); remove it and resume "
                                   "to run its samples again") from None
    return seen
