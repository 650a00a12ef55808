"""The cache of tests/embedded_build.py: a source shared by several libraries is compiled once,
yet no library links a stale object, a test's own folder still gets its own file, and warnings
stay errors. Each test builds a few lines of C into a temporary cache of its own."""

from __future__ import annotations

import ctypes
import subprocess
import threading

import pytest

from tests import embedded_build
from tests.embedded_build import build_library, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler")

SHARED = ("shared.c",
          '#include "value.h"\nint shared(void);\nint shared(void) { return VALUE; }\n')
A = ("a.c", "int shared(void);\nint a(void);\nint a(void) { return shared() + 1; }\n")
B = ("b.c", "int shared(void);\nint b(void);\nint b(void) { return shared() + 2; }\n")


@pytest.fixture
def compiles(tmp_path, monkeypatch):
    """A cache in ``tmp_path`` and the list of sources the compiler is asked to compile."""
    monkeypatch.setattr(embedded_build, "CACHE", tmp_path / "cache")
    seen: list[str] = []
    run = subprocess.run

    def counting(command, *args, **kwargs):
        if "-c" in command:
            seen.append(command[command.index("-c") + 1].rsplit("/", 1)[-1])
        return run(command, *args, **kwargs)

    monkeypatch.setattr(embedded_build.subprocess, "run", counting)
    return seen


def header(folder, value: int):
    folder.mkdir(exist_ok=True)
    (folder / "value.h").write_text(f"#define VALUE {value}\n")
    return folder


def test_a_source_shared_by_two_libraries_is_compiled_once(tmp_path, compiles):
    inc = header(tmp_path / "inc", 40)
    a = build_library("a", [SHARED, A], ("-O2",), include=[inc])
    b = build_library("b", [SHARED, B], ("-O2", "-lm"), include=[inc])  # -lm: the link alone
    assert sorted(compiles) == ["a.c", "b.c", "shared.c"]
    assert ctypes.CDLL(str(a)).a() == 41
    assert ctypes.CDLL(str(b)).b() == 42
    assert build_library("a", [SHARED, A], ("-O2",), include=[inc]) == a
    assert len(compiles) == 3  # nothing compiled again


def test_other_compile_flags_compile_the_source_again(tmp_path, compiles):
    inc = header(tmp_path / "inc", 40)
    build_library("a", [SHARED, A], ("-O2",), include=[inc])
    build_library("a", [SHARED, A], ("-O1",), include=[inc])
    assert sorted(compiles) == ["a.c", "a.c", "shared.c", "shared.c"]


def test_a_changed_header_is_never_linked_stale(tmp_path, compiles):
    inc = header(tmp_path / "inc", 40)
    first = build_library("a", [SHARED, A], include=[inc])
    header(inc, 50)
    second = build_library("a", [SHARED, A], include=[inc])
    assert second != first
    assert ctypes.CDLL(str(second)).a() == 51
    # Every object of that folder is rebuilt, a.c too, though it includes nothing.
    assert sorted(compiles) == ["a.c", "a.c", "shared.c", "shared.c"]


def test_the_same_headers_elsewhere_share_objects_not_the_library(tmp_path, compiles):
    one = build_library("a", [SHARED, A], include=[header(tmp_path / "one", 40)])
    two = build_library("a", [SHARED, A], include=[header(tmp_path / "two", 40)])
    assert sorted(compiles) == ["a.c", "shared.c"]
    assert one != two  # each folder loads a file of its own: its statics start afresh
    assert ctypes.CDLL(str(two)).a() == 41


def test_a_warning_is_an_error_with_the_compilers_words(tmp_path, compiles):
    unused = ("unused.c", "int f(void);\nint f(void) { int x; return 1; }\n")
    with pytest.raises(RuntimeError, match="unused variable"):
        build_library("bad", [unused])
    assert not list((tmp_path / "cache").glob("bad-*/libbad.so"))
    assert not list((tmp_path / "cache").glob("obj/unused-*/unused.o"))


def test_two_builders_of_one_library_at_once_both_end_with_it(tmp_path, compiles):
    inc = header(tmp_path / "inc", 40)
    paths, errors = [], []

    def build():
        try:
            paths.append(build_library("a", [SHARED, A], include=[inc]))
        except Exception as error:  # noqa: BLE001 - reported by the assertion below
            errors.append(error)

    threads = [threading.Thread(target=build) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == [] and len(paths) == 2 and paths[0] == paths[1]
    assert ctypes.CDLL(str(paths[0])).a() == 41
    assert not list((tmp_path / "cache").rglob(".*"))  # no partial file left behind
