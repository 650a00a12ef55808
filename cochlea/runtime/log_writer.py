"""The run's log written behind the loop: finished rows of the period buffer appended to
``log.bin`` by a thread of its own, so no period formats or touches the disk.

The buffer may be a ring (row ``k`` in slot ``k % len(buffer)``): the loop publishes how many
rows it has finished (``done_rows``), the writer how many are safely handed to the file
(``written``), and the loop never overwrites a slot the writer has not written. A write that
fails (a full disk, an I/O error) ends the writer with the error kept in ``error`` for the loop
to see; the writer never raises into the loop.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from ..errors import CochleaError

#: An as-fast run waits for a writer that is behind; one that writes nothing for this long
#: (a hung disk) is a log failure there too.
WRITER_STALL_S = 10.0


class LogWriter(threading.Thread):
    """Appends finished rows of the period buffer (a ring) to ``log.bin`` behind the loop."""

    def __init__(self, buffer: np.ndarray, path: Path, interval: float = 0.2):
        super().__init__(name="cochlea-log-writer", daemon=True)
        self.buffer, self.path, self.interval = buffer, path, interval
        self.done_rows = 0  # rows the loop has finished (written by the loop only)
        self.written = 0  # rows handed to the file (written by this thread only)
        self.error: OSError | None = None
        self.finished = threading.Event()
        self._nudge = threading.Event()  # wakes the writer before its interval is up
        # Opened by the caller's thread, before anything moves: a log that cannot even be
        # created is the user's to fix (the folder), not a stop in the middle of a run.
        try:
            self._file = open(path, "wb")
        except OSError as exc:
            raise CochleaError(f"cannot create the log {path}: {exc.strerror or exc}: choose "
                               "a writable --out") from None

    def run(self) -> None:
        try:
            with self._file as f:
                while not self.finished.is_set():
                    self._nudge.wait(self.interval)
                    self._nudge.clear()
                    self._flush(f)
                self._flush(f)
        except OSError as exc:  # the loop sees it at its next period and stops safely
            self.error = exc

    def wait_for(self, rows: int, stall_s: float | None = None) -> bool:
        """Wake the writer and wait until it has written ``rows`` rows (an as-fast run, which
        may outpace a disk: nothing is late there). False if it failed, or made no progress
        for ``stall_s`` seconds (a hung disk; default :data:`WRITER_STALL_S`)."""
        stall_s = WRITER_STALL_S if stall_s is None else stall_s
        last, since = self.written, time.monotonic()
        while self.written < rows:
            if self.error is not None or not self.is_alive():
                return False
            if self.written != last:
                last, since = self.written, time.monotonic()
            elif time.monotonic() - since > stall_s:
                return False
            self._nudge.set()
            time.sleep(1e-4)
        return True

    def _flush(self, f) -> None:
        end = self.done_rows
        ring = len(self.buffer)
        while self.written < end:
            first = self.written % ring
            last = min(first + end - self.written, ring)  # up to the ring's end, then wrap
            self._write(f, self.buffer[first:last])
            self.written += last - first
        f.flush()

    def _write(self, f, rows: np.ndarray) -> None:
        """One contiguous block of rows to the file (raises OSError on a full disk)."""
        f.write(memoryview(rows).cast("B"))

    def close(self) -> None:
        self.finished.set()
        self._nudge.set()
        self.join()

    def discard(self) -> None:
        """Close the file of a writer that never started (the backend did not enable)."""
        if not self.is_alive() and not self.finished.is_set():
            self._file.close()
            self.finished.set()
