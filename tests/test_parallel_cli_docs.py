"""The parallel mechanism on the command line, its figure, and the examples of its
documentation."""

from __future__ import annotations

import pytest

from cochlea.apps.cochlea_model import main as model_main
from cochlea.apps.figures import DOCS_DIR, draw_parallel

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def test_cli_prints_the_parallel_summary(capsys):
    assert model_main(["parallel"]) == 0
    out = capsys.readouterr().out
    assert "model 'parallel': 5 joints, lagrange dynamics" in out
    assert "joint slider.d1: prismatic, 0..0.15 m" in out
    assert "base parameters (27):" in out
    assert "motor slider.d1: XM540-W270 ID 1" in out and "pinion 0.02 m" in out
    assert "left  end effector C  = (0.125772, 0.114928) m, phi  = 19.354 deg" in out
    assert "right end effector C' = (-0.125772, 0.114928) m, phi' = 160.646 deg" in out
    assert "inside the workspace" in out


def test_cli_at_a_given_configuration(capsys):
    assert model_main(["parallel", "--parameterisation", "mass", "--at", "131.5", "29",
                       "0.073", "43", "150"]) == 0
    out = capsys.readouterr().out
    assert "mass parameters (13):" in out
    assert "q = [131.5, 29.0, 0.073, 43.0, 150.0]" in out
    assert "C  = (0.141200, 0.123377) m" in out
    assert model_main(["parallel", "--at", "10", "29", "0.073", "43", "150"]) == 0
    assert "outside the workspace: left.th1 = 10.000 deg is outside [45, 180] deg" in \
        capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["parallel", "--arm", "arm1"], "--arm is for the serial system"),
    (["parallel", "--at-deg", "1", "2", "3"], "with --at"),
    (["parallel", "--method", "newton-euler"], "Lagrange method only"),
    (["serial", "--at", "1", "2", "3", "4", "5"], "give the serial arm's joint angles"),
])
def test_cli_refuses_options_of_the_other_robot(argv, message, capsys):
    assert model_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("cochlea-model: ") and message in err


@pytest.mark.parametrize("argv", [
    ["serial", "--arm", "arm1", "--at-deg", "nan", "0", "0"],
    ["serial", "--arm", "arm1", "--at-deg", "0", "inf", "0"],
    ["serial", "--arm", "arm1", "--at-deg", "1_0", "0", "0"],  # float(): 10
    ["parallel", "--at", "nan", "29", "0.073", "43", "150"],
    ["parallel", "--at", "131.5", "29", "inf", "43", "150"],
    ["parallel", "--at", "131.5", "1e300", "0.073", "43", "150"],
], ids=["serial-nan", "serial-inf", "serial-underscore", "parallel-nan", "parallel-inf",
        "parallel-huge"])
def test_cli_refuses_a_configuration_that_is_not_a_finite_number(argv, capsys):
    """Before, NaN and inf printed rows of NaN with exit 0."""
    assert model_main(argv) == 2
    captured = capsys.readouterr()
    assert "expected a finite decimal number" in captured.err
    assert len(captured.err.strip().splitlines()) == 1 and "nan" not in captured.out.lower()


def test_cli_serial_unchanged(capsys):
    assert model_main(["serial", "--arm", "arm1", "--at-deg", "73", "83", "110"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("model 'serial/arm1': 3 joints, newton-euler dynamics")


@pytest.mark.slow
def test_figure_is_written(tmp_path):
    import matplotlib.pyplot as plt

    path = tmp_path / "geometry.png"
    plt.close(draw_parallel(path=path))
    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 10_000
    committed = DOCS_DIR / "parallel_geometry.png"
    assert committed.read_bytes().startswith(PNG_SIGNATURE)
