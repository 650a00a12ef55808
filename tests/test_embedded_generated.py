"""The per-scenario embedded controllers (generated_c/embedded/, docs/embedded.md): fresh, clean
C99 in both precisions with only libm to link, the desired trajectory equal to CasADi's, the
controller equal to the simulation's, and the float build close to the double one."""

from __future__ import annotations

import ctypes
import filecmp
import re
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from cochlea.apps.cochlea_codegen import write_embedded_folder
from cochlea.kernels.catalogue import load_config
from cochlea.kernels.embedded import MATH_FUNCTIONS
from cochlea.robots.plant import plant_step
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.setup import MeasurementGrid

ROOT = Path(__file__).resolve().parent.parent
EMBEDDED = ROOT / "generated_c" / "embedded"
CONFIG = load_config()
SCENARIOS = CONFIG.embedded.scenarios
THESIS = ("serial_joint", "serial_task", "parallel_joint", "parallel_task")
CC = shutil.which("gcc") or shutil.which("cc")
STRICT = ["-std=c99", "-pedantic", "-ffreestanding", "-fno-builtin", "-Wall", "-Wextra",
          "-Werror"]
FLOAT = ["-DCOCHLEA_FLOAT", "-Wdouble-promotion", "-Wfloat-conversion"]
LIBM = set(MATH_FUNCTIONS) | {f + "f" for f in MATH_FUNCTIONS}

needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler")


def test_every_shipped_scenario_is_listed():
    shipped = {p.stem for p in (ROOT / "models" / "scenarios").glob("*.toml")}
    assert set(SCENARIOS) == shipped


@pytest.mark.slow
def test_embedded_folder_is_fresh(tmp_path):
    """Regenerating gives generated_c/embedded/ byte for byte (run cochlea-codegen if not)."""
    write_embedded_folder(CONFIG, tmp_path)  # what cochlea-codegen writes there
    fresh = sorted(p.name for p in tmp_path.iterdir())
    assert fresh == sorted(p.name for p in EMBEDDED.iterdir()), "run cochlea-codegen"
    stale = [n for n in fresh if not filecmp.cmp(tmp_path / n, EMBEDDED / n, shallow=False)]
    assert not stale, f"generated_c/embedded/ is stale ({', '.join(stale)}): run cochlea-codegen"
    for name in fresh:
        text = (tmp_path / name).read_text()
        assert str(ROOT) not in text and not re.search(r"\b20\d\d-\d\d-\d\d\b", text)
        assert "malloc" not in text and "stdio" not in text


def test_make_lib_sources_exclude_the_subfolder():
    """``make lib`` compiles generated_c/*.c only: the embedded controllers are not in it."""
    makefile = (ROOT / "Makefile").read_text()
    assert "$(wildcard $(GEN)/*.c)" in makefile


# --------------------------------------------------------------------------------------------
# Compilation
# --------------------------------------------------------------------------------------------


def _undefined(obj: Path) -> set[str]:
    out = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True, check=True)
    return {line.split()[-1] for line in out.stdout.splitlines() if line.strip()}


@needs_cc
@pytest.mark.parametrize("precision", ["double", "float"])
@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.slow
def test_compiles_freestanding_and_links_only_libm(name, precision, tmp_path):
    flags = STRICT + (FLOAT if precision == "float" else [])
    source = EMBEDDED / f"{name}.c"
    for opt in ("-O0", "-O2"):
        obj = tmp_path / f"{name}{opt}.o"
        run = subprocess.run([CC, opt, *flags, "-c", str(source), "-o", str(obj)],
                             capture_output=True, text=True)
        assert run.returncode == 0 and not run.stderr, run.stderr[:3000]
        undefined = _undefined(obj)
        assert undefined <= LIBM, undefined - LIBM
        if precision == "float":  # the working precision's family, besides p_hat's update
            assert {"sinf", "cosf"} & undefined or not {"sin", "cos"} & undefined


# --------------------------------------------------------------------------------------------
# A shared library per scenario and precision, through a tiny shim
# --------------------------------------------------------------------------------------------

_SHIM = """#include "{name}.h"
static {name}_state state;
static {name}_config config;
int shim_sizes(int *out) {{
  out[0] = {N}_UNITS; out[1] = {N}_NQ; out[2] = {N}_NX; out[3] = {N}_ND;
  out[4] = {N}_NP; out[5] = {N}_NG; out[6] = {N}_NE; return (int)sizeof({name}_real);
}}
int shim_init(void) {{ {name}_default_config(&config); return {name}_init(&state, &config); }}
int shim_step(double t, const {name}_real *m, {name}_real *cmd, {name}_real *err) {{
  return {name}_step(&state, t, m, cmd, err);
}}
void shim_p_hat(double *out) {{ int i; for (i = 0; i < {N}_NP; ++i) out[i] = state.p_hat[i]; }}
void shim_config(double *gains, double *gamma, double *bound, double *p_hat0, double *limit,
                 double *h) {{
  int i;
  for (i = 0; i < {N}_NG; ++i) gains[i] = config.gains[i];
  for (i = 0; i < {N}_NP; ++i) {{ gamma[i] = config.gamma[i]; p_hat0[i] = config.p_hat0[i]; }}
  for (i = 0; i < {N}_UNITS; ++i) bound[i] = config.bound[i];
  for (i = 0; i < {N}_NQ; ++i) limit[i] = config.effort_limit[i];
  *h = config.h;
}}
void shim_terminate(void) {{ {name}_terminate(&state); }}
int shim_desired(double t, {name}_real *xd, {name}_real *xd_dot, {name}_real *xd_ddot) {{
  return {name}_desired(t, xd, xd_dot, xd_ddot);
}}
int shim_tool_points(const {name}_real *q, {name}_real *points, {name}_real *centres) {{
  return {name}_tool_points(q, points, centres);
}}
int shim_n_points(void) {{ return {N}_NPOINTS; }}
"""

_P = ctypes.c_void_p


class Embedded:
    """One scenario's generated controller, built as a shared library and called via ctypes."""

    def __init__(self, name: str, path: Path):
        self.name = name
        self.lib = lib = ctypes.CDLL(str(path))
        sizes = np.zeros(7, np.intc)
        real_size = lib.shim_sizes(sizes.ctypes.data_as(_P))
        self.real = np.float32 if real_size == 4 else np.float64
        (self.units, self.nq, self.nx, self.nd, self.np, self.ng, self.ne) = map(int, sizes)
        lib.shim_step.argtypes = [ctypes.c_double, _P, _P, _P]
        lib.shim_desired.argtypes = [ctypes.c_double, _P, _P, _P]
        self.measurement = np.zeros(self.nx, self.real)
        self.command = np.zeros(self.nq, self.real)
        self.errors = np.zeros(self.ne, self.real)
        self.p = np.zeros(self.np)
        self._args = [a.ctypes.data_as(_P) for a in (self.measurement, self.command, self.errors)]

    def init(self) -> int:
        return self.lib.shim_init()

    def step(self, t: float, measurement) -> int:
        self.measurement[:] = measurement
        return self.lib.shim_step(t, *self._args)

    def p_hat(self) -> np.ndarray:
        self.lib.shim_p_hat(self.p.ctypes.data_as(_P))
        return self.p.copy()

    def config(self) -> dict[str, np.ndarray]:
        out = {"gains": np.zeros(self.ng), "gamma": np.zeros(self.np),
               "bound": np.zeros(self.units), "p_hat0": np.zeros(self.np),
               "effort_limit": np.zeros(self.nq), "h": np.zeros(1)}
        self.lib.shim_config(*(v.ctypes.data_as(_P) for v in out.values()))
        return out

    def desired(self, t: float) -> tuple[np.ndarray, ...]:
        out = [np.zeros(self.nd, self.real) for _ in range(3)]
        assert self.lib.shim_desired(t, *(o.ctypes.data_as(_P) for o in out)) == 0
        return tuple(out)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """``(scenario, precision) -> path`` of the shared libraries (built on demand, in parallel
    the first time)."""
    if CC is None:
        pytest.skip("no C compiler")
    folder = tmp_path_factory.mktemp("embedded")

    def build(key):
        name, precision = key
        shim = folder / f"shim_{name}_{precision}.c"
        shim.write_text(_SHIM.format(name=name, N=name.upper()))
        lib = folder / f"lib{name}_{precision}.so"
        extra = ["-DCOCHLEA_FLOAT"] if precision == "float" else []
        subprocess.run([CC, "-O1", "-fPIC", "-shared", "-std=c99", *extra, "-I", str(EMBEDDED),
                        str(shim), str(EMBEDDED / f"{name}.c"), "-o", str(lib), "-lm"],
                       check=True, capture_output=True)
        return key, lib

    keys = [(n, "double") for n in SCENARIOS] + [(n, "float") for n in THESIS]
    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(pool.map(build, keys))


def _measurement(xs: list[np.ndarray]) -> np.ndarray:
    """The layout of the generated step: unit after unit, [q, qd] each (xs: each unit's x)."""
    return np.concatenate(xs)


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.slow
def test_default_config_is_the_scenarios(built, name):
    c = Embedded(name, built[name, "double"])
    sc = load_scenario(name)
    setups = unit_setups(sc)
    assert c.init() == 0
    got = c.config()
    assert c.units == len(setups)
    assert c.nq == sum(u.controller_model.nq for u in setups) and c.nx == 2 * c.nq
    np.testing.assert_array_equal(got["gains"], np.concatenate([u.gains for u in setups]))
    np.testing.assert_array_equal(got["gamma"], np.concatenate([u.gamma for u in setups]))
    np.testing.assert_array_equal(got["p_hat0"], np.concatenate([u.p_hat0 for u in setups]))
    np.testing.assert_array_equal(got["bound"], [u.bound for u in setups])
    np.testing.assert_array_equal(got["effort_limit"],
                                  np.concatenate([u.effort_limit for u in setups]))
    assert got["h"][0] == sc.period
    np.testing.assert_array_equal(c.p_hat(), got["p_hat0"])
    c.lib.shim_terminate()
    assert c.step(0.0, np.zeros(c.nx)) == -1  # not initialised


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.slow
def test_desired_trajectory_equals_casadi(built, name):
    c = Embedded(name, built[name, "double"])
    sc = load_scenario(name)
    setups = unit_setups(sc)
    times = np.linspace(0.0, sc.duration, 1000)
    dense = []
    for u in setups:
        t = ca.SX.sym("t")
        dense.append(ca.Function("d", [t], [ca.densify(v) for v in u.desired(t)]))
    worst = 0.0
    for t in times:
        got = c.desired(float(t))
        want = [np.concatenate([np.array(f(t)[i]).ravel() for f in dense]) for i in range(3)]
        for g, w in zip(got, want):
            worst = max(worst, float(np.max(np.abs(g - w) / np.maximum(1.0, np.abs(w)))))
    assert worst <= 1e-12, worst


@pytest.mark.parametrize("name", SCENARIOS)
def test_tool_points_and_centres_are_the_supervisors(built, name):
    """``<name>_tool_points``, which the embedded supervisor's keep-out check reads: each unit's
    tool points from its world pose and each point's circle centre by the robot's rule
    (:meth:`cochlea.sim.setup.UnitSetup.keep_out_centre`: the parallel mechanism's centre rides
    on its slider), at random joint positions."""
    lib = ctypes.CDLL(str(built[name, "double"]))
    setups = unit_setups(load_scenario(name))
    n = lib.shim_n_points()
    assert n == sum(len(u.tool_points) for u in setups)
    rng = np.random.default_rng(7)
    nq = sum(u.controller_model.nq for u in setups)
    for _ in range(20):
        q = rng.uniform(-1.0, 1.0, nq)
        points, centres = np.full(2 * n + 1, np.nan), np.full(2 * n + 1, np.nan)
        assert lib.shim_tool_points(*(a.ctypes.data_as(_P) for a in (q, points, centres))) == 0
        want_points, want_centres, start = [], [], 0
        for u in setups:
            qu = q[start:start + u.controller_model.nq]
            start += u.controller_model.nq
            pose = np.array(u.fk_world(qu)).ravel()
            for _, (iu, iv) in u.tool_points:
                want_points += [pose[iu], pose[iv]]
                want_centres += [float(c) for c in u.keep_out_centre(qu)]
        np.testing.assert_allclose(points[:2 * n], want_points, rtol=0, atol=1e-14)
        np.testing.assert_array_equal(centres[:2 * n], want_centres)


def _replay(c: Embedded, name: str, duration: float):
    """Run the generated step on what the CasADi simulation's controller measured, period by
    period; return the largest differences (commands, estimates, errors), each relative to
    the run's peak."""
    sc = load_scenario(name)
    result = simulate(sc, duration=duration, kernels="casadi")
    assert not result.diverged
    setups = [u.setup for u in result.units]
    grids = [None if u.quantum is None else MeasurementGrid(u.quantum, u.grid_offset)
             for u in setups]
    delay = sc.plant.delay_periods
    logs = result.units
    tau = np.hstack([u.tau for u in logs])
    p_hat = np.hstack([u.p_hat for u in logs])
    errors = np.hstack([u.errors for u in logs])
    steps = len(result.time)
    assert c.init() == 0
    np.testing.assert_array_equal(c.p_hat(), p_hat[0])
    d_tau = d_p = d_e = 0.0
    for k in range(steps):
        seen = []
        for u, grid in zip(logs, grids):
            j = k - delay if k >= delay else 0
            x = np.concatenate([u.true_q[j], u.true_qd[j]])  # the plant's state, logged
            seen.append(grid.apply(x) if grid is not None else x)
            # ... delayed and on the grid: what the log says the controller measured.
            assert np.array_equal(seen[-1], np.concatenate([u.q[k], u.qd[k]]))
        assert c.step(float(result.time[k]), _measurement(seen)) == 0
        command = np.array(c.command, dtype=float)
        start = 0
        for u in setups:  # as the drives apply it (realistic plant)
            n = u.controller_model.nq
            if u.effort_grid is not None:
                u.effort_grid.apply(command[start:start + n])
            start += n
        d_tau = max(d_tau, float(np.max(np.abs(command - tau[k]))))
        d_e = max(d_e, float(np.max(np.abs(c.errors - errors[k]))))
        if k + 1 < steps:
            d_p = max(d_p, float(np.max(np.abs(c.p_hat() - p_hat[k + 1]))))
    return (d_tau / max(np.abs(tau).max(), 1e-12), d_p / max(np.abs(p_hat).max(), 1e-12),
            d_e / max(np.abs(errors).max(), 1e-12))


@pytest.mark.parametrize("name", THESIS)
@pytest.mark.slow
def test_step_equals_the_simulation(built, name):
    """The thesis's four studies on the ideal plant, 2000 periods: the commands, the estimates
    and the errors of the simulation (its controller's step, the supervisor's clip)."""
    c = Embedded(name, built[name, "double"])
    d_tau, d_p, d_e = _replay(c, name, 2.0)
    assert d_tau <= 1e-9 and d_p <= 1e-9 and d_e <= 1e-9, (d_tau, d_p, d_e)


@pytest.mark.parametrize("name", [n for n in SCENARIOS if n not in THESIS])
@pytest.mark.slow
def test_step_equals_the_realistic_simulation(built, name):
    """The realistic studies: the measurement delayed and on the encoder grid as the simulation
    measures it, the command clipped, then applied on the drives' current grid."""
    c = Embedded(name, built[name, "double"])
    d_tau, d_p, d_e = _replay(c, name, 2.0)
    assert d_tau <= 1e-9 and d_p <= 1e-9 and d_e <= 1e-9, (d_tau, d_p, d_e)


# --------------------------------------------------------------------------------------------
# Float against double, each in its own closed loop on the same plant
# --------------------------------------------------------------------------------------------


def _closed_loop(c: Embedded, name: str, steps: int):
    sc = load_scenario(name)
    setups = unit_setups(sc)
    plants = [plant_step(u.plant_model, sc.plant_substeps) for u in setups]
    xs = [np.array(u.x0, dtype=float) for u in setups]
    assert c.init() == 0
    taus, estimates = np.empty((steps, c.nq)), np.empty((steps, c.np))
    for k in range(steps):
        assert c.step(k * sc.period, _measurement(xs)) == 0
        taus[k] = c.command
        estimates[k] = c.p_hat()
        start = 0
        for i, (u, plant) in enumerate(zip(setups, plants)):
            n = u.controller_model.nq
            xs[i] = np.array(plant(xs[i], taus[k, start:start + n], u.plant_params,
                                   u.friction, sc.period)).ravel()
            start += n
    return taus, estimates


def estimate_drift(p_f: np.ndarray, p_d: np.ndarray) -> tuple[float, float]:
    """How far the float build's estimate ``p_f`` is from the double build's ``p_d`` (rows:
    periods): the largest distance over the run relative to the largest norm ``p_d`` reaches,
    and the distance at the end relative to ``p_d`` there. Not each period's relative: in its
    first periods the estimate is a small fraction of its size (serial_task's |p_hat| at
    period 73 a tenth of its final), where that measured float's resolution of a small number
    (5.2e-6 there, 3.6e-7 at the end) rather than a drift."""
    distance = np.linalg.norm(p_f - p_d, axis=1)
    return (float(distance.max() / np.linalg.norm(p_d, axis=1).max()),
            float(distance[-1] / max(np.linalg.norm(p_d[-1]), 1e-300)))


#: The float build's estimate against the double build's, each in its own closed loop on the
#: same plant (:func:`_closed_loop`), 2000 periods of the four thesis studies
#: (:func:`estimate_drift`): at most DRIFT_BOUND in every period relative to the estimate's
#: largest norm, and at the end relative to the estimate there (docs/embedded.md). Measured
#: with the compensated two-float sum and the exact angle wrap: largest 6.2e-8, 5.0e-7, 9.3e-8,
#: 7.0e-8, at the end 3.0e-8, 3.6e-7, 4.7e-8, 4.4e-8 (serial_joint, serial_task,
#: parallel_joint, parallel_task; with atan2(sin, cos) as the wrap serial_task's were 1.3e-6
#: and 1.3e-6). A plain float sum loses the small increments and drifts: at the end 3.7e-6,
#: 7.3e-6, 6.6e-6, 3.2e-6.
DRIFT_BOUND = 2e-6


@pytest.mark.parametrize("name", THESIS)
@pytest.mark.slow
def test_float_build_follows_the_double_build(built, name):
    steps = 2000
    tau_d, p_d = _closed_loop(Embedded(name, built[name, "double"]), name, steps)
    tau_f, p_f = _closed_loop(Embedded(name, built[name, "float"]), name, steps)
    torque = np.max(np.abs(tau_f - tau_d)) / np.max(np.abs(tau_d))
    assert np.abs(p_d[-1]).max() > 0  # the estimate moved
    largest, final = estimate_drift(p_f, p_d)
    assert torque <= 1e-5, torque
    assert largest <= DRIFT_BOUND and final <= DRIFT_BOUND, (largest, final)
