"""A user's robot on C kernels (issue 25, item 4): ``cochlea-codegen --scenario FILE --out DIR``
generates and compiles the kernels of a robot cochlea does not ship (a 2-DoF arm imported from
a URDF with ``cochlea-urdf import``), the as-fast run on them gives the CasADi run's log, a
library that lacks or mismatches a kernel is refused in one line under ``--kernels c``, and
every run states the kernels it used (console and summary.json)."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps import cochlea_codegen, cochlea_run, cochlea_urdf
from cochlea.errors import EXIT_USER_ERROR
from cochlea.kernels.library import ENVIRONMENT, library_path
from cochlea.sim import CKernelsUnavailable, load_scenario, simulate, unit_setups

#: Two revolute joints about parallel axes, XM540 motors (cochlea-urdf import's default).
ARM2_URDF = """<?xml version="1.0"?>
<robot name="arm2dof">
  <link name="base"/>
  <link name="upper">
    <inertial><origin xyz="0.12 0 0"/><mass value="0.5"/>
      <inertia ixx="0.0004" iyy="0.003" izz="0.003" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <link name="fore">
    <inertial><origin xyz="0.1 0 0"/><mass value="0.3"/>
      <inertia ixx="0.0002" iyy="0.0015" izz="0.0015" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="upper"/><origin xyz="0 0 0.05"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" velocity="3" effort="8"/>
  </joint>
  <joint name="elbow" type="revolute">
    <parent link="upper"/><child link="fore"/><origin xyz="0.25 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" velocity="3" effort="8"/>
  </joint>
</robot>
"""
ROOT = Path(__file__).resolve().parent.parent
FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "pose", "true_q",
          "true_qd", "true_x")


def assert_same_log(result, reference, tol=1e-10):
    assert np.array_equal(result.time, reference.time)
    assert result.diverged == reference.diverged
    for u, r in zip(result.units, reference.units, strict=True):
        for key in FIELDS:
            np.testing.assert_allclose(getattr(u, key), getattr(r, key), rtol=tol, atol=tol,
                                       err_msg=f"{u.name}.{key}")


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """The user's three commands: import the URDF (description and starter scenario),
    generate and compile the kernels; ``(scenario path, kernels folder)``."""
    folder = tmp_path_factory.mktemp("user")
    urdf = folder / "arm2.urdf"
    urdf.write_text(ARM2_URDF, encoding="utf-8")
    assert cochlea_urdf.main(["import", str(urdf), "--out", str(folder / "robot.toml"),
                              "--scenario-out", str(folder / "starter.toml")]) == 0
    # The realistic plant needs the drives' rotor inertia, which a URDF does not carry.
    robot = folder / "robot.toml"
    robot.write_text(robot.read_text(encoding="utf-8").replace(
        "  torque_limit_Nm = 8.0\n", "  torque_limit_Nm = 8.0\n  armature_kgm2 = 0.01\n"),
        encoding="utf-8")
    kernels = folder / "kernels"
    assert cochlea_codegen.main(["--scenario", str(folder / "starter.toml"),
                                 "--out", str(kernels), "--embedded", "--plant", "ideal",
                                 "--plant", "realistic"]) == 0
    return folder / "starter.toml", kernels


@pytest.mark.slow
def test_the_folder_holds_the_c_its_manifest_and_the_library(user):
    scenario, kernels = user
    names = {p.name for p in kernels.iterdir()}
    assert {"manifest.c", "closed_loop.c", "cochlea.h", "README.md", "libcochlea.so"} <= names
    assert library_path(kernels) == kernels / "libcochlea.so"
    # Deterministic: generating again gives the same files, byte for byte.
    assert cochlea_codegen.main(["--scenario", str(scenario), "--out", str(kernels),
                                 "--plant", "ideal", "--plant", "realistic", "--check"]) == 0
    header = (kernels / "cochlea.h").read_text()
    (kernels / "cochlea.h").write_text("/* edited */\n")
    assert cochlea_codegen.main(["--scenario", str(scenario), "--out", str(kernels),
                                 "--plant", "ideal", "--plant", "realistic", "--check"]) == 1
    (kernels / "cochlea.h").write_text(header)
    assert cochlea_codegen.main(["--scenario", str(scenario), "--out", str(kernels),
                                 "--plant", "ideal", "--plant", "realistic", "--embedded",
                                 "--check"]) == 0


@pytest.mark.parametrize("plant", ["ideal", "coulomb", "realistic"])
@pytest.mark.slow
def test_the_c_run_gives_the_casadi_log(user, plant):
    """The as-fast run on the user's C kernels equals the CasADi reference (as the shipped
    robots' do, tests/test_sim_compiled.py); with Coulomb friction, on the sibling plant step
    the generator adds for it; with the realistic preset (``--plant realistic``: the geared
    plant, the drives' grids, a period of delay), on its geared plant step."""
    scenario, kernels = user
    sc = load_scenario(scenario, plant_preset="realistic" if plant == "realistic" else None)
    if plant == "coulomb":
        sc = dataclasses.replace(sc, plant=dataclasses.replace(
            sc.plant, coulomb_friction=np.full(2, 0.02)))
    setups = unit_setups(sc)
    result = simulate(sc, 1.0, setups, kernels="c", library=kernels)
    assert result.kernels == {"used": "c", "requested": "c",
                              "library": str((kernels / "libcochlea.so").resolve()),
                              "fallback_reason": None}
    reference = simulate(sc, 1.0, setups, kernels="casadi")
    assert reference.kernels["used"] == "casadi"
    assert_same_log(result, reference)


#: The shipped library has no kernel of the user's robot (or is not built in this checkout).
NOT_THERE = "has no kernel .*cochlea-codegen --scenario|does not exist"


@pytest.mark.slow
def test_a_library_without_or_with_other_kernels_is_refused(user):
    scenario, kernels = user
    sc = load_scenario(scenario)
    setups = unit_setups(sc)
    with pytest.raises(CKernelsUnavailable, match=NOT_THERE):
        simulate(sc, 0.01, setups, kernels="c")  # the shipped library: no such robot
    # Another parameterisation: the same names, another computation (source hashes differ).
    mass = dataclasses.replace(sc, parameterisation="mass")
    with pytest.raises(CKernelsUnavailable, match="computes something else"):
        simulate(mass, 0.01, unit_setups(mass), kernels="c", library=kernels)
    with pytest.warns(UserWarning, match="CasADi kernels"):  # auto: falls back, and says so
        fallback = simulate(mass, 0.01, unit_setups(mass), library=kernels)
    assert fallback.kernels["used"] == "casadi" and fallback.kernels["requested"] == "auto"
    assert "computes something else" in fallback.kernels["fallback_reason"]


def _run(tmp_path, capsys, scenario, *options):
    out = tmp_path / "run"
    code = cochlea_run.main(["--robot", "serial", "--space", "joint", "--scenario",
                             str(scenario), "--realtime", "off", "--duration", "0.2",
                             "--out", str(out), *options])
    return code, out, capsys.readouterr()


@pytest.mark.slow
def test_a_run_states_its_kernels(user, tmp_path, capsys):
    scenario, kernels = user
    environment = os.environ.get(ENVIRONMENT)
    code, out, io = _run(tmp_path / "c", capsys, scenario, "--kernels", "c", "--library",
                         str(kernels))
    assert code == 0, io.err
    assert f"cochlea-run: kernels: C kernels from {(kernels / 'libcochlea.so').resolve()}" \
        in io.out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kernels"]["used"] == "c"
    assert os.environ.get(ENVIRONMENT) == environment  # the run put $COCHLEA_LIB back

    # auto, and the shipped library has no kernel of this robot: CasADi, said on the console
    # and in summary.json with the reason.
    code, out, io = _run(tmp_path / "auto", capsys, scenario)
    assert code == 0, io.err
    assert "cochlea-run: kernels: CasADi (the C kernels cannot run this scenario: " in io.out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kernels"]["used"] == "casadi"
    assert re.search(NOT_THERE, summary["kernels"]["fallback_reason"])

    # c, and the library lacks them: one line, exit 2, no folder.
    code, out, io = _run(tmp_path / "refused", capsys, scenario, "--kernels", "c")
    assert code == EXIT_USER_ERROR
    assert io.err.startswith("cochlea-run: --kernels c: ") and io.err.count("\n") == 1
    assert not out.exists()


@pytest.mark.slow
def test_codegen_option_mistakes_are_one_line(user, tmp_path, capsys):
    scenario, _ = user
    assert cochlea_codegen.main(["--scenario", str(scenario)]) == EXIT_USER_ERROR
    assert "--scenario needs --out DIR" in capsys.readouterr().err
    assert cochlea_codegen.main(["--description", str(scenario.parent / "robot.toml"),
                                 "--out", str(tmp_path / "k")]) == EXIT_USER_ERROR
    assert "go with --scenario" in capsys.readouterr().err
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    assert cochlea_codegen.main(["--scenario", str(scenario), "--out",
                                 str(tmp_path / "mine")]) == EXIT_USER_ERROR
    assert "did not generate" in capsys.readouterr().err


def test_an_output_folder_holding_an_input_is_refused(tmp_path, capsys):
    """The generator replaces and removes the files of --out (and --out/embedded) once it has
    generated there (manifest.c): a scenario or description kept in that folder was deleted."""
    gen = tmp_path / "gen"
    gen.mkdir()
    urdf = tmp_path / "arm2.urdf"
    urdf.write_text(ARM2_URDF, encoding="utf-8")
    assert cochlea_urdf.main(["import", str(urdf), "--out", str(gen / "robot.toml"),
                              "--scenario-out", str(gen / "starter.toml")]) == 0
    (gen / "manifest.c").write_text("/* generated */\n")
    capsys.readouterr()
    assert cochlea_codegen.main(["--scenario", str(gen / "starter.toml"), "--out", str(gen),
                                 "--no-build"]) == EXIT_USER_ERROR
    assert "holds the input --scenario" in capsys.readouterr().err
    elsewhere = tmp_path / "starter.toml"
    elsewhere.write_text((gen / "starter.toml").read_text().replace(
        'description = "robot.toml"', 'description = "gen/robot.toml"'))
    assert cochlea_codegen.main(["--scenario", str(elsewhere), "--out", str(gen),
                                 "--no-build"]) == EXIT_USER_ERROR
    assert "holds the input the scenario's description" in capsys.readouterr().err
    assert sorted(p.name for p in gen.iterdir()) == ["manifest.c", "robot.toml", "starter.toml"]


@pytest.mark.slow
def test_the_embedded_program_builds_for_the_users_scenario(user, tmp_path):
    """``--embedded``: the scenario's embedded controller and the robot's drive table in
    DIR/embedded/, and ``make GEN=DIR`` links them into the embedded program, which lists the
    user's scenario (docs/codegen.md; running it needs motors or cochlea-emulator)."""
    _, out = user
    assert sorted(p.name for p in (out / "embedded").iterdir()) == [
        "scenarios.c", "scenarios.h", "serial_drives.h", "starter.c", "starter.h",
        "starter_scenario.c"]
    drives = (out / "embedded" / "serial_drives.h").read_text()
    assert "#define SERIAL_N_DRIVES 2" in drives and "XM540-W270" in drives  # the user's arm
    program = tmp_path / "build" / "cochlea-embedded"
    subprocess.run(["make", "-s", f"GEN={out}", f"BUILD={tmp_path / 'build'}", str(program)],
                   cwd=ROOT, check=True, capture_output=True)
    listed = subprocess.run([str(program), "--list"], capture_output=True, text=True, check=True)
    assert listed.stdout.startswith("starter (serial robot, joint space, controller e)")


@pytest.mark.slow
def test_the_all_in_c_simulation_gives_the_simulations_log(user, tmp_path):
    """The all-in-C simulation (embedded/sim/simulate.c) of the user's scenario: its embedded
    controller and plant kernels in one program, the log simulate()'s to 1e-9 (relative to
    each value's peak, as tests/test_embedded_sim.py holds the shipped scenarios)."""
    from bench import embedded_bench as eb
    from cochlea.kernels import library as ckernels

    scenario, out = user
    sc = load_scenario(scenario)
    setups = unit_setups(sc)
    binary = eb.build_simulation(scenario, "double", ckernels.load(out), out)
    assert binary == out / "embedded-sim" / "starter" / "double" / "simulate"
    log = tmp_path / "log.bin"
    info = eb.run_simulation(binary, 1.0, log)
    result = eb.read_log(log, info, sc, setups)
    reference = simulate(sc, 1.0, setups, kernels="c", library=out)
    for u, r in zip(result.units, reference.units, strict=True):
        for key in eb.LOG_FIELDS:
            a, b = getattr(u, key), getattr(r, key)
            assert np.max(np.abs(a - b)) <= 1e-9 * max(1.0, np.max(np.abs(b))), key


@pytest.mark.slow
def test_a_sweep_runs_on_the_users_kernels_or_refuses_before_any_worker(user, tmp_path,
                                                                          capsys, monkeypatch):
    from cochlea.apps import cochlea_sweep
    from cochlea.sweep import sampling
    from cochlea.sweep import spec as sweep_spec

    scenario, kernels = user
    spec = tmp_path / "sweep.toml"
    spec.write_text(f'format = "cochlea-sweep/1"\nscenario = "{scenario}"\nsamples = 2\n'
                    "seed = 1\nduration_s = 0.5\n[perturb]\nmass_scale = {uniform = [0.9, 1.1]}\n")
    out = tmp_path / "sweep"
    assert cochlea_sweep.main([str(spec), "--out", str(out), "--kernels", "c", "--library",
                               str(tmp_path / "missing")]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert err.startswith("cochlea-sweep: --kernels c: ") and err.count("\n") == 1
    assert not out.exists()  # decided before any worker started or any file was written
    # What a worker runs for a sample, on the user's library (the environment as it was after).
    monkeypatch.setenv(ENVIRONMENT, os.environ.get(ENVIRONMENT, ""))
    text = sampling.scenario_text(sweep_spec.load(spec), 1)
    row = cochlea_sweep.evaluate(text, kernels="c", library=str(kernels / "libcochlea.so"))
    assert not row["diverged"] and row["stop_rule"] == "none", row  # 0.5 s: not converged yet
    rms = [v for k, v in row.items() if ".final_rms." in k]
    assert rms and all(np.isfinite(v) for v in rms)


def test_a_users_kernels_build_beside_them_not_over_the_shipped_program(tmp_path):
    """``make embedded GEN=DIR`` without ``BUILD=`` builds into DIR/build: it used to write
    build/cochlea-embedded, replacing the shipped scenarios' program with the user's."""
    gen = tmp_path / "kernels"
    planned = subprocess.run(["make", "-n", "embedded", f"GEN={gen}"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
    outputs = [word for word in planned.split() if word.endswith("cochlea-embedded")]
    assert outputs == [str(gen / "build" / "cochlea-embedded")]
    shipped = subprocess.run(["make", "-n", "-B", "embedded"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
    assert "-o build/cochlea-embedded " in shipped
