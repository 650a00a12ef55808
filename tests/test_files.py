"""cochlea.files: the one place where an output path is checked and a file is written whole.

Each class of defect has one test: a path that cannot take an output (every kind of place, a
missing or read-only folder) comes back as a Problem with its code and creates nothing; a write
that fails at any step (an error in the block, the sync, the rename), or that a signal
interrupts, leaves no temporary file and the previous file as it was; a process killed outright
leaves only a temporary file, which clean_temporary recognises.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from cochlea import files

ROOT = Path(__file__).resolve().parent.parent


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot create a file in: a mode 555 one, or (root ignores modes)
    /sys, which takes no new file whoever asks."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    if os.access(folder, os.W_OK):
        folder.chmod(0o755)
        folder.rmdir()
        return Path("/sys")
    return folder


# ---- checks: every kind of place, and nothing created -----------------------------------------


def places(tmp_path: Path) -> dict[str, Path]:
    """One path of each kind a user may name."""
    (tmp_path / "file").write_text("x")
    (tmp_path / "folder").mkdir()
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    (tmp_path / "link").symlink_to(tmp_path / "file")
    (tmp_path / "hard").write_text("x")
    os.link(tmp_path / "hard", tmp_path / "hard2")
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(tmp_path / "sock"))
    sock.close()
    return {name: tmp_path / name for name in
            ("file", "folder", "fifo", "dangling", "link", "hard", "sock")}


@pytest.mark.parametrize("name, code", [
    ("new", None), ("folder", None), ("missing/deeper", None),
    ("file", "not_folder"), ("fifo", "not_folder"), ("sock", "not_folder"),
    ("dangling", "unusable"), ("file/under", "ancestor_not_folder"),
])
def test_a_folder_that_cannot_take_outputs_is_named_by_its_problem(tmp_path, name, code):
    places(tmp_path)
    before = listing(tmp_path)
    problem = files.folder_problem(tmp_path / name)
    assert (problem and problem.code) == code, problem
    if code == "ancestor_not_folder":
        assert problem.path == tmp_path / "file" and problem.kind == "a file"
    if code == "not_folder":
        assert problem.kind in ("a file", "a pipe (FIFO)", "a socket")
    assert listing(tmp_path) == before


def test_a_read_only_folder_is_refused_as_a_folder_and_as_a_files_folder(tmp_path):
    ro = read_only_folder(tmp_path)
    for probe_it in (True, False) if ro != Path("/sys") else (True,):
        existing = files.folder_problem(ro, probe_it=probe_it)
        assert existing is not None and existing.code == "not_writable", (probe_it, existing)
    below = files.folder_problem(ro / "new" / "run", probe_it=True)
    assert below.code == "ancestor_not_writable" and below.path == ro and below.reason
    problem = files.file_problem(ro / "out.json")
    assert problem.code == "folder_not_writable" and problem.path == ro and problem.reason
    if ro != Path("/sys"):
        assert listing(ro) == []  # the probe's file did not stay


@pytest.mark.parametrize("name, options, code", [
    ("new.json", {}, None),
    ("file", {}, None),
    ("file", {"replace": False}, "exists"),
    ("link", {}, None),                         # the link is replaced, not its file
    ("link", {"links": False}, "symlink"),
    ("dangling", {}, "unusable"),
    ("dangling", {"links": False}, "symlink"),
    ("folder", {}, "not_regular"),
    ("fifo", {}, "not_regular"),
    ("sock", {}, "not_regular"),
    ("hard", {}, None),
    ("hard", {"hard_links": False}, "hard_links"),
    ("missing/out.json", {}, "folder_missing"),
    ("file/out.json", {}, "folder_not_folder"),
    ("file/deeper/out.json", {}, "under_file"),
])
def test_a_file_that_cannot_be_written_is_named_by_its_problem(tmp_path, name, options, code):
    places(tmp_path)
    before = listing(tmp_path)
    problem = files.file_problem(tmp_path / name, **options)
    assert (problem and problem.code) == code, problem
    assert problem is None or problem.code in files.CODES
    assert listing(tmp_path) == before


def test_an_output_that_is_an_input_is_refused(tmp_path):
    (tmp_path / "log.csv").write_text("t\n")
    (tmp_path / "alias.csv").symlink_to(tmp_path / "log.csv")
    problem = files.file_problem(tmp_path / "log.csv", inputs=(tmp_path / "alias.csv",))
    assert problem.code == "is_input" and problem.path == tmp_path / "alias.csv"


# ---- writes: whole or not at all ---------------------------------------------------------------


def test_a_write_is_whole_keeps_the_suffix_and_the_mode(tmp_path):
    target = tmp_path / "figure.png"
    target.write_bytes(b"old")
    target.chmod(0o640)
    with files.atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".figure.")
        assert tmp.name.endswith(".tmp.png") and files.is_temporary(tmp)
        assert target.read_bytes() == b"old"  # nothing visible before the block ends
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and (target.stat().st_mode & 0o777) == 0o640
    with files.atomic_path(tmp_path / "part.parquet", keep_suffix=False) as tmp:
        # A folder whose *.parquet must all be whole: no glob of the suffix sees the write.
        assert not list(tmp_path.glob("*.parquet")) and files.is_temporary(tmp)
        tmp.write_bytes(b"whole")
    (tmp_path / "part.parquet").unlink()
    files.write_atomic(tmp_path / "new.txt", "text é")
    assert (tmp_path / "new.txt").read_text(encoding="utf-8") == "text é"
    assert listing(tmp_path) == ["figure.png", "new.txt"]


def _fail_sync(monkeypatch):
    def fsync(fd):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(files.os, "fsync", fsync)


def _fail_rename(monkeypatch):
    def replace(a, b):
        raise OSError(5, "Input/output error")
    monkeypatch.setattr(files.os, "replace", replace)


class Boom(Exception):
    pass


@pytest.mark.parametrize("step", ["in the block", "sync", "rename"])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch, step):
    target = tmp_path / "summary.json"
    target.write_text("old")
    if step == "sync":
        _fail_sync(monkeypatch)
    elif step == "rename":
        _fail_rename(monkeypatch)
    with pytest.raises((Boom, OSError)):
        with files.atomic_path(target) as tmp:
            tmp.write_text("half")
            if step == "in the block":
                raise Boom
    assert listing(tmp_path) == ["summary.json"] and target.read_text() == "old"
    # Staged outputs: the same, for every file staged.
    with pytest.raises((Boom, OSError)), files.Staged() as stage:
        stage.write_text(target, "new")
        stage.write_text(tmp_path / "other.txt", "new")
        if step == "in the block":
            raise Boom
        stage.commit()
    assert listing(tmp_path) == ["summary.json"] and target.read_text() == "old"


def test_a_new_file_is_never_put_over_one_that_appeared(tmp_path):
    target = tmp_path / "sample.toml"
    with pytest.raises(FileExistsError):
        with files.atomic_path(target, replace=False) as tmp:
            tmp.write_text("ours")
            target.write_text("someone else's")
    assert listing(tmp_path) == ["sample.toml"] and target.read_text() == "someone else's"
    files.write_atomic(tmp_path / "free.toml", "ours", replace=False)
    assert listing(tmp_path) == ["free.toml", "sample.toml"]


def test_only_files_refuses_to_replace_anything_else(tmp_path):
    (tmp_path / "folder").mkdir()
    os.mkfifo(tmp_path / "fifo")
    for name in ("folder", "fifo"):
        with pytest.raises(OSError, match="not a file"):
            files.write_atomic(tmp_path / name, b"x", only_files=True)
    assert listing(tmp_path) == ["fifo", "folder"]


class Stop(BaseException):
    pass


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_during_a_write_leaves_the_old_file_and_no_temporary(tmp_path, signum):
    """A tool's stop signals unwind (KeyboardInterrupt, or a handler that raises): the write
    is undone on the way out, whichever file is being written."""
    target = tmp_path / "log.csv"
    target.write_text("old")

    def stop(signum, frame):
        raise Stop(signum)

    before = signal.signal(signum, stop)
    try:
        with pytest.raises(Stop):
            with files.atomic_path(target) as tmp:
                tmp.write_text("half")
                os.kill(os.getpid(), signum)
        with pytest.raises(Stop), files.Staged() as stage:
            stage.write_text(target, "new")
            os.kill(os.getpid(), signum)
            stage.commit()
    finally:
        signal.signal(signum, before)
    assert listing(tmp_path) == ["log.csv"] and target.read_text() == "old"


WRITER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from cochlea import files
    with files.atomic_path(Path(sys.argv[1])) as tmp:
        with open(tmp, "w") as f:
            f.write("half"); f.flush()
            print("writing", flush=True)
            time.sleep(60)
""")


@pytest.mark.slow
def test_a_writer_killed_outright_leaves_only_a_temporary_file_that_is_cleaned(tmp_path):
    """SIGKILL (or a SIGTERM nobody handles) cannot be unwound: the target is untouched and the
    one file left is a temporary one, which :func:`files.clean_temporary` removes (a resumed
    sweep does)."""
    target = tmp_path / "out" / "part.parquet"
    target.parent.mkdir()
    target.write_text("old")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdout=subprocess.PIPE,
                            text=True, env=env)
    try:
        assert proc.stdout.readline() == "writing\n"
        proc.send_signal(signal.SIGTERM)  # no handler: the process dies where it is
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGTERM
    left = [p for p in target.parent.iterdir() if p != target]
    assert target.read_text() == "old" and len(left) == 1 and files.is_temporary(left[0])
    os.mkfifo(target.parent / "fifo.tmp")  # not a regular file: never removed
    files.clean_temporary(target.parent)
    assert listing(target.parent) == ["fifo.tmp", "part.parquet"]


def test_temporary_names_are_recognised_and_others_are_not():
    for name in (".log.ab12cd.tmp.csv", ".summary.x1.tmp.json", "part.parquet.tmp",
                 ".trial-000009.parquet.x.tmp"):
        assert files.is_temporary(Path(name)), name
    for name in ("log.csv", "tmp.csv", "results.tmp.csv", ".cochlea.lock"):
        assert not files.is_temporary(Path(name)), name


# --------------------------------------------------------------------------------------------
# Inputs: a regular file only, bounded
# --------------------------------------------------------------------------------------------


@pytest.fixture
def fifo(tmp_path):
    """A FIFO in place of an input file; should a reader block on it after all, a writer
    opens and closes it after 10 s, so the test fails on the reader's result, not by hanging."""
    path = tmp_path / "input.toml"
    os.mkfifo(path)
    done = threading.Event()

    def release():
        if not done.wait(10.0):
            os.close(os.open(path, os.O_RDWR))  # Linux: a writer, without waiting for a reader

    thread = threading.Thread(target=release, daemon=True)
    thread.start()
    yield path
    done.set()
    thread.join()


def test_read_regular_reads_a_file_bounded_and_refuses_any_other_kind(tmp_path, fifo):
    path = tmp_path / "f.bin"
    path.write_bytes(b"x" * 100)
    assert files.read_regular(path, 1000) == b"x" * 100
    assert files.read_regular(path, 10) == b"x" * 11  # one past the limit: "too large"
    with pytest.raises(OSError, match="FIFO"):
        files.read_regular(fifo, 1000)
    with pytest.raises(OSError, match="device"):
        files.read_regular("/dev/zero", 1000)  # would never end
    with pytest.raises(IsADirectoryError):
        files.read_regular(tmp_path, 1000)
    with pytest.raises(FileNotFoundError):
        files.read_regular(tmp_path / "missing", 1000)
    with pytest.raises(ValueError):
        files.read_regular(str(tmp_path / "a\0b"), 1000)


def _urdf(path):
    from cochlea.robots.serial.urdf import read_urdf
    return read_urdf(path)


def _scenario(path):
    from cochlea.sim import load_scenario
    return load_scenario(path)


def _description(path):
    from cochlea.robots.description import read_toml
    return read_toml(path)


def _homing(path):
    from cochlea.dynamixel.homing import load_record
    return load_record(path)


def _codegen(path):
    from cochlea.kernels.catalogue import load_config
    return load_config(path)


@pytest.mark.parametrize("reader", [_description, _scenario, _urdf, _homing, _codegen])
def test_every_input_reader_refuses_a_fifo_at_once_naming_it(fifo, reader):
    """A FIFO (or a device) named as a description, scenario, URDF, homing record or codegen
    configuration: one error naming its kind, before anything blocks (the readers opened it
    plainly and waited for a writer that never came)."""
    from cochlea.errors import CochleaError

    with pytest.raises(CochleaError, match="FIFO"):
        reader(fifo)
