"""The C kernels through ctypes: each one equals the CasADi Function it was generated from, and
binding checks shapes and dtypes once, up front."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import cochlea
from cochlea.kernels import generate as codegen
from cochlea.kernels import library as ckernels
from cochlea.kernels.library import KernelError, LibraryError

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def lib():
    subprocess.run(["make", "-s", "lib"], cwd=ROOT, check=True, capture_output=True)
    return ckernels.load()


@pytest.fixture(scope="module")
def kernels():
    found, _ = codegen.collect(codegen.load_config())
    return found


@functools.cache
def _model(robot: str, unit: str, parameterisation: str = "inertial", actuators: str = "none"):
    arm = unit.split("_")[1] if robot == "serial" else None
    return cochlea.model(robot, arm=arm, parameterisation=parameterisation, actuators=actuators)


def _inputs(kernel: codegen.Kernel, rng) -> list[np.ndarray]:
    """Random inputs in a physical range: joint states inside the workspace, positive gains,
    parameters near nominal, a 1 ms period."""
    f = kernel.source
    m = _model(kernel.robot, kernel.unit)
    if kernel.robot == "parallel":
        q = m.geometry.random_configuration(rng)
    else:
        q = rng.uniform(-np.pi, np.pi, m.nq)
    values = []
    for i in range(f.n_in()):
        name, size = f.name_in(i), f.size1_in(i) * f.size2_in(i)
        if name == "q":
            v = q
        elif name == "x" and size == 4 * m.nq:  # the geared plant: link, then rotor
            qd = rng.uniform(-1, 1, m.nq)
            v = np.concatenate([q, qd, q + rng.uniform(-0.01, 0.01, m.nq),
                                qd + rng.uniform(-0.1, 0.1, m.nq)])
        elif name == "x":
            v = np.concatenate([q, rng.uniform(-1, 1, m.nq)])
        elif name == "drive":  # armature, backlash, stiffness, damping, Fc, Fs, vs
            rows = [3.4e-3, 0.006, 1e3, 0.1, 0.1, 0.15, 0.02]
            v = np.concatenate([np.full(m.nq, r) * rng.uniform(0.5, 1.5, m.nq) for r in rows])
        elif name == "dry":  # Coulomb, static, Stribeck velocity
            fc = rng.uniform(0.0, 0.05, m.nq)
            v = np.concatenate([fc, 1.5 * fc, np.full(m.nq, 0.02)])
        elif name in ("p", "p_hat"):  # of the kernel's model: with its drives' terms, if any
            full = _model(kernel.robot, kernel.unit, "inertial", kernel.actuators)
            if size == len(full.p_nominal):  # full inertial: scale the whole robot (physical)
                v = full.p_nominal * rng.uniform(0.5, 1.5)
            else:  # one mass per body
                v = _model(kernel.robot, kernel.unit, "mass",
                           kernel.actuators).p_nominal * rng.uniform(0.5, 1.5, size)
        elif name == "xd" and size == len(q):
            v = q + rng.uniform(-0.05, 0.05, size)
        elif name == "xd" and kernel.kind in ("g", "d"):
            v = np.array(m.fk_world(q) if kernel.kind == "g" else m.fk(q)).ravel() \
                + rng.uniform(-0.005, 0.005, size)
        elif name in ("gains", "Gamma"):
            v = rng.uniform(0.5, 3.0, size)
        elif name == "bound":
            v = np.array([10.0])
        elif name == "h":
            v = np.array([1e-3])
        elif name == "tau":  # small enough for the light distal links over one period
            v = rng.uniform(-0.01, 0.01, size)
        elif name == "friction":
            v = rng.uniform(0.0, 1e-3, size)
        else:  # velocities, accelerations
            v = rng.uniform(-1.0, 1.0, size)
        values.append(np.asarray(v, float))
    return values


@pytest.mark.slow
def test_every_kernel_equals_its_casadi_function(lib, kernels, rng):
    """All generated kernels at 20 random points each: relative error <= 1e-12."""
    assert set(lib.names) == {k.name for k in kernels}
    # Aliases included: each runs another kernel's C and is compared with its own source.
    assert sum(lib.symbol(k.name) != k.name for k in kernels) >= 30
    for k in kernels:
        bound = lib.kernel(k.name)
        for _ in range(20):
            args = _inputs(k, rng)
            expected = [np.array(ca.densify(o)) for o in k.source.call(args)]
            got = bound.evaluate(*args)
            for a, e, g in zip(bound.signature.outputs, expected, got):
                e = e.reshape(a.shape, order="F")
                scale = max(1.0, float(np.max(np.abs(e)))) if e.size else 1.0
                assert np.all(np.isfinite(g)), (k.name, a.name)
                assert np.max(np.abs(g - e), initial=0.0) <= 1e-12 * scale, (k.name, a.name)


@pytest.mark.slow
def test_aliases_keep_their_names_signatures_and_hashes(lib, kernels):
    """A kernel that runs another's C (serial_arm2_e_thesis_step runs serial_arm1_e_step) is
    bound, described and checked for staleness under its own name, as before bodies were
    shared; so is a closed-loop driver that runs another's."""
    from cochlea.kernels.naming import source_hash

    for k in kernels:
        assert lib.symbol(k.name) == k.symbol, k.name
        assert lib.source_hash(k.name) == source_hash(k.source), k.name
        if k.is_alias:
            sig, canonical = lib.signature(k.name), lib.signature(k.symbol)
            assert sig.name == k.name and lib.kernel(k.name).name == k.name
            assert (sig.inputs, sig.outputs, sig.sz_arg, sig.sz_res) == \
                (canonical.inputs, canonical.outputs, canonical.sz_arg, canonical.sz_res)
    assert lib.symbol("serial_arm2_e_thesis_step") == "serial_arm1_e_step"
    alias, own = (lib.closed_loop(f"serial_arm2_e{v}_closed_loop") for v in ("_thesis", ""))
    assert alias.name == "serial_arm2_e_thesis_closed_loop" and alias.meta["symbol"] == own.name
    inputs = dict(x0=np.full(6, 0.3), p_hat0=np.ones(3), xd=np.zeros((5, 3)),
                  xd_dot=np.zeros((5, 3)), xd_ddot=np.zeros((5, 3)), gains=np.ones(own.n_gains),
                  Gamma=np.ones(3), bound=10.0, h=1e-3, plant_p=np.ones(30),
                  friction=np.zeros(3))
    a, b = alias.run(5, **inputs), own.run(5, **inputs)
    assert a.rows == b.rows == 5
    for key in ("x", "p_hat", "tau", "errors", "pose"):
        assert np.array_equal(getattr(a, key), getattr(b, key)), key


def test_step_through_buffers_is_the_controller_step(lib, rng):
    """The hot path: write into input buffers, call, read the output views."""
    m = cochlea.model("serial", parameterisation="mass")
    c = cochlea.control.build(m, "e", task_angles=(2,))
    step = lib.kernel("serial_arm1_e_step")
    assert [a.name for a in step.signature.inputs] == list(c.step.name_in())
    tau = step["tau"]
    for _ in range(5):
        args = [rng.uniform(-1, 1, c.step.size1_in(i)) for i in range(c.step.n_in())]
        args[8], args[9] = np.array(0.5), np.array(1e-3)
        for name, value in zip(c.step.name_in(), args):
            step[name][...] = value.reshape(step[name].shape)
        step()
        expected = np.array(c.step(*args)[0]).ravel()
        assert np.max(np.abs(tau - expected)) <= 1e-12 * max(1, np.max(np.abs(expected)))
    assert step["tau"] is tau  # the same buffer every call


def test_matrices_are_column_major_views(lib, rng):
    m = cochlea.model("parallel")
    q = m.geometry.random_configuration(rng)
    M = lib.kernel("parallel_M")
    M["q"][:] = q
    M()
    assert M["M"].shape == (5, 5) and M["M"].flags.f_contiguous
    assert np.allclose(M["M"], np.array(m.M(q)), rtol=1e-13, atol=1e-15)
    J = lib.kernel("parallel_J", q=np.asarray(q, float).copy())
    J()
    assert J["J"].shape == (6, 5)
    assert np.allclose(J["J"], np.array(m.J(q)), rtol=1e-13, atol=1e-15)


def test_caller_buffers_are_used_in_place(lib):
    q = np.radians([73.0, 83.0, 110.0])
    out = np.zeros((3, 3), order="F")
    M = lib.kernel("serial_arm1_M", q=q, M=out)
    M()
    assert np.allclose(out, np.array(cochlea.model("serial").M(q)), rtol=1e-13)
    q[0] += 0.1  # the kernel reads the caller's array at each call
    M()
    assert np.allclose(out, np.array(cochlea.model("serial").M(q)), rtol=1e-13)


@pytest.mark.parametrize("buffers, message", [
    ({"q": np.zeros(3, dtype=np.float32)}, "dtype float64"),
    ({"q": np.zeros(4)}, r"shape \(3,\)"),
    ({"q": [0.0, 0.0, 0.0]}, "numpy array"),
    ({"M": np.zeros((3, 3))}, "column-major"),  # C order
    ({"M": np.zeros((3, 6), order="F")[:, ::2]}, "column-major"),
    ({"speed": np.zeros(3)}, "no argument speed"),
])
def test_binding_checks_buffers_once(lib, buffers, message):
    with pytest.raises(KernelError, match=message):
        lib.kernel("serial_arm1_M", **buffers)


def test_read_only_output_buffer_is_refused(lib):
    out = np.zeros((3, 3), order="F")
    out.flags.writeable = False
    with pytest.raises(KernelError, match="writeable"):
        lib.kernel("serial_arm1_M", M=out)


def test_missing_library_and_kernel_say_what_to_do(lib, tmp_path):
    with pytest.raises(LibraryError, match="make lib"):
        ckernels.load(tmp_path / "libcochlea.so")
    with pytest.raises(LibraryError, match="no kernel 'serial_arm3_M'"):
        lib.kernel("serial_arm3_M")
    with pytest.raises(LibraryError, match="no closed loop"):
        lib.closed_loop("serial_arm1_x_closed_loop")


def test_library_path_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(ckernels.ENVIRONMENT, str(tmp_path / "other.so"))
    assert ckernels.library_path() == tmp_path / "other.so"
    monkeypatch.delenv(ckernels.ENVIRONMENT)
    assert ckernels.library_path() == ckernels.default_library()


def test_casadi_loads_the_library_back(lib, rng):
    """casadi.external on libcochlea.so (the benchmark's Function.buffer() path): the default
    casadi_int keeps the library loadable by CasADi itself."""
    f = ca.external("serial_arm1_g_step", str(lib.path))
    m = cochlea.model("serial", parameterisation="mass")
    c = cochlea.control.build(m, "g", task_angles=(2,))
    args = [rng.uniform(0.2, 1.0, c.step.size1_in(i)) for i in range(c.step.n_in())]
    for got, expected in zip(f(*args), c.step(*args)):
        assert np.allclose(np.array(got), np.array(expected), rtol=1e-13, atol=1e-15)


def test_closed_loop_checks_its_arrays(lib):
    loop = lib.closed_loop("serial_arm1_e_closed_loop")
    good = dict(x0=np.zeros(6), p_hat0=np.zeros(3), xd=np.zeros((4, 3)), xd_dot=np.zeros((4, 3)),
                xd_ddot=np.zeros((4, 3)), gains=np.ones(loop.n_gains), Gamma=np.ones(3),
                bound=1.0, h=1e-3, plant_p=np.ones(30), friction=np.zeros(3))
    assert loop.run(4, **good).rows == 4
    with pytest.raises(KernelError, match=r"xd must have shape \(4, 3\)"):
        loop.run(4, **{**good, "xd": np.zeros((3, 3))})
    with pytest.raises(KernelError, match="noise must have shape"):
        loop.run(4, **good, noise=np.zeros((4, 3)))
    with pytest.raises(KernelError, match="delay"):
        loop.run(4, **good, delay=-1)


def test_the_benchmarks_numpy_law_is_the_c_step(lib, rng):
    """bench/numpy_law.py (the benchmark's NumPy baseline) computes controller e's step."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("numpy_law", ROOT / "bench" / "numpy_law.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    system = cochlea.load_serial("serial")
    for arm in system.arms:
        law = module.NumpyStepE(arm, arm.base_rotation.T @ system.gravity)
        step = lib.kernel(f"serial_{arm.name}_e_step")
        n_gains = step["gains"].size
        for i in range(20):
            args = [rng.uniform(-3, 3, 3), rng.uniform(-1, 1, 3), rng.uniform(-3, 3, 3),
                    rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3), rng.uniform(0, 0.2, 3),
                    rng.uniform(0.5, 5, n_gains), rng.uniform(0.5, 2, 3),
                    np.array(0.3 if i % 2 else 10.0), np.array(1e-3),  # projection on / off
                    np.zeros(3), np.full(3, -np.inf), np.full(3, np.inf), np.zeros(3),
                    np.ones(3)]  # the robust options, neutral
            for got, want in zip(law(*args), step.evaluate(*args)):
                assert np.max(np.abs(got - want)) <= 1e-12 * max(1, np.max(np.abs(want)))
