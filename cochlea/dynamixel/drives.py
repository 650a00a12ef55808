"""Joint <-> motor conversions: position counts, velocity units, current units and the fit.

Per joint (SI on the joint side: rad or m, rad/s or m/s, N m or N):

* **Position.** The motor's angle is ``theta = counts * 2 pi / counts_per_rev`` (Present
  Position; its model's data: 4096 on the X series and MX(2.0), 0.088 deg per count; the P
  series' multi-turn signed pulses, 607500 a turn on the PH42-020-S300-R).
  ``zero_offset_deg`` in the description is the motor angle at which the joint coordinate is
  zero, ``direction`` (+1 or -1) whether they turn the same way, and ``ratio`` the
  joint travel per motor radian (1 for a revolute joint: the motor's output shaft is the joint;
  for a prismatic joint its transmission's m/rad, > 0: a pinion's or belt pulley's pitch
  radius, a lead screw's lead over 2 pi; the parallel robot's slider and a serial arm's
  prismatic joint alike, ``[...transmission]`` in the description)::

      q = direction * ratio * (theta - zero_offset)

* **Velocity.** ``qd = direction * ratio * v * unit`` (Present Velocity: 0.229 rpm/LSB on the X
  series, 0.01 rpm/LSB on the P series).
* **Current.** ``I = lsb * unit`` with 3.36 mA/LSB (MX-64(2.0)), 2.69 mA/LSB (XM540-W270), 1 mA
  (P series): each model's ``current_unit_mA``.

A model whose unit the toolkit needs is not sourced (``unsourced`` in its data) is refused in
one line, never guessed (:func:`joint_drives`).
* **Effort.** The motor torque is ``tau_m = direction * ratio * effort`` (the same power
  ``effort * qd = tau_m * theta_dot``, an ideal transmission); at a prismatic joint the effort
  is a force (N) and ``tau_m`` is ``force * ratio`` (N m): a 20 mm pinion turns 100 N into
  2 N m, a 20 mm lead screw into 0.32 N m.

Every conversion is one multiplication (and its inverse) by ``direction * ratio`` and the
motor's unit: position and velocity round to the motor's counts and LSBs, nothing else is
approximated (tests/test_user_prismatic.py round-trips them).

The fit (thesis Table C.1) maps current to torque: :class:`~cochlea.robots.motor_fit.Fit`, with
the rule for the offset and the ramp, lives with the robots (:mod:`cochlea.robots.motor_fit`,
pure conversions the simulation uses too) and is re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CochleaError, DescriptionError, ModelError
from ..robots import robot
from ..robots.description import Motor
from ..robots.motor_fit import DEFAULT_RAMP_NM, Fit, MotorFitError, current_limit_lsb
from ..runtime.backend import BackendError
from .control_table import BRIDGE_LAYOUTS, MODELS, Item, ModelSpec
from .protocol import le

__all__ = ["DEFAULT_RAMP_NM", "Fit", "JointDrive", "current_limit_lsb", "drive_item",
           "encode_item", "joint_drives", "shared_item"]


@dataclass(frozen=True)
class JointDrive:
    """One joint and the motor driving it, with every conversion between them."""

    name: str  # e.g. "arm1.link2", "slider.d1", "arm.carriage"
    type: str  # "revolute" | "prismatic"
    motor: Motor
    spec: ModelSpec
    direction: int  # +1 | -1
    zero_offset: float  # rad, motor angle at joint zero
    ratio: float  # joint travel per motor radian (1 for revolute, m/rad for prismatic)
    fit: Fit
    position_limits: tuple[float, float]
    effort_limit: float  # N m or N
    current_limit_lsb: int  # Current Limit (38) this joint uses

    @property
    def id(self) -> int:
        return self.motor.id

    @property
    def unit(self) -> str:
        return "rad" if self.type == "revolute" else "m"

    # ---- position and velocity ---------------------------------------------------------------

    @property
    def q_per_count(self) -> float:
        return self.direction * self.ratio * self.spec.rad_per_count

    @property
    def q_offset(self) -> float:
        """``q = q_per_count * counts + q_offset``."""
        return -self.direction * self.ratio * self.zero_offset

    @property
    def qd_per_lsb(self) -> float:
        return self.direction * self.ratio * self.spec.rad_s_per_velocity_lsb

    def q(self, counts):
        return self.q_per_count * np.asarray(counts, dtype=float) + self.q_offset

    def counts(self, q):
        """Present Position (counts) at joint coordinate q, rounded."""
        return np.rint((np.asarray(q, dtype=float) - self.q_offset) / self.q_per_count)

    def qd(self, lsb):
        return self.qd_per_lsb * np.asarray(lsb, dtype=float)

    def velocity_lsb(self, qd):
        return np.rint(np.asarray(qd, dtype=float) / self.qd_per_lsb)

    # ---- effort and current --------------------------------------------------------------------

    @property
    def torque_per_effort(self) -> float:
        """Motor torque (N m) per unit of joint effort (N m or N)."""
        return self.direction * self.ratio

    @property
    def lsb_per_ampere(self) -> float:
        return 1000.0 / self.spec.current_unit_mA

    def current_mA(self, lsb):
        return np.asarray(lsb, dtype=float) * self.spec.current_unit_mA

    def goal_current_lsb(self, effort, offset_current: bool = True):
        """Goal Current (LSB) for a joint effort: the fit's inverse, rounded, within the
        current limit; ``offset_current=False`` without the fit's offset (the bridge's option
        when the controller compensates friction)."""
        amps = self.fit.current(self.torque_per_effort * np.asarray(effort, dtype=float),
                                offset_current)
        lim = self.current_limit_lsb
        return np.clip(np.rint(amps * self.lsb_per_ampere), -lim, lim)

    def effort(self, lsb, slope_only: bool = False):
        """Joint effort (N m or N) a current (LSB) produces through the fit, the offset's
        friction taken off. ``slope_only``: the motor's own torque, ``a I``, for a plant that
        models the gearbox's friction itself (the fit's offset is that friction: taking it off
        here too would count it twice)."""
        amps = np.asarray(lsb, dtype=float) / self.lsb_per_ampere
        torque = self.fit.a * amps if slope_only else self.fit.torque(amps)
        return torque / self.torque_per_effort


def joint_drives(robot_name: str, description: str | Path | None = None,
                 ramp: float = DEFAULT_RAMP_NM, *, system=None) -> list[JointDrive]:
    """The joints of a whole system in the loop's order (serial: arm 1's joints then arm 2's;
    parallel: th1, th2, d1, th1', th2'), each with its motor. ``system``: the description
    already loaded (then ``description`` is not read again)."""
    try:
        adapter = robot(robot_name)
        if system is None:
            system = adapter.load(description)
        joints = adapter.actuated_joints(system)
    except (DescriptionError, ModelError) as exc:
        raise BackendError(str(exc)) from exc
    drives = []
    for j in joints:
        spec = MODELS[j.motor.model]
        try:  # the bridge, the emulator and cochlea-dxl speak the X and the P series' tables
            spec.require_layout("the Dynamixel bridge and emulator", BRIDGE_LAYOUTS)
        except CochleaError as exc:
            raise BackendError(f"joint {j.name}: {exc}") from None
        problem = spec.units_problem()  # counts per turn, velocity unit: never guessed
        if problem:
            raise BackendError(f"joint {j.name}: {problem}")
        try:
            fit = Fit.from_description(j.motor.fit, ramp)
        except MotorFitError as exc:
            raise BackendError(str(exc)) from exc
        drives.append(JointDrive(j.name, j.type, j.motor, spec, j.motor.direction,
                                 j.motor.zero_offset, j.ratio, fit, tuple(j.position_limits),
                                 j.effort_limit,
                                 current_limit_lsb(j.motor, spec, fit, j.effort_limit, j.ratio)))
    return drives


def check_baud(drives: list[JointDrive], baud: int) -> None:
    """Refuse, in one line naming the motor, a baud rate (bit/s) a model of ``drives`` does
    not support (its data: ``cochlea/dynamixel/models``), before any port is opened."""
    for d in drives:
        problem = d.spec.baud_problem(int(baud))
        if problem:
            raise BackendError(f"ID {d.id} ({d.name}, {d.spec.name}): {problem}")


# ---- the control-table items of the drives' models (their data: cochlea/dynamixel/models) -------

def drive_item(d: JointDrive, name: str, who: str = "the bridge") -> Item:
    """Item ``name`` of the model driving ``d`` (address and size from its data); a model
    without it is refused in one line naming the joint and ``who`` cannot drive it."""
    try:
        return d.spec.item(name)
    except KeyError:
        raise BackendError(f"joint {d.name}: the {d.spec.name} has no {name} item: {who} "
                           "cannot drive it") from None


def shared_item(drives: list[JointDrive], name: str, who: str = "the bridge") -> Item:
    """Item ``name`` where every motor of ``drives`` has it: one address and one size, what a
    single SYNC_WRITE or SYNC_READ of it to all of them needs. A chain whose models place it
    differently is refused in one line naming them (an X-series arm with a P-series joint:
    the per-period transfers are BULK ones there, chosen by the bridge's
    :func:`~cochlea.dynamixel.bridge.choose_transfers`; no shipped chain is)."""
    items = [drive_item(d, name, who) for d in drives]
    if len({(it.address, it.size) for it in items}) > 1:
        places = sorted({f"{d.spec.name}: address {it.address}, {it.size} byte"
                         + ("s" if it.size > 1 else "") for d, it in zip(drives, items)})
        raise BackendError(f"{who} cannot send one SYNC_WRITE/SYNC_READ of {name} to this "
                           f"chain: its models place it differently ({'; '.join(places)})")
    return items[0]


def encode_item(d: JointDrive, it: Item, value: int) -> bytes:
    """``value`` as the bytes of item ``it`` of ``d``'s model (little-endian, ``it.size``
    bytes). A value the item cannot hold (outside its size, or outside the range its data
    says a write accepts) is refused in one line: it would be truncated, or refused by the
    motor mid-start-up."""
    bits = 8 * it.size
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if it.signed else (0, (1 << bits) - 1)
    if it.writable:
        lo, hi = max(lo, it.lo), min(hi, it.hi)
    if not lo <= int(value) <= hi:
        raise BackendError(f"joint {d.name} (ID {d.id}): {it.name} = {value} does not fit the "
                           f"{d.spec.name}'s item ({it.address}, {it.size} bytes, "
                           f"{lo}..{hi})")
    return le(int(value), it.size)
