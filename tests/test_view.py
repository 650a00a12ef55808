"""cochlea-view: a run replayed in 3-D in the browser (docs/logs.md).

The replay's frames are held to the robot model's forward kinematics (``fk_world``) and to the
log, row by row, for the shipped serial arms, the parallel mechanism and an arm imported from a
URDF; the page is loaded, from the command's own server, in a real headless Chromium (Debian's
``chromium``: found, or installed with apt-get when the tests run as root; the test fails, one
line, if neither works), which must draw it (its status line, from the DOM), draw equal images
for equal loads, and different images of the robot at two replay times; each class of bad input
is one line and its documented exit code, with nothing left under the output's name.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps.cochlea_view import EXIT_HTML_OUT, EXIT_PORT, main
from cochlea.errors import EXIT_USER_ERROR
from cochlea.export.run_log import open_run
from cochlea.view.replay import DEFAULT_RATE_HZ, build_replay

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = "/usr/bin/chromium"
#: The links' colour on the page (#1f5fbf).
LINK_RGB = (0x1F, 0x5F, 0xBF)
TOL = 2e-7  # m: the page's positions are rounded to 0.1 um


def find_chromium() -> str:
    """Debian's Chromium: found, or installed with apt-get (as root, e.g. on a fresh CI
    machine); a one-line failure otherwise."""
    found = shutil.which("chromium") or (CHROMIUM if os.path.exists(CHROMIUM) else None)
    if found:
        return found
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        pytest.fail("cochlea-view's tests need Debian's chromium: run them as root (they "
                    "apt-get install it) or install it: apt-get install -y chromium",
                    pytrace=False)
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    for command in (["apt-get", "install", "-y", "chromium"],
                    ["apt-get", "update"], ["apt-get", "install", "-y", "chromium"]):
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=900)
        if command[1] == "install" and done.returncode == 0:
            break
    found = shutil.which("chromium")
    if not found:
        pytest.fail(f"apt-get install -y chromium failed: {done.stderr.strip()[-300:]}",
                    pytrace=False)
    return found


def chromium(browser: str, url: str, *args: str) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run(
            [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}",
             *args, url], capture_output=True, text=True, timeout=120)


def screenshot(browser: str, url: str, path: Path) -> np.ndarray:
    from PIL import Image
    done = chromium(browser, url, f"--screenshot={path}", "--window-size=800,600")
    assert done.returncode == 0 and path.is_file(), done.stderr[-500:]
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def cochlea(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def cochlea_run(out: Path, *args: str) -> Path:
    done = cochlea("cochlea.apps.cochlea_run", *args, "--out", str(out), "--status", "off",
                   "--realtime", "off", cwd=out.parent)
    assert done.returncode == 0, done.stderr
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """As-fast runs of the serial arms in task space, the parallel mechanism in joint space,
    and an arm imported from a URDF (tests/data/arm4.urdf up to its bracket: a 3-D arm with a
    tilted joint axis) in joint space."""
    base = tmp_path_factory.mktemp("view_runs")
    done = cochlea("cochlea.apps.cochlea_urdf", "import", str(ROOT / "tests/data/arm4.urdf"),
                   "--tip", "bracket", "--out", str(base / "arm4.toml"), "--scenario-out",
                   str(base / "arm4_joint.toml"), cwd=base)
    assert done.returncode == 0, done.stderr
    return {
        "serial_task": cochlea_run(base / "serial_task", "--robot", "serial", "--space", "task",
                                   "--duration", "1.0"),
        "parallel_joint": cochlea_run(base / "parallel_joint", "--robot", "parallel",
                                      "--space", "joint", "--duration", "1.0"),
        "imported_arm": cochlea_run(base / "imported_arm", "--robot", "serial", "--space",
                                    "joint", "--scenario", str(base / "arm4_joint.toml"),
                                    "--duration", "1.0"),
    }


@pytest.fixture(scope="module")
def replays(runs) -> dict[str, dict]:
    return {name: build_replay(open_run(folder)) for name, folder in runs.items()}


def log_rows(folder: Path) -> tuple[list[str], np.ndarray]:
    with open(folder / "log.csv") as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(folder / "log.csv", delimiter=",", skiprows=1, ndmin=2)


# ---- the frames against the model ------------------------------------------------------------


@pytest.mark.parametrize("name", ["serial_task", "parallel_joint", "imported_arm"])
@pytest.mark.slow
def test_frames_are_the_models_forward_kinematics(runs, replays, name):
    """Every kept row is a row of the log, about 50 per second; the tool's frame and the actual
    tool path are the model's ``fk_world`` at that row's ``q``; a joint-space run's desired
    path is ``fk_world`` at the desired joints, a task-space run's the desired columns; each
    link joins two frames one link length apart at every time (rigid)."""
    run = open_run(runs[name])
    replay = replays[name]
    header, rows = log_rows(runs[name])
    times = np.array(replay["times"])
    index = np.searchsorted(rows[:, 0], times)
    assert np.allclose(rows[index, 0], times, atol=1e-12)
    assert index[0] == 0 and index[-1] == len(rows) - 1
    assert np.all(np.diff(times)[:-1] >= 1 / DEFAULT_RATE_HZ - 1.5e-3)
    assert len(times) >= rows[-1, 0] * DEFAULT_RATE_HZ
    for unit, view in zip(run.units, replay["units"]):
        model = run.adapter.model(run.system, unit.name)
        cols = [header.index(f"{unit.name}.q.{e}") for e in unit.groups["q"].elements]
        frames = np.array(view["frames"], float)  # (n, k, 3)
        fk = np.array([np.array(model.fk_world(rows[r, cols])).ravel() for r in index])
        tools = [(0, 1)] if fk.shape[1] == 3 else [(0, 1), (3, 4)]
        tool_frames = [i for i, f in enumerate(view["frame_names"]) if f.endswith("/tool")]
        if not tool_frames:  # the parallel mechanism: its end effectors C and C' (link5)
            tool_frames = [i for i, f in enumerate(view["frame_names"]) if f.endswith("/link5")]
        assert len(tool_frames) == len(tools)
        for (u, v), frame, actual in zip(tools, tool_frames, view["actual"]):
            assert np.abs(frames[:, frame, :2] - fk[:, [u, v]]).max() < TOL
            assert np.abs(np.array(actual, float)[:, :2] - fk[:, [u, v]]).max() < TOL
            assert np.abs(np.array(actual, float) - frames[:, frame]).max() < TOL
        desired = unit.groups["desired"]
        if run.summary["space"] == "joint":
            fk_d = np.array([np.array(model.fk_world(rows[r, desired.columns])).ravel()
                             for r in index])
        else:
            fk_d = rows[np.ix_(index, desired.columns)]
        for (u, v), wanted in zip(tools, view["desired"]):
            assert np.abs(np.array(wanted, float)[:, :2] - fk_d[:, [u, v]]).max() < TOL
        names = view["frame_names"]
        edges = [(names[a], names[b]) for a, b in view["edges"]]
        if run.adapter.name == "parallel":  # each side's parallelogram and its rod S -> C
            assert sorted(edges) == sorted(
                (f"mechanism/{side}/{a}", f"mechanism/{side}/{b}") for side in ("left", "right")
                for a, b in (("link1", "link2"), ("link4", "link3"), ("link2", "link5"),
                             ("link3", "link5"), ("link7", "link5")))
        else:  # the chain: base, links, tool
            assert edges == list(zip(names[:-1], names[1:]))
        # every link is rigid (one length at every time) but the rod, which slides through S
        lengths = np.array([np.linalg.norm(frames[:, a] - frames[:, b], axis=1)
                            for a, b in view["edges"] if not names[a].endswith("/link7")])
        assert np.abs(lengths - lengths[:, :1]).max() < 1e-6


@pytest.mark.slow
def test_keep_out_and_stop_come_from_the_description_and_summary(runs, replays, tmp_path):
    """The keep-out circle is the description's ``keep_out_radius_m`` (the mechanism's
    follows its slider d1); a supervisor's stop in summary.json is marked, a clean run has
    none."""
    serial, parallel = replays["serial_task"], replays["parallel_joint"]
    for replay, folder in ((serial, runs["serial_task"]), (parallel, runs["parallel_joint"])):
        run = open_run(folder)
        assert [k["radius"] for k in replay["keep_out"]] == [run.system.keep_out_radius]
        assert replay["stop"] is None
    header, rows = log_rows(runs["parallel_joint"])
    d1 = rows[np.searchsorted(rows[:, 0], parallel["times"]),
              header.index("mechanism.q.slider.d1_m")]
    assert np.abs(np.array(parallel["keep_out"][0]["moving"]) - d1).max() < TOL
    assert serial["keep_out"][0]["moving"] is None
    stopped = tmp_path / "stopped"
    shutil.copytree(runs["serial_task"], stopped)
    summary = json.loads((stopped / "summary.json").read_text())
    summary["stop"] = {"rule": "keep-out", "time_s": 0.5, "exit_code": 5,
                       "detail": "arm1's tool 19.8 mm from the cochlea centre"}
    (stopped / "summary.json").write_text(json.dumps(summary))
    stop = build_replay(open_run(stopped))["stop"]
    assert stop == {"rule": "keep-out", "kind": "stopped", "time_s": 0.5,
                    "detail": "arm1's tool 19.8 mm from the cochlea centre"}


# ---- in a real browser -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser() -> str:
    return find_chromium()


class Server:
    """``cochlea-view RUN_DIR --port 0 --no-open`` in a subprocess; its URL."""

    def __init__(self, folder: Path):
        # Ctrl-C (stop's SIGINT) reaches it as a terminal's would: a test run started in the
        # background by a non-interactive shell has SIGINT ignored, which a child inherits.
        self.process = subprocess.Popen(
            [sys.executable, "-m", "cochlea.apps.cochlea_view", str(folder), "--no-open"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        line = self.process.stdout.readline()
        assert "serving" in line, (line, self.process.stderr.read() if
                                   self.process.poll() is not None else "")
        self.url = line.split(" on ")[-1].split()[0]

    def stop(self) -> int:
        self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()  # the test fails, and leaves no server behind
            self.process.wait()
            raise


@pytest.mark.parametrize("name", ["serial_task", "parallel_joint", "imported_arm"])
@pytest.mark.slow
def test_the_browser_draws_the_replay_and_the_robot_moves(runs, replays, browser, name,
                                                          tmp_path):
    server = Server(runs[name])
    try:
        assert server.url.startswith("http://127.0.0.1:")
        frames = len(replays[name]["times"])
        end = replays[name]["times"][-1]
        dom = chromium(browser, f"{server.url}?t=0.05", "--dump-dom")
        assert dom.returncode == 0, dom.stderr[-500:]
        assert f'<span id="status">drawn {frames} frames, t = 0.040 s</span>' in dom.stdout
        first = screenshot(browser, f"{server.url}?t=0.05", tmp_path / "a.png")
        again = screenshot(browser, f"{server.url}?t=0.05", tmp_path / "b.png")
        last = screenshot(browser, f"{server.url}?t={end}", tmp_path / "c.png")
    finally:
        assert server.stop() == 0
    assert np.array_equal(first, again)  # equal loads, equal images
    robot = np.zeros(first.shape[:2], bool)
    for image in (first, last):
        robot |= (np.abs(image - LINK_RGB).sum(axis=2) < 30)
    assert robot.sum() > 200, "no links drawn"
    ys, xs = np.nonzero(robot)
    region = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    changed = np.abs(first[region] - last[region]).sum(axis=2) > 30
    assert changed.sum() > 50, "the robot's region is the same at both times"


@pytest.mark.slow
def test_the_stop_is_shown_on_the_page(runs, browser, tmp_path):
    stopped = tmp_path / "stopped"
    shutil.copytree(runs["parallel_joint"], stopped)
    summary = json.loads((stopped / "summary.json").read_text())
    summary["supervisor"] = {"rule": "keep-out", "time_s": 0.4, "exit_code": 5,
                             "detail": "C 10 mm from S", "saturated_periods": 0}
    (stopped / "summary.json").write_text(json.dumps(summary))
    page = tmp_path / "replay.html"
    assert main([str(stopped), "--html-out", str(page)]) == 0
    dom = chromium(browser, page.as_uri() + "?t=0.6", "--dump-dom")
    assert ('<span id="stop">supervisor: would have stopped by rule keep-out at t = 0.4 s'
            '</span>') in dom.stdout


# ---- bad input ---------------------------------------------------------------------------------


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("cochlea-view: ") and "Traceback" not in err
    return err


@pytest.mark.slow
def test_bad_input_is_one_line_and_its_exit_code(runs, tmp_path, capsys):
    good = runs["serial_task"]
    page = tmp_path / "page.html"
    # not a run folder; a damaged log
    assert main([str(tmp_path / "missing"), "--html-out", str(page)]) == EXIT_USER_ERROR
    one_line(capsys)
    assert main([str(tmp_path), "--html-out", str(page)]) == EXIT_USER_ERROR
    one_line(capsys)
    damaged = tmp_path / "damaged"
    shutil.copytree(good, damaged)
    text = (damaged / "log.csv").read_text().splitlines()
    text[40] = text[40].replace(",", ",x", 1)
    (damaged / "log.csv").write_text("\n".join(text) + "\n")
    assert main([str(damaged), "--html-out", str(page)]) == EXIT_USER_ERROR
    assert "damaged" in one_line(capsys)
    truncated = tmp_path / "truncated"
    shutil.copytree(good, truncated)
    (truncated / "log.csv").write_text("\n".join(text[:30]) + "\n")
    assert main([str(truncated), "--html-out", str(page)]) == EXIT_USER_ERROR
    one_line(capsys)
    # --html-out: not a regular file, its folder missing; nothing left under its name
    for out in (tmp_path, Path("/dev/null"), tmp_path / "no_folder" / "page.html"):
        assert main([str(good), "--html-out", str(out)]) == EXIT_HTML_OUT
        one_line(capsys)
    assert not page.exists() and not (tmp_path / "no_folder").exists()
    link = tmp_path / "dangling.html"
    link.symlink_to(tmp_path / "nowhere")
    assert main([str(good), "--html-out", str(link)]) == EXIT_HTML_OUT
    one_line(capsys)
    # a port in use (held here, on 127.0.0.1), a number that is no port
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert main([str(good), "--no-open", "--port", str(port)]) == EXIT_PORT
        assert "cannot serve" in one_line(capsys)
    assert main([str(good), "--no-open", "--port", "70000"]) == EXIT_PORT
    one_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["damaged", "dangling.html",
                                                         "truncated"]


@pytest.mark.slow
def test_html_out_is_never_one_of_the_runs_own_files(runs, tmp_path, capsys):
    """--html-out naming the run's log.csv, summary.json or a figure (directly or through a
    link) is refused (exit 4, one line) and the run's files are unchanged (a probe found
    log.csv replaced by the page, exit 0)."""
    run = tmp_path / "run"
    shutil.copytree(runs["parallel_joint"], run)
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    (tmp_path / "link.html").symlink_to(run / "summary.json")
    for out in (run / "log.csv", run / "summary.json", run / "paths.png",
                tmp_path / "link.html"):
        assert main([str(run), "--html-out", str(out)]) == EXIT_HTML_OUT
        assert "the run's own" in one_line(capsys)
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before


@pytest.mark.slow
def test_sigterm_while_the_page_is_written_leaves_nothing(runs, tmp_path):
    """SIGTERM while --html-out is written unwinds as Ctrl-C: exit 143, one line, and neither
    the page nor its hidden temporary file is left (the temporary file was)."""
    script = (
        "import os, signal, sys, pathlib\n"
        "from cochlea.apps.cochlea_view import main\n"
        "real = pathlib.Path.write_text\n"
        "def write_text(self, text, *a, **k):\n"
        "    real(self, text[:100], *a, **k)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    return real(self, text, *a, **k)\n"
        "pathlib.Path.write_text = write_text\n"
        "sys.exit(main(sys.argv[1:]))\n")
    out = tmp_path / "out"
    out.mkdir()
    done = subprocess.run([sys.executable, "-c", script, str(runs["parallel_joint"]),
                           "--html-out", str(out / "page.html")], capture_output=True,
                          text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 143, done.stderr
    assert done.stderr == "cochlea-view: terminated; nothing written\n"
    assert list(out.iterdir()) == []


@pytest.mark.slow
def test_html_out_writes_a_self_contained_page(runs, replays, tmp_path, capsys):
    page = tmp_path / "replay.html"
    page.write_text("old")
    assert main([str(runs["imported_arm"]), "--html-out", str(page)]) == 0
    text = page.read_text()
    assert "http://" not in text and "https://" not in text and "src=" not in text
    data = text.split('<script id="replay" type="application/json">')[1].split("</script>")[0]
    assert json.loads(data) == json.loads(json.dumps(replays["imported_arm"]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["replay.html"]


@pytest.mark.slow
def test_a_long_run_is_kept_at_a_lower_rate(runs, monkeypatch):
    """The page's frames are capped (MAX_FRAMES): a run longer than the cap at 50 Hz is kept
    at the rate that fits, first and last rows included."""
    from cochlea.view import replay as module
    monkeypatch.setattr(module, "MAX_FRAMES", 10)
    capped = module.build_replay(open_run(runs["parallel_joint"]))
    assert capped["rate_hz"] == pytest.approx(10 / 1.0)
    assert 10 <= len(capped["times"]) <= 12
    assert capped["times"][0] == 0.0 or capped["times"][0] < 2e-3
    header, rows = log_rows(runs["parallel_joint"])
    assert capped["times"][-1] == rows[-1, 0]


def _last_row_edited(run: Path, folder: Path, cells: dict[str, str]) -> Path:
    """A copy of ``run`` in ``folder`` whose log.csv's last row has ``cells`` (column: text)."""
    shutil.copytree(run, folder)
    lines = (folder / "log.csv").read_text().splitlines()
    header = lines[0].split(",")
    row = lines[-1].split(",")
    for column, text in cells.items():
        row[header.index(column)] = text
    lines[-1] = ",".join(row)
    (folder / "log.csv").write_text("\n".join(lines) + "\n")
    return folder


@pytest.mark.slow
def test_a_row_whose_q_is_not_finite_is_not_drawn(runs, tmp_path):
    """A run stopped by the rule non-finite logs NaN joints: that row has no frames and no
    actual tool point, and the page (strict JSON) is still written."""
    folder = _last_row_edited(runs["serial_task"], tmp_path / "nan",
                              {"arm2.q.joint2_rad": "nan"})
    replay = build_replay(open_run(folder))
    arm1, arm2 = replay["units"]
    assert arm2["frames"][-1] is None and arm2["actual"][0][-1] == [None, None, None]
    assert arm1["frames"][-1] is not None and None not in arm1["actual"][0][-1]
    assert main([str(folder), "--html-out", str(tmp_path / "page.html")]) == 0


@pytest.mark.slow
def test_a_value_too_large_to_round_is_drawn_as_it_is(runs, tmp_path, capsys):
    """A desired cell of 1e305 (and a q of 1e300): rounding it to 0.1 um overflowed to inf and
    the page's strict JSON refused it (ValueError traceback); now a finite value is kept, one
    that is not finite becomes null, and the page is written."""
    folder = _last_row_edited(runs["serial_task"], tmp_path / "big",
                              {"arm1.desired.x_m": "1e305", "arm2.q.joint1_rad": "1e300"})
    page = tmp_path / "page.html"
    assert main([str(folder), "--html-out", str(page)]) == 0, capsys.readouterr().err
    data = page.read_text().split('<script id="replay" type="application/json">')[1]
    replay = json.loads(data.split("</script>")[0])
    assert replay["units"][0]["desired"][0][-1][0] == 1e305


@pytest.mark.slow
@pytest.mark.parametrize("field, value", [("duration_s", 10**30), ("space", float("inf")),
                                          ("periods", float("nan")), ("stop", {"rule": "x",
                                                                               "time_s": 10**30})])
def test_a_summary_with_numbers_no_reader_expects_is_one_line_or_drawn(runs, tmp_path, capsys,
                                                                        field, value):
    """Fuzzing 400 summaries (a field set to 10**400, infinity, NaN, text...) found two
    tracebacks: an integer no float holds (duration_s) and an infinity copied into the page's
    JSON (space). Now an integer beyond 64 bits is a damaged summary (one line, exit 2) and a
    field of the wrong kind is left out of the page."""
    damaged = tmp_path / "run"
    shutil.copytree(runs["serial_task"], damaged)
    summary = json.loads((damaged / "summary.json").read_text())
    summary[field] = value
    (damaged / "summary.json").write_text(json.dumps(summary).replace(
        "1000000000000000000000000000000", "1" + "0" * 400))
    code = main([str(damaged), "--html-out", str(tmp_path / "page.html")])
    if field in ("duration_s", "stop"):
        assert code == EXIT_USER_ERROR and "integer of 401 digits" in one_line(capsys)
    elif field == "periods":  # the count the log is checked against: a whole number only
        assert code == EXIT_USER_ERROR and "its periods is nan" in one_line(capsys)
    else:
        assert code == 0 and (tmp_path / "page.html").is_file()
