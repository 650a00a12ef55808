"""What the real-time loop drives: a backend that reads joint states and writes joint efforts.

The loop (``cochlea.runtime``) knows nothing of plants, buses or motors: it calls a backend
through this small interface, once per period, with preallocated arrays. A backend covers every
joint of the system in one vector (serial: arm 1's joints then arm 2's; parallel: the
mechanism's five), in SI joint coordinates: rad and m, rad/s and m/s, N m and N.

Contract:

* ``enable()`` prepares the hardware or plant and makes it ready to accept commands; a failure
  raises :class:`BackendError` before anything moves.
* ``read(x)`` fills ``x = [q, qd]`` in place and returns True, or returns False when this
  period's read failed (timeout, CRC error, ...): the loop counts consecutive failures for its
  watchdog. It must not raise during the loop and must not allocate.
* ``write(tau)`` commands the efforts, held until the next write; returns False on failure.
  A backend that knows the efforts its drives really apply (the sim backend with current
  quantisation) writes them back into ``tau``: the loop logs ``tau`` after the write.
* ``disable()`` commands zero effort and then switches the drives off (torque off). It must
  never raise, must be idempotent, and must be safe to call at any time, also from a stop
  caused by the backend itself.
* ``last_io_time_s`` is the time the last ``read`` plus ``write`` took (s), for the summary.
* ``joint_current_A``: a backend whose drives measure their current holds an array of one
  value per joint, allocated once and refreshed in place by every good ``read``: the motor
  current in A, signed so that a positive current drives the joint positively (the drive's
  ``direction`` and transmission applied). The loop copies it into the period's row. ``None``
  (the simulated plant) when nothing is measured: the logs then have no current columns.
* ``true_state``: a backend that knows the plant's true state (the simulated robot) holds an
  array ``[q, qd]`` (2 nq), allocated once and refreshed by every ``read`` with the state the
  plant is in at that read, before any delay, noise or measurement grid: what ``read`` reports
  is the measurement. The loop logs both (``true_q``/``true_qd`` beside ``q``/``qd``), and the
  run is judged on the true tracking error. Absent or ``None`` on the motors, which know only
  what they measure.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..errors import CochleaError


class BackendError(CochleaError):
    """A backend could not start (port missing, motor absent, wrong model number, ...)."""


class Backend(Protocol):
    name: str
    nq: int
    last_io_time_s: float
    joint_current_A: np.ndarray | None
    true_state: np.ndarray | None

    def enable(self) -> None: ...

    def read(self, x: np.ndarray) -> bool: ...

    def write(self, tau: np.ndarray) -> bool: ...

    def disable(self) -> None: ...
