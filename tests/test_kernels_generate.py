"""cochlea-codegen: the configuration, determinism, and generated_c/ kept fresh (the CI check)."""

from __future__ import annotations

import dataclasses
import filecmp
import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from cochlea.kernels import generate as codegen
from cochlea.kernels.catalogue import CONTROLLER_PARTS
from cochlea.kernels.generate import CodegenError, load_config
from cochlea.resources import CODEGEN_DIR

ROOT = Path(__file__).resolve().parent.parent
GENERATED = ROOT / "generated_c"


@pytest.fixture(scope="module")
def config():
    return load_config()


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory, config):
    out = tmp_path_factory.mktemp("generated_c")
    codegen.generate(config, out)
    return out


@pytest.mark.slow
def test_generated_c_is_fresh(regenerated):
    """The CI check: regenerating from models/ and codegen/ gives generated_c/ byte for byte.
    If this fails, run `cochlea-codegen` (or `make codegen`) and commit generated_c/."""
    fresh = sorted(p.name for p in regenerated.iterdir() if p.is_file())
    # generated_c/embedded/ has its own test (test_embedded_generated.py)
    committed = sorted(p.name for p in GENERATED.iterdir() if p.is_file())
    assert fresh == committed, "files added or removed: run cochlea-codegen"
    stale = [name for name in fresh
             if not filecmp.cmp(regenerated / name, GENERATED / name, shallow=False)]
    assert not stale, f"generated_c/ is stale ({', '.join(stale)}): run cochlea-codegen"


@pytest.mark.slow
def test_generation_is_deterministic(regenerated, config, tmp_path):
    codegen.generate(config, tmp_path)
    for path in (p for p in regenerated.iterdir() if p.is_file()):
        assert path.read_bytes() == (tmp_path / path.name).read_bytes(), path.name


@pytest.mark.slow
def test_check_mode_reports_a_stale_folder(config, tmp_path):
    stale = tmp_path / "generated_c"
    shutil.copytree(GENERATED, stale)
    (stale / "serial_arm1.c").write_text((stale / "serial_arm1.c").read_text() + "\n")
    (stale / "extra.c").write_text("int x;\n")
    assert codegen.check(dataclasses.replace(config, output=stale)) == ["extra.c",
                                                                        "serial_arm1.c"]


def test_console_script_is_declared():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["cochlea-codegen"] == "cochlea.apps.cochlea_codegen:main"


@pytest.mark.slow
def test_check_command_exit_codes(tmp_path):
    script = [sys.executable, "-m", "cochlea.apps.cochlea_codegen"]
    ok = subprocess.run(script + ["--check"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "up to date" in ok.stdout
    text = (CODEGEN_DIR / "kernels.toml").read_text()
    moved = tmp_path / "kernels.toml"
    moved.write_text(text.replace('output = "generated_c"', f'output = "{tmp_path / "out"}"'))
    (tmp_path / "out").mkdir()
    stale = subprocess.run(script + ["--check", "--config", str(moved)], capture_output=True,
                           text=True)
    assert stale.returncode == 1
    assert "stale" in stale.stderr and "cochlea-codegen" in stale.stderr


def test_every_configured_kernel_is_generated(config):
    manifest = _manifest_json()
    names = set(manifest["kernels"])
    for robot in config.robots:
        prefixes = [f"{robot.name}_{u}" for u in robot.units] or [robot.name]
        for prefix in prefixes:
            for key in robot.kernels:
                assert f"{prefix}_{key}" in names
            assert f"{prefix}_plant_step" in names
            assert (f"{prefix}_plant_step_coulomb" in names) == robot.plant_coulomb
            for kind in robot.controllers:
                for variant in robot.variants:
                    group = f"{prefix}_{kind}" + ("" if variant == "corrected" else f"_{variant}")
                    for part in CONTROLLER_PARTS:
                        assert f"{group}_{part}" in names
                    assert f"{group}_closed_loop" in manifest["closed_loops"]
                    coulomb = manifest["closed_loops"].get(f"{group}_closed_loop_coulomb")
                    assert (coulomb is not None) == robot.plant_coulomb
                    if coulomb is not None:
                        assert coulomb["plant"] == f"{prefix}_plant_step_coulomb"
    # The list: M, C, G, fk, J, forward dynamics, RK4 plant step per robot.
    for unit in ("serial_arm1", "serial_arm2", "parallel"):
        for key in ("M", "C", "G", "fk", "J", "forward_dynamics", "plant_step"):
            assert f"{unit}_{key}" in names


def test_kernels_need_no_work_memory():
    for name, entry in _manifest_json()["kernels"].items():
        assert entry["work"]["iw"] == 0 and entry["work"]["w"] == 0, name
        assert entry["work"]["arg"] == len(entry["inputs"]), name
        assert entry["work"]["res"] == len(entry["outputs"]), name


def test_readme_documents_every_function():
    readme = (GENERATED / "README.md").read_text()
    manifest = _manifest_json()
    for name, entry in manifest["kernels"].items():
        section = readme.split(f"### `{name}`\n", 1)
        assert len(section) == 2, f"README has no section for {name}"
        body = section[1].split("### ", 1)[0]
        if entry["symbol"] != name:  # an alias: documented where its symbol is
            assert body.startswith(f"\nSame as `{entry['symbol']}` (an alias"), name
            body = readme.split(f"### `{entry['symbol']}`\n", 1)[1].split("### ", 1)[0]
        assert "Work memory" in body
        for i, arg in enumerate(entry["inputs"]):
            row = f"| in {i} | `{arg['name']}` | {arg['rows']}x{arg['cols']} | "
            assert row in body, (name, row)
        for i, arg in enumerate(entry["outputs"]):
            row = f"| out {i} | `{arg['name']}` | {arg['rows']}x{arg['cols']} | "
            assert row in body, (name, row)
            assert not body.split(row, 1)[1].startswith(" |"), f"{name}.{arg['name']}: no unit"
    for loop, entry in manifest["closed_loops"].items():
        runs = "" if entry["symbol"] == loop else f" (same as `{entry['symbol']}`)"
        assert f"| `{loop}`{runs} |" in readme
    assert "make lib" in readme and "without Python" in readme


def test_generated_code_has_no_timestamps_or_paths():
    for path in sorted(GENERATED.rglob("*")):
        if not path.is_file():
            continue
        text = path.read_text()
        assert str(ROOT) not in text, path.name
        assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text), path.name


def test_configuration_errors_name_the_key(tmp_path):
    good = (CODEGEN_DIR / "kernels.toml").read_text()
    cases = [
        (good.replace('format = "cochlea-codegen/1"', 'format = "x"'), "format"),
        (good.replace('controllers = ["e", "g"]', 'controllers = ["d"]'),
         "robot[0].controllers"),
        (good.replace('variants = ["corrected", "thesis"]', 'variants = ["best"]', 1),
         "robot[0].variants"),
        (good.replace("plant_substeps = 1", "plant_substeps = 0", 1), "robot[0].plant_substeps"),
        ("speed = 3\n" + good, "speed"),
        (good.replace('task = ["fk_world", "J_world"]', 'task = ["fk"]'), "robot[0].task"),
        (good.replace('plant_actuators = ["none", "armature"]', 'plant_actuators = ["rotor"]',
                      1), "robot[0].plant_actuators"),
        (good.replace('controller_actuators = ["none", "all"]',
                      'controller_actuators = ["all", "all"]', 1),
         "robot[0].controller_actuators"),
        (good.replace('plant_actuators = ["none", "armature"]', 'plant_actuators = []', 1),
         "robot[0].plant_actuators"),
    ]
    for text, key in cases:
        path = tmp_path / "k.toml"
        path.write_text(text)
        with pytest.raises(CodegenError, match=re.escape(f"{path}: {key}:")):
            load_config(path)
    bad_kernel = tmp_path / "kernel.toml"
    bad_kernel.write_text(good.replace('"M", "C"', '"Mass", "C"', 1))
    with pytest.raises(CodegenError, match="has no Function 'Mass'"):
        codegen.collect(load_config(bad_kernel))
    # A configuration that fails to build leaves the folder as it was.
    out = tmp_path / "generated"
    out.mkdir()
    (out / "serial_arm1.c").write_text("/* committed */\n")
    with pytest.raises(CodegenError, match="has no Function 'Mass'"):
        codegen.generate(load_config(bad_kernel), out)
    assert (out / "serial_arm1.c").read_text() == "/* committed */\n"


def _top(text: str, line: str) -> str:
    """``text`` with its [[robot]] tables left out and ``line`` a top-level key."""
    return text.replace('format = "cochlea-codegen/1"',
                        f'format = "cochlea-codegen/1"\n{line}').split("[[robot]]", 1)[0]


@pytest.mark.parametrize("edit, key, expected", [
    (lambda t: t.replace("[[robot]]", "[robot]", 1).split("[[robot]]")[0], "robot",
     "an array of tables; [robot] is one table"),
    (lambda t: _top(t, "robot = 5"), "robot", "[[robot]] tables"),
    (lambda t: _top(t, "robot = [1]"), "robot", "[[robot]] tables"),
    (lambda t: re.sub(r"\[casadi\]\n(?:.*\n)*?\n", "", t, count=1).replace(
        'format = "cochlea-codegen/1"', 'format = "cochlea-codegen/1"\ncasadi = 5'), "casadi",
     "a table of CasADi options"),
    (lambda t: t.replace("[casadi]\n", "[casadi]\nbogus_option = 1\n"), "casadi",
     "Unrecognized option: bogus_option"),
    (lambda t: t.replace("[function]\n", "[function]\nbogus_option = 1\n"), "function",
     "Unknown option: bogus_option"),
    (lambda t: t.replace("[function]\n", '[function]\ncse = "yes"\n').replace(
        "cse = false", ""), "function", "Illegal type for cse"),
    (lambda t: t.replace("cse = true", "cse = true\nbogus_option = 1"), "embedded.function",
     "Unknown option: bogus_option"),
    (lambda t: t.replace('units = ["arm1", "arm2"]', "units = [1, 2]", 1), "robot[0].units",
     "a list of strings"),
    (lambda t: t.replace("plant_substeps = 1", "plant_substeps = true", 1),
     "robot[0].plant_substeps", "an integer"),
    (lambda t: t.replace("plant_substeps = 1", "plant_substeps = 1000000000", 1),
     "robot[0].plant_substeps", "in 1..100"),
    (lambda t: "a = " + "[" * 100_000 + "]" * 100_000 + "\n" + t, "", "nested too deep"),
], ids=["robot-table", "robot-int", "robot-list-int", "casadi-int", "casadi-unknown",
        "function-unknown", "function-type", "embedded-function-unknown", "units-int",
        "substeps-bool", "substeps-huge", "deep"])
def test_a_configuration_of_the_wrong_shape_is_one_clear_error(tmp_path, edit, key, expected):
    """Each of these was a TypeError, a RecursionError or CasADi's own RuntimeError (the
    embedded one only after every kernel was generated), or a misleading message."""
    path = tmp_path / "k.toml"
    path.write_text(edit((CODEGEN_DIR / "kernels.toml").read_text()))
    with pytest.raises(CodegenError) as err:
        load_config(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {key}") and expected in message, message
    assert "\n" not in message and len(message) < 400 + len(str(path))


def _manifest_json() -> dict:
    text = (GENERATED / "manifest.c").read_text()
    body = text.split("static const char manifest[] =\n", 1)[1].split(";\n", 1)[0]
    lines = re.findall(r'^  "(.*)\\n"$', body, flags=re.M)
    return json.loads("\n".join(line.replace('\\"', '"').replace("\\\\", "\\")
                                for line in lines))


def _normalised_body(path, names) -> str:
    """A generated C file with its comments and every kernel, group and driver name replaced
    by one placeholder: what it computes, not what it is called."""
    text = re.sub(r"/\*.*?\*/", "", path.read_text(), flags=re.S)
    text = re.sub(r"//[^\n]*", "", text)
    pattern = re.compile(r"\b(?:" + "|".join(sorted(map(re.escape, names), key=len,
                                                        reverse=True)) + r")(?=\w*)")
    text = pattern.sub("NAME", text)
    return re.sub(r"\bNAME\w*", "NAME", text)


@pytest.mark.slow
def test_no_committed_file_repeats_another_up_to_names():
    manifest = _manifest_json()
    names = set(manifest["kernels"]) | set(manifest["closed_loops"])
    names |= {entry["group"] for entry in manifest["kernels"].values()}
    names |= {n.upper() for n in names}  # the headers' include guards and macros
    bodies: dict[str, str] = {}
    for path in sorted(GENERATED.glob("*.c")):  # bodies (a header only declares them)
        body = _normalised_body(path, names)
        assert body not in bodies, f"{path.name} repeats {bodies.get(body)} up to names"
        bodies[body] = path.name


@pytest.mark.slow
def test_aliases_run_an_emitted_kernel_that_computes_the_same(config):
    """Every alias names a kernel that has C of its own, with its signature; and the
    computations really are equal (the generator's identity, recomputed here on CasADi)."""
    manifest = _manifest_json()
    kernels = manifest["kernels"]
    aliases = {n: e["symbol"] for n, e in kernels.items() if e["symbol"] != n}
    # What the issue found duplicated is shared now, and the thesis variants that differ stay.
    assert aliases["serial_arm1_e_thesis_step"] == "serial_arm1_e_step"
    assert aliases["serial_arm2_e_step"] == "serial_arm1_e_step"
    assert aliases["serial_arm2_M"] == "serial_arm1_M"
    assert "serial_arm2_fk_world" not in aliases and "serial_arm1_g_thesis_step" not in aliases
    assert "parallel_f_thesis_step" not in aliases and "parallel_d_thesis_step" not in aliases
    c_text = "".join(p.read_text() for p in GENERATED.glob("*.c"))
    for name, symbol in aliases.items():
        assert kernels[symbol]["symbol"] == symbol, name  # one step: no alias of an alias
        assert re.search(rf"\bint {re.escape(symbol)}\(const casadi_real\*\* arg", c_text)
        assert not re.search(rf"\bint {re.escape(name)}\(", c_text), name
        for key in ("inputs", "outputs"):
            assert kernels[name][key] == kernels[symbol][key], name
    for loop, entry in manifest["closed_loops"].items():
        if entry["symbol"] != loop:
            driver = manifest["closed_loops"][entry["symbol"]]
            assert [kernels[entry[k]]["symbol"] for k in ("step", "plant", "pose")] == \
                [kernels[driver[k]]["symbol"] for k in ("step", "plant", "pose")], loop
    # The identity the generator used: equal for the pairs above, different for a real change.
    from cochlea.kernels.catalogue import collect
    from cochlea.kernels.naming import computation_hash

    built = {k.name: k.function for k in collect(config)[0]}
    for name, symbol in aliases.items():
        assert computation_hash(built[name]) == computation_hash(built[symbol]), name
    assert computation_hash(built["serial_arm1_g_step"]) != \
        computation_hash(built["serial_arm1_g_thesis_step"])


_KERNEL = re.compile(r"^CASADI_SYMBOL_EXPORT int (\w+)\(const casadi_real\*\* arg, "
                     r"casadi_real\*\* res, casadi_int\* iw, casadi_real\* w, int mem\)\{\n"
                     r"  return (casadi_f\d+)\(", flags=re.M)


def test_no_emitted_kernel_repeats_another_up_to_names():
    """Inside the files too (arm 2's M, C, G, plant step, ... were arm 1's): no two kernels with
    C of their own have the same signature and the same body once CasADi's local names are
    normalised. Kernels whose arguments are named differently (``parallel_fk`` and
    ``parallel_fk_world``, equal because the mechanism's frame is the world's) have different
    signatures, so neither can run the other's C: they stay."""
    manifest = _manifest_json()["kernels"]
    emitted: dict[str, str] = {}
    seen: dict[tuple[str, str], str] = {}
    for path in sorted(GENERATED.glob("*.c")):
        text = path.read_text()
        for name, local in _KERNEL.findall(text):
            body = re.search(rf"^static int {local}\(.*?^\}}$", text, flags=re.S | re.M)
            assert body, (path.name, name)
            emitted[name] = path.name
            signature = json.dumps([manifest[name]["inputs"], manifest[name]["outputs"]])
            key = (signature, body.group(0).replace(local, "F"))
            assert key not in seen, f"{name} ({path.name}) repeats {seen.get(key)}"
            seen[key] = name
    # The parser found every kernel that has C of its own, and none of the aliases.
    assert set(emitted) == {n for n, e in manifest.items() if e["symbol"] == n}
