"""``cochlea-codegen``: regenerate ``generated_c/`` (or check it is fresh, ``--check``); with
``--scenario FILE --out DIR``, generate and compile the C kernels of a user's robot and scenario
into ``DIR`` (``DIR/libcochlea.so``, which ``cochlea-run --library DIR`` runs on)."""

from __future__ import annotations

import dataclasses
import filecmp
import sys
import tempfile
import time
from pathlib import Path

from ..console import OneLineParser, tolerate_closed_stdout
from ..dynamixel.embedded_drives import drives_header, write_drive_tables
from ..errors import EXIT_USER_ERROR, CochleaError
from ..kernels.build import compile_library
from ..kernels.catalogue import CodegenConfig, collect_units
from ..kernels.generate import CONFIG, check, generate, load_config, write_kernels
from ..sim import load_scenario, unit_setups
from ..sim.compiled import scenario_units
from ..sim.embedded import check_embeddable, scenario_sources, write_embedded
from ..sim.scenario import PLANT_PRESETS, load_system
from .outputs import check_folder, refuse_inputs_inside


def write_embedded_folder(config, folder) -> list[Path]:
    """generated_c/embedded/: every embedded scenario's controller, then the Dynamixel drive
    tables of the robots (embedded/core/drives.h reads them)."""
    return sorted(write_embedded(config, folder) + write_drive_tables(folder))


def _load_config(path: Path):
    if path.is_dir():
        raise CochleaError(f"--config {path} is a folder: name the generator's TOML "
                           "configuration file")
    try:
        return load_config(path)
    except UnicodeDecodeError as exc:
        raise CochleaError(f"--config {path}: not UTF-8 text (byte {exc.start}): save the "
                           "configuration as UTF-8") from None


def _check_out(out: Path, option: str) -> None:
    """The output folder, checked before anything is generated. The generator replaces every
    file at the folder's top level, so a folder that holds other files (it has no manifest.c,
    the mark of generated_c/) is refused rather than emptied."""
    check_folder(out, option, empty=False)
    if out.is_dir() and not (out / "manifest.c").is_file() and any(
            p.is_file() for p in out.iterdir()):
        raise CochleaError(f"{option} {out} holds files that cochlea-codegen did not generate "
                           "(no manifest.c), and it replaces every file there: choose a new "
                           "or empty folder, or a generated_c/ folder")


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(
        prog="cochlea-codegen",
        description="Regenerate the C kernels (generated_c/) from the robot descriptions in "
                    "models/robots/ and the configuration codegen/kernels.toml, "
                    "and the scenarios' embedded controllers (generated_c/embedded/).",
        epilog="Then `make lib` builds build/libcochlea.so (no Python needed).")
    parser.add_argument("--config", type=Path, default=CONFIG, help="generator configuration")
    parser.add_argument("--out", type=Path, help="output folder (default: the configuration's)")
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary folder and exit 1 if generated_c/ "
                             "(with --scenario: --out) differs (stale)")
    user = parser.add_argument_group(
        "a user's robot and scenario (docs/codegen.md, \"Your own robot's C kernels\")")
    user.add_argument("--scenario", type=Path, metavar="FILE",
                      help="generate the kernels this scenario's runs call (controller, plant "
                           "steps, pose, closed loops, model kernels) into --out and compile "
                           "--out/libcochlea.so")
    user.add_argument("--description", type=Path, metavar="FILE",
                      help="--scenario: the robot description to use instead of the one the "
                           "scenario names (runs must then use it too)")
    user.add_argument("--plant", action="append", choices=list(PLANT_PRESETS),
                      help="--scenario: also the plant of this preset (as cochlea-run --plant "
                           "sets it; repeat for several; default: the scenario's own)")
    user.add_argument("--embedded", action="store_true",
                      help="--scenario: also the scenario's embedded controller and its "
                           "robot's drive table in --out/embedded/ (then `make embedded "
                           "GEN=DIR BUILD=DIR/build`: docs/codegen.md)")
    user.add_argument("--no-build", action="store_true",
                      help="--scenario: write the C only (compile it later with cc, as "
                           "`make lib` does)")
    args = parser.parse_args(argv)
    tolerate_closed_stdout()
    try:
        if args.scenario is not None or args.description is not None or args.plant \
                or args.no_build or args.embedded:
            return _user(args)
        config = _load_config(args.config)
        if args.check:
            differ = check(config, write_embedded_folder)
            if differ:
                print(f"cochlea-codegen: {config.output} is stale; these files differ: "
                      + ", ".join(differ) + ". Run cochlea-codegen and commit the result.",
                      file=sys.stderr)
                return 1
            print(f"cochlea-codegen: {config.output} is up to date")
            return 0
        out = args.out if args.out is not None else config.output
        option = "--out" if args.out is not None else f"{config.path}: output"
        refuse_inputs_inside(out, option, [("--config", config.path)])
        _check_out(out, option)
        start = time.perf_counter()
        try:
            paths = generate(config, out, write_embedded_folder)
        except OSError as exc:  # a full disk, or the folder changed under us
            raise CochleaError(f"cannot write {out} ({exc.strerror or exc}); it is as it was: "
                               "free some space and run cochlea-codegen again") from None
    except CochleaError as exc:
        print(f"cochlea-codegen: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    size = sum(p.stat().st_size for p in paths)
    print(f"cochlea-codegen: {len(paths)} files, {size / 1024:.0f} KiB in "
          f"{paths[0].parent} ({time.perf_counter() - start:.1f} s)")
    return 0


def scenario_config(where: Path) -> CodegenConfig:
    """The shipped configuration's CasADi options and library name, for a user's kernels."""
    shipped = load_config(CONFIG)
    return dataclasses.replace(shipped, path=where, robots=(), embedded=dataclasses.replace(
        shipped.embedded, scenarios=()))


def scenario_kernels(scenario: Path, description: Path | None = None,
                     presets: list[str] | None = None):
    """``(config, kernels, loops)`` of a user's scenario: per plant preset (default: the
    scenario's own), the scenario loaded as cochlea-run loads it and its units' kernels."""
    kernels, loops, units = [], [], []
    for preset in presets or [None]:
        sc = load_scenario(scenario, plant_preset=preset)
        if description is not None:
            sc = dataclasses.replace(sc, description=str(description),
                                     system=load_system(sc.robot, str(description)))
        units += scenario_units(sc, unit_setups(sc, gravity=False))
    config = scenario_config(scenario)
    kernels, loops = collect_units(units, config.function, str(scenario))
    return config, kernels, loops


def _embedded_drives(scenario: Path, description: Path | None) -> str:
    """The drive table of the scenario's robot, or its refusal in one line (CochleaError)."""
    sc = load_scenario(scenario)
    check_embeddable(sc)
    system = sc.system if description is None else load_system(sc.robot, str(description))
    return drives_header(sc.robot, system=system)


def write_scenario_embedded(scenario: Path, description: Path | None, config: CodegenConfig,
                            folder: Path) -> list[Path]:
    """``folder`` (``DIR/embedded``): the scenario's embedded controller, the table of
    scenarios holding it, and its robot's drive table from its description, what
    ``make embedded GEN=DIR`` compiles into the embedded program (the folder's other files
    are removed)."""
    sc = load_scenario(scenario)
    if description is not None:
        sc = dataclasses.replace(sc, description=str(description),
                                 system=load_system(sc.robot, str(description)))
    files = scenario_sources(sc, config.embedded.function)
    files[f"{sc.robot}_drives.h"] = drives_header(sc.robot, system=sc.system)
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        if old.is_file():
            old.unlink()
    written = []
    for name, text in sorted(files.items()):
        (folder / name).write_text(text)
        written.append(folder / name)
    return written


def _user(args) -> int:
    """``--scenario FILE --out DIR``: generate (and compile) a user's kernels."""
    if args.scenario is None:
        raise CochleaError("--description, --plant, --embedded and --no-build go with "
                           "--scenario FILE")
    if args.out is None:
        raise CochleaError("--scenario needs --out DIR: the folder for the C kernels and "
                           "their libcochlea.so")
    if args.config != CONFIG:
        raise CochleaError("--config lists the shipped robots' kernels; with --scenario the "
                           "scenario says what to generate: leave --config out")
    out = args.out
    if out.resolve() == load_config(CONFIG).output:
        raise CochleaError(f"--out {out} is the shipped robots' generated_c/: choose a folder "
                           "of your own for a scenario's kernels")
    inputs = [("--scenario", args.scenario), ("the scenario's description",
                                               load_scenario(args.scenario).system.path)]
    if args.description is not None:
        inputs.append(("--description", args.description))
    refuse_inputs_inside(out, "--out", inputs)  # its files are replaced and removed
    if not args.check:
        _check_out(out, "--out")
    start = time.perf_counter()
    if args.embedded and not args.check:  # a chain the embedded bridge cannot drive: refused
        _embedded_drives(args.scenario, args.description)  # before any file is written
    config, kernels, loops = scenario_kernels(args.scenario, args.description, args.plant)
    if args.check:
        with tempfile.TemporaryDirectory(prefix="cochlea-codegen-") as tmp:
            tmp = Path(tmp)
            written = write_kernels(config, kernels, loops, tmp)
            if args.embedded:  # and the embedded folder, compared as embedded/<file>
                written += write_scenario_embedded(args.scenario, args.description, config,
                                                   tmp / config.embedded.folder)
            fresh = {str(p.relative_to(tmp)) for p in written}
            folders = [out] + ([out / config.embedded.folder] if args.embedded else [])
            have = {str(p.relative_to(out)) for f in folders if f.is_dir() for p in f.iterdir()
                    if p.is_file() and p.suffix != ".so"}
            differ = sorted((fresh ^ have) | {n for n in fresh & have if not filecmp.cmp(
                tmp / n, out / n, shallow=False)})
        if differ:
            print(f"cochlea-codegen: {out} is stale for {args.scenario}; these files differ: "
                  + ", ".join(differ), file=sys.stderr)
            return 1
        print(f"cochlea-codegen: {out} is up to date for {args.scenario}")
        return 0
    try:
        paths = write_kernels(config, kernels, loops, out)
    except OSError as exc:
        raise CochleaError(f"cannot write {out} ({exc.strerror or exc}); it is as it was: "
                           "free some space and run cochlea-codegen again") from None
    if args.embedded:
        paths += write_scenario_embedded(args.scenario, args.description, config,
                                         out / config.embedded.folder)
    generated = time.perf_counter() - start
    size = sum(p.stat().st_size for p in paths)
    print(f"cochlea-codegen: {len(kernels)} kernels and {len(loops)} closed loops of "
          f"{args.scenario}: {len(paths)} files, {size / 1024:.0f} KiB in {out} "
          f"({generated:.1f} s)", flush=True)
    if args.no_build:
        return 0
    start = time.perf_counter()
    library = compile_library(out)
    print(f"cochlea-codegen: compiled {library} ({time.perf_counter() - start:.1f} s); run on "
          f"it with cochlea-run --scenario {args.scenario} --kernels c --library {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
