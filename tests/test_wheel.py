"""An installed cochlea works outside the repository: descriptions, scenarios, templates and the
compiled C kernels all come from the wheel.

The wheel is built from a copy of the checkout's files (tracked and new, not ignored: what a
clean clone has plus the work in progress), installed with ``--no-deps`` into a fresh virtual
environment in a temporary folder, and run from another temporary folder. The dependencies
(CasADi, numpy, ...) are the test environment's own, made visible to the new environment by a
path file: installing them again from the network would test pip, not cochlea.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow


def _checkout_files() -> list[str]:
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                            check=True, capture_output=True).stdout.decode().split("\0")
    return [f for f in listed if f and (ROOT / f).is_file()]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(bin folder of the fresh environment, a working folder outside the repository)``."""
    base = tmp_path_factory.mktemp("wheel")
    source = base / "source"
    for name in _checkout_files():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    dist = base / "dist"
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                            str(dist), str(source)], capture_output=True, text=True)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = dist.glob("cochlea-*.whl")

    env_dir = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True)
    python = env_dir / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; "
                              "print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    # The test environment's packages, after the new environment's own (so its cochlea wins).
    (Path(purelib) / "test-environment.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    installed = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install",
                                "--no-deps", "-q", str(wheel)], capture_output=True, text=True)
    assert installed.returncode == 0, installed.stderr[-3000:]
    work = base / "work"
    work.mkdir()
    return env_dir / "bin", work


def _run(installed, *command: str) -> subprocess.CompletedProcess:
    bin_dir, work = installed
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "COCHLEA_LIB")}
    return subprocess.run([str(bin_dir / command[0]), *command[1:]], cwd=work, env=env,
                          capture_output=True, text=True, timeout=600)


def test_the_wheel_holds_the_data_and_the_library(installed):
    located = _run(installed, "python", "-c",
                   "import cochlea, cochlea.resources as r\n"
                   "from cochlea.kernels import library\n"
                   "print(cochlea.__file__); print(r.checkout())\n"
                   "print(sorted(p.name for p in r.ROBOTS_DIR.iterdir()))\n"
                   "print(sorted(p.name for p in r.SCENARIOS_DIR.iterdir()))\n"
                   "print(sorted(p.name for p in r.EXAMPLES_DIR.iterdir()))\n"
                   "print(sorted(p.name for p in r.CODEGEN_DIR.iterdir()))\n"
                   "print(library.load().path)\n"
                   "from cochlea.dynamixel import lane\n"
                   "print(lane.library_path() if lane.load() is not None else None)")
    assert located.returncode == 0, located.stderr
    package, checkout, robots, scenarios, examples, codegen, lib, bus_lane = \
        located.stdout.splitlines()
    assert str(installed[0].parent) in package and str(ROOT) not in package
    assert checkout == "None"
    assert robots == "['parallel.toml', 'serial.toml']"
    assert "serial_task.toml" in scenarios and "parallel_joint.toml" in scenarios
    # models/ and codegen/ of the checkout, carried as cochlea/data/ (setup.py)
    assert "planar2_xm540.toml" in examples
    # cochlea_trig.h: what cochlea-codegen copies beside a user's ideal plant steps
    assert codegen == "['closed_loop.c.in', 'cochlea_trig.h', 'kernels.toml']"
    assert lib.startswith(str(installed[0].parent)) and lib.endswith("cochlea/lib/libcochlea.so")
    # the bus lane (the emulator's and the bridge's packet work in C) beside it
    assert bus_lane == str(Path(lib).parent / "libcochlea-lane.so")


def test_cochlea_run_outside_the_repository(installed):
    run = _run(installed, "cochlea-run", "--robot", "serial", "--space", "task",
               "--realtime", "off", "--out", "serial_task")
    assert run.returncode == 0, run.stderr
    assert "converged: yes" in run.stdout
    # No fallback: the wheel's own C kernels ran, and the run says so.
    assert "kernels: C kernels from " in run.stdout and "cochlea/lib/libcochlea.so" in run.stdout
    assert "CasADi" not in run.stdout + run.stderr
    out = installed[1] / "serial_task"
    assert (out / "log.csv").is_file() and (out / "summary.json").is_file()


def test_cochlea_model_outside_the_repository(installed):
    model = _run(installed, "cochlea-model")
    assert model.returncode == 0, model.stderr
    assert "serial/arm1" in model.stdout and "M(q) [kg m^2]" in model.stdout
    parallel = _run(installed, "cochlea-model", "parallel")
    assert parallel.returncode == 0, parallel.stderr
    assert "inside the workspace" in parallel.stdout
