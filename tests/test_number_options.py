"""Every numeric option of the command-line tools reads a plain ASCII decimal number
(cochlea.text.number_argument, whole_argument): Python's float() and int() also take ``0_5``
(5: a tenfold speed or force from a typo), ``nan``, ``inf`` and other scripts' digits, and
several of these options move motors (homing's speed and force, calibration's reference)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from cochlea.apps import cochlea_dxl, cochlea_excite, cochlea_identify, cochlea_run
from cochlea.dynamixel import emulator
from cochlea.errors import CochleaError
from cochlea.text import number_argument, strict_float, strict_int, whole_argument

PACKAGE = Path(__file__).resolve().parent.parent / "cochlea"
TYPOS = ["0_5", "nan", "inf", "-infinity", "\u0665", "\uff15", "1e999", "", "0x10", "5 mm"]


def test_no_option_parses_with_float_or_int():
    """No add_argument(type=float) or (type=int) anywhere in the package, nor a type built on
    them (an ID:VALUE parser's kind)."""
    found = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not (isinstance(node, ast.Call) and getattr(node.func, "attr", "") ==
                    "add_argument"):
                continue
            for keyword in node.keywords:
                value = keyword.value
                names = [value] + (list(value.args) if isinstance(value, ast.Call) else [])
                if keyword.arg == "type" and any(isinstance(v, ast.Name) and v.id in
                                                 ("float", "int") for v in names):
                    found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert not found, found


@pytest.mark.parametrize("text", TYPOS)
def test_the_types_refuse_what_float_and_int_take(text):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError):
        number_argument(text)
    with pytest.raises(argparse.ArgumentTypeError):
        whole_argument(text)
    with pytest.raises(ValueError):
        strict_float(text)
    with pytest.raises(ValueError):
        strict_int(text)


@pytest.mark.parametrize("text, value", [("0.5", 0.5), (" -2 ", -2.0), ("1e-3", 1e-3),
                                         (".5", 0.5), ("+3.", 3.0)])
def test_plain_decimals_are_read(text, value):
    assert number_argument(text) == value


@pytest.mark.parametrize("main, argv", [
    (cochlea_run.main, ["--robot", "serial", "--space", "joint", "--duration", "0_5"]),
    (cochlea_run.main, ["--robot", "serial", "--space", "joint", "--watchdog-misses", "2_0"]),
    (cochlea_dxl.main, ["home", "--robot", "parallel", "--port", "/dev/cochlea-none",
                        "--speed-mm-s", "0_5"]),
    (cochlea_dxl.main, ["home", "--robot", "parallel", "--port", "/dev/cochlea-none",
                        "--force-N", "nan"]),
    (cochlea_dxl.main, ["calibrate", "--robot", "serial", "--port", "/dev/cochlea-none",
                        "--min-motion-deg", "\u0665"]),
    (cochlea_identify.main, ["--robot", "serial", "--cutoff-hz", "inf"]),
    (cochlea_excite.main, ["--robot", "serial", "--harmonics", "3_0"]),
    (emulator.main, ["--robot", "serial", "--seed", "\uff11"]),
    (emulator.main, ["--robot", "serial", "--drop-replies", "0_5"]),
    (emulator.main, ["--robot", "serial", "--true-offset", "1:1_0"]),
    (emulator.main, ["--robot", "serial", "--missing-motor", "1_1"]),
])
def test_tools_refuse_a_typo_in_a_number_before_anything_runs(main, argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]  # argparse's usage may come first
    assert argv[-2] in last and "expected" in last, last


def test_calibrate_reads_its_reference_and_currents_strictly():
    from cochlea.dynamixel.bringup import calibrate

    for argv, message in ((["--reference", "left.th1=1_0"], "expected a finite number"),
                          (["--torque-fit", "--joint", "left.th1", "--lever-m", "0.1", "--csv",
                            "x.csv", "--currents-mA", "1_00,200"], "--currents-mA")):
        args = calibrate_args(calibrate, "--robot", "parallel", "--port", "/dev/cochlea-none",
                              *argv)
        with pytest.raises(CochleaError, match=message):
            calibrate.run(args)


def calibrate_args(module, *argv):
    import argparse

    p = argparse.ArgumentParser()
    module.add_arguments(p)
    return p.parse_args(list(argv))
