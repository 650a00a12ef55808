"""The Dynamixel motor models and their control tables, Protocol 2.0 (ROBOTIS e-Manual).

The models are data (``cochlea/dynamixel/models/*.toml``, docs/dynamixel.md "Models"): one
file per family with each model's number, units, limits, baud rates and datasheet figures (a
value no source gave is listed as unsourced, never guessed), and one file per control-table
layout with each item's address, size, access, range and unit. The X series and MX(2.0) share
one layout (the addresses below); the P series has another. Each layout names where its RAM
area starts (``ram_from``: 64 on the X series, 512 on the P series); the items below it live
in EEPROM and accept writes only while Torque Enable is 0. Multi-byte items are
little-endian; ``signed`` items are two's complement.

Only the items the bridge and the emulator use, plus their neighbours in the documented table,
are listed; indirect addresses and the external ports are left out.
"""

from __future__ import annotations

import math
import numbers
import sys
import tomllib
from dataclasses import dataclass
from importlib import resources

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
    #: Where the RAM area of the item's control table starts (its layout's ``ram_from``): the
    #: items below it are in EEPROM. 64 (the X series') only for an item made by hand.
    ram_from: int = 64
    #: The values a write may take where not every integer from lo to hi is one (Operating
    #: Mode: the modes the model has), else None.
    values: tuple[int, ...] | None = None

    @property
    def eeprom(self) -> bool:
        return self.address < self.ram_from


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


#: Every field a model's entry in a family file carries (``cochlea/dynamixel/models/*.toml``),
#: given or listed in the entry's ``unsourced`` (no source found: never an invented value).
SOURCED_FIELDS = ("current_unit_mA", "current_limit_max", "baud_rates", "fast_sync_read",
                  "firmware_from", "gear_ratio", "backlash_arcmin", "stall_torque_Nm",
                  "stall_current_A", "stall_voltage_V")
#: ... and per layout, the fields its table needs (a missing one: the layout's fallback).
LAYOUT_FIELDS = {"x": ("velocity_limit", "position_p_gain", "acceleration_limit"),
                 "p": ("velocity_limit", "position_limit", "counts_per_rev"),
                 "xl320": ()}
#: The layouts the Python bridge, the emulator and cochlea-dxl speak (each item's address and
#: size from the data; the per-period block in the same order and sizes on both).
BRIDGE_LAYOUTS = ("x", "p")
#: The layouts the embedded drive tables and the C bridge speak: the Python bridge's (each
#: motor's items and units from its data in the generated tables; a mixed X + P chain by
#: BULK_READ / BULK_WRITE, embedded/core/bridge.c).
EMBEDDED_LAYOUTS = BRIDGE_LAYOUTS


@dataclass(frozen=True)
class ModelSpec:
    """One motor model: its number, units and control table, read from the data files of
    ``cochlea/dynamixel/models`` (docs/dynamixel.md, "Models"). A value no source gave is
    None and its name is in ``unsourced``."""

    name: str
    number: int  # Model Number (0)
    firmware: int  # Firmware Version (6) the emulator reports
    current_unit_mA: float | None  # Goal/Present Current per LSB
    current_limit_max: int | None  # largest Current Limit (38), LSB
    items: tuple[Item, ...]
    #: The gearbox (:class:`Gearbox`): datasheet figures and labelled estimates.
    gearbox: Gearbox | None = None
    family: str = ""
    layout: str = "x"
    url: str = ""
    current_control: bool = True
    #: Baud rates (bit/s) the model accepts; None: not sourced (no check possible).
    baud_rates: tuple[int, ...] | None = None
    fast_sync_read: bool | None = None
    #: The first firmware version with what the bridge needs (Bus Watchdog (98)).
    firmware_from: int | None = None
    counts_per_rev: int | None = COUNTS_PER_REV
    velocity_unit_rpm: float | None = VELOCITY_UNIT_RPM
    gear_ratio: float | None = None
    backlash_arcmin: float | None = None
    stall_torque_Nm: float | None = None
    stall_current_A: float | None = None
    stall_voltage_V: float | None = None
    source_file: str = ""
    unsourced: tuple[str, ...] = ()
    #: Where the RAM area starts (its layout's ``ram_from``): a REBOOT restores from here on.
    ram_from: int = 64

    @property
    def max_current_mA(self) -> float | None:
        if self.current_limit_max is None or self.current_unit_mA is None:
            return None
        return self.current_limit_max * self.current_unit_mA

    @property
    def table_size(self) -> int:
        return max(i.address + i.size for i in self.items)

    @property
    def rad_per_count(self) -> float | None:
        return None if self.counts_per_rev is None else 2.0 * math.pi / self.counts_per_rev

    @property
    def rad_s_per_velocity_lsb(self) -> float | None:
        return (None if self.velocity_unit_rpm is None
                else self.velocity_unit_rpm * 2.0 * math.pi / 60.0)

    def item(self, name: str) -> Item:
        for it in self.items:
            if it.name == name:
                return it
        raise KeyError(name)

    # -- what the toolkit refuses up front ------------------------------------------------

    def current_control_problem(self) -> str | None:
        """Why this model cannot drive a current-controlled joint, or None: no Current
        Control mode, or its current unit / largest Current Limit not sourced."""
        if not self.current_control:
            return f"the {self.name} has no Current Control mode (e-Manual: {self.url})"
        missing = [f for f in ("current_unit_mA", "current_limit_max")
                   if getattr(self, f) is None]
        if missing:
            are, them = ("are", "them") if len(missing) > 1 else ("is", "it")
            return (f"the {self.name}'s {' and '.join(missing)} {are} not sourced yet "
                    f"(cochlea/dynamixel/models/{self.source_file}): add {them} from {self.url}")
        return None

    def units_problem(self) -> str | None:
        """Why the toolkit cannot convert this model's position and velocity, or None: its
        counts per turn (``counts_per_rev``) or velocity unit not sourced (never guessed)."""
        missing = [f for f in ("counts_per_rev", "velocity_unit_rpm")
                   if getattr(self, f) is None]
        if not missing:
            return None
        are = "are" if len(missing) > 1 else "is"
        return (f"the {self.name}'s {' and '.join(missing)} {are} not sourced yet "
                f"(cochlea/dynamixel/models/{self.source_file}): add "
                f"{'them' if len(missing) > 1 else 'it'} from {self.url}")

    def baud_problem(self, baud: int) -> str | None:
        """Why the model cannot talk at ``baud`` (bit/s), or None."""
        if self.baud_rates is not None and baud not in self.baud_rates:
            return (f"the {self.name} does not support {baud} baud (it takes "
                    + ", ".join(str(b) for b in self.baud_rates) + ")")
        return None

    def require_layout(self, component: str,
                       layouts: tuple[str, ...] = BRIDGE_LAYOUTS) -> None:
        """Refuse, in one line, a model whose control table is none of ``layouts`` in
        ``component`` (which would send it another table's addresses)."""
        if self.layout not in layouts:
            spoken = " and ".join(f"the {name.upper()} series'" for name in layouts)
            raise CochleaError(
                f"{self.name}: not supported by {component} yet: its control table "
                f"({self.layout} layout, Goal Current at {self._address('Goal Current')}) "
                f"is not {spoken} it speaks")

    def _address(self, name: str) -> str:
        try:
            return str(self.item(name).address)
        except KeyError:
            return "none"


class ModelDataError(CochleaError):
    """A file of ``cochlea/dynamixel/models`` is unreadable or malformed (an installation
    problem, not the user's input): names the file, the entry and what was expected."""


#: Exit code of a program whose installed motor data (``cochlea/dynamixel/models``) is broken.
EXIT_MODEL_DATA = 78

#: The package folder holding the data files.
MODELS_PACKAGE = "cochlea.dynamixel.models"

_TABLE_FIELDS = {"current_limit_max", "velocity_limit", "position_p_gain", "position_limit"}


def _check(cond: bool, where: str, expected: str, got: object = None) -> None:
    if not cond:
        shown = repr(got)
        if len(shown) > 80:
            shown = shown[:77] + "..."
        raise ModelDataError(f"{where}: expected {expected}, got {shown}")


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _read_toml(name: str, text: bytes) -> dict:
    try:
        return tomllib.loads(text.decode("utf-8"))
    except ValueError as exc:  # not UTF-8, not TOML, or a 4300-digit integer
        raise ModelDataError(f"{name}: not a valid UTF-8 TOML file "
                             f"({str(exc).splitlines()[0] if str(exc) else 'unreadable'})"
                             ) from None


_ITEM_KEYS = {"name", "address", "size", "access", "default", "min", "max", "signed", "unit",
              "only_if", "values"}
_LAYOUT_KEYS = {"layout", "url", "counts_per_rev", "velocity_unit_rpm", "emulator_firmware",
                "fallback", "unsourced", "item", "ram_from"}


def _layout(name: str, data: dict) -> dict:
    """A layout file: its items (values may name a model field) and its defaults."""
    unknown = sorted(set(data) - _LAYOUT_KEYS)
    _check(not unknown, f"{name}: {unknown[0] if unknown else ''}", "no such key (known: "
           + ", ".join(sorted(_LAYOUT_KEYS)) + ")")
    _check(isinstance(data.get("layout"), str), f"{name}: layout", "a layout name",
           data.get("layout"))
    _check(isinstance(data.get("url"), str) and data["url"].startswith("https://"),
           f"{name}: url", "the e-Manual page (https://...)", data.get("url"))
    _check(_is_int(data.get("ram_from")) and 0 < data["ram_from"] < 1024, f"{name}: ram_from",
           "the address where the RAM area starts (the items below it are in EEPROM)",
           data.get("ram_from"))
    for f in ("counts_per_rev", "emulator_firmware"):
        if f in data:
            _check(_is_int(data[f]) and data[f] >= 0, f"{name}: {f}", "an integer >= 0",
                   data[f])
    if "velocity_unit_rpm" in data:
        _check(_is_num(data["velocity_unit_rpm"]) and data["velocity_unit_rpm"] > 0,
               f"{name}: velocity_unit_rpm", "a positive number", data["velocity_unit_rpm"])
    raw = data.get("item")
    _check(isinstance(raw, list) and bool(raw) and all(isinstance(i, dict) for i in raw),
           f"{name}: item", "one or more [[item]] tables", raw)
    seen: set[str] = set()
    for k, it in enumerate(raw):
        where = f"{name}: item[{k}]"
        unknown = sorted(set(it) - _ITEM_KEYS)
        _check(not unknown, f"{where}.{unknown[0] if unknown else ''}", "no such key (known: "
               + ", ".join(sorted(_ITEM_KEYS)) + ")")
        _check(isinstance(it.get("name"), str) and it["name"] not in seen, f"{where}.name",
               "a name no other item uses", it.get("name"))
        seen.add(it["name"])
        where = f"{name}: item {it['name']}"
        _check(_is_int(it.get("address")) and 0 <= it["address"] < 1024, f"{where}.address",
               "an integer in 0..1023", it.get("address"))
        _check(it.get("size") in (1, 2, 4), f"{where}.size", "1, 2 or 4 (bytes)", it.get("size"))
        _check(it.get("access") in ("R", "RW"), f"{where}.access", "'R' or 'RW'",
               it.get("access"))
        _check(isinstance(it.get("unit"), str) and it["unit"] != "", f"{where}.unit",
               "a unit (text, '-' for none)", it.get("unit"))
        _check(("min" in it) == ("max" in it), f"{where}", "min and max together")
        for key in ("default", "min", "max"):
            if key in it or key == "default":
                v = it.get(key)
                _check(_is_int(v) or (isinstance(v, str) and v.lstrip("-") in _TABLE_FIELDS),
                       f"{where}.{key}", "an integer or a model field ("
                       + ", ".join(sorted(_TABLE_FIELDS)) + ")", v)
        if "signed" in it:
            _check(isinstance(it["signed"], bool), f"{where}.signed", "true or false",
                   it["signed"])
        if "values" in it:
            v = it["values"]
            _check(isinstance(v, list) and bool(v) and all(_is_int(x) for x in v)
                   and len(set(v)) == len(v) and _is_int(it.get("min"))
                   and _is_int(it.get("max")) and all(it["min"] <= x <= it["max"] for x in v),
                   f"{where}.values", "distinct integers within min..max", v)
    return data


_MODEL_KEYS = (set(SOURCED_FIELDS) | {f for fs in LAYOUT_FIELDS.values() for f in fs}
               | {"name", "number", "url", "current_control", "unsourced",
                  "emulator_firmware", "gearbox_estimates"})


def _field_ok(field: str, v) -> tuple[bool, str]:
    if field in ("current_unit_mA", "gear_ratio", "backlash_arcmin", "stall_torque_Nm",
                 "stall_current_A", "stall_voltage_V"):
        return _is_num(v) and v > 0, "a positive number"
    if field in ("current_limit_max", "velocity_limit", "position_p_gain", "position_limit",
                 "counts_per_rev", "firmware_from"):
        return _is_int(v) and 0 < v < 2**31, "a positive integer"
    if field in ("fast_sync_read", "acceleration_limit"):
        return isinstance(v, bool), "true or false"
    if field == "baud_rates":
        return (isinstance(v, list) and bool(v) and all(_is_int(b) and b in BAUD_RATES.values()
                                                        for b in v),
                "a list of Dynamixel baud rates ("
                + ", ".join(str(b) for b in BAUD_RATES.values()) + ")")
    return False, "a known field"


def _resolve(value, fields: dict) -> int:
    if isinstance(value, str):
        sign = -1 if value.startswith("-") else 1
        return sign * int(fields[value.lstrip("-")])
    return int(value)


def _model(file: str, family: str, layout: dict, k: int, m: object) -> ModelSpec:
    where = f"{file}: model[{k}]"
    _check(isinstance(m, dict), where, "a [[model]] table", m)
    unknown = sorted(set(m) - _MODEL_KEYS)
    _check(not unknown, f"{where}.{unknown[0] if unknown else ''}", "no such key (known: "
           + ", ".join(sorted(_MODEL_KEYS)) + ")")
    name = m.get("name")
    _check(isinstance(name, str) and name != "", f"{where}.name", "a model name", name)
    where = f"{file}: model {name}"
    number = m.get("number")
    _check(_is_int(number) and 0 <= number < 65536, f"{where}.number",
           "a Model Number (0..65535)", number)
    _check(isinstance(m.get("url"), str) and m["url"].startswith("https://"), f"{where}.url",
           "the e-Manual page (https://...)", m.get("url"))
    _check(isinstance(m.get("current_control"), bool), f"{where}.current_control",
           "true or false", m.get("current_control"))
    unsourced = m.get("unsourced", [])
    _check(isinstance(unsourced, list) and all(isinstance(u, str) for u in unsourced),
           f"{where}.unsourced", "a list of field names", unsourced)
    lay = layout["layout"]
    wanted = SOURCED_FIELDS + LAYOUT_FIELDS.get(lay, ())
    for u in unsourced:
        _check(u in wanted, f"{where}.unsourced", "field names among " + ", ".join(wanted), u)
    fields: dict = {}
    for f in wanted:
        given, listed = f in m, f in unsourced
        _check(given != listed, f"{where}.{f}",
               "a value or the name in unsourced, not both" if given else
               "a value (or the name in unsourced: no source found)",
               m.get(f) if given else None)
        if given:
            ok, expected = _field_ok(f, m[f])
            _check(ok, f"{where}.{f}", expected, m[f])
        fields[f] = m.get(f)
    # The layout's units where the model's own are not per model (X: 4096 counts, 0.229 rpm).
    for f in ("counts_per_rev", "velocity_unit_rpm"):
        if fields.get(f) is None and f not in unsourced:
            fields[f] = layout.get(f)
    # The table: the model's values, the layout's fallback where it gives none (those items'
    # defaults are then not the model's: the emulator's only).
    table = dict(layout.get("fallback", {}))
    table.update({f: v for f, v in fields.items() if v is not None})
    for f in _TABLE_FIELDS:
        table.setdefault(f, 0)  # e.g. no Current Limit sourced: the table is for lookup only
    items = []
    for it in layout["item"]:
        if "only_if" in it and not table.get(it["only_if"]):
            continue
        items.append(Item(it["name"], it["address"], it["size"], it["access"] == "RW",
                          _resolve(it["default"], table), _resolve(it.get("min", 0), table),
                          _resolve(it.get("max", 0), table), bool(it.get("signed", False)),
                          layout["ram_from"],
                          tuple(it["values"]) if "values" in it else None))
    items.sort(key=lambda i: i.address)
    gearbox = None
    est = m.get("gearbox_estimates")
    if est is not None:
        _check(isinstance(est, dict) and set(est) == {"stiffness_Nm_rad", "damping_Nms_rad",
                                                      "stribeck_velocity_rad_s"}
               and all(_is_num(v) and v > 0 for v in est.values())
               and fields["gear_ratio"] is not None and fields["backlash_arcmin"] is not None,
               f"{where}.gearbox_estimates", "stiffness_Nm_rad, damping_Nms_rad and "
               "stribeck_velocity_rad_s (positive), with gear_ratio and backlash_arcmin", est)
        gearbox = Gearbox(float(fields["gear_ratio"]), float(fields["backlash_arcmin"]),
                          float(est["stiffness_Nm_rad"]), float(est["damping_Nms_rad"]),
                          float(est["stribeck_velocity_rad_s"]))
    firmware = m.get("emulator_firmware", layout.get("emulator_firmware", 0))
    _check(_is_int(firmware) and 0 <= firmware < 256, f"{where}.emulator_firmware",
           "an integer in 0..255", firmware)
    baud = fields["baud_rates"]
    unit = fields["current_unit_mA"]
    return ModelSpec(
        name, number, firmware, None if unit is None else float(unit),
        fields["current_limit_max"], tuple(items), gearbox, family=family, layout=lay,
        url=m["url"], current_control=m["current_control"],
        baud_rates=None if baud is None else tuple(baud),
        fast_sync_read=fields["fast_sync_read"], firmware_from=fields["firmware_from"],
        counts_per_rev=fields.get("counts_per_rev"),
        velocity_unit_rpm=fields.get("velocity_unit_rpm"),
        gear_ratio=fields["gear_ratio"], backlash_arcmin=fields["backlash_arcmin"],
        stall_torque_Nm=fields["stall_torque_Nm"], stall_current_A=fields["stall_current_A"],
        stall_voltage_V=fields["stall_voltage_V"], source_file=file,
        unsourced=tuple(unsourced), ram_from=layout["ram_from"])


def load_models(files: dict[str, bytes] | None = None) -> dict[str, ModelSpec]:
    """Every model of the data files, by the name a description uses: ``files`` maps a file
    name to its bytes (default: the package's ``cochlea/dynamixel/models/*.toml``, read
    through :mod:`importlib.resources`). ``layout_*.toml`` are control-table layouts, the
    rest family files. Any problem is one :class:`ModelDataError` naming the file and the
    entry."""
    if files is None:
        folder = resources.files(MODELS_PACKAGE)
        files = {p.name: p.read_bytes() for p in folder.iterdir() if p.name.endswith(".toml")}
    layouts = {}
    for fname in sorted(f for f in files if f.startswith("layout_")):
        data = _layout(fname, _read_toml(fname, files[fname]))
        _check(data["layout"] not in layouts, f"{fname}: layout", "a layout no other file "
               "defines", data["layout"])
        layouts[data["layout"]] = data
    models: dict[str, ModelSpec] = {}
    numbers: dict[int, str] = {}
    for fname in sorted(f for f in files if not f.startswith("layout_")):
        data = _read_toml(fname, files[fname])
        unknown = sorted(set(data) - {"family", "layout", "model"})
        _check(not unknown, f"{fname}: {unknown[0] if unknown else ''}",
               "no such key (known: family, layout, model)")
        family = data.get("family")
        _check(isinstance(family, str) and family != "", f"{fname}: family", "a family name",
               family)
        _check(data.get("layout") in layouts, f"{fname}: layout",
               "one of " + ", ".join(sorted(layouts)), data.get("layout"))
        entries = data.get("model")
        _check(isinstance(entries, list) and bool(entries), f"{fname}: model",
               "one or more [[model]] tables", entries)
        for k, m in enumerate(entries):
            spec = _model(fname, family, layouts[data["layout"]], k, m)
            _check(spec.name not in models, f"{fname}: model {spec.name}",
                   "a name no other entry uses", spec.name)
            _check(spec.number not in numbers, f"{fname}: model {spec.name}.number",
                   f"a number no other model uses (also {numbers.get(spec.number)})",
                   spec.number)
            models[spec.name] = spec
            numbers[spec.number] = spec.name
    # The robots' two models first (every "one of ..." list starts with them), then the rest.
    first = [n for n in ("MX-64", "XM540-W270") if n in models]
    return {n: models[n] for n in first + [n for n in models if n not in first]}


def _load_or_exit() -> dict[str, ModelSpec]:
    """:func:`load_models`, or one line on stderr and exit :data:`EXIT_MODEL_DATA` (the
    installation is broken: nothing can run)."""
    try:
        return load_models()
    except ModelDataError as exc:
        print(f"cochlea: broken motor data in cochlea/dynamixel/models: {exc}",
              file=sys.stderr)
        raise SystemExit(EXIT_MODEL_DATA) from None


#: The models by the name a description uses (MX-64 and XM540-W270 first).
MODELS = _load_or_exit()
MODELS_BY_NUMBER = {m.number: m for m in MODELS.values()}
#: The two models the shipped robots use (MX-64(2.0): gear 200 : 1, backlash 20 arcmin;
#: XM540-W270: 272.5 : 1, 15 arcmin; e-Manual).
MX64 = MODELS["MX-64"]
XM540_W270 = MODELS["XM540-W270"]

# The X layout's addresses (layout_x.toml), for the emulator's X-series motors. The bridges
# take every address from each model's items instead (ModelSpec.item).
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
