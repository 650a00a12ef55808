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

import contextlib
import hashlib
import os
import stat
import tempfile
from pathlib import Path

from ..errors import CochleaError


class DuplicateLog(CochleaError):
    """The same log (same content) given twice to a fit, or as a validation log."""


class OutputRefused(CochleaError):
    """An output path that cannot take the file: refused before anything runs."""


class WriteFailed(CochleaError):
    """Writing an output failed (full disk, read-only, I/O error); nothing partial is left and
    every previous file is kept."""


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a pipe (FIFO)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


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


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def probe_folder(folder: Path, where: str) -> None:
    """Create and remove a temporary file in ``folder``: refuses a folder this process cannot
    write in (read-only file system, no permission), whatever ``os.access`` says for root."""
    try:
        fd, name = tempfile.mkstemp(prefix=".cochlea-probe-", dir=folder)
    except OSError as exc:
        raise OutputRefused(f"{where}: cannot write in the folder {folder} "
                            f"({exc.strerror}): name a file in a folder you may write") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)


def check_output(path: Path, option: str, inputs: tuple[Path, ...] = (),
                 replace: bool = True) -> None:
    """Refuse ``path`` as an output file unless it is a new name or (with ``replace``) an
    existing regular file, in an existing folder this process may write, and names none of
    ``inputs``. Creates nothing (the probe's file is removed)."""
    where = f"{option} {path}"
    if os.path.lexists(path):
        mode = os.lstat(path).st_mode
        if stat.S_ISLNK(mode):
            raise OutputRefused(f"{where} is a symbolic link: name a new file (a link is never "
                                "replaced, nor the file it points to)")
        if not stat.S_ISREG(mode):
            raise OutputRefused(f"{where} is {_kind(mode)}: expected a new file name or an "
                                "existing regular file")
        if not replace:
            raise OutputRefused(f"{where} exists: name a new file")
        for source in inputs:
            if _same_file(path, source):
                raise OutputRefused(f"{where} is the input {source}: name a new file (an "
                                    "input is never overwritten)")
        if os.stat(path).st_nlink > 1:
            raise OutputRefused(f"{where} has other hard links: name a new file (replacing "
                                "it would part it from them)")
    parent = Path(os.path.abspath(path)).parent
    if not os.path.lexists(parent):
        ancestor = parent
        while not os.path.lexists(ancestor):
            ancestor = ancestor.parent
        if not os.path.isdir(ancestor):
            raise OutputRefused(f"{where}: {ancestor} is a file, not a folder: name a file in "
                                "a folder")
        raise OutputRefused(f"{where}: the folder {parent} does not exist: create it first")
    if not os.path.isdir(parent):
        raise OutputRefused(f"{where}: {parent} is not a folder: name a file in a folder")
    probe_folder(parent, where)


class Staged:
    """Outputs written to temporary names in their own folders, renamed over their targets
    together by :meth:`commit`; on failure (or without a commit) every temporary file is
    removed and every target is as it was."""

    def __init__(self):
        self._files: list[tuple[Path, Path]] = []  # (temporary, target)

    def __enter__(self) -> Staged:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        failure = self._failure(exc) if isinstance(exc, OSError) else None
        self.discard()
        if failure is not None:
            raise failure from None

    def _failure(self, exc: OSError) -> WriteFailed:
        # A write on an open file names none: the file being written is the last one staged.
        name = exc.filename
        target = next((t for tmp, t in self._files if str(tmp) == str(name)), name)
        if target is None and self._files:
            target = self._files[-1][1]
        return WriteFailed(f"cannot write {target or 'the outputs'} "
                           f"({exc.strerror or exc}): nothing was written; every previous "
                           "output is kept as it was")

    def path(self, target: Path) -> Path:
        """A new temporary file beside ``target`` (same folder, same suffix: matplotlib picks
        the format by it) to write; :meth:`commit` renames it to ``target``."""
        target = Path(target)
        try:
            fd, name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}",
                                        dir=target.parent if str(target.parent) else ".")
        except OSError as exc:
            exc.filename = str(target)
            raise
        os.close(fd)
        self._files.append((Path(name), target))
        # mkstemp's 0600 would tighten the file: the previous file's mode, or the umask's.
        try:
            mode = stat.S_IMODE(os.stat(target).st_mode)
        except OSError:
            mask = os.umask(0)
            os.umask(mask)
            mode = 0o666 & ~mask
        os.chmod(name, mode)
        return Path(name)

    def path_of(self, target: Path) -> Path:
        """The temporary file staged for ``target``."""
        return next(tmp for tmp, t in self._files if t == Path(target))

    def write_text(self, target: Path, text: str) -> None:
        tmp = self.path(target)
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    def commit(self) -> None:
        """Sync every temporary file, then rename each over its target."""
        for tmp, _ in self._files:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        for tmp, target in self._files:
            os.replace(tmp, target)
        self._files = []

    def discard(self) -> None:
        for tmp, _ in self._files:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        self._files = []
