"""A serial chain's forward dynamics with its parameters' values folded in, in few operations.

With the parameters fixed (a simulated plant's true values), every entry of the mass matrix
``M(q)``, every Christoffel coefficient of the bias ``h(q, qd) = C(q, qd) qd + G(q) + F(qd)``
and every gravity torque is a *fixed* trigonometric polynomial of the joint angles (and a
polynomial of the prismatic joints' travel): a link's pose is linear in the sine and cosine of
each angle before it, the kinetic energy quadratic in the poses, so per revolute joint the
frequencies are at most 2, per prismatic joint the degree at most 2. Such a function is fixed
exactly by its values on a grid of 5 angles per revolute joint (a discrete Fourier transform)
and 3 positions per prismatic joint (an interpolation): :func:`folded_forward_dynamics` samples
the model's own ``M_p`` and ``inverse_dynamics_p`` there, keeps the coefficients that are not
rounding, and writes

    qdd = M(q)^-1 (tau - h(q, qd))

as those sums (the angles' multiples and sums from one sine and cosine per joint, by the
addition theorems) and an ``L D L^T`` solve of the symmetric ``M``: the shipped arm's plant
(3R, horizontal) takes 112 operations an evaluation against the articulated-body algorithm's
145 (:mod:`cochlea.robots.serial.aba`, general in the parameters), whose four evaluations are
most of a simulated period (issue 30).

The result is the model's ``forward_dynamics_p`` to rounding, not bit for bit: it is checked at
random states over the whole circle of every angle, and a model whose dynamics are not of that
form (a friction law that is not a polynomial of the velocity of degree 2 at most), whose grid
would be too large (:data:`MAX_GRID`) or whose check fails gets None, and its caller keeps the
general form.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import casadi as ca
import numpy as np

from ..model import RobotModel

#: Angles per revolute joint in the grid: frequencies -2..2.
ANGLES = 5
#: Positions per prismatic joint: degree 2.
POSITIONS = 3
#: Largest grid sampled (5^6: a 6R arm); beyond it the general form is kept.
MAX_GRID = ANGLES ** 6
#: A coefficient smaller than this times its group's largest value on the grid (the mass
#: matrix's, the bias's velocity-squared terms', ...) is rounding of a zero and dropped.
DROP = 1e-13
#: The check: at every sampled state the largest difference from ``forward_dynamics_p``, relative
#: to the largest acceleration there.
CHECK = 1e-12
CHECK_SAMPLES = 64


def _axes(model: RobotModel) -> list[np.ndarray]:
    axes = []
    for joint in model.joints:
        if joint.type == "revolute":
            axes.append(2.0 * np.pi * np.arange(ANGLES) / ANGLES)
        else:
            lo, hi = joint.position_limits
            lo, hi = (lo, hi) if np.isfinite(lo) and np.isfinite(hi) and hi > lo else (-1.0, 1.0)
            axes.append(np.array([lo, 0.5 * (lo + hi), hi]))
    return axes


def _coefficients(values: np.ndarray, kinds: list[str], axes: list[np.ndarray]) -> np.ndarray:
    """``values`` (functions x grid points, C order over the axes) -> the functions'
    coefficients over the same axes: per revolute axis frequency ``j`` (``j - 5`` above 2) of
    ``exp(i j q)``, per prismatic axis the power of ``q``."""
    c = values.reshape(values.shape[0], *(len(a) for a in axes)).astype(complex)
    for axis, (kind, nodes) in enumerate(zip(kinds, axes, strict=True)):
        if kind == "revolute":
            c = np.fft.fft(c, axis=axis + 1) / ANGLES
        else:
            inverse = np.linalg.inv(np.vander(nodes, POSITIONS, increasing=True))
            c = np.moveaxis(np.tensordot(inverse, c, axes=([1], [axis + 1])), 0, axis + 1)
    return c


class _Terms:
    """The basis functions of the fitted sums, built once each from one sine and cosine per
    joint: ``cos(k . q)``, ``sin(k . q)`` times powers of the prismatic joints' travel."""

    def __init__(self, q: ca.SX, kinds: list[str]):
        self.q, self.kinds = q, kinds
        self._trig: dict[tuple[int, ...], tuple] = {}
        self._single: dict[tuple[int, int], tuple] = {}
        self._basis: dict[tuple, ca.SX] = {}

    def _angle(self, axis: int, k: int) -> tuple:
        """(cos, sin) of ``k q[axis]`` for k in -2..2, k != 0."""
        key = (axis, k)
        if key not in self._single:
            if abs(k) == 1:
                c, s = ca.cos(self.q[axis]), ca.sin(self.q[axis])
                self._single[(axis, 1)] = (c, s)
            else:
                c1, s1 = self._angle(axis, 1)
                c, s = c1 * c1 - s1 * s1, 2 * (s1 * c1)
            self._single[key] = (c, -s if k < 0 else s)
        return self._single[key]

    def trig(self, k: tuple[int, ...]) -> tuple:
        """(cos, sin) of ``k . q`` over the revolute joints (k not all zero)."""
        if k not in self._trig:
            last = max(i for i, v in enumerate(k) if v)
            rest = tuple(0 if i == last else v for i, v in enumerate(k))
            c1, s1 = self._angle(last, k[last])
            if any(rest):
                cr, sr = self.trig(rest)
                self._trig[k] = (cr * c1 - sr * s1, sr * c1 + cr * s1)
            else:
                self._trig[k] = (c1, s1)
        return self._trig[k]

    def basis(self, key: tuple) -> ca.SX | None:
        """``key = (kind, k, powers)``: kind "cos", "sin" or "one". None: the constant 1."""
        if key not in self._basis:
            kind, k, powers = key
            value = None if kind == "one" else self.trig(k)[0 if kind == "cos" else 1]
            for i, e in enumerate(powers):
                for _ in range(e):
                    value = self.q[i] if value is None else value * self.q[i]
            self._basis[key] = value
        return self._basis[key]


def _real_terms(c: np.ndarray, kinds: list[str], drop: float) -> dict[tuple, float]:
    """One function's complex coefficients -> its real terms ``{(kind, k, powers): value}``,
    ``k`` and ``-k`` together (the function is real: 2 Re c cos(k.q) - 2 Im c sin(k.q))."""
    terms = {}
    for index in itertools.product(*(range(s) for s in c.shape)):
        value = c[index]
        if abs(value) <= drop:
            continue
        k = tuple((i if i <= 2 else i - ANGLES) if kind == "revolute" else 0
                  for i, kind in zip(index, kinds, strict=True))
        powers = tuple(0 if kind == "revolute" else i for i, kind in zip(index, kinds,
                                                                           strict=True))
        if not any(k):
            terms[("one", k, powers)] = value.real
            continue
        if next(v for v in k if v) < 0:
            continue  # -k's term, written with k's
        if abs(2 * value.real) > drop:
            terms[("cos", k, powers)] = 2 * value.real
        if abs(2 * value.imag) > drop:
            terms[("sin", k, powers)] = -2 * value.imag
    return terms


def _sum(terms: dict[tuple, float], basis: _Terms, factor=None):
    """``sum(value * basis(key)) * factor`` (factor None: 1), 0 when there are no terms."""
    out = None
    for key, value in terms.items():
        b = basis.basis(key)
        term = value if b is None else value * b
        out = term if out is None else out + term
    if out is None:
        return None
    return out if factor is None else out * factor


def _ldl_solve(M, b, n: int) -> ca.SX:
    """``M^-1 b`` for the symmetric positive definite ``M`` (n x n entries): ``L D L^T``,
    no pivoting (M is a mass matrix), one division per pivot."""
    L = [[None] * n for _ in range(n)]
    d_inv = [None] * n
    D = [None] * n
    for j in range(n):
        s = M[j][j]
        for k in range(j):
            s = s - L[j][k] * (L[j][k] * D[k])
        D[j], d_inv[j] = s, 1 / s
        for i in range(j + 1, n):
            s = M[i][j]
            for k in range(j):
                s = s - L[i][k] * (L[j][k] * D[k])
            L[i][j] = s * d_inv[j]
    y = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s
    x = [None] * n
    for i in reversed(range(n)):
        s = y[i] * d_inv[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * x[k]
        x[i] = s
    return ca.vertcat(*x)


def folded_forward_dynamics(model: RobotModel, p) -> Callable | None:
    """``model``'s forward dynamics at the parameter values ``p`` (its own parameterisation),
    as fitted sums and an ``L D L^T`` solve (the module's docstring): a callable
    ``(q, qd, tau, p) -> qdd`` of symbolic ``q, qd, tau`` whose ``p`` is ignored (the values
    are folded in; pass the same), equal to ``model.forward_dynamics_p(q, qd, tau, p)`` to
    rounding (checked here); None where the form does not apply."""
    n = model.nq
    kinds = [j.type for j in model.joints]
    if n == 0 or any(k not in ("revolute", "prismatic") for k in kinds):
        return None
    axes = _axes(model)
    grid_size = int(np.prod([len(a) for a in axes]))
    if grid_size > MAX_GRID:
        return None
    p = ca.DM(np.ravel(np.asarray(p, float)))
    q, qd, tau = (ca.SX.sym(name, n) for name in ("q", "qd", "tau"))
    zeros = ca.SX.zeros(n)
    M = model.M_p(q, p)
    h = model.inverse_dynamics_p(q, qd, zeros, p)
    h0 = ca.substitute(h, qd, zeros)
    h1 = ca.substitute(ca.jacobian(h, qd), qd, zeros)
    upper = [(i, j) for i in range(n) for j in range(i, n)]
    hessians = [ca.hessian(h[i], qd)[0] for i in range(n)]
    groups = {
        "M": [M[i, j] for i, j in upper],
        "h0": [h0[i] for i in range(n)],
        "h1": [h1[i, j] for i in range(n) for j in range(n)],
        "h2": [hessians[i][j, k] * (0.5 if j == k else 1.0) for i in range(n)
               for j, k in upper],
    }
    everything = ca.vertcat(*(e for g in groups.values() for e in g))
    if ca.depends_on(everything, ca.vertcat(qd, tau)):
        return None  # the bias is not quadratic in the velocities (dry friction's smoothing)
    sample = ca.Function("folded_sample", [q], [everything])
    grid = np.array(list(itertools.product(*axes))).T
    values = np.array(sample.map(grid_size)(grid), float)
    if not np.all(np.isfinite(values)):
        return None
    coefficients = _coefficients(values, kinds, axes)
    basis = _Terms(q, kinds)
    fitted, at = {}, 0
    for name, group in groups.items():
        scale = float(np.max(np.abs(values[at:at + len(group)]), initial=0.0))
        fitted[name] = [_real_terms(coefficients[at + i], kinds, DROP * scale)
                        for i in range(len(group))]
        at += len(group)

    entries = dict(zip(upper, fitted["M"], strict=True))
    mass = [[None] * n for _ in range(n)]
    for (i, j), terms in entries.items():
        value = _sum(terms, basis)
        mass[i][j] = mass[j][i] = ca.SX(0.0) if value is None else value
    if any(not entries[(i, i)] for i in range(n)):
        return None  # a joint without inertia: no solve
    products = {(j, k): qd[j] * qd[k] for j, k in upper}
    bias = []
    h2 = iter(fitted["h2"])
    for i in range(n):
        # Each basis function once per joint: it multiplies its velocities' polynomial.
        by_basis: dict[tuple, list] = {}
        for key, value in fitted["h0"][i].items():
            by_basis.setdefault(key, []).append((value, None))
        for j in range(n):
            for key, value in fitted["h1"][i * n + j].items():
                by_basis.setdefault(key, []).append((value, qd[j]))
        for jk in upper:
            for key, value in next(h2).items():
                by_basis.setdefault(key, []).append((value, products[jk]))
        total = None
        for key, parts in by_basis.items():
            velocity = None
            for value, monomial in parts:
                term = value if monomial is None else value * monomial
                velocity = term if velocity is None else velocity + term
            b = basis.basis(key)
            term = velocity if b is None else b * velocity
            total = term if total is None else total + term
        bias.append(ca.SX(0.0) if total is None else total)
    qdd = _ldl_solve(mass, [tau[i] - bias[i] for i in range(n)], n)
    folded = ca.Function(f"{model.name.replace('/', '_')}_folded_forward_dynamics",
                         [q, qd, tau], [qdd], ["q", "qd", "tau"], ["qdd"])
    if not _agrees(model, folded, p):
        return None
    return lambda q_, qd_, tau_, p_=None: folded(q_, qd_, tau_)


def _agrees(model: RobotModel, folded: ca.Function, p: ca.DM) -> bool:
    """Whether ``folded`` is ``forward_dynamics_p`` at ``p`` to :data:`CHECK` at random states:
    every angle over its whole circle, travel within its limits, velocities and efforts up to
    their limits (at least 1)."""
    rng = np.random.default_rng(20261128)
    for _ in range(CHECK_SAMPLES):
        q, qd, tau = [], [], []
        for joint in model.joints:
            lo, hi = joint.position_limits
            if joint.type == "revolute" or not (np.isfinite(lo) and np.isfinite(hi)):
                lo, hi = -np.pi, np.pi
            q.append(rng.uniform(lo, hi))
            qd.append(rng.uniform(-1, 1) * _bound(joint.velocity_limit))
            tau.append(rng.uniform(-1, 1) * _bound(joint.effort_limit))
        reference = np.asarray(model.forward_dynamics_p(q, qd, tau, p), float).ravel()
        value = np.asarray(folded(q, qd, tau), float).ravel()
        if not (np.all(np.isfinite(value)) and np.all(np.isfinite(reference))):
            return False
        if np.max(np.abs(value - reference)) > CHECK * np.max(np.abs(reference)):
            return False
    return True


def _bound(limit: float) -> float:
    """A sampling range from a joint's limit: the limit, at least 1 and at most 1e3."""
    return float(np.clip(limit, 1.0, 1e3)) if np.isfinite(limit) else 1e3
