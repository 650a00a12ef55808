"""cochlea-dxl's subcommands: bring-up of the real motors (issue 15)."""
