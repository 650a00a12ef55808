"""Dynamixel hardware bridge and virtual Dynamixel chain (Protocol 2.0).

Modules, one concept each:

* :mod:`~cochlea.dynamixel.control_table` -- the motor models (the lineup's data files in
  ``models/``) and their control tables: addresses, sizes, access, ranges, units;
* :mod:`~cochlea.dynamixel.protocol` -- Protocol 2.0 frames: CRC-16, byte stuffing, instruction
  builders and a streaming packet parser that reports every failure as a value;
* :mod:`~cochlea.dynamixel.drives` -- joint <-> motor conversions and the torque/current fit;
* :mod:`~cochlea.dynamixel.budget` -- the bytes and time one control period needs on the bus;
* :mod:`~cochlea.dynamixel.port` -- the serial port (pyserial), read into preallocated buffers;
* :mod:`~cochlea.dynamixel.bridge` -- :class:`DynamixelBackend`, the backend the loop drives;
* :mod:`~cochlea.dynamixel.emulator` -- ``cochlea-emulator``, the motors of a description on a
  pseudo-terminal, moved by the plant model in real time.

docs/dynamixel.md describes the start-up and shut-down sequences, the units and fits, the bus
budget, the emulator and how to run against real hardware. This package module imports
nothing, so :mod:`cochlea.robots.description` (a lower layer) can use the control tables.
"""
