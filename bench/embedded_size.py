"""``make embedded-size``: the embedded core built for each target, with its code size and the
worst stack of each entry point, written to docs/embedded.md and bench/embedded_size.json.

The core is every ``embedded/core/*.c`` and every ``generated_c/embedded/*.c`` (picked up by
glob, so a new file is in it as soon as it lands), compiled to objects with the portability
flags of issue 12 (C99, pedantic, freestanding, no builtins, warnings as errors; in float also
``-Wdouble-promotion -Wfloat-conversion``). No linking: the objects need no libc, compiler
runtime or start-up code, and the numbers are the core's own.

Targets: the host (``$CC`` or ``cc``), a Cortex-M4F (Thumb-2, bare metal, single-precision FPU,
hard-float ABI) and aarch64 Linux, both through ``zig cc`` from the ``ziglang`` wheel (the test
extra). tests/test_embedded_portability.py uses this module's builder and ELF reader.

- **size**: text (code and read-only data), data and bss, the sums of the objects' ELF
  sections by their flags, as binutils' ``size`` counts them (a linked image adds alignment,
  start-up code, libm, the HAL, and drops unused functions with ``--gc-sections``);
- **stack**: each function's frame from the compiler's ``-fstack-usage`` file; the worst stack
  of an entry point adds the deepest chain of its direct callees, through a call graph read
  from the objects' relocations (``-ffunction-sections`` puts every function in its own section,
  so every call between two functions is a relocation). Not included: the frames of libm and
  of the compiler's run-time helpers, and calls through pointers (the HAL's callbacks).

The output is deterministic for given compilers (sorted, no timestamps); compile times are
printed, not written.

    make embedded-size
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import textwrap
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT)]

from cochlea.kernels.embedded import MATH_FUNCTIONS

CORE = ROOT / "embedded" / "core"
GENERATED = ROOT / "generated_c" / "embedded"
INCLUDE = (CORE, GENERATED)
DOC = ROOT / "docs" / "embedded.md"
JSON_OUT = ROOT / "bench" / "embedded_size.json"
BEGIN, END = "<!-- embedded-size:begin -->", "<!-- embedded-size:end -->"

#: Issue 12's portability flags, in every build.
STRICT = ("-std=c99", "-pedantic", "-ffreestanding", "-fno-builtin", "-Wall", "-Wextra",
          "-Werror")
#: Added in the float build.
FLOAT = ("-DCOCHLEA_FLOAT", "-Wdouble-promotion", "-Wfloat-conversion")
#: The size build: small code, one section per function (the call graph needs it, and a
#: firmware build links with --gc-sections the same way).
SIZE_FLAGS = ("-Os", "-ffunction-sections", "-fdata-sections")

#: The libm functions the core may call: those the generated code may call and nearbyint
#: (drives.c), each in double and in float.
_MATH = (*MATH_FUNCTIONS, "nearbyint")
LIBM = frozenset(_MATH) | frozenset(f + "f" for f in _MATH)
#: The compiler's run-time floating-point helpers of the ARM run-time ABI (libgcc or
#: compiler-rt): a Cortex-M4F has no double-precision unit, so double arithmetic (the estimate
#: is kept in double in both builds) calls them. Their memory helpers (__aeabi_memcpy and
#: friends) are not in this set: they are libc in disguise.
AEABI = frozenset(
    [f"__aeabi_{p}{op}" for p in "df" for op in (
        "add", "sub", "rsub", "mul", "div", "neg", "cmpeq", "cmplt", "cmple", "cmpge", "cmpgt",
        "cmpun", "rcmple")]
    + [f"__aeabi_c{p}{op}" for p in "df" for op in ("cmpeq", "cmple", "rcmple")]
    + [f"__aeabi_{a}2{b}" for a in "df" for b in ("iz", "uiz", "lz", "ulz")]
    + [f"__aeabi_{a}2{b}" for a in ("i", "ui", "l", "ul") for b in "df"]
    + ["__aeabi_d2f", "__aeabi_f2d", "__aeabi_d2h", "__aeabi_f2h", "__aeabi_h2f"])
#: What the objects of the core may leave undefined.
ALLOWED = LIBM | AEABI
#: Single-precision helpers: a float build for an FPU target must not call them.
SOFT_SINGLE = frozenset(n for n in AEABI if re.match(r"__aeabi_c?f[a-z]|__aeabi_u?i2f$", n))



# --------------------------------------------------------------------------------------------
# Targets and builds
# --------------------------------------------------------------------------------------------


def core_sources() -> list[Path]:
    """Every C file of the portable core: the runtime, then the generated files."""
    return sorted(CORE.glob("*.c")) + sorted(GENERATED.glob("*.c"))


@dataclass(frozen=True)
class Target:
    """A compiler and the flags that select its target."""

    name: str
    title: str
    zig: bool  # compiled with ``zig cc`` (else the host's cc)
    flags: tuple[str, ...] = ()
    machine: int | None = None  # the ELF e_machine its objects must have (None: any)
    bits: int | None = None
    #: zig ships no libc for a bare-metal target: its musl headers for this architecture
    #: provide <math.h> (declarations only; a firmware links newlib's or picolibc's libm).
    math_headers: str | None = None


EM_X86_64, EM_ARM, EM_AARCH64 = 62, 40, 183
TARGETS = {
    "host": Target("host", f"host {platform.machine()}", zig=False),
    "cortex-m4f": Target(
        "cortex-m4f", "Cortex-M4F", zig=True,
        # zig's cortex_m4 has no FPU (LLVM's has): without +vfp4d16sp the objects say
        # hard-float ABI but do every float operation in software.
        flags=("-target", "thumb-freestanding-eabihf", "-mcpu=cortex_m4+vfp4d16sp",
               "-mfloat-abi=hard", "-fno-unwind-tables", "-fno-asynchronous-unwind-tables"),
        machine=EM_ARM, bits=32, math_headers="arm-linux-musl"),
    "aarch64": Target("aarch64", "aarch64 Linux", zig=True, flags=("-target", "aarch64-linux-gnu"),
                      machine=EM_AARCH64, bits=64),
}
#: What the size report builds, in its column order.
BUILDS = (("host", "double"), ("cortex-m4f", "float"), ("cortex-m4f", "double"),
          ("aarch64", "float"), ("aarch64", "double"))


def host_cc() -> str | None:
    cc = os.environ.get("CC", "cc")
    return cc if shutil.which(cc) else None


def have_zig() -> bool:
    return importlib.util.find_spec("ziglang") is not None


def _zig(*args: str) -> list[str]:
    return [sys.executable, "-m", "ziglang", *args]


def compiler_version(target: Target) -> str:
    """One line naming the compiler (for zig: its version and the clang inside)."""
    if target.zig:
        zig = subprocess.run(_zig("version"), capture_output=True, text=True, check=True)
        clang = subprocess.run(_zig("cc", "--version"), capture_output=True, text=True,
                               check=True)
        return f"zig {zig.stdout.strip()} ({clang.stdout.splitlines()[0].strip()})"
    done = subprocess.run([host_cc() or "cc", "--version"], capture_output=True, text=True,
                          check=True)
    return done.stdout.splitlines()[0].strip()


def _zig_lib_dir() -> Path:
    env = subprocess.run(_zig("env"), capture_output=True, text=True, check=True).stdout
    match = re.search(r'lib_dir"?\s*[=:]\s*"([^"]+)"', env)
    if not match:
        raise RuntimeError(f"cannot find zig's lib_dir in `zig env`:\n{env}")
    return Path(match.group(1))


class BuildError(RuntimeError):
    """A source did not compile, or the compiler said something it must not."""


@dataclass
class Build:
    target: Target
    precision: str
    objects: list[Path]
    seconds: float  # wall time of the whole build (sources compiled in parallel)
    stack_files: dict[Path, Path] = field(default_factory=dict)  # object -> its .su
    assembly: dict[Path, Path] = field(default_factory=dict)  # object -> its assembly (-S)


def compile_core(target: Target, precision: str, out: Path, flags: tuple[str, ...] = ("-O2",),
                 stack: bool = False, sources: list[Path] | None = None,
                 jobs: int | None = None) -> Build:
    """Compile the core (or ``sources``) for ``target`` into objects in ``out``, with STRICT
    (and FLOAT in float) plus ``flags``; with ``stack``, one ``.su`` per object. Every source
    is compiled, even after a failure, and a :class:`BuildError` lists all the failures and
    every diagnostic except the known clang float warning."""
    if precision not in ("double", "float"):
        raise ValueError(precision)
    out.mkdir(parents=True, exist_ok=True)
    sources = core_sources() if sources is None else sources
    if target.zig:
        command = _zig("cc", *target.flags)
        if target.math_headers:
            lib = _zig_lib_dir() / "libc" / "include"
            command += ["-isystem", str(lib / target.math_headers),
                        "-isystem", str(lib / "generic-musl")]
        # zig caches C objects and, on a hit, neither compiles nor writes the .su: a fresh
        # cache per build makes every build real (and its time a cold compile).
        env = dict(os.environ, ZIG_GLOBAL_CACHE_DIR=str(out / "zig-cache"),
                   ZIG_LOCAL_CACHE_DIR=str(out / "zig-cache"))
    else:
        cc = host_cc()
        if cc is None:
            raise BuildError("no C compiler (set CC or install cc)")
        command, env = [cc], None
    command += [*STRICT, *(FLOAT if precision == "float" else ()), *flags,
                *(f"-I{d}" for d in INCLUDE)]
    names = [s.stem for s in sources]
    if len(set(names)) != len(names):
        raise BuildError(f"two sources share a name: {names}")

    def one(source: Path) -> tuple[Path, Path | None, str, int]:
        obj = out / f"{source.stem}.o"
        su = out / f"{source.stem}.su"
        extra = []
        if stack:
            extra = (["-Xclang", "-stack-usage-file", "-Xclang", str(su)] if target.zig
                     else ["-fstack-usage"])  # cc writes it beside the object
        done = subprocess.run([*command, *extra, "-c", str(source), "-o", str(obj)],
                              capture_output=True, text=True, env=env)
        return obj, su if stack else None, done.stderr, done.returncode

    def assemble(source: Path) -> tuple[Path, str, int]:
        asm = out / f"{source.stem}.s"
        quiet = ["-Wno-unused-command-line-argument"] if target.zig else []  # zig adds -c
        done = subprocess.run([*command, *quiet, "-S", str(source), "-o", str(asm)],
                              capture_output=True, text=True, env=env)
        return asm, done.stderr, done.returncode

    with ThreadPoolExecutor(max_workers=jobs or os.cpu_count() or 2) as pool:
        start = time.perf_counter()
        results = list(pool.map(one, sources))
        seconds = time.perf_counter() - start
        # The stack report reads the calls through pointers from the assembly: the same
        # compiler and flags, so the same code as the objects.
        assembly = list(pool.map(assemble, sources)) if stack else []
    problems = []
    for source, (_, _, stderr, code) in zip(sources, results):
        lines = [line for line in stderr.splitlines() if re.search(r": (warning|error):", line)]
        if code != 0 or lines:
            shown = source.relative_to(ROOT) if source.is_relative_to(ROOT) else source
            problems.append(f"{shown} (exit {code}):\n{stderr.strip()}")
    if problems:
        raise BuildError(f"{' '.join(command)}\n" + "\n".join(problems))
    build = Build(target, precision, [r[0] for r in results], seconds)
    if stack:
        failed = [f"{s.name}: {a[1]}" for s, a in zip(sources, assembly) if a[2] != 0]
        if failed:
            raise BuildError("assembly failed:\n" + "\n".join(failed))
        build.stack_files = {r[0]: r[1] for r in results}
        build.assembly = {r[0]: a[0] for r, a in zip(results, assembly)}
        # clang writes no .su for an object without functions (a table of scenarios).
        missing = [str(s) for o, s in build.stack_files.items()
                   if not s.exists() and Elf.read(o).defined_functions(local=True)]
        if missing:
            raise BuildError(f"no stack usage file: {missing}")
    return build


# --------------------------------------------------------------------------------------------
# A small ELF reader (relocatable objects, 32 and 64 bit, little endian)
# --------------------------------------------------------------------------------------------

SHT_SYMTAB, SHT_RELA, SHT_NOBITS, SHT_REL = 2, 4, 8, 9
SHT_ARM_ATTRIBUTES = 0x70000003
SHF_WRITE, SHF_ALLOC, SHF_EXECINSTR = 0x1, 0x2, 0x4
STB_LOCAL = 0
STT_OBJECT, STT_FUNC, STT_SECTION = 1, 2, 3
SHN_UNDEF = 0
EF_ARM_ABI_FLOAT_HARD = 0x400
#: Tags of the ARM build attributes (aeabi) this module reads.
TAG_FP_ARCH, TAG_ABI_HARDFP_USE, TAG_ABI_VFP_ARGS = 10, 27, 28


@dataclass(frozen=True)
class Section:
    name: str
    type: int
    flags: int
    offset: int
    size: int
    link: int
    info: int


@dataclass(frozen=True)
class Symbol:
    name: str
    value: int
    size: int
    bind: int
    type: int
    shndx: int


@dataclass(frozen=True)
class Relocation:
    section: int  # the section it patches
    offset: int
    symbol: int  # index into Elf.symbols
    addend: int | None  # None for REL (the addend is in the patched bytes)


class Elf:
    """The parts of an ELF relocatable object this script needs."""

    def __init__(self, data: bytes, name: str = "?"):
        if data[:4] != b"\x7fELF":
            raise ValueError(f"{name}: not an ELF file")
        if data[5] != 1:
            raise ValueError(f"{name}: not little endian")
        self.name = name
        self.bits = {1: 32, 2: 64}[data[4]]
        wide = self.bits == 64
        head = struct.unpack_from("<16sHHIQQQIHHHHHH" if wide else "<16sHHIIIIIHHHHHH", data)
        (_, self.type, self.machine, _, _, _, shoff, self.flags, _, _, _, shentsize, shnum,
         shstrndx) = head
        if shnum == 0 and shoff:
            raise ValueError(f"{name}: extended section numbering is not supported")
        raw = [struct.unpack_from("<IIQQQQIIQQ" if wide else "<IIIIIIIIII", data,
                                  shoff + i * shentsize) for i in range(shnum)]
        names = raw[shstrndx][4] if raw else 0

        def string(table_offset: int, index: int) -> str:
            end = data.index(b"\0", table_offset + index)
            return data[table_offset + index:end].decode()

        self.sections = [Section(string(names, r[0]), r[1], r[2], r[4], r[5], r[6], r[7])
                         for r in raw]
        self._data = data
        self.symbols: list[Symbol] = []
        self.relocations: list[Relocation] = []
        for section in self.sections:
            if section.type == SHT_SYMTAB:
                strtab = self.sections[section.link].offset
                size = 24 if wide else 16
                for i in range(section.size // size):
                    at = section.offset + i * size
                    if wide:
                        n, info, _, shndx, value, sz = struct.unpack_from("<IBBHQQ", data, at)
                    else:
                        n, value, sz, info, _, shndx = struct.unpack_from("<IIIBBH", data, at)
                    self.symbols.append(Symbol(string(strtab, n), value, sz, info >> 4,
                                               info & 0xF, shndx))
        for section in self.sections:
            if section.type in (SHT_REL, SHT_RELA):
                rela = section.type == SHT_RELA
                fmt = ("<QQq" if rela else "<QQ") if wide else ("<IIi" if rela else "<II")
                size = struct.calcsize(fmt)
                for i in range(section.size // size):
                    entry = struct.unpack_from(fmt, data, section.offset + i * size)
                    sym = entry[1] >> 32 if wide else entry[1] >> 8
                    self.relocations.append(Relocation(section.info, entry[0], sym,
                                                       entry[2] if rela else None))

    @classmethod
    def read(cls, path: Path) -> Elf:
        return cls(Path(path).read_bytes(), str(path))

    def undefined(self) -> set[str]:
        """The symbols it needs from elsewhere (``nm -u``)."""
        return {s.name for s in self.symbols if s.shndx == SHN_UNDEF and s.name}

    def defined_functions(self, local: bool = False) -> list[Symbol]:
        return [s for s in self.symbols if s.type == STT_FUNC and s.shndx != SHN_UNDEF
                and (local or s.bind != STB_LOCAL)]

    def sizes(self) -> dict[str, int]:
        """text (code and read-only data), data and bss, as binutils' ``size`` counts them."""
        out = {"text": 0, "data": 0, "bss": 0}
        for s in self.sections:
            if not s.flags & SHF_ALLOC:
                continue
            kind = "bss" if s.type == SHT_NOBITS else "data" if s.flags & SHF_WRITE else "text"
            out[kind] += s.size
        return out

    def arm_attributes(self) -> dict[int, int | str]:
        """The file-scope ``aeabi`` build attributes of an ARM object (tag -> value)."""
        section = next((s for s in self.sections if s.type == SHT_ARM_ATTRIBUTES), None)
        if section is None:
            return {}
        data = self._data[section.offset:section.offset + section.size]
        if data[:1] != b"A":
            raise ValueError(f"{self.name}: unknown attributes format {data[:1]!r}")

        def uleb(at: int) -> tuple[int, int]:
            value = shift = 0
            while True:
                byte = data[at]
                at += 1
                value |= (byte & 0x7F) << shift
                shift += 7
                if not byte & 0x80:
                    return value, at

        def ntbs(at: int) -> tuple[str, int]:
            end = data.index(b"\0", at)
            return data[at:end].decode(), end + 1

        out: dict[int, int | str] = {}
        at = 1
        while at < len(data):
            (length,) = struct.unpack_from("<I", data, at)
            vendor, body = ntbs(at + 4)
            end = at + length
            while vendor == "aeabi" and body < end:
                tag, inner = uleb(body)
                (size,) = struct.unpack_from("<I", data, inner)
                stop = body + size
                inner += 4
                while tag == 1 and inner < stop:  # Tag_File: attributes of the whole object
                    attr, inner = uleb(inner)
                    if attr in (4, 5, 67) or (attr > 32 and attr % 2 == 1):
                        out[attr], inner = ntbs(inner)
                    elif attr == 32:  # Tag_compatibility: a number, then a string
                        out[attr], inner = uleb(inner)
                        _, inner = ntbs(inner)
                    else:
                        out[attr], inner = uleb(inner)
                body = stop
            at = end
        return out


def foreign_symbols(objects: list[Path], allowed: frozenset[str] = ALLOWED) -> set[str]:
    """What the objects together call outside themselves, libm and the ARM floating-point
    helpers set aside: must be empty for the core."""
    elves = [Elf.read(o) for o in objects]
    defined = {s.name for e in elves for s in e.symbols
               if s.shndx != SHN_UNDEF and s.bind != STB_LOCAL}
    undefined = set().union(*(e.undefined() for e in elves))
    return undefined - defined - allowed


# --------------------------------------------------------------------------------------------
# Stack: the compiler's frames and the call graph of the objects
# --------------------------------------------------------------------------------------------

#: The entry points the report lists: a scenario's step, desired and init, the codec, the
#: bridge and the supervisor's checks; and every global function of the loop (loop.c,
#: scenarios.c, <scenario>_scenario.c), whatever its name.
ENTRY = re.compile(r"^(?:\w+_(?:step|desired|init)|dxl_\w+|cochlea_bridge_\w+|"
                   r"cochlea_check_\w+|cochlea_saturate)$")
LOOP_OBJECTS = re.compile(r"^(?:loop|scenarios|\w+_scenario)$")


def read_stack_usage(path: Path) -> dict[str, tuple[int, bool]]:
    """A ``.su`` file: function -> (bytes, bounded). GCC writes ``file:line:col:name``, clang
    ``file:line:name``. The qualifier ``static`` or ``dynamic,bounded`` (GCC, for pushes of
    outgoing arguments) gives a bound; ``dynamic`` alone (alloca, a VLA) does not. A name that
    appears twice keeps its larger frame."""
    out: dict[str, tuple[int, bool]] = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        where, size, qualifier = line.rsplit("\t", 2)
        name = where.rsplit(":", 1)[1]
        value = (int(size), qualifier != "dynamic")
        out[name] = max(out.get(name, value), value)
    return out


def _frame(frames: dict[str, tuple[int, bool]], names: list[str]) -> tuple[int, bool] | None:
    """The frame of a function known by ``names`` (its symbol, then its aliases): GCC's .su
    names a clone ``f.constprop`` where the symbol is ``f.constprop.0``, and identical code
    folding leaves one function with two names."""
    for name in names:
        for candidate in (name, re.sub(r"\.\d+$", "", name)):
            if candidate in frames:
                return frames[candidate]
    return None


#: A call through a pointer in the assembly: x86-64 (AT&T) ``call *`` and ``jmp *%reg`` (a
#: tail call), Thumb ``blx rN`` and ``bx rN`` (not ``bx lr``, the return), AArch64 ``blr xN``
#: and ``br xN``. The jumps may also be a switch's jump table: a function so marked may make
#: none.
INDIRECT = re.compile(r"^\s*(?:call[lq]?\s+\*|jmp[lq]?\s+\*%|blx\s+r\d|bx\s+r(?:\d|1[0-2]|ip)\b|"
                      r"blr\s+x\d|br\s+x\d)")
_FUNCTION_TYPE = re.compile(r"^\s*\.type\s+([\w.$]+)\s*,\s*[@%]function")


def indirect_callers(assembly: dict[Path, Path]) -> set[tuple[str, str]]:
    """The functions, keyed ``(object stem, name)``, whose code calls through a pointer."""
    out = set()
    for obj, asm in assembly.items():
        lines = asm.read_text().splitlines()
        functions = {m.group(1) for m in map(_FUNCTION_TYPE.match, lines) if m}
        current = None
        for line in lines:
            label = re.match(r"^([\w.$]+):", line)
            if label and label.group(1) in functions:
                current = label.group(1)
            elif current and INDIRECT.match(line):
                out.add((obj.stem, current))
    return out


@dataclass
class Stack:
    frame: int | None  # this function's own frame (None: unknown)
    worst: int | None  # frame plus the deepest chain of direct callees (None: no bound)
    path: list[str]  # that deepest chain, this function first
    external: list[str]  # functions it may reach outside the core (frames not counted)
    why: str = ""  # why there is no bound: "recursion", "dynamic frame" or "no frame"
    indirect: bool = False  # it, or a function it calls, calls through a pointer (not counted)


def call_graph(objects: list[Path]) -> tuple[dict, dict, dict, dict]:
    """``(callees, names, aliases, stored)``: for each function, keyed ``(object stem, name)``,
    the functions it references from its code (direct calls, and addresses it takes: an
    over-estimate); an external callee is keyed ``("", name)``. ``names`` maps a global name to
    its key, ``aliases`` a key to every name at the same address, ``stored`` an object's stem
    to the functions whose address its data holds (a table of callbacks)."""
    elves = {Path(o).stem: Elf.read(o) for o in objects}
    names: dict[str, tuple[str, str]] = {}
    for stem, elf in elves.items():
        for s in elf.defined_functions():
            names[s.name] = (stem, s.name)
    callees: dict[tuple[str, str], set[tuple[str, str]]] = {}
    aliases: dict[tuple[str, str], list[str]] = {}
    stored: dict[str, set[tuple[str, str]]] = {}
    for stem, elf in elves.items():
        functions = elf.defined_functions(local=True)
        by_section: dict[int, list[Symbol]] = {}
        at: dict[tuple[int, int], list[str]] = {}
        for s in functions:
            by_section.setdefault(s.shndx, []).append(s)
            callees.setdefault((stem, s.name), set())
            at.setdefault((s.shndx, s.value), []).append(s.name)
        for s in functions:
            aliases[(stem, s.name)] = [s.name, *sorted(set(at[(s.shndx, s.value)]) - {s.name})]

        def key(s: Symbol, stem: str = stem) -> tuple[str, str]:
            if s.bind == STB_LOCAL:
                return (stem, s.name)
            return names.get(s.name, ("", s.name))

        def start(s: Symbol, thumb: bool = elf.machine == EM_ARM) -> int:
            return s.value & ~1 if thumb else s.value  # bit 0 marks a Thumb function

        for r in elf.relocations:
            patched = elf.sections[r.section]
            if not patched.flags & SHF_EXECINSTR:
                target = elf.symbols[r.symbol]
                unwind = patched.name.startswith((".eh_frame", ".ARM.ex"))
                if patched.flags & SHF_ALLOC and not unwind:
                    if target.type == STT_FUNC:
                        stored.setdefault(stem, set()).add(key(target))
                    elif target.type == STT_SECTION:
                        stored.setdefault(stem, set()).update(
                            key(s) for s in by_section.get(target.shndx, []))
                continue
            callers = [s for s in by_section.get(r.section, [])
                       if start(s) <= r.offset < start(s) + max(s.size, 1)]
            target = elf.symbols[r.symbol]
            if target.type == STT_SECTION:
                inside = by_section.get(target.shndx, [])
                if len(inside) > 1 and r.addend is not None:
                    near = [s for s in inside
                            if start(s) <= r.addend + 4 < start(s) + max(s.size, 1)]
                    inside = near or inside
                # A function's references to its own section are not calls (literal pools,
                # local labels); a call to itself names its symbol and is kept (recursion).
                targets = [key(s) for s in inside]
                for caller in callers:
                    callees[(stem, caller.name)].update(t for t in targets
                                                        if t != (stem, caller.name))
            elif target.type == STT_FUNC or (target.shndx == SHN_UNDEF and target.name):
                for caller in callers:
                    callees[(stem, caller.name)].add(key(target))
    return callees, names, aliases, stored


def stack_report(build: Build) -> tuple[dict[str, Stack], dict[str, dict[str, Stack]]]:
    """``(entries, callbacks)`` of ``build`` (compiled with ``stack=True``): the worst stack of
    each entry point, and of each function a scenario object's table points to (by object)."""
    frames = {obj.stem: read_stack_usage(su) for obj, su in build.stack_files.items()
              if su.exists()}
    callees, names, aliases, stored = call_graph(build.objects)
    indirect = indirect_callers(build.assembly)
    memo: dict[tuple[str, str], Stack] = {}

    def walk(node: tuple[str, str], active: frozenset) -> Stack:
        if node in memo:
            return memo[node]
        if node[0] == "":
            return Stack(0, 0, [], [node[1]])
        if node in active:
            return Stack(None, None, [node[1]], [], "recursion")
        found = _frame(frames.get(node[0], {}), aliases.get(node, [node[1]]))
        frame = found[0] if found else None
        why = "no frame" if found is None else "" if found[1] else "dynamic frame"
        best: Stack | None = None
        external: set[str] = set()
        through_pointer = node in indirect
        for callee in sorted(callees.get(node, ())):
            below = walk(callee, active | {node})
            external |= set(below.external)
            through_pointer |= below.indirect
            if below.worst is None:
                why = why or below.why
            elif callee[0] and (best is None or below.worst > best.worst):
                best = below
        worst = None if why else frame + (best.worst if best else 0)
        # Memoised in any context: a node that reaches an active one is on a cycle, unbounded.
        memo[node] = Stack(frame, worst, [node[1], *(best.path if best else [])],
                           sorted(external), why, through_pointer)
        return memo[node]

    entries = {}
    for stem, name in sorted(set(names.values())):
        if ENTRY.match(name) or LOOP_OBJECTS.match(stem):
            entries[name] = walk((stem, name), frozenset())
    callbacks = {}
    for stem, functions in sorted(stored.items()):
        if LOOP_OBJECTS.match(stem):
            callbacks[stem] = {name: walk((where, name), frozenset())
                               for where, name in sorted(functions) if where}
    return entries, callbacks


# --------------------------------------------------------------------------------------------
# Measure, render, write
# --------------------------------------------------------------------------------------------


def measure(target: Target, precision: str, work: Path) -> dict:
    """Build the core for one target with SIZE_FLAGS and measure it: sizes per object and in
    total, the undefined symbols, the worst stack per entry point."""
    build = compile_core(target, precision, work / f"{target.name}-{precision}",
                         flags=SIZE_FLAGS, stack=True)
    foreign = foreign_symbols(build.objects)
    if foreign:
        raise BuildError(f"{target.name} {precision}: calls outside libm: {sorted(foreign)}")
    objects = {}
    undefined: set[str] = set()
    machine = set()
    for obj in build.objects:
        elf = Elf.read(obj)
        machine.add(elf.machine)
        objects[obj.stem] = elf.sizes()
        undefined |= elf.undefined()
    defined = {s.name for o in build.objects for s in Elf.read(o).symbols
               if s.shndx != SHN_UNDEF and s.bind != STB_LOCAL}
    total = {k: sum(o[k] for o in objects.values()) for k in ("text", "data", "bss")}
    runtime = {k: sum(objects[s.stem][k] for s in CORE.glob("*.c")) for k in total}
    entries, callbacks = stack_report(build)

    def row(s: Stack) -> dict:
        return {"frame": s.frame, "worst": s.worst, "path": s.path, "external": s.external,
                "why": s.why, "indirect": s.indirect}

    return {
        "target": target.name, "title": target.title, "precision": precision,
        "compiler": compiler_version(target),
        "flags": [*target.flags, *STRICT, *(FLOAT if precision == "float" else ()),
                  *SIZE_FLAGS],
        "elf_machine": sorted(machine),
        "objects": dict(sorted(objects.items())), "total": total, "runtime_core": runtime,
        "undefined": sorted(undefined - defined),
        "stack": {name: row(s) for name, s in sorted(entries.items())},
        "callbacks": {stem: {name: row(s) for name, s in sorted(table.items())}
                      for stem, table in sorted(callbacks.items())},
        "seconds": build.seconds,
    }


def _cell(entry: dict | None) -> str:
    if entry is None:
        return ""
    if entry["worst"] is None:
        return f"no bound ({entry['why']})"
    worst = str(entry["worst"]) + (" †" if entry["indirect"] else "")
    return worst if entry["worst"] == entry["frame"] else f"{worst} ({entry['frame']})"


#: What the loop may call through its backend when the bridge is the backend (the bridge's
#: backend adapters are taken into cochlea_bridge_backend's chain, where their addresses are).
BRIDGE_BACKEND = ("cochlea_bridge_read", "cochlea_bridge_write", "cochlea_bridge_stop",
                  "cochlea_bridge_backend")


def loop_with_scenario(result: dict, stem: str) -> int | None:
    """A bound of the loop's stack with one scenario and the bridge as its backend:
    cochlea_loop_run's chain plus the deepest of what it calls through pointers, the scenario's
    callbacks and the bridge's read, write and stop (each with its own chain)."""
    loop = result["stack"].get("cochlea_loop_run")
    below = [s["worst"] for s in result["callbacks"].get(stem, {}).values()]
    below += [result["stack"][n]["worst"] for n in BRIDGE_BACKEND if n in result["stack"]]
    if loop is None or loop["worst"] is None or not below or None in below:
        return None
    return loop["worst"] + max(below)


def _paragraph(text: str) -> str:
    return textwrap.fill(text, width=100, break_long_words=False, break_on_hyphens=False)


def markdown(results: list[dict]) -> str:
    """The section between the markers in docs/embedded.md."""
    heads = [f"{r['title']} {r['precision']}" for r in results]
    compilers = sorted({r["compiler"] for r in results})
    lines = [
        _paragraph(
            "Written by `make embedded-size` (`bench/embedded_size.py`; the same numbers with "
            "the call chains in `bench/embedded_size.json`). Compilers: "
            + "; ".join(f"`{c}`" for c in compilers) + ". Every `embedded/core/*.c` and "
            "`generated_c/embedded/*.c` is compiled to an object (no linking) with "
            f"`{' '.join(STRICT)} {' '.join(SIZE_FLAGS)}`; float adds `{' '.join(FLOAT)}`. "
            "The targets:"),
        "",
    ]
    for name, target in TARGETS.items():
        if any(r["target"] == name for r in results):
            if target.zig:
                line = f"- {target.title}: `zig cc {' '.join(target.flags)}`"
                if target.math_headers:
                    line += (f" (zig has no libc for bare metal: `<math.h>` comes from its "
                             f"{target.math_headers} headers, as newlib's would on a board)")
            else:
                line = f"- {target.title}: the host's `cc`"
            lines.append(textwrap.fill(line, width=100, subsequent_indent="  ",
                                       break_long_words=False, break_on_hyphens=False))
    lines += [
        "",
        _paragraph(
            "Sizes in bytes, summed over the objects' sections as binutils' `size` counts them: "
            "text is code and read-only data (with the unwind tables, `.eh_frame`, on the host "
            "and aarch64: about 4 KB). A firmware links one scenario, not all of them, and adds "
            "libm, the compiler's helpers, its HAL and its start-up code; `--gc-sections` drops "
            "what it never calls."),
        "",
        "| object | " + " | ".join(heads) + " |",
        "|---|" + "---:|" * len(results),
    ]
    for stem in sorted(results[0]["objects"]):
        lines.append(f"| {stem} | " + " | ".join(str(r["objects"][stem]["text"])
                                               for r in results) + " |")
    for label, key in (("**runtime core** (embedded/core) text", "runtime_core"),
                       ("**all** text", "total")):
        lines.append(f"| {label} | " + " | ".join(str(r[key]["text"]) for r in results) + " |")
    for kind in ("data", "bss"):
        lines.append(f"| **all** {kind} | " + " | ".join(str(r["total"][kind]) for r in results)
                     + " |")
    lines += [
        "",
        _paragraph(
            "Worst stack per entry point, in bytes: the function's own frame (the compiler's "
            "`-fstack-usage`) plus the deepest chain of core functions it calls directly, "
            "through a call graph read from the objects' relocations; in parentheses the "
            "function's own frame where callees add to it. Not counted: the frames of libm and "
            "of the compiler's floating-point helpers, and calls through pointers: † marks an "
            "entry point whose chain makes such calls (the HAL's callbacks, the backend, the "
            "scenario's callbacks; read from the assembly, where a switch's jump table can "
            "look the same)."),
        "",
        "| entry point | " + " | ".join(heads) + " |",
        "|---|" + "---:|" * len(results),
    ]
    for name in sorted(set().union(*(r["stack"] for r in results))):
        lines.append(f"| `{name}` | " + " | ".join(_cell(r["stack"].get(name))
                                                  for r in results) + " |")
    scenarios = sorted(set().union(*(r["callbacks"] for r in results)))
    if scenarios and any("cochlea_loop_run" in r["stack"] for r in results):
        lines += [
            "",
            _paragraph(
                "The loop with each scenario, the bridge as its backend: `cochlea_loop_run`'s "
                "chain plus the deepest of what it calls through pointers (the scenario's "
                "callbacks in `<scenario>_scenario.c`; the bridge's read, write and stop, and "
                "its backend adapters where `cochlea_bridge_backend` takes their addresses), in "
                "bytes, an upper bound. A firmware adds its HAL callbacks, its row callback, "
                "libm and its interrupts."),
            "",
            "| loop with | " + " | ".join(heads) + " |",
            "|---|" + "---:|" * len(results),
        ]
        for stem in scenarios:
            cells = [loop_with_scenario(r, stem) for r in results]
            name = stem.removesuffix("_scenario")
            lines.append(f"| {name} | " + " | ".join("" if c is None else str(c) for c in cells)
                         + " |")
    deepest: dict[tuple[str, ...], list[str]] = {}
    for r, head in zip(results, heads):
        steps = {n: s for n, s in r["stack"].items()
                 if n.endswith("_step") and s["worst"] is not None}
        if steps:
            name = max(steps, key=lambda n: (steps[n]["worst"], n))
            deepest.setdefault(tuple(steps[name]["path"]), []).append(head)
    if deepest:
        chains = [" > ".join(f"`{f}`" for f in path)
                  + ("" if len(where) == len(results) else f" ({', '.join(where)})")
                  for path, where in deepest.items()]
        lines += ["", _paragraph("The deepest step's chain: " + "; ".join(chains) + ".")]
    return "\n".join(lines) + "\n"


def write_section(doc: Path, section: str) -> None:
    """Replace what lies between the markers of ``doc`` with ``section``."""
    text = doc.read_text()
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise SystemExit(f"{doc}: expected one {BEGIN} before one {END}")
    head, rest = text.split(BEGIN)
    _, tail = rest.split(END)
    doc.write_text(f"{head}{BEGIN}\n{section}{END}{tail}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-write", action="store_true",
                        help="print the section instead of writing the files")
    args = parser.parse_args(argv)
    if not have_zig():
        sys.exit("ziglang is not installed: pip install -e '.[test]'")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, precision in BUILDS:
            result = measure(TARGETS[name], precision, Path(tmp))
            print(f"{result['title']:>14} {precision:6}  compiled in {result.pop('seconds'):5.2f} s"
                  f"  text {result['total']['text']:7}  ({result['compiler']})", flush=True)
            results.append(result)
    section = markdown(results)
    if args.no_write:
        print(section)
        return 0
    JSON_OUT.write_text(json.dumps({"builds": results}, indent=1, sort_keys=True) + "\n")
    write_section(DOC, section)
    print(f"wrote {JSON_OUT.relative_to(ROOT)} and the size section of {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
