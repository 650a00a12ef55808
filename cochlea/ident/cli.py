"""The command-line parser of ``cochlea-identify`` and ``cochlea-excite``: a malformed option
(an unknown one, ``--harmonics 1e9`` for a whole number) is one line on stderr and exit code 2,
like every other refusal, not argparse's usage block."""

from __future__ import annotations

import argparse
import sys

from ..errors import EXIT_USER_ERROR, printable


class OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):  # noqa: D102 (argparse's hook)
        print(printable(f"{self.prog}: {message} (see {self.prog} --help)"), file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
