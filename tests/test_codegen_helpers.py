"""CasADi's runtime helpers in the generated C are ``static`` and its min and max inline
(cochlea/kernels/helpers.py, and the embedded laws' ``CFMIN``/``CFMAX``): the inline forms
return libm's bits for every pair of doubles and floats (infinities, subnormals, quiet and
signalling NaNs; a tie of +0 and -0 either zero, as C leaves it), the rewrite refuses a helper
it does not know, and the library exports no helper (an exported one is called through the
PLT and never inlined)."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import casadi as ca
import pytest

from cochlea.kernels import library as ckernels
from cochlea.kernels.catalogue import CodegenError
from cochlea.kernels.helpers import min_max_functions, static_helpers

ROOT = Path(__file__).resolve().parent.parent
GENERATED = ROOT / "generated_c"
CC = os.environ.get("CC", "cc")


def _casadi_c(tmp_path: Path) -> str:
    """CasADi's own C of a Function using sq, fmin, fmax, fabs and sign."""
    x, y = ca.SX.sym("x"), ca.SX.sym("y")
    f = ca.Function("helpers", [x, y], [ca.vertcat(x ** 2, ca.fmin(x, y), ca.fmax(x, y),
                                                  ca.fabs(x), ca.sign(y))])
    gen = ca.CodeGenerator("helpers.c", {"with_header": False})
    gen.add(f)
    gen.generate(str(tmp_path) + "/")
    return (tmp_path / "helpers.c").read_text()


def test_every_helper_of_casadis_c_becomes_static_and_min_max_compare(tmp_path):
    text = static_helpers(_casadi_c(tmp_path))
    helpers = re.findall(r"^(.*)\bcasadi_(sq|fmin|fmax|fabs|sign)\(casadi_real x", text, re.M)
    assert sorted(name for _, name in helpers) == ["fabs", "fmax", "fmin", "sign", "sq"]
    assert all(prefix.startswith("static casadi_real") for prefix, _ in helpers)
    assert "return fmax(x, y);" not in text and "return fmin(x, y);" not in text
    assert "x > y ? x : y >= x ? y : fmax(x, y)" in text
    assert "x < y ? x : y <= x ? y : fmin(x, y)" in text
    # and the file compiles warning-free as the library is built
    (tmp_path / "helpers.c").write_text(text)
    subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror",
                    "-Wno-unused-parameter", "-fPIC", "-c", str(tmp_path / "helpers.c"), "-o",
                    str(tmp_path / "helpers.o")], check=True)


def test_a_min_or_max_helper_in_another_form_is_refused(tmp_path):
    text = _casadi_c(tmp_path).replace("return fmax(x, y);", "return x>y ? x : y;")
    with pytest.raises(CodegenError, match="casadi_fmax is not in the form"):
        static_helpers(text)


def test_generated_files_have_no_external_helper_and_the_library_exports_none():
    for path in sorted(GENERATED.glob("*.c")):
        assert not re.search(r"^casadi_real casadi_\w+\(", path.read_text(), re.M), path.name
    exported = subprocess.run(["nm", "-D", "--defined-only", str(ckernels.library_path())],
                              capture_output=True, text=True, check=True).stdout
    helpers = re.findall(r"\b\w+_(?:sq|fmin|fmax|fabs|sign)\b", exported)
    assert helpers == []
    assert re.search(r"\bserial_arm1_e_step\b", exported)  # the kernels stay exported


#: Compares the inline min/max with libm's bit for bit over special values and random bit
#: patterns (NaN payloads, signalling NaNs, subnormals), in double and in float.
PROGRAM = r"""
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#define CM_double(fn) fn
#define CM_float(fn) fn##f
%(helpers)s
/* Equal bits, or two zeros: C leaves fmin/fmax of +0 and -0 open, and GCC, which takes them
 * for commutative, may swap libm's operands itself (fmax(-0, +0) gives -0 at -O2, +0 at -O0). */
static int same(double a, double b) { return !memcmp(&a, &b, 8) || (a == 0 && b == 0); }
static int samef(float a, float b) { return !memcmp(&a, &b, 4) || (a == 0 && b == 0); }
static uint64_t state = 88172645463325252ull;
static uint64_t next(void) { state ^= state << 13; state ^= state >> 7; state ^= state << 17;
                             return state; }
int main(void) {
  const double special[] = {0.0, -0.0, 1.0, -1.0, 2.5, INFINITY, -INFINITY, NAN, -NAN,
                            4.9e-324, -4.9e-324, 1e308};
  long bad = 0, i, n = sizeof special / sizeof *special;
  for (i = 0; i < n * n + 4000000; ++i) {
    double x, y, r[6];
    float xf, yf, rf[4];
    uint64_t a = next(), b = next();
    uint32_t af = (uint32_t)a, bf = (uint32_t)b;
    if (i < n * n) { x = special[i / n]; y = special[i %% n]; }
    else {
      if (i %% 3 == 0) b = a ^ (1ull << 63);  /* ties of opposite signs, x and -x */
      if (i %% 5 == 0) b = a;
      if (i %% 7 == 0) a = 0x7ff0000000000001ull;  /* a signalling NaN */
      memcpy(&x, &a, 8); memcpy(&y, &b, 8);
    }
    r[0] = fmin(x, y); r[1] = DMIN(x, y); r[2] = fmax(x, y); r[3] = DMAX(x, y);
    r[4] = CFMIN(x, y); r[5] = CFMAX(x, y);  /* the embedded laws' double build */
    if (!same(r[0], r[1]) || !same(r[2], r[3]) || !same(r[0], r[4]) || !same(r[2], r[5])) {
      if (bad++ < 5) printf("double %%a %%a\n", x, y);
    }
    if (i < n * n) { xf = (float)x; yf = (float)y; }
    else {
      if (i %% 3 == 0) bf = af ^ 0x80000000u;
      if (i %% 5 == 0) bf = af;
      if (i %% 7 == 0) af = 0x7f800001u;
      memcpy(&xf, &af, 4); memcpy(&yf, &bf, 4);
    }
    rf[0] = fminf(xf, yf); rf[1] = FMIN(xf, yf); rf[2] = fmaxf(xf, yf); rf[3] = FMAX(xf, yf);
    if (!samef(rf[0], rf[1]) || !samef(rf[2], rf[3])) {
      if (bad++ < 5) printf("float %%a %%a\n", (double)xf, (double)yf);
    }
  }
  printf("%%ld\n", bad);
  return 0;
}
"""


def _helpers_in_c(tmp_path: Path) -> str:
    """The library's helpers (from CasADi's C, rewritten) and the embedded laws' ones, for
    double and float, renamed so that one program holds them all."""
    text = static_helpers(_casadi_c(tmp_path))
    library = "\n".join(re.findall(r"^static casadi_real casadi_fm(?:in|ax)\(.*?\n\}", text,
                                   re.M | re.S))
    library = (library.replace("casadi_real", "double").replace("casadi_fmin", "DMIN")
               .replace("casadi_fmax", "DMAX"))
    used = "CFMIN( CFMAX("
    embedded = (min_max_functions("float", used).replace("CM(", "CM_float(")
                .replace("CFMIN", "FMIN").replace("CFMAX", "FMAX"))
    double = min_max_functions("double", used).replace("CM(", "CM_double(")
    return f"{library}\n{embedded}\n{double}"


def test_inline_min_and_max_return_libms_bits_for_every_pair(tmp_path):
    source = tmp_path / "min_max.c"
    source.write_text(PROGRAM % {"helpers": _helpers_in_c(tmp_path)})
    program = tmp_path / "min_max"
    subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror",
                    str(source), "-o", str(program), "-lm"], check=True)
    out = subprocess.run([str(program)], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "0", out


def test_the_embedded_laws_call_no_libm_min_or_max_directly():
    for path in sorted((GENERATED / "embedded").glob("*.c")):
        text = path.read_text()
        calls = re.findall(r"\bCM\(fm(?:in|ax)\)\(", text)
        helpers = len(re.findall(r"^static \w+ CFM(?:IN|AX)\(", text, re.M))
        assert len(calls) == helpers, path.name  # only inside CFMIN/CFMAX, for a NaN
