"""Output folders and the report (issue 13, classes 4-6): bad output paths refused before
anything is created, the disk checked up front and a failed report said in one line, the report
written atomically and completed through repeated interrupts, and concurrent runs that never
share or mix a folder."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps import cochlea_codegen, cochlea_run, outputs, report

RUN = [sys.executable, "-m", "cochlea.apps.cochlea_run"]
SERIAL_FAST = ["--robot", "serial", "--space", "task", "--realtime", "off"]


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _one_line(stderr: str, start: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    assert lines[0].startswith(start), stderr
    return lines[0]


def _read_only_place(tmp_path: Path) -> Path:
    """A path we may not create. Root ignores permission bits, so there a path under procfs
    (no room on that disk, no folders to make) stands in for a read-only folder."""
    if os.geteuid() == 0:
        return Path("/proc/self/cochlea-out")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    return locked / "run"


def _bad_outs(tmp_path: Path) -> list[tuple[Path, str]]:
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    return [(tmp_path / "a_file", "is a file, not a folder"),
            (tmp_path / "a_file" / "run", "is a file, not a folder"),
            (tmp_path / "a_file" / "deep" / "run", "is a file, not a folder"),
            (Path("/dev/null"), "is a device, not a folder"),
            (tmp_path / "full", "exists and is not empty"),
            (_read_only_place(tmp_path), "")]


# --------------------------------------------------------------------------------------------
# Class 4: output paths and the disk
# --------------------------------------------------------------------------------------------


def test_run_refuses_every_bad_out_before_creating_anything(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for out, message in _bad_outs(tmp_path):
        before = _tree(tmp_path)
        assert cochlea_run.main([*SERIAL_FAST, "--duration", "0.1", "--out", str(out)]) == 2
        line = _one_line(capsys.readouterr().err, f"cochlea-run: --out {out}")
        assert message in line
        assert _tree(tmp_path) == before  # nothing created, not even runs/
    assert (tmp_path / "full" / "notes.txt").read_text() == "mine"


def test_codegen_refuses_bad_paths_before_generating(tmp_path, capsys):
    for out, message in _bad_outs(tmp_path):
        # codegen rewrites a folder it generated before; one of other files is refused
        message = message.replace("exists and is not empty", "did not generate")
        before = _tree(tmp_path)
        assert cochlea_codegen.main(["--out", str(out)]) == 2
        assert message in _one_line(capsys.readouterr().err, f"cochlea-codegen: --out {out}")
        assert _tree(tmp_path) == before
    # A folder of someone else's files: the generator would empty it, so it is refused.
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "thesis.tex").write_text("mine")
    assert cochlea_codegen.main(["--out", str(docs)]) == 2
    assert "did not generate (no manifest.c)" in _one_line(capsys.readouterr().err,
                                                           "cochlea-codegen: --out")
    assert (docs / "thesis.tex").read_text() == "mine"
    # --config: a folder, and a file that is not UTF-8.
    latin = tmp_path / "latin1.toml"
    latin.write_bytes("# d\xe9j\xe0 vu\nformat = 1\n".encode("latin-1"))
    for config, message in [(tmp_path, "is a folder"), (latin, "not UTF-8")]:
        assert cochlea_codegen.main(["--config", str(config)]) == 2
        assert message in _one_line(capsys.readouterr().err,
                                    f"cochlea-codegen: --config {config}")


@pytest.mark.slow
def test_run_refuses_a_log_that_will_not_fit_on_the_disk(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    need = {}

    def tiny_disk(path):
        need["asked"] = Path(path)
        return 10 * 2**20  # 10 MiB free

    monkeypatch.setattr(outputs, "free_bytes", tiny_disk)
    for extra in (["--out", str(tmp_path / "run")], []):  # explicit, and the default folder
        assert cochlea_run.main([*SERIAL_FAST, "--duration", "0.1", *extra]) == 2
        line = _one_line(capsys.readouterr().err, "cochlea-run: ")
        assert "100 periods of log.csv" in line and "only 10.0 MiB are free" in line
        assert _tree(tmp_path) == []
    # The estimate grows with the periods: an hour at 1 kHz is refused where 0.1 s would fit
    # on a 1 GiB disk.
    monkeypatch.setattr(outputs, "free_bytes", lambda path: 2**30)
    assert cochlea_run.main(["--robot", "serial", "--space", "task", "--duration", "3600",
                             "--out", str(tmp_path / "hour")]) == 2
    assert "3600000 periods of log.bin and log.csv" in capsys.readouterr().err
    assert not (tmp_path / "hour").exists()


def _full_disk(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("broken, lost", [
    ("write_csv", ["log.csv"]),
    ("write_text_atomic", ["summary.json"]),
    ("both", ["log.csv", "summary.json"]),
])
@pytest.mark.slow
def test_a_report_that_cannot_be_written_says_what_was_lost(tmp_path, capsys, monkeypatch,
                                                             broken, lost):
    for name in (["write_csv", "write_text_atomic"] if broken == "both" else [broken]):
        monkeypatch.setattr(report, name, _full_disk)
    out = tmp_path / "run"
    code = cochlea_run.main([*SERIAL_FAST, "--duration", "0.2", "--out", str(out)])
    assert code == cochlea_run.EXIT_REPORT_FAILED
    line = _one_line(capsys.readouterr().err, "cochlea-run: the report could not be written")
    assert "No space left on device" in line and f"lost {', '.join(lost)};" in line
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left
    assert (out / "paths.png").exists()  # what could be written was
    for name in ("log.csv", "summary.json"):
        assert (out / name).exists() == (name not in lost)
    if "summary.json" not in lost:
        assert json.loads((out / "summary.json").read_text())["report_lost"] == lost


@pytest.mark.realtime
def test_a_failed_report_of_a_real_run_keeps_its_raw_log(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(report, "write_csv", _full_disk)
    out = tmp_path / "run"
    code = cochlea_run.main(["--robot", "serial", "--space", "task", "--duration", "0.3",
                             "--watchdog-misses", "500", "--out", str(out)])
    assert code == cochlea_run.EXIT_REPORT_FAILED
    err = capsys.readouterr().err
    assert "lost log.csv" in err and "log.bin is the whole raw log" in err
    columns = json.loads((out / "log.columns.json").read_text())
    assert np.fromfile(out / "log.bin").size == 300 * columns["row_length"]


def test_atomic_files_leave_the_old_content_or_the_whole_new_one(tmp_path):
    path = tmp_path / "summary.json"
    outputs.write_text_atomic(path, "old\n")
    with pytest.raises(RuntimeError):
        with outputs.atomic_path(path) as tmp:
            tmp.write_text("half of the ne")
            raise RuntimeError("interrupted mid-write")
    assert path.read_text() == "old\n" and _tree(tmp_path) == ["summary.json"]
    with outputs.atomic_path(path) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".json"  # same disk, same format
        tmp.write_text("new\n")
        assert path.read_text() == "old\n"  # readers see the old file until the rename
    assert path.read_text() == "new\n" and _tree(tmp_path) == ["summary.json"]


# --------------------------------------------------------------------------------------------
# Class 5: interrupts during the report
# --------------------------------------------------------------------------------------------


def _start(args, cwd):
    return subprocess.Popen([*RUN, *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(proc, condition, what, timeout=120):
    deadline = time.monotonic() + timeout
    while not condition():
        assert proc.poll() is None, f"the run ended before {what}: {proc.communicate()}"
        assert time.monotonic() < deadline, f"no {what} in {timeout} s"
        time.sleep(0.005)


def _hammer(proc, signum):
    """Send ``signum`` every 20 ms until the process has ended; return (stdout, stderr)."""
    sent = 0
    while proc.poll() is None:
        proc.send_signal(signum)
        sent += 1
        time.sleep(0.02)
    stdout, stderr = proc.communicate(timeout=60)
    return stdout, stderr, sent


def _assert_report_whole(out: Path, periods: int | None = None):
    summary = json.loads((out / "summary.json").read_text())
    assert "report_lost" not in summary
    rows = np.loadtxt(out / "log.csv", delimiter=",", skiprows=1, ndmin=2).shape[0]
    assert rows == summary["periods"]
    if periods is not None:
        assert rows == periods
    assert len(list(out.glob("*.png"))) == 9
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary, lock
    return summary


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.slow
def test_interrupts_during_the_report_are_acknowledged_not_obeyed(tmp_path, signum):
    out = tmp_path / "run"
    proc = _start([*SERIAL_FAST, "--duration", "20", "--out", str(out)], tmp_path)
    # The report has begun when the CSV's temporary file appears.
    _wait_for(proc, lambda: any(out.glob(".log.*.tmp.csv")), "log.csv being written")
    _, stderr, sent = _hammer(proc, signum)
    assert sent >= 2
    assert proc.returncode == 0, stderr
    assert "finishing the log, please wait" in stderr
    assert "before the run started" not in stderr and "Traceback" not in stderr
    _assert_report_whole(out, 20000)


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
@pytest.mark.slow
def test_an_interrupted_simulation_leaves_nothing_and_says_so(tmp_path, signum, code):
    out = tmp_path / "deep" / "run"
    # The CasADi reference (about 7x real time): the C kernels would finish 200 s in under a
    # second, before the signal lands, and the run would rightly complete.
    proc = _start([*SERIAL_FAST, "--kernels", "casadi", "--duration", "200", "--out", str(out)],
                  tmp_path)
    assert " -> " in proc.stdout.readline()  # simulating now (about half a minute long)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == code
    _one_line(stderr, "cochlea-run: ")
    assert "during the as-fast simulation; nothing written" in stderr
    assert _tree(tmp_path) == []  # the folders it created are gone too


def test_an_interrupt_while_preparing_undoes_the_start(tmp_path, capsys, monkeypatch):
    """Ctrl-C after the folder was claimed, while the loop is built: nothing ran, so the
    message says so, and the identical retry finds no folder in its way."""
    real = cochlea_run.RealTimeLoop
    before = signal.getsignal(signal.SIGINT)  # ignored when the tests run in the background

    def interrupted_loop(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kwargs)

    monkeypatch.setattr(cochlea_run, "RealTimeLoop", interrupted_loop)
    out = tmp_path / "run"
    args = ["--robot", "serial", "--space", "task", "--duration", "0.2", "--out", str(out)]
    assert cochlea_run.main(args) == cochlea_run.EXIT_INTERRUPTED
    _one_line(capsys.readouterr().err,
              "cochlea-run: interrupted before the run started; nothing moved")
    assert _tree(tmp_path) == []
    assert signal.getsignal(signal.SIGINT) is before  # handed back


@pytest.mark.parametrize("where", ["_mkdir_missing", "_lock"])
@pytest.mark.parametrize("default_folder", [False, True], ids=["--out", "runs/"])
def test_an_interrupt_while_the_folder_is_claimed_leaves_no_folder(tmp_path, capsys,
                                                                    monkeypatch, where,
                                                                    default_folder):
    """Ctrl-C between creating the folders and locking them: held off until the folder is
    recorded, then obeyed, and the start undone (no empty folder blocks the retry)."""
    monkeypatch.chdir(tmp_path)
    real = getattr(outputs, where)

    def interrupted(*args, **kwargs):
        result = real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)
        return result

    monkeypatch.setattr(outputs, where, interrupted)
    args = ["--robot", "serial", "--space", "task", "--duration", "0.2"]
    if not default_folder:
        args += ["--out", str(tmp_path / "deep" / "run")]
    assert cochlea_run.main(args) == cochlea_run.EXIT_INTERRUPTED
    _one_line(capsys.readouterr().err,
              "cochlea-run: interrupted before the run started; nothing moved")
    assert _tree(tmp_path) == []


@pytest.mark.realtime
def test_repeated_ctrl_c_stops_a_real_run_once_and_keeps_every_row(tmp_path):
    out = tmp_path / "run"
    proc = _start(["--robot", "serial", "--space", "task", "--duration", "30",
                   "--watchdog-misses", "500", "--out", str(out)], tmp_path)
    _wait_for(proc, lambda: (out / "log.bin").exists() and (out / "log.bin").stat().st_size,
              "log.bin")
    _, stderr, _ = _hammer(proc, signal.SIGINT)
    assert proc.returncode == 0, stderr
    assert "stopped by the user at t = " in stderr and "finishing the log" in stderr
    assert "before the run started" not in stderr and "Traceback" not in stderr
    summary = _assert_report_whole(out)
    assert summary["stop"]["rule"] == "user-stop"
    columns = json.loads((out / "log.columns.json").read_text())
    assert np.fromfile(out / "log.bin").size == summary["periods"] * columns["row_length"]


# --------------------------------------------------------------------------------------------
# Class 6: concurrent runs
# --------------------------------------------------------------------------------------------


def test_default_folders_started_in_the_same_second_are_distinct(tmp_path):
    names = [outputs.claim_new(tmp_path / "runs", "serial_task_20260101-120000")
             for _ in range(3)]
    try:
        assert [f.path.name for f in names] == ["serial_task_20260101-120000",
                                                "serial_task_20260101-120000-2",
                                                "serial_task_20260101-120000-3"]
    finally:
        for f in names:
            f.release()
    assert all(not any(f.path.iterdir()) for f in names)  # the lock files are gone again


@pytest.mark.slow
def test_simultaneous_runs_each_get_their_own_folder_and_summary(tmp_path):
    procs = [_start([*SERIAL_FAST, "--duration", "0.1"], tmp_path) for _ in range(3)]
    for proc in procs:
        _, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 0, stderr
    folders = sorted((tmp_path / "runs").iterdir())
    assert len(folders) == 3
    for folder in folders:
        _assert_report_whole(folder, 100)


_HOLDER = """
import sys, time
from pathlib import Path
from cochlea.apps import outputs
folder = outputs.claim(Path(sys.argv[1]))
print("claimed", flush=True)
time.sleep(600)
"""


@pytest.mark.slow
def test_an_out_in_use_is_refused_and_freed_when_its_run_dies(tmp_path, capsys):
    out = tmp_path / "shared"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "claimed"
        with pytest.raises(outputs.CochleaError, match=f"in use by another run "
                                                       f"\\(pid {holder.pid}\\)"):
            outputs.claim(out)
        # A run given the same --out while the folder is still empty but locked.
        assert cochlea_run.main([*SERIAL_FAST, "--duration", "0.1", "--out", str(out)]) == 2
        assert f"in use by another run (pid {holder.pid})" in _one_line(
            capsys.readouterr().err, f"cochlea-run: --out {out}")
    finally:
        holder.kill()  # SIGKILL: no clean-up ran; the kernel dropped the lock
        holder.wait()
    claimed = outputs.claim(out)  # the stale lock file does not block the folder
    claimed.release()
    assert _tree(out) == []


@pytest.mark.slow
def test_an_out_that_already_holds_a_run_is_refused_even_unlocked(tmp_path, capsys):
    out = tmp_path / "run"
    assert cochlea_run.main([*SERIAL_FAST, "--duration", "0.1", "--out", str(out)]) == 0
    before = _tree(tmp_path)
    capsys.readouterr()
    assert cochlea_run.main([*SERIAL_FAST, "--duration", "0.1", "--out", str(out)]) == 2
    assert "exists and is not empty" in _one_line(capsys.readouterr().err, "cochlea-run:")
    with pytest.raises(outputs.CochleaError, match="exists and is not empty"):
        outputs.claim(out)
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("existing", [False, True])
@pytest.mark.slow
def test_a_start_that_fails_removes_what_it_created(tmp_path, existing):
    """The backend cannot start (no such port): the folders made for the run go again (a
    folder the user made stays, empty), so the identical retry fails the same way, not with
    'not empty'."""
    out = tmp_path / "a" / "b" / "run"
    if existing:
        out.mkdir(parents=True)
    args = ["--robot", "serial", "--space", "joint", "--backend", "dynamixel", "--port",
            str(tmp_path / "no-such-port"), "--out", str(out)]
    for _ in range(2):
        done = subprocess.run([*RUN, *args], cwd=tmp_path, capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 5, done.stderr
        assert "the backend could not start, nothing moved" in done.stderr
        assert "Traceback" not in done.stderr
        assert _tree(tmp_path) == (["a", "a/b", "a/b/run"] if existing else [])


# --------------------------------------------------------------------------------------------
# cochlea-codegen: all or nothing
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"),
                                     KeyboardInterrupt()], ids=["full disk", "Ctrl-C"])
@pytest.mark.slow
def test_codegen_that_fails_midway_leaves_the_old_files_whole(tmp_path, capsys, monkeypatch,
                                                              failure):
    import shutil

    from cochlea.kernels import generate as generate_mod

    out = tmp_path / "generated_c"
    shutil.copytree(generate_mod.load_config().output, out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real_group = generate_mod._generate_group
    calls = []

    def fail_on_second_group(*args, **kwargs):  # one group's files are written, then it fails
        calls.append(args[0])
        if len(calls) == 2:
            raise failure
        return real_group(*args, **kwargs)

    monkeypatch.setattr(generate_mod, "_generate_group", fail_on_second_group)
    if isinstance(failure, OSError):
        assert cochlea_codegen.main(["--out", str(out)]) == 2
        line = _one_line(capsys.readouterr().err, f"cochlea-codegen: cannot write {out}")
        assert "No space left on device" in line and "as it was" in line
    else:
        with pytest.raises(KeyboardInterrupt):
            cochlea_codegen.main(["--out", str(out)])
    assert len(calls) == 2
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["generated_c"]  # no staging left


@pytest.mark.slow  # a held section of 0.5 s each
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signals_held_over_a_section_are_obeyed_after_it(signum):
    """What codegen's renames and cochlea-run's folder claim rely on: a signal sent to the
    process (any thread may take it) inside the section runs its handler only after it."""
    import threading

    from cochlea.console import signals_held

    steps, handled = [], []

    def handler(s, frame):
        handled.append((s, list(steps)))

    previous = signal.signal(signum, handler)
    worker = threading.Thread(target=time.sleep, args=(0.5,))  # another thread that may take it
    worker.start()
    try:
        with signals_held():
            steps.append("first")
            os.kill(os.getpid(), signum)
            time.sleep(0.01)
            steps.append("second")
        assert handled == [(signum, ["first", "second"])]
        assert signal.getsignal(signum) is handler  # the program's handler is back
    finally:
        signal.signal(signum, previous)
        worker.join()


# --------------------------------------------------------------------------------------------
# A reader that goes away: `cochlea-run ... | head -1`
# --------------------------------------------------------------------------------------------


def _closed_pipe() -> int:
    """The write end of a pipe whose reader is already gone: the first write fails (EPIPE)."""
    r, w = os.pipe()
    os.close(r)
    return w


@pytest.mark.slow
def test_run_whose_reader_went_away_still_runs_and_reports(tmp_path):
    out = tmp_path / "run"
    w = _closed_pipe()
    try:
        done = subprocess.run([*RUN, *SERIAL_FAST, "--duration", "0.2", "--out", str(out)],
                              stdout=w, stderr=subprocess.PIPE, text=True, timeout=300)
    finally:
        os.close(w)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["duration_s"] == pytest.approx(0.2)
    rows = (out / "log.csv").read_text().count("\n") - 1
    assert rows == 200  # every period of 0.2 s at 1 kHz


@pytest.mark.slow
def test_run_through_head_prints_its_first_line_and_keeps_its_log(tmp_path):
    out = tmp_path / "run"
    done = subprocess.run(" ".join([*RUN, *SERIAL_FAST, "--duration", "0.2", "--out", str(out)])
                          + " | head -1; exit ${PIPESTATUS[0]}", shell=True,
                          executable="/bin/bash", capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert done.stdout.startswith("cochlea-run: ") and done.stdout.count("\n") == 1
    assert (out / "summary.json").is_file()


@pytest.mark.slow
def test_codegen_check_whose_reader_went_away_exits_with_its_verdict(tmp_path):
    w = _closed_pipe()
    try:
        done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_codegen", "--check"],
                              stdout=w, stderr=subprocess.PIPE, text=True, timeout=300)
    finally:
        os.close(w)
    assert done.returncode == 0 and done.stderr == "", done.stderr


@pytest.mark.parametrize("next_phase", ["defer", "forward"])
def test_a_signal_a_library_swallowed_while_preparing_still_stops_the_run(next_phase):
    """A SIGTERM during the as-fast simulation once ended in exit 0 (CI, session 12): the
    shield's exception was raised inside a library that runs Python's signal handlers itself
    and swallowed it. The shield remembers the signal and raises it again before the next
    phase, so the run still ends as interrupted."""
    shield = outputs.SignalShield("test")
    shield.install()
    try:
        try:  # the library: runs the handler, swallows what it raises
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        except outputs.Interrupted:
            pass
        with pytest.raises(outputs.Interrupted) as caught:
            shield.defer() if next_phase == "defer" else shield.forward(lambda *a: None)
        assert caught.value.signum == signal.SIGTERM
    finally:
        shield.restore()
