"""The all-in-C simulation (embedded/sim/simulate.c): the embedded controller and the generated
plant kernels in one C program, with no Python and no CasADi, log the simulation's periods.

The tolerance. Both runs integrate the same plant kernel from the same state; what may differ is
the controller: the embedded step evaluates the desired trajectory and the law through its own
generated C, held to the CasADi Functions to 1e-12 relative per step
(tests/test_embedded_generated.py). How much the closed loop amplifies a per-step relative
difference was measured with the float build, whose per-step rounding is 2**-24: over 2 s of the
four thesis studies, no logged value moved by more than 132 x 2**-24 relative to max(1, its
peak). So per-step differences of 1e-12 show at most about 1.3e-10; TOLERANCE = 1e-9 (relative
to max(1, peak), every logged value) leaves a factor of 7. On the realistic studies a difference
could also move a measurement across a grid step; at 1e-12 that has a chance of the order of
1e-12 / 1.5e-3 per sample, never seen. Measured with the same compiler: 0 (bit for bit equal),
on the serial and the realistic studies over their full length (bench/results.md). The two ideal
parallel studies' plant integrates the closed chain's forward dynamics in its block form
(cochlea/robots/parallel/forward.py), equal to the general kernel's Lagrange form to rounding
only: over their full 10 s their logs differ from simulate()'s by 6.5e-15 (parallel_joint) and
2.3e-15 (parallel_task) relative to max(1, peak) at most, 1.0e-14 and 3.6e-15 absolute.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from bench import embedded_bench as eb
from cochlea.sim import load_scenario, simulate, unit_setups

ROOT = Path(__file__).resolve().parent.parent
DURATION = 2.0  # s
TOLERANCE = 1e-9  # relative to max(1, peak) of each logged value; see the module's docstring
#: The ideal parallel studies over their whole length (the block form of the closed chain's
#: forward dynamics against the general kernel's Lagrange form): 6.5e-15 measured, and these
#: plants do not amplify rounding (one ulp added to every effort moved their logs by 1e-14).
FULL_LENGTH_PARALLEL = 1e-12

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None,
                                reason="no C compiler")


@pytest.fixture(scope="module", autouse=True)
def library():
    """The simulation this is compared with runs on libcochlea.so; the program's plant kernels
    are found through its manifest."""
    subprocess.run(["make", "-s", "lib"], cwd=ROOT, check=True, capture_output=True)


def run_logged(name: str, precision: str, tmp_path: Path, duration: float = DURATION):
    sc = eb.sim_scenario(name)
    setups = unit_setups(sc)
    log = tmp_path / f"{name}_{precision}.log"
    info = eb.run_simulation(eb.build_simulation(name, precision), duration, log)
    return eb.read_log(log, info, sc, setups), info, sc, setups


def worst_relative(result, reference) -> dict[str, float]:
    """Per logged value: the largest difference relative to max(1, the reference's peak)."""
    worst = {}
    for u, r in zip(result.units, reference.units, strict=True):
        assert u.name == r.name
        for key in eb.LOG_FIELDS:
            a, b = getattr(u, key), getattr(r, key)
            assert a.shape == b.shape, (u.name, key)
            scale = max(1.0, float(np.max(np.abs(b))))
            worst[f"{u.name}.{key}"] = float(np.max(np.abs(a - b))) / scale
    return worst


@pytest.mark.parametrize("name", eb.SCENARIOS)
@pytest.mark.slow
def test_log_equals_the_simulation(name, tmp_path):
    """2 s of every study: states, desired trajectory, errors, applied efforts, estimates and
    poses equal ``simulate()``'s, period for period (ideal plant; realistic: delayed, encoder
    grid, current grid, the geared plant with backlash and static friction)."""
    result, info, sc, setups = run_logged(name, "double", tmp_path)
    reference = simulate(sc, duration=DURATION, setups=setups)
    assert info["status"] == "completed" and info["precision"] == "double"
    assert info["periods"] == info["rows"] == len(reference.time) == round(DURATION / sc.period)
    np.testing.assert_array_equal(result.time, reference.time)
    worst = worst_relative(result, reference)
    assert max(worst.values()) <= TOLERANCE, worst


@pytest.mark.parametrize("name", eb.THESIS)
@pytest.mark.slow
def test_float_build_follows_the_simulation(name, tmp_path):
    """The float controller in the same loop: efforts within 1e-5 of the run's peak effort, as
    the float build's own test holds it (tests/test_embedded_generated.py), and the joints
    within 1e-5 (rad, m)."""
    result, info, sc, setups = run_logged(name, "float", tmp_path)
    reference = simulate(sc, duration=DURATION, setups=setups)
    assert info["status"] == "completed" and info["precision"] == "float"
    peak = max(float(np.max(np.abs(r.tau))) for r in reference.units)
    for u, r in zip(result.units, reference.units):
        assert np.max(np.abs(u.tau - r.tau)) <= 1e-5 * peak
        assert np.max(np.abs(u.q - r.q)) <= 1e-5


#: The full-length bound where sin and cos come from sim_trig.h (the serial thesis studies):
#: relative to max(1, peak), per logged value. Measured 1.3e-14 at most (docs/embedded.md).
TRIG_TOLERANCE = 1e-12


@pytest.mark.parametrize("name", [
    "serial_joint", "serial_task",
    pytest.param("parallel_joint", marks=pytest.mark.slow),
    pytest.param("parallel_task", marks=pytest.mark.slow)])
def test_full_length_log_is_the_simulations(name, tmp_path):
    """The whole study, log written, against ``simulate()`` (its C path runs the general
    kernels with libm). The log's desired trajectory is the sample the step used (evaluated
    once a period). The parallel studies' specialised plant runs the closed chain's block form,
    equal to the general kernel's to rounding: their logs within FULL_LENGTH_PARALLEL
    (relative to max(1, peak)), not 0. The serial studies take sin and cos from sim_trig.h's
    inline sim_sincos (plant and controller; within an ulp of libm's): every logged value
    within TRIG_TOLERANCE of max(1, its peak), the bound issue 30 sets, and the run does
    differ (the inline path runs). Any other study: bit for bit."""
    result, info, sc, setups = run_logged(name, "double", tmp_path, duration=sc_duration(name))
    reference = simulate(sc, setups=setups)
    assert info["status"] == "completed" and info["rows"] == len(reference.time)
    if name.startswith("parallel"):
        worst = worst_relative(result, reference)
        assert max(worst.values()) <= FULL_LENGTH_PARALLEL, worst
        assert max(worst.values()) > 0.0  # the block form runs, not the general kernel's
        return
    if not eb.inline_trig_applies(sc, setups):
        for u, r in zip(result.units, reference.units, strict=True):
            for key in eb.LOG_FIELDS:
                a, b = getattr(u, key), getattr(r, key)
                assert a.shape == b.shape and np.array_equal(a, b), (u.name, key)
        return
    assert name.startswith("serial")
    np.testing.assert_array_equal(result.time, reference.time)
    worst = worst_relative(result, reference)
    assert max(worst.values()) <= TRIG_TOLERANCE, worst
    assert max(worst.values()) > 0


def sc_duration(name: str) -> float:
    return float(load_scenario(name).duration)


@pytest.mark.parametrize("writer", ["thread", "units"])
def test_the_log_ends_on_any_row_of_its_blocks(writer, tmp_path, monkeypatch):
    """The log's ring of blocks (simulate.c: SIM_BLOCKS of SIM_BLOCK_ROWS rows), written by a
    writer thread or by the units: a run that ends on a block's last row, after the ring
    wrapped, one row into a block, or before the first block is full, logs the first rows of a
    longer run, byte for byte."""
    monkeypatch.setenv("COCHLEA_SIM_LOG_WRITER", writer)
    binary = eb.build_simulation("serial_joint")
    longer = tmp_path / "longer.log"
    info = eb.run_simulation(binary, 3.0, longer)
    block = (1 << 18) // (8 * info["columns"]) + 1  # SIM_BLOCK_ROWS
    whole = longer.read_bytes()
    for rows in (block, 4 * block, 4 * block + 1, 7):
        log = tmp_path / f"{rows}.log"
        part = eb.run_simulation(binary, rows * 1e-3, log)
        assert part["rows"] == rows and part["status"] == "completed"
        assert part["log_writer"] == writer
        assert log.read_bytes() == whole[:rows * 8 * info["columns"]], rows


@pytest.mark.parametrize("name", ["serial_joint", "parallel_joint"])
def test_both_log_writers_write_the_same_log(name, tmp_path, monkeypatch):
    """The units writing their log (whichever is ahead of the oldest block not written) and a
    writer thread write the same bytes, the serial arms' two units and the mechanism's one."""
    binary = eb.build_simulation(name)
    logs = {}
    for writer in ("thread", "units"):
        monkeypatch.setenv("COCHLEA_SIM_LOG_WRITER", writer)
        logs[writer] = tmp_path / f"{writer}.log"
        info = eb.run_simulation(binary, 2.345, logs[writer])
        assert info["log_writer"] == writer and info["status"] == "completed"
        assert (info["writer_cpu_s"] > 0) == (writer == "thread")
    assert logs["thread"].read_bytes() == logs["units"].read_bytes()
    monkeypatch.setenv("COCHLEA_SIM_LOG_WRITER", "both")
    done = subprocess.run([str(binary), "--log", str(tmp_path / "x.log")], capture_output=True,
                          text=True)
    assert done.returncode == 2 and "COCHLEA_SIM_LOG_WRITER" in done.stderr
    assert not done.stdout and not (tmp_path / "x.log").exists()


def test_the_units_write_their_log_where_they_are_as_many_as_the_processors(tmp_path):
    """Left to choose, the serial arms write their own log where the process has no more
    processors than arms (a writer thread would leave one arm a processor to itself and the
    other arm and the writer the other one), each arm held on a processor of its own; the
    mechanism's one unit has a writer thread beside it."""
    cpus = os.sched_getaffinity(0)
    if len(cpus) > 2:
        two = set(sorted(cpus)[:2])
    else:
        two = cpus
    binary = eb.build_simulation("serial_joint")
    done = subprocess.run([str(binary), "--duration", "0.5", "--log", str(tmp_path / "a.log")],
                          preexec_fn=lambda: os.sched_setaffinity(0, two), capture_output=True,
                          text=True, check=True, env={k: v for k, v in os.environ.items()
                                                      if k != "COCHLEA_SIM_LOG_WRITER"})
    info = json.loads(done.stdout)
    assert info["log_writer"] == "units" and info["writer_cpu_s"] == 0.0
    if len(two) == 2:
        assert sorted(info["unit_processors"]) == sorted(two)
    parallel = eb.run_simulation(eb.build_simulation("parallel_joint"), 0.5, tmp_path / "p.log")
    assert parallel["log_writer"] == "thread"
    assert eb.run_simulation(binary, 0.5)["log_writer"] == "none"


@pytest.mark.parametrize("name", ["serial_joint", "parallel_task"])
def test_specialised_plant_is_the_general_one(name):
    """A unit's plant with the scenario's constants folded in (x, tau) gives the general
    Function's next state to 1e-12 relative, at states and efforts away from the start, in
    fewer operations: the serial arms' through their folded sums and L D L^T solve
    (cochlea/robots/serial/folded.py), the parallel mechanism's through the closed chain's
    block form (1503 operations against the general kernel's 2389)."""
    sc = eb.sim_scenario(name)
    u = unit_setups(sc)[0]
    general = u.plant_function(sc.plant_substeps)
    special = eb.specialised_plant(u, sc.plant_substeps, sc.period, "sim_unit_plant")
    assert special.n_in() == 2 and special.n_instructions() < general.n_instructions()
    rng = np.random.default_rng(3)
    n = u.plant_model.nq
    differs = False
    for _ in range(20):
        x = np.asarray(u.plant_x0) + rng.normal(0.0, 0.2, len(u.plant_x0))
        tau = rng.normal(0.0, 1.0, n)
        constants = [u.plant_params, u.friction, sc.period] + \
            ([u.drive] if general.n_in() == 6 else [])
        a = np.asarray(general(x, tau, *constants)).ravel()
        b = np.asarray(special(x, tau)).ravel()
        assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(a)), np.max(np.abs(a - b))
        differs = differs or not np.array_equal(a, b)
    assert differs  # the cheaper form runs, not the general one folded


def test_the_serial_plant_takes_the_folded_form():
    """The ideal serial arms' plant period integrates the folded forward dynamics: it has fewer
    operations than the articulated-body algorithm folded (520 against 652 measured), so
    specialised_plant chooses it; the geared plant keeps its general kernel."""
    sc = eb.sim_scenario("serial_joint")
    u = unit_setups(sc)[0]
    general = u.plant_function(sc.plant_substeps)
    constants = [ca.DM(np.ravel(c)) for c in (u.plant_params, u.friction, sc.period)]
    x, tau = ca.SX.sym("x", 2 * u.plant_model.nq), ca.SX.sym("tau", u.plant_model.nq)
    folded_general = ca.Function("g", [x, tau], [general(x, tau, *constants)])
    special = eb.specialised_plant(u, sc.plant_substeps, sc.period, "sim_unit_plant")
    assert special.n_instructions() < 0.9 * folded_general.n_instructions()


@pytest.mark.slow
def test_the_geared_plant_stays_general():
    """The geared plant (realistic preset) runs its generated_c/ kernel: folding its constants
    moved results by an ulp, which backlash and stiction grew to 1e-2 rad over a study. Its
    study keeps libm (SIM_INLINE_TRIG 0), as the parallel mechanism does; the ideal serial
    studies take every sin and cos of their plants and logged poses from sim_sincos, paired
    (one call for a sin and a cos of one angle: 4 RK4 stages x 2 angles an arm, and 3 angles
    a pose), so they link no general kernel."""
    header, plant_c, groups = eb.sim_scenario_header("serial_joint_realistic")
    assert "serial_arm1_gear_plant_step, serial_arm1_fk_world" in header
    assert "sim_arm1_plant" not in plant_c and "serial_arm1" in groups
    assert "#define SIM_INLINE_TRIG 0" in header
    header, plant_c, groups = eb.sim_scenario_header("serial_task")
    assert "sim_arm1_plant, sim_arm1_pose" in header and groups == []
    assert "int sim_arm1_plant(" in plant_c and "int sim_arm2_pose(" in plant_c
    assert "#define SIM_INLINE_TRIG 1" in header
    # an arm: the plain period's 4 stages x 2 angles, the stage period's first stage (its
    # later stages shift those: cochlea/robots/stage_trig.py), the pose's 3 angles
    assert plant_c.count("sim_sincos(") == 2 * (8 + 2 + 3)
    assert "sin(" not in plant_c.replace("sim_sin(", "")
    header, plant_c, _ = eb.sim_scenario_header("parallel_joint")
    assert "#define SIM_INLINE_TRIG 0" in header and "sim_sincos" not in plant_c


def test_inline_trig_pairs_a_sin_and_a_cos_of_one_value():
    """A sin and a cos of a variable between two of its assignments share one sim_sincos; of
    another value of it, or alone, each gets its own."""
    text = "\n".join(["static int f(void) {", "  a1=sin(a0);", "  a2=cos(a0);",
                      "  a0=(a1+a2);", "  a3=cos(a0);", "  a0=sin(a0);", "  a4=sin(a5);",
                      "}"])
    out = eb.inline_trig(text).split("\n")
    assert out[1] == "  casadi_real sim_s0, sim_c0; sim_sincos(a0, &sim_s0, &sim_c0); a1=sim_s0;"
    assert out[2] == "  a2=sim_c0;" and out[3] == "  a0=(a1+a2);"
    assert out[4] == "  casadi_real sim_s1, sim_c1; sim_sincos(a0, &sim_s1, &sim_c1); a3=sim_c1;"
    assert out[5] == "  a0=sim_s1;" and out[6] == "  a4=sim_sin(a5);"
    with pytest.raises(RuntimeError):
        eb.inline_trig("static int f(void) {\n  a1=sin((a0+a2));\n}")


def test_shared_reciprocals_divide_once_per_value():
    """Several divisions by one value of a variable: one reciprocal at the first, then
    multiplications; a lone division, or one by another value of it, stays a division."""
    text = "\n".join(["static int f(void) {", "  a1=(a2/a0);", "  a3=(a4/a0);", "  a5=(a6/a7);",
                      "  a0=(a1+a3);", "  a8=(a1/a0);", "}", "static int g(void) {",
                      "  a1=(a2/a0);", "}"])
    out = eb.shared_reciprocals(text).split("\n")
    assert out[1] == "  casadi_real sim_r0 = 1. / a0; a1=(a2*sim_r0);"
    assert out[2] == "  a3=(a4*sim_r0);" and out[3] == "  a5=(a6/a7);"
    assert out[5] == "  a8=(a1/a0);" and out[8] == "  a1=(a2/a0);"


@pytest.mark.slow
def test_full_length_without_a_log():
    """The scenario's own duration by default; without a log nothing is written."""
    sc = load_scenario("serial_task")
    info = eb.run_simulation(eb.build_simulation("serial_task"))
    assert info["status"] == "completed" and info["log"] is False
    assert info["rows"] == info["periods"] == round(sc.duration / sc.period)
    assert info["duration_s"] == sc.duration and info["period_s"] == sc.period
    assert 0 < info["loop_s"] <= info["main_s"]
    assert 0 < info["loop_cpu_s"] <= info["loop_s"] + 1e-3  # each thread: CPU <= wall


@pytest.mark.slow
def test_needs_neither_python_nor_casadi():
    """The program links the C library (its threads: the log's writer) and libm only,
    statically where the C library allows, so that nothing is loaded at start-up."""
    binary = eb.build_simulation("parallel_task_realistic")
    dynamic = subprocess.run(["readelf", "-d", str(binary)], capture_output=True, text=True,
                             check=True).stdout
    needed = {line.split("[")[1].split("]")[0] for line in dynamic.splitlines()
              if "(NEEDED)" in line}
    assert needed <= {"libm.so.6", "libc.so.6", "libpthread.so.0"}, needed


@pytest.mark.parametrize("args", [["--duration", "-1"], ["--duration", "2s"], ["--rate", "1"],
                                  ["--log"], ["--log", "/nonexistent/folder/log.bin"],
                                  ["--log", "/"],  # a folder: refused, never removed
                                  pytest.param(["--log", "/dev/full"], marks=pytest.mark.skipif(
                                      not Path("/dev/full").exists(), reason="no /dev/full"))])
def test_refuses_bad_arguments(args):
    """One line on stderr, exit 2, no summary: also when the log's writer thread finds the
    disk full."""
    done = subprocess.run([str(eb.build_simulation("serial_joint")), *args],
                          capture_output=True, text=True)
    assert done.returncode == 2 and done.stderr and not done.stdout


def test_an_existing_log_is_replaced_by_a_new_file(tmp_path):
    """--log over a previous log removes it and writes a new file instead of truncating it
    (4-5 ms less on ext4): a reader holding the old file still reads all of it, and the path
    has the new run's log. A symbolic link is not removed (its target gets the log, the link
    stays), nor a file with another name (both names see the new log)."""
    binary = eb.build_simulation("serial_joint")
    log = tmp_path / "run.log"
    first = eb.run_simulation(binary, 0.05, log)
    old = log.read_bytes()
    assert len(old) == first["rows"] * 8 * first["columns"] > 0
    with open(log, "rb") as held:
        info = eb.run_simulation(binary, 0.02, log)
        assert held.read() == old  # removed, not truncated under the reader
    assert log.stat().st_size == info["rows"] * 8 * info["columns"] < len(old)
    assert log.read_bytes() == old[:log.stat().st_size]

    target, link = tmp_path / "target.log", tmp_path / "link.log"
    target.write_bytes(b"x" * 100000)
    link.symlink_to(target)
    eb.run_simulation(binary, 0.02, link)
    assert link.is_symlink() and target.read_bytes() == log.read_bytes()

    other = tmp_path / "other.log"
    os.link(target, other)
    eb.run_simulation(binary, 0.01, other)
    assert target.stat().st_ino == other.stat().st_ino
    assert target.read_bytes() == other.read_bytes() == old[:len(other.read_bytes())]
    assert len(other.read_bytes()) == 10 * 8 * info["columns"]


def test_zero_duration_runs_no_period(tmp_path):
    log = tmp_path / "empty.log"
    info = eb.run_simulation(eb.build_simulation("serial_joint"), 0.0, log)
    assert info["status"] == "completed" and info["rows"] == 0 and log.stat().st_size == 0
    assert json.loads(json.dumps(info)) == info


def test_a_duration_of_a_half_period_more_rounds_as_the_simulation_does():
    """--duration rounds to whole periods as simulate() does, halves to even: 2.5 periods
    (0.0025 s at 1 kHz) run 2, 3.5 run 4 (C's lround ran 3 and 4: a row more than the
    simulation's log at every even whole)."""
    binary = eb.build_simulation("serial_joint")
    sc = load_scenario("serial_joint")
    for duration in (0.0025, 0.0035, 0.0045000000000000005, 0.0019, 0.0021):
        info = eb.run_simulation(binary, duration)
        assert info["rows"] == len(simulate(sc, duration=duration).time), duration


def _disturbed(name, **changes):
    import dataclasses

    sc = load_scenario(name)
    return dataclasses.replace(sc, plant=dataclasses.replace(sc.plant, **changes))


@pytest.mark.parametrize("name", ["serial_joint_realistic", "parallel_task_realistic"])
@pytest.mark.slow
def test_issue_24s_disturbances_run_in_c(name, tmp_path, monkeypatch):
    """[plant] delay_jitter_periods, encoder_noise_counts and torque_constant_error in the
    all-C simulation, issue 24's values: the jitter and the counts drawn from the seed's
    streams as numpy draws them (PCG64 in C), the plant given 1 + e times the applied effort;
    the log equals simulate()'s (a build of its own, outside build/embedded-sim)."""
    import numpy as np

    nq = 3 if name.startswith("serial") else 5
    sc = _disturbed(name, delay_jitter_periods=2, encoder_noise_counts=1, seed=7,
                    torque_constant_error=np.linspace(-0.05, 0.05, nq))
    monkeypatch.setattr(eb, "sim_scenario", lambda _: sc)
    monkeypatch.setattr(eb, "BUILD", tmp_path / "build")
    result, info, _, setups = run_logged(name, "double", tmp_path, 0.5)
    assert setups[0].torque_scale is not None and info["rows"] == 500
    reference = simulate(sc, duration=0.5, setups=setups)
    worst = worst_relative(result, reference)
    assert max(worst.values()) <= TOLERANCE, worst
    nominal = simulate(load_scenario(name), duration=0.5)
    assert np.abs(result.units[0].true_q - nominal.units[0].true_q).max() > 1e-9
    u = reference.units[0]
    assert not np.array_equal(u.q, u.true_q)


def test_each_arm_runs_on_a_thread_of_its_own():
    """The serial studies' two arms run on two threads (each its own plant, controller state
    and history, for the whole run); the parallel mechanism, one unit, on one. The summary
    gives each unit thread's CPU time, and loop_cpu_s is the busiest one's."""
    serial = eb.run_simulation(eb.build_simulation("serial_joint"), 0.2)
    assert serial["threads"] == 2 and len(serial["unit_cpu_s"]) == 2
    assert serial["loop_cpu_s"] == max(serial["unit_cpu_s"]) > 0
    parallel = eb.run_simulation(eb.build_simulation("parallel_joint"), 0.05)
    assert parallel["threads"] == 1 and parallel["unit_cpu_s"] == [parallel["loop_cpu_s"]]


def test_each_arm_has_a_processor_of_its_own_when_there_are_enough(tmp_path):
    """Without a log the two arms' threads are the only busy ones: each is held on a
    processor of its own (left to the scheduler, the second started on the first's processor
    and the two shared it for much of a short run). With the log's writer too there are more
    busy threads than this machine's processors and the scheduler places them; either way
    each arm's log is the same, bit for bit."""
    binary = eb.build_simulation("serial_joint")
    cpus = os.sched_getaffinity(0)
    alone = eb.run_simulation(binary, 0.2)
    assert len(alone["unit_processors"]) == 2
    assert set(alone["unit_processors"]) <= cpus
    if len(cpus) >= 2:
        assert alone["unit_processors"][0] != alone["unit_processors"][1]
    # A process held to one processor runs both arms there (nothing placed, nothing refused).
    one = min(cpus)
    def hold():
        os.sched_setaffinity(0, {one})

    held = subprocess.run([str(binary), "--duration", "0.2"], preexec_fn=hold,
                          capture_output=True, text=True, check=True)
    assert json.loads(held.stdout)["unit_processors"] == [one, one]
    first, second = tmp_path / "a.bin", tmp_path / "b.bin"
    eb.run_simulation(binary, 0.2, first)
    subprocess.run([str(binary), "--duration", "0.2", "--log", str(second)], preexec_fn=hold,
                   capture_output=True, text=True, check=True)
    assert first.read_bytes() == second.read_bytes()


@pytest.mark.slow  # runs the program and a busy loop turn about
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU")
def test_the_sibling_slowdown_is_measured_turn_about_and_leaves_no_busy_loop():
    """bench's measure of how much a thread slows beside a busy vCPU: the program's loop CPU
    time alone and beside the busy loop, pinned to two different CPUs, their ratio; the busy
    loop is ended (no child of this process left that was not there before: earlier tests of
    the session may have left a child that outlives them, multiprocessing's resource tracker
    for one)."""
    children = Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children")
    before = set(children.read_text().split()) if children.exists() else set()
    row = eb.sibling_slowdown(rounds=2, runs=1)
    assert row["runs"] == 2 and row["cpus"][0] != row["cpus"][1]
    assert row["alone_cpu_s"] > 0 and row["busy_cpu_s"] > 0
    assert row["ratio"] == row["busy_cpu_s"] / row["alone_cpu_s"]
    if eb._idle_us(row["cpus"][1]) is not None:  # the kernel says how idle it was
        assert 0.0 <= row["other_idle_busy"] <= 0.5  # the busy loop kept it busy
    if children.exists():
        assert set(children.read_text().split()) <= before


@pytest.mark.parametrize("scale, first, status", [(0.01, "arm2", "diverged"),
                                                  (0.05, "arm1", "step-failed")])
@pytest.mark.slow
def test_the_run_ends_where_the_first_arm_stops(scale, first, status, tmp_path, monkeypatch):
    """Link 3 made light (mass_scale) drives both arms of serial_joint unstable, one before
    the other. Each arm's thread stops where its arm does; the run and its log end at the first
    stop, as one loop over the arms ends them (measured: the same rows, status and log bytes
    as the program before the threads) and as simulate() ends every unit's log: arm 2 first
    (the thread beside the main one; its state diverges), then arm 1 first (the main thread's;
    its step refuses non-finite commands first, so the log keeps the periods before that one,
    which simulate() logs as well)."""
    import dataclasses

    from cochlea.sim.result import truncate

    sc = load_scenario("serial_joint")
    sc = dataclasses.replace(sc, plant=dataclasses.replace(
        sc.plant, mass_scale=np.array([1.0, 1.0, scale])))
    monkeypatch.setattr(eb, "sim_scenario", lambda _: sc)
    monkeypatch.setattr(eb, "BUILD", tmp_path / "build")
    # libm's sin and cos: near the blow-up an ulp can move the stop by a period; so the
    # reference is CasADi's (libm), not the C kernels' (their ideal plant steps take sin and
    # cos inline: docs/codegen.md)
    monkeypatch.setattr(eb, "INLINE_TRIG_ROBOTS", ())
    # and the plant's general form folded (the folded sums round differently: near the blow-up
    # arm 2 then stopped on its step, not its state)
    monkeypatch.setattr(eb, "folded_forward_dynamics", lambda model, p: None)
    # and the plain RK4 stages, compiled for any x86-64 (no fused multiply-adds)
    monkeypatch.setattr(eb, "STAGE_TRIG", False)
    monkeypatch.setenv("COCHLEA_SIM_HOST_ISA", "0")
    result, info, _, setups = run_logged("serial_joint", "double", tmp_path, 2.0)
    reference = simulate(sc, duration=2.0, setups=setups, kernels="casadi")
    assert min(reference.diverged, key=reference.diverged.get) == first
    assert info["status"] == status and info["threads"] == 2
    rows = len(reference.time) - (status == "step-failed")
    assert info["rows"] == rows < 2000
    truncate(reference.units, rows)
    reference.time = reference.time[:rows]
    worst = worst_relative(result, reference)
    assert max(worst.values()) <= TOLERANCE, worst


def _c_library(tmp_path: Path, name: str, source: str) -> Path:
    """``source`` compiled as the simulation compiles its plant (eb.CFLAGS, embedded/sim on
    the include path) into a shared library."""
    c = tmp_path / f"{name}.c"
    c.write_text(source)
    lib = tmp_path / f"lib{name}.so"
    subprocess.run([os.environ.get("CC", "cc"), *eb.CFLAGS, "-fPIC", "-shared",
                    f"-I{eb.SIM_SOURCE}", str(c), "-o", str(lib), "-lm"], check=True)
    return lib


def _reference_sincos(x: float) -> tuple:
    """sin x and cos x to 50 digits (Decimal: x reduced by a 90-digit pi, Taylor series)."""
    from decimal import Decimal, localcontext

    with localcontext() as ctx:
        ctx.prec = 60
        pi = Decimal("3.14159265358979323846264338327950288419716939937510582097494459230781"
                     "64062862089986280348")
        X = Decimal(x)
        k = int((X / (pi / 2)).to_integral_value())
        r = X - k * (pi / 2)
        r2, sin_r, cos_r, term = r * r, r, Decimal(1), r
        for n in range(1, 40):
            term = -term * r2 / ((2 * n) * (2 * n + 1))
            sin_r += term
        term = Decimal(1)
        for n in range(1, 40):
            term = -term * r2 / ((2 * n - 1) * (2 * n))
            cos_r += term
        return [(sin_r, cos_r), (cos_r, -sin_r), (-sin_r, -cos_r), (-cos_r, sin_r)][k % 4]


def test_sim_sincos_is_within_an_ulp(tmp_path):
    """embedded/sim/sim_trig.h's sin and cos (the serial studies' plants and controllers): at
    most 1 ulp from the exact value (a 50-digit reference) on angles over the studies' range
    and beyond, next to multiples of pi/2 (where the reduction cancels most), tiny ones; at
    most 1 ulp from libm's on 10^5 more; libm's own values outside |x| < 2^19, NaN for NaN
    and infinities."""
    import ctypes
    import math
    from decimal import Decimal

    lib = ctypes.CDLL(str(_c_library(tmp_path, "trig", "\n".join([
        '#include "sim_trig.h"',
        "void trig(const double *x, double *s, double *c, long n) {",
        "  long i;",
        "  for (i = 0; i < n; ++i) sim_sincos(x[i], s + i, c + i);",
        "}"]))))

    def ours(x):
        x = np.ascontiguousarray(x, dtype=np.float64)
        s, c = np.empty_like(x), np.empty_like(x)
        p = ctypes.POINTER(ctypes.c_double)
        lib.trig(x.ctypes.data_as(p), s.ctypes.data_as(p), c.ctypes.data_as(p),
                 ctypes.c_long(len(x)))
        return s, c

    rng = np.random.default_rng(30)
    near = [v for k in range(-12, 13) if k for v in
            (k * math.pi / 2, np.nextafter(k * math.pi / 2, 0), np.nextafter(k * math.pi / 2, 9))]
    xs = np.concatenate([rng.uniform(-7.0, 7.0, 400), rng.uniform(-2e3, 2e3, 40), near,
                         [0.0, -0.0, 1e-300, -3e-9, 0.785398, 2.35619, 4e5, -5.2e5]])
    s, c = ours(xs)
    for x, a, b in zip(xs, s, c):
        exact_s, exact_c = _reference_sincos(float(x))
        for got, exact in ((a, exact_s), (b, exact_c)):
            assert abs(Decimal(float(got)) - exact) <= Decimal(math.ulp(float(exact))), x
    x = rng.uniform(-10.0, 10.0, 100000)
    s, c = ours(x)
    assert np.all(np.abs(s - np.sin(x)) <= np.spacing(np.abs(np.sin(x))))
    assert np.all(np.abs(c - np.cos(x)) <= np.spacing(np.abs(np.cos(x))))
    assert np.mean(s != np.sin(x)) < 0.1  # mostly libm's own (which is correctly rounded)
    far = np.array([2.0 ** 19, -1e6, 1e300])
    s, c = ours(far)
    assert np.array_equal(s, np.sin(far)) and np.array_equal(c, np.cos(far))
    s, c = ours(np.array([np.nan, np.inf, -np.inf]))
    assert np.all(np.isnan(s)) and np.all(np.isnan(c))


def test_the_serial_plant_in_c_is_the_general_one_within_rounding(tmp_path):
    """sim_plant.c of serial_joint as the program compiles it (sin and cos from sim_sincos,
    the articulated inertia's three divisions a stage as one reciprocal): each arm's period
    from states and efforts away from the start equals the general Function's (CasADi, libm,
    divisions) within 1e-14 of max(1, |value|)."""
    import ctypes

    _, plant_c, _ = eb.sim_scenario_header("serial_joint")
    assert "sim_sincos(" in plant_c and "= 1. / a" in plant_c
    lib = ctypes.CDLL(str(_c_library(tmp_path, "plant", plant_c)))
    sc = eb.sim_scenario("serial_joint")
    rng = np.random.default_rng(4)
    worst = 0.0
    for u in unit_setups(sc):
        f = getattr(lib, f"sim_{u.name}_plant")
        general = u.plant_function(sc.plant_substeps)
        for _ in range(20):
            x = np.asarray(u.plant_x0) + rng.normal(0.0, 0.5, len(u.plant_x0))
            tau = rng.normal(0.0, 1.0, u.plant_model.nq)
            out = np.zeros(len(x))
            args = (ctypes.POINTER(ctypes.c_double) * 2)(
                np.ctypeslib.as_ctypes(x), np.ctypeslib.as_ctypes(tau))
            res = (ctypes.POINTER(ctypes.c_double) * 1)(np.ctypeslib.as_ctypes(out))
            assert f(args, res, None, None, 0) == 0
            expected = np.asarray(general(x, tau, u.plant_params, u.friction,
                                          sc.period)).ravel()
            worst = max(worst, float(np.max(np.abs(out - expected)
                                            / np.maximum(1.0, np.abs(expected)))))
    assert worst <= 1e-14, worst


def test_the_plant_takes_the_plain_period_past_the_shifts_reach(tmp_path):
    """sim_plant.c of parallel_task: the unit's plant (``sim_mechanism_plant``) is its stage
    period's result bit for bit where every RK4 offset is within reach (and that differs from
    the plain period's somewhere: the shifted sines run), and the plain period's bit for bit at
    a joint speed past reach (400 rad/s: 0.2 rad an RK4 stage), where the series are not exact
    enough; the input state is left as it was."""
    import ctypes

    _, plant_c, _ = eb.sim_scenario_header("parallel_task")
    lib = ctypes.CDLL(str(_c_library(tmp_path, "plant", plant_c)))
    sc = eb.sim_scenario("parallel_task")
    u = unit_setups(sc)[0]
    n = u.plant_model.nq
    rng = np.random.default_rng(8)

    def call(name, x, tau):
        x = np.array(x, float)
        before = x.copy()
        out, far = np.zeros(len(x)), np.zeros(1)
        args = (ctypes.POINTER(ctypes.c_double) * 2)(
            np.ctypeslib.as_ctypes(x), np.ctypeslib.as_ctypes(tau))
        res = (ctypes.POINTER(ctypes.c_double) * 2)(np.ctypeslib.as_ctypes(out),
                                                    np.ctypeslib.as_ctypes(far))
        assert getattr(lib, name)(args, res, None, None, 0) == 0
        np.testing.assert_array_equal(x, before)
        return out, far[0]

    differs = False
    for _ in range(20):
        x = np.asarray(u.plant_x0) + rng.normal(0.0, 0.3, len(u.plant_x0))
        tau = rng.normal(0.0, 1.0, n)
        got, _ = call("sim_mechanism_plant", x, tau)
        stages, far = call("sim_mechanism_plant_stages", x, tau)
        plain, _ = call("sim_mechanism_plant_plain", x, tau)
        assert far == 0.0
        np.testing.assert_array_equal(got, stages)
        differs = differs or not np.array_equal(got, plain)
    assert differs
    x = np.asarray(u.plant_x0, float).copy()
    x[n] = 400.0  # rad/s at motor 1
    tau = np.zeros(n)
    _, far = call("sim_mechanism_plant_stages", x, tau)
    assert far >= 1.0
    np.testing.assert_array_equal(call("sim_mechanism_plant", x, tau)[0],
                                  call("sim_mechanism_plant_plain", x, tau)[0])


def test_the_host_isa_flags_go_to_studies_that_may_move_by_rounding(monkeypatch, capsys):
    """x86-64 v3 code with fused multiply-adds (HOST_ISA_FLAGS) for the ideal studies where the
    building machine has the level, never for a realistic study (geared plant, grids: bit for
    bit), and not with COCHLEA_SIM_HOST_ISA=0; another value of it is refused by name."""
    monkeypatch.setattr(eb, "_host_has_v3", lambda cc: True)
    ideal = eb.sim_scenario("parallel_task")
    realistic = eb.sim_scenario("serial_task_realistic")
    assert eb.host_isa_flags(ideal, unit_setups(ideal)) == eb.HOST_ISA_FLAGS
    assert eb.host_isa_flags(realistic, unit_setups(realistic)) == ()
    monkeypatch.setenv("COCHLEA_SIM_HOST_ISA", "0")
    assert eb.host_isa_flags(ideal, unit_setups(ideal)) == ()
    for bad in ("no", "", "01", "true"):
        monkeypatch.setenv("COCHLEA_SIM_HOST_ISA", bad)
        with pytest.raises(ValueError, match="COCHLEA_SIM_HOST_ISA"):
            eb.host_isa_flags(ideal, unit_setups(ideal))
    assert eb.main(["build", "parallel_task"]) == 2  # the command: one line, no traceback
    assert "COCHLEA_SIM_HOST_ISA is 'true'" in capsys.readouterr().err
    monkeypatch.delenv("COCHLEA_SIM_HOST_ISA")
    monkeypatch.setattr(eb, "_host_has_v3", lambda cc: False)
    assert eb.host_isa_flags(ideal, unit_setups(ideal)) == ()


# realtime: the healthy arm's CPU time depends on when the diverging arm's thread runs; with
# other tests beside it on both cores (make test's first pass) it ran 11 blocks, not 1.
@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.parametrize("unit", [0, 1])
def test_the_other_arm_is_cut_where_one_diverges_at_once(unit, tmp_path, monkeypatch):
    """One arm made unstable (negative viscous friction) diverges within a few periods while
    the other would run the whole 20 s: the log ends where simulate() ends it, and the healthy
    arm's thread stops at its first block (the writer has ended) instead of running on (20 s
    take it about 10 ms of CPU; a block of 596 rows, 0.3 ms) -- whether the unstable arm is on
    the main thread (0) or beside it (1)."""
    import dataclasses

    sc = load_scenario("serial_joint")
    setups = unit_setups(sc)
    setups[unit] = dataclasses.replace(setups[unit], friction=np.full(3, -0.05))
    monkeypatch.setattr(eb, "unit_setups", lambda _: setups)
    monkeypatch.setattr(eb, "BUILD", tmp_path / "build")
    monkeypatch.setattr(eb, "INLINE_TRIG_ROBOTS", ())
    # the general plant folded: a state growing without bound grows the folded sums' rounding
    # differences with it (the rows compared here are simulate()'s kernels' to the last bit)
    monkeypatch.setattr(eb, "folded_forward_dynamics", lambda model, p: None)
    monkeypatch.setattr(eb, "STAGE_TRIG", False)  # and plain RK4 stages, no fused operations
    monkeypatch.setenv("COCHLEA_SIM_HOST_ISA", "0")
    log = tmp_path / "log.bin"
    info = eb.run_simulation(eb.build_simulation("serial_joint"), 20.0, log)
    result = eb.read_log(log, info, sc, setups)
    reference = simulate(sc, duration=20.0, setups=setups)
    assert list(reference.diverged) == [setups[unit].name]
    assert info["status"] == "diverged" and info["rows"] == len(reference.time) < 10
    worst = worst_relative(result, reference)
    assert max(worst.values()) <= TOLERANCE, worst
    assert info["unit_cpu_s"][1 - unit] < 3e-3, info["unit_cpu_s"]
    # the 8.8 MB the writer reserved for 20 s given back: the file holds its rows' blocks only
    assert log.stat().st_blocks * 512 <= log.stat().st_size + (1 << 16)
