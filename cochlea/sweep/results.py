"""A sweep's folder: ``sweep.json`` (the spec, its base scenario and their hash), ``spec.toml``
(the spec as written) and ``parts/part-FIRST-LAST.parquet``, one Parquet file per finished
batch (one row per sample), each written to a temporary name and renamed: a file in ``parts/``
is always whole, so an interrupted sweep loses at most its unfinished batches and the same
command resumes it with the missing samples only.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from .. import files
from ..errors import CochleaError
from ..log_schema import EFFORT_UNIT
from .spec import Spec

MANIFEST = "sweep.json"
PARTS = "parts"
#: Held (flock) by the sweep running in a folder; the kernel drops it when the process dies.
LOCK = ".cochlea-sweep.lock"
MANIFEST_FORMAT = "cochlea-sweep-folder/1"


# Exit codes of cochlea-sweep and cochlea-tune (docs/sweeps.md has the table). 0 done; tune's
# 1 (no feasible candidate), 18 (report failed) and 130 (interrupted) are the commands' own.
#: The spec or an option is wrong (cochlea.errors.EXIT_USER_ERROR): nothing ran or was written.
EXIT_SPEC = 2
#: ``--out`` cannot be used (not a folder, under a file, not writable, other files, another
#: spec's folder; replay: the file exists): nothing ran or was written.
EXIT_OUT = 3
#: ``--out`` is in use by another run of cochlea-sweep or cochlea-tune: nothing changed.
EXIT_BUSY = 4
#: The folder's own files are damaged (sweep.json, tune.json, the journal, a part file).
EXIT_DAMAGED = 5
#: A write failed while running (a full disk, an I/O error): every finished batch or trial is
#: kept, the unfinished file removed; the same command resumes once there is room.
EXIT_WRITE = 6
#: A sample failed on a worker (not a refusal the checks could see): the finished batches are
#: kept.
EXIT_SAMPLE = 7


class SweepFolderError(CochleaError):
    """A sweep folder that cannot be used (another spec's, not a sweep's, unreadable)."""

    exit_code = EXIT_OUT


class FolderBusy(SweepFolderError):
    """Another run holds the folder's lock."""

    exit_code = EXIT_BUSY


class FolderDamaged(SweepFolderError):
    """A file the folder's run wrote cannot be read back."""

    exit_code = EXIT_DAMAGED


class WriteFailed(CochleaError):
    """A file of the run could not be written (a full disk, an I/O error)."""

    exit_code = EXIT_WRITE


class SampleFailed(CochleaError):
    """A sample raised on a worker."""

    exit_code = EXIT_SAMPLE


def exit_code(exc: CochleaError) -> int:
    """The exit code of a refusal (:data:`EXIT_SPEC` unless the error says otherwise)."""
    return getattr(exc, "exit_code", EXIT_SPEC)


def kind_words(mode: int) -> str:
    """What a path of this ``st_mode`` is, in words for a message (cochlea-sweep's and
    cochlea-tune's wording: device kinds named)."""
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    return files.kind(mode)


def check_out(out: Path, option: str = "--out") -> None:
    """Refuse ``out`` as an output folder unless it is a folder we may write or can be made
    one (its nearest existing ancestor a writable folder). Writes nothing."""
    out = Path(out)
    where = f"{option} {out}"
    p = files.folder_problem(out)
    if p is None:
        return
    raise SweepFolderError({
        "unusable": f"{where}: cannot use it ({p.reason}): name a new or empty folder",
        "not_folder": f"{where} is {kind_words(p.mode or 0)}, not a folder: name a new or empty "
                      "folder",
        "not_writable": f"{where}: the folder is not writable (permissions or a read-only "
                        "file system): name a folder you may write",
        "ancestor_unusable": f"{where}: cannot create it under {p.path} ({p.reason})",
        "ancestor_not_folder": f"{where}: cannot create it, {p.path} is {kind_words(p.mode or 0)}, "
                               "not a folder",
        "ancestor_not_writable": f"{where}: cannot create it, {p.path} is not writable "
                                 "(permissions or a read-only file system): name a folder "
                                 "you may write",
    }[p.code])


def make_folder(out: Path, option: str = "--out") -> list[Path]:
    """Create ``out`` and its missing parents; return those this call created, outermost
    first (:func:`remove_folders` undoes it)."""
    missing = []
    path = Path(os.path.abspath(out))
    while not os.path.lexists(path):
        missing.append(path)
        path = path.parent
    created: list[Path] = []
    for folder in reversed(missing):
        try:
            folder.mkdir()
        except FileExistsError:
            continue  # another run made it meanwhile: not ours to remove
        except OSError as exc:
            remove_folders(created)
            raise SweepFolderError(f"{option} {out}: cannot create {folder} ({exc.strerror})"
                                   ) from None
        created.append(folder)
    return created


def remove_folders(created: list[Path]) -> None:
    """Remove the folders :func:`make_folder` created, innermost first, only while empty."""
    for folder in reversed(created):
        with contextlib.suppress(OSError):
            folder.rmdir()


def remove_ours(path: Path) -> None:
    """Unlink ``path`` only if it is a regular file (never a link, FIFO, device, folder)."""
    files.remove_regular(path)


def write_atomic(path: Path, data: bytes) -> None:
    """``data`` into ``path`` whole or not at all (:func:`cochlea.files.write_atomic`), renamed
    over ``path`` only when ``path`` is absent or a regular file. A failure (a full disk)
    removes the temporary file and raises :class:`WriteFailed`."""
    path = Path(path)
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise WriteFailed(f"{path}: cannot write it ({exc.strerror})") from None
    if mode is not None and not stat.S_ISREG(mode):
        raise WriteFailed(f"{path} is {kind_words(mode)}, not a file this run wrote: it is left as "
                          "it is; move it away and run the same command again")
    try:
        # NAME.XXXXXXXX.tmp: every *.parquet in parts/ is a whole batch, whoever globs it.
        files.write_atomic(path, data, only_files=True, keep_suffix=False)
    except OSError as exc:
        raise WriteFailed(f"{path}: cannot write it ({exc.strerror or exc})") from None


def is_temporary(path: Path) -> bool:
    """A temporary file of :func:`write_atomic` (or an older run's ``NAME.tmp``)."""
    return files.is_temporary(path)


def clean_temporary(folder: Path) -> None:
    """Remove the temporary files a killed run left in ``folder`` (regular files only)."""
    files.clean_temporary(folder)


def flatten(name: str, value: Any) -> dict[str, Any]:
    """One input as columns: a scalar as ``name``, a list as ``name[0]``, ``name[1]``, ..."""
    if isinstance(value, list):
        return {f"{name}[{j}]": v for j, v in enumerate(value)}
    return {name: value}


# --------------------------------------------------------------------------------------------
# The result columns: the one log schema's UNIT.GROUP.ELEMENT_UNIT (docs/logs.md)
# --------------------------------------------------------------------------------------------

#: The per-sample result groups (docs/sweeps.md, "Columns of a row"): final RMS of the true
#: tracking error per tracked coordinate (rad, m), peak applied |effort| per joint (N m, N),
#: and that peak over the joint's limit (dimensionless, ``_1``).
RMS, PEAK, RATIO = "final_rms", "peak_torque", "torque_ratio"
GROUPS = (RMS, PEAK, RATIO)


def rms_column(unit: str, coord: str, position_unit: str) -> str:
    """``arm1.final_rms.x_m``: a tracked coordinate's final RMS (``position_unit`` rad | m)."""
    return f"{unit}.{RMS}.{coord}_{position_unit}"


def peak_column(unit: str, joint: str, position_unit: str) -> str:
    """``arm1.peak_torque.joint1_N_m``, ``mechanism.peak_torque.slider.d1_N``: a joint's peak
    |effort| (its position unit, rad | m, decides N m or N)."""
    return f"{unit}.{PEAK}.{joint}_{EFFORT_UNIT[position_unit]}"


def ratio_column(unit: str, joint: str) -> str:
    """``arm1.torque_ratio.joint1_1``: a joint's peak |effort| over its limit."""
    return f"{unit}.{RATIO}.{joint}_1"


def group(column: str) -> str | None:
    """The result group of a column named by :func:`rms_column` & co., else None (an input,
    ``success``, ...). Unit names hold no dot, so the group is the second dotted part."""
    parts = column.split(".", 2)
    return parts[1] if len(parts) == 3 and parts[1] in GROUPS else None


def columns(names, wanted: str) -> list[str]:
    """The columns of one result group among ``names``, in their order."""
    return [c for c in names if group(c) == wanted]


def label(column: str) -> str:
    """A result column without its group: ``arm1.x_m`` for ``arm1.final_rms.x_m``."""
    unit, _, rest = column.split(".", 2)
    return f"{unit}.{rest}"


def legacy_name(column: str) -> str | None:
    """The schema's name of a column that a sweep of cochlea 0.x wrote before the columns
    followed the log schema (``final_rms.UNIT.COORD_UNIT``, ``peak_torque.UNIT.JOINT_Nm`` or
    ``_N``, ``torque_ratio.UNIT.JOINT``), else None."""
    old, dot, rest = column.partition(".")
    if not dot or old not in GROUPS or "." not in rest:
        return None
    unit, _, element = rest.partition(".")
    if old == RATIO:
        return f"{unit}.{RATIO}.{element}_1"
    if old == PEAK and element.endswith("_Nm"):
        element = element[:-len("_Nm")] + "_N_m"
    return f"{unit}.{old}.{element}"


def upgrade(table: pa.Table) -> pa.Table:
    """``table`` with a legacy part file's result columns renamed to the schema's (a folder
    written by an older cochlea-sweep or cochlea-tune is read as a new one); a table whose
    columns already follow the schema is returned as it is."""
    names = table.column_names
    if any(group(c) for c in names):
        return table
    renamed = [legacy_name(c) or c for c in names]
    return table if renamed == names else table.rename_columns(renamed)


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
    write_atomic(out / "spec.toml", spec.text.encode("utf-8"))
    # The manifest last: a folder with it is a whole sweep folder.
    write_atomic(out / MANIFEST, (json.dumps(data, indent=1) + "\n").encode("utf-8"))


def read_manifest(out: Path) -> Manifest:
    path = out / MANIFEST
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SweepFolderError(f"{out}: not a sweep folder (no {MANIFEST}): give the --out "
                               "of a cochlea-sweep run") from None
    except NotADirectoryError:  # DIR a file (or under one): not a damaged manifest
        what = (f"it is {kind_words(os.stat(out).st_mode)}" if out.exists() and not out.is_dir()
                else "not a folder")
        raise SweepFolderError(f"{out}: not a sweep folder ({what}): give the --out of a "
                               "cochlea-sweep run") from None
    except (OSError, ValueError) as exc:
        raise FolderDamaged(f"{path}: unreadable sweep manifest "
                            f"({getattr(exc, 'strerror', None) or exc})") from None
    if not isinstance(data, dict):
        raise FolderDamaged(f"{path}: damaged sweep manifest: expected a JSON object, got "
                            f"{type(data).__name__}")
    if data.get("format") != MANIFEST_FORMAT:
        raise FolderDamaged(f"{path}: damaged sweep manifest: format: expected "
                            f"{MANIFEST_FORMAT!r}, got {data.get('format')!r}")
    fields = {"digest": "a string", "robot": "a string", "space": "a string",
              "spec_text": "a string", "scenario_text": "a string",
              "scenario_path": "a file path", "spec_path": "a file path"}
    for key, what in fields.items():
        value = data.get(key)
        if not isinstance(value, str) or (what == "a file path" and not Path(value).name):
            raise FolderDamaged(f"{path}: damaged sweep manifest: {key}: expected {what}, got "
                                f"{value!r:.80}")
    total = data.get("total")
    if not isinstance(total, int) or isinstance(total, bool) or total < 1:
        raise FolderDamaged(f"{path}: damaged sweep manifest: total: expected a positive "
                            f"integer, got {total!r:.80}")
    return Manifest(data["digest"], total, data["robot"], data["space"], data["spec_text"],
                    data["scenario_text"], data["scenario_path"], data["spec_path"])


def check(out: Path, spec: Spec) -> bool:
    """Whether ``out`` is this spec's sweep folder (to resume); False: new or empty. Any other
    folder is refused. Writes nothing."""
    check_out(out)
    if out.is_dir() and any(p.name != LOCK for p in out.iterdir()):
        if not os.path.lexists(out / MANIFEST):
            raise SweepFolderError(f"--out {out}: expected a new or empty folder, or a sweep "
                                   "folder to resume; it holds other files")
        manifest = read_manifest(out)
        if manifest.digest != spec.digest:
            raise SweepFolderError(f"--out {out}: made by a different spec or scenario (hash "
                                   f"{manifest.digest[:12]}, this one {spec.digest[:12]}): give "
                                   "a new --out, or the spec that made it to resume")
        return True
    return False


def claim(out: Path, lock: str = LOCK, program: str = "cochlea-sweep",
          error: type[CochleaError] | None = None) -> tuple[int, list[Path]]:
    """Create ``out`` if it is missing and lock it (:func:`hold`): the lock is held before
    anything in the folder is written or removed. Returns the lock and the folders created
    (removed again when the lock is refused)."""
    created = make_folder(out)
    try:
        return hold(out, lock, program, error), created
    except CochleaError:
        if created:
            remove_ours(out / lock)
        remove_folders(created)
        raise


def prepare(out: Path, spec: Spec) -> None:
    """With the folder's lock held (:func:`claim`): a new (or empty) folder becomes this
    spec's (:func:`check` first); half-written parts of a killed run are removed."""
    if not check(out, spec):
        make_folder(out)  # made by claim() already; a caller without the lock needs it too
        write_manifest(out, spec)
    parts = out / PARTS
    try:
        parts.mkdir(exist_ok=True)
    except OSError as exc:
        raise WriteFailed(f"{parts}: cannot create it ({exc.strerror})") from None
    if not parts.is_dir() or parts.is_symlink():
        raise FolderDamaged(f"{parts}: expected the sweep's folder of part files, got "
                            "something else: move it away and run the same command again")
    clean_temporary(parts)


def discard(out: Path, created: list[Path], lock: str = LOCK) -> None:
    """Undo :func:`claim` and :func:`prepare` of a new folder that ran nothing: what this run
    wrote there is removed, then the folders it created (only while empty)."""
    if not created:
        return
    for name in (MANIFEST, "spec.toml", lock):
        remove_ours(out / name)
    clean_temporary(out)
    with contextlib.suppress(OSError):
        (out / PARTS).rmdir()
    remove_folders(created)


def hold(out: Path, lock: str = LOCK, program: str = "cochlea-sweep",
         error: type[CochleaError] | None = None) -> int:
    """Lock ``out`` for this process (``lock``, a file in it): a second sweep on the same folder
    would run the same missing samples and write them twice (``cochlea-tune`` locks its folder
    the same way). The lock file stays (removing it would let a third process lock a new file
    while a second still holds the old one)."""
    try:
        fd = os.open(out / lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o644)
    except OSError as exc:
        raise (error or SweepFolderError)(f"--out {out}: cannot write its lock file {lock} "
                                          f"({exc.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise (error or SweepFolderError)(f"--out {out}: its lock file {lock} is not a "
                                          "regular file: move it away")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise (error or SweepFolderError)(f"--out {out}: cannot lock it ({exc.strerror})"
                                              ) from None
        raise FolderBusy(
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
    sink = pa.BufferOutputStream()
    pq.write_table(pa.Table.from_pylist(rows), sink)
    write_atomic(final, sink.getvalue().to_pybytes())
    return final


#: The columns of every row (docs/sweeps.md, "Columns of a row"), in every sweep's part files
#: since the first: what a resume and the report read besides the inputs and the per-unit
#: results.
ROW_COLUMNS = ("sample", "grid", "draw", "converged", "diverged", "convergence_ratio",
               "estimate_bound_hit", "stop_rule", "stop_time_s", "saturated_periods", "success",
               "wall_s")
_PART_NAME = re.compile(r"part-(\d{9})-(\d{9})\.parquet")
_MOVE_AWAY = "; move it away and run the same command to run its samples again"


def _part_samples(f: Path, names: list[str], samples: pa.ChunkedArray | None,
                  total: int) -> list[int]:
    """The samples of part file ``f`` (its columns ``names``, its ``sample`` column), checked:
    every row column there, ``sample`` whole numbers in ``0..total-1``, each once, from the
    first to the last its name says; else :class:`FolderDamaged` naming it (a file that is
    not one of this sweep's batches: a resume would skip or repeat samples, the report count
    them wrongly)."""
    damaged = f"{f}: not a part file of this sweep"
    missing = [c for c in ROW_COLUMNS if c not in names]
    if missing:
        raise FolderDamaged(f"{damaged} (no column {missing[0]!r}){_MOVE_AWAY}")
    if samples is None or not pa.types.is_integer(samples.type) or samples.null_count:
        what = "none" if samples is None else f"{samples.type}" + (
            f" with {samples.null_count} empty" if samples.null_count else "")
        raise FolderDamaged(f"{damaged} (sample: expected whole numbers, got {what})"
                            f"{_MOVE_AWAY}")
    values = samples.to_pylist()
    if not values:
        raise FolderDamaged(f"{damaged} (no rows){_MOVE_AWAY}")
    outside = [v for v in values if not 0 <= v < total]
    if outside:
        raise FolderDamaged(f"{damaged} (sample {outside[0]}: expected 0 to {total - 1}, the "
                            f"sweep's {total} samples){_MOVE_AWAY}")
    if len(set(values)) != len(values):
        twice = next(v for v in values if values.count(v) > 1)
        raise FolderDamaged(f"{damaged} (sample {twice} in two rows){_MOVE_AWAY}")
    m = _PART_NAME.fullmatch(f.name)
    first, last = min(values), max(values)
    if m is None or (int(m[1]), int(m[2])) != (first, last):
        raise FolderDamaged(f"{damaged} (its rows are samples {first} to {last}: its name "
                            f"would be part-{first:09d}-{last:09d}.parquet){_MOVE_AWAY}")
    return values


def _part_files(out: Path) -> list[Path]:
    return sorted((out / PARTS).glob("part-*.parquet"))


def _once(f: Path, values: list[int], seen: dict[int, Path]) -> None:
    """Each sample in one part file only (a copy of a part under another name: counted twice)."""
    for v in values:
        other = seen.setdefault(v, f)
        if other is not f:
            raise FolderDamaged(f"{f}: not a part file of this sweep (sample {v} is also in "
                                f"{other.name}){_MOVE_AWAY}")


def read(out: Path, total: int | None = None) -> pa.Table:
    """Every finished sample's row, sorted by sample (an empty table when there is none); each
    part file checked (:func:`_part_samples`). ``total``: the sweep's samples (default: its
    manifest's)."""
    files = _part_files(out)
    if not files:
        return pa.table({"sample": pa.array([], pa.int64())})
    total = read_manifest(out).total if total is None else total
    tables, seen = [], {}
    for f in files:
        try:
            table = upgrade(pq.read_table(f))
        except (OSError, pa.ArrowException) as exc:
            raise FolderDamaged(f"{f}: unreadable part file ({exc}){_MOVE_AWAY}") from None
        sample = table["sample"] if "sample" in table.column_names else None
        _once(f, _part_samples(f, table.column_names, sample, total), seen)
        tables.append(table)
    try:
        table = pa.concat_tables(tables, promote_options="default")
    except pa.ArrowException:
        # A column of one type in a file and another in the next: name the first such file.
        for f, t in zip(files[1:], tables[1:]):
            try:
                pa.unify_schemas([tables[0].schema, t.schema])
            except pa.ArrowException as exc:
                raise FolderDamaged(f"{f}: not a part file of this sweep (its columns do not "
                                    f"match {files[0].name}'s: {exc}){_MOVE_AWAY}") from None
        raise
    return table.sort_by("sample")


def done(out: Path, total: int | None = None) -> set[int]:
    """The samples already in the folder's part files (each checked: :func:`_part_samples`).
    ``total``: the sweep's samples (default: its manifest's)."""
    if not (out / PARTS).is_dir() or not _part_files(out):
        return set()
    total = read_manifest(out).total if total is None else total
    seen: dict[int, Path] = {}
    for f in _part_files(out):
        try:
            names = upgrade(pq.read_schema(f).empty_table()).column_names
            sample = pq.read_table(f, columns=["sample"])["sample"] if "sample" in names \
                else None
        except (OSError, pa.ArrowException) as exc:
            raise FolderDamaged(f"{f}: unreadable part file ({exc}){_MOVE_AWAY}") from None
        _once(f, _part_samples(f, names, sample, total), seen)
    return set(seen)
