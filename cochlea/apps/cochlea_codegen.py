"""``cochlea-codegen``: regenerate ``generated_c/`` (or check it is fresh, ``--check``)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..console import tolerate_closed_stdout
from ..dynamixel.embedded_drives import write_drive_tables
from ..errors import EXIT_USER_ERROR, CochleaError
from ..kernels.generate import CONFIG, check, generate, load_config
from ..sim.embedded import write_embedded
from .outputs import check_folder


def write_embedded_folder(config, folder) -> list[Path]:
    """generated_c/embedded/: every embedded scenario's controller, then the Dynamixel drive
    tables of the robots (embedded/core/drives.h reads them)."""
    return sorted(write_embedded(config, folder) + write_drive_tables(folder))


def _load_config(path: Path):
    if path.is_dir():
        raise CochleaError(f"--config {path} is a folder: name the generator's TOML "
                           "configuration file")
    try:
        return load_config(path)
    except UnicodeDecodeError as exc:
        raise CochleaError(f"--config {path}: not UTF-8 text (byte {exc.start}): save the "
                           "configuration as UTF-8") from None


def _check_out(out: Path, option: str) -> None:
    """The output folder, checked before anything is generated. The generator replaces every
    file at the folder's top level, so a folder that holds other files (it has no manifest.c,
    the mark of generated_c/) is refused rather than emptied."""
    check_folder(out, option, empty=False)
    if out.is_dir() and not (out / "manifest.c").is_file() and any(
            p.is_file() for p in out.iterdir()):
        raise CochleaError(f"{option} {out} holds files that cochlea-codegen did not generate "
                           "(no manifest.c), and it replaces every file there: choose a new "
                           "or empty folder, or a generated_c/ folder")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cochlea-codegen",
        description="Regenerate the C kernels (generated_c/) from the robot descriptions in "
                    "models/robots/ and the configuration codegen/kernels.toml, "
                    "and the scenarios' embedded controllers (generated_c/embedded/).",
        epilog="Then `make lib` builds build/libcochlea.so (no Python needed).")
    parser.add_argument("--config", type=Path, default=CONFIG, help="generator configuration")
    parser.add_argument("--out", type=Path, help="output folder (default: the configuration's)")
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary folder and exit 1 if generated_c/ "
                             "differs (stale)")
    args = parser.parse_args(argv)
    tolerate_closed_stdout()
    try:
        config = _load_config(args.config)
        if args.check:
            differ = check(config, write_embedded_folder)
            if differ:
                print(f"cochlea-codegen: {config.output} is stale; these files differ: "
                      + ", ".join(differ) + ". Run cochlea-codegen and commit the result.",
                      file=sys.stderr)
                return 1
            print(f"cochlea-codegen: {config.output} is up to date")
            return 0
        out = args.out if args.out is not None else config.output
        _check_out(out, "--out" if args.out is not None else f"{config.path}: output")
        start = time.perf_counter()
        try:
            paths = generate(config, out, write_embedded_folder)
        except OSError as exc:  # a full disk, or the folder changed under us
            raise CochleaError(f"cannot write {out} ({exc.strerror or exc}); it is as it was: "
                               "free some space and run cochlea-codegen again") from None
    except CochleaError as exc:
        print(f"cochlea-codegen: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    size = sum(p.stat().st_size for p in paths)
    print(f"cochlea-codegen: {len(paths)} files, {size / 1024:.0f} KiB in "
          f"{paths[0].parent} ({time.perf_counter() - start:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
