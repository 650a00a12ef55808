"""cochlea-sweep and cochlea-tune against hostile inputs and faults (issue 26), a test per
class: one run never breaks another; nothing a user owns (a FIFO, a device, a link, a folder)
is replaced or removed; every bad input or fault is one line with its own documented exit code
(docs/sweeps.md), with nothing written outside the output folder and no partial file; inputs the
workers would refuse are refused up front, before a folder is made.

The full and read-only disks are a private small tmpfs in a mount namespace (``unshare -m``,
as root): a test that cannot make one fails saying so."""

from __future__ import annotations

import csv
import fcntl
import json
import os
import shutil
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from cochlea.apps import cochlea_sweep, cochlea_tune
from cochlea.sweep import results
from cochlea.sweep import spec as sweep_spec
from cochlea.sweep import tune as tuning

SPEC = """format = "cochlea-sweep/1"
scenario = "serial_task"
samples = 2
seed = 7
duration_s = 0.1

[perturb]
mass_scale = {{uniform = [0.9, 1.1]}}
{extra}
"""
#: A tune spec whose searched gain mixes a number and a vector (the number is every component).
TUNE = SPEC.format(extra="""
[gains.arm1]
G_g = {choice = [2.0, [2.0, 2.0, 3.0]]}

[tune]
trials = 3
seed = 10                  # proposes the number, the vector, the number
parallel_candidates = 3
startup_trials = 3
""")
RUN = ["--workers", "1", "--progress", "off"]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1]),
                                                    os.environ.get("PYTHONPATH", "")])}


def write(folder: Path, text: str, name: str = "spec.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def one_line(err: str, program: str = "cochlea-sweep") -> str:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{program}: "), err
    return lines[0]


def tree(folder: Path) -> dict[str, object]:
    """Every path under ``folder`` with its kind and, for a file, its bytes."""
    out: dict[str, object] = {}
    for p in sorted(folder.rglob("*")):
        mode = os.lstat(p).st_mode
        out[str(p.relative_to(folder))] = (p.read_bytes() if stat.S_ISREG(mode)
                                           else stat.S_IFMT(mode))
    return out


@pytest.fixture(scope="module")
def swept(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("swept")
    spec = write(folder, SPEC.format(extra=""))
    out = folder / "out"
    assert cochlea_sweep.main([str(spec), "--out", str(out), *RUN]) == 0
    return spec, out


@pytest.fixture(scope="module")
def tuned(tmp_path_factory) -> tuple[Path, Path]:
    """A finished search whose choice mixes a number and a vector: it used to end in a
    KeyError writing trials.csv, and every resume in the same one."""
    folder = tmp_path_factory.mktemp("tuned")
    spec = write(folder, TUNE)
    out = folder / "out"
    assert cochlea_tune.main([str(spec), "--out", str(out), *RUN]) == 0
    return spec, out


@pytest.mark.slow
def test_a_choice_mixing_a_number_and_a_vector_tunes_and_resumes(tuned, capsys):
    spec, out = tuned
    with open(out / tuning.TRIALS_CSV) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3
    for r in rows:  # a number is every component: three columns, all filled
        values = [r[f"gains.arm1.G_g[{j}]"] for j in range(3)]
        assert all(values), r
        assert values in (["2.0"] * 3, ["2.0", "2.0", "3.0"]), values
    assert len({tuple(r[f"gains.arm1.G_g[{j}]"] for j in range(3)) for r in rows}) == 2
    before = (out / tuning.TRIALS_CSV).read_bytes()
    capsys.readouterr()
    assert cochlea_tune.main([str(spec), "--out", str(out), *RUN]) == 0  # the resume too
    assert (out / tuning.TRIALS_CSV).read_bytes() == before


# --------------------------------------------------------------------------------------------
# One run never breaks another
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_refused_second_sweep_leaves_the_running_ones_files_and_lock(swept, tmp_path,
                                                                      capsys):
    spec_path, _ = swept
    out = tmp_path / "out"
    spec = sweep_spec.load(spec_path)
    results.prepare(out, spec)
    fd = results.hold(out)  # the first run: holds the lock ...
    try:
        in_flight = out / results.PARTS / "part-000000000-000000000.parquet.tmp"
        in_flight.write_bytes(b"half a batch")  # ... and is writing a batch
        before = tree(out)
        code = cochlea_sweep.main([str(spec_path), "--out", str(out), *RUN])
        line = one_line(capsys.readouterr().err)
        assert code == results.EXIT_BUSY and "another cochlea-sweep" in line
        assert tree(out) == before  # its batch in flight included
        probe = os.open(out / results.LOCK, os.O_RDONLY)
        try:  # the first run still holds its lock
            with pytest.raises(BlockingIOError):
                fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            os.close(probe)
    finally:
        results.release(fd)


@pytest.mark.slow
def test_a_refused_second_search_leaves_the_running_ones_files(tuned, tmp_path, capsys):
    spec, finished = tuned
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    fd = tuning.hold(out)
    try:
        (out / tuning.SAMPLES / ".trial-000009.parquet.x.tmp").write_bytes(b"in flight")
        (out / (tuning.JOURNAL + ".lock")).write_text("optuna's")
        before = tree(out)
        code = cochlea_tune.main([str(spec), "--out", str(out), "--trials", "5", *RUN])
        line = one_line(capsys.readouterr().err, "cochlea-tune")
        assert code == results.EXIT_BUSY and "another cochlea-tune" in line
        assert tree(out) == before
    finally:
        tuning.release(out, fd)


# --------------------------------------------------------------------------------------------
# Nothing that is not ours is replaced or removed
# --------------------------------------------------------------------------------------------


def _not_ours(folder: Path) -> dict[str, Path]:
    folder.mkdir()
    fifo = folder / "fifo"
    os.mkfifo(fifo)
    device = folder / "null"
    os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # as root, as CI runs
    target = folder / "target.toml"
    target.write_text("mine")
    link = folder / "link.toml"
    link.symlink_to(target)
    sub = folder / "sub"
    sub.mkdir()
    return {"a FIFO": fifo, "a character device": device, "a symbolic link": link,
            "a folder": sub, "a file": target}


@pytest.mark.slow
def test_replay_out_never_replaces_what_is_there(swept, tmp_path, capsys):
    _, out = swept
    paths = _not_ours(tmp_path / "mine")
    before = tree(tmp_path / "mine")
    for kind, path in paths.items():
        code = cochlea_sweep.main(["replay", str(out), "1", "--out", str(path)])
        line = one_line(capsys.readouterr().err)
        assert code == results.EXIT_OUT, (kind, line)
        assert str(path) in line and kind in line, line
    assert tree(tmp_path / "mine") == before
    new = tmp_path / "mine" / "new.toml"
    assert cochlea_sweep.main(["replay", str(out), "1", "--out", str(new)]) == 0
    assert new.read_text() == cochlea_sweep.sampling.scenario_text(
        cochlea_sweep.replay_spec(out), 1)
    assert sorted(tree(tmp_path / "mine")) == sorted([*before, "new.toml"])  # no temporary


@pytest.mark.slow
def test_a_resume_removes_only_its_own_temporary_files(swept, tmp_path):
    spec, finished = swept
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    parts = out / results.PARTS
    os.mkfifo(parts / "fifo.tmp")
    (parts / "folder.tmp").mkdir()
    (parts / "link.tmp").symlink_to(tmp_path / "elsewhere")
    (parts / "stale.parquet.tmp").write_bytes(b"a killed run's")  # ours: removed
    fd, created = results.claim(out)  # what a resuming cochlea-sweep does, before its workers
    try:
        results.prepare(out, sweep_spec.load(spec))
    finally:
        results.release(fd)
    assert created == []
    names = {p.name for p in parts.iterdir()}
    assert {"fifo.tmp", "folder.tmp", "link.tmp"} <= names and "stale.parquet.tmp" not in names
    assert stat.S_ISFIFO(os.lstat(parts / "fifo.tmp").st_mode)
    assert results.done(out) == {0, 1}


@pytest.mark.slow
def test_a_search_never_writes_over_a_path_that_is_not_its_file(tuned, tmp_path, capsys):
    spec, finished = tuned
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    (out / tuning.TRIALS_CSV).unlink()
    os.mkfifo(out / tuning.TRIALS_CSV)  # opened for writing, it would hang the search
    os.mkfifo(out / "trials.csv.tmp")
    code = cochlea_tune.main([str(spec), "--out", str(out), *RUN])
    line = one_line(capsys.readouterr().err, "cochlea-tune")
    assert code == results.EXIT_WRITE and "trials.csv is a FIFO" in line, line
    assert stat.S_ISFIFO(os.lstat(out / tuning.TRIALS_CSV).st_mode)
    assert stat.S_ISFIFO(os.lstat(out / "trials.csv.tmp").st_mode)


# --------------------------------------------------------------------------------------------
# Refused up front, in one line, before a folder is made
# --------------------------------------------------------------------------------------------

UP_FRONT = {
    # case: (edit of the spec, what the line names)
    "infinite sigma": ("mass_scale = {uniform = [0.9, 1.1]}", "mass_scale = {normal = [1.0, inf]}",
                       "perturb.mass_scale.normal"),
    "huge sigma": ("mass_scale = {uniform = [0.9, 1.1]}", "mass_scale = {normal = [1.0, 1e300]}",
                   "perturb.mass_scale.normal"),
    "sigma the range never holds": ("mass_scale = {uniform = [0.9, 1.1]}",
                                    "mass_scale = {normal = [99.9, 1e4]}", "(0, 100]"),
    "a mean outside the range keeps the range": ("mass_scale = {uniform = [0.9, 1.1]}",
                                                 "mass_scale = {normal = [-1.0, 0.1]}",
                                                 "mu in (0, 100]"),
    "a duration the workers refuse": ("duration_s = 0.1", "duration_s = 4000.0",
                                      "3,600,000 control periods"),
    "too many samples": ("samples = 2", "samples = 100000000", "at most 1,000,000"),
    # A rule between [plant] keys that only a middle sample, or no drawn sample, breaks: every
    # combination the spec's values allow is checked (it stopped the sweep with exit 7 at
    # that sample, part 0 written, and every resume at the same sample).
    "encoder noise off the encoder in the middle": (
        "mass_scale = {uniform = [0.9, 1.1]}", "encoder_noise_counts = 1\n"
        "position_encoder = {grid = [true, false, true]}", "can give (plant.encoder_noise_counts "
        "= 1, plant.position_encoder = false)"),
    "encoder noise under one of two presets": (
        "mass_scale = {uniform = [0.9, 1.1]}", 'plant = {grid = ["realistic", "ideal", '
        '"realistic"]}\nencoder_noise_counts = {uniform = [0, 2]}', "plant.encoder_noise_counts"),
    # Seed 7 draws the 2nd and 4th value of 4 for plant.gearbox: true is never drawn here.
    "the gearbox without armature, not drawn": (
        "mass_scale = {uniform = [0.9, 1.1]}", "gearbox = {choice = [true, false, true, false]}",
        "(plant.gearbox = true)"),
    "a gear key without the gearbox, not drawn": (
        "mass_scale = {uniform = [0.9, 1.1]}", "armature = true\ngearbox = {choice = [false, "
        "true, false, true]}\nbacklash_SI = 0.001", "plant.backlash_SI"),
    "delay and jitter beyond their sum at the ends of a range": (
        "mass_scale = {uniform = [0.9, 1.1]}", "delay_periods = {uniform = [0, 1000]}\n"
        "delay_jitter_periods = {choice = [0, 1]}", "plant.delay_jitter_periods"),
    "too many samples over a grid": ("samples = 2", "samples = 500000", "at most 1,000,000"),
}
GRID = "G_g = {grid = [1.0, 2.0, 3.0]}"


@pytest.mark.parametrize("case", sorted(UP_FRONT))
@pytest.mark.parametrize("program", ["sweep", "tune"])
def test_an_input_the_workers_would_refuse_is_refused_up_front(case, program, tmp_path,
                                                               capsys):
    old, new, named = UP_FRONT[case]
    text = TUNE if program == "tune" else SPEC.format(extra="")
    assert old in text
    text = text.replace(old, new, 1)
    if "grid" in case:  # 500,000 draws at each of 3 grid points
        text = (text.replace("G_g = {choice = [2.0, [2.0, 2.0, 3.0]]}", GRID)
                if program == "tune" else text + f"\n[gains.arm1]\n{GRID}\n")
    spec = write(tmp_path, text)
    out = tmp_path / "out"
    main = cochlea_sweep.main if program == "sweep" else cochlea_tune.main
    code = main([str(spec), "--out", str(out), *RUN])
    line = one_line(capsys.readouterr().err, f"cochlea-{program}")
    assert code == results.EXIT_SPEC and named in line and str(spec) in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.toml"]


@pytest.mark.parametrize("program", ["sweep", "tune"])
def test_an_out_under_a_file_is_named_for_what_it_is(program, tmp_path, capsys):
    spec = write(tmp_path, TUNE if program == "tune" else SPEC.format(extra=""))
    blocker = tmp_path / "notes.txt"
    blocker.write_text("mine")
    main = cochlea_sweep.main if program == "sweep" else cochlea_tune.main
    for out in (blocker / "out", blocker / "a" / "b", blocker):
        code = main([str(spec), "--out", str(out), *RUN])
        line = one_line(capsys.readouterr().err, f"cochlea-{program}")
        assert code == results.EXIT_OUT, line
        assert "is a file, not a folder" in line and "not empty" not in line, line
    assert blocker.read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "spec.toml"]


@pytest.mark.slow
def test_a_sample_that_fails_on_a_worker_is_one_line_and_leaves_no_folder(tmp_path, capsys,
                                                                          monkeypatch):
    # Whatever a worker raises (here: the evaluation is given arguments it does not take,
    # inside the worker) ends as one line; the new folder that got no sample is removed.
    monkeypatch.setattr(cochlea_sweep, "evaluate", int)
    spec = write(tmp_path, SPEC.format(extra=""))
    out = tmp_path / "out"
    code = cochlea_sweep.main([str(spec), "--out", str(out), *RUN])
    line = one_line(capsys.readouterr().err)
    assert code == results.EXIT_SAMPLE and "failed on a worker (TypeError" in line, line
    assert not out.exists()


@pytest.mark.slow
def test_a_worker_logs_a_failed_sample_on_one_line(tmp_path):
    # The worker processes' own stderr (capsys sees only this process's): distributed.worker
    # logged "Compute Failed" on six lines, the last a "Traceback:" of cochlea's internals.
    spec = write(tmp_path, SPEC.format(extra=""))
    script = ("import sys\nfrom cochlea.apps import cochlea_sweep\n"
              "cochlea_sweep.evaluate = int  # raises inside the worker\n"
              "sys.exit(cochlea_sweep.main(sys.argv[1:]))\n")
    done = subprocess.run([sys.executable, "-c", script, str(spec), "--out",
                           str(tmp_path / "out"), *RUN], capture_output=True, text=True,
                          env=ENV, timeout=300)
    assert done.returncode == results.EXIT_SAMPLE, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    failed = [ln for ln in lines if "Compute Failed" in ln]
    assert len(failed) == 1 and "Exception: \"TypeError(" in failed[0], done.stderr
    assert lines[-1].startswith("cochlea-sweep: a sample failed on a worker (TypeError"), lines
    assert all(ln.startswith("cochlea-sweep: ") or " - distributed." in ln for ln in lines), lines


# --------------------------------------------------------------------------------------------
# Damaged folders
# --------------------------------------------------------------------------------------------

DAMAGED = {
    "not JSON": b'{"format": "cochlea-sweep-folder/1", "dig',
    "not UTF-8": b"\xff\xfe\x00garbage",
    "a list": b"[1, 2]",
    "null": b"null",
    "a number as the spec": None,  # spec_text = 5
    "an empty scenario path": None,  # scenario_path = ""
    "a spec that no longer loads": None,  # spec_text with samples = 0
    "a folder": None,
}


@pytest.mark.parametrize("case", sorted(DAMAGED))
@pytest.mark.slow
def test_a_damaged_sweep_json_is_one_line(case, swept, tmp_path, capsys):
    spec, finished = swept
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    manifest = out / results.MANIFEST
    data = json.loads(manifest.read_text())
    if case == "a folder":
        manifest.unlink()
        manifest.mkdir()
    elif DAMAGED[case] is not None:
        manifest.write_bytes(DAMAGED[case])
    else:
        if case == "a number as the spec":
            data["spec_text"] = 5
        elif case == "an empty scenario path":
            data["scenario_path"] = ""
        else:
            data["spec_text"] = data["spec_text"].replace("samples = 2", "samples = 0")
        manifest.write_text(json.dumps(data))
    before = tree(out)
    commands = [["replay", str(out), "0"]]
    if case != "a spec that no longer loads":  # report and resume do not load the texts
        commands += [["report", str(out)], [str(spec), "--out", str(out), *RUN]]
    for argv in commands:
        code = cochlea_sweep.main(argv)
        line = one_line(capsys.readouterr().err)
        assert code == results.EXIT_DAMAGED, (argv[0], line)
        assert str(manifest) in line, line
    assert tree(out) == before


def _foreign_part(parts: Path, case: str) -> Path:
    """A file in a sweep's parts/ (the fixture's two batches, part-0-0 and part-1-1) that is
    not one of its batches (``case``: one of FOREIGN_PARTS)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    first, second = (parts / f"part-{i:09d}-{i:09d}.parquet" for i in (0, 1))
    row0, row1 = pq.read_table(first), pq.read_table(second)
    path = second  # in place of the sweep's own second batch, unless said otherwise
    if case == "a copy under another name":
        path = parts / "part-000000007-000000007.parquet"
        table = row0
    elif case == "a sample in two files":
        path = parts / "part-000000000-000000001.parquet"
        table = pa.concat_tables([row0, row1])
    elif case == "a sample beyond the sweep":
        path = parts / "part-000000009-000000009.parquet"
        table = row1.set_column(0, "sample", pa.array([9]))
    else:
        table = {
            "one column foo": pa.table({"foo": [1, 2]}),
            "samples as text with a gap": pa.table({"sample": ["x", None]}),
            "a name that is not its range": row0,
            "a column of another type": row1.set_column(
                row1.column_names.index("success"), "success", pa.array(["yes"])),
        }[case]
    pq.write_table(table, path)
    return path


FOREIGN_PARTS = ["one column foo", "samples as text with a gap", "a copy under another name",
                 "a sample beyond the sweep", "a name that is not its range",
                 "a column of another type", "a sample in two files"]


@pytest.mark.parametrize("case", FOREIGN_PARTS)
@pytest.mark.slow
def test_a_part_file_not_of_the_sweep_is_one_line_exit_5(case, swept, tmp_path, capsys):
    # They gave exit 18 with advice that never worked (a column foo; samples as text), a
    # resume that ran nothing (samples as text), or exit 0 with "2 of 1 samples finished" (a
    # copy of part 0 under another name).
    spec, finished = swept
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    foreign = _foreign_part(out / results.PARTS, case)
    before = tree(out)
    for argv in (["report", str(out)], [str(spec), "--out", str(out), *RUN]):
        code = cochlea_sweep.main(argv)
        line = one_line(capsys.readouterr().err)
        assert code == results.EXIT_DAMAGED, (argv[0], line)
        assert f"{foreign}: not a part file of this sweep" in line, line
        assert "move it away and run the same command" in line, line
    assert tree(out) == before
    foreign.unlink()  # as the line says: the same command then runs what is missing
    assert cochlea_sweep.main([str(spec), "--out", str(out), *RUN]) == 0
    assert sorted(results.done(out)) == [0, 1]
    capsys.readouterr()


@pytest.mark.slow
def test_a_damaged_journal_line_is_one_line(tuned, tmp_path, capsys):
    def damage(journal):
        lines = journal.read_bytes().splitlines(keepends=True)
        lines[2] = b'{"op_code": 5, "worker_id": \n'
        journal.write_bytes(b"".join(lines))

    journal, line = _tune_refuses_its_journal(tuned, tmp_path, capsys, damage, "--trials", "5")
    assert str(journal) in line, line


def _tune_refuses_its_journal(tuned, tmp_path, capsys, damage, *argv) -> tuple[Path, str]:
    """A finished search copied, its journal damaged (``damage(path)``), resumed: exit 5 with
    one line, and the folder left as it was. The journal's path and the line."""
    spec, finished = tuned
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    journal = out / tuning.JOURNAL
    damage(journal)
    before = tree(out)
    code = cochlea_tune.main([str(spec), "--out", str(out), *argv, *RUN])
    line = one_line(capsys.readouterr().err, "cochlea-tune")
    assert code == results.EXIT_DAMAGED, line
    assert tree(out) == before
    return journal, line


@pytest.mark.parametrize("command", ["report", "replay"])
def test_a_file_given_as_the_sweep_folder_is_not_a_sweep_folder(command, tmp_path, capsys):
    # It was exit 5, "unreadable sweep manifest (Not a directory)": a damaged folder.
    afile = write(tmp_path, "notes", "afile")
    for folder in (afile, afile / "below"):
        code = cochlea_sweep.main([command, str(folder)] + (["0"] if command == "replay" else []))
        line = one_line(capsys.readouterr().err)
        assert code == results.EXIT_OUT, line
        assert line.startswith(f"cochlea-sweep: {folder}: not a sweep folder ("), line
    assert afile.read_text() == "notes"


@pytest.mark.slow
def test_a_journal_of_another_search_is_one_line_exit_5(tuned, tmp_path, capsys):
    # A study.journal whose G_g was searched on a range (this search's is a choice by index):
    # its values were taken for this search's (a choice's index from a gain; the other way, a
    # choice's index 0 as G_g = 0 in tuned.toml, exit 0).
    import optuna
    from optuna.distributions import FloatDistribution
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    def another_search(journal):
        journal.unlink()
        study = optuna.create_study(study_name=tuning.STUDY, direction="minimize",
                                    storage=JournalStorage(JournalFileBackend(str(journal))))
        for _ in range(3):
            trial = study.ask({"gains.arm1.G_g": FloatDistribution(1.0, 5.0)})
            study.tell(trial, 0.5)

    journal, line = _tune_refuses_its_journal(tuned, tmp_path, capsys, another_search)
    assert f"{journal}: not this search's journal: trial 0's gains.arm1.G_g is " \
           "FloatDistribution(" in line, line


@pytest.mark.parametrize("key", ["nominal", 3])
@pytest.mark.slow
def test_a_run_file_not_of_the_search_is_one_line_exit_5(key, tuned, tmp_path, capsys):
    # samples/nominal.parquet (or a trial's, asked but not yet told) with columns sample, foo:
    # a KeyError 'convergence_ratio' traceback judging it (exit 0 with a wrong verdict had the
    # columns been there but the rows not the sample's).
    import pyarrow as pa
    import pyarrow.parquet as pq

    spec, finished = tuned
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    foreign = tuning.rows_path(out, key)
    pq.write_table(pa.table({"sample": [0, 1], "foo": [1.0, 2.0]}), foreign)
    code = cochlea_tune.main([str(spec), "--out", str(out), "--trials", "4", *RUN])
    line = one_line(capsys.readouterr().err, "cochlea-tune")
    assert code == results.EXIT_DAMAGED, line
    assert f"{foreign}: not a run file of this search (no column 'grid')" in line, line
    assert (out / tuning.RESULT).read_bytes() == (finished / tuning.RESULT).read_bytes()


# --------------------------------------------------------------------------------------------
# Full and read-only disks: a private tmpfs in a mount namespace
# --------------------------------------------------------------------------------------------

CHECK = """
import sys, pathlib, pyarrow.parquet as pq
root = pathlib.Path(sys.argv[1])
for p in sorted(root.rglob("*")):
    print("PATH", p.relative_to(root))
    if p.suffix == ".parquet":
        pq.read_table(p)  # whole, or this fails
"""


def in_tmpfs(tmp_path: Path, command: list[str], *, size_kb: int = 200, free_kb: int | None = None,
             read_only: bool = False) -> tuple[int, str, list[str]]:
    """``command`` (with ``{DISK}`` for the mount point) on a private tmpfs of ``size_kb``,
    filled to ``free_kb`` free; returns its exit code, its stderr and the paths on the disk
    after it (each Parquet file read back whole)."""
    if shutil.which("unshare") is None or subprocess.run(
            ["unshare", "-m", "true"], capture_output=True).returncode != 0:
        pytest.fail("unshare -m is not available here (run as root on Linux): the full and "
                    "read-only disk cases cannot be made", pytrace=False)
    disk = tmp_path / "disk"
    disk.mkdir()
    fill = "" if free_kb is None else (
        f"head -c {(size_kb - free_kb) * 1024} /dev/zero > {disk}/fill && ")
    mount_opts = f"size={size_kb}k" + (",ro" if read_only else "")
    cmd = " ".join(f"'{c}'" for c in command).replace("{DISK}", str(disk))
    check = tmp_path / "check.py"
    check.write_text(CHECK)
    script = (f"mount -t tmpfs -o size={size_kb}k tmpfs {disk} && {fill}"
              + (f"mount -o remount,{mount_opts} {disk} && " if read_only else "")
              + f"{cmd}; rc=$?; {sys.executable} {check} {disk} || exit 99; exit $rc")
    done = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True,
                          text=True, env=ENV, timeout=300)
    paths = [ln[5:] for ln in done.stdout.splitlines() if ln.startswith("PATH ")]
    assert done.returncode != 99, done.stderr
    return done.returncode, done.stderr, paths


def _bin(program: str) -> list[str]:
    return [sys.executable, "-m", f"cochlea.apps.cochlea_{program}"]


@pytest.mark.parametrize("program", ["sweep", "tune"])
@pytest.mark.slow
def test_a_read_only_disk_is_one_line(program, tmp_path):
    spec = write(tmp_path, TUNE if program == "tune" else SPEC.format(extra=""))
    code, err, paths = in_tmpfs(tmp_path, [*_bin(program), str(spec), "--out", "{DISK}/out",
                                           *RUN], read_only=True)
    line = one_line(err, f"cochlea-{program}")
    assert code == results.EXIT_OUT and "read-only" in line, line
    assert paths == []


@pytest.mark.parametrize("program", ["sweep", "tune"])
@pytest.mark.slow
def test_a_full_disk_is_one_line_and_leaves_no_partial_file(program, tmp_path):
    # Room for the folder's manifest and spec, not for a batch of samples (about 10 kB).
    spec = write(tmp_path, TUNE if program == "tune" else SPEC.format(extra=""))
    code, err, paths = in_tmpfs(tmp_path, [*_bin(program), str(spec), "--out", "{DISK}/out",
                                           *RUN], free_kb=12)
    line = one_line(err, f"cochlea-{program}")
    assert code == results.EXIT_WRITE and "No space left on device" in line, line
    assert not [p for p in paths if p.endswith(".tmp") or ".tmp" in Path(p).name], paths
    assert [p for p in paths if p.endswith(".parquet")] == []  # none half-written as whole


@pytest.mark.slow
def test_a_sweep_beside_another_cluster_prints_nothing_of_dask(tmp_path):
    # Distributed's default HTTP port (8787) taken, as by another sweep, tune or Dask cluster on
    # the machine: the scheduler chose another and warned "Port 8787 is already in use" into
    # the sweep's stderr (found with two sweeps at once in make test's shared-out pass).
    with socket.socket() as taken:
        try:
            taken.bind(("", 8787))
            taken.listen()
        except OSError:
            pass  # already taken: the case itself
        spec = write(tmp_path, SPEC.format(extra=""))
        done = subprocess.run([*_bin("sweep"), str(spec), "--out", str(tmp_path / "out"), *RUN],
                              capture_output=True, text=True, env=ENV, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "", done.stderr
