"""Builds C sources of ``embedded/`` into shared libraries for the tests that load them through
ctypes (or run them in a subprocess under the sanitizers).

A library is cached in ``build/embedded-tests/<key>/`` where the key hashes the compiler, the
flags and the sources' contents, so each flavour (plain, ASan+UBSan, ...) is compiled once and
rebuilt only when a source changes. The library is written under a temporary name and renamed,
so two test processes building the same key at once both end with a whole file.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EMBEDDED = ROOT / "embedded"
CACHE = ROOT / "build" / "embedded-tests"

#: What the sanitizer tests use: every report is fatal, so a bad access ends the process.
SANITIZE = ("-O1", "-g", "-fsanitize=address,undefined", "-fno-omit-frame-pointer",
            "-fno-sanitize-recover=all")
#: Warnings as errors in every build, so a test build never hides what a target build shows.
WARNINGS = ("-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-Wconversion")


def compiler() -> str | None:
    """The C compiler the tests use (``$CC`` or gcc), or None when there is none."""
    cc = os.environ.get("CC", "gcc")
    return cc if shutil.which(cc) else None


def build_library(name: str, sources: Sequence[Path | tuple[str, str]],
                  flags: Sequence[str] = ("-O2",), include: Sequence[Path] = ()) -> Path:
    """Compile ``sources`` into ``lib<name>.so`` with ``flags`` (plus -fPIC -shared and
    :data:`WARNINGS`) and return its path. A source is a file, or ``(filename, text)`` for a
    small harness a test writes itself. Raises ``RuntimeError`` with the compiler's output
    when the build fails."""
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler (set CC or install gcc)")
    texts = []
    for source in sources:
        if isinstance(source, tuple):
            texts.append(source)
        else:
            texts.append((Path(source).name, Path(source).read_text()))
    headers = sorted(p for folder in include for p in Path(folder).glob("*.h"))
    command_flags = [*WARNINGS, *flags, "-fPIC", "-shared"]
    key = hashlib.sha256(repr((cc, command_flags, texts,
                               [(str(h), h.read_text()) for h in headers])).encode())
    folder = CACHE / f"{name}-{key.hexdigest()[:16]}"
    library = folder / f"lib{name}.so"
    if library.exists():
        return library
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for filename, text in texts:
        path = folder / filename
        path.write_text(text)
        paths.append(path)
    partial = folder / f".lib{name}.{os.getpid()}.so"
    command = [cc, *command_flags, *(f"-I{d}" for d in include), *map(str, paths),
               "-o", str(partial)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr}")
    os.replace(partial, library)
    return library


def sanitizer_environment() -> dict[str, str]:
    """The environment of a Python subprocess that loads an ASan-instrumented library: the ASan
    runtime preloaded (it must come before libc's allocator), Python's small-object allocator
    off so that every buffer Python hands to C is a malloc block with ASan redzones around it,
    and leak checking off (the interpreter itself keeps memory until exit)."""
    cc = compiler() or "gcc"
    libasan = subprocess.run([cc, "-print-file-name=libasan.so"], capture_output=True,
                             text=True).stdout.strip()
    env = dict(os.environ)
    env["LD_PRELOAD"] = libasan
    env["ASAN_OPTIONS"] = "detect_leaks=0:abort_on_error=0:exitcode=86"
    env["UBSAN_OPTIONS"] = "print_stacktrace=1:halt_on_error=1"
    env["PYTHONMALLOC"] = "malloc"
    return env
