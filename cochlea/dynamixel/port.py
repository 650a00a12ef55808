"""The serial port of the bridge: pyserial opens and configures it (8N1, the baud rate, the
adapter's low-latency mode, an exclusive lock); the per-period reads and writes then go straight
to its file descriptor, into and out of preallocated buffers, with absolute deadlines.

The virtual chain (``cochlea-emulator --listen``) may be reached over a socket instead of a
pseudo-terminal: a ``--port`` of ``unix:PATH`` or ``socket://HOST:PORT`` opens a
:class:`SocketPort` (:func:`open_port`), the same bytes on a stream socket. A real motor's port
is a device path and never one of these (a socket has no baud rate and no adapter).

Nothing here raises once the port is open: failures come back as return values.
"""

from __future__ import annotations

import io
import os
import select
import socket
import termios
import time
from pathlib import Path

from ..runtime.backend import BackendError


def latency_timer_ms(path: str) -> int | None:
    """The USB serial adapter's latency timer (ms) from sysfs, or None (not such an adapter)."""
    try:
        name = Path(os.path.realpath(path)).name
        text = Path(f"/sys/bus/usb-serial/devices/{name}/latency_timer").read_text()
        return int(text.strip())
    except (OSError, ValueError):
        return None


class SerialPort:
    def __init__(self, path: str, baud: int):
        import serial  # noqa: PLC0415 (pyserial is a dependency; imported where used)

        self.path = path
        self.baud = baud
        try:
            self.serial = serial.Serial(path, baud, timeout=0, write_timeout=0.1,
                                        exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise BackendError(f"cannot open the serial port {path} at {baud} baud: {exc}") \
                from None
        # FTDI adapters hold received bytes up to their latency timer (16 ms by default);
        # ASYNC_LOW_LATENCY asks the driver for the shortest. Pseudo-terminals refuse it.
        try:
            self.serial.set_low_latency_mode(True)
            self.low_latency = True
        except (OSError, ValueError, AttributeError, NotImplementedError):
            self.low_latency = False
        self.latency_timer_ms = latency_timer_ms(path)
        self.fd = self.serial.fileno()
        self._file = io.FileIO(self.fd, "rb", closefd=False)
        self._rlist = [self.fd]
        self._wlist = [self.fd]
        self.closed = False

    def discard_input(self) -> bool:
        """Drop whatever arrived late (a reply of an earlier transaction)."""
        try:
            termios.tcflush(self.fd, termios.TCIFLUSH)
            return True
        except (OSError, termios.error):
            return False

    def write(self, view: memoryview, n: int, deadline: float) -> bool:
        """Write ``view[:n]`` whole before ``deadline`` (perf_counter seconds)."""
        done = 0
        try:
            while done < n:
                try:
                    done += os.write(self.fd, view[done:n])
                except BlockingIOError:
                    remaining = deadline - time.perf_counter()
                    if remaining <= 0:
                        return False
                    select.select((), self._wlist, (), remaining)
            return True
        except (OSError, ValueError):
            return False

    def read_into(self, view: memoryview, deadline: float) -> int:
        """Wait for bytes until ``deadline`` and read what has arrived into ``view``: the count
        (0 when the deadline passed first, -1 on an error of the port)."""
        try:
            remaining = deadline - time.perf_counter()
            ready, _, _ = select.select(self._rlist, (), (), remaining if remaining > 0 else 0)
            if not ready:
                return 0
            n = self._file.readinto(view)
            if n is None:
                return 0
            return n if n > 0 else -1  # readable with no bytes: the device went away
        except (OSError, ValueError):
            return -1

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.serial.close()
        except Exception:  # noqa: BLE001 (closing must not raise)
            pass


#: How a socket address starts (``--port``, ``cochlea-emulator --listen``): a Unix-domain socket
#: by its path, or TCP as pyserial writes it.
UNIX_PREFIX, TCP_PREFIX = "unix:", "socket://"
#: How long connecting to the emulator's socket may take, seconds (it listens already).
CONNECT_TIMEOUT_S = 2.0


def is_socket_address(path: str) -> bool:
    """Whether ``path`` names the emulator's socket (``unix:PATH``, ``socket://HOST:PORT``)
    rather than a serial device."""
    return str(path).startswith((UNIX_PREFIX, TCP_PREFIX))


def socket_address(text: str, *, listening: bool = False) -> tuple[int, object]:
    """``(family, address)`` of ``unix:PATH`` or ``socket://HOST:PORT``; ValueError with what
    was expected. Port 0 (any free port) only where ``listening``."""
    text = str(text)
    if text.startswith(UNIX_PREFIX):
        path = text[len(UNIX_PREFIX):]
        if not path or "\0" in path:
            raise ValueError(f"{text!r}: expected unix:PATH, a socket's file path")
        return socket.AF_UNIX, path
    if text.startswith(TCP_PREFIX):
        host, sep, port = text[len(TCP_PREFIX):].rpartition(":")
        host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
        try:
            number = int(port)
        except ValueError:
            number = -1
        if not sep or not host or not (0 if listening else 1) <= number <= 65535:
            raise ValueError(f"{text!r}: expected socket://HOST:PORT, PORT "
                             f"{0 if listening else 1}..65535")
        return (socket.AF_INET6 if ":" in host else socket.AF_INET), (host, number)
    raise ValueError(f"{text!r}: expected unix:PATH or socket://HOST:PORT")


class SocketPort(SerialPort):
    """The emulator's socket as the bridge's port: the same per-period calls on a connected
    stream socket (a Unix-domain socket delivers the bytes in the writer's own system call; a
    pseudo-terminal leaves them to the kernel's workers of ordinary priority, which a loaded
    machine delays: docs/dynamixel.md, "Does the virtual chain keep up")."""

    def __init__(self, path: str, baud: int):  # noqa: PLW0231 (no serial device to open)
        self.path = path
        self.baud = baud
        try:
            family, address = socket_address(path)
            sock = socket.socket(family, socket.SOCK_STREAM)
        except (ValueError, OSError) as exc:
            raise BackendError(f"cannot open {path}: {exc}") from None
        try:
            sock.settimeout(CONNECT_TIMEOUT_S)
            sock.connect(address)
            sock.setblocking(False)
            if family != socket.AF_UNIX:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            sock.close()
            reason = exc.strerror or str(exc) or type(exc).__name__
            raise BackendError(f"cannot connect to {path}: {reason} (is cochlea-emulator "
                               f"--listen {path} running?)") from None
        self.serial = sock  # closed by close()
        self.low_latency = False  # no adapter: nothing holds the bytes
        self.latency_timer_ms = None
        self.fd = sock.fileno()
        self._rlist = [self.fd]
        self._wlist = [self.fd]
        self.closed = False

    def discard_input(self) -> bool:
        try:
            while self.serial.recv(4096):
                pass
            return False  # the other end closed
        except BlockingIOError:
            return True
        except (OSError, ValueError):
            return False

    def read_into(self, view: memoryview, deadline: float) -> int:
        try:
            remaining = deadline - time.perf_counter()
            ready, _, _ = select.select(self._rlist, (), (), remaining if remaining > 0 else 0)
            if not ready:
                return 0
            n = self.serial.recv_into(view)
            return n if n > 0 else -1  # readable with no bytes: the emulator went away
        except BlockingIOError:
            return 0
        except (OSError, ValueError):
            return -1


def open_port(path: str, baud: int) -> SerialPort:
    """The bridge's port: :class:`SocketPort` for ``unix:PATH`` / ``socket://HOST:PORT`` (the
    emulator's socket), else the serial device (:class:`SerialPort`)."""
    return SocketPort(path, baud) if is_socket_address(path) else SerialPort(path, baud)
