"""Issue 27, items 4 and 5 (Python side): mixed chains and Fast Sync Read.

* the frames (FAST_SYNC_READ 0x8A, its one combined status packet, BULK_READ 0x92, BULK_WRITE
  0x93) against the official SDK (``dynamixel_sdk``, the test extra), and the SDK as an
  independent client of the emulator;
* the choice of the per-period transfers from the models' data (``choose_transfers``), the
  budget of the transfers actually sent;
* the bridge over the emulator with each transfer, chains of XM430-W350s, XL330-M288s and a
  mixed one, through ``cochlea-dxl scan`` and ``cochlea-run --backend dynamixel``;
* the bad inputs: a Fast Sync Read reply with a motor missing, a corrupted CRC in the middle
  of the combined packet (on the wire, and a motor's own running CRC), a model without the
  instruction, an unknown model number on the bus: one failure kind through the bridge's
  read-fault path, never an exception.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import dynamixel_sdk as sdk
import numpy as np
import pytest

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import FAILURE_NAMES, DynamixelBackend, choose_transfers
from cochlea.dynamixel.budget import bus_budget
from cochlea.dynamixel.control_table import INSTRUCTION_ERROR, MODELS, Item
from cochlea.dynamixel.emulator import Faults, VirtualChain
from cochlea.runtime.backend import BackendError

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "models" / "examples"


@pytest.fixture(autouse=True)
def no_gc():
    """The emulator is a thread of this process: a full collection can stall it (as in
    test_dynamixel_bridge.py)."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


class CapturePort:
    """Enough of the SDK's PortHandler to capture what it sends and to feed it replies."""

    def __init__(self, reply: bytes = b""):
        self.sent: list[bytes] = []
        self.reply = bytearray(reply)
        self.is_using = False

    def clearPort(self):
        pass

    def writePort(self, packet):
        self.sent.append(bytes(packet))
        return len(packet)

    def readPort(self, length):
        out = bytes(self.reply[:length])
        del self.reply[:length]
        return out

    def setPacketTimeout(self, packet_length):
        pass

    def setPacketTimeoutMillis(self, msec):
        pass

    def isPacketTimeout(self):
        return True

    def getBaudRate(self):
        return 4_000_000


PH = sdk.PacketHandler(2.0)


# ---- frames against the SDK ------------------------------------------------------------------

def test_the_sdk_has_the_instructions_used_as_oracle():
    assert hasattr(sdk.GroupSyncRead, "fastSyncRead") and hasattr(sdk, "GroupBulkRead")
    assert hasattr(sdk, "GroupBulkWrite")


@pytest.mark.parametrize("address,length,ids", [(132, 4, [1, 2]), (120, 16, [1, 2, 3, 4, 5, 6]),
                                                (126, 10, [7, 3, 200])])
def test_fast_sync_read_request_matches_the_sdk(address, length, ids):
    port = CapturePort()
    group = sdk.GroupSyncRead(port, PH, address, length)
    for i in ids:
        assert group.addParam(i)
    assert group.fastSyncReadTxPacket() == sdk.COMM_SUCCESS
    assert port.sent == [proto.fast_sync_read(address, length, ids)]
    assert proto.fast_sync_read(address, length, ids)[7] == 0x8A


def test_bulk_read_and_bulk_write_match_the_sdk():
    port = CapturePort()
    group = sdk.GroupBulkRead(port, PH)
    reads = [(1, 144, 2), (2, 146, 1), (9, 120, 16)]
    for r in reads:
        assert group.addParam(*r)
    assert group.txPacket() == sdk.COMM_SUCCESS
    assert port.sent == [proto.bulk_read(reads)]
    # The e-Manual's BULK_READ example: ID 1 Present Voltage (144, 2), ID 2 Temperature (146, 1).
    assert proto.bulk_read(reads[:2]).hex() == "fffffd00fe0d0092019000020002920001001a05"
    port = CapturePort()
    group = sdk.GroupBulkWrite(port, PH)
    writes = [(1, 102, b"\x10\x00"), (2, 102, b"\xf0\xff"), (3, 64, b"\x01")]
    for motor_id, address, data in writes:
        assert group.addParam(motor_id, address, len(data), list(data))
    assert group.txPacket() == sdk.COMM_SUCCESS
    assert port.sent == [proto.bulk_write(writes)]
    # The e-Manual's BULK_WRITE example (Max Voltage Limit 160 on ID 1, Temperature Limit 80).
    assert proto.bulk_write([(1, 32, b"\xa0\x00"), (2, 31, b"\x50")]).hex() == \
        "fffffd00fe1000930120000200a000021f00010050b768"
    # The buffer rebuilt in place each period gives the same frame.
    frame, starts = proto.bulk_write_buffer([(1, 102, 2), (2, 102, 2)])
    frame.params[starts[0]:starts[0] + 2] = b"\x10\x00"
    frame.params[starts[1]:starts[1] + 2] = b"\xf0\xff"
    n = frame.encode()
    assert bytes(frame.out[:n]) == proto.bulk_write(writes[:2])


@pytest.mark.parametrize("length", [1, 4, 10, 16])
def test_the_combined_status_packet_is_read_by_the_sdk(length):
    """One header (ID 0xFE, 0x55), per motor ERR ID DATA CRC, the last motor's CRC the
    packet's, LEN from the instruction to it: the SDK's GroupSyncRead.fastSyncRead parses our
    packet into each motor's data (and our parser and check agree)."""
    rng = np.random.default_rng(length)
    ids = [3, 7, 1, 12]
    data = {i: bytes(rng.integers(0, 0xFC, length, dtype=np.uint8)) for i in ids}
    packet = proto.fast_sync_status([(i, 0, data[i]) for i in ids])
    assert packet[:5] == b"\xff\xff\xfd\x00\xfe" and packet[7] == 0x55
    assert int.from_bytes(packet[5:7], "little") == 1 + len(ids) * (length + 4)
    assert len(packet) == 8 + len(ids) * (length + 4)
    port = CapturePort(packet)
    group = sdk.GroupSyncRead(port, PH, 132, length)
    for i in ids:
        group.addParam(i)
    assert group.fastSyncRead() == sdk.COMM_SUCCESS
    for i in ids:
        assert bytes(group.data_dict[i]) == data[i]
    parser = proto.PacketParser(status=True)
    parser.feed(packet)
    assert parser.parse() == proto.OK and parser.id == proto.BROADCAST_ID
    assert proto.check_fast_sync(parser, ids, length) == (0, -1)
    for k, i in enumerate(ids):
        at = proto.fast_block(parser, k, length)
        assert parser.buf[at + 1] == i and bytes(parser.buf[at + 2:at + 2 + length]) == data[i]


def test_the_combined_packet_checks_find_each_bad_block():
    ids, length = [1, 2, 3], 4
    good = proto.fast_sync_status([(i, 0, bytes([i] * length)) for i in ids])

    def check(packet, asked=ids):
        parser = proto.PacketParser(status=True)
        parser.feed(packet)
        code = parser.parse()
        return code, (proto.check_fast_sync(parser, asked, length) if code == proto.OK else None)

    assert check(good) == (proto.OK, (0, -1))
    # A motor missing (the packet of the others): the first one not there.
    assert check(proto.fast_sync_status([(1, 0, b"\1" * 4), (3, 0, b"\3" * 4)])) == \
        (proto.OK, (proto.FAST_WRONG_ID, 1))
    assert check(proto.fast_sync_status([(1, 0, b"\1" * 4), (2, 0, b"\2" * 4)])) == \
        (proto.OK, (proto.FAST_MISSING, 2))
    # A middle CRC corrupted on the wire: the packet's CRC fails.
    bad = bytearray(good)
    bad[8 + (length + 4) - 2] ^= 0xFF
    assert check(bytes(bad))[0] == proto.CRC_FAILURE
    # A motor whose own running CRC is wrong, the packet's CRC right: that motor.
    bad = bytearray(good)
    bad[8 + 2 * (length + 4) - 2] ^= 0x5A
    crc = proto.crc16(bad, 0, len(bad) - 2)
    bad[-2:] = bytes([crc & 0xFF, crc >> 8])
    assert check(bytes(bad)) == (proto.OK, (proto.FAST_BLOCK_CRC, 1))
    # More motors than asked, or a length that is no whole number of blocks: refused.
    assert check(good, [1, 2])[1][0] == proto.FAST_WRONG_ID


# ---- the choice from the data, the budget -------------------------------------------------------

def _moved(spec, name, shift):
    items = tuple(dataclasses.replace(it, address=it.address + shift)
                  if it.name in name else it for it in spec.items)
    return dataclasses.replace(spec, name=spec.name + "*", items=items)


def test_the_transfers_are_chosen_from_the_data():
    x430, x540, mx64 = MODELS["XM430-W350"], MODELS["XM540-W270"], MODELS["MX-64"]
    read, write, why = choose_transfers([x430, x540, mx64])
    assert (read, write) == ("sync", "sync") and "MX-64 without FAST_SYNC_READ" in why
    # The X series answers it (its data: the DynamixelSDK's example); MX(2.0) does not.
    read, write, why = choose_transfers([x430, x540])
    assert (read, write) == ("fast", "sync") and why == "every model answers FAST_SYNC_READ " \
        "(its data)"
    # Unsourced support is not assumed.
    unsure = dataclasses.replace(x430, name="XM430-W350?", fast_sync_read=None)
    read, _, why = choose_transfers([unsure, x540])
    assert read == "sync" and why == "SYNC_READ (XM430-W350?: FAST_SYNC_READ support not sourced)"
    fast = [x430, x540]
    assert choose_transfers(fast + [mx64])[0] == "sync"
    # The state items of one model elsewhere (the whole block moved): BULK_READ.
    state = ("Present Current", "Present Velocity", "Present Position")
    assert choose_transfers(fast + [_moved(x430, state, 256)])[:2] == ("bulk", "sync")
    # Goal Current elsewhere: BULK_WRITE.
    assert choose_transfers([x430, _moved(x430, ("Goal Current",), 256)])[1] == "bulk"
    # The items placed differently within the block: no single layout reads them.
    with pytest.raises(BackendError, match="differently within the block"):
        choose_transfers([x430, _moved(x430, ("Present Position",), 4)])
    # A model without the items (the XL-320's table): refused in one line.
    with pytest.raises(BackendError, match="has no"):
        choose_transfers([x430, MODELS["XL-320"]] if "XL-320" in MODELS else
                         [x430, dataclasses.replace(x430, items=(Item("ID", 7, 1, True, 1),))])


def test_the_budget_counts_the_transfers_sent():
    sync = bus_budget(6, 4_000_000, read_length=16)
    fast = bus_budget(6, 4_000_000, read_length=16, read_instruction="fast")
    bulk = bus_budget(6, 4_000_000, read_length=16, read_instruction="bulk",
                      write_instruction="bulk")
    assert sync.total_bytes == 32 + 20 + 6 * 27 == 214
    assert fast.total_bytes == 32 + 20 + (8 + 6 * 20) == 180
    assert bulk.total_bytes == (10 + 6 * 7) + (10 + 6 * 5) + 6 * 27 == 254
    assert fast.waits_s == pytest.approx(sync.waits_s / 6)
    assert "FAST_SYNC_READ" in fast.describe() and "BULK_WRITE" in bulk.describe()
    with pytest.raises(ValueError):
        bus_budget(6, 4_000_000, read_instruction="fastest")


# ---- the bridge over the emulator ---------------------------------------------------------------

def connect(chain: VirtualChain, **options) -> DynamixelBackend:
    options.setdefault("timeout_s", 0.05)
    return DynamixelBackend(chain.robot, chain.path, description=chain.scenario.description,
                            **options)


def mostly(oks: list[bool]) -> bool:
    """All periods good but a couple (the emulator is a thread of this process, on a shared
    machine: a read can miss its 50 ms now and then; the fault tests count failures)."""
    return sum(oks) >= len(oks) - 2


def read_state(backend: DynamixelBackend, x: np.ndarray) -> bool:
    return any(backend.read(x) for _ in range(3))


def exchange(backend: DynamixelBackend, periods: int, tau: float = 0.01) -> list[bool]:
    x, oks = np.zeros(2 * backend.nq), []
    for _ in range(periods):
        oks.append(backend.read(x))
        backend.write(np.full(backend.nq, tau))
        time.sleep(0.002)
    return oks


@pytest.mark.parametrize("read,write,fast", [("auto", "auto", None), ("fast", "auto", True),
                                             ("bulk", "bulk", None)])
def test_each_transfer_reads_and_writes_the_chain(read, write, fast):
    """The same state and commands whichever transfer carries them: positions match the
    emulator's motors, each Goal Current written lands in the motor's register."""
    chain = VirtualChain("serial")
    chain.fast_sync_read = fast
    with chain:
        backend = connect(chain, read_instruction=read, write_instruction=write)
        backend.enable()
        try:
            # Zero commands: the torque stays off, the joints hold: the state read is the
            # emulator's, to an encoder count.
            assert mostly(exchange(backend, 10, 0.0))
            x = np.zeros(12)
            assert read_state(backend, x)
            assert np.allclose(x[:6], chain.joint_state()[:6], atol=2 * np.abs(
                backend.position_quantum()).max())
            assert mostly(exchange(backend, 30))
            summary = backend.summary()["bus_budget"]
            expect = {"auto": "SYNC_READ", "fast": "FAST_SYNC_READ", "bulk": "BULK_READ"}[read]
            assert summary["read_instruction"] == expect
            assert summary["write_instruction"] == ("BULK_WRITE" if write == "bulk"
                                                    else "SYNC_WRITE")
            kind = "bulk-write" if write == "bulk" else "sync-write"
            goals = {e[2]: e[4] for e in chain.events if e[1] == kind and e[3] == 102}
            assert set(goals) == set(backend.ids)
            for m in chain.motors:
                assert int.from_bytes(m.table[102:104], "little", signed=True) == \
                    int(backend.goal_current_lsb[backend.ids.index(m.id)])
            asked = {"auto": "sync-read", "fast": "fast-sync-read", "bulk": "bulk-read"}[read]
            assert any(e[1] == asked for e in chain.events)
        finally:
            backend.disable()
        assert "confirmed by all 6" in backend.shutdown_report


def test_the_sdk_reads_the_emulator_with_fast_sync_and_bulk_read():
    """The SDK as an independent client: GroupSyncRead.fastSyncRead and GroupBulkRead give
    the emulator's registers; a model without FAST_SYNC_READ (the MX-64's data) answers an
    Instruction Error instead."""
    chain = VirtualChain("serial")
    chain.fast_sync_read = True
    with chain:
        port = sdk.PortHandler(chain.path)
        assert port.openPort() and port.setBaudRate(4_000_000)
        try:
            ids = [m.id for m in chain.motors]
            group = sdk.GroupSyncRead(port, PH, 132, 4)
            for i in ids:
                group.addParam(i)
            assert group.fastSyncRead() == sdk.COMM_SUCCESS
            for m in chain.motors:
                assert group.getData(m.id, 132, 4) == int.from_bytes(m.table[132:136], "little")
            bulk = sdk.GroupBulkRead(port, PH)
            for m in chain.motors:
                bulk.addParam(m.id, 7, 1)  # its ID register
            assert bulk.txRxPacket() == sdk.COMM_SUCCESS
            assert [bulk.getData(i, 7, 1) for i in ids] == ids
            chain.fast_sync_read = None  # the data: MX-64, no FAST_SYNC_READ
            port.clearPort()
            assert PH.syncReadTx(port, 132, 4, ids, len(ids), True) == sdk.COMM_SUCCESS
            packet, result = PH.rxPacket(port, False)
            assert result == sdk.COMM_SUCCESS and packet[8] == INSTRUCTION_ERROR
        finally:
            port.closePort()
    assert any(e[1] == "refused" and "FAST_SYNC_READ" in str(e[4]) for e in chain.events)


def _fails(backend: DynamixelBackend, periods: int = 40) -> tuple[list[bool], str]:
    oks = exchange(backend, periods)
    return oks, backend.describe_last_failure()


@pytest.mark.parametrize("faults,kind,motor", [
    # a motor missing from the packet
    (Faults(drop=1.0, ids=frozenset({3}), delay_s=0.05), "length", 3),
    # a block's CRC corrupted on the wire (the packet's CRC fails: the motor is unknown)
    (Faults(crc=1.0, ids=frozenset({2}), delay_s=0.05), "crc", -1),
    # the last block's CRC: the packet's own
    (Faults(crc=1.0, ids=frozenset({6}), delay_s=0.05), "crc", -1),
])
@pytest.mark.slow
def test_a_bad_fast_sync_reply_is_a_failed_read(faults, kind, motor):
    """Each bad reply fails the period (False, a failure kind and the motor where known),
    through the same counters the SYNC_READ faults use; no exception reaches the loop."""
    chain = VirtualChain("serial", faults=faults)
    chain.fast_sync_read = True
    with chain:
        backend = connect(chain, read_instruction="fast")
        backend.enable()
        try:
            oks, last = _fails(backend)
        finally:
            backend.disable()
    # The faults start 50 ms after the torque came on (its confirmations must get through).
    assert oks[0] and not any(oks[-10:])
    assert backend.failures[FAILURE_NAMES.index(kind)] >= 5
    assert backend.failures[FAILURE_NAMES.index("internal")] == 0
    assert last.startswith(kind) and (motor < 0 or f"ID {motor}" in last)


@pytest.mark.slow
def test_a_wrong_running_crc_names_its_motor(monkeypatch):
    """A motor that appends a wrong CRC after its block while the packet's own CRC is right:
    the read fails as ``crc`` naming that motor."""
    original = proto.fast_sync_status

    def bad(blocks):
        packet = bytearray(original(blocks))
        length = len(blocks[0][2])
        if len(blocks) > 2:
            packet[8 + 2 * (length + 4) - 2] ^= 0x5A  # motor 2's (index 1) running CRC
            crc = proto.crc16(packet, 0, len(packet) - 2)
            packet[-2:] = bytes([crc & 0xFF, crc >> 8])
        return bytes(packet)

    chain = VirtualChain("serial")
    chain.fast_sync_read = True
    with chain:
        backend = connect(chain, read_instruction="fast")
        monkeypatch.setattr(proto, "fast_sync_status", bad)
        try:
            with pytest.raises(BackendError, match=r"no good FAST_SYNC_READ .*crc \(ID 2"):
                backend.enable()
        finally:
            backend.disable()


@pytest.mark.slow
def test_fast_sync_read_on_a_model_without_it_stops_the_start_up():
    chain = VirtualChain("serial")  # MX-64s: the data says no FAST_SYNC_READ
    with chain:
        backend = connect(chain, read_instruction="fast")
        with pytest.raises(BackendError) as info:
            backend.enable()
    message = str(info.value)
    assert "\n" not in message and "FAST_SYNC_READ" in message and "error-byte" in message
    assert message.endswith("cochlea-run --read-instruction sync reads with SYNC_READ")
    assert "torque off confirmed by all 6" in backend.shutdown_report


def test_an_unknown_model_number_stops_the_start_up():
    with VirtualChain("serial", faults=Faults(model_number={4: 9999})) as chain:
        backend = connect(chain)
        with pytest.raises(BackendError) as info:
            backend.enable()
    message = str(info.value)
    assert "\n" not in message and "ID 4" in message and "model number 9999" in message
    assert backend.shutdown_report != "not started"


# ---- chains of each family and a mixed one: cochlea-dxl scan and cochlea-run ----------------

#: XL330-M288: 0.52 N m stall at 1.47 A (5 V, its e-Manual): a placeholder fit of 35.4 N cm/A
#: and a torque limit inside its reach.
XL330_FIT = ('fit = { a = 35.374, b = 0.0, x = "current_A", y = "torque_Ncm", '
             'source = "placeholder" }')


def chain_files(tmp_path: Path, models: list[str]) -> Path:
    """The planar2 example (models/examples) with the motors ``models`` (joint order): its
    scenario, in ``tmp_path``."""
    text = (EXAMPLES / "planar2_xm540.toml").read_text()
    parts = re.split(r'(model = "XM540-W270")', text)
    out, k = [], 0
    for part in parts:
        if part == 'model = "XM540-W270"':
            out.append(f'model = "{models[k]}"')
            k += 1
        else:
            out.append(part)
    text = "".join(out)
    assert k == len(models)
    if "XL330-M288" in models:  # both joints then (the fit line follows the model line)
        text = re.sub(r"fit = \{ a = 240\.909[^\n]*", XL330_FIT, text)
        text = text.replace("torque_limit_Nm = 5.0", "torque_limit_Nm = 0.25")
    (tmp_path / "planar2_xm540.toml").write_text(text)
    scenario = tmp_path / "scenario.toml"
    scenario.write_text((EXAMPLES / "planar2_xm540_joint.toml").read_text()
                        .replace("duration_s = 20.0", "duration_s = 1.0"))
    return scenario


CHAINS = {"xm430": ["XM430-W350", "XM430-W350"], "xl330": ["XL330-M288", "XL330-M288"],
          "mixed": ["XM540-W270", "XM430-W350"], "mixed-mx": ["XM540-W270", "MX-64"]}


@pytest.mark.parametrize("name", list(CHAINS))
@pytest.mark.slow
def test_each_chain_over_the_emulator(tmp_path, name):
    """Each family and the mixed chains: the bridge chooses FAST_SYNC_READ where every model
    answers it (the X series), SYNC_READ with an MX-64 on the bus, SYNC_WRITE (one layout),
    and reads the state right."""
    scenario = chain_files(tmp_path, CHAINS[name])
    with VirtualChain("serial", scenario) as chain:
        assert [m.spec.name for m in chain.motors] == CHAINS[name]
        backend = connect(chain)
        backend.enable()
        try:
            assert mostly(exchange(backend, 10, 0.0))  # torque off: the joints hold
            x = np.zeros(4)
            assert read_state(backend, x)
            assert np.allclose(x[:2], chain.joint_state()[:2],
                               atol=2 * np.abs(backend.position_quantum()).max())
            assert mostly(exchange(backend, 20, 0.001))
        finally:
            backend.disable()
    summary = backend.summary()["bus_budget"]
    assert summary["read_instruction"] == ("SYNC_READ" if "MX-64" in CHAINS[name]
                                           else "FAST_SYNC_READ")
    assert summary["write_instruction"] == "SYNC_WRITE"
    assert set(backend.firmware) == set(backend.ids)  # from each motor's PING


def _emulator(scenario: Path, log: Path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot", "serial", "--scenario",
         str(scenario), "--log", str(log)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    path = proc.stdout.readline().strip()
    assert path.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else path
    return proc, path


@pytest.mark.parametrize("name", ["xm430", "mixed"])
@pytest.mark.slow
def test_scan_and_run_over_the_virtual_chain(tmp_path, name):
    """``cochlea-dxl scan`` finds each model of the chain; a short ``cochlea-run --backend
    dynamixel`` over it completes with the read instruction in its summary."""
    scenario = chain_files(tmp_path, CHAINS[name])
    proc, port = _emulator(scenario, tmp_path / "emu.log")
    try:
        scan = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_dxl", "scan",
                               "--port", port, "--baud", "4000000"],
                              capture_output=True, text=True, timeout=120, cwd=tmp_path)
        assert scan.returncode == 0, scan.stderr
        for model in set(CHAINS[name]):
            assert model in scan.stdout, scan.stdout
        out = tmp_path / "run"
        done = subprocess.run(
            [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
             "joint", "--scenario", str(scenario), "--backend", "dynamixel", "--port", port,
             "--out", str(out), "--watchdog-misses", "300"],
            capture_output=True, text=True, timeout=180, cwd=tmp_path)
        forced = subprocess.run(  # a firmware without FAST_SYNC_READ: the user's way back
            [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
             "joint", "--scenario", str(scenario), "--backend", "dynamixel", "--port", port,
             "--out", str(tmp_path / "forced"), "--watchdog-misses", "300", "--duration",
             "0.3", "--read-instruction", "sync"],
            capture_output=True, text=True, timeout=180, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 0, done.stderr
    assert "cochlea-run: bus: FAST_SYNC_READ + SYNC_WRITE per period" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    bus = summary["timing"]["bus"]["bus_budget"]
    # The budget of what is sent: SYNC_WRITE, FAST_SYNC_READ of 120..135, one status packet:
    # its 8-byte header (to the instruction), then per motor its error, ID, 16 data bytes and
    # CRC (the last CRC the packet's).
    assert bus["bytes_per_period"] == (14 + 2 * 3) + (14 + 2) + 8 + 2 * (1 + 1 + 16 + 2)
    assert bus["read_instruction"] == "FAST_SYNC_READ"
    assert bus["read_choice"] == "every model answers FAST_SYNC_READ (its data)"
    assert forced.returncode == 0, forced.stderr
    bus = json.loads((tmp_path / "forced" / "summary.json").read_text()
                     )["timing"]["bus"]["bus_budget"]
    assert bus["read_instruction"] == "SYNC_READ" and bus["bytes_per_period"] == 90
    assert bus["read_choice"].startswith("SYNC_READ (asked; the data: ")


class _FixedReply:
    """A port that accepts every write and answers every read with one prebuilt reply."""

    low_latency = None

    def __init__(self, reply: bytes):
        self.view = memoryview(reply)

    def write(self, view, n, deadline):
        return True

    def read_into(self, target, deadline):
        target[:len(self.view)] = self.view
        return len(self.view)

    def discard_input(self):
        pass

    def close(self):
        pass


@pytest.mark.parametrize("read,write", [("fast", "sync"), ("bulk", "bulk")])
@pytest.mark.slow
def test_the_fast_and_bulk_periods_allocate_nothing_and_convert_right(read, write):
    """The FAST_SYNC_READ / BULK_WRITE periods make no buffer, list or array (as the
    SYNC_READ one, tests/test_dynamixel_drives.py), and convert the registers as it does."""
    from tests.conftest import assert_periods_allocate_nothing

    backend = DynamixelBackend("serial", "/dev/scripted", read_instruction=read,
                               write_instruction=write)
    rng = np.random.default_rng(5)
    regs = {i: (int(rng.integers(-2000, 2000)), int(rng.integers(-500, 500)),
                int(rng.integers(-10**6, 10**6))) for i in backend.ids}
    data = {i: proto.le(c, 2) + proto.le(v, 4) + proto.le(p, 4) for i, (c, v, p) in regs.items()}
    reply = (proto.fast_sync_status([(i, 0, data[i]) for i in backend.ids]) if read == "fast"
             else b"".join(proto.status(i, 0, data[i]) for i in backend.ids))
    backend._port, backend._active = _FixedReply(reply), True
    x = np.zeros(12)
    assert backend.read(x)
    for j, d in enumerate(backend.drives):
        c, v, p = regs[d.id]
        assert x[j] == pytest.approx(float(d.q(p)))
        assert x[6 + j] == pytest.approx(float(d.qd(v)))
    tau = rng.uniform(-0.1, 0.1, 6)
    assert backend.write(tau)
    assert list(backend.goal_current_lsb) == [d.goal_current_lsb(t)
                                              for d, t in zip(backend.drives, tau)]
    assert_periods_allocate_nothing(backend, x, tau)
    backend._active, backend._port = False, None


@pytest.mark.slow
def test_an_unknown_model_number_through_scan_and_run(tmp_path):
    """``cochlea-dxl scan`` lists the motor as unknown, ``cochlea-run`` stops before anything
    moves with one line (exit 5) and writes nothing."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot", "serial",
         "--model-number", "2:9999", "--log", str(tmp_path / "emu.log")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        scan = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_dxl", "scan",
                               "--port", port, "--baud", "4000000", "--ids", "0-8"],
                              capture_output=True, text=True, timeout=120, cwd=tmp_path)
        out = tmp_path / "run"
        done = subprocess.run(
            [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
             "joint", "--backend", "dynamixel", "--port", port, "--duration", "0.5",
             "--out", str(out)], capture_output=True, text=True, timeout=180, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert scan.returncode == 0 and "unknown (9999)" in scan.stdout, scan.stdout + scan.stderr
    assert done.returncode == 5, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert "nothing moved" in lines[0] and "ID 2" in lines[0] and "9999" in lines[0]
    assert not out.exists()
