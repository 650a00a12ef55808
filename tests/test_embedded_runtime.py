"""The embedded runtime's hand-written C core against the Python runtime it ports: the drive
conversions (embedded/core/drives.c, on the tables cochlea-codegen writes from the
descriptions) give the bridge's counts and currents bit for bit, and the supervisor
(embedded/core/supervisor.c) stops on the same rule, joint and value as
cochlea/runtime/supervisor.py. Both compile freestanding and need nothing but libm."""

from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.embedded_drives import drives_header
from cochlea.runtime.supervisor import STOP_CODES, Limits, Supervisor

from .embedded_build import build_library

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "embedded" / "core"
FREESTANDING = ["-std=c99", "-pedantic", "-ffreestanding", "-fno-builtin", "-Wall", "-Wextra",
                "-Werror", "-Wconversion", "-Wdouble-promotion"]
LIBM = {"sqrt", "fabs", "nearbyint"}

SHIM = """
#include "{robot}_drives.h"
#include "cochlea_rt.h"
const cochlea_drive *table(void) {{ return {robot}_drives; }}
int n_drives(void) {{ return {upper}_N_DRIVES; }}
const double *limit(int which) {{
    const double *all[4] = {{{robot}_position_lo, {robot}_position_hi, {robot}_velocity,
                            {robot}_effort}};
    return all[which];
}}
"""


class Drive(ctypes.Structure):
    _fields_ = [("name", ctypes.c_char_p), ("id", ctypes.c_uint8),
                ("model_number", ctypes.c_uint16), ("revolute", ctypes.c_int)] + [
        (f, ctypes.c_double) for f in ("q_per_count", "q_offset", "qd_per_lsb",
                                        "torque_per_effort", "inv_a", "inv_ramp", "i0",
                                        "lsb_per_ampere", "ampere_per_lsb")] + [
        ("current_limit_lsb", ctypes.c_int32)] + [
        (f, ctypes.c_double) for f in ("position_lo", "position_hi", "velocity_limit",
                                        "effort_limit")] + [("bus", ctypes.c_void_p)]


class Stop(ctypes.Structure):
    _fields_ = [("rule", ctypes.c_int), ("time_s", ctypes.c_double), ("joint", ctypes.c_int),
                ("unit", ctypes.c_int), ("what", ctypes.c_int), ("value", ctypes.c_double),
                ("limit", ctypes.c_double), ("point", ctypes.c_double * 2),
                ("centre", ctypes.c_double * 2), ("count", ctypes.c_int),
                ("reason", ctypes.c_int)]


class CLimits(ctypes.Structure):
    _fields_ = [("n_joints", ctypes.c_int)] + [
        (f, ctypes.POINTER(ctypes.c_double)) for f in ("position_lo", "position_hi",
                                                        "velocity", "effort")] + [
        ("keep_out_radius", ctypes.c_double), ("watchdog_misses", ctypes.c_int),
        ("watchdog_errors", ctypes.c_int)]


RULES = ["none", "completed", "user-stop", "position-limit", "velocity-limit", "keep-out",
         "non-finite", "estimate-bound", "watchdog", "terminated", "log-failure"]


def _compile(tmp: Path, robot: str, description: Path | None = None) -> ctypes.CDLL:
    """The core and a shim over the drive table, as a port includes it (a header of its own)."""
    (tmp / f"{robot}_drives.h").write_text(drives_header(robot, description))
    lib = build_library(f"core_{robot}", [CORE / "drives.c", CORE / "supervisor.c",
                                          ("shim.c", SHIM.format(robot=robot,
                                                                 upper=robot.upper()))],
                        include=[CORE, tmp])
    c = ctypes.CDLL(str(lib))
    c.table.restype = ctypes.POINTER(Drive)
    c.limit.restype = ctypes.POINTER(ctypes.c_double)
    c.cochlea_drive_position.restype = ctypes.c_double
    c.cochlea_drive_position.argtypes = [ctypes.POINTER(Drive), ctypes.c_int32, ctypes.c_double]
    c.cochlea_drive_velocity.restype = ctypes.c_double
    c.cochlea_drive_velocity.argtypes = [ctypes.POINTER(Drive), ctypes.c_int32]
    c.cochlea_drive_unwrap.restype = ctypes.c_double
    c.cochlea_drive_unwrap.argtypes = [ctypes.POINTER(Drive), ctypes.c_double, ctypes.c_double]
    c.cochlea_drive_goal_current.restype = ctypes.c_int16
    c.cochlea_drive_goal_current.argtypes = [ctypes.POINTER(Drive), ctypes.c_double,
                                             ctypes.c_int]
    c.cochlea_drive_current.restype = ctypes.c_double
    c.cochlea_drive_current.argtypes = [ctypes.POINTER(Drive), ctypes.c_int16]
    c.cochlea_rule_name.restype = ctypes.c_char_p
    return c


@pytest.fixture(scope="module", params=["serial", "parallel"])
def built(request, tmp_path_factory):
    return request.param, _compile(tmp_path_factory.mktemp(request.param), request.param)


@pytest.mark.slow
def test_the_core_compiles_freestanding_and_needs_only_libm(tmp_path):
    """Codec, drives, supervisor and bridge: C99, freestanding, warning-free; together they
    call nothing outside themselves but libm."""
    undefined, defined = set(), set()
    for source in ("dxl.c", "drives.c", "supervisor.c", "bridge.c"):
        obj = tmp_path / (source + ".o")
        subprocess.run(["cc", *FREESTANDING, f"-I{CORE}", "-c", str(CORE / source), "-o",
                        str(obj)], check=True, capture_output=True, text=True)
        undefined |= set(subprocess.run(["nm", "-u", str(obj)], check=True,
                                        capture_output=True, text=True).stdout.split()[1::2])
        defined |= {line.split()[-1] for line in subprocess.run(
            ["nm", "-g", "--defined-only", str(obj)], check=True, capture_output=True,
            text=True).stdout.splitlines()}
    assert undefined - defined <= LIBM, undefined - defined
    assert {"cochlea_bridge_start", "cochlea_check_state", "dxl_parser_parse"} <= defined


@pytest.mark.slow
def test_the_drive_tables_are_the_bridges(built):
    robot, c = built
    drives = joint_drives(robot)
    assert c.n_drives() == len(drives)
    table = c.table()
    for i, d in enumerate(drives):
        row = table[i]
        assert (row.name.decode(), row.id, row.model_number, row.revolute) == (
            d.name, d.id, d.spec.number, int(d.type == "revolute"))
        assert (row.q_per_count, row.q_offset, row.qd_per_lsb, row.torque_per_effort) == (
            d.q_per_count, d.q_offset, d.qd_per_lsb, d.torque_per_effort)
        assert (row.inv_a, row.inv_ramp, row.i0, row.lsb_per_ampere) == (
            1.0 / d.fit.a, 1.0 / d.fit.ramp, d.fit.offset_current, d.lsb_per_ampere)
        assert row.current_limit_lsb == d.current_limit_lsb
        assert (row.position_lo, row.position_hi, row.effort_limit) == (
            *d.position_limits, d.effort_limit)


def test_conversions_equal_the_bridges_bit_for_bit(built, rng):
    robot, c = built
    for i, d in enumerate(joint_drives(robot)):
        row = ctypes.byref(c.table()[i])
        counts = rng.integers(-2**20, 2**20, 300)
        for k in counts:
            assert c.cochlea_drive_position(row, int(k), d.q_offset) == float(d.q(k))
            assert c.cochlea_drive_velocity(row, int(k) % 2048 - 1024) == float(
                d.qd(int(k) % 2048 - 1024))
        # Efforts across the ramp, past the current limit, and a few exact zeros.
        efforts = np.concatenate([rng.uniform(-1.5, 1.5, 400) * d.effort_limit,
                                  rng.uniform(-0.05, 0.05, 200), [0.0, -0.0]])
        for e in efforts:
            assert c.cochlea_drive_goal_current(row, float(e), 1) == int(d.goal_current_lsb(e))
            # Without the offset (the controller compensates friction): the slope alone.
            assert c.cochlea_drive_goal_current(row, float(e), 0) == int(
                d.goal_current_lsb(e, offset_current=False))
        for bad in (float("nan"), float("inf"), -float("inf")):
            assert c.cochlea_drive_goal_current(row, bad, 1) == 0
            assert c.cochlea_drive_goal_current(row, bad, 0) == 0
        # The start-up unwrap: the turn nearest the middle of the limits (the bridge's rule).
        lo, hi = d.position_limits
        for q in rng.uniform(-12, 12, 100):
            offset = c.cochlea_drive_unwrap(row, float(q), d.q_offset)
            if d.type == "revolute":
                turns = round(((lo + hi) / 2 - q) / (2 * np.pi))
                assert offset == d.q_offset + 2 * np.pi * turns
            else:
                assert offset == d.q_offset


@pytest.mark.slow
def test_the_measured_current_is_the_python_bridges_at_the_joints_sign(tmp_path, rng):
    """Present Current (LSB) to the joint's current (A), as cochlea-run logs it: the Python
    bridge's joint_current_A after a read of the same registers, bit for bit, on a description
    where arm 1's second motor is mounted against its joint (direction -1), over the whole
    int16 range of the register."""
    from cochlea.dynamixel.bridge import DynamixelBackend
    from tests.test_current_fit import _description_with, _shipped_fit
    from tests.test_dynamixel_drives import ScriptedPort

    old = "id = 2\n  " + _shipped_fit(122.3, -23.7) + "\n  direction = 1"
    description = _description_with(tmp_path, old, old.replace("direction = 1",
                                                                "direction = -1"))
    c = _compile(tmp_path, "serial", description)
    backend = DynamixelBackend("serial", "/dev/scripted", description=description)
    port = ScriptedPort(backend)
    backend._port, backend._active = port, True
    assert [d.direction for d in backend.drives][:2] == [1, -1]
    n = backend.nq
    x = np.zeros(2 * n)
    signs = set()
    for trial in range(40):
        amps = rng.integers(-2**15, 2**15, n)
        if trial == 0:
            amps[:] = [-2**15, 2**15 - 1, 0, 1, -1, 7]
        port.registers = {i: (int(a), 0, 0) for i, a in zip(backend.ids, amps)}
        assert backend.read(x)
        for j in range(n):
            value = c.cochlea_drive_current(ctypes.byref(c.table()[j]), int(amps[j]))
            assert value == backend.joint_current_A[j], (j, amps[j])
            if amps[j]:
                signs.add((backend.drives[j].direction, bool(np.sign(value) == np.sign(amps[j]))))
    # A motor mounted against its joint reports the opposite sign of the joint's current.
    assert signs == {(1, True), (-1, False)}


def _limits(c, n, keep_out=0.0):
    p = [c.limit(i) for i in range(4)]
    return CLimits(n, *p, keep_out, 20, 5)


def _python_supervisor(c, n, keep_out=None):
    arrays = [np.ctypeslib.as_array(c.limit(i), (n,)).copy() for i in range(4)]
    names = tuple(f"j{i}" for i in range(n))
    return Supervisor(Limits(*arrays, names, ("rad",) * n, keep_out), [], lambda q: [])


def test_the_supervisor_breaks_the_same_rule_on_the_same_joint(built, rng):
    robot, c = built
    n = c.n_drives()
    limits = _limits(c, n)
    python = _python_supervisor(c, n)
    lo, hi, vel = (np.ctypeslib.as_array(c.limit(i), (n,)) for i in range(3))
    stop = Stop()
    seen = set()
    for trial in range(3000):
        q = rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo))
        qd = rng.uniform(-1.3, 1.3, n) * vel
        if trial % 7 == 0:  # finite values whose squares overflow are not "non-finite"
            (q if trial % 2 else qd)[rng.integers(n)] = rng.choice([np.nan, np.inf, -np.inf,
                                                                   1e200, -1e300])
        x = np.concatenate([q, qd])
        expected = python.check_state(0.5, x, x[:n], x[n:])
        broke = c.cochlea_check_state(ctypes.byref(limits), ctypes.c_double(0.5),
                                      q.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                                      qd.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                                      ctypes.byref(stop))
        assert bool(broke) == (expected is not None)
        if expected is None:
            continue
        rule = RULES[stop.rule]
        seen.add(rule)
        assert rule == expected.rule and stop.time_s == 0.5
        if rule in ("position-limit", "velocity-limit"):
            assert python.limits.joint_names[stop.joint] in expected.detail.split(" ")[0]
            value = q[stop.joint] if rule == "position-limit" else qd[stop.joint]
            assert stop.value == value
    assert seen == {"non-finite", "position-limit", "velocity-limit"}


def test_command_rules_and_saturation(built, rng):
    robot, c = built
    n = c.n_drives()
    limits = _limits(c, n)
    effort = np.ctypeslib.as_array(c.limit(3), (n,))
    stop = Stop()
    dp = ctypes.POINTER(ctypes.c_double)
    bounds = np.array([2.0, 3.0])
    sizes = (ctypes.c_int * 2)(3, 4)
    rules, huge = set(), set()
    for trial in range(500):
        tau = rng.uniform(-2, 2, n) * effort
        estimates = [rng.uniform(-1.3, 1.3, 3), rng.uniform(-1.7, 1.7, 4)]
        if trial % 5 == 0:
            tau[rng.integers(n)] = np.nan
        if trial % 11 == 0:
            estimates[1][2] = np.inf
        if trial % 13 == 0:  # finite, its squares overflow: estimate-bound, its true norm
            estimates[trial % 2][1] = -1e200
        pointers = (dp * 2)(*(e.ctypes.data_as(dp) for e in estimates))
        python = Supervisor(Limits(*[np.zeros(n)] * 3, effort.copy(), ("j",) * n,
                                   ("rad",) * n), [type("U", (), {"name": f"u{i}", "bound": b})
                                                   for i, b in enumerate(bounds)], None)
        expected = python.check_command(1.0, tau, estimates)
        broke = c.cochlea_check_command(ctypes.byref(limits), ctypes.c_double(1.0),
                                        tau.ctypes.data_as(dp), 2, pointers, sizes,
                                        bounds.ctypes.data_as(dp), ctypes.byref(stop))
        assert bool(broke) == (expected is not None)
        if expected is not None:
            assert RULES[stop.rule] == expected.rule
            rules.add(expected.rule)
            if expected.rule == "estimate-bound":
                norm = float(expected.detail.split("= ")[1].split(",")[0])
                assert stop.value == pytest.approx(norm, rel=1e-3)
                huge.add(norm > 1e199)
        clipped = tau.copy()
        count = c.cochlea_saturate(ctypes.byref(limits), clipped.ctypes.data_as(dp))
        if np.isfinite(tau).all():
            python.saturate(tau)
            assert np.array_equal(clipped, tau)
            assert count == int(np.sum(np.abs(tau) == effort))
    assert rules == {"non-finite", "estimate-bound"} and huge == {True, False}


def test_keep_out_and_exit_codes(built):
    _, c = built
    n = c.n_drives()
    limits = _limits(c, n, keep_out=0.1)
    stop = Stop()
    points = np.array([0.3, 0.0, 0.05, 0.05])
    centres = np.zeros(4)
    dp = ctypes.POINTER(ctypes.c_double)
    assert c.cochlea_check_keep_out(ctypes.byref(limits), ctypes.c_double(2.0), 2,
                                    points.ctypes.data_as(dp), centres.ctypes.data_as(dp),
                                    ctypes.byref(stop)) == 1
    assert RULES[stop.rule] == "keep-out" and stop.unit == 1
    assert stop.value == pytest.approx(np.hypot(0.05, 0.05)) and stop.limit == 0.1
    off = _limits(c, n, keep_out=0.0)
    assert c.cochlea_check_keep_out(ctypes.byref(off), ctypes.c_double(2.0), 2,
                                    points.ctypes.data_as(dp), centres.ctypes.data_as(dp),
                                    ctypes.byref(stop)) == 0
    for i, rule in enumerate(RULES):
        assert c.cochlea_rule_name(i).decode() == rule
        assert c.cochlea_exit_code(i) == STOP_CODES.get(rule, 0)
    assert c.cochlea_exit_code(99) == 5
