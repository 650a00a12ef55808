"""cochlea-identify: base parameters from a simulated excitation run of a plant perturbed away
from the description, bad logs refused in one line, and the write-back into a description."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cochlea
from cochlea.apps.cochlea_identify import main
from cochlea.ident import writeback
from cochlea.resources import SCENARIOS_DIR
from cochlea.sim import load_scenario, unit_setups

ROOT = Path(__file__).resolve().parent.parent
RUN = [sys.executable, "-m", "cochlea.apps.cochlea_run"]


def fourier_leader(centre_deg, amplitude_deg, period_s, harmonics, seed):
    """A finite Fourier series per joint that starts at its centre, as scenario formulas."""
    rng = np.random.default_rng(seed)
    w = 2 * math.pi / period_s
    out = []
    for c, amp in zip(centre_deg, amplitude_deg):
        phase = rng.uniform(0, 2 * math.pi, harmonics)
        weight = rng.uniform(0.5, 1.0, harmonics) / np.arange(1, harmonics + 1)
        weight *= amp / weight.sum()
        terms = [f"{c:g}"] + [f"{a:.6g}*(sin({k + 1}*{w:.6g}*t + {p:.6g}) - {math.sin(p):.6g})"
                              for k, (a, p) in enumerate(zip(weight, phase))]
        out.append(" + ".join(terms) + " deg")
    return out


#: The perturbed plant: masses +-20 %, a 20 g payload, armature, viscous friction away from
#: the description's 0.01 N m s/rad. The ideal plant: no stick-slip (see the module's notes).
SERIAL_PLANT = """
[plant]
plant = "ideal"
armature = true
mass_scale = [1.2, 0.8, 1.15]
payload_kg = 0.02
viscous_friction_SI = [0.015, 0.008, 0.012]
"""


def serial_scenario(tmp: Path, duration: float = 20.0) -> Path:
    text = (SCENARIOS_DIR / "serial_joint_realistic.toml").read_text()
    start = text.index("leader = [")
    end = text.index("]", text.index('deg",\n]')) + 1
    lead = fourier_leader([81.14, 71.02, 117.8], [25, 25, 25], 2.0, 3, seed=1)
    text = text[:start] + "leader = [\n" + "".join(f'  "{x}",\n' for x in lead) + "]" + \
        text[end:]
    text = text.replace('initial_joint = ["73 deg", "83 deg", "110 deg"]',
                        'initial_joint = ["81.14 deg", "71.02 deg", "117.8 deg"]')
    text = text.replace("duration_s = 20.0", f"duration_s = {duration}")
    text = text[:text.index("[plant]")] + SERIAL_PLANT
    path = tmp / "serial_excite.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serial")
    scenario = serial_scenario(tmp)
    subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario", str(scenario),
                          "--out", str(tmp / "run"), "--realtime", "off"],
                   check=True, capture_output=True, cwd=ROOT)
    return tmp, scenario


def true_base(model, scenario: Path, unit: str) -> np.ndarray:
    """The perturbed plant's base parameters: its full inertial parameters, armature
    included, then each joint's viscous and Coulomb friction, through from_full."""
    u = next(s for s in unit_setups(load_scenario(scenario)) if s.name == unit)
    coulomb = u.coulomb if u.coulomb is not None else np.zeros_like(u.friction)
    full = np.concatenate([u.plant_params, np.column_stack([u.friction, coulomb]).ravel()])
    return model.parameters.from_full @ full


def test_serial_excitation_recovers_the_perturbed_plant(serial_run, capsys):
    tmp, scenario = serial_run
    out = tmp / "ident.json"
    assert main([str(tmp / "run"), "--robot", "serial", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    m = cochlea.model("serial", parameterisation="base", actuators="all")
    truth = true_base(m, scenario, "arm1")
    wls = np.array([p["wls"] for p in doc["parameters"]])
    rel = np.array([p["wls_relative_std_error_percent"] or np.inf for p in doc["parameters"]])
    # Well excited: relative standard error below 1 %. Those must be within 2 % of the truth.
    good = rel < 1.0
    assert good.sum() >= 8  # armatures, viscous friction, the leading inertias
    err = np.abs(wls[good] - truth[good]) / np.abs(truth[good])
    assert err.max() < 0.02, dict(zip(np.array(m.parameters.names)[good], err))
    # The perturbation is visible: the description's nominal values are further away.
    assert (np.abs(m.parameters.nominal - truth) > 0.05 * np.abs(truth)).any()
    assert max(doc["prediction_nrms_percent"]["wls"]) < 5.0
    assert (tmp / "ident_torques.png").stat().st_size > 0
    assert (tmp / "ident_parameters.png").stat().st_size > 0
    assert "held-out effort NRMS" in capsys.readouterr().out


def _bad(args, capsys, out: Path):
    assert main(args + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("cochlea-identify: ")
    assert not out.exists() and not list(out.parent.glob("ident*.png"))
    return err


def _copy_log(src: Path, dst: Path, edit) -> Path:
    dst.mkdir()
    lines = (src / "log.csv").read_text().splitlines(keepends=True)
    (dst / "log.csv").write_text("".join(edit(lines)))
    return dst


def test_bad_logs_are_refused_in_one_line(serial_run, tmp_path, capsys):
    tmp, _ = serial_run
    run = tmp / "run"
    out = tmp_path / "ident.json"
    serial = ["--robot", "serial"]

    err = _bad([str(tmp_path / "nowhere")] + serial, capsys, out)
    assert "no such run folder" in err

    def drop_tau(lines):
        header = lines[0].rstrip("\n").split(",")
        k = header.index("arm1.tau.joint2_Nm")
        return [",".join(c for i, c in enumerate(x.rstrip("\n").split(",")) if i != k) + "\n"
                for x in lines]
    err = _bad([str(_copy_log(run, tmp_path / "cols", drop_tau))] + serial, capsys, out)
    assert "arm1.tau.joint2_Nm" in err

    err = _bad([str(_copy_log(run, tmp_path / "short", lambda x: x[:400]))] + serial, capsys,
               out)
    assert "too short" in err

    def nan_row(lines):
        cells = lines[1234].split(",")
        cells[1] = "nan"
        return lines[:1234] + [",".join(cells)] + lines[1235:]
    err = _bad([str(_copy_log(run, tmp_path / "nan", nan_row))] + serial, capsys, out)
    assert "row 1234 of the data (line 1235)" in err and "arm1.q.joint1_rad" in err

    def frozen(lines):  # the robot held still: every row the first row's state
        header = lines[0].rstrip("\n").split(",")
        first = lines[1].rstrip("\n").split(",")
        keep = [i for i, c in enumerate(header) if ".q." in c or ".qd." in c]
        rows = []
        for x in lines[1:]:
            cells = x.rstrip("\n").split(",")
            for i in keep:
                cells[i] = first[i]
            rows.append(",".join(cells) + "\n")
        return lines[:1] + rows
    err = _bad([str(_copy_log(run, tmp_path / "still", frozen))] + serial, capsys, out)
    assert "not excited" in err and "cochlea-excite" in err

    err = _bad([str(run), "--robot", "parallel"], capsys, out)
    assert "log of the serial robot" in err

    err = _bad([str(run)] + serial + ["--arm", "arm7"], capsys, out)
    assert "arm7" in err


def test_write_back_reproduces_the_base_parameters(tmp_path, capsys):
    original = (ROOT / "cochlea/data/robots/serial.toml").read_text()
    description = tmp_path / "serial.toml"
    description.write_text(original)
    m = cochlea.model("serial", parameterisation="base", actuators="all")
    names = m.parameters.names
    beta = m.parameters.nominal.copy()
    # An identification's kind of change: armature, friction and the link-2 grouping moved.
    for name, factor in (("b1", 1.1), ("b4", 1.3), ("b8", 0.9), ("b10", 1.5), ("b13", 0.8)):
        beta[names.index(name)] *= factor
    phi = writeback.closest_full(m, beta)
    assert np.allclose(m.parameters.from_full @ phi, beta, rtol=1e-12, atol=1e-15)
    written = writeback.write_back(m, "serial", "arm1", description, phi,
                                   [("runs/x", "0" * 64)])
    assert written == tmp_path / "serial.identified.toml"
    assert description.read_text() == original  # untouched
    text = written.read_text()
    assert text.startswith("# Dynamic parameters (arm1) identified by cochlea-identify")
    assert "runs/x" in text and "# estimate, see the header" in text  # comments kept
    new = cochlea.model("serial", parameterisation="base", actuators="all",
                        description=written)
    assert np.allclose(new.parameters.nominal, beta, rtol=1e-9, atol=1e-15)
    q, qd, qdd = np.array([0.3, -0.7, 1.1]), np.array([0.5, -0.2, 0.9]), np.array([2., 1, -3])
    assert np.allclose(np.array(new.inverse_dynamics(q, qd, qdd)),
                       np.array(m.inverse_dynamics_p(q, qd, qdd, beta)), rtol=1e-9)
    arm2 = cochlea.model("serial", arm="arm2", parameterisation="base", actuators="all")
    assert np.array_equal(cochlea.model("serial", arm="arm2", parameterisation="base",
                                        actuators="all", description=written
                                        ).parameters.nominal, arm2.parameters.nominal)
    # A second write-back finds its target taken.
    with pytest.raises(writeback.WriteBackError, match="already exists"):
        writeback.write_back(m, "serial", "arm1", description, phi, [])
    assert description.read_text() == original


def test_write_back_refuses_an_existing_target_before_fitting(tmp_path, capsys):
    description = tmp_path / "serial.toml"
    description.write_text((ROOT / "cochlea/data/robots/serial.toml").read_text())
    (tmp_path / "serial.identified.toml").write_text("taken")
    err = _bad([str(tmp_path / "nowhere"), "--robot", "serial", "--update-description",
                str(description)], capsys, tmp_path / "ident.json")
    assert "already exists" in err
    assert (tmp_path / "serial.identified.toml").read_text() == "taken"


def test_key_lines_follow_arrays_of_tables():
    lines = ["[[arm]]\n", "name = 'a'\n", "  [[arm.link]]\n", "  mass_kg = 1.0  # c\n",
             "  [arm.link.joint]\n", "  armature_kgm2 = 2.0\n", "  [[arm.link]]\n",
             "  mass_kg = 3.0\n", "[[arm]]\n", "  [[arm.link]]\n", "  mass_kg = 4.0\n"]
    where = writeback.key_lines(lines)
    assert where[("arm", 0, "link", 0, "mass_kg")] == 3
    assert where[("arm", 0, "link", 0, "joint", "armature_kgm2")] == 5
    assert where[("arm", 0, "link", 1, "mass_kg")] == 7
    assert where[("arm", 1, "link", 0, "mass_kg")] == 10
    edited = writeback.edit("".join(lines), {("arm", 0, "link", 0, "mass_kg"): "9.5"},
                            Path("x.toml"))
    assert "  mass_kg = 9.5  # c\n" in edited
