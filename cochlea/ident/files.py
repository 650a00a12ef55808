"""The files ``cochlea-identify`` and ``cochlea-excite`` read and write, checked before anything
runs (issue 26).

- Inputs: every log is a regular file (a FIFO or a device would block or never end), and no log
  is given twice -- the same content under another name, a copy, a hard or symbolic link -- in
  the fit set, nor as a validation log that is one of the fit logs: the fit would count its
  samples twice and report standard errors too small by sqrt(2) without any sign of it.
- Outputs: each is a new name or an existing regular file (the previous report, replaced as a
  whole) in an existing folder this process may write, probed by creating and removing a
  temporary file there (a read-only file system, a folder of another user). A symbolic link,
  a folder, a FIFO, a device or a socket under that name is refused and left as it is; so is an
  output that names one of the inputs (a log, the description).
- Writes are staged: every output is written to a temporary name in its own folder, and only
  when all of them are complete are they renamed over their targets. A full disk, a read-only
  file system or an I/O error while writing leaves no partial file and every previous file as
  it was (:class:`WriteFailed`).
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

from .. import files
from ..errors import CochleaError


class DuplicateLog(CochleaError):
    """The same log (same content) given twice to a fit, or as a validation log."""


class OutputRefused(CochleaError):
    """An output path that cannot take the file: refused before anything runs."""


class WriteFailed(CochleaError):
    """Writing an output failed (full disk, read-only, I/O error); nothing partial is left and
    every previous file is kept."""


def _kind(mode: int) -> str:
    return files.kind(mode)


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def log_file(folder: str | Path) -> Path:
    """The log.csv of a run folder (or the file itself)."""
    folder = Path(folder)
    return folder / "log.csv" if folder.is_dir() else folder


def run_inputs(folder: str | Path) -> tuple[Path, ...]:
    """The log.csv of a run folder (or the file itself) and every other file of that run
    (summary.json, log.bin, log.columns.json, the figures): an output never replaces one."""
    log = log_file(folder)
    return (log, *(p for p in files.run_files(log.parent) if p.name != log.name))


def check_distinct_logs(fit: list[str | Path], validate: list[str | Path]) -> None:
    """Refuse a log given twice (same content: a copy, a hard or symbolic link, the same path)
    among the fit logs, and a validation log with the content of a fit log. Files that cannot
    be read are left to the log reader, which names what was expected."""
    seen: dict[str, str] = {}
    for role, folders in (("fit", fit), ("validation", validate)):
        for folder in folders:
            file = log_file(folder)
            try:
                if not stat.S_ISREG(os.stat(file).st_mode):
                    continue  # refused by the reader, with its kind
                digest = sha256(file)
            except OSError:
                continue
            if digest in seen:
                first = seen[digest]
                if role == "fit":
                    raise DuplicateLog(
                        f"{folder}: the same log as {first} (identical content, sha256 "
                        f"{digest[:12]}...): a log fitted twice counts its samples twice and "
                        "its standard errors come out too small by sqrt(2); give each log once")
                raise DuplicateLog(
                    f"--validate {folder}: the same log as the fitted {first} (identical "
                    f"content, sha256 {digest[:12]}...): a log validated on itself says nothing "
                    "of the fit; validate on another run")
            if role == "fit":
                seen[digest] = str(folder)


def probe_folder(folder: Path, where: str) -> None:
    """Create and remove a temporary file in ``folder``: refuses a folder this process cannot
    write in (read-only file system, no permission), whatever ``os.access`` says for root."""
    reason = files.probe(folder)
    if reason is not None:
        raise OutputRefused(f"{where}: cannot write in the folder {folder} ({reason}): name a "
                            "file in a folder you may write")


def check_output(path: Path, option: str, inputs: tuple[Path, ...] = (),
                 replace: bool = True) -> None:
    """Refuse ``path`` as an output file unless it is a new name or (with ``replace``) an
    existing regular file, in an existing folder this process may write (probed), and names
    none of ``inputs`` (:func:`cochlea.files.file_problem`). Creates nothing."""
    where = f"{option} {path}"
    p = files.file_problem(path, replace=replace, links=False, inputs=inputs,
                           hard_links=False)
    if p is None:
        return
    raise OutputRefused({
        "unusable": f"{where}: cannot use it ({p.reason})",
        "symlink": f"{where} is a symbolic link: name a new file (a link is never replaced, "
                   "nor the file it points to)",
        "not_regular": f"{where} is {_kind(p.mode or 0)}: expected a new file name or an "
                       "existing regular file",
        "exists": f"{where} exists: name a new file",
        "is_input": f"{where} is the input {p.path}: name a new file (an input is never "
                    "overwritten)",
        "hard_links": f"{where} has other hard links: name a new file (replacing it would "
                      "part it from them)",
        "under_file": f"{where}: {p.path} is a file, not a folder: name a file in a folder",
        "folder_missing": f"{where}: the folder {p.path} does not exist: create it first",
        "folder_not_folder": f"{where}: {p.path} is not a folder: name a file in a folder",
        "folder_not_writable": f"{where}: cannot write in the folder {p.path} ({p.reason}): "
                               "name a file in a folder you may write",
    }[p.code])


class Staged(files.Staged):
    """Outputs written to temporary names in their own folders, renamed over their targets
    together by :meth:`commit` (:class:`cochlea.files.Staged`); on failure (or without a
    commit) every temporary file is removed and every target is as it was, and an OSError
    becomes :class:`WriteFailed` naming the output it was writing."""

    def __exit__(self, kind, exc, tb) -> None:
        failure = self._failure(exc) if isinstance(exc, OSError) else None
        self.discard()
        if failure is not None:
            raise failure from None

    def _failure(self, exc: OSError) -> WriteFailed:
        target = self.target_of(exc.filename)
        return WriteFailed(f"cannot write {target or 'the outputs'} "
                           f"({exc.strerror or exc}): nothing was written; every previous "
                           "output is kept as it was")
