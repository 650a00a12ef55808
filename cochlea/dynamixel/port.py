"""The serial port of the bridge: pyserial opens and configures it (8N1, the baud rate, the
adapter's low-latency mode, an exclusive lock); the per-period reads and writes then go straight
to its file descriptor, into and out of preallocated buffers, with absolute deadlines.

Nothing here raises once the port is open: failures come back as return values.
"""

from __future__ import annotations

import io
import os
import select
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
