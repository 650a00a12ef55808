"""``cochlea-codegen``: regenerate ``generated_c/`` (or check it is fresh, ``--check``)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..dynamixel.embedded_drives import write_drive_tables
from ..errors import EXIT_USER_ERROR, CochleaError
from ..kernels.generate import CONFIG, check, generate, load_config
from ..sim.embedded import write_embedded


def write_embedded_folder(config, folder) -> list[Path]:
    """generated_c/embedded/: every embedded scenario's controller, then the Dynamixel drive
    tables of the robots (embedded/core/drives.h reads them)."""
    return sorted(write_embedded(config, folder) + write_drive_tables(folder))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cochlea-codegen",
        description="Regenerate the C kernels (generated_c/) from the robot descriptions in "
                    "cochlea/data/robots/ and the configuration cochlea/data/codegen/kernels.toml, "
                    "and the scenarios' embedded controllers (generated_c/embedded/).",
        epilog="Then `make lib` builds build/libcochlea.so (no Python needed).")
    parser.add_argument("--config", type=Path, default=CONFIG, help="generator configuration")
    parser.add_argument("--out", type=Path, help="output folder (default: the configuration's)")
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary folder and exit 1 if generated_c/ "
                             "differs (stale)")
    args = parser.parse_args(argv)
    try:
        config = load_config(args.config)
        if args.check:
            differ = check(config, write_embedded_folder)
            if differ:
                print(f"cochlea-codegen: {config.output} is stale; these files differ: "
                      + ", ".join(differ) + ". Run cochlea-codegen and commit the result.",
                      file=sys.stderr)
                return 1
            print(f"cochlea-codegen: {config.output} is up to date")
            return 0
        start = time.perf_counter()
        paths = generate(config, args.out, write_embedded_folder)
    except CochleaError as exc:
        print(f"cochlea-codegen: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    size = sum(p.stat().st_size for p in paths)
    print(f"cochlea-codegen: {len(paths)} files, {size / 1024:.0f} KiB in "
          f"{paths[0].parent} ({time.perf_counter() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
