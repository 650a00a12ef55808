"""cochlea.ros2.tf2_msgs_build, the step of ``make test`` that gives the environment tf2_msgs
(no wheel on the package index): done once (the installed version names its inputs), refused
in one line when what it would install is not Jazzy's TFMessage or when a tool is missing, and
never installing anything then. Whether the installed type works on the wire and in a run is
tests/test_ros2.py's."""

from __future__ import annotations

import sysconfig

import pytest

from cochlea.ros2 import tf2_msgs_build as build


def one_line(capsys, code: int, *argv: str, stream: str = "err") -> str:
    assert build.main(list(argv)) == code
    out = capsys.readouterr()
    text = getattr(out, stream)
    lines = text.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{build.PROG}: "), (out.out, out.err)
    assert "Traceback" not in out.out + out.err
    return lines[0]


def test_an_installed_build_is_not_built_again(capsys, tmp_path):
    """make test runs the step every time: with this version installed it does nothing."""
    assert build.installed_version() == build.version(), "tf2_msgs not built: make test does"
    line = one_line(capsys, 0, "--cache", str(tmp_path), stream="out")
    assert "is installed" in line and not any(tmp_path.iterdir())


@pytest.fixture
def unchanged(monkeypatch, tmp_path):
    """The installed version before and after (a refused build installs nothing), and no wheel
    left in the cache; the environment the generators set restored."""
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    before = build.installed_version()
    yield tmp_path
    assert build.installed_version() == before
    assert not list(tmp_path.glob("*.whl"))


def test_a_type_that_is_not_jazzys_is_refused(capsys, monkeypatch, unchanged):
    """A definition whose type hash is not Jazzy's (one field renamed) is generated, and
    refused before anything is compiled or installed."""
    monkeypatch.setattr(build, "MSG", "geometry_msgs/TransformStamped[] transform\n")
    line = one_line(capsys, build.EXIT_FAILED, "--force", "--cache", str(unchanged))
    assert "type hash RIHS01_" in line and f"not Jazzy's {build.JAZZY_HASH}" in line


def test_a_missing_compiler_is_one_line(capsys, monkeypatch, unchanged):
    monkeypatch.setenv("CC", str(unchanged / "no-such-cc"))
    line = one_line(capsys, build.EXIT_FAILED, "--force", "--cache", str(unchanged))
    assert "no C/C++ compiler (" in line and "no-such-cc not found" in line


def test_missing_python_headers_are_one_line(capsys, monkeypatch, unchanged):
    monkeypatch.setattr(sysconfig, "get_paths", lambda: {"include": str(unchanged)})
    line = one_line(capsys, build.EXIT_FAILED, "--force", "--cache", str(unchanged))
    assert f"{unchanged}/Python.h is missing" in line and "python3-dev" in line


def test_without_the_ros_extra_it_says_how_to_install_it(capsys, monkeypatch, unchanged):
    monkeypatch.setattr(build, "INPUTS", (*build.INPUTS, "ros-no-such-generator"))
    line = one_line(capsys, build.EXIT_NO_ROS, "--force", "--cache", str(unchanged))
    assert "ros-no-such-generator is not installed" in line and "cochlea[ros]" in line
    monkeypatch.setattr(build, "MISSING", "No module named 'rosidl_generator_c'")
    monkeypatch.setattr(build, "INPUTS", build.INPUTS[:-1])
    line = one_line(capsys, build.EXIT_NO_ROS, "--force", "--cache", str(unchanged))
    assert "rosidl_generator_c" in line and "cochlea[ros]" in line
