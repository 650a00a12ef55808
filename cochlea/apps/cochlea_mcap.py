"""``cochlea-mcap RUN_DIR [--out FILE.mcap]``: a run folder's log as an MCAP file of standard
ROS 2 messages (CDR, ``ros2msg`` schemas) that Foxglove and ``ros2 bag`` read; default
``RUN_DIR/log.mcap``. Topics and types: docs/logs.md.

Bad input -- a folder that is not a finished run, a damaged or truncated log, a scenario (so a
description) that can no longer be loaded, an output that exists and is not a regular file,
an output that cannot be written -- is one line on stderr and exit code 2 (EXIT_USER_ERROR);
nothing is left under the output's name (the file is written under a hidden temporary name in
the same folder and renamed once complete, an existing file being replaced only then).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..console import OneLineParser
from ..errors import EXIT_USER_ERROR, CochleaError, printable
from ..export.run_log import open_run
from ..export.to_mcap import Exporter
from .outputs import atomic_path, check_output_file, interrupted_exit, signals_unwind

PROG = "cochlea-mcap"


def check_output(path: Path, run_dir: Path | None = None) -> None:
    """Refuse an output that exists and is not a regular file, or whose folder is missing or
    not writable, or that is one of the files of ``run_dir`` (the run being read); creates
    nothing."""
    check_output_file(path, "--out", ".mcap", run_dir=run_dir)


def export(run_dir: Path, out: Path | None = None) -> tuple[Path, dict[str, int]]:
    """Write ``run_dir``'s log to ``out`` (default ``run_dir/log.mcap``); the messages per
    topic."""
    if out is not None:
        check_output(Path(out), Path(run_dir))  # before the run is read at all
    run = open_run(run_dir)
    out = Path(out) if out is not None else run.folder / "log.mcap"
    check_output(out, run.folder)
    try:
        # A logged inf or NaN (a pose of a run stopped by non-finite) is exported as logged,
        # without numpy's warnings on the console (one line is all a tool prints).
        with atomic_path(out) as tmp, open(tmp, "wb") as stream, \
                np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            counts = Exporter(run, stream).export()
    except OSError as exc:
        raise CochleaError(f"--out {out}: cannot write it ({exc.strerror or exc}); nothing "
                           "was left under that name") from None
    return out, counts


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR",
                        help="a run's output folder (cochlea-run or the embedded program)")
    parser.add_argument("--out", type=Path, default=None, metavar="FILE.mcap",
                        help="the MCAP file to write (default: RUN_DIR/log.mcap)")
    args = parser.parse_args(argv)
    try:
        with signals_unwind():  # SIGTERM, SIGHUP: as Ctrl-C, the temporary file removed
            out, counts = export(args.run_dir, args.out)
    except CochleaError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt as exc:
        word, code = interrupted_exit(exc)
        print(f"{PROG}: {word}; nothing written", file=sys.stderr)
        return code
    print(printable(f"{PROG}: wrote {out}: {sum(counts.values())} messages on "
                    f"{len(counts)} topics"))
    return 0


__all__ = ["main", "export", "check_output"]

if __name__ == "__main__":
    sys.exit(main())
