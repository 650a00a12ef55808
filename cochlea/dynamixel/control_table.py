"""Control tables of the two motor models the robots use, in Protocol 2.0 (ROBOTIS e-Manual).

Both MX-64(2.0) and XM540-W270 share the addresses below; they differ in model number, the
current unit and a few limits. Items at addresses below 64 live in EEPROM and accept writes only
while Torque Enable (64) is 0. Multi-byte items are little-endian; ``signed`` items are two's
complement.

Only the items the bridge and the emulator use, plus their neighbours in the documented table,
are listed; indirect addresses and the external ports are left out.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

from ..errors import CochleaError

#: Protocol 2.0 instruction codes.
PING, READ, WRITE, REG_WRITE, ACTION, FACTORY_RESET, REBOOT, CLEAR = (
    0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08, 0x10)
STATUS = 0x55
SYNC_READ, SYNC_WRITE, BULK_READ, BULK_WRITE, FAST_SYNC_READ = 0x82, 0x83, 0x92, 0x93, 0x8A
INSTRUCTION_NAMES = {PING: "PING", READ: "READ", WRITE: "WRITE", REG_WRITE: "REG_WRITE",
                     ACTION: "ACTION", FACTORY_RESET: "FACTORY_RESET", REBOOT: "REBOOT",
                     CLEAR: "CLEAR", STATUS: "STATUS", SYNC_READ: "SYNC_READ",
                     SYNC_WRITE: "SYNC_WRITE", BULK_READ: "BULK_READ",
                     BULK_WRITE: "BULK_WRITE", FAST_SYNC_READ: "FAST_SYNC_READ"}

BROADCAST_ID = 0xFE
MAX_ID = 252

#: Error field of a status packet: bit 7 is the hardware alert, bits 0-6 an error number.
ALERT_BIT = 0x80
RESULT_FAIL, INSTRUCTION_ERROR, CRC_ERROR, DATA_RANGE, DATA_LENGTH, DATA_LIMIT, ACCESS = range(1, 8)
ERROR_NAMES = {RESULT_FAIL: "Result Fail", INSTRUCTION_ERROR: "Instruction Error",
               CRC_ERROR: "CRC Error", DATA_RANGE: "Data Range Error",
               DATA_LENGTH: "Data Length Error", DATA_LIMIT: "Data Limit Error",
               ACCESS: "Access Error"}

#: Hardware Error Status (70) bits (also the Shutdown (63) bits).
HARDWARE_ERROR_BITS = {0: "input voltage", 2: "overheating", 3: "motor encoder",
                       4: "electrical shock", 5: "overload"}

#: Baud Rate (8) codes.
BAUD_RATES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
              6: 4_000_000, 7: 4_500_000}

#: Operating Mode (11) values.
CURRENT_MODE, VELOCITY_MODE, POSITION_MODE, EXTENDED_POSITION_MODE, CURRENT_POSITION_MODE, \
    PWM_MODE = 0, 1, 3, 4, 5, 16
OPERATING_MODES = (0, 1, 3, 4, 5, 16)

#: Units shared by both models.
COUNTS_PER_REV = 4096  # Present Position, 0.088 deg per count
VELOCITY_UNIT_RPM = 0.229  # Present Velocity per LSB
RETURN_DELAY_UNIT_S = 2e-6  # Return Delay Time per LSB
WATCHDOG_UNIT_S = 0.020  # Bus Watchdog per LSB


def describe_error(error: int) -> str:
    """A status packet's error byte in words, e.g. ``"Data Limit Error"``."""
    parts = []
    number = error & 0x7F
    if number:
        parts.append(ERROR_NAMES.get(number, f"unknown error {number}"))
    if error & ALERT_BIT:
        parts.append("hardware alert")
    return " + ".join(parts) if parts else "no error"


def baud_code(baud: object, option: str = "--baud") -> int:
    """The Baud Rate (8) code of ``baud``. Any other rate is refused, naming ``option``: the
    motors answer only at these, and a serial port set to another one (or 0, which termios
    takes as "hang up") finds no motor at all."""
    codes = {rate: code for code, rate in BAUD_RATES.items()}
    if isinstance(baud, bool) or not isinstance(baud, numbers.Integral) or int(baud) not in codes:
        raise CochleaError(f"{option} {baud} is not a Dynamixel rate: expected one of "
                           + ", ".join(str(b) for b in BAUD_RATES.values()))
    return codes[int(baud)]


def describe_hardware_error(status: int) -> str:
    """Hardware Error Status (70) in words, e.g. ``"overload"``."""
    names = [name for bit, name in HARDWARE_ERROR_BITS.items() if status & (1 << bit)]
    return ", ".join(names) if names else (f"0x{status:02X}" if status else "none")


@dataclass(frozen=True)
class Item:
    name: str
    address: int
    size: int  # bytes
    writable: bool
    default: int
    lo: int = 0  # valid range of a write (inclusive)
    hi: int = 0
    signed: bool = False

    @property
    def eeprom(self) -> bool:
        return self.address < 64


@dataclass(frozen=True)
class Gearbox:
    """A model's gearbox at its output shaft, for the simulated plant (``[plant] gearbox``).

    Datasheet figures (ROBOTIS e-Manual, each model's specifications): ``ratio`` and
    ``backlash_arcmin``. The rest are ESTIMATES, no datasheet or measurement found:

    * ``stiffness_Nm_rad``: the gear train's torsional stiffness at the output. Chosen so that
      the engaged gear's resonance is far above the controllers' bandwidth (the realistic
      studies' sliding loops close at 100-170 rad/s): at 1e4 N m/rad the whole serial arm on
      joint 1 (1.8e-3 kg m^2) rings against its rotor (3.4e-3) at about 2900 rad/s (460 Hz),
      link 3 (6e-6 kg m^2, the lightest load) at 6.5 kHz; the MX-64's 6 N m stall torque winds
      the train up by 0.034 deg, a tenth of its backlash. The test of "far above": without
      backlash every realistic study's closed loop is the rigid plant's (converged, the same
      verdict); at 1e3 N m/rad (mesh damping 0.1) the parallel task-space study already fails to
      converge, at 100 (0.01) the serial joint-space study loses joint 2. The XM540-W270's
      larger gears: twice as stiff.
    * ``damping_Nms_rad``: the gear mesh's damping: 0.35 N m s/rad, a damping ratio of 0.05 on
      the slowest engaged mode (joint 1 of a serial arm; 0.7 on link 3's), an assumed value for
      a lubricated spur-gear mesh.
    * ``stribeck_velocity_rad_s``: the output speed below which static friction rises above
      Coulomb (``Fc + (Fs - Fc) exp(-(v / vs)^2)``), 0.02 rad/s (1.1 deg/s, just under one
      velocity-register count of 0.024 rad/s): the smoothing velocity the controllers'
      friction model uses (docs/models.md), so the plant's friction and the model's change
      over the same speeds.
    """

    ratio: float
    backlash_arcmin: float
    stiffness_Nm_rad: float
    damping_Nms_rad: float
    stribeck_velocity_rad_s: float

    @property
    def backlash_rad(self) -> float:
        return math.radians(self.backlash_arcmin / 60.0)


@dataclass(frozen=True)
class ModelSpec:
    """One motor model: its number, units and control table."""

    name: str
    number: int  # Model Number (0)
    firmware: int  # Firmware Version (6) the emulator reports
    current_unit_mA: float  # Goal/Present Current per LSB
    current_limit_max: int  # largest Current Limit (38), LSB
    items: tuple[Item, ...]
    #: The gearbox (:class:`Gearbox`): datasheet figures and labelled estimates.
    gearbox: Gearbox | None = None

    @property
    def max_current_mA(self) -> float:
        return self.current_limit_max * self.current_unit_mA

    @property
    def table_size(self) -> int:
        return max(i.address + i.size for i in self.items)

    def item(self, name: str) -> Item:
        for it in self.items:
            if it.name == name:
                return it
        raise KeyError(name)


def _items(current_limit: int, velocity_limit: int, position_p: int,
           acceleration_limit: bool) -> tuple[Item, ...]:
    R, W = False, True
    items = [
        Item("Model Number", 0, 2, R, 0),
        Item("Model Information", 2, 4, R, 0),
        Item("Firmware Version", 6, 1, R, 0),
        Item("ID", 7, 1, W, 1, 0, MAX_ID),
        Item("Baud Rate", 8, 1, W, 1, 0, 7),
        Item("Return Delay Time", 9, 1, W, 250, 0, 254),
        Item("Drive Mode", 10, 1, W, 0, 0, 5),
        Item("Operating Mode", 11, 1, W, POSITION_MODE, 0, 16),
        Item("Secondary ID", 12, 1, W, 255, 0, 255),
        Item("Protocol Type", 13, 1, W, 2, 1, 2),
        Item("Homing Offset", 20, 4, W, 0, -1_044_479, 1_044_479, True),
        Item("Moving Threshold", 24, 4, W, 10, 0, 1023),
        Item("Temperature Limit", 31, 1, W, 80, 0, 100),
        Item("Max Voltage Limit", 32, 2, W, 160, 95, 160),
        Item("Min Voltage Limit", 34, 2, W, 95, 95, 160),
        Item("PWM Limit", 36, 2, W, 885, 0, 885),
        Item("Current Limit", 38, 2, W, current_limit, 0, current_limit),
        Item("Velocity Limit", 44, 4, W, velocity_limit, 0, 1023),
        Item("Max Position Limit", 48, 4, W, 4095, 0, 4095),
        Item("Min Position Limit", 52, 4, W, 0, 0, 4095),
        Item("Shutdown", 63, 1, W, 52, 0, 255),
        Item("Torque Enable", 64, 1, W, 0, 0, 1),
        Item("LED", 65, 1, W, 0, 0, 1),
        Item("Status Return Level", 68, 1, W, 2, 0, 2),
        Item("Registered Instruction", 69, 1, R, 0),
        Item("Hardware Error Status", 70, 1, R, 0),
        Item("Velocity I Gain", 76, 2, W, 1920, 0, 16383),
        Item("Velocity P Gain", 78, 2, W, 100, 0, 16383),
        Item("Position D Gain", 80, 2, W, 0, 0, 16383),
        Item("Position I Gain", 82, 2, W, 0, 0, 16383),
        Item("Position P Gain", 84, 2, W, position_p, 0, 16383),
        Item("Feedforward 2nd Gain", 88, 2, W, 0, 0, 16383),
        Item("Feedforward 1st Gain", 90, 2, W, 0, 0, 16383),
        # Bus Watchdog reads -1 after it tripped; only 0..127 can be written.
        Item("Bus Watchdog", 98, 1, W, 0, 0, 127, True),
        # Goal values are bounded by their limits at write time (see the emulator).
        Item("Goal PWM", 100, 2, W, 0, -885, 885, True),
        Item("Goal Current", 102, 2, W, current_limit, -current_limit, current_limit, True),
        Item("Goal Velocity", 104, 4, W, 0, -1023, 1023, True),
        Item("Profile Acceleration", 108, 4, W, 0, 0, 32767),
        Item("Profile Velocity", 112, 4, W, 0, 0, 32767),
        Item("Goal Position", 116, 4, W, 0, -1_048_575, 1_048_575, True),
        Item("Realtime Tick", 120, 2, R, 0),
        Item("Moving", 122, 1, R, 0),
        Item("Moving Status", 123, 1, R, 0),
        Item("Present PWM", 124, 2, R, 0, signed=True),
        Item("Present Current", 126, 2, R, 0, signed=True),
        Item("Present Velocity", 128, 4, R, 0, signed=True),
        Item("Present Position", 132, 4, R, 0, signed=True),
        Item("Velocity Trajectory", 136, 4, R, 0, signed=True),
        Item("Position Trajectory", 140, 4, R, 0, signed=True),
        Item("Present Input Voltage", 144, 2, R, 120),
        Item("Present Temperature", 146, 1, R, 30),
    ]
    if acceleration_limit:
        items.append(Item("Acceleration Limit", 40, 4, W, 32767, 0, 32767))
    return tuple(sorted(items, key=lambda i: i.address))


#: MX-64: gear ratio 200 : 1, backlash 20 arcmin (0.33 deg) (e-Manual, MX-64(2.0)).
MX64 = ModelSpec("MX-64", 311, 41, 3.36, 1941,
                 _items(1941, 435, 850, acceleration_limit=True),
                 Gearbox(200.0, 20.0, 1.0e4, 0.35, 0.02))
#: XM540-W270: gear ratio 272.5 : 1, backlash 15 arcmin (0.25 deg) (e-Manual, XM540-W270).
XM540_W270 = ModelSpec("XM540-W270", 1120, 46, 2.69, 2047,
                       _items(2047, 128, 800, acceleration_limit=False),
                       Gearbox(272.5, 15.0, 2.0e4, 0.35, 0.02))

#: The models by the name a description uses.
MODELS = {MX64.name: MX64, XM540_W270.name: XM540_W270}
MODELS_BY_NUMBER = {m.number: m for m in MODELS.values()}

# Addresses the bridge uses.
ADDR_MODEL_NUMBER = 0
ADDR_RETURN_DELAY = 9
ADDR_OPERATING_MODE = 11
ADDR_CURRENT_LIMIT = 38
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR = 70
ADDR_BUS_WATCHDOG = 98
ADDR_GOAL_CURRENT = 102
ADDR_PRESENT_CURRENT = 126
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
#: One read of 126..135 gives Present Current (2), Present Velocity (4), Present Position (4).
STATE_ADDRESS, STATE_LENGTH = ADDR_PRESENT_CURRENT, 10

RAD_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV
RAD_S_PER_VELOCITY_LSB = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0
