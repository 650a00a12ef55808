"""The official ROBOTIS SDK (``dynamixel-sdk``, a test-only dependency) as the byte-level oracle
of the bridge's frames, and as a client of the virtual chain (``cochlea-emulator``) over its
pseudo-terminal.

The SDK's transmit path does not apply byte stuffing (an upstream bug): frames that need it are
checked against the specification in ``test_dynamixel_protocol.py`` instead, and the random
frames below skip them.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.control_table import RAD_PER_COUNT

sdk = pytest.importorskip("dynamixel_sdk")


class CapturePort:
    """Enough of the SDK's PortHandler to capture what it transmits (no replies)."""

    def __init__(self):
        self.sent: list[bytes] = []

    @property
    def is_using(self):  # never busy: no transaction waits for a reply here
        return False

    @is_using.setter
    def is_using(self, value):
        pass

    def clearPort(self):
        pass

    def writePort(self, packet):
        self.sent.append(bytes(packet))
        return len(packet)

    def readPort(self, length):
        return b""

    def setPacketTimeout(self, packet_length):
        pass

    def setPacketTimeoutMillis(self, msec):
        pass

    def isPacketTimeout(self):
        return True

    def getBaudRate(self):
        return 4_000_000


@pytest.fixture
def oracle():
    return CapturePort(), sdk.PacketHandler(2.0)


def _stuffing_free(frame: bytes) -> bool:
    return proto.unstuff(frame[7:-2]) == frame[7:-2]


def test_ping_read_write_frames_are_byte_identical(oracle):
    port, ph = oracle
    ph.ping(port, 1)
    ph.read4ByteTxRx(port, 5, 132)
    ph.readTxRx(port, 6, 126, 10)
    ph.write1ByteTxOnly(port, 1, 64, 1)
    ph.write2ByteTxOnly(port, 2, 38, 731)
    ph.write4ByteTxOnly(port, 3, 116, 2048)
    ph.reboot(port, 4)
    assert port.sent == [
        proto.ping(1),
        proto.read(5, 132, 4),
        proto.read(6, 126, 10),
        proto.write(1, 64, b"\x01"),
        proto.write(2, 38, proto.le(731, 2)),
        proto.write(3, 116, proto.le(2048, 4)),
        proto.reboot(4),
    ]


def test_the_bridges_per_period_frames_are_byte_identical(oracle):
    """One SYNC_READ of 126..135 and one SYNC_WRITE of Goal Current, as the bridge sends them."""
    port, ph = oracle
    backend = DynamixelBackend("serial", "/dev/null-not-opened")
    read = sdk.GroupSyncRead(port, ph, 126, 10)
    for motor_id in backend.ids:
        read.addParam(motor_id)
    read.txPacket()
    assert port.sent[-1] == backend._read_frame

    goal = [12, -40, 0, 731, -731, 5]
    backend._goal[:] = goal
    n = backend._write_frame.encode()
    write = sdk.GroupSyncWrite(port, ph, 102, 2)
    for motor_id, value in zip(backend.ids, goal):
        value &= 0xFFFF
        write.addParam(motor_id, [sdk.DXL_LOBYTE(value), sdk.DXL_HIBYTE(value)])
    write.txPacket()
    assert port.sent[-1] == bytes(backend._write_frame.out[:n])


@settings(max_examples=300, deadline=None, database=None, derandomize=True)
@given(motor_id=st.integers(0, 252), address=st.integers(0, 700),
       data=st.binary(min_size=1, max_size=8),
       ids=st.lists(st.integers(0, 252), min_size=1, max_size=8, unique=True))
@pytest.mark.slow
def test_random_frames_match_the_sdk(motor_id, address, data, ids):
    port, ph = CapturePort(), sdk.PacketHandler(2.0)
    ph.writeTxOnly(port, motor_id, address, len(data), list(data))
    ph.readTx(port, motor_id, address, len(data))
    read = sdk.GroupSyncRead(port, ph, address, len(data))
    write = sdk.GroupSyncWrite(port, ph, address, len(data))
    for i in ids:
        read.addParam(i)
        write.addParam(i, list(data))
    read.txPacket()
    write.txPacket()
    ours = [proto.write(motor_id, address, data), proto.read(motor_id, address, len(data)),
            proto.sync_read(address, len(data), ids),
            proto.sync_write(address, len(data), [(i, data) for i in ids])]
    assert len(port.sent) == len(ours)
    for theirs, mine in zip(port.sent, ours):
        if _stuffing_free(mine):
            assert theirs == mine


@pytest.fixture(scope="module")
def emulator():
    """``cochlea-emulator --robot serial`` in a subprocess; yields the pseudo-terminal's path."""
    script = Path(sys.executable).with_name("cochlea-emulator")
    command = [str(script)] if script.exists() else [sys.executable, "-m",
                                                     "cochlea.dynamixel.emulator"]
    proc = subprocess.Popen(command + ["--robot", "serial", "--duration", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    path = proc.stdout.readline().strip()
    assert path.startswith("/dev/"), (path, proc.stderr.read() if proc.poll() is not None else "")
    yield path
    proc.terminate()
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "stopped" in out


@pytest.mark.slow
def test_the_sdk_pings_reads_and_sync_writes_the_emulator(emulator):
    port = sdk.PortHandler(emulator)
    assert port.openPort()
    ph = sdk.PacketHandler(2.0)
    try:
        for motor_id in range(1, 7):
            model, result, error = ph.ping(port, motor_id)
            assert (model, result, error) == (311, sdk.COMM_SUCCESS, 0)
        _, result, _ = ph.ping(port, 9)  # nobody there
        assert result == sdk.COMM_RX_TIMEOUT

        # serial_joint starts arm 1 at 73 deg: Present Position in counts (zero offset 0).
        counts, result, error = ph.read4ByteTxRx(port, 1, 132)
        assert (result, error) == (sdk.COMM_SUCCESS, 0)
        assert counts == round(73 * 3.141592653589793 / 180 / RAD_PER_COUNT)

        write = sdk.GroupSyncWrite(port, ph, 102, 2)
        values = {1: 100, 2: 200, 3: 300, 4: 400, 5: 500, 6: 600}
        for motor_id, value in values.items():
            assert write.addParam(motor_id, [sdk.DXL_LOBYTE(value), sdk.DXL_HIBYTE(value)])
        assert write.txPacket() == sdk.COMM_SUCCESS

        read = sdk.GroupSyncRead(port, ph, 102, 2)
        for motor_id in values:
            read.addParam(motor_id)
        assert read.txRxPacket() == sdk.COMM_SUCCESS
        for motor_id, value in values.items():
            assert read.isAvailable(motor_id, 102, 2)
            assert read.getData(motor_id, 102, 2) == value

        # A write the motor refuses comes back in the error byte: Operating Mode 2 is no mode.
        result, error = ph.write1ByteTxRx(port, 1, 11, 2)
        assert (result, error) == (sdk.COMM_SUCCESS, 4)  # Data Range Error
    finally:
        port.closePort()
