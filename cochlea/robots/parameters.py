"""Dynamic-parameter sets: full inertial, base (minimal identifiable), and thesis-style mass-only.

Every parameterisation is a linear map onto the full inertial parameters,
``phi_full = to_full @ p``, so one symbolic model serves all of them and the regressor of any
set is the Jacobian of the same dynamics with respect to its ``p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ModelError

PARAMETERISATIONS = ("inertial", "base", "mass")


@dataclass(frozen=True)
class Parameterisation:
    kind: str  # one of PARAMETERISATIONS
    names: tuple[str, ...]
    nominal: np.ndarray
    si_units: tuple[str, ...]  # the SI unit of each parameter ("kg", "kg m", "kg m^2")
    to_full: np.ndarray  # (n_full, n): phi_full = to_full @ p
    meanings: tuple[str, ...]  # what each parameter is or combines, printable
    #: (n, n_full): ``p = from_full @ phi_full``, how any full parameter vector (a perturbed
    #: plant's, an identified one) maps onto this set; None for the mass-only set, which is a
    #: restriction of the full set (its bodies' shapes fixed), not a projection of it.
    from_full: np.ndarray | None = None

    def describe(self) -> str:
        width = max(len(n) for n in self.names)
        lines = [f"{self.kind} parameters ({len(self.names)}):"]
        for name, value, unit, meaning in zip(self.names, self.nominal, self.si_units,
                                              self.meanings):
            lines.append(f"  {name:<{width}} = {value: .6e} {unit:<7}  {meaning}")
        return "\n".join(lines)


def inertial(names, nominal, units, meanings) -> Parameterisation:
    n = len(names)
    return Parameterisation("inertial", tuple(names), np.asarray(nominal, float), tuple(units),
                            np.eye(n), tuple(meanings), np.eye(n))


def mass_only(full_names, full_nominal, bodies: list[tuple[str, slice]], full_units=(),
              full_meanings=()) -> Parameterisation:
    """One parameter per body, its mass, with the body's geometry held at nominal.

    All inertial parameters of a rigid body scale with its mass when its shape and density
    distribution are kept, so ``phi_body(m) = m * phi_body_nominal / m_nominal``: the thesis's
    parameterisation in link masses. A single-parameter block named like its parameter (an
    actuator's armature, see :func:`cochlea.robots.model.with_armatures`) is estimated itself.
    """
    full_nominal = np.asarray(full_nominal, float)
    to_full = np.zeros((len(full_names), len(bodies)))
    names, nominal, units, meanings = [], [], [], []
    for k, (body, block) in enumerate(bodies):
        if full_names[block.start] == body:  # an actuator parameter (armature): kept itself
            to_full[block, k] = 1.0
            names.append(body)
            nominal.append(full_nominal[block.start])
            units.append(full_units[block.start])
            meanings.append(full_meanings[block.start])
            continue
        m = full_nominal[block][0]
        to_full[block, k] = full_nominal[block] / m
        names.append(f"{body}.m")
        nominal.append(m)
        units.append("kg")
        meanings.append(f"mass of {body}, geometry fixed at nominal")
    return Parameterisation("mass", tuple(names), np.array(nominal), tuple(units), to_full,
                            tuple(meanings))


def _format_coefficient(c: float) -> str:
    return f"{c:.6g}"


def base(regressor_full: ca.Function, full_names, full_nominal, full_units, input_sizes,
         *, samples: int = 40, seed: int = 0, tol: float = 1e-8) -> Parameterisation:
    """Base parameters by numerical elimination on a regressor sampled at random states.

    Columns are taken in order (link by link, from the base) and kept when they add to the span
    of those already kept; a zero column is unidentifiable and dropped, a dependent column is
    regrouped into the kept ones: ``beta = phi_kept + K phi_dropped``. Taking columns in order
    groups distal masses into proximal inertias, the classic grouping of the robotics
    literature (e.g. ``Izz1 + l1^2 (m2 + m3)`` for a planar arm).
    """
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(samples):
        args = [rng.uniform(-np.pi, np.pi, size) for size in input_sizes]
        rows.append(np.array(regressor_full(*args)))
    W = np.vstack(rows)
    norms = np.linalg.norm(W, axis=0)
    scale = norms.max()
    if scale == 0.0:
        raise ModelError("the regressor is zero at every sampled state: nothing is identifiable")

    kept: list[int] = []
    basis = np.zeros((W.shape[0], 0))
    for j in range(W.shape[1]):
        if norms[j] <= tol * scale:
            continue
        w = W[:, j] / norms[j]
        residual = w - basis @ (basis.T @ w)
        residual = residual - basis @ (basis.T @ residual)  # re-orthogonalise once
        size = np.linalg.norm(residual)
        if size > tol ** 0.5:
            kept.append(j)
            basis = np.hstack([basis, (residual / size)[:, None]])

    dropped = [j for j in range(W.shape[1]) if j not in kept]
    W_kept = W[:, kept]
    K = np.linalg.lstsq(W_kept, W[:, dropped], rcond=None)[0] if dropped else \
        np.zeros((len(kept), 0))
    misfit = np.linalg.norm(W_kept @ K - W[:, dropped]) / scale if dropped else 0.0
    if misfit > 1e-8:
        raise ModelError(f"base parameters: regrouping leaves a relative misfit of {misfit:.1e}")
    K[np.abs(K) < 1e-10 * max(1.0, np.abs(K).max(initial=0.0))] = 0.0

    combine = np.zeros((len(kept), W.shape[1]))  # beta = combine @ phi_full
    combine[np.arange(len(kept)), kept] = 1.0
    combine[:, dropped] = K
    full_nominal = np.asarray(full_nominal, float)

    names, meanings = [], []
    for b, j in enumerate(kept):
        terms = [full_names[j]]
        for d_col, d in enumerate(dropped):
            c = K[b, d_col]
            if c != 0.0:
                sign = "-" if c < 0 else "+"
                terms.append(f"{sign} {_format_coefficient(abs(c))}*{full_names[d]}")
        names.append(f"b{b + 1}")
        meanings.append(" ".join(terms))

    to_full = np.zeros((W.shape[1], len(kept)))
    to_full[kept, np.arange(len(kept))] = 1.0
    units = tuple(full_units[j] for j in kept)
    return Parameterisation("base", tuple(names), combine @ full_nominal, units, to_full,
                            tuple(meanings), combine)
