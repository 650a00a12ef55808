"""The run's log written behind the loop: finished rows of the period buffer appended to
``log.bin`` by a thread of its own, so no period formats or touches the disk."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np


class LogWriter(threading.Thread):
    """Appends finished rows of the period buffer to ``log.bin`` behind the loop."""

    def __init__(self, buffer: np.ndarray, path: Path, interval: float = 0.2):
        super().__init__(name="cochlea-log-writer", daemon=True)
        self.buffer, self.path, self.interval = buffer, path, interval
        self.done_rows = 0  # rows the loop has finished (written by the loop only)
        self.written = 0
        self.finished = threading.Event()

    def run(self) -> None:
        with open(self.path, "wb") as f:
            while not self.finished.wait(self.interval):
                self._flush(f)
            self._flush(f)

    def _flush(self, f) -> None:
        end = self.done_rows
        if end > self.written:
            self.buffer[self.written:end].tofile(f)
            f.flush()
            self.written = end

    def close(self) -> None:
        self.finished.set()
        self.join()
