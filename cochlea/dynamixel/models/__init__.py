"""The Dynamixel lineup as data: one TOML file per model family and one per control-table
layout, read by :func:`cochlea.dynamixel.control_table.load_models` through
:mod:`importlib.resources` (docs/dynamixel.md, "Models")."""
