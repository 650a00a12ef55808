"""The embedded runtime's Dynamixel bridge (embedded/core/bridge.c on the POSIX port's HAL,
embedded/posix/hal_posix.c) against the virtual Dynamixel chain, through ctypes: the start-up
sequence, the reads and writes of each period, the safe shut-down, and the start-up faults,
each as the Python bridge (cochlea/dynamixel/bridge.py) does them."""

from __future__ import annotations

import ctypes
import gc
import math
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.embedded_drives import drives_header
from cochlea.dynamixel.emulator import Faults, VirtualChain

from .embedded_build import build_library
from .test_dynamixel_bridge import (
    TORQUE_ON_FAULTS,
    expected_torque_on_traffic,
    torque_on_chain,
    torque_on_traffic,
)

ROOT = Path(__file__).resolve().parent.parent
CORE, POSIX = ROOT / "embedded" / "core", ROOT / "embedded" / "posix"

PROBE = """
#include "bridge.h"
#include "hal_posix.h"
#include "{robot}_drives.h"
static cochlea_posix_port port;
static cochlea_hal hal;
static cochlea_bridge bridge;
cochlea_start_report report;
int probe_open(const char *path, double timeout_s, double watchdog_s) {{
    if (cochlea_posix_open(&port, path, 4000000) != 0) return -1;
    cochlea_posix_hal(&hal, &port);
    return cochlea_bridge_init(&bridge, &hal, {robot}_drives, {upper}_N_DRIVES,
                               (int64_t)(timeout_s * 1e9), watchdog_s);
}}
int probe_start(void) {{ return cochlea_bridge_start(&bridge, &report); }}
int probe_read(double *q, double *qd) {{ return cochlea_bridge_read(&bridge, q, qd); }}
int probe_write(const double *tau) {{ return cochlea_bridge_write(&bridge, tau); }}
int probe_stop(void) {{ return cochlea_bridge_stop(&bridge); }}
int probe_goal(int i) {{ return bridge.goal[i]; }}
unsigned probe_failures(int kind) {{ return bridge.failures[kind]; }}
int probe_last_failure(void) {{ return bridge.last_failure; }}
int probe_last_failure_id(void) {{ return bridge.last_failure_id; }}
int probe_use_tick(void) {{ return cochlea_bridge_use_realtime_tick(&bridge); }}
const unsigned char *probe_read_frame(size_t *n) {{
    *n = bridge.read_len;
    return bridge.read_frame;
}}
void probe_close(void) {{ cochlea_posix_close(&port); }}
"""


class Report(ctypes.Structure):
    _fields_ = [("error", ctypes.c_int), ("step", ctypes.c_int), ("drive", ctypes.c_int),
                ("detail", ctypes.c_int), ("value", ctypes.c_double)]


START_ERRORS = ["ok", "no-answer", "crc", "port", "alert", "refused", "wrong-model", "no-read",
                "outside-limits", "bad-config", "not-homed"]


def build_probe(tmp: Path, robot: str, description: Path | None = None) -> Path:
    """The bridge, the POSIX HAL and a shim over the drive table (a header in ``tmp``)."""
    (tmp / f"{robot}_drives.h").write_text(drives_header(robot, description))
    probe = PROBE.format(robot=robot, upper=robot.upper())
    return build_library(f"probe_{robot}", [CORE / "dxl.c", CORE / "drives.c",
                                            CORE / "bridge.c", POSIX / "hal_posix.c",
                                            ("probe.c", probe)], include=[CORE, POSIX, tmp])


class Probe:
    """The C bridge of one robot, on a pseudo-terminal."""

    def __init__(self, lib: Path, n: int):
        # A fresh copy per probe: the shim's bridge is a static, one per loaded library.
        self.c = ctypes.CDLL(str(lib), mode=ctypes.RTLD_LOCAL)
        self.n = n
        self.report = Report.in_dll(self.c, "report")
        dp = ctypes.POINTER(ctypes.c_double)
        self.c.probe_open.argtypes = [ctypes.c_char_p, ctypes.c_double, ctypes.c_double]
        self.c.probe_read.argtypes = [dp, dp]
        self.c.probe_write.argtypes = [dp]
        self.c.probe_failures.restype = ctypes.c_uint

    def open(self, path: str, timeout_s: float = 0.05, watchdog_s: float = 0.1) -> int:
        return self.c.probe_open(path.encode(), timeout_s, watchdog_s)

    def read(self):
        q, qd = np.zeros(self.n), np.zeros(self.n)
        dp = ctypes.POINTER(ctypes.c_double)
        ok = self.c.probe_read(q.ctypes.data_as(dp), qd.ctypes.data_as(dp))
        return ok, q, qd

    def write(self, tau) -> int:
        tau = np.ascontiguousarray(tau, float)
        return self.c.probe_write(tau.ctypes.data_as(ctypes.POINTER(ctypes.c_double)))

    @property
    def start_error(self) -> str:
        return START_ERRORS[self.report.error]


@pytest.fixture(scope="module")
def libs(tmp_path_factory):
    return {robot: build_probe(tmp_path_factory.mktemp(robot), robot)
            for robot in ("serial", "parallel")}


@pytest.fixture(autouse=True)
def no_gc():
    """The emulator is a thread of this process: no collector pause may stall it."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


def probe_on(libs, tmp_path, robot, chain) -> Probe:
    # Each test loads its own copy, so the static bridge starts afresh.
    copy = tmp_path / f"probe_{robot}_{id(chain)}.so"
    copy.write_bytes(libs[robot].read_bytes())
    p = Probe(copy, len(joint_drives(robot)))
    assert p.open(chain.path) == 0
    return p


@pytest.mark.parametrize("robot", ["serial", "parallel"])
@pytest.mark.slow
def test_start_read_write_stop_as_the_python_bridge(libs, tmp_path, robot):
    chain = VirtualChain(robot).start()
    try:
        p = probe_on(libs, tmp_path, robot, chain)
        assert p.c.probe_start() == 1, (p.start_error, p.report.step, p.report.drive)
        drives = joint_drives(robot)
        limits = {d.id: d.current_limit_lsb for d in drives}
        writes = [(e[2], e[3], e[4]) for e in chain.events if e[1] == "write"]
        steps = [(64, 0), (98, 0), (11, 0), (9, 0), (38, None), (102, 0), (98, 5)]
        for d in drives:
            mine = [(a, v) for i, a, v in writes if i == d.id]
            assert mine == [(a, limits[d.id] if v is None else v) for a, v in steps]
        # Torque on with the first nonzero command, not at the start (as the Python bridge).
        assert not any(m.torque_on for m in chain.motors)
        # A read is the chain's state to one encoder count and one velocity LSB (the joints
        # move under gravity meanwhile: the state before and after the read bracket it).
        before = chain.joint_state()
        ok, q, qd = p.read()
        after = chain.joint_state()
        n = len(drives)
        assert ok == 1
        resolution = np.concatenate([[abs(d.q_per_count) for d in drives],
                                     [abs(d.qd_per_lsb) for d in drives]])
        lo, hi = np.minimum(before, after), np.maximum(before, after)
        x = np.concatenate([q, qd])
        assert np.all((x >= lo - 1.01 * resolution) & (x <= hi + 1.01 * resolution))
        # A write sets every Goal Current to the bridge's conversion of the effort.
        tau = np.linspace(-0.4, 0.4, n) * np.array([d.effort_limit for d in drives])
        assert p.write(np.zeros(n)) == 1
        assert not any(m.torque_on for m in chain.motors)
        assert p.write(tau) == 1
        expected = [int(d.goal_current_lsb(t)) for d, t in zip(drives, tau)]
        assert [p.c.probe_goal(i) for i in range(n)] == expected
        # Its two transactions, after the Goal Current: as the Python bridge's.
        assert torque_on_traffic(chain) == [("sync-write", d.id, 64, 1) for d in drives] + [
            ("sync-read", 254, 64, 1)]
        assert all(m.torque_on for m in chain.motors)
        deadline = 100
        while [m.get(102) for m in chain.motors] != expected and deadline:
            p.read()  # a transaction gives the emulator's thread time to apply the write
            deadline -= 1
        assert [m.get(102) for m in chain.motors] == expected
        # A NaN command: zero current everywhere, and reported.
        bad = tau.copy()
        bad[1] = math.nan
        assert p.write(bad) == 0 and p.c.probe_failures(7) == 1
        assert [p.c.probe_goal(i) for i in range(n)] == [0] * n
        # The safe stop: every motor confirms torque off.
        assert p.c.probe_stop() == n
        assert not any(m.torque_on for m in chain.motors)
        assert p.read()[0] == 0 and p.c.probe_last_failure() == 8  # not enabled
        p.c.probe_close()
    finally:
        chain.close()


@pytest.mark.parametrize("faults, error, step, detail", [
    (Faults(missing=frozenset({3})), "no-answer", 1, None),
    (Faults(model_number={2: 1020}), "wrong-model", 1, 1020),
])
@pytest.mark.slow
def test_start_up_faults_stop_before_anything_moves(libs, tmp_path, faults, error, step, detail):
    chain = VirtualChain("serial", faults=faults).start()
    try:
        p = probe_on(libs, tmp_path, "serial", chain)
        assert p.c.probe_start() == 0
        assert (p.start_error, p.report.step) == (error, step)
        ids = [d.id for d in joint_drives("serial")]
        culprit = next(iter(faults.missing)) if faults.missing else next(iter(faults.model_number))
        assert ids[p.report.drive] == culprit
        if detail is not None:
            assert p.report.detail == detail
        assert not any(m.torque_on for m in chain.motors)
        assert not any(e[1] in ("write", "sync-write") and e[3:] == (64, 1)
                       for e in chain.events)
        p.c.probe_close()
    finally:
        chain.close()


@pytest.mark.slow
def test_a_joint_outside_its_limits_is_refused_at_start(tmp_path):
    """As the Python bridge's test: arm1.link1 is at 73 deg; a table whose motor zero is at
    -107 deg reads 180 deg, outside +-170 deg whichever turn it takes; at -120 deg it reads
    193 deg, taken as -167 deg (single-turn encoder) and accepted."""
    from cochlea.resources import ROBOTS_DIR

    chain = VirtualChain("serial").start()
    try:
        for offset, accepted in (("-107.0", False), ("-120.0", True)):
            folder = tmp_path / offset
            folder.mkdir()
            wrong = folder / "serial.toml"
            wrong.write_text((ROBOTS_DIR / "serial.toml").read_text().replace(
                "zero_offset_deg = 0.0", f"zero_offset_deg = {offset}", 1))
            copy = folder / "probe.so"  # its own copy: the shim's bridge is a static
            copy.write_bytes(build_probe(folder, "serial", wrong).read_bytes())
            p = Probe(copy, 6)
            assert p.open(chain.path) == 0
            assert p.c.probe_start() == int(accepted)
            if accepted:
                ok, q, _ = p.read()
                assert ok and q[0] == pytest.approx(math.radians(193 - 360), abs=1e-3)
                assert p.c.probe_stop() == 6
            else:
                assert (p.start_error, p.report.drive) == ("outside-limits", 0)
                assert abs(math.degrees(p.report.value)) == pytest.approx(180.0, abs=0.1)
                assert not any(m.torque_on for m in chain.motors)
            p.c.probe_close()
    finally:
        chain.close()


@pytest.mark.slow
def test_dropped_replies_are_failures_not_stops(libs, tmp_path):
    """Motor 4 stops answering 0.2 s after the start: each read fails (a timeout, counted),
    the bridge does not stop by itself, and the shut-down still reaches every motor."""
    chain = VirtualChain("serial", faults=Faults(drop=1.0, ids=frozenset({4}),
                                                 delay_s=0.2)).start()
    try:
        p = probe_on(libs, tmp_path, "serial", chain)
        assert p.c.probe_start() == 1
        assert p.read()[0] == 1
        # The torque comes on with the first nonzero command; the faults count from there.
        assert p.write(np.full(6, 0.01)) == 1
        time.sleep(0.3)
        ok, _, _ = p.read()
        assert ok == 0 and p.c.probe_last_failure() == 0  # timeout
        assert p.c.probe_failures(0) >= 1
        assert p.c.probe_stop() == 5  # motor 4 got torque off but its reply is dropped
        assert not any(m.torque_on for m in chain.motors)
        p.c.probe_close()
    finally:
        chain.close()


@pytest.mark.slow
def test_a_repeated_status_packet_is_refused_by_its_realtime_tick(libs, tmp_path):
    """As the Python bridge's test (test_runtime_hardening.py): motor 3 repeats its last status
    packet five times from 0.1 s on; read at 250 Hz, each repeat is more than a tick after the
    original, and the C bridge refuses it as a stale packet, then reads fresh packets again."""
    from cochlea.dynamixel import protocol as proto

    stale_kind = 9  # COCHLEA_FAIL_STALE: the Python bridge's name, "stale-packet"
    with VirtualChain("serial", faults=Faults(stale=(3, 5), delay_s=0.1)) as chain:
        p = probe_on(libs, tmp_path, "serial", chain)
        assert p.c.probe_use_tick() == 0
        # The tick in the same packet as the state: one SYNC_READ of 120..135, as Python's.
        size = ctypes.c_size_t()
        p.c.probe_read_frame.restype = ctypes.POINTER(ctypes.c_ubyte)
        frame = p.c.probe_read_frame(ctypes.byref(size))
        ids = [d.id for d in joint_drives("serial")]
        assert bytes(frame[:size.value]) == proto.sync_read(120, 16, ids)
        assert p.c.probe_start() == 1, p.start_error
        results = []
        assert p.read()[0] == 1 and p.write(np.full(6, 0.01)) == 1  # torque on, faults start
        try:
            end = time.perf_counter() + 0.6
            while time.perf_counter() < end:
                ok = p.read()[0]
                results.append((ok, p.c.probe_last_failure(), p.c.probe_last_failure_id()))
                p.write(np.zeros(6))
                time.sleep(0.004)
        finally:
            p.c.probe_stop()
            p.c.probe_close()
        repeated = chain.counts["stale"]
    assert repeated == 5  # the emulator repeated its packet five times, then answered afresh
    stale = [i for i, (ok, kind, _) in enumerate(results) if not ok and kind == stale_kind]
    assert 1 <= len(stale) <= repeated and all(results[i][2] == 3 for i in stale)
    assert p.c.probe_failures(stale_kind) == len(stale)
    assert results[0][0] == 1
    assert any(ok for ok, _, _ in results[stale[-1] + 1:])  # fresh packets are good again


NOT_ENABLED = 8  # COCHLEA_FAIL_NOT_ENABLED: the Python bridge's "not-enabled"


@pytest.mark.slow
@pytest.mark.parametrize("fault", [None, *TORQUE_ON_FAULTS])
def test_the_torque_on_is_the_python_bridges_on_the_wire(libs, tmp_path, fault):
    """Start-up step 9 in C, against the Python bridge on a chain with the same fault of motor 3
    (TORQUE_ON_FAULTS, or none): the emulator's event log from the first nonzero Goal Current
    to the next instruction about another item is the same for both (one SYNC_WRITE of Torque
    Enable 1 to every motor, one SYNC_READ of Torque Enable, asked again while a reply is
    missing); a motor that does not confirm fails that write and every read after it as
    not-enabled, naming it, nothing sent; the stop reaches every motor that hears the bus."""
    from cochlea.dynamixel.bridge import DynamixelBackend

    tau = np.full(6, 0.01)
    traffic = {}
    for side in ("python", "c"):
        chain = torque_on_chain(fault)
        try:
            if side == "python":  # the C bridge's timeout (setup: 4 x 50 ms) and 3 tries
                backend = DynamixelBackend("serial", chain.path, timeout_s=0.05, retries=3,
                                           description=chain.scenario.description)
                backend.enable()
                try:
                    assert backend.read(np.zeros(12))
                    assert backend.write(tau) is (fault is None)
                finally:
                    backend.disable()
            else:
                p = probe_on(libs, tmp_path, "serial", chain)
                assert p.c.probe_start() == 1, p.start_error
                assert p.read()[0] == 1
                if fault is None:
                    assert p.write(tau) == 1
                    assert all(m.torque_on for m in chain.motors)
                    assert p.read()[0] == 1
                else:
                    assert p.write(tau) == 0
                    failure = (p.c.probe_last_failure(), p.c.probe_last_failure_id())
                    assert failure == (NOT_ENABLED, 3)
                    heard = len(chain.events)
                    for _ in range(6):
                        assert p.read()[0] == 0
                        failure = (p.c.probe_last_failure(), p.c.probe_last_failure_id())
                        assert failure == (NOT_ENABLED, 3)
                    assert len(chain.events) == heard
                silent = fault == "stops answering"
                assert p.c.probe_stop() == 6 - silent
                assert not any(m.torque_on for m in chain.motors if m.id != 3 or not silent)
                p.c.probe_close()
            traffic[side] = torque_on_traffic(chain)
        finally:
            chain.close()
    assert traffic["c"] == traffic["python"] == expected_torque_on_traffic(fault, 3)
