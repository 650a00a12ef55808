"""The bus budget: how many bytes and how much time one control period needs on the bus.

Per period the bridge sends one SYNC_WRITE of Goal Current and one SYNC_READ of the state, and
every motor answers the read with one status packet:

* SYNC_WRITE: ``14 + n (1 + 2)`` bytes (header 7, instruction, address 2, length 2, per motor
  ID + 2 data bytes, CRC 2);
* SYNC_READ request: ``14 + n`` bytes;
* each status packet: ``11 + L`` bytes (header 7, 0x55, error, L data bytes, CRC 2). ``L = 10``
  (126..135, the state alone) by default, as the embedded C program reads; ``cochlea-run``'s
  bridge reads 120..135, ``L = 16``: the Realtime Tick (120) that tells a stale packet, then
  122..125 which lie between, then the state (``read_length=16``; 6 motors: 214 bytes per
  period instead of 178, 0.54 ms of wire at 4 Mbaud instead of 0.45 ms).

Each byte takes 10 bit times (8N1). Before each status packet the motor waits its Return Delay
Time (2 us per LSB; the bridge sets 0) plus its own turnaround, which the e-Manual does not give
(tens of microseconds; 20 us assumed here). On top comes the USB adapter: an FTDI-based one
(U2D2) holds received bytes until its latency timer expires, 16 ms by default and 1 ms at best,
so one read transaction costs up to that much more. Byte stuffing can add a byte now and then;
it is not counted.

The transfers actually sent (``read_instruction``, ``write_instruction``: docs/dynamixel.md
"Mixed chains and Fast Sync Read"):

* ``sync``: SYNC_READ as above, one status packet per motor, each after its own wait;
* ``fast``: FAST_SYNC_READ (0x8A), the same ``14 + n`` byte request, one combined status
  packet of ``8 + n (L + 4)`` bytes (header 7, 0x55, per motor ERR, ID, L data bytes and a
  CRC, the last motor's CRC the packet's): 6 motors, L = 16: 128 bytes instead of 6 x 27 =
  162, and one wait (return delay + turnaround) instead of 6 -- the motors are counted as
  sending their blocks back to back, an assumption (the e-Manual gives no gap figure);
* ``bulk``: BULK_READ (0x92), ``10 + 5 n`` bytes (per motor ID, address 2, length 2), one
  status packet per motor as for SYNC_READ;
* writes: SYNC_WRITE ``14 + n (1 + W)``, or BULK_WRITE (0x93) ``10 + n (5 + W)`` (per motor ID,
  address 2, length 2, W data bytes).

For 6 motors (178 bytes): 1.78 ms of wire at 1 Mbaud, 0.89 ms at 2 Mbaud, 0.45 ms at 4 Mbaud,
plus 0.12 ms of turnaround: a strict 1 kHz cycle fits only at 4 Mbaud and only without the
adapter's latency, hence "marginal".
"""

from __future__ import annotations

from dataclasses import dataclass

from .control_table import STATE_LENGTH

BITS_PER_BYTE = 10
#: Assumed time a motor takes to start its status packet, on top of its Return Delay Time (s).
DEFAULT_TURNAROUND_S = 20e-6
#: The latency timer of an FTDI adapter set to its best value (s).
DEFAULT_ADAPTER_LATENCY_S = 1e-3


@dataclass(frozen=True)
class Verdict:
    level: str  # "ok" | "warn" | "refuse"
    message: str

    @property
    def ok(self) -> bool:
        return self.level == "ok"


@dataclass(frozen=True)
class BusBudget:
    motors: int
    baud: int
    return_delay_s: float
    turnaround_s: float
    adapter_latency_s: float
    sync_write_bytes: int
    sync_read_bytes: int
    reply_bytes: int  # one status packet (sync, bulk); the combined one's share (fast)
    read_instruction: str = "sync"  # "sync" | "fast" | "bulk"
    write_instruction: str = "sync"  # "sync" | "bulk"
    #: The one combined status packet of a FAST_SYNC_READ (0 otherwise).
    combined_reply_bytes: int = 0

    @property
    def total_bytes(self) -> int:
        replies = (self.combined_reply_bytes if self.read_instruction == "fast"
                   else self.motors * self.reply_bytes)
        return self.sync_write_bytes + self.sync_read_bytes + replies

    @property
    def replies(self) -> int:
        """Status packets per period (each after a return delay and a turnaround)."""
        return 1 if self.read_instruction == "fast" else self.motors

    @property
    def byte_time_s(self) -> float:
        return BITS_PER_BYTE / self.baud

    @property
    def wire_s(self) -> float:
        return self.total_bytes * self.byte_time_s

    @property
    def waits_s(self) -> float:
        """Return delays and turnarounds of all status packets."""
        return self.replies * (self.return_delay_s + self.turnaround_s)

    @property
    def bus_s(self) -> float:
        """Time the bus itself needs per period: the least any adapter can do."""
        return self.wire_s + self.waits_s

    @property
    def cycle_s(self) -> float:
        """Bus time plus one adapter latency (the read waits for the adapter to hand over)."""
        return self.bus_s + self.adapter_latency_s

    def describe(self) -> str:
        write = "SYNC_WRITE" if self.write_instruction == "sync" else "BULK_WRITE"
        read = {"sync": "SYNC_READ", "fast": "FAST_SYNC_READ", "bulk": "BULK_READ"}[
            self.read_instruction]
        replies = (f"one combined status packet of {self.combined_reply_bytes}"
                   if self.read_instruction == "fast"
                   else f"{self.motors} status packets x {self.reply_bytes}")
        return (f"{self.motors} motors at {self.baud} baud: {self.total_bytes} bytes per period "
                f"({write} {self.sync_write_bytes}, {read} {self.sync_read_bytes}, "
                f"{replies}) = "
                f"{self.wire_s * 1e6:.0f} us on the wire + {self.waits_s * 1e6:.0f} us of "
                f"return delay and turnaround = {self.bus_s * 1e6:.0f} us; with the adapter's "
                f"{self.adapter_latency_s * 1e3:g} ms latency {self.cycle_s * 1e6:.0f} us")

    def check(self, rate_hz: float) -> Verdict:
        """``refuse`` when the bus alone cannot carry one period's traffic within the period,
        ``warn`` when it can but not with the adapter's latency on top, ``ok`` otherwise."""
        period = 1.0 / rate_hz
        text = f"bus budget for {self.describe()}; the period is {period * 1e6:.0f} us " \
               f"({rate_hz:g} Hz)"
        if self.bus_s > period:
            return Verdict("refuse", f"{text}: the bus cannot meet the loop rate; use a higher "
                           "baud rate (4 Mbaud), Return Delay Time 0, or a lower rate")
        if self.cycle_s > period:
            return Verdict("warn", f"{text}: the bus fits but the adapter's latency does not, so "
                           "periods will overrun now and then; set the adapter's latency timer "
                           "to 1 ms and watch the measured cycle times")
        return Verdict("ok", f"{text}: fits")


def bus_budget(motors: int, baud: int, *, return_delay_s: float = 0.0,
               turnaround_s: float = DEFAULT_TURNAROUND_S,
               adapter_latency_s: float = DEFAULT_ADAPTER_LATENCY_S,
               read_length: int = STATE_LENGTH, write_length: int = 2,
               read_instruction: str = "sync", write_instruction: str = "sync") -> BusBudget:
    """The budget of one period: one write of ``write_length`` bytes per motor
    (``write_instruction`` "sync" or "bulk"), one read of ``read_length`` bytes per motor
    (``read_instruction`` "sync", "fast" or "bulk"; see the module docstring)."""
    if motors < 1 or baud <= 0:
        raise ValueError(f"need at least one motor and a positive baud rate, got {motors}, {baud}")
    if read_instruction not in ("sync", "fast", "bulk") or write_instruction not in ("sync",
                                                                                     "bulk"):
        raise ValueError(f"unknown transfer {read_instruction!r} / {write_instruction!r}")
    write = (14 + motors * (1 + write_length) if write_instruction == "sync"
             else 10 + motors * (5 + write_length))
    request = 10 + 5 * motors if read_instruction == "bulk" else 14 + motors
    return BusBudget(motors, baud, return_delay_s, turnaround_s, adapter_latency_s,
                     write, request, 11 + read_length, read_instruction, write_instruction,
                     8 + motors * (read_length + 4) if read_instruction == "fast" else 0)
