"""Compile a folder of generated C into its kernel library, as ``make lib`` compiles
``generated_c/`` (the same flags: ``-std=c99 -fPIC -Wall -Wextra -Werror``, ``-O2``), from
Python: what ``cochlea-codegen --description ... --scenario ... --out DIR`` runs after writing
``DIR``, so a user's kernels need no Makefile.

Each ``.c`` file is compiled on its own (up to ``jobs`` at once: the cores), into a temporary
folder, then linked into ``DIR/libcochlea.so``; the library is replaced whole (written beside
it, then renamed), so a failed build leaves the previous one. ``$CC`` names the compiler
(default ``cc``) and ``$CFLAGS_C`` the optimisation flags (default ``-O2``), as in the Makefile.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .library import LIBRARY_NAME, LibraryError

FLAGS = ("-std=c99", "-fPIC", "-Wall", "-Wextra", "-Werror")


def compiler() -> list[str]:
    """``$CC`` (default ``cc``) as an argument list."""
    return shlex.split(os.environ.get("CC") or "cc")


def _run(command: list[str]) -> None:
    try:
        done = subprocess.run(command, capture_output=True, text=True)
    except OSError as exc:
        raise LibraryError(f"cannot run the C compiler {command[0]!r} ({exc.strerror or exc}): "
                           "install one (cc, gcc or clang) or set $CC") from None
    if done.returncode:
        first = (done.stderr or done.stdout).strip().splitlines()
        raise LibraryError(f"{' '.join(command[:2])} ... failed (exit {done.returncode}): "
                           + (first[0] if first else "no message"))


def compile_library(folder: str | Path, jobs: int | None = None) -> Path:
    """Compile every ``folder/*.c`` into ``folder/libcochlea.so``; return its path."""
    folder = Path(folder)
    sources = sorted(folder.glob("*.c"))
    if not sources:
        raise LibraryError(f"{folder} has no .c files to compile: generate them first")
    cc = compiler()
    optimise = shlex.split(os.environ.get("CFLAGS_C") or "-O2")
    jobs = max(1, jobs or os.cpu_count() or 1)
    target = folder / LIBRARY_NAME
    with tempfile.TemporaryDirectory(prefix="cochlea-build-") as tmp:
        objects = [Path(tmp) / f"{src.stem}.o" for src in sources]
        # Largest first: the long compilations start at once and the short ones fill in.
        order = sorted(range(len(sources)), key=lambda i: -sources[i].stat().st_size)
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            list(pool.map(lambda i: _run([*cc, *optimise, *FLAGS, "-c", str(sources[i]),
                                          "-o", str(objects[i])]), order))
        staged = Path(tmp) / LIBRARY_NAME
        _run([*cc, "-shared", "-o", str(staged), *map(str, objects), "-lm"])
        partial = folder / f".{LIBRARY_NAME}.new"
        shutil.copyfile(staged, partial)
        os.replace(partial, target)
    return target
