"""The virtual chain on a socket (issue 30, item 2): ``cochlea-emulator --listen unix:PATH`` or
``socket://HOST:PORT`` answers with the very bytes it sends on its pseudo-terminal, at their
wire time; the bridges (``--port unix:PATH``: the Python bridge's SocketPort, the C program's
POSIX port) reach it there; a bridge that goes away leaves the chain listening for the next,
and every address that cannot be read, bound or reached is one line, never a traceback."""

from __future__ import annotations

import gc
import json
import os
import resource
import select
import socket
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.emulator import VirtualChain
from cochlea.dynamixel.emulator import main as emulator_main
from cochlea.dynamixel.port import SocketPort, is_socket_address, open_port, socket_address
from cochlea.errors import EXIT_USER_ERROR
from cochlea.runtime.backend import BackendError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def no_gc():
    """The chain runs in a thread of this process: no collection of the test process stalls
    it (as in test_dynamixel_bridge)."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


def take(read, n: int, fd: int) -> bytes:
    got = b""
    while len(got) < n and select.select([fd], [], [], 5.0)[0]:
        chunk = read()
        if not chunk:
            break
        got += chunk
    return got


def connected(address: str) -> socket.socket:
    family, where = socket_address(address)
    s = socket.socket(family, socket.SOCK_STREAM)
    s.settimeout(5)
    s.connect(where)
    return s


# Requests whose replies do not depend on the time: the torque is off, so the joints hold.
REQUESTS = [
    proto.ping(1),
    proto.read(3, 0, 2),  # Model Number
    proto.read(2, 132, 4),  # Present Position
    proto.write(4, 11, bytes([9])),  # an Operating Mode the motor does not have: Data Range
    proto.sync_read(132, 4, [1, 2, 3, 4, 5, 6]),
    proto.write(5, 64, bytes([1])),  # Torque Enable 1
    proto.write(5, 64, bytes([0])),
    proto.read(6, 1000, 4),  # past the table: an error status
    proto.ping(1)[:-1] + bytes([proto.ping(1)[-1] ^ 0xFF]),  # a bad CRC: a CRC error status
]


def replies_over(chain: VirtualChain, write, read, fd: int) -> list[bytes]:
    out = []
    for frame in REQUESTS:
        write(frame)
        time.sleep(0.02)  # every reply of this request is in
        got = b""
        while select.select([fd], [], [], 0.2)[0]:
            chunk = read()
            if not chunk:
                break
            got += chunk
        out.append(got)
    return out


@pytest.mark.hil
@pytest.mark.parametrize("listen", ["unix:{tmp}/chain.sock", "socket://127.0.0.1:0"])
def test_the_socket_carries_the_pseudo_terminals_bytes(tmp_path, listen):
    """The same requests get byte for byte the same replies on the pseudo-terminal and on the
    socket (errors and a corrupted instruction's CRC error status included)."""
    with VirtualChain("serial", "serial_joint") as pty_chain:
        fd = os.open(pty_chain.path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        try:
            on_pty = replies_over(pty_chain, lambda b: os.write(fd, b),
                                  lambda: os.read(fd, 4096), fd)
        finally:
            os.close(fd)
    with VirtualChain("serial", "serial_joint", listen=listen.format(tmp=tmp_path)) as chain:
        if listen.startswith("unix:"):
            assert chain.path == f"unix:{tmp_path}/chain.sock"
        else:  # the port the system chose
            assert chain.path.startswith("socket://127.0.0.1:") and int(chain.path[20:]) > 0
        with connected(chain.path) as s:
            on_socket = replies_over(chain, s.sendall, lambda: s.recv(4096), s.fileno())
    assert all(on_pty) and on_socket == on_pty
    assert not (tmp_path / "chain.sock").exists()  # the chain removes the socket it made


@pytest.mark.hil
def test_wire_timed_replies_over_a_socket_are_not_early(tmp_path):
    """The emulator still holds each reply for its wire time at --baud: 57600 baud, the
    SYNC_READ and six replies (182 bytes) take 31.6 ms from the request's write."""
    chain = VirtualChain("serial", "serial_joint", wire_timing=True, baud=57600,
                         listen=f"unix:{tmp_path}/c.sock")
    ids = [m.id for m in chain.motors]
    request = proto.sync_read(132, 4, ids)
    wire_s = (len(request) + 6 * 15) * 10 / 57600
    with chain, connected(chain.path) as s:
        for _ in range(3):
            t = time.perf_counter()
            s.sendall(request)
            assert len(take(lambda: s.recv(4096), 6 * 15, s.fileno())) == 6 * 15
            assert time.perf_counter() - t >= wire_s


@pytest.mark.hil
def test_a_bridge_that_goes_away_leaves_the_chain_listening(tmp_path):
    """A client that disconnects mid-frame: the chain drops the half instruction and serves
    the next client (as a new host on the line), and does not spin on the closed socket
    meanwhile (its thread is this process's only busy one)."""
    with VirtualChain("serial", "serial_joint", listen=f"unix:{tmp_path}/c.sock") as chain:
        with connected(chain.path) as s:
            s.sendall(proto.ping(1))
            assert take(lambda: s.recv(4096), 14, s.fileno()) == proto.status(
                1, 0, bytes(chain.by_id[1].table[i] for i in (0, 1, 6)))
            s.sendall(proto.sync_read(132, 4, [1, 2, 3])[:9])  # half a frame, then gone
        time.sleep(0.1)
        assert chain.master == -1
        cpu, wall = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        time.sleep(0.5)
        used = resource.getrusage(resource.RUSAGE_SELF)
        busy = (used.ru_utime + used.ru_stime - cpu.ru_utime - cpu.ru_stime) / \
            (time.perf_counter() - wall)
        assert busy < 0.3, f"the chain used {busy:.0%} of a core with nobody connected"
        with connected(chain.path) as s:
            s.sendall(proto.ping(2))
            assert take(lambda: s.recv(4096), 14, s.fileno()) == proto.status(
                2, 0, bytes(chain.by_id[2].table[i] for i in (0, 1, 6)))
        assert chain._thread is not None and chain._thread.is_alive()
        assert chain.counts["bad_instructions"] == 0  # the half frame was not parsed


@pytest.mark.hil
@pytest.mark.parametrize("robot", ["serial", "parallel"])
def test_the_python_bridge_runs_over_the_socket(tmp_path, robot):
    """The bridge's port for ``unix:PATH`` is a SocketPort: its start-up, reads and writes, and
    its shut-down on the virtual chain; no adapter latency in its budget; the slider's homing
    not asked of the virtual chain (as on its pseudo-terminal)."""
    with VirtualChain(robot, f"{robot}_joint", listen=f"unix:{tmp_path}/c.sock") as chain:
        backend = DynamixelBackend(robot, chain.path, description=chain.scenario.description,
                                   timeout_s=0.05)
        assert backend.budget.cycle_s == backend.budget.bus_s
        backend.enable()
        try:
            assert isinstance(backend._port, SocketPort)
            x = np.zeros(2 * backend.nq)
            good = sum(backend.read(x) and backend.write(np.zeros(backend.nq))
                       for _ in range(50))
            assert good >= 45, backend.summary()
            assert np.isfinite(x).all()
            assert chain.counts["instructions"] > 100  # a SYNC_READ and a SYNC_WRITE each
        finally:
            backend.disable()
        assert backend.shutdown_report is not None
        assert all(m.table[64] == 0 for m in chain.motors)  # torque off on every motor
    assert backend.homing_report == ("no slider" if robot == "serial" else
                                     "not checked (a socket: the virtual chain)")


@pytest.mark.hil
def test_bring_up_talks_to_the_chain_over_its_socket(tmp_path):
    """cochlea-dxl's bus (scan, configure, calibrate, home) opens the emulator's socket as the
    bridge does: a PING of every motor answers; with nothing listening there, one line naming
    the socket, not a serial port."""
    from cochlea.dynamixel.bringup.common import Bus, BusError

    with VirtualChain("serial", "serial_joint", listen=f"unix:{tmp_path}/c.sock") as chain:
        with Bus(chain.path, 4_000_000) as bus:
            for motor in chain.motors:
                assert bus.ping(motor.drive.id)[0] == motor.spec.number
    with pytest.raises(BusError) as caught:
        Bus(f"unix:{tmp_path}/c.sock", 4_000_000)
    message = str(caught.value)
    assert "expected the emulator's socket" in message and "\n" not in message


def test_a_socket_port_sees_its_emulator_go_away(tmp_path):
    """discard_input drops what is waiting; after the other end closes, a read is -1 (a port
    error: the loop's read failures and its safe stop follow), never an exception."""
    where = str(tmp_path / "s.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(where)
    server.listen(1)
    port = open_port(f"unix:{where}", 4_000_000)
    try:
        assert isinstance(port, SocketPort) and port.latency_timer_ms is None
        peer, _ = server.accept()
        peer.sendall(b"stale")
        time.sleep(0.05)
        assert port.discard_input()
        buf = bytearray(64)
        assert port.read_into(memoryview(buf), time.perf_counter() + 0.02) == 0
        peer.sendall(b"abc")
        assert port.read_into(memoryview(buf), time.perf_counter() + 1.0) == 3
        assert bytes(buf[:3]) == b"abc"
        assert port.write(memoryview(b"xyz"), 3, time.perf_counter() + 1.0)
        assert peer.recv(16) == b"xyz"
        peer.close()
        assert port.read_into(memoryview(buf), time.perf_counter() + 1.0) == -1
        assert not port.write(memoryview(b"x" * 4096), 4096, time.perf_counter() + 0.1) or \
            not port.write(memoryview(b"x" * 4096), 4096, time.perf_counter() + 0.1)
    finally:
        port.close()
        server.close()
    assert port.closed


def test_a_device_path_is_never_a_socket():
    """The real motors' path is untouched: anything but unix: / socket:// opens the serial
    device (here one that does not exist: its own message)."""
    with pytest.raises(BackendError, match="cannot open the serial port /dev/ttyUSB-none"):
        open_port("/dev/ttyUSB-none", 4_000_000)
    assert not any(is_socket_address(p) for p in ("/dev/ttyUSB0", "/dev/pts/3", "COM3",
                                                   "./unix:x", "tcp://127.0.0.1:1"))


@pytest.mark.parametrize("address,expected", [
    ("unix:/nonexistent-folder/c.sock", "cannot connect to unix:/nonexistent-folder/c.sock"),
    ("socket://127.0.0.1:1", "cannot connect to socket://127.0.0.1:1"),
    ("socket://127.0.0.1:0", "expected socket://HOST:PORT, PORT 1..65535"),
    ("socket://127.0.0.1", "expected socket://HOST:PORT"),
    ("unix:", "expected unix:PATH")])
def test_an_address_the_bridge_cannot_reach_is_one_line(address, expected):
    with pytest.raises(BackendError, match="^[^\n]*$") as err:
        open_port(address, 4_000_000)
    assert expected in str(err.value)


def refused(capsys, argv: list[str]) -> str:
    try:
        code = emulator_main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == EXIT_USER_ERROR, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cochlea-emulator: "), err
    return lines[0]


@pytest.mark.parametrize("address", ["unix:", "socket://127.0.0.1", "socket://:80",
                                     "socket://127.0.0.1:70000", "socket://h:x", "tcp:1",
                                     "/tmp/chain.sock"])
def test_a_listen_address_that_cannot_be_read_is_refused_in_one_line(capsys, address):
    line = refused(capsys, ["--robot", "serial", "--listen", address])
    assert "--listen" in line and "expected" in line


def test_check_baud_needs_the_pseudo_terminal(capsys, tmp_path):
    line = refused(capsys, ["--robot", "serial", "--check-baud", "--listen",
                            f"unix:{tmp_path}/c.sock"])
    assert "--check-baud needs the pseudo-terminal" in line
    assert list(tmp_path.iterdir()) == []


def emulator(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                           "serial", "--priority", "normal", *args], capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.hil
def test_an_address_that_cannot_be_bound_is_one_line(tmp_path):
    """A folder that does not exist, a path someone else has: exit 1, one line naming the
    address and why; the file in the way is left as it was."""
    taken = tmp_path / "taken"
    taken.write_text("mine")
    for address, why in [(f"unix:{tmp_path}/no/such/c.sock", "No such file or directory"),
                         (f"unix:{taken}", "Address already in use")]:
        done = emulator("--listen", address, "--duration", "1")
        assert done.returncode == 1 and "Traceback" not in done.stderr
        assert done.stderr.strip().splitlines() == [
            f"cochlea-emulator: cannot open --listen {address}: {why}"], done.stderr
    assert taken.read_text() == "mine"


@pytest.mark.hil
def test_the_command_serves_on_the_socket_and_removes_it(tmp_path):
    """``cochlea-emulator --listen unix:PATH`` prints the address first, serves a PING, and
    leaves no socket file when its --duration ends."""
    address = f"unix:{tmp_path}/c.sock"
    proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                             "serial", "--priority", "normal", "--listen", address,
                             "--duration", "6"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == address
        with connected(address) as s:
            s.sendall(proto.ping(4))
            reply = take(lambda: s.recv(4096), 14, s.fileno())
        assert len(reply) == 14 and reply[4] == 4 and reply[7] == 0x55
    finally:
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "Traceback" not in err, err
    assert not (tmp_path / "c.sock").exists()



@pytest.mark.slow
@pytest.mark.parametrize("address,why", [
    ("unix:/nonexistent-folder/c.sock", "No such file or directory"),
    ("socket://127.0.0.1:1", "Connection refused"),
    ("socket://127.0.0.1", "Invalid argument"),
    ("socket://[::1]:x", "Invalid argument")])
def test_the_c_program_that_cannot_reach_the_socket_says_so_in_one_line(tmp_path, program,
                                                                       address, why):
    out = tmp_path / "run"
    done = subprocess.run([str(program), "--scenario", "serial_joint", "--port", address,
                           "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 5, done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        "cochlea-embedded: the backend could not start, nothing moved: cannot connect to "
        f"the socket {address}: {why}")
    assert "Traceback" not in done.stderr and not out.exists()


@pytest.mark.hil
def test_the_c_program_runs_over_the_socket_and_stops_safely_when_it_goes(tmp_path, program):
    """build/cochlea-embedded --port unix:PATH on the in-process chain: it runs; the chain
    closing its end mid-run ends in the watchdog's safe stop (exit 15, read failures), the
    log complete."""
    chain = VirtualChain("serial", "serial_joint", listen=f"unix:{tmp_path}/c.sock").start()
    out = tmp_path / "run"
    try:
        proc = subprocess.Popen([str(program), "--scenario", "serial_joint", "--port",
                                 chain.path, "--duration", "10", "--out", str(out),
                                 "--watchdog-misses", "300"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        time.sleep(1.5)
        running = proc.poll() is None
        chain.close()  # the emulator goes away: its socket closes under the program
        _, err = proc.communicate(timeout=60)
    finally:
        chain.close()
    assert running, err
    assert proc.returncode == 15 and "stopped by rule watchdog" in err, err
    assert "read failures" in err and "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"]["bus"]["failures"].get("port", 0) > 0, summary["timing"]["bus"]
    assert 200 < summary["periods"] < 10_000


@pytest.mark.hil
def test_the_c_program_does_not_ask_the_virtual_chain_s_slider_for_its_homing(tmp_path, program):
    """--homing auto over the emulator's socket: not checked, as over its pseudo-terminal
    (only cochlea-emulator listens on a socket; a real motor's port is a device)."""
    out = tmp_path / "run"
    with VirtualChain("parallel", "parallel_joint", listen=f"unix:{tmp_path}/c.sock") as chain:
        time.sleep(0.5)
        done = subprocess.run([str(program), "--scenario", "parallel_joint", "--port",
                               chain.path, "--duration", "0.2", "--out", str(out),
                               "--watchdog-misses", "300", "--watchdog-errors", "100"],
                              capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    bus = json.loads((out / "summary.json").read_text())["timing"]["bus"]
    assert bus["homing"] == "not checked (a socket: the virtual chain)"


@pytest.mark.hil
def test_cochlea_run_with_no_emulator_on_the_socket_is_one_line(tmp_path):
    """--port unix:PATH with nothing listening: exit 5 (the backend could not start), one line
    naming the address and the command to start, no output folder left."""
    address = f"unix:{tmp_path}/none.sock"
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial",
                           "--space", "joint", "--backend", "dynamixel", "--port", address,
                           "--duration", "1", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 5, done.stderr
    assert done.stderr.strip().splitlines() == [
        "cochlea-run: the backend could not start, nothing moved: cannot connect to "
        f"{address}: No such file or directory (is cochlea-emulator --listen {address} "
        "running?)"]
    assert not (tmp_path / "run").exists()
