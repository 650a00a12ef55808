"""Issue 12's portability proof. The whole embedded core (every embedded/core/*.c and every
generated_c/embedded/*.c; the POSIX port is not in it) compiles freestanding and warning-free,
in double and in float, with the host's cc, and cross-compiles with ``zig cc`` (the ziglang
wheel of the test extra) for a Cortex-M4F (Thumb-2, bare metal, hard float) and for aarch64
Linux. The objects are what they claim to be (ELF machine, float ABI), and together they call
nothing but libm (and, on the Cortex-M4F, the compiler's floating-point helpers). The builder
and the ELF reader are bench/embedded_size.py's (``make embedded-size``), checked here too: the
reader against binutils, the symbol check on code that calls libc, the stack report on a known
call graph."""

from __future__ import annotations

import importlib.util
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("embedded_size", ROOT / "bench" / "embedded_size.py")
size = importlib.util.module_from_spec(_spec)
sys.modules["embedded_size"] = size  # dataclasses look their module up by name
_spec.loader.exec_module(size)

BUILDS = [("host", "double"), ("host", "float"), ("cortex-m4f", "float"),
          ("cortex-m4f", "double"), ("aarch64", "double"), ("aarch64", "float")]
HOST_MACHINE = {"x86_64": size.EM_X86_64, "aarch64": size.EM_AARCH64,
                "arm64": size.EM_AARCH64}.get(platform.machine())
#: ARM build attributes: the architecture profile, Thumb use, and the float unit and ABI.
TAG_CPU_ARCH_PROFILE, TAG_ARM_ISA_USE, TAG_THUMB_ISA_USE = 7, 8, 9

needs_cc = pytest.mark.skipif(size.host_cc() is None, reason="no C compiler")
needs_zig = pytest.mark.skipif(not size.have_zig(),
                               reason="ziglang is not installed: pip install -e '.[test]'")
PARAMS = [pytest.param(t, p, marks=needs_cc if t == "host" else needs_zig, id=f"{t}-{p}")
          for t, p in BUILDS]


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """``build(target, precision)``: the core compiled at -O2 (once per module)."""
    done: dict[tuple[str, str], object] = {}
    folder = tmp_path_factory.mktemp("portability")

    def get(target: str, precision: str):
        if (target, precision) not in done:
            try:
                done[target, precision] = size.compile_core(
                    size.TARGETS[target], precision, folder / f"{target}-{precision}")
            except size.BuildError as error:
                pytest.fail(str(error)[:5000])
        return done[target, precision]

    return get


def test_the_core_is_every_c_file_but_the_ports():
    sources = size.core_sources()
    core = ROOT / "embedded" / "core"
    generated = ROOT / "generated_c" / "embedded"
    assert set(sources) == set(core.glob("*.c")) | set(generated.glob("*.c"))
    assert {"bridge", "drives", "dxl", "supervisor", "serial_task", "parallel_task"} <= {
        s.stem for s in sources}
    assert not [s for s in sources if "posix" in s.parts]


@pytest.mark.parametrize("target, precision", PARAMS)
@pytest.mark.slow
def test_the_core_compiles_freestanding_and_calls_only_libm(build, target, precision):
    """Warnings as errors, none let through (GCC and clang); the objects together call
    nothing but libm and, on the Cortex-M4F, the ARM run-time ABI's floating-point helpers."""
    built = build(target, precision)
    assert size.foreign_symbols(built.objects) == set()
    elves = [size.Elf.read(o) for o in built.objects]
    undefined = set().union(*(e.undefined() for e in elves))
    if precision == "float":  # the working precision's family, besides the estimate's update
        # and the desired trajectory (in double: a float time would staircase, issue 28)
        assert {"sinf", "cosf"} <= undefined
    else:
        assert {"sin", "cos"} <= undefined and not {"sinf", "cosf"} & undefined
    spec = size.TARGETS[target]
    machine = spec.machine if spec.machine is not None else HOST_MACHINE
    for elf in elves:
        assert elf.type == 1, f"{elf.name}: not a relocatable object"
        if machine is not None:
            assert elf.machine == machine, f"{elf.name}: e_machine {elf.machine}"
        if spec.bits is not None:
            assert elf.bits == spec.bits


@needs_zig
@pytest.mark.parametrize("precision", ["float", "double"])
@pytest.mark.slow
def test_the_cortex_m4f_objects_are_thumb2_with_hard_float(build, precision):
    """Thumb-2 code for an M-profile core, the hard-float ABI (float arguments in VFP
    registers), a single-precision FPU, and in float no software single-precision helper."""
    built = build("cortex-m4f", precision)
    undefined = set()
    for obj in built.objects:
        elf = size.Elf.read(obj)
        assert elf.flags & size.EF_ARM_ABI_FLOAT_HARD, f"{obj.name}: soft-float ABI"
        attributes = elf.arm_attributes()
        assert attributes.get(TAG_CPU_ARCH_PROFILE) == ord("M"), obj.name
        assert attributes.get(TAG_ARM_ISA_USE, 0) == 0, obj.name  # Thumb only
        assert attributes.get(TAG_THUMB_ISA_USE) == 2, obj.name  # Thumb-2
        assert attributes.get(size.TAG_ABI_VFP_ARGS) == 1, obj.name  # VFP registers
        assert attributes.get(size.TAG_FP_ARCH, 0) > 0, f"{obj.name}: no FPU"
        undefined |= elf.undefined()
    assert not undefined & size.SOFT_SINGLE, sorted(undefined & size.SOFT_SINGLE)
    if precision == "float":
        assert undefined & {"sinf", "sqrtf"}




# --------------------------------------------------------------------------------------------
# The tools: the ELF reader, the symbol check, the stack report
# --------------------------------------------------------------------------------------------


@pytest.mark.skipif(not (shutil.which("nm") and shutil.which("size")), reason="no binutils")
@pytest.mark.parametrize("target, precision", PARAMS)
@pytest.mark.slow
def test_the_elf_reader_agrees_with_binutils(build, target, precision):
    """Undefined symbols as ``nm -u`` lists them, text/data/bss as ``size`` sums them (for the
    objects the host's binutils can read)."""
    read = 0
    for obj in build(target, precision).objects:
        berkeley = subprocess.run(["size", str(obj)], capture_output=True, text=True)
        if berkeley.returncode != 0:
            continue  # a binutils without this architecture
        text, data, bss = map(int, berkeley.stdout.splitlines()[1].split()[:3])
        nm = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True, check=True)
        elf = size.Elf.read(obj)
        assert elf.sizes() == {"text": text, "data": data, "bss": bss}, obj.name
        assert elf.undefined() == {line.split()[-1] for line in nm.stdout.splitlines()
                                   if line.strip()}, obj.name
        read += 1
    if target == "host":
        assert read == len(build(target, precision).objects)


LIBC_CALLS = """
#include <stddef.h>
void *memcpy(void *d, const void *s, size_t n);
void *malloc(size_t n);
int printf(const char *format, ...);
double sin(double x);
double use(double *out, const double *in) {
    double *copy = malloc(8 * sizeof *copy);
    memcpy(copy, in, 8 * sizeof *copy);
    printf("%f", copy[0]);
    *out = copy[1];
    return sin(copy[2]);
}
"""


@needs_cc
def test_the_symbol_check_catches_libc(tmp_path):
    """The check is not vacuous: code that calls memcpy, malloc and printf fails it (and its
    sin passes); the ARM helpers allowed are floating-point ones, not __aeabi_memcpy."""
    source = tmp_path / "libc_calls.c"
    source.write_text(LIBC_CALLS)
    built = size.compile_core(size.TARGETS["host"], "double", tmp_path / "out",
                              sources=[source])
    assert size.foreign_symbols(built.objects) == {"memcpy", "malloc", "printf"}
    assert "__aeabi_dadd" in size.ALLOWED and "__aeabi_d2f" in size.ALLOWED
    assert not {"__aeabi_memcpy", "__aeabi_memset", "__aeabi_memclr",
                "__aeabi_unwind_cpp_pr0"} & size.ALLOWED
    assert {"sqrt", "sqrtf", "nearbyint", "atan2f"} <= size.ALLOWED


CALLS = {
    "demo.c": """
double demo_leaf(volatile double *v);
int demo_init(int n);
double demo_step(void) {
    volatile double a[16];
    int i;
    for (i = 0; i < 16; ++i) a[i] = i;
    return demo_leaf(a) + a[3];
}
int demo_init(int n) {
    volatile int pad[8];
    pad[0] = n;
    return n > 0 ? demo_init(n - 1) + pad[0] : 0;
}
""",
    "leaf.c": """
#include <math.h>
double demo_leaf(volatile double *v) {
    volatile double b[64];
    int i;
    for (i = 0; i < 64; ++i) b[i] = v[i % 16];
    return sin(b[5]);
}
double demo_desired(double t) { return sin(t); }
""",
}


@needs_cc
def test_the_stack_report_adds_callee_frames(tmp_path):
    """On a known call graph: a step's worst stack is its frame plus its callee's (across
    objects), a call into libm adds nothing and is listed, recursion has no bound."""
    sources = []
    for name, text in CALLS.items():
        (tmp_path / name).write_text(text)
        sources.append(tmp_path / name)
    built = size.compile_core(size.TARGETS["host"], "double", tmp_path / "out",
                              flags=("-O0", "-ffunction-sections"), sources=sources, stack=True)
    report, callbacks = size.stack_report(built)
    step, desired, init = report["demo_step"], report["demo_desired"], report["demo_init"]
    assert callbacks == {} and not step.indirect
    assert step.path == ["demo_step", "demo_leaf"]
    assert step.frame >= 16 * 8 and step.worst >= step.frame + 64 * 8
    assert step.external == ["sin"]
    assert desired.worst == desired.frame and desired.external == ["sin"]
    assert init.worst is None and init.why == "recursion"


@needs_cc
@pytest.mark.slow
def test_the_size_report_measures_the_host(tmp_path):
    """bench/embedded_size.py on the host: every object has content, every entry point a stack,
    the scenario steps a frame; its section replaces only what lies between the markers."""
    result = size.measure(size.TARGETS["host"], "double", tmp_path)
    assert set(result["objects"]) == {s.stem for s in size.core_sources()}
    # A table of pointers (scenarios.c) may be all data: writable until relocated.
    assert all(o["text"] + o["data"] > 0 for o in result["objects"].values())
    assert result["total"]["text"] > result["runtime_core"]["text"] > 0
    assert set(result["undefined"]) <= size.ALLOWED
    stack = result["stack"]
    steps = [name for name in stack if name.endswith("_step")]
    assert len(steps) >= 8 and "cochlea_bridge_start" in stack and "dxl_ping" in stack
    for name, entry in stack.items():
        assert entry["worst"] is not None, (name, entry)
        assert entry["worst"] >= entry["frame"] >= 0 and entry["path"][0] == name
    assert all(stack[name]["frame"] > 0 for name in steps)
    assert stack["cochlea_bridge_start"]["worst"] > stack["cochlea_bridge_start"]["frame"]

    section = size.markdown([result])
    assert all(f"`{name}`" in section for name in stack)
    doc = tmp_path / "doc.md"
    doc.write_text(f"# Title\n\nbefore\n{size.BEGIN}\nold\n{size.END}\nafter\n")
    size.write_section(doc, section)
    text = doc.read_text()
    assert text.startswith("# Title\n\nbefore\n") and text.endswith(f"{size.END}\nafter\n")
    assert "old" not in text and section in text
    size.write_section(doc, section)  # idempotent
    assert doc.read_text() == text


def test_the_doc_has_the_size_section():
    text = (ROOT / "docs" / "embedded.md").read_text()
    assert text.count(size.BEGIN) == 1 and text.count(size.END) == 1
    assert "## Code size and stack per target" in text
