"""One place for the files the tools write: an output path checked before anything runs, and
files written whole or not at all (docs/runtime.md, "Output folders").

The checks create nothing the user sees (the writability probe's file is removed at once) and
raise nothing of a tool's: they return a :class:`Problem` (what is wrong, and where), and each
tool words it in its own one-line message with its own exit code (``cochlea-run``'s
``--out``, ``cochlea-sweep``'s, ``cochlea-identify``'s, ``cochlea-mcap``'s, ...).

- :func:`folder_problem`: an output *folder* (it exists and is a folder we may write, or its
  nearest existing ancestor is one, so that it can be created).
- :func:`file_problem`: an output *file* (a new name, or an existing regular file to replace,
  in an existing folder this process can write in: probed by creating and removing a
  temporary file there, which sees a read-only file system or another user's folder even as
  root, where ``os.access`` says yes).

The writes (:func:`atomic_path`, :func:`write_atomic`, :class:`Staged`): the data goes to a
new temporary file beside the target (same folder, so the same disk: the rename is atomic;
named ``.STEM.XXXXXXXX.tmpSUFFIX``, hidden, the target's suffix kept because matplotlib picks
the format by it), is flushed to disk, and only then renamed over the target (or linked to a
new name, where nothing may be replaced). On any failure, an exception or a signal that
unwinds (SIGINT, or a tool's SIGTERM/SIGHUP handler that raises), the temporary file is
removed and the target is as it was: a reader sees the old file or the whole new one, never a
part. A process killed outright (SIGKILL, a SIGTERM nobody handles) can leave only a
temporary file, never a partial target; :func:`clean_temporary` removes those (a resumed
sweep does).
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

#: What a temporary file's name holds between its target's stem and suffix.
TMP_MARK = ".tmp"
#: The probe's name prefix (created and removed at once by :func:`probe`).
PROBE_PREFIX = ".cochlea-probe-"


def kind(mode: int) -> str:
    """What a path of ``mode`` (``os.lstat`` or ``os.stat``) is, in words."""
    for test, name in ((stat.S_ISREG, "a file"), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a pipe (FIFO)"),
                       (stat.S_ISCHR, "a device"), (stat.S_ISBLK, "a device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def read_regular(path: str | Path, limit: int) -> bytes:
    """At most ``limit + 1`` bytes of the regular file at ``path`` (one more than ``limit``
    says the file is larger: the caller words that). An input that is not a regular file --
    a FIFO, a device, a socket -- is refused before a byte is read: opening or reading one
    blocks until a writer comes, or never ends (OSError EINVAL, its kind in the message); a
    folder is IsADirectoryError; a missing file FileNotFoundError; a NUL byte in the name
    ValueError, as ``open`` raises them. The file is opened without blocking and without
    becoming the controlling terminal, so a pipe or a serial port named by mistake costs
    nothing."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(errno.EISDIR, "a folder, not a file", str(path))
        if not stat.S_ISREG(mode):
            raise OSError(errno.EINVAL, f"{kind(mode)}, not a regular file", str(path))
        os.set_blocking(fd, True)
        chunks, left = [], limit + 1
        while left > 0 and (chunk := os.read(fd, min(left, 1 << 20))):
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def existing_ancestor(path: Path) -> Path:
    """The nearest part of ``path`` (itself included, made absolute) that exists."""
    path = Path(os.path.abspath(path))
    while not os.path.lexists(path):
        path = path.parent
    return path


@dataclass(frozen=True)
class Problem:
    """Why a path cannot take an output: ``code`` (one of :data:`CODES`), ``path`` the place
    it concerns (the output itself, its folder or an ancestor), ``mode`` that place's mode
    where its kind matters, ``reason`` the system's words (``strerror``) where it gave any."""

    code: str
    path: Path
    mode: int | None = None
    reason: str | None = None

    @property
    def kind(self) -> str:
        return kind(self.mode) if self.mode is not None else "missing"


#: The codes of :class:`Problem`, and what each means.
CODES = {
    # a folder (folder_problem)
    "unusable": "the path exists but cannot be examined (a dangling link, a loop, no access)",
    "not_folder": "the path exists and is not a folder (mode: what it is)",
    "not_writable": "the folder exists and this process may not write in it",
    "ancestor_unusable": "the path is missing and its nearest existing ancestor cannot be "
                         "examined",
    "ancestor_not_folder": "the path is missing and its nearest existing ancestor is not a "
                           "folder (mode: what it is)",
    "ancestor_not_writable": "the path is missing and its nearest existing ancestor is not "
                             "writable",
    # a file (file_problem)
    "symlink": "the path is a symbolic link (refused where links are)",
    "not_regular": "the path exists and is not a regular file (mode: what it is)",
    "exists": "the path exists and nothing may be replaced",
    "is_input": "the path is the same file as an input (path: that input)",
    "hard_links": "the path is a file with other hard links (replacing it parts them)",
    "under_file": "the folder is missing and the nearest existing ancestor is not a folder "
                  "(path: that ancestor)",
    "folder_missing": "the file's folder does not exist (path: the folder)",
    "folder_not_folder": "the file's folder is not a folder (path: it)",
    "folder_not_writable": "the file's folder cannot be written in (path: the folder)",
}


def probe(folder: Path) -> str | None:
    """Create and remove a temporary file in ``folder``: None when that works, else the
    system's reason (a read-only file system, no permission), whatever ``os.access`` says."""
    try:
        fd, name = tempfile.mkstemp(prefix=PROBE_PREFIX, dir=folder)
    except OSError as exc:
        return exc.strerror or str(exc)
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)
    return None


def writable(folder: Path, probe_it: bool) -> str | None:
    """None when this process can create files in the folder ``folder``, else why not."""
    if probe_it:
        return probe(folder)
    if not os.access(folder, os.W_OK | os.X_OK):
        return os.strerror(13)  # EACCES's words
    return None


def folder_problem(path: Path, *, probe_it: bool = False) -> Problem | None:
    """Why ``path`` cannot be (or become) an output folder, or None. An existing ``path`` must
    be a folder we may write; a missing one needs its nearest existing ancestor to be a folder
    we may write (it is created there). ``probe_it``: test writing by creating a file
    (:func:`probe`) rather than asking ``os.access``. Creates nothing."""
    path = Path(path)
    if os.path.lexists(path):
        try:
            mode = os.stat(path).st_mode
        except OSError as exc:  # a dangling symbolic link, a loop of them, no permission
            return Problem("unusable", path, reason=exc.strerror)
        if not stat.S_ISDIR(mode):
            return Problem("not_folder", path, mode)
        if (reason := writable(path, probe_it)) is not None:
            return Problem("not_writable", path, mode, reason)
        return None
    base = existing_ancestor(path)
    try:
        mode = os.stat(base).st_mode
    except OSError as exc:
        return Problem("ancestor_unusable", base, reason=exc.strerror)
    if not stat.S_ISDIR(mode):
        return Problem("ancestor_not_folder", base, mode)
    if (reason := writable(base, probe_it)) is not None:
        return Problem("ancestor_not_writable", base, mode, reason)
    return None


def same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


#: The files a run leaves in its folder (docs/logs.md, "The run folder"), besides its figures
#: (``*.png``): a tool that reads a run folder never writes over one of them.
RUN_FILES = ("log.csv", "summary.json", "log.bin", "log.columns.json")


def run_files(folder: Path) -> list[Path]:
    """The run's own files in ``folder`` (:data:`RUN_FILES` and the figures ``*.png``) that
    exist, the run's lock file with them."""
    folder = Path(folder)
    found = [folder / name for name in RUN_FILES + (".cochlea.lock",)
             if os.path.lexists(folder / name)]
    with contextlib.suppress(OSError):
        found += sorted(p for p in folder.iterdir() if p.suffix.lower() == ".png")
    return found


def run_file_of(path: Path, folder: Path) -> Path | None:
    """The file of the run folder ``folder`` that writing ``path`` would replace or stand in
    for, or None: ``path`` is in that folder (by any name of it: a link, ``..``) under one of
    the run's names (:data:`RUN_FILES`, a figure ``*.png``, present or not), or is (a link to,
    another hard link of) one of its files."""
    path = Path(path)
    parent = Path(os.path.abspath(path)).parent
    if same_file(parent, folder):
        name = path.name
        if name in RUN_FILES or name == ".cochlea.lock" or Path(name).suffix.lower() == ".png":
            return Path(folder) / name
    if os.path.lexists(path):
        for own in run_files(folder):
            if same_file(path, own) or os.path.abspath(path) == os.path.abspath(own):
                return own
    return None


def file_problem(path: Path, *, replace: bool = True, links: bool = True,
                 inputs: tuple[Path, ...] = (), hard_links: bool = True,
                 probe_it: bool = True) -> Problem | None:
    """Why ``path`` cannot take an output file, or None: it must be a new name or (with
    ``replace``) an existing regular file, not one of ``inputs``, in an existing folder this
    process can write in (``probe_it``: by creating and removing a file there).

    ``links``: a symbolic link to a regular file is replaced (the link, not the file it points
    to); without it any link is refused. ``hard_links``: a file with other hard links may be
    replaced (parting it from them); without it, refused. Creates nothing."""
    path = Path(path)
    if os.path.lexists(path):
        try:
            lmode = os.lstat(path).st_mode
            mode = os.stat(path).st_mode if links else lmode
        except OSError as exc:
            return Problem("unusable", path, reason=exc.strerror)
        if stat.S_ISLNK(mode):
            return Problem("symlink", path, mode)
        if not stat.S_ISREG(mode):
            return Problem("not_regular", path, mode)
        if not replace:
            return Problem("exists", path, mode)
        for source in inputs:
            if same_file(path, source):
                return Problem("is_input", Path(source), mode)
        if not hard_links and os.stat(path).st_nlink > 1:
            return Problem("hard_links", path, mode)
    parent = Path(os.path.abspath(path)).parent
    if not os.path.lexists(parent):
        ancestor = existing_ancestor(parent)
        if not os.path.isdir(ancestor):
            return Problem("under_file", ancestor)
        return Problem("folder_missing", parent)
    if not os.path.isdir(parent):
        return Problem("folder_not_folder", parent)
    if (reason := writable(parent, probe_it)) is not None:
        return Problem("folder_not_writable", parent, reason=reason)
    return None


# --------------------------------------------------------------------------------------------
# Whole files
# --------------------------------------------------------------------------------------------


def default_mode(path: Path | None = None) -> int:
    """The permission bits a new file gets: ``path``'s own when it exists (a replaced file keeps
    its mode), else what the umask leaves of 0o666."""
    if path is not None:
        with contextlib.suppress(OSError):
            return stat.S_IMODE(os.stat(path).st_mode)
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def temporary(path: Path, keep_suffix: bool = True) -> Path:
    """Create a new empty temporary file beside ``path`` (``.STEM.XXXXXXXX.tmpSUFFIX``; without
    ``keep_suffix`` ``.NAME.XXXXXXXX.tmp``, which no ``*.SUFFIX`` glob of the folder matches),
    created exclusively (nothing there is opened or followed), with the mode ``path`` will
    have, and return its name. An OSError names ``path`` as its filename."""
    path = Path(path)
    prefix, suffix = ((f".{path.stem}.", f"{TMP_MARK}{path.suffix}") if keep_suffix
                      else (f".{path.name}.", TMP_MARK))
    try:
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix,
                                    dir=path.parent if str(path.parent) else ".")
    except OSError as exc:
        exc.filename = str(path)
        raise
    os.close(fd)
    try:
        os.chmod(name, default_mode(path))  # mkstemp's 0600 would tighten the file
    except BaseException:
        remove_regular(Path(name))
        raise
    return Path(name)


def is_temporary(path: Path) -> bool:
    """A temporary file of this module (``.STEM.XXXXXXXX.tmpSUFFIX``), or an older writer's
    (``.NAME.XXXX.tmp``, ``NAME.tmp``)."""
    name = Path(path).name
    return name.endswith(TMP_MARK) or (name.startswith(".") and TMP_MARK + "." in name)


def remove_regular(path: Path) -> None:
    """Unlink ``path`` only if it is a regular file (never a link, FIFO, device, folder)."""
    with contextlib.suppress(OSError):
        if stat.S_ISREG(os.lstat(path).st_mode):
            os.unlink(path)


def clean_temporary(folder: Path) -> None:
    """Remove the temporary files a killed writer left in ``folder`` (regular files only)."""
    with contextlib.suppress(OSError):
        for p in Path(folder).iterdir():
            if is_temporary(p):
                remove_regular(p)


def sync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def sync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename in it) to disk; where a file system cannot, nothing."""
    with contextlib.suppress(OSError):
        fd = os.open(folder if str(folder) else ".", os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def publish(tmp: Path, path: Path, *, replace: bool = True) -> None:
    """Sync the whole temporary file ``tmp`` and give it the name ``path``: renamed over it
    (``replace``), or linked to it only if nothing has that name (FileExistsError otherwise:
    nothing replaced), then the temporary name removed."""
    sync_file(tmp)
    if replace:
        os.replace(tmp, path)
    else:
        os.link(tmp, path)
        remove_regular(tmp)
    sync_folder(Path(path).parent)


def refuse_non_regular(path: Path) -> None:
    """Raise (an OSError naming ``path``) if ``path`` exists and is not a regular file: a
    write never replaces a folder, a link, a FIFO or a device someone put there."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        raise OSError(0, f"{kind(mode)} is there, not a file", str(path))


@contextlib.contextmanager
def atomic_path(path: Path, *, replace: bool = True, only_files: bool = False,
                keep_suffix: bool = True):
    """Yield a new temporary path beside ``path`` to write (closed, empty); when the block ends
    it is synced and renamed to ``path`` (``replace``; else linked, only if ``path`` is still
    free); when the block raises (an error, a signal that unwinds) it is removed and ``path``
    is as it was. ``only_files``: refuse (OSError) a ``path`` that exists and is not a regular
    file, before anything is written. ``keep_suffix``: the temporary name ends with
    ``path``'s suffix (matplotlib picks a figure's format by it); without it, with ``.tmp``
    (a folder whose ``*.parquet`` must all be whole, :func:`temporary`)."""
    path = Path(path)
    if only_files:
        refuse_non_regular(path)
    tmp = temporary(path, keep_suffix)
    try:
        yield tmp
        publish(tmp, path, replace=replace)
    except BaseException:
        remove_regular(tmp)
        raise


def write_atomic(path: Path, data: bytes | str, *, replace: bool = True,
                 only_files: bool = False, keep_suffix: bool = True) -> None:
    """``data`` (text is written as UTF-8) into ``path``, whole or not at all
    (:func:`atomic_path`)."""
    with atomic_path(path, replace=replace, only_files=only_files,
                     keep_suffix=keep_suffix) as tmp:
        with open(tmp, "wb") as f:
            f.write(data.encode("utf-8") if isinstance(data, str) else data)


class Staged:
    """Several outputs written to temporary names beside their targets and renamed over them
    together by :meth:`commit`, only when all are complete; on failure (an exception, a signal
    that unwinds, or no commit) every temporary file is removed and every target is as it
    was."""

    def __init__(self):
        self._files: list[tuple[Path, Path]] = []  # (temporary, target)

    def __enter__(self) -> Staged:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        self.discard()

    def path(self, target: Path) -> Path:
        """A new temporary file beside ``target`` to write; :meth:`commit` renames it."""
        target = Path(target)
        tmp = temporary(target)
        self._files.append((tmp, target))
        return tmp

    def path_of(self, target: Path) -> Path:
        """The temporary file staged for ``target``."""
        return next(tmp for tmp, t in self._files if t == Path(target))

    def target_of(self, name: str | os.PathLike | None) -> Path | None:
        """The target of the temporary file ``name`` (a failing write names its file), else
        the last one staged (a write on an open file names none), else None."""
        target = next((t for tmp, t in self._files if str(tmp) == str(name)), None)
        if target is None and name is not None:
            return Path(name)
        if target is None and self._files:
            target = self._files[-1][1]
        return target

    def write_text(self, target: Path, text: str) -> None:
        with open(self.path(target), "w", encoding="utf-8") as f:
            f.write(text)

    def commit(self) -> None:
        """Sync every temporary file, then rename each over its target."""
        for tmp, _ in self._files:
            sync_file(tmp)
        for tmp, target in self._files:
            os.replace(tmp, target)
        for folder in {target.parent for _, target in self._files}:
            sync_folder(folder)
        self._files = []

    def discard(self) -> None:
        for tmp, _ in self._files:
            remove_regular(tmp)
        self._files = []
