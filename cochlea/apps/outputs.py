"""Where the command-line programs write: output folders checked before anything moves, claimed
by one run at a time, removed again when a start fails, and files that a reader never sees
half written.

The rules (docs/runtime.md, "Output folders"):

- An ``--out`` that cannot become a folder of ours (a file, a device such as /dev/null, a path
  under a file, a place we may not write, a folder that already holds something) is refused in
  one line naming the option, before anything is created or moves.
- A default folder is created with ``mkdir`` (never ``exist_ok``): two runs started in the same
  second get two folders (``NAME``, ``NAME-2``, ...).
- A claimed folder holds a lock file locked with ``flock`` for the life of the run; a second run
  given the same ``--out`` is refused. The kernel drops the lock when a process dies, so a
  killed run never blocks a retry.
- A start that fails before the run removes what it created, so the identical retry works; once
  the run has produced a log nothing is ever removed.
- Files are written to a temporary name in the same folder and renamed (``os.replace``), so a
  reader (or a second interrupt, or a full disk) never leaves a half file under the real name
  (:mod:`cochlea.files`, which every tool's output checks and writes share).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import signal
import stat
from pathlib import Path

from .. import files
from ..console import STOP_SIGNALS, stop_signals_raise
from ..errors import CochleaError, printable

#: The lock file of a claimed folder (removed when the run ends).
LOCK_NAME = ".cochlea.lock"
#: Default folders tried for one name before giving up (``NAME``, ``NAME-2``, ...).
MAX_SUFFIX = 1000
#: Bytes of one value in log.csv: ``%.10g`` (up to 10 digits, a sign, a point, an exponent)
#: and the comma.
CSV_VALUE_BYTES = 17
#: Room left for summary.json and the figures beyond the logs' own estimate.
REPORT_MARGIN_BYTES = 16 * 2**20


class ReportError(Exception):
    """Part of a run's report could not be written (full disk, I/O error): names what was lost
    and what is kept. Not a user error: the run itself happened."""

    def __str__(self) -> str:
        return printable(super().__str__())  # one line, whatever the folder's name holds

    def __init__(self, folder: Path, lost: list[str], cause: Exception):
        self.folder, self.lost, self.cause = folder, lost, cause
        disk = isinstance(cause, OSError)
        # A figure that cannot be drawn (values matplotlib cannot scale: 1e308, an overflow)
        # is not a disk's failure: its own words, and no advice to free space.
        reason = (getattr(cause, "strerror", None) or str(cause)) if disk else \
            f"a figure could not be drawn: {type(cause).__name__}: {cause}"
        kept = sorted(p.name for p in folder.iterdir()
                      if p.is_file() and not p.name.startswith(".")) if folder.is_dir() else []
        super().__init__(
            f"the report could not be written in full ({reason}): lost "
            + ", ".join(lost) + "; kept in " + str(folder) + ": "
            + (", ".join(kept) if kept else "nothing")
            + (" (log.bin is the whole raw log; log.columns.json names its columns)"
               if "log.bin" in kept else "")
            + (". Free some space before the next run" if disk else ""))


# --------------------------------------------------------------------------------------------
# Checks that create nothing
# --------------------------------------------------------------------------------------------


def _kind(mode: int) -> str:
    return "not a folder" if stat.S_ISDIR(mode) else files.kind(mode).replace(" (FIFO)", "")



def _lock_owner(folder: Path) -> str | None:
    """The pid written in ``folder``'s lock file while another process holds it, else None."""
    try:
        fd = os.open(folder / LOCK_NAME, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return (os.read(fd, 64).decode(errors="replace").strip() or "?")
    finally:
        os.close(fd)  # also drops the shared lock taken to test it
    return None


def check_folder(path: Path, option: str = "--out", *, empty: bool = True,
                 allow: tuple[str, ...] = ()) -> None:
    """Refuse ``path`` as an output folder unless it is, or can become, a folder we may write
    (and, with ``empty``, one that holds nothing but the names in ``allow``). Creates nothing."""
    where = f"{option} {path}"
    problem = files.folder_problem(path)
    if problem is not None:
        raise CochleaError(_folder_message(where, problem))
    if not os.path.lexists(path):
        return
    owner = _lock_owner(Path(path))
    if owner is not None:
        raise CochleaError(f"{where} is in use by another run (pid {owner}): wait for it "
                           "to end or choose another folder")
    if empty:
        try:
            # A lock file nobody holds is a run killed before it wrote anything.
            others = [p.name for p in Path(path).iterdir()
                      if p.name not in allow and p.name != LOCK_NAME]
        except OSError as exc:
            raise CochleaError(f"{where}: cannot list the folder ({exc.strerror})") from None
        if others:
            raise CochleaError(f"{where} exists and is not empty: choose a new folder "
                               "(runs never overwrite a log)")


def _folder_message(where: str, p: files.Problem) -> str:
    """cochlea-run's words for a :class:`cochlea.files.Problem` of an output folder."""
    return {
        "unusable": f"{where}: cannot use it ({p.reason}): name a new or empty folder",
        "not_folder": f"{where} is {_kind(p.mode or 0)}, not a folder: name "
                      "a new or empty folder",
        "not_writable": f"{where}: the folder is not writable: name a folder you may write",
        "ancestor_unusable": f"{where}: cannot create it under {p.path} ({p.reason})",
        "ancestor_not_folder": f"{where}: cannot create it, {p.path} is "
                               f"{_kind(p.mode or 0)}, not a folder",
        "ancestor_not_writable": f"{where}: cannot create it, {p.path} is not writable: name "
                                 "a folder you may write",
    }[p.code]


def free_bytes(path: Path) -> int:
    """Bytes an unprivileged user may still write on the disk that holds (or would hold)
    ``path``."""
    return shutil.disk_usage(files.existing_ancestor(path)).free


def log_bytes(setups, periods: int, realtime: bool) -> int:
    """An estimate of the bytes of a run's logs: log.bin (real time, float64 rows) and
    log.csv (as :func:`cochlea.apps.report.columns` lays it out), plus room for the rest."""
    raw = 1 + 4  # time, then the four timing columns
    csv = 1 + (4 if realtime else 0)
    for u in setups:
        nq, nd, n_p = u.controller_model.nq, u.controller.n_desired, u.controller.n_params
        # log.bin: q, qd, tau, the errors, p_hat, the current (drives that measure it), the
        # true q and qd (simulated robot): both counted, an estimate on the high side.
        raw += 3 * nq + nd + nq + n_p + nq + 2 * nq
        # log.csv: as log.bin's, the desired and its rate, the pose; then (a simulated run)
        # the true q, qd, pose and error.
        csv += 2 * nq + 3 * nd + 2 * nq + n_p + len(u.task_names)
        csv += 2 * nq + len(u.task_names) + nd
    total = periods * csv * CSV_VALUE_BYTES
    if realtime:
        total += periods * raw * 8
    return total + REPORT_MARGIN_BYTES


def check_free_space(path: Path, need: int, option: str, what: str) -> None:
    """Refuse a run whose logs will not fit on the disk of ``path``, before anything moves."""
    free = free_bytes(path)
    if need > free:
        raise CochleaError(f"{option} {path}: the run's log needs about {_size(need)} ({what}) "
                           f"but only {_size(free)} are free on that disk: free some space, "
                           f"choose another {option} or a shorter --duration")


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError  # pragma: no cover


# --------------------------------------------------------------------------------------------
# A claimed folder
# --------------------------------------------------------------------------------------------


class OutputFolder:
    """A folder this process writes into, locked for it until :meth:`release`.

    ``track`` the files written before the run starts; :meth:`discard` removes them and the
    folders created for the run, but only while the folder holds nothing else (a log is never
    removed)."""

    def __init__(self, path: Path, created: list[Path], lock_fd: int, option: str):
        self.path, self.created, self.option = path, created, option
        self._lock_fd: int | None = lock_fd
        self._tracked: set[str] = set()

    @property
    def lock_path(self) -> Path:
        return self.path / LOCK_NAME

    def track(self, path: Path) -> Path:
        self._tracked.add(Path(path).name)
        return path

    def discard(self) -> None:
        """Undo a failed start: remove what it created, if nothing else was written since."""
        with contextlib.suppress(OSError):
            names = {p.name for p in self.path.iterdir()} - {LOCK_NAME}
            if not names <= self._tracked:
                return  # something else (a log) is there: keep everything
            for name in names:
                (self.path / name).unlink()
        self.release()
        for folder in reversed(self.created):  # innermost first
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty: never remove what others put there

    def release(self) -> None:
        """Remove the lock file, then drop the lock (in that order: a run waiting for it finds
        the folder's contents, never a stale lock)."""
        if self._lock_fd is None:
            return
        with contextlib.suppress(OSError):
            self.lock_path.unlink()
        os.close(self._lock_fd)
        self._lock_fd = None


def _mkdir_missing(path: Path, option: str) -> list[Path]:
    """Create ``path``'s missing parents (not ``path``); return those created, outermost
    first."""
    missing = []
    parent = Path(path).parent
    while not os.path.lexists(parent):
        missing.append(parent)
        parent = parent.parent
    created = []
    for folder in reversed(missing):
        try:
            folder.mkdir()
        except FileExistsError:
            continue  # another run made it in the meantime: fine, it is not ours to remove
        except OSError as exc:
            _rmdirs(created)
            raise CochleaError(f"{option} {path}: cannot create {folder} ({exc.strerror})"
                               ) from None
        created.append(folder)
    return created


def _rmdirs(created: list[Path]) -> None:
    for folder in reversed(created):
        with contextlib.suppress(OSError):
            folder.rmdir()


def _lock(path: Path, option: str, created: list[Path]) -> int:
    """Lock ``path`` for this process, or refuse: another run holds it, or it is not empty."""
    lock_path = path / LOCK_NAME
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        _rmdirs(created)
        raise CochleaError(f"{option} {path}: cannot write in the folder ({exc.strerror})"
                           ) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise CochleaError(f"{option} {path}: cannot lock the folder ({exc.strerror})"
                               ) from None
        owner = _lock_owner(path) or "?"
        raise CochleaError(f"{option} {path} is in use by another run (pid {owner}): wait "
                           "for it to end or choose another folder") from None
    try:
        same = os.fstat(fd).st_ino == os.stat(lock_path).st_ino
        others = [p.name for p in path.iterdir() if p.name != LOCK_NAME]
    except OSError:
        same, others = False, []
    if not same or others:
        # The lock was another run's, released as it ended: the folder holds its results now.
        os.close(fd)
        raise CochleaError(f"{option} {path} exists and is not empty: choose a new folder "
                           "(runs never overwrite a log)")
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def claim(path: Path, option: str = "--out") -> OutputFolder:
    """Create (or take, if it exists and is empty) the folder ``path`` and lock it."""
    check_folder(path, option, allow=(LOCK_NAME,))
    created = _mkdir_missing(path, option)
    try:
        path.mkdir()
        created.append(path)
    except FileExistsError:
        pass  # an empty folder the user made (or a racing run: the lock decides)
    except OSError as exc:
        _rmdirs(created)
        raise CochleaError(f"{option} {path}: cannot create the folder ({exc.strerror})"
                           ) from None
    return OutputFolder(path, created, _lock(path, option, created), option)


def claim_new(parent: Path, name: str, option: str = "--out") -> OutputFolder:
    """A new folder ``parent/name`` (or ``name-2``, ``name-3``, ...) that no other run has,
    even one started in the same second: ``mkdir`` either creates it or fails."""
    what = f"the default output folder {parent / name}"
    check_folder(parent, what, empty=False)
    created = _mkdir_missing(parent / name, what)
    for i in range(1, MAX_SUFFIX + 1):
        path = parent / (name if i == 1 else f"{name}-{i}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            _rmdirs(created)
            raise CochleaError(f"cannot create {what} ({exc.strerror}): run from a folder you "
                               f"may write, or give {option} DIR") from None
        created.append(path)
        return OutputFolder(path, created, _lock(path, option, created), option)
    _rmdirs(created)
    raise CochleaError(f"{parent} already holds {MAX_SUFFIX} folders named {name}*: give "
                       f"{option} DIR")


# --------------------------------------------------------------------------------------------
# Atomic files
# --------------------------------------------------------------------------------------------


def check_output_file(path: Path, option: str, suffix: str,
                      error: type[CochleaError] = CochleaError,
                      run_dir: Path | None = None) -> None:
    """Refuse an output file that exists and is not a regular file, or whose folder is missing
    or cannot be written in (probed: :func:`cochlea.files.file_problem`), or that is one of the
    files of ``run_dir``, the run folder being read (:func:`cochlea.files.run_file_of`: its log,
    summary, raw log, column list or figures, by any name); creates nothing (cochlea-mcap's
    ``--out``, cochlea-view's ``--html-out``)."""
    if run_dir is not None and Path(run_dir).is_dir():
        own = files.run_file_of(path, run_dir)
        if own is not None:
            raise error(f"{option} {path} is the run's own {own.name} in {run_dir}: name "
                        f"another {suffix} file (the run's files are never overwritten)")
    p = files.file_problem(path)
    if p is None:
        return
    folder = Path(path).parent
    raise error({
        "unusable": f"{option} {path}: cannot use it ({p.reason})",
        "not_regular": f"{option} {path} exists and is not a regular file: name a new file or "
                       f"an existing {suffix} file to replace",
        "under_file": f"{option} {path}: the folder {folder} does not exist",
        "folder_missing": f"{option} {path}: the folder {folder} does not exist",
        "folder_not_folder": f"{option} {path}: the folder {folder} does not exist",
        "folder_not_writable": f"{option} {path}: the folder {folder} is not writable",
    }[p.code])


def same_path(a: Path, b: Path) -> bool:
    """``a`` and ``b`` name one file: the same existing file (a hard or symbolic link, another
    spelling), or, for names not there yet, the same path once links and ``..`` are resolved."""
    return files.same_file(a, b) or os.path.realpath(a) == os.path.realpath(b)


def refuse_overlap(outputs: list[tuple[str, Path]],
                   inputs: list[tuple[str, Path]] = ()) -> None:
    """Before anything is written: refuse an output that is one of the command's inputs (it
    would be destroyed) or another of its outputs (one would replace the other), in one line
    naming both. ``outputs`` and ``inputs`` are ``(option, path)`` pairs."""
    for i, (option, path) in enumerate(outputs):
        for what, source in inputs:
            if same_path(path, source):
                raise CochleaError(f"{option} {path} is the input {what} {source}: name a new "
                                   "file (an input is never overwritten)")
        for other, earlier in outputs[:i]:
            if same_path(path, earlier):
                raise CochleaError(f"{option} {path} and {other} {earlier} are the same file: "
                                   "name two files")


def refuse_inputs_inside(folder: Path, option: str, inputs: list[tuple[str, Path]]) -> None:
    """Refuse an output ``folder`` that holds (at any depth, or is) one of ``inputs``: the
    generator replaces and removes the files of the folders it writes."""
    root = os.path.realpath(folder)
    for what, source in inputs:
        real = os.path.realpath(source)
        if real == root or real.startswith(root.rstrip(os.sep) + os.sep):
            raise CochleaError(f"{option} {folder} holds the input {what} {source}, and "
                               "its files are replaced: choose a folder without inputs in it")


#: A temporary file beside its target, renamed over it once whole (cochlea.files).
atomic_path = files.atomic_path


def write_text_atomic(path: Path, text: str) -> None:
    files.write_atomic(path, text)


# --------------------------------------------------------------------------------------------
# Signals while a run is prepared, runs and is reported
# --------------------------------------------------------------------------------------------


class Interrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP while a run was prepared: nothing moved; ``signum`` says
    which."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


#: The shell's exit code of each stop signal: 130 (SIGINT), 143 (SIGTERM), 129 (SIGHUP).
SIGNAL_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGHUP: 129}
#: How each stop signal is named on the console.
SIGNAL_WORD = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated",
               signal.SIGHUP: "hung up (SIGHUP)"}


@contextlib.contextmanager
def signals_unwind():
    """SIGTERM and SIGHUP raise :class:`Interrupted` (a KeyboardInterrupt) for the section, as
    Ctrl-C does: a tool writing one output file (cochlea-mcap, cochlea-view --html-out)
    unwinds through :func:`atomic_path`, which removes its temporary file, instead of dying
    with it left beside the output. ``signum`` of the exception says which signal; a Ctrl-C is
    a plain KeyboardInterrupt (SIGINT). The previous handlers come back afterwards."""
    with stop_signals_raise(Interrupted):
        yield


def interrupted_exit(exc: BaseException) -> tuple[str, int]:
    """The word and exit code of a KeyboardInterrupt raised by Ctrl-C or
    :func:`signals_unwind`."""
    signum = getattr(exc, "signum", signal.SIGINT)
    return SIGNAL_WORD.get(signum, "interrupted"), SIGNAL_EXIT.get(signum, 130)


class SignalShield:
    """SIGINT, SIGTERM and SIGHUP (a hang-up, handled as SIGTERM) for the life of a run, in
    three phases:

    - ``prepare()``: a signal raises :class:`Interrupted` (the start is undone, nothing moved);
    - ``forward(handler)``: a signal goes to ``handler`` (the loop's own safe stop);
    - ``defer()``: the log and report are being written; a signal is acknowledged on stderr and
      otherwise ignored, however many arrive, so the report is completed;
    - ``ignore()``: all is written and the program exits with the run's own code.
    """

    SIGNALS = STOP_SIGNALS

    def __init__(self, program: str):
        self.program = program
        self.received: list[int] = []
        #: Signals that arrived while preparing (each raised :class:`Interrupted` where it
        #: landed; see :meth:`_raise_pending`).
        self._pending: list[int] = []
        self._mode: object = "prepare"
        self._previous: dict | None = None

    def install(self) -> None:
        self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}

    def restore(self) -> None:
        for s, handler in (self._previous or {}).items():
            signal.signal(s, handler)
        self._previous = None

    def prepare(self) -> None:
        self._mode = "prepare"

    def forward(self, handler) -> None:
        self._raise_pending()
        self._mode = handler

    def defer(self) -> None:
        self._raise_pending()
        self._mode = "defer"

    def _raise_pending(self) -> None:
        """A signal that arrived while preparing raised :class:`Interrupted` where it landed,
        but a library that runs Python's signal handlers itself may swallow that exception
        (CasADi checks for Ctrl-C inside its evaluations: a SIGTERM during the as-fast
        simulation was once lost so, and the run completed with exit 0). It is raised again
        here, before the next phase begins."""
        if self._pending:
            raise Interrupted(self._pending[0])

    def ignore(self) -> None:
        """Everything is written and the program exits: a signal changes nothing now. SIG_IGN,
        not a Python handler: the interpreter resets its own handlers to the default (death
        by the signal) while it shuts down."""
        self._mode = "ignore"
        for s in self.SIGNALS:
            signal.signal(s, signal.SIG_IGN)

    def _handle(self, signum, frame) -> None:
        mode = self._mode
        if mode == "prepare":
            self._pending.append(signum)
            raise Interrupted(signum)
        if mode == "ignore":
            return
        if mode == "defer":
            self.received.append(signum)
            # os.write, not print: the main thread may be inside a print to stderr right now.
            with contextlib.suppress(OSError):
                os.write(2, f"{self.program}: finishing the log, please wait (interrupts are "
                            "ignored until the report is written)\n".encode())
            return
        mode(signum, frame)
