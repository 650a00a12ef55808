"""cochlea-identify and cochlea-excite against hostile inputs and outputs (issue 26): one class
of defect per test. Each refusal is one line naming the file, option or value, with its
documented exit code (docs/identification.md and docs/excitation.md, "Exit codes"); a refused
command changes nothing; a write that fails (full disk, read-only file system) leaves no
partial file and the previous one intact. Logs are short and synthetic (a noise-free Fourier
motion of arm1 and its nominal inverse dynamics), so every fit takes about a second."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import cochlea
from cochlea.apps import cochlea_excite, cochlea_identify
from cochlea.apps.cochlea_identify import EXIT_DUPLICATE_LOG, EXIT_OUTPUT_REFUSED, EXIT_WRITE_FAILED
from cochlea.errors import EXIT_USER_ERROR
from cochlea.ident import estimate, files
from cochlea.ident.cli import EXIT_TERMINATED, Terminated, exit_code, sigterm_unwinds
from cochlea.ident.logs import read_run

ROOT = Path(__file__).resolve().parent.parent
FIT = ["--robot", "serial", "--min-speed", "0", "--effort-lag", "0"]
EXCITE_FAST = ["--robot", "serial", "--period", "4", "--harmonics", "3", "--starts", "1",
               "--iterations", "25", "--periods", "1"]


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    """A 4 s run folder of arm1 at 1 kHz: three harmonics per joint about its working pose."""
    m = cochlea.model("serial", parameterisation="base", actuators="all")
    t = np.arange(4000) / 1000.0
    rng = np.random.default_rng(1)
    q, qd, qdd = (np.zeros((len(t), 3)) for _ in range(3))
    for j, centre in enumerate(np.radians([81.14, 71.02, 117.8])):
        q[:, j] = centre
        for k in range(1, 4):
            a, w, p = math.radians(8) / k, math.pi * k, rng.uniform(0, 2 * math.pi)
            q[:, j] += a * np.sin(w * t + p)
            qd[:, j] += a * w * np.cos(w * t + p)
            qdd[:, j] -= a * w * w * np.sin(w * t + p)
    tau = np.array([np.array(m.inverse_dynamics(*x)).ravel() for x in zip(q, qd, qdd)])
    names = [j.name for j in m.joints]
    header = (["time_s"] + [f"arm1.q.{n}_rad" for n in names]
              + [f"arm1.qd.{n}_rad_s" for n in names] + [f"arm1.tau.{n}_Nm" for n in names])
    folder = tmp_path_factory.mktemp("log") / "run"
    folder.mkdir()
    np.savetxt(folder / "log.csv", np.column_stack([t, q, qd, tau]), delimiter=",",
               header=",".join(header), comments="", fmt="%.10g")
    return folder


def _snapshot(folder: Path) -> dict:
    """Every entry under ``folder``: its kind and content (links not followed)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_symlink():
            out[str(p)] = ("link", os.readlink(p))
        elif p.is_file():
            out[str(p)] = ("file", p.read_bytes())
        else:
            out[str(p)] = ("other", p.lstat().st_mode)
    return out


def _refused(capsys, main, argv, code, program="cochlea-identify") -> str:
    try:
        got = main(argv)
    except SystemExit as stop:  # the parser's own refusal (a number that is no number)
        got = stop.code
    assert got == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"{program}: "), err
    assert "Traceback" not in err
    return err


# ---- the same log twice ---------------------------------------------------------------------


@pytest.mark.slow
def test_the_same_log_twice_is_refused_whatever_its_name(log, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(log, copy)
    hard = tmp_path / "hard"
    hard.mkdir()
    os.link(log / "log.csv", hard / "log.csv")
    (tmp_path / "link").symlink_to(log)
    out = tmp_path / "ident.json"
    before = _snapshot(tmp_path)
    for second in (log, copy, hard, tmp_path / "link", log / "log.csv"):
        err = _refused(capsys, cochlea_identify.main,
                       [str(log), str(second), *FIT, "--out", str(out)], EXIT_DUPLICATE_LOG)
        assert str(second) in err and str(log) in err and "sqrt(2)" in err
        # A validation log that is a fitted one, under any name.
        err = _refused(capsys, cochlea_identify.main,
                       [str(log), "--validate", str(second), *FIT, "--out", str(out)],
                       EXIT_DUPLICATE_LOG)
        assert f"--validate {second}" in err
    assert _snapshot(tmp_path) == before


# ---- outputs refused before anything is read ------------------------------------------------


@pytest.mark.slow
def test_outputs_that_cannot_take_the_file_are_refused_and_left_alone(log, tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (tmp_path / "link.json").symlink_to(victim)
    (tmp_path / "dangling.json").symlink_to(tmp_path / "nowhere.json")
    os.mkfifo(tmp_path / "fifo.json")
    (tmp_path / "folder.json").mkdir()
    (tmp_path / "ok.json").write_text("previous")
    (tmp_path / "ok_torques.png").symlink_to(victim)  # the report's figure is a link
    before = _snapshot(tmp_path)
    cases = {
        "link.json": "symbolic link", "dangling.json": "symbolic link",
        "fifo.json": "pipe", "folder.json": "folder",
        "victim.txt/x.json": "not a folder", "missing/x.json": "does not exist",
        "ok.json": "ok_torques.png",
    }
    # The log named does not exist: the outputs are refused first, before anything is read.
    for name, expected in cases.items():
        err = _refused(capsys, cochlea_identify.main,
                       [str(tmp_path / "nowhere"), *FIT, "--out", str(tmp_path / name)],
                       EXIT_OUTPUT_REFUSED)
        assert expected in err and "--out" in err, err
    err = _refused(capsys, cochlea_identify.main,
                   [str(log), *FIT, "--out", "/dev/null"], EXIT_OUTPUT_REFUSED)
    assert "device" in err
    # An input is never an output: the log itself, the description.
    err = _refused(capsys, cochlea_identify.main,
                   [str(log), *FIT, "--out", str(log / "log.csv"), "--no-figures"],
                   EXIT_OUTPUT_REFUSED)
    assert "input" in err
    description = tmp_path / "serial.toml"
    description.write_text((ROOT / "models/robots/serial.toml").read_text())
    before[str(description)] = ("file", description.read_bytes())
    err = _refused(capsys, cochlea_identify.main,
                   [str(log), *FIT, "--description", str(description), "--out",
                    str(description), "--no-figures"], EXIT_OUTPUT_REFUSED)
    assert "input" in err
    # The write-back target: --in-place through a link, a name already taken.
    (tmp_path / "desc_link.toml").symlink_to(description)
    before[str(tmp_path / "desc_link.toml")] = ("link", str(description))
    err = _refused(capsys, cochlea_identify.main,
                   [str(log), *FIT, "--out", str(tmp_path / "new.json"), "--no-figures",
                    "--update-description", str(tmp_path / "desc_link.toml"), "--in-place"],
                   EXIT_OUTPUT_REFUSED)
    assert "symbolic link" in err
    (tmp_path / "serial.identified.toml").symlink_to(victim)
    before[str(tmp_path / "serial.identified.toml")] = ("link", str(victim))
    err = _refused(capsys, cochlea_identify.main,
                   [str(log), *FIT, "--out", str(tmp_path / "new.json"), "--no-figures",
                    "--update-description", str(description)], EXIT_OUTPUT_REFUSED)
    assert "already exists" in err or "symbolic link" in err
    assert _snapshot(tmp_path) == before


def test_excite_outputs_are_refused_and_left_alone(tmp_path, capsys):
    victim = tmp_path / "victim.toml"
    victim.write_text("keep me")
    (tmp_path / "link.toml").symlink_to(victim)
    os.mkfifo(tmp_path / "fifo.toml")
    description = tmp_path / "serial.toml"
    description.write_text((ROOT / "models/robots/serial.toml").read_text())
    before = _snapshot(tmp_path)
    for name, expected, extra in (("link.toml", "symbolic link", ["--force"]),
                                  ("fifo.toml", "pipe", ["--force"]),
                                  ("victim.toml/x.toml", "not a folder", []),
                                  ("serial.toml", "input", ["--force", "--description",
                                                            str(description)]),
                                  (".", "folder", [])):
        err = _refused(capsys, cochlea_excite.main,
                       [*EXCITE_FAST, "--out", str(tmp_path / name), *extra],
                       EXIT_OUTPUT_REFUSED, "cochlea-excite")
        assert expected in err, err
    err = _refused(capsys, cochlea_excite.main, [*EXCITE_FAST, "--out", "/dev/null",
                                                 "--force"], EXIT_OUTPUT_REFUSED,
                   "cochlea-excite")
    assert "device" in err
    assert _snapshot(tmp_path) == before


# ---- damaged logs -----------------------------------------------------------------------------


def _cell(lines: list[str], row: int, column: int, value: str) -> bytes:
    cells = lines[row].rstrip("\n").split(",")
    cells[column] = value
    return "".join(lines[:row] + [",".join(cells) + "\n"] + lines[row + 1:]).encode()


@pytest.mark.slow
def test_damaged_logs_are_refused_in_one_line_naming_the_file(log, tmp_path, capsys):
    text = (log / "log.csv").read_text()
    lines = text.splitlines(keepends=True)
    header = lines[0]
    cases = {
        "binary": (b"\x00\x01\x02" * 100, "binary"),
        "truncated": (text[:-7].encode(), "cut short"),
        "empty": (b"", "empty"),
        "header_only": (header.encode(), "at least two rows"),
        "degrees": (text.replace("arm1.q.joint2_rad", "arm1.q.joint2_deg", 1).encode(),
                    "'arm1.q.joint2_deg' where 'arm1.q.joint2_rad' was expected"),
        "twice": (text.replace("arm1.qd.joint1_rad_s", "arm1.q.joint1_rad", 1).encode(),
                  "appears 2 times"),
        "nan": (_cell(lines, 50, 1, "nan"), "non-finite"),
        "inf": (_cell(lines, 60, 4, "-inf"), "non-finite"),
        "latin1": ((header + "0,\xe9\n").encode("latin-1"), "expected"),
        "short_row": ("".join(lines[:80] + [lines[80].rsplit(",", 1)[0] + "\n"]
                              + lines[81:]).encode(), "expected numbers"),
    }
    out = tmp_path / "ident.json"
    for name, (content, expected) in cases.items():
        folder = tmp_path / name
        folder.mkdir()
        (folder / "log.csv").write_bytes(content)
        err = _refused(capsys, cochlea_identify.main, [str(folder), *FIT, "--out", str(out)],
                       EXIT_USER_ERROR)
        assert str(folder / "log.csv") in err and expected in err, (name, err)
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / "log.csv")  # would block a reader for ever
    err = _refused(capsys, cochlea_identify.main, [str(fifo), *FIT, "--out", str(out)],
                   EXIT_USER_ERROR)
    assert "regular file" in err
    assert not out.exists() and not list(tmp_path.glob("*.png"))


def _edited(log: Path, folder: Path, edit) -> Path:
    """A copy of ``log`` whose data (time, q, qd, tau of arm1, a float array) ``edit`` changed
    in place."""
    header = (log / "log.csv").read_text().split("\n", 1)[0]
    data = np.loadtxt(log / "log.csv", delimiter=",", skiprows=1)
    edit(data)
    folder.mkdir()
    np.savetxt(folder / "log.csv", data, delimiter=",", header=header, comments="",
               fmt="%.10g")
    return folder


def _tau(data: np.ndarray) -> np.ndarray:
    return data[:, 7:10]


UNIT_MISTAKES = {
    # positions in degrees under the _rad columns, whole turns off, efforts in mN m
    "degrees": (lambda d: d.__setitem__((slice(None), slice(1, 4)), np.degrees(d[:, 1:4])),
                "arm1.q.joint1_rad", "row 1 of the data", "degrees"),
    "offset": (lambda d: d.__setitem__((slice(2000, None), 2), d[2000:, 2] + 1000.0),
               "arm1.q.joint2_rad", "row 2001 of the data", "offset"),
    "millinewton_metres": (lambda d: _tau(d).__imul__(1000.0), "arm1.tau.joint1_Nm",
                           "effort limit 2.5 N m", "mN m"),
    "out_of_range": (lambda d: _tau(d).__imul__(1e300), "arm1.tau.joint1_Nm",
                     "row 1 of the data", "corrupt"),
    # efforts not recorded: zero, or one constant
    "zero": (lambda d: _tau(d).__imul__(0.0), "arm1.tau.joint1_Nm", "no signal", "0 N m"),
    "constant": (lambda d: d.__setitem__((slice(None), 9), 0.25), "arm1.tau.joint3_Nm",
                 "no signal", "on every row"),
    # time_s off its uniform grid: a 100 s gap, a repeated row, an irregular clock
    "gap": (lambda d: d.__setitem__((slice(2000, None), 0), d[2000:, 0] + 100.0), "time_s",
            "row 2001 of the data", "uniform grid"),
    "repeated": (lambda d: d.__setitem__((11, 0), d[10, 0]), "time_s", "row 12 of the data",
                 "strictly increasing"),
    "irregular": (lambda d: d.__setitem__((slice(None), 0), np.cumsum(
        np.random.default_rng(0).uniform(0.2e-3, 1.8e-3, len(d)))), "time_s", "row ",
        "uniform grid"),
}


@pytest.mark.parametrize("case", list(UNIT_MISTAKES))
def test_unit_mistakes_and_bad_time_are_refused_naming_column_row_and_cause(
        log, tmp_path, capsys, case):
    # Each was fitted and written with exit 0: estimates 1000 times nominal (mN m), positions
    # 57 times their size (degrees), filters on a grid with a 100 s hole; all-zero efforts
    # crashed with LinAlgError (SVD did not converge), huge ones wrote NaN into the report.
    edit, column, where, cause = UNIT_MISTAKES[case]
    folder = _edited(log, tmp_path / case, edit)
    out = tmp_path / "ident.json"
    err = _refused(capsys, cochlea_identify.main,
                   [str(folder), *FIT, "--out", str(out), "--no-figures"], EXIT_USER_ERROR)
    assert str(folder / "log.csv") in err and column in err and where in err \
        and cause in err, err
    assert not out.exists()


def test_zero_residuals_weigh_the_joints_equally():
    # An exact fit (every residual zero) gave 1 / 1e-312 = inf weights, then NaN in the
    # weighted regressor and "SVD did not converge".
    W = np.eye(6)
    joint = np.tile(np.arange(3), 2)
    ols = estimate.LeastSquares(np.zeros(6), np.zeros(6), np.zeros(3))
    with np.errstate(all="raise"):
        weights = estimate.joint_weights(W, np.zeros(6), joint, 3, ols)
    assert np.array_equal(weights, np.ones(6))


@pytest.mark.slow
def test_a_fit_out_of_floating_point_range_is_one_line_and_writes_nothing(
        log, tmp_path, capsys, monkeypatch):
    # Past the log's checks (read_run replaced), efforts of 1e300 N m: the fit overflows. It
    # printed ~20 RuntimeWarnings and wrote estimates and NRMS as NaN / Infinity, exit 0.
    m = cochlea.model("serial", parameterisation="base", actuators="all")
    good = read_run(log, m, "serial", "arm1")
    monkeypatch.setattr(cochlea_identify, "read_run", lambda *a: dataclasses.replace(
        good, tau=good.tau * 1e300))
    out = tmp_path / "ident.json"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        err = _refused(capsys, cochlea_identify.main, [str(log), *FIT, "--out", str(out)],
                       EXIT_USER_ERROR)
    assert "not finite" in err or "inf" in err, err
    assert "units" in err and list(tmp_path.iterdir()) == []
    # A linear-algebra failure anywhere in the fit is one line too, not a traceback.
    monkeypatch.setattr(cochlea_identify, "read_run", lambda *a: good)

    def no_convergence(*a, **k):
        raise np.linalg.LinAlgError("SVD did not converge")
    monkeypatch.setattr(estimate, "_solve", no_convergence)
    err = _refused(capsys, cochlea_identify.main, [str(log), *FIT, "--out", str(out)],
                   EXIT_USER_ERROR)
    assert "SVD did not converge" in err and list(tmp_path.iterdir()) == []


def test_a_report_with_a_non_finite_number_is_refused():
    doc = {"parameters": [{"name": "b1", "wls": 1.0}, {"name": "b2", "wls": math.nan}],
           "condition_number": None}
    with pytest.raises(estimate.NumericalError, match=r"parameters\[1\]\.wls is nan"):
        cochlea_identify._check_finite(doc)
    cochlea_identify._check_finite({"a": [1.0, None, 2], "b": "inf"})  # null and text pass


# ---- hostile numbers and malformed options ----------------------------------------------------


@pytest.mark.parametrize("argv,names", [
    (["--period", "inf"], "--period"), (["--period", "1e308"], "--period"),
    (["--period", "-4"], "--period"), (["--periods", str(10**30)], "--periods"),
    (["--harmonics", str(10**12)], "--harmonics"), (["--harmonics", "1e9"], "--harmonics"),
    (["--amplitude-deg=-1e308"], "--amplitude-deg"), (["--starts", "10000000"], "--starts"),
    (["--iterations", str(2**63)], "--iterations"), (["--seed", str(2**70)], "--seed"),
    (["--periods", "1000", "--period", "600"], "--periods"), (["--bogus"], "--bogus"),
])
def test_excite_hostile_numbers_refused_up_front(tmp_path, capsys, argv, names):
    out = tmp_path / "x.toml"
    full = ["--robot", "serial", "--out", str(out), *argv]
    try:
        code = cochlea_excite.main(full)
    except SystemExit as stop:  # argparse's own refusal (--harmonics 1e9, --bogus)
        code = stop.code
    assert code == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("cochlea-excite: "), err
    assert names in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv,names", [
    (["--decimate", str(10**30)], "--decimate"), (["--decimate", "0"], "--decimate"),
    (["--cutoff-hz", "1e-300"], "--cutoff-hz"), (["--cutoff-hz", "inf"], "--cutoff-hz"),
    (["--parallel-cutoff-hz", "1e-300"], "--parallel-cutoff-hz"),
    (["--holdout", "1e-300"], "--holdout"), (["--holdout", "nan"], "--holdout"),
    (["--guard-s", "inf"], "--guard-s"), (["--max-condition", "inf"], "--max-condition"),
])
def test_identify_hostile_numbers_refused_before_the_logs(tmp_path, capsys, argv, names):
    # The log does not exist: the numbers are refused first, before anything is read.
    out = tmp_path / "ident.json"
    err = _refused(capsys, cochlea_identify.main,
                   [str(tmp_path / "nowhere"), *FIT, "--out", str(out), *argv],
                   EXIT_USER_ERROR)
    assert names in err and len(err) < 300, err
    assert list(tmp_path.iterdir()) == []


def test_identify_malformed_option_is_one_line(log, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        cochlea_identify.main([str(log), *FIT, "--decimate", "1e400"])
    assert stop.value.code == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--decimate" in err


# ---- full disk and read-only file systems -----------------------------------------------------


def _in_tmpfs(mount: Path, script: str, size: str = "64k") -> subprocess.CompletedProcess:
    """``script`` (sh) in a private mount namespace with a tmpfs of ``size`` on ``mount``."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    return subprocess.run(["unshare", "-m", "sh", "-c",
                           f"mount -t tmpfs -o size={size} tmpfs '{mount}' && {script}"],
                          capture_output=True, text=True, env=env, timeout=300)


def _need_root():
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.fail("these tests mount a private tmpfs: run them as root with unshare (CI "
                    "does)")


@pytest.mark.slow
def test_full_disk_leaves_the_previous_outputs_and_no_partial_file(log, tmp_path):
    _need_root()
    disk = tmp_path / "disk"
    disk.mkdir()
    identify = f"{sys.executable} -m cochlea.apps.cochlea_identify"
    excite = f"{sys.executable} -m cochlea.apps.cochlea_excite"
    fast = " ".join(EXCITE_FAST)
    description = ROOT / "models/robots/serial.toml"
    # The previous report, figures and description; then the disk filled but for ~2 KiB.
    script = (
        f"cp '{description}' {disk}/serial.toml && echo previous > {disk}/ident.json && "
        f"echo previous > {disk}/ident_torques.png && echo previous > {disk}/x.toml && "
        f"(dd if=/dev/zero of={disk}/filler bs=1k count=200 2>/dev/null; true) && "
        f"rm -f {disk}/filler && dd if=/dev/zero of={disk}/filler bs=1k count=$(( "
        f"$(df -k {disk} | awk 'NR==2{{print $4}}') - 2 )) 2>/dev/null; "
        f"{identify} '{log}' {' '.join(FIT)} --out {disk}/ident.json; echo rc=$?; "
        f"{identify} '{log}' {' '.join(FIT)} --out {disk}/ident.json --no-figures "
        f"--update-description {disk}/serial.toml --in-place; echo rc=$?; "
        f"{excite} {fast} --out {disk}/x.toml --force; echo rc=$?; "
        f"echo LS; ls -A {disk}; cat {disk}/ident.json {disk}/ident_torques.png {disk}/x.toml; "
        f"cmp {disk}/serial.toml '{description}' && echo same")
    run = _in_tmpfs(disk, script)
    out = run.stdout.splitlines()
    codes = [line for line in out if line.startswith("rc=")]
    assert codes == [f"rc={EXIT_WRITE_FAILED}"] * 3, run.stdout + run.stderr
    err = run.stderr.splitlines()
    assert len(err) == 3 and all("No space left on device" in e and "previous" in e
                                 for e in err), run.stderr
    listing = out[out.index("LS") + 1:][:5]
    assert sorted(listing) == ["filler", "ident.json", "ident_torques.png", "serial.toml",
                               "x.toml"], run.stdout  # no temporary file left behind
    assert out[-4:] == ["previous", "previous", "previous", "same"], run.stdout


@pytest.mark.slow
def test_read_only_outputs_are_refused_before_the_fit(log, tmp_path):
    _need_root()
    disk = tmp_path / "ro"
    disk.mkdir()
    identify = f"{sys.executable} -m cochlea.apps.cochlea_identify"
    excite = f"{sys.executable} -m cochlea.apps.cochlea_excite"
    description = ROOT / "models/robots/serial.toml"
    script = (
        f"cp '{description}' {disk}/serial.toml && echo previous > {disk}/ident.json && "
        f"mount -o remount,ro {disk} && "
        # A log that does not exist: refused for the output, so before anything is read.
        f"{identify} {tmp_path}/nowhere {' '.join(FIT)} --out {disk}/ident.json; echo rc=$?; "
        f"{identify} '{log}' {' '.join(FIT)} --out {tmp_path}/ident.json "
        f"--update-description {disk}/serial.toml; echo rc=$?; "
        f"{excite} {' '.join(EXCITE_FAST)} --out {disk}/x.toml; echo rc=$?; "
        f"echo LS; ls -A {disk}; cat {disk}/ident.json")
    run = _in_tmpfs(disk, script)
    codes = [line for line in run.stdout.splitlines() if line.startswith("rc=")]
    assert codes == [f"rc={EXIT_OUTPUT_REFUSED}"] * 3, run.stdout + run.stderr
    err = run.stderr.splitlines()
    assert len(err) == 3 and all("Read-only file system" in e for e in err), run.stderr
    assert run.stdout.splitlines()[-3:] == ["ident.json", "serial.toml", "previous"]
    assert not (tmp_path / "ident.json").exists()  # the report never written without its write-back


@pytest.mark.slow
def test_a_report_lands_whole_with_the_previous_mode(log, tmp_path, capsys):
    out = tmp_path / "ident.json"
    out.write_text("previous")
    out.chmod(0o640)
    assert cochlea_identify.main([str(log), *FIT, "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["figures"] == [str(tmp_path / "ident_torques.png"),
                              str(tmp_path / "ident_parameters.png")]
    assert (out.stat().st_mode & 0o777) == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "ident.json", "ident_parameters.png", "ident_torques.png"]


def test_an_interrupted_write_leaves_no_temporary_file(tmp_path):
    """SIGTERM (or Ctrl-C) while the outputs are staged: the temporary files go, the previous
    outputs stay, and the program ends with the shell's code for the signal."""
    report = tmp_path / "ident.json"
    report.write_text("previous")
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), sigterm_unwinds(), files.Staged() as stage:
        stage.write_text(report, "new")
        stage.write_text(tmp_path / "figure.png", "half")
        os.kill(os.getpid(), signal.SIGTERM)
        stage.commit()  # not reached
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ident.json"]
    assert report.read_text() == "previous"
    assert signal.getsignal(signal.SIGTERM) == before  # the previous handler is back
    assert EXIT_TERMINATED == 143


def test_a_hang_up_during_a_write_unwinds_like_sigterm(tmp_path):
    """SIGHUP (the terminal or SSH session closed) is a stop like SIGTERM, not a death that
    leaves staged temporary files: the same unwinding, and the shell's code 128 + 1."""
    report = tmp_path / "ident.json"
    report.write_text("previous")
    before = signal.getsignal(signal.SIGHUP)
    with pytest.raises(Terminated) as caught, sigterm_unwinds(), files.Staged() as stage:
        stage.write_text(report, "new")
        os.kill(os.getpid(), signal.SIGHUP)
        stage.commit()  # not reached
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ident.json"]
    assert report.read_text() == "previous"
    assert signal.getsignal(signal.SIGHUP) == before
    assert exit_code(caught.value) == 129
