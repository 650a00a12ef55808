"""Builds the C kernels and the shipped data into the wheel, so an installed cochlea runs as a
checkout does.

Everything else about the package is declared in pyproject.toml. A regular (non-editable) build
copies the top-level ``models/`` (robot descriptions, scenarios, example robots) and ``codegen/``
(the generator's configuration and template) into ``cochlea/data/`` of the build tree, never of
the source tree, and compiles ``generated_c/*.c`` -- committed, warning-free C99 -- into
``cochlea/lib/libcochlea.so`` with the C compiler ``$CC`` (default ``cc``), the same flags as
``make lib``. Without a compiler the wheel is built without the library and cochlea runs on its
CasADi kernels (with a warning). An editable install copies and compiles nothing: a checkout
reads ``models/`` and ``codegen/`` where they are (``cochlea.resources.data_root``) and uses
``build/libcochlea.so`` from ``make lib``.
"""

from __future__ import annotations

import os
import shlex
import shutil
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
#: Top-level folders the wheel carries as ``cochlea/data/<name>/``.
DATA_FOLDERS = ("models", "codegen")


class BuildWithKernels(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        for name in DATA_FOLDERS:
            target = Path(self.build_lib) / "cochlea" / "data" / name
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(ROOT / name, target,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        sources = sorted((ROOT / "generated_c").glob("*.c"))
        if not sources:
            self.warn("generated_c/ is missing: the wheel has no C kernels")
            return
        out = Path(self.build_lib) / "cochlea" / "lib"
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="cochlea-kernels-") as objects:
            self._compile(sources, Path(objects), out)
        self._compile_lane(out)

    def _compile_lane(self, out: Path) -> None:
        """``libcochlea-lane.so`` (``make lib``'s rule): the bus period's packet work in C for
        the emulator and the bridge; without it both answer in Python, the same bytes."""
        cc = shlex.split(os.environ.get("CC", "cc"))
        sources = [ROOT / "cochlea" / "dynamixel" / "c" / "lane.c",
                   ROOT / "embedded" / "core" / "dxl.c"]
        try:
            subprocess.run([*cc, *FLAGS, f"-I{ROOT / 'embedded' / 'core'}", "-shared", "-o",
                            str(out / "libcochlea-lane.so"), *map(str, sources)], check=True,
                           capture_output=True, text=True)
        except (OSError, subprocess.CalledProcessError) as exc:
            detail = getattr(exc, "stderr", "") or str(exc)
            print(f"cochlea: the bus lane was not compiled ({detail.strip()[:500]}); the "
                  "installed emulator and bridge will do their packet work in Python",
                  file=sys.stderr)

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
