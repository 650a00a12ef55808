"""Everything after the model on a user robot (issue 25 item 5): the tools on a description
the package does not ship, tests/data/planar2.toml (a planar 2R arm on XM540-W270s, one arm,
its base at the world origin, asymmetric joint limits) and its scenario planar2_joint.toml."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps import cochlea_excite, cochlea_identify
from cochlea.errors import CochleaError, DescriptionError
from cochlea.ident import excite
from cochlea.robots import robot
from cochlea.sim import load_scenario

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parent / "data"
DESCRIPTION = DATA / "planar2.toml"
SCENARIO = DATA / "planar2_joint.toml"
RUN = [sys.executable, "-m", "cochlea.apps.cochlea_run"]
FAST = excite.ExcitationOptions(period=4.0, harmonics=3, starts=2, iterations=60, periods=4)

#: The perturbed plant of the identification: masses +20 % / -15 %, a 50 g payload, armature,
#: viscous friction away from the description's 0.05 N m s/rad, the drives' current
#: quantisation, encoder and velocity grids and one period of delay (as tests/test_identify.py
#: does for the shipped arms; no Coulomb friction, see there).
PLANT = """[plant]
plant = "ideal"
armature = true
mass_scale = [1.2, 0.85]
payload_kg = 0.05
viscous_friction_SI = [0.07, 0.035]
current_quantisation = true
position_encoder = true
velocity_register = true
delay_periods = 1
"""


def _with_keys(tmp: Path, extra_arm: str = "", extra_top: str = "") -> Path:
    """A copy of the user description with optional keys added (beside it in ``tmp``)."""
    text = DESCRIPTION.read_text()
    text = text.replace('base_yaw_deg = 0.0\n', 'base_yaw_deg = 0.0\n' + extra_arm, 1)
    path = tmp / "planar2.toml"
    path.write_text(text + extra_top)
    return path


@pytest.mark.slow
def test_excitation_defaults_to_the_middle_of_the_limits():
    result = excite.design("serial", None, FAST, description=DESCRIPTION)
    system = robot("serial").load(DESCRIPTION)
    limits = np.array([link.joint.position_limits for link in system.arms[0].links])
    assert np.allclose(result.working_pose, limits.mean(axis=1))  # [30, 10] deg
    assert result.unit == "arm" and result.held == {}
    times = np.arange(int(FAST.period * 1000) + 1) / 1000.0
    q, qd, _ = result.series.evaluate(times)
    vmax = np.array([link.joint.velocity_limit for link in system.arms[0].links])
    assert (np.abs(qd).max(axis=1) <= vmax).all()
    assert (np.abs(q - result.working_pose[:, None]).max(axis=1)
            <= FAST.amplitude_rad * (1 + 1e-3)).all()
    # No keep-out key and the base inside the keep-out circle: no circle, no other arm.
    assert result.keep_out_distance is None and result.clearance_distance is None
    assert result.condition < 1e3


@pytest.mark.slow
def test_working_pose_and_keep_out_volumes_come_from_the_description(tmp_path):
    # A sphere of 4 cm at 0.32 m along 50 deg: the tool passes near it around the working
    # pose (40, 0) deg (tool at 0.35 m along 40 deg) and must keep out.
    c = [0.32 * math.cos(math.radians(52)), 0.32 * math.sin(math.radians(52)), 0.0]
    path = _with_keys(tmp_path, "working_pose_deg = [40.0, 0.0]\n",
                      f'\n[[keep_out]]\nname = "post"\ncentre_m = {c}\nradius_m = 0.04\n')
    system = robot("serial").load(path)
    assert np.allclose(np.degrees(system.arms[0].working_pose), [40.0, 0.0])
    assert system.keep_out_volumes[0].name == "post"
    result = excite.design("serial", None, FAST, description=path)
    assert np.allclose(np.degrees(result.working_pose), [40.0, 0.0])
    assert 0.0 <= result.keep_out_volume_distance < 0.05  # it works close to the post
    # A working pose inside the volume is refused in one clear line.
    (tmp_path / "inside").mkdir()
    inside = _with_keys(tmp_path / "inside", "working_pose_deg = [52.0, 0.0]\n",
                        f'\n[[keep_out]]\nname = "post"\ncentre_m = {c}\nradius_m = 0.04\n')
    with pytest.raises(CochleaError, match="keep-out volume post"):
        excite.design("serial", None, FAST, description=inside)


@pytest.mark.slow
def test_without_armature_the_excitation_runs_on_the_ideal_plant(tmp_path):
    """A description with no armature (an imported URDF's) cannot have the geared plant:
    the written scenario asks for the rigid links, and loads."""
    path = _with_keys(tmp_path)
    path.write_text(path.read_text().replace("  armature_kgm2 = 0.02\n", ""))
    out = tmp_path / "excite.toml"
    assert cochlea_excite.main(["--robot", "serial", "--description", str(path), "--out",
                                str(out), "--period", "4", "--harmonics", "3", "--starts", "1",
                                "--iterations", "30", "--periods", "1"]) == 0
    assert 'plant = "ideal"' in out.read_text()
    assert load_scenario(out).system.path.resolve() == path.resolve()
    text = excite.scenario_text(excite.design("serial", None, FAST, description=DESCRIPTION),
                                "test")
    assert 'plant = "realistic"' in text  # the 2R arm has its armature


def test_tracking_scenario_mistakes_are_refused(tmp_path):
    # A scenario of another description.
    with pytest.raises(CochleaError, match="must run the excited description"):
        excite.design("serial", None, FAST, description=DESCRIPTION, tracking="serial_joint")
    # Two arms and no --scenario: the starter moves one arm only.
    text = DESCRIPTION.read_text()
    second = text[text.index("[[arm]]"):].replace('name = "arm"', 'name = "other"', 1)
    second = second.replace("id = 1", "id = 3").replace("id = 2", "id = 4")
    second = second.replace("base_xyz_m = [0.0, 0.0, 0.0]", "base_xyz_m = [0.6, 0.0, 0.0]")
    two = tmp_path / "two.toml"
    two.write_text(text + "\n" + second)
    with pytest.raises(CochleaError, match="give --scenario"):
        excite.design("serial", None, FAST, description=two)


@pytest.mark.parametrize("extra_arm, extra_top, key", [
    ("working_pose_deg = [160.0, 0.0]\n", "", "arm[0].working_pose_deg[0]"),
    ("working_pose_deg = [10.0]\n", "", "arm[0].working_pose_deg"),
    ("", "\n[[keep_out]]\ncentre_m = [0.1, 0.0]\nradius_m = 0.02\n", "keep_out[0].centre_m"),
    ("", "\n[[keep_out]]\ncentre_m = [0.1, 0.0, 0.0]\nradius_m = -1\n", "keep_out[0].radius_m"),
])
def test_bad_optional_keys_are_refused(tmp_path, extra_arm, extra_top, key):
    with pytest.raises(DescriptionError, match=key.replace("[", r"\[").replace("]", r"\]")):
        robot("serial").load(_with_keys(tmp_path, extra_arm, extra_top))


@pytest.mark.slow
def test_excite_then_identify_a_perturbed_plant(tmp_path, capsys):
    """cochlea-excite --description, the scenario run on a perturbed simulated plant of the
    user robot, cochlea-identify predicting the held-out torques within 5 %."""
    out = tmp_path / "excite.toml"
    assert cochlea_excite.main(["--robot", "serial", "--description", str(DESCRIPTION),
                                "--out", str(out), "--period", "4", "--harmonics", "3",
                                "--starts", "2", "--iterations", "60"]) == 0
    printed = capsys.readouterr().out
    assert "-> " in printed and "cochlea-run" in printed
    sc = load_scenario(out)  # its description resolves against the scenario's folder
    assert sc.system.path.resolve() == DESCRIPTION.resolve()
    text = out.read_text()
    perturbed = tmp_path / "perturbed.toml"
    perturbed.write_text(text[:text.index("[plant]")] + PLANT)
    subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario", str(perturbed),
                          "--out", str(tmp_path / "run"), "--realtime", "off"],
                   check=True, capture_output=True, cwd=ROOT)
    report = tmp_path / "ident.json"
    assert cochlea_identify.main([str(tmp_path / "run"), "--robot", "serial", "--description",
                                  str(DESCRIPTION), "--out", str(report), "--min-speed", "0",
                                  "--no-figures"]) == 0
    doc = json.loads(report.read_text())
    assert max(doc["prediction_nrms_percent"]["wls"]) < 5.0
    # The viscous frictions (0.07, 0.035, the description says 0.05) are recovered.
    m = robot("serial").model(robot("serial").load(DESCRIPTION), "arm", "base", actuators="all")
    fv = [p["wls"] for name, p in zip(m.parameters.meanings, doc["parameters"])
          if name.endswith(".Fv")]
    assert fv == pytest.approx([0.07, 0.035], rel=0.02)
    # The physically consistent fit written back into a copy of the user's description.
    copy = tmp_path / "planar2.toml"
    copy.write_text(DESCRIPTION.read_text())
    assert cochlea_identify.main([str(tmp_path / "run"), "--robot", "serial", "--description",
                                  str(copy), "--out", str(tmp_path / "ident2.json"),
                                  "--min-speed", "0", "--no-figures", "--physical",
                                  "--update-description", str(copy)]) == 0
    written = robot("serial").load(tmp_path / "planar2.identified.toml").arms[0].links
    assert [link.joint.actuator.viscous for link in written] == \
        pytest.approx([0.07, 0.035], rel=0.02)


# --------------------------------------------------------------------------------------------
# The virtual chain, a sweep and a tune: no change was needed for these (issue 25 item 5)
# --------------------------------------------------------------------------------------------


@pytest.mark.hil
def test_joint_space_run_over_the_virtual_chain(tmp_path):
    """cochlea-emulator takes the user robot's motors from the scenario's description;
    cochlea-run --backend dynamixel tracks the scenario over the pseudo-terminal."""
    log, out = tmp_path / "emulator.log", tmp_path / "hil"
    proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                             "serial", "--scenario", str(SCENARIO), "--log", str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        assert "XM540-W270" in proc.stdout.readline()
        done = subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario",
                                     str(SCENARIO), "--backend", "dynamixel", "--port", port,
                                     "--duration", "3", "--out", str(out),
                                     "--watchdog-misses", "300"],
                              capture_output=True, text=True, timeout=180, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed"
    assert "torque off confirmed by all 2" in summary["timing"]["bus"]["shutdown"]
    for name, tracked in summary["units"]["arm"]["tracked"].items():
        # From 2 deg off to within the simulation's tracking plus a few encoder counts.
        assert tracked["final_rms_error"] < 0.1 * tracked["initial_abs_error"], (name, tracked)


def _spec(folder: Path, extra: str) -> Path:
    for f in (DESCRIPTION, SCENARIO):
        (folder / f.name).write_text(f.read_text())
    path = folder / "spec.toml"
    path.write_text(f'''format = "cochlea-sweep/1"
scenario = "{SCENARIO.name}"
samples = 2
seed = 7
duration_s = 0.4

[perturb]
mass_scale = {{uniform = [0.8, 1.2]}}
payload_kg = {{uniform = [0.0, 0.05]}}
{extra}''')
    return path


@pytest.mark.slow
def test_a_small_sweep_of_the_user_scenario(tmp_path, monkeypatch):
    from cochlea.apps import cochlea_sweep
    from cochlea.sweep import results

    spec = _spec(tmp_path, "\n[gains.arm]\nG_e = {grid = [[0.5, 0.3], [1.0, 0.6]]}\n")
    monkeypatch.chdir(ROOT)  # the spec's scenario resolves against the spec, not here
    out = tmp_path / "out"
    assert cochlea_sweep.main([str(spec), "--out", str(out), "--workers", "1",
                               "--progress", "off"]) == 0
    rows = results.read(out).to_pylist()
    assert len(rows) == 4  # 2 draws x 2 grid points
    # Every run to its end (no supervisor stop), none diverging.
    assert all(r["stop_rule"] == "none" and not r["diverged"] for r in rows), rows


@pytest.mark.slow
def test_a_small_tune_of_the_user_scenario(tmp_path, monkeypatch):
    from cochlea.apps import cochlea_tune

    spec = _spec(tmp_path, "\n[gains.arm]\nG_e = {uniform = [0.2, 2.0], each = true}\n\n"
                           "[tune]\ntrials = 3\nparallel_candidates = 1\nstartup_trials = 2\n")
    monkeypatch.chdir(ROOT)
    out = tmp_path / "out"
    assert cochlea_tune.main([str(spec), "--out", str(out), "--workers", "1",
                              "--progress", "off"]) == 0
    tuned = load_scenario(out / "tuned.toml")  # runs the user's description
    assert tuned.system.path.resolve() == (tmp_path / DESCRIPTION.name).resolve()
    with open(out / "trials.csv") as f:
        trials = f.read().splitlines()[1:]
    assert len(trials) == 3 and all(",True," in t for t in trials)  # each feasible


# --------------------------------------------------------------------------------------------
# cochlea-dxl calibrate: reference pose and positive sense from the description
# --------------------------------------------------------------------------------------------


def test_calibration_defaults_for_a_user_robot(tmp_path):
    adapter = robot("serial")
    system = adapter.load(DESCRIPTION)
    assert not adapter.is_shipped(system) and adapter.is_shipped(adapter.load(None))
    refs = adapter.calibration_references(system, shipped=False)
    assert {n: q for n, (q, _) in refs.items()} == {"arm.upper": 0.0, "arm.fore": 0.0}
    assert "right-hand rule" in adapter.calibration_positive(system, "arm.upper", False)
    # A joint whose limits exclude zero: the middle of its limits.
    moved = _with_keys(tmp_path)
    moved.write_text(moved.read_text().replace("[-90.0, 150.0]", "[20.0, 150.0]"))
    refs = adapter.calibration_references(adapter.load(moved), shipped=False)
    assert refs["arm.upper"][0] == pytest.approx(math.radians(85.0))
    # The shipped arms keep their documented pose and sense.
    shipped = adapter.load(None)
    assert adapter.calibration_references(shipped)["arm1.link1"] == \
        adapter.calibration_reference["*"]
    assert adapter.calibration_positive(shipped, "arm1.link1") == adapter.positive_direction


@pytest.mark.hil
def test_calibrate_a_user_robot_over_the_emulator(tmp_path, monkeypatch):
    """cochlea-dxl calibrate on the emulated chain of the user robot (its scenario names the
    description): the description's calibration_pose_deg and positive_direction are the
    prompts', and the injected offsets and directions are recovered."""
    import gc

    from cochlea.dynamixel.bringup import calibrate
    from cochlea.dynamixel.control_table import RAD_PER_COUNT
    from cochlea.dynamixel.drives import joint_drives
    from cochlea.dynamixel.emulator import Truth, VirtualChain

    description = _with_keys(tmp_path, 'calibration_pose_deg = [90.0, -45.0]\n'
                                       'positive_direction = "counter-clockwise seen from '
                                       'above the table"\n')
    scenario = tmp_path / SCENARIO.name
    scenario.write_text(SCENARIO.read_text())
    true_offset, true_direction = {1: 57.0, 2: -130.5}, {2: -1}
    refs = {"arm.upper": math.radians(90.0), "arm.fore": math.radians(-45.0)}
    gc.collect()
    gc.disable()  # the emulator is a thread of this process
    chain = VirtualChain("serial", scenario, truth=Truth(true_offset, true_direction)).start()
    prompts = []

    def ask(prompt):
        prompts.append(prompt)
        name = prompt.split(" ")[0].rstrip(":")
        chain.move_joint(name, refs[name] + (0.0 if "reference pose" in prompt else 0.2))
        return ""

    monkeypatch.setattr(calibrate, "ask", ask)
    parser = __import__("argparse").ArgumentParser()
    calibrate.add_arguments(parser)
    out = tmp_path / "calibrated.toml"
    try:
        code = calibrate.run(parser.parse_args(["--robot", "serial", "--port", chain.path,
                                                "--description", str(description),
                                                "--out", str(out)]))
    finally:
        chain.close()
        gc.enable()
    assert code == 0 and len(prompts) == 4
    assert "calibration_pose_deg" in prompts[0] and "(arm.upper = 90 deg)" in prompts[0]
    assert "above the table" in prompts[1]
    for d in joint_drives("serial", out):
        assert d.direction == true_direction.get(d.id, 1), d.name
        error = (math.degrees(d.zero_offset) - true_offset[d.id] + 180.0) % 360.0 - 180.0
        assert abs(error) <= math.degrees(RAD_PER_COUNT), (d.name, error)
    # The calibrated copy keeps the optional keys and still loads as the user robot.
    assert robot("serial").load(out).arms[0].calibration_pose is not None
