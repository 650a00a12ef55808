"""Builds the C kernels into the wheel, so an installed cochlea runs on them as a checkout does.

Everything else about the package is declared in pyproject.toml. A regular (non-editable) build
compiles ``generated_c/*.c`` -- committed, warning-free C99 -- into ``cochlea/lib/libcochlea.so``
with the C compiler ``$CC`` (default ``cc``), the same flags as ``make lib``. Without a compiler
the wheel is built without the library and cochlea runs on its CasADi kernels (with a warning).
An editable install compiles nothing: a checkout uses ``build/libcochlea.so`` from ``make lib``.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from setuptools import Distribution, setup
from setuptools.command.bdist_wheel import bdist_wheel
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
FLAGS = ["-std=c99", "-fPIC", "-O2", "-Wall", "-Wextra", "-Werror"]


class BuildWithKernels(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        sources = sorted((ROOT / "generated_c").glob("*.c"))
        if not sources:
            self.warn("generated_c/ is missing: the wheel has no C kernels")
            return
        out = Path(self.build_lib) / "cochlea" / "lib"
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="cochlea-kernels-") as objects:
            self._compile(sources, Path(objects), out)

    def _compile(self, sources: list[Path], objects: Path, out: Path) -> None:
        cc = shlex.split(os.environ.get("CC", "cc"))

        def compile_one(source: Path) -> Path:
            target = objects / f"{source.stem}.o"
            subprocess.run([*cc, *FLAGS, "-c", str(source), "-o", str(target)], check=True,
                           capture_output=True, text=True)
            return target

        try:
            with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
                built = list(pool.map(compile_one, sources))
            subprocess.run([*cc, "-shared", "-o", str(out / "libcochlea.so"),
                            *map(str, built), "-lm"], check=True, capture_output=True, text=True)
        except (OSError, subprocess.CalledProcessError) as exc:
            detail = getattr(exc, "stderr", "") or str(exc)
            print(f"cochlea: the C kernels were not compiled ({detail.strip()[:500]}); the "
                  "installed package will run on its CasADi kernels", file=sys.stderr)


class BinaryDistribution(Distribution):
    """The wheel carries a compiled library: it is for this platform, not any."""

    def has_ext_modules(self) -> bool:
        return True


class PlatformWheel(bdist_wheel):
    """Tagged py3-none-<platform>: the library is plain C, loaded through ctypes, so it does not
    depend on the Python version or ABI."""

    def get_tag(self) -> tuple[str, str, str]:
        return ("py3", "none", super().get_tag()[2])


setup(cmdclass={"build_py": BuildWithKernels, "bdist_wheel": PlatformWheel},
      distclass=BinaryDistribution)
