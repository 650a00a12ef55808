"""Builds C sources of ``embedded/`` into shared libraries for the tests that load them through
ctypes (or run them in a subprocess under the sanitizers).

Each source is compiled once into an object cached in ``build/embedded-tests/obj/<stem>-<key>/``,
where the key hashes the compiler (name, resolved path, modification time), the compile flags,
the source's name and text and every header of the include folders (by the folder's place in
the search order, name and text, not the folder's path). A library links cached objects into
``build/embedded-tests/<name>-<key>/lib<name>.so``, keyed by those object keys, the link-only
flags (``-l``, ``-L``, ``-Wl,``: not given to the compiler) and the include folders' paths (a
test that builds in a temporary folder of its own still loads a file of its own).

So the core and the generated controllers, which test_embedded_loop, test_embedded_hardening
and test_embedded_float each link with a harness of their own, are compiled with -O2 once, not
once per library (issue 30: on a fresh clone those were three identical builds of ~5.5 s each);
a library is rebuilt only when a source, a header or a flag changes; each flavour (plain,
ASan+UBSan, ...) has objects of its own. A change to any header of an include folder rebuilds
every object compiled against that folder: coarse, but a header that a source includes can
never leave a stale object behind.

Every file (source copy, object, library) is written under a temporary name and renamed, so two
test processes building the same key at once both end with whole files. Warnings are errors in
every compile (:data:`WARNINGS`).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import threading
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
#: Flags for the link alone: libraries and linker options.
LINK_ONLY = ("-l", "-L", "-Wl,")


def compiler() -> str | None:
    """The C compiler the tests use (``$CC`` or gcc), or None when there is none."""
    cc = os.environ.get("CC", "gcc")
    return cc if shutil.which(cc) else None


def _key(*parts: object) -> str:
    """A short hash of ``parts`` (their repr), for a cache folder's name."""
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def _writer() -> str:
    """This process and thread, to name a file being written: no two writers share one."""
    return f"{os.getpid()}-{threading.get_ident()}"


def _write_whole(path: Path, text: str) -> None:
    """Write ``path`` under a temporary name and rename it, so that a compiler reading it while
    another process writes the same text sees one whole file or the other, never a truncated
    one."""
    partial = path.with_name(f".{path.name}.{_writer()}")
    partial.write_text(text)
    os.replace(partial, path)


def _compiler_identity(cc: str) -> tuple[str, str, int]:
    """The compiler's name, resolved path and modification time: a new compiler is a new key."""
    real = os.path.realpath(shutil.which(cc) or cc)
    return cc, real, os.stat(real).st_mtime_ns


def _split_flags(flags: Sequence[str]) -> tuple[list[str], list[str]]:
    """``flags`` as (compile and link, link only): libraries and linker options are not given
    to the compiler, where they would only earn an "unused" warning and split the cache."""
    link_only = [f for f in flags if f.startswith(LINK_ONLY)]
    return [f for f in flags if not f.startswith(LINK_ONLY)], link_only


def _compile_object(cc: str, key: str, filename: str, text: str, compile_flags: list[str],
                    include: Sequence[Path]) -> Path:
    """The object of one source, compiled once per ``key`` (compiler, flags, source, headers)."""
    stem = Path(filename).stem
    folder = CACHE / "obj" / f"{stem}-{key}"
    obj = folder / f"{stem}.o"
    if obj.exists():
        return obj
    folder.mkdir(parents=True, exist_ok=True)
    source = folder / filename
    _write_whole(source, text)
    partial = folder / f".{stem}.{_writer()}.o"
    command = [cc, *compile_flags, *(f"-I{d}" for d in include), "-c", str(source),
               "-o", str(partial)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr}")
    os.replace(partial, obj)
    return obj


def build_library(name: str, sources: Sequence[Path | tuple[str, str]],
                  flags: Sequence[str] = ("-O2",), include: Sequence[Path] = ()) -> Path:
    """Compile ``sources`` into ``lib<name>.so`` with ``flags`` (plus -fPIC -shared and
    :data:`WARNINGS`) and return its path. A source is a file, or ``(filename, text)`` for a
    small harness a test writes itself. Each source is compiled into an object of its own,
    cached by its own key, so a source another library compiled with the same flags and headers
    is not compiled again. Raises ``RuntimeError`` with the compiler's output when a build
    fails."""
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler (set CC or install gcc)")
    identity = _compiler_identity(cc)
    texts = []
    for source in sources:
        if isinstance(source, tuple):
            texts.append(source)
        else:
            texts.append((Path(source).name, Path(source).read_text()))
    # The headers by their folder's place in the search order, not its path: the same headers
    # in another temporary folder make the same objects.
    headers = [(i, h.name, h.read_text()) for i, folder in enumerate(include)
               for h in sorted(Path(folder).glob("*.h"))]
    compile_flags, link_only = _split_flags(flags)
    compile_flags = [*WARNINGS, *compile_flags, "-fPIC"]
    keys = [_key(identity, compile_flags, filename, text, headers) for filename, text in texts]
    # The include folders' paths do name the library (as they always did): a test that builds
    # in its own temporary folder loads its own file, so a static of the library starts afresh
    # (dlopen hands back the loaded copy for a path it has seen). Linking is cheap.
    library_key = _key(identity, compile_flags, link_only, keys, [str(d) for d in include])
    folder = CACHE / f"{name}-{library_key}"
    library = folder / f"lib{name}.so"
    if library.exists():
        return library
    objects = [_compile_object(cc, key, filename, text, compile_flags, include)
               for key, (filename, text) in zip(keys, texts, strict=True)]
    folder.mkdir(parents=True, exist_ok=True)
    partial = folder / f".lib{name}.{_writer()}.so"
    command = [cc, *compile_flags, "-shared", *map(str, objects), *link_only, "-o", str(partial)]
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
