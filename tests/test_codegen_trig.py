"""The ideal plant steps take each angle's sin and cos from one inline ``cochlea_sincos``
(cochlea/kernels/trig.py, codegen/cochlea_trig.h): the rewrite of CasADi's C, the header's
accuracy (also where a compiler contracts a * b + c), which generated kernels use it (the
geared plant, the controllers and the model kernels keep libm) and the library's plant steps
against their CasADi Functions (libm) within rounding."""

from __future__ import annotations

import ctypes
import math
import os
import re
import subprocess
from decimal import Decimal, localcontext
from pathlib import Path

import numpy as np
import pytest

import cochlea
from cochlea.kernels import library as ckernels
from cochlea.kernels.catalogue import CodegenError
from cochlea.kernels.trig import HEADER, HEADER_NAME, inline_trig
from cochlea.robots.plant import plant_step

ROOT = Path(__file__).resolve().parent.parent
GENERATED = ROOT / "generated_c"
FLAGS = ("-std=c99", "-pedantic", "-O2", "-Wall", "-Wextra", "-Werror", "-fPIC", "-shared")

_SIGNATURE = ("(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, "
              "int mem)")
#: CasADi's C of two straight-line functions, as it writes them (variables reused): ``plant``
#: takes sin and cos of x twice (one value), of a reassigned x, and writes the latter over x
#: (its sin read first); ``model`` is not asked for and keeps libm.
SOURCE = f"""#include <math.h>
#ifndef casadi_real
#define casadi_real double
#endif
#ifndef casadi_int
#define casadi_int long long int
#endif

/* plant:(x)->(y[5]) */
static int casadi_f0{_SIGNATURE} {{
  casadi_real a0, a1, a2, a3, a4;
  (void)iw; (void)w; (void)mem;
  a0=arg[0]? arg[0][0] : 0;
  a1=sin(a0);
  a2=cos(a0);
  a3=sin(a0);
  if (res[0]!=0) res[0][0]=a1;
  if (res[0]!=0) res[0][1]=a2;
  if (res[0]!=0) res[0][2]=a3;
  a0=(a0+a1);
  a4=cos(a0);
  a0=sin(a0);
  if (res[0]!=0) res[0][3]=a4;
  if (res[0]!=0) res[0][4]=a0;
  return 0;
}}

int plant{_SIGNATURE}{{
  return casadi_f0(arg, res, iw, w, mem);
}}

/* model:(x)->(y) */
static int casadi_f1{_SIGNATURE} {{
  casadi_real a0, a1;
  (void)iw; (void)w; (void)mem;
  a0=arg[0]? arg[0][0] : 0;
  a1=sin(a0);
  if (res[0]!=0) res[0][0]=a1;
  return 0;
}}

int model{_SIGNATURE}{{
  return casadi_f1(arg, res, iw, w, mem);
}}
""".replace("\nint ", "\nCASADI_SYMBOL_EXPORT int ").replace(
    "#include <math.h>\n", "#include <math.h>\n#define CASADI_SYMBOL_EXPORT\n", 1)


def _body(text: str, symbol: str) -> str:
    match = re.search(rf"^static int {symbol}\(.*?^\}}$", text, flags=re.M | re.S)
    assert match, symbol
    return match.group(0)


def _compile(tmp_path: Path, name: str, source: str, flags=FLAGS) -> ctypes.CDLL:
    c = tmp_path / f"{name}.c"
    c.write_text(source)
    lib = tmp_path / f"lib{name}.so"
    subprocess.run([os.environ.get("CC", "cc"), *flags, f"-I{GENERATED}", str(c), "-o",
                    str(lib), "-lm"], check=True)
    return ctypes.CDLL(str(lib))


def _call(lib: ctypes.CDLL, name: str, x: float, n_out: int) -> np.ndarray:
    x_in = (ctypes.c_double * 1)(x)
    out = (ctypes.c_double * n_out)()
    arg = (ctypes.POINTER(ctypes.c_double) * 1)(ctypes.cast(x_in, ctypes.POINTER(ctypes.c_double)))
    res = (ctypes.POINTER(ctypes.c_double) * 1)(ctypes.cast(out, ctypes.POINTER(ctypes.c_double)))
    assert getattr(lib, name)(arg, res, None, None, 0) == 0
    return np.array(out[:])


def test_one_sincos_per_value_of_an_angle(tmp_path):
    """sin(a) and cos(a) of one value of a: one cochlea_sincos at the first (a repeated sin
    copies it); a reassigned a: a new one, though the new value's cos is written over a; the
    function not asked for keeps libm; the header is included once; the rewritten C compiles
    warning-free (C99, pedantic) and computes what libm does within an ulp."""
    text, count = inline_trig(SOURCE, ["plant"])
    assert count == 2
    plant, model = _body(text, "casadi_f0"), _body(text, "casadi_f1")
    assert plant.count("cochlea_sincos(") == 2
    assert not re.search(r"\b(sin|cos)\(", plant)
    assert "cochlea_sincos(a0, &trig_s0, &trig_c0); a1=trig_s0;" in plant
    assert "a2=trig_c0;" in plant and "a3=trig_s0;" in plant
    assert "cochlea_sincos(a0, &trig_s1, &trig_c1); a4=trig_c1;" in plant
    assert "a0=trig_s1;" in plant
    assert model == _body(SOURCE, "casadi_f1")
    assert text.count(f'#include "{HEADER_NAME}"') == 1
    assert inline_trig(SOURCE, []) == (SOURCE, 0)

    lib = _compile(tmp_path, "plant", text)
    for x in (0.3, -2.9, 7.0, 1e6):
        y = _call(lib, "plant", x, 5)
        x2 = x + math.sin(x)
        want = [math.sin(x), math.cos(x), math.sin(x), math.cos(x2), math.sin(x2)]
        assert np.all(np.abs(y - want) <= np.spacing(np.abs(want))), x
    assert _call(lib, "model", 0.3, 1)[0] == math.sin(0.3)


@pytest.mark.parametrize("line, message", [
    ("  a1=sin((a0+a0));", "a sin or cos of other than a variable"),
    ("  if (res[0]!=0) res[0][0]=cos(a0);", "a sin or cos of other than a variable")])
def test_a_form_it_cannot_pair_is_refused(line, message):
    source = SOURCE.replace("  a1=sin(a0);\n  a2=cos(a0);", line, 1)
    with pytest.raises(CodegenError, match=re.escape(message)):
        inline_trig(source, ["plant"])
    with pytest.raises(CodegenError, match="no exported function nothing"):
        inline_trig(SOURCE, ["nothing"])


def _reference_sincos(x: float) -> tuple[Decimal, Decimal]:
    """sin x and cos x to 50 digits (x reduced by a 90-digit pi, Taylor series)."""
    with localcontext() as ctx:
        ctx.prec = 60
        pi = Decimal("3.14159265358979323846264338327950288419716939937510582097494459230781"
                     "64062862089986280348")
        r0 = Decimal(x)
        k = int((r0 / (pi / 2)).to_integral_value())
        r = r0 - k * (pi / 2)
        r2, sin_r, cos_r, term = r * r, r, Decimal(1), r
        for n in range(1, 40):
            term = -term * r2 / ((2 * n) * (2 * n + 1))
            sin_r += term
        term = Decimal(1)
        for n in range(1, 40):
            term = -term * r2 / ((2 * n - 1) * (2 * n))
            cos_r += term
        return [(sin_r, cos_r), (cos_r, -sin_r), (-sin_r, -cos_r), (-cos_r, sin_r)][k % 4]


_TRIG = "\n".join([
    '#include "cochlea_trig.h"',
    '#include "sim_trig.h" /* the same header: one definition */',
    "void trig(const double *x, double *s, double *c, long n) {",
    "  long i;",
    "  for (i = 0; i < n; ++i) cochlea_sincos(x[i], s + i, c + i);",
    "}",
    "void sim(const double *x, double *s, double *c, long n) {",
    "  long i;",
    "  for (i = 0; i < n; ++i) sim_sincos(x[i], s + i, c + i);",
    "}"])


def _fma_gcc() -> bool:
    """The host's cc is GCC on an x86-64 with FMA (where -std=gnu99 contracts)."""
    cc = os.environ.get("CC", "cc")
    version = subprocess.run([cc, "--version"], capture_output=True, text=True).stdout
    cpu = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    return ("Free Software Foundation" in version and os.uname().machine == "x86_64"
            and re.search(r"^flags\s*:.*\bfma\b", cpu, flags=re.M) is not None)


BUILDS = {"c99": ("-std=c99",), "gnu99-fma": ("-std=gnu99", "-mfma", "-ffp-contract=fast")}


@pytest.mark.parametrize("build", BUILDS)
def test_cochlea_sincos_is_within_an_ulp(tmp_path, build):
    """At most 1 ulp from a 50-digit reference over the studies' range and beyond, next to
    multiples of pi/2 and tiny; libm's outside |x| < 2^19; NaN for NaN and infinities; the
    inline code runs (some results differ from libm's); sim_sincos is the same function. Also
    where GCC contracts (-std=gnu99 on an FMA target: the build has fused multiply-adds)."""
    flags = BUILDS[build]
    if build != "c99":
        if not _fma_gcc():
            pytest.skip("needs GCC on an x86-64 with FMA")
        asm = tmp_path / "trig.s"
        (tmp_path / "trig_asm.c").write_text(_TRIG)
        subprocess.run([os.environ.get("CC", "cc"), *flags, "-O2", f"-I{GENERATED}",
                        f"-I{ROOT / 'embedded' / 'sim'}", "-S", str(tmp_path / "trig_asm.c"),
                        "-o", str(asm)], check=True)
        assert "vfmadd" in asm.read_text() or "vfmsub" in asm.read_text()
    lib = _compile(tmp_path, "trig", _TRIG, (*flags, *FLAGS[1:], f"-I{ROOT / 'embedded/sim'}"))
    p = ctypes.POINTER(ctypes.c_double)

    def ours(x, which="trig"):
        x = np.ascontiguousarray(x, dtype=np.float64)
        s, c = np.empty_like(x), np.empty_like(x)
        getattr(lib, which)(x.ctypes.data_as(p), s.ctypes.data_as(p), c.ctypes.data_as(p),
                            ctypes.c_long(len(x)))
        return s, c

    rng = np.random.default_rng(16)
    near = [v for k in range(-12, 13) if k for v in
            (k * math.pi / 2, np.nextafter(k * math.pi / 2, 0), np.nextafter(k * math.pi / 2, 9))]
    xs = np.concatenate([rng.uniform(-7.0, 7.0, 300), rng.uniform(-2e3, 2e3, 30), near,
                         [0.0, -0.0, 1e-300, -3e-9, 0.785398, 2.35619, 4e5, -5.2e5]])
    s, c = ours(xs)
    for x, a, b in zip(xs, s, c):
        exact_s, exact_c = _reference_sincos(float(x))
        for got, exact in ((a, exact_s), (b, exact_c)):
            assert abs(Decimal(float(got)) - exact) <= Decimal(math.ulp(float(exact))), x
    x = rng.uniform(-10.0, 10.0, 20000)
    s, c = ours(x)
    assert np.array_equal(np.stack(ours(x, "sim")), np.stack([s, c]))
    assert 0 < np.count_nonzero(s != np.sin(x)) < 0.1 * len(x)
    far = np.array([2.0 ** 19, -1e6, 1e300])
    s, c = ours(far)
    assert np.array_equal(s, np.sin(far)) and np.array_equal(c, np.cos(far))
    s, c = ours(np.array([np.nan, np.inf, -np.inf]))
    assert np.all(np.isnan(s)) and np.all(np.isnan(c))


def test_clang_keeps_the_sincos_uncontracted(tmp_path):
    """zig cc (clang) contracts within an expression by default (-ffp-contract=on) and the
    embedded builds use it: cochlea_trig.h's pragma leaves no fused multiply-add in the
    sincos for aarch64 (which has one), where the same code without the pragma has some."""
    pytest.importorskip("ziglang")
    import sys

    source = tmp_path / "trig.c"
    source.write_text("\n".join([line for line in _TRIG.split("\n") if "sim" not in line][:5]))
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / HEADER_NAME).write_text(HEADER.read_text().replace(
        "#pragma STDC FP_CONTRACT OFF", ""))
    fused = {}
    for name, include in (("guarded", GENERATED), ("bare", bare)):
        asm = tmp_path / f"{name}.s"
        subprocess.run([sys.executable, "-m", "ziglang", "cc", "-target", "aarch64-linux-gnu",
                        "-std=c99", "-O2", f"-I{include}", "-S", str(source), "-o", str(asm)],
                       check=True, capture_output=True)
        fused[name] = len(re.findall(r"\bf(n?)m(add|sub)\b", asm.read_text()))
    assert fused["guarded"] == 0 and fused["bare"] > 0


def _symbol_body(manifest: dict, name: str) -> str:
    meta = manifest["kernels"][name]
    text = (GENERATED / f"{meta['group']}.c").read_text()
    call = re.search(rf"^CASADI_SYMBOL_EXPORT int {re.escape(meta['symbol'])}\(.*?\n  return "
                     r"(casadi_f\d+)\(", text, flags=re.M | re.S)
    assert call, name
    return _body(text, call.group(1))


@pytest.fixture(scope="module")
def lib():
    subprocess.run(["make", "-s", "lib"], cwd=ROOT, check=True, capture_output=True)
    return ckernels.load()


def _inline(name: str) -> bool:
    return re.search(r"_plant_step(_coulomb)?$", name) is not None and \
        not name.endswith("_gear_plant_step")


def test_only_the_ideal_plant_steps_inline_their_trig(lib):
    """generated_c/: the ideal plant steps (rigid and armature, with and without dry friction)
    have no libm sin or cos left, each unit's four; the geared plant, the controllers and the
    model kernels keep libm; cochlea_trig.h is codegen's, and sim_trig.h uses it."""
    manifest = lib.manifest
    inline = sorted(n for n, k in manifest["kernels"].items()
                    if _inline(n) and k["symbol"] == n)
    assert inline == sorted(f"{u}_{a}plant_step{c}" for u in ("serial_arm1", "parallel")
                            for a in ("", "armature_") for c in ("", "_coulomb"))
    for name in inline:
        body = _symbol_body(manifest, name)
        assert body.count("cochlea_sincos(") >= 4 and not re.search(r"\b(sin|cos)\(", body)
    for name in ("serial_arm1_gear_plant_step", "parallel_gear_plant_step", "parallel_M",
                 "serial_arm1_fk_world", "serial_arm2_fk_world", "serial_arm1_g_step",
                 "parallel_f_step", "parallel_d_actuated_step"):
        body = _symbol_body(manifest, name)
        assert "cochlea_sincos" not in body and re.search(r"\b(sin|cos)\(", body), name
    assert (GENERATED / HEADER_NAME).read_bytes() == HEADER.read_bytes()
    users = {p.name for p in GENERATED.glob("*.c") if HEADER_NAME in p.read_text()}
    assert users == {"serial_arm1.c", "parallel.c"}
    assert '#include "../../generated_c/cochlea_trig.h"' in \
        (ROOT / "embedded" / "sim" / "sim_trig.h").read_text()


@pytest.mark.parametrize("robot, arm", [("serial", "arm1"), ("serial", "arm2"),
                                        ("parallel", None)])
def test_the_ideal_plant_steps_are_casadis_within_rounding(lib, robot, arm):
    """The library's plant step against its CasADi Function (libm's sin and cos) at states
    across the workspace: equal to 1e-14 of max(1, |value|), not always bit for bit (the
    inline sin and cos are what run)."""
    m = cochlea.model(robot, arm=arm, parameterisation="inertial")
    f = plant_step(m, 1)
    kernel = lib.kernel(f.name())
    rng = np.random.default_rng(7)
    worst, differ = 0.0, 0
    for _ in range(40):
        q = m.geometry.random_configuration(rng) if robot == "parallel" else \
            rng.uniform(-np.pi, np.pi, m.nq)
        args = [np.concatenate([q, rng.uniform(-1.0, 1.0, m.nq)]),
                rng.uniform(-0.01, 0.01, m.nq), m.p_nominal, rng.uniform(0.0, 1e-3, m.nq),
                np.array([1e-3])]
        want = np.array(f(*args)).ravel()
        got = kernel.evaluate(*args)[0].ravel()
        worst = max(worst, float(np.max(np.abs(got - want) / np.maximum(1.0, np.abs(want)))))
        differ += not np.array_equal(got, want)
    assert worst <= 1e-14
    assert differ > 0


def test_a_users_folder_gets_the_header(tmp_path):
    """cochlea-codegen writes cochlea_trig.h beside a folder's kernels that include it (a
    user's --out folder compiles on its own)."""
    from cochlea.kernels.catalogue import Kernel
    from cochlea.kernels.generate import _generate_group

    m = cochlea.model("serial", arm="arm1", parameterisation="inertial")
    f = plant_step(m, 1)
    k = Kernel(f.name(), f, f, "unit", "plant", "serial", "serial_arm1")
    _generate_group("unit", [k], tmp_path, {"with_header": True, "casadi_real": "double"})
    assert (tmp_path / HEADER_NAME).read_bytes() == HEADER.read_bytes()
    subprocess.run([os.environ.get("CC", "cc"), *FLAGS[:-2], "-c", str(tmp_path / "unit.c"),
                    "-o", str(tmp_path / "unit.o")], check=True)
