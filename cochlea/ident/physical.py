"""Physically consistent identification: the least-squares fit restricted to parameters a real
body can have, so that the result can be simulated and written back to a description.

Ordinary least squares fits the base parameters freely and may land on a set no rigid body
has (a negative mass, an inertia breaking the triangle inequality, a negative friction). Here
every body's parameters are a smooth function of unconstrained coordinates ``theta`` that can
only produce consistent bodies, and :func:`scipy.optimize.least_squares` minimises

    || w * (W from_full phi(theta) - tau) ||^2  +  lam || N^T D^-1 (phi(theta) - prior) ||^2

* a rigid body with all ten parameters about its frame origin (the serial links): its 4x4
  pseudo-inertia ``J = [[Sigma, h], [h^T, m]]``, ``Sigma = tr(I)/2 1 - I``, positive definite
  (Wensing, Kim & Slotine 2017: positive mass, positive-definite inertia about the centre of
  mass, strict triangle inequalities). Log-Cholesky (Rucker & Wensing 2022): ``J = U U^T``,
  ``U = e^a [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]]``;
* a planar body with ``m, mx, my, Izz`` (the parallel mechanism's links): the pseudo-inertia
  condition reduces to ``m > 0`` and an inertia about the centre of mass ``Izz_c > 0`` (the
  in-plane spread is not seen, the out-of-plane thickness is free), so ``m = e^2a``,
  ``(mx, my) = m (t1, t2)``, ``Izz = e^2d + m |t|^2``;
* a body seen only through its mass (the slider): ``m = e^2a``;
* an actuator's armature, viscous or Coulomb friction (``<joint>.Ia``, ``.Fv``, ``.Fc``):
  ``scale e^2s``, never negative; a term the data want at or below zero ends at 1e-12 of its
  prior value (see LOG_FLOOR), which is zero for any use of it. (A square ``s^2`` reaches zero
  exactly but the solver halves ``s`` forever on the way, into subnormal numbers.)

Every body is the sum of that parametrised body and a FLOOR body at the frame origin (mass
:data:`MASS_FLOOR_KG`, inertia :data:`INERTIA_FLOOR_KGM2` about every axis): adding a
consistent body only adds mass and inertia about the centre of mass, so the result always
clears the descriptions' own bounds (``MIN_MASS_KG``, ``MIN_INERTIA_KGM2``) and never sits on
the boundary of the consistent set, where the logarithms would run off to minus infinity.

The regulariser pulls toward ``prior`` only the directions the data do not determine: ``N``
spans the null space of the weighted regressor in full-parameter coordinates scaled by ``D``
(each body's mass, mass x radius of gyration, mass x radius^2). Unidentifiable parameters
(out-of-plane inertias of the planar arms, the split of a regrouped sum between bodies) stay
at the prior unless consistency needs them to move; identified ones follow the data.

Where they must move (a thin rod's inertia about its axis is not identified, yet bounds the
identified one through the triangle inequality), the prior-centred optimum is biased. Proximal
rounds remove the bias: the regulariser is re-centred on the last solution, its weight cut
tenfold, and the solve restarted from that point made clear of the boundary (a coordinate run
toward minus infinity has no gradient left). Rounds end when the base parameters stop moving or
the fit improves by less than a thousandth of the least-squares residual (noise).

Coordinates are relative to each body's prior mass and radius of gyration (theta = 0 is a body
of the prior's size), so that the solver's columns have comparable sizes.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

# scipy.optimize is imported where it is used: at the top it costs every cochlea-identify start
# (a --help, a refused file) about a second.
from ..errors import ModelError
from ..robots.description import (
    MAX_ARMATURE,
    MAX_EFFORT,
    MAX_INERTIA_KGM2,
    MAX_LENGTH_M,
    MAX_MASS_KG,
    MIN_INERTIA_KGM2,
    MIN_MASS_KG,
)
from ..robots.model import INERTIAL_NAMES

#: The floor body added to every identified body (see the module's docstring): twice the
#: descriptions' smallest mass and inertia, so that rounding never takes a result below them.
MASS_FLOOR_KG = 2.0 * MIN_MASS_KG
INERTIA_FLOOR_KGM2 = 2.0 * MIN_INERTIA_KGM2

#: Parameter kinds of an actuator (``<joint>.Ia``, ``.Fv``, ``.Fc``), each >= 0.
ACTUATOR_KINDS = ("Ia", "Fv", "Fc")
PLANAR_KINDS = ("m", "mx", "my", "Izz")

#: Weight of the regulariser relative to the largest squared singular value of the scaled,
#: weighted regressor: small enough that a direction the data determine (down to the
#: singular-value cut below) is not moved measurably, large enough to fix the others.
REGULARISATION = 1e-8
#: Singular values below this fraction of the largest count as "not determined by the data".
RANK_TOLERANCE = 1e-9
#: At most this many re-centred solves after the first (see physically_consistent_fit).
MAX_PROXIMAL_ROUNDS = 8
#: A round that moves no base parameter by more than this fraction of its typical size ends
#: them.
ROUND_TOLERANCE = 1e-10
#: Each round's regulariser weight is this fraction of the previous one's: the rounds close
#: the gap to the best consistent fit faster and faster.
ROUND_SHRINK = 0.1
#: Rounds stop when they improve the fit by less than this fraction of the ordinary
#: least-squares residual (the noise): statistically the same fit.
ROUND_SIGNIFICANCE = 1e-3
#: Lowest value a logarithmic coordinate is let reach without resistance (see the fit).
LOG_FLOOR = float(np.log(1e-6))
#: The solver's tolerances (MINPACK's Levenberg-Marquardt; looser ones, 1e-12, stop the rounds'
#: solves early and leave 1e-4 of bias with exact data) and its budget of residual evaluations
#: per solve: at an optimum on the boundary of the consistent set (a mass or friction the data
#: push below zero) the coordinates creep toward minus infinity and only the budget ends the
#: solve; the cost is then within 1e-3 of a solve twenty times longer (docs).
TOL = 1e-15
MAX_NFEV = 300
#: Trailing coordinates with an all-zero Jacobian column handed to the solver after theta.
#: SciPy's MINPACK (its C translation, measured with 1.17.1) reads one element past the end of
#: the Jacobian when its pivoted QR (qrfac) recomputes the norm of the column stored last:
#: whatever the heap holds there entered the pivoting and the step, so two fits of the same data
#: could land on different optima (valgrind: "invalid read ... 0 bytes after a block", the
#: Jacobian's; glibc's MALLOC_PERTURB_ changes the result without the pad). A zero column has
#: norm zero, is never pivoted away from the last place and never has its norm recomputed, so
#: the read never happens; its step is always zero (MINPACK treats it as a rank-deficient
#: direction), and the solve is a function of the data alone.
MINPACK_PAD = 1


@dataclass(frozen=True)
class PhysicalFit:
    """A physically consistent estimate."""

    full: np.ndarray  # phi_full in model.full_parameters order, physically consistent
    base: np.ndarray  # model.parameters.from_full @ full
    cost: float  # weighted residual sum of squares at the solution (no regulariser)
    iterations: int  # Jacobian evaluations: the start kept, then its re-centred rounds


@dataclass(frozen=True)
class _Block:
    """The parameters of one body or one actuator term, as indices into the full vector."""

    owner: str  # "link2", "left.link7", "slider", "joint1" (actuator terms: one block each)
    kind: str  # "spatial" | "planar" | "mass" | "actuator"
    index: dict[str, int]  # parameter kind ("m", "Izz", "Fc") -> index in the full vector

    @property
    def size(self) -> int:
        return len(self.index)


def _blocks(names: tuple[str, ...]) -> list[_Block]:
    """Group the full parameters by owner and recognise what each group is."""
    groups: dict[str, dict[str, int]] = {}
    blocks: list[_Block] = []
    for i, name in enumerate(names):
        owner, _, kind = name.rpartition(".")
        if kind in ACTUATOR_KINDS:
            blocks.append(_Block(owner, "actuator", {kind: i}))
        elif kind in INERTIAL_NAMES and owner:
            groups.setdefault(owner, {})[kind] = i
        else:
            raise ModelError(f"physically consistent fit: parameter {name!r} is neither a "
                             f"body's ({', '.join(INERTIAL_NAMES)}) nor an actuator's "
                             f"({', '.join(ACTUATOR_KINDS)})")
    for owner, index in groups.items():
        kinds = set(index)
        if kinds == set(INERTIAL_NAMES):
            blocks.append(_Block(owner, "spatial", index))
        elif kinds == set(PLANAR_KINDS):
            blocks.append(_Block(owner, "planar", index))
        elif kinds == {"m"}:
            blocks.append(_Block(owner, "mass", index))
        else:
            raise ModelError(f"physically consistent fit: body {owner!r} has parameters "
                             f"{sorted(kinds)}; known are all ten {INERTIAL_NAMES}, the planar "
                             f"{PLANAR_KINDS} or the mass alone")
    return blocks


# --------------------------------------------------------------------------------------------
# Body algebra
# --------------------------------------------------------------------------------------------


def inertia_tensor(ixx, iyy, izz, ixy, ixz, iyz) -> np.ndarray:
    """The 3x3 inertia tensor from the description's six numbers (``Ixy`` is the tensor's
    entry, ``-m x y`` for a point mass)."""
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=float)


def pseudo_inertia(phi10) -> np.ndarray:
    """The 4x4 pseudo-inertia ``[[Sigma, h], [h^T, m]]`` of ``[m, mx, my, mz, Ixx, Iyy, Izz,
    Ixy, Ixz, Iyz]`` about the frame origin; ``Sigma = tr(I)/2 1 - I`` is the second moment
    ``integral r r^T dm``."""
    m, hx, hy, hz = phi10[:4]
    inertia = inertia_tensor(*phi10[4:])
    J = np.zeros((4, 4))
    J[:3, :3] = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    J[:3, 3] = J[3, :3] = (hx, hy, hz)
    J[3, 3] = m
    return J


def body_values(model, full) -> dict[str, dict[str, object]]:
    """Each body and actuator of ``full`` in the descriptions' terms (SI): a body's
    ``mass_kg``, ``com_m`` (3 or 2 numbers) and ``inertia_com_kgm2`` (the six
    ``[Ixx, Iyy, Izz, Ixy, Ixz, Iyz]`` about the centre of mass, or the planar scalar); an
    actuator's ``Ia``, ``Fv``, ``Fc`` under its joint's name."""
    full = np.asarray(full, float)
    values: dict[str, dict[str, object]] = {}
    for b in _blocks(model.full_parameters.names):
        p = {k: float(full[i]) for k, i in b.index.items()}
        if b.kind == "actuator":
            values.setdefault(b.owner, {}).update(p)
            continue
        m = p["m"]
        entry: dict[str, object] = {"mass_kg": m}
        if b.kind == "spatial":
            c = np.array([p["mx"], p["my"], p["mz"]]) / m
            origin = inertia_tensor(*(p[k] for k in INERTIAL_NAMES[4:]))
            com = origin - m * (float(c @ c) * np.eye(3) - np.outer(c, c))  # parallel axes
            entry["com_m"] = c
            entry["inertia_com_kgm2"] = np.array([com[0, 0], com[1, 1], com[2, 2], com[0, 1],
                                                  com[0, 2], com[1, 2]])
        elif b.kind == "planar":
            c = np.array([p["mx"], p["my"]]) / m
            entry["com_m"] = c
            entry["inertia_com_kgm2"] = p["Izz"] - m * float(c @ c)
        values[b.owner] = entry
    return values


def consistency_violations(model, full) -> list[str]:
    """What makes ``full`` physically inconsistent, one line per body or actuator term
    (empty: consistent). Rigid bodies: pseudo-inertia positive definite (hence positive mass,
    positive-definite inertia about the centre of mass, triangle inequalities); planar bodies:
    positive mass and inertia about the centre of mass; actuators: every term >= 0."""
    full = np.asarray(full, float)
    problems = []
    for b in _blocks(model.full_parameters.names):
        p = {k: float(full[i]) for k, i in b.index.items()}
        if b.kind == "actuator":
            (kind, value), = p.items()
            if not value >= 0.0:
                problems.append(f"{b.owner}.{kind} = {value:.3g} is negative")
            continue
        if not p["m"] > 0.0:
            problems.append(f"{b.owner}: mass {p['m']:.3g} kg is not positive")
            continue
        if b.kind == "spatial":
            eig = np.linalg.eigvalsh(pseudo_inertia([p[k] for k in INERTIAL_NAMES]))
            if not eig[0] > 0.0:
                problems.append(f"{b.owner}: pseudo-inertia not positive definite (smallest "
                                f"eigenvalue {eig[0]:.3g})")
        elif b.kind == "planar":
            izz_c = p["Izz"] - (p["mx"] ** 2 + p["my"] ** 2) / p["m"]
            if not izz_c > 0.0:
                problems.append(f"{b.owner}: inertia about the centre of mass {izz_c:.3g} "
                                "kg m^2 is not positive")
    return problems


def beyond_description_bounds(model, full) -> list[str]:
    """Where a consistent ``full`` exceeds what a description may say (a mass above
    ``MAX_MASS_KG``, a centre of mass beyond ``MAX_LENGTH_M``, an inertia above
    ``MAX_INERTIA_KGM2``, an actuator term above its joint type's limit): such a body is
    real but absurd, and no description file could hold it. One line each."""
    types = {j.name: j.type for j in model.joints}
    top = {"Ia": MAX_ARMATURE, "Fv": MAX_EFFORT, "Fc": MAX_EFFORT}
    problems = []
    for owner, v in body_values(model, full).items():
        if "mass_kg" not in v:
            for kind, value in v.items():
                limit = top[kind][types.get(owner, "revolute")]
                if value > limit:
                    problems.append(f"{owner}.{kind} = {value:.4g} above {limit:g}")
            continue
        if v["mass_kg"] > MAX_MASS_KG:
            problems.append(f"{owner}: mass {v['mass_kg']:.4g} kg above {MAX_MASS_KG:g} kg")
        if "com_m" in v and np.max(np.abs(v["com_m"])) > MAX_LENGTH_M:
            problems.append(f"{owner}: centre of mass {np.max(np.abs(v['com_m'])):.4g} m from "
                            f"the frame, beyond {MAX_LENGTH_M:g} m")
        if "inertia_com_kgm2" in v and np.max(np.abs(v["inertia_com_kgm2"])) > MAX_INERTIA_KGM2:
            problems.append(f"{owner}: inertia {np.max(np.abs(v['inertia_com_kgm2'])):.4g} "
                            f"kg m^2 above {MAX_INERTIA_KGM2:g} kg m^2")
    return problems


# --------------------------------------------------------------------------------------------
# The parametrisation theta -> phi (symbolic, for the exact Jacobian) and back (projection)
# --------------------------------------------------------------------------------------------

_THETA_SIZE = {"spatial": 10, "planar": 4, "mass": 1, "actuator": 1}
#: Which of a block's coordinates are logarithms (of the free mass, of the Cholesky diagonal,
#: of the planar inertia about the centre of mass, of an actuator term).
_LOG_COORDINATES = {"spatial": (0, 1, 2, 3), "planar": (0, 3), "mass": (0,), "actuator": (0,)}


def _log_indices(blocks: list[_Block]) -> np.ndarray:
    indices, k = [], 0
    for b in blocks:
        indices.extend(k + j for j in _LOG_COORDINATES[b.kind])
        k += _THETA_SIZE[b.kind]
    return np.array(indices, dtype=int)


def _body_scale(b: _Block, scale: np.ndarray) -> tuple[float, float]:
    """A body's typical mass m0 and radius r0, from :func:`_scales`."""
    m0 = float(scale[b.index["m"]])
    r0 = float(scale[b.index["mx"]]) / m0 if "mx" in b.index else 1.0
    return m0, r0


def _phi_symbolic(blocks: list[_Block], n_full: int, scale: np.ndarray
                  ) -> tuple[ca.Function, int]:
    """``phi(theta)`` and its Jacobian as one CasADi Function ``theta -> (phi, dphi/dtheta)``.

    Coordinates are relative to each body's typical mass m0 and radius r0 (so that the prior
    sits near theta = 0 and the solver sees columns of similar size): masses ``m0 e^2a``,
    lengths (centre of mass, Cholesky factor) in units of r0, actuator terms ``scale e^2s``."""
    n_theta = sum(_THETA_SIZE[b.kind] for b in blocks)
    theta = ca.SX.sym("theta", n_theta)
    phi = [ca.SX(0)] * n_full
    k = 0
    for b in blocks:
        t = theta[k:k + _THETA_SIZE[b.kind]]
        k += _THETA_SIZE[b.kind]
        if b.kind == "actuator":
            (i,) = b.index.values()
            phi[i] = scale[i] * ca.exp(2 * t[0])
            continue
        m0, r0 = _body_scale(b, scale)
        if b.kind == "mass":
            phi[b.index["m"]] = MASS_FLOOR_KG + m0 * ca.exp(2 * t[0])
        elif b.kind == "planar":
            m = MASS_FLOOR_KG + m0 * ca.exp(2 * t[0])
            cx, cy = r0 * t[1], r0 * t[2]
            phi[b.index["m"]] = m
            phi[b.index["mx"]] = m * cx
            phi[b.index["my"]] = m * cy
            phi[b.index["Izz"]] = (INERTIA_FLOOR_KGM2 + m0 * r0 ** 2 * ca.exp(2 * t[3])
                                   + m * (cx ** 2 + cy ** 2))
        else:
            a, d1, d2, d3, s12, s13, s23, t1, t2, t3 = (t[j] for j in range(10))
            # U of the body in units of m0 and r0, then J = S U U^T S, S = diag(r0,r0,r0,1)
            U = np.sqrt(m0) * ca.exp(a) * ca.vertcat(
                ca.horzcat(ca.exp(d1), s12, s13, t1),
                ca.horzcat(0, ca.exp(d2), s23, t2),
                ca.horzcat(0, 0, ca.exp(d3), t3),
                ca.horzcat(0, 0, 0, 1))
            S = ca.diag(ca.DM([r0, r0, r0, 1.0]))
            J = S @ U @ U.T @ S
            # The floor body at the origin: Sigma = (I_floor / 2) 1 gives I = I_floor 1.
            sigma = J[:3, :3] + 0.5 * INERTIA_FLOOR_KGM2 * ca.SX.eye(3)
            inertia = ca.trace(sigma) * ca.SX.eye(3) - sigma
            values = {"m": MASS_FLOOR_KG + J[3, 3], "mx": J[0, 3], "my": J[1, 3],
                      "mz": J[2, 3], "Ixx": inertia[0, 0], "Iyy": inertia[1, 1],
                      "Izz": inertia[2, 2], "Ixy": inertia[0, 1], "Ixz": inertia[0, 2],
                      "Iyz": inertia[1, 2]}
            for kind, i in b.index.items():
                phi[i] = values[kind]
    phi = ca.vertcat(*phi)
    return ca.Function("phi_of_theta", [theta], [phi, ca.jacobian(phi, theta)]), n_theta


def _scales(blocks: list[_Block], prior: np.ndarray) -> np.ndarray:
    """A typical magnitude of every full parameter, from the prior body it belongs to:
    mass ``m0``, first moments ``m0 r0``, inertias ``m0 r0^2`` with ``r0`` the radius of
    gyration about the frame origin; an actuator term its own prior value."""
    scale = np.ones(len(prior))
    for b in blocks:
        if b.kind == "actuator":
            (i,) = b.index.values()
            scale[i] = max(abs(prior[i]), 1e-9)
            continue
        m0 = max(abs(prior[b.index["m"]]), 1e-3)
        if b.kind == "spatial":
            trace = sum(prior[b.index[k]] for k in ("Ixx", "Iyy", "Izz"))
            r0 = np.sqrt(max(trace, 0.0) / (2.0 * m0))
        elif b.kind == "planar":
            r0 = np.sqrt(max(prior[b.index["Izz"]], 0.0) / m0)
        else:
            r0 = 1.0
        r0 = max(r0, 1e-3)
        for kind, i in b.index.items():
            scale[i] = m0 if kind == "m" else m0 * r0 if kind in ("mx", "my", "mz") \
                else m0 * r0 * r0
    return scale


def _upper_cholesky(S: np.ndarray) -> np.ndarray:
    """Upper-triangular ``L`` with ``L L^T = S`` (S positive definite): the lower Cholesky
    factor of S with rows and columns reversed, reversed back."""
    flip = S[::-1, ::-1]
    return np.linalg.cholesky(flip)[::-1, ::-1]


def _theta_of_phi(blocks: list[_Block], phi: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Coordinates of the consistent body nearest ``phi`` in a simple sense: the mass, the
    inertia about the centre of mass (its eigenvalues) and actuator terms clipped to a small
    positive fraction of their scale, the centre of mass kept. Exact inverse of
    :func:`_phi_symbolic` for a consistent ``phi`` clear of the floor."""
    theta = []
    for b in blocks:
        p = {k: float(phi[i]) for k, i in b.index.items()}
        if b.kind == "actuator":
            (i,) = b.index.values()
            theta.append(0.5 * np.log(max(phi[i] / scale[i], 1e-6)))
            continue
        m0, r0 = _body_scale(b, scale)
        m_free = max(p["m"] - MASS_FLOOR_KG, 1e-3 * m0)
        a = 0.5 * np.log(m_free / m0)
        if b.kind == "mass":
            theta.append(a)
        elif b.kind == "planar":
            m = m_free + MASS_FLOOR_KG
            t = np.array([p["mx"], p["my"]]) / m
            izz_c = p["Izz"] - INERTIA_FLOOR_KGM2 - m * float(t @ t)
            izz_c = max(izz_c, 1e-3 * m0 * r0 ** 2)
            theta.extend([a, t[0] / r0, t[1] / r0, 0.5 * np.log(izz_c / (m0 * r0 ** 2))])
        else:
            J = pseudo_inertia([p[k] for k in INERTIAL_NAMES])
            J[:3, :3] -= 0.5 * INERTIA_FLOOR_KGM2 * np.eye(3)
            t = J[:3, 3] / m_free
            # J = e^2a [[L L^T + t t^T, t], [t^T, 1]] with e^2a = m_free
            S = J[:3, :3] / m_free - np.outer(t, t)
            S = 0.5 * (S + S.T)
            w, V = np.linalg.eigh(S)
            S = (V * np.maximum(w, 1e-3 * r0 ** 2)) @ V.T
            L = _upper_cholesky(S) / r0
            t = t / r0
            theta.extend([a, np.log(L[0, 0]), np.log(L[1, 1]), np.log(L[2, 2]), L[0, 1],
                          L[0, 2], L[1, 2], t[0], t[1], t[2]])
    return np.array(theta, float)


# --------------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------------


def _check_inputs(model, W, tau, weights, prior):
    base = model.parameters
    if base.from_full is None:
        raise ModelError(f"physically consistent fit: the {base.kind!r} parameterisation has no "
                         "map from the full parameters; build the model with "
                         "parameterisation='base' (or 'inertial')")
    n_base, n_full = base.from_full.shape
    W = np.asarray(W, float)
    tau = np.asarray(tau, float).reshape(-1)
    if W.ndim != 2 or W.shape[1] != n_base or W.shape[0] != tau.size or tau.size == 0:
        raise ModelError(f"physically consistent fit: expected a regressor of shape (rows, "
                         f"{n_base}) and {W.shape[0] if W.ndim == 2 else 'rows'} torques, got "
                         f"{W.shape} and {tau.shape}")
    w = np.ones(tau.size) if weights is None else np.asarray(weights, float).reshape(-1)
    if w.size != tau.size or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
        raise ModelError(f"physically consistent fit: expected {tau.size} finite non-negative "
                         "row weights, not all zero")
    if not (np.all(np.isfinite(W)) and np.all(np.isfinite(tau))):
        raise ModelError("physically consistent fit: the regressor or the torques hold NaN or "
                         "infinite values (drop those rows first)")
    prior = np.asarray(model.full_parameters.nominal if prior is None else prior, float)
    if prior.shape != (n_full,) or not np.all(np.isfinite(prior)):
        raise ModelError(f"physically consistent fit: prior_full must be {n_full} finite numbers "
                         f"in model.full_parameters order, got shape {prior.shape}")
    return W, tau, w, prior


def physically_consistent_fit(model, W, tau, weights=None, *, prior_full=None) -> PhysicalFit:
    """The weighted least-squares estimate restricted to physically consistent parameters.

    ``model``: the model the regressor was built with (``parameterisation="base"``); ``W``:
    (rows, n_base) stacked base regressor; ``tau``: (rows,) measured efforts; ``weights``:
    (rows,) multiplying each row (``1/sigma``), or None; ``prior_full``: the full parameter
    vector the directions the data do not determine are pulled to (default: the model's
    nominal). Two starts, the prior and the ordinary least-squares estimate (each made
    consistent), are refined and the better kept: deterministic, no random start.

    Raises :class:`~cochlea.errors.ModelError` for inputs of the wrong shape or with NaN, a
    regressor that is all zero, and a result beyond the descriptions' bounds (a consistent
    but absurd body, e.g. a 3 t link that noisy, poorly exciting data asked for).
    """
    W, tau, w, prior = _check_inputs(model, W, tau, weights, prior_full)
    from_full = np.asarray(model.parameters.from_full, float)
    blocks = _blocks(model.full_parameters.names)
    n_full = from_full.shape[1]
    scale = _scales(blocks, prior)

    A = w[:, None] * W
    b = w * tau
    # The data term through a thin QR: ||A beta - b||^2 = ||R beta - Q^T b||^2 + (the part of
    # b outside A's range), so the solver's residual has n_base rows however long the log.
    Q, R = np.linalg.qr(A)
    c = Q.T @ b

    # Scaled full coordinates x = phi / scale: the null space of the data in them.
    A_full = R @ from_full * scale
    _, s, Vt = np.linalg.svd(A_full, full_matrices=True)
    if s.size == 0 or s[0] == 0.0:
        raise ModelError("physically consistent fit: the regressor is zero, nothing was excited")
    rank = int(np.sum(s > RANK_TOLERANCE * s[0]))
    N = Vt[rank:].T  # (n_full, n_null)
    lam = REGULARISATION * s[0] ** 2
    n_data = c.size
    # Rows of the residual: the data, then the regulariser's (weight and centre change over
    # the proximal rounds below, in place).
    G = np.vstack([R @ from_full, np.sqrt(lam) * (N.T / scale)])
    h = np.concatenate([c, np.sqrt(lam) * (N.T @ (prior / scale))])

    phi_of_theta, _ = _phi_symbolic(blocks, n_full, scale)

    # Where the data push a body toward the boundary of the consistent set (a mass or an
    # inertia they want below zero), its logarithmic coordinates would creep toward minus
    # infinity, into subnormal numbers that make each iteration a thousand times slower. A
    # one-sided penalty stops them at LOG_FLOOR (a free part 1e-12 of the body's typical
    # size, far below the floor body): inactive, and without effect, anywhere above it.
    logs = _log_indices(blocks)
    hinge = np.sqrt(lam)

    def residual(theta):
        data = G @ np.asarray(phi_of_theta(theta)[0]).ravel() - h
        return np.concatenate([data, hinge * np.maximum(LOG_FLOOR - theta[logs], 0.0)])

    def jacobian(theta):
        below = np.zeros((logs.size, theta.size))
        active = theta[logs] < LOG_FLOOR
        below[np.flatnonzero(active), logs[active]] = -hinge
        return np.vstack([G @ np.asarray(phi_of_theta(theta)[1]), below])

    # Start 2: the ordinary least-squares estimate, completed in the undetermined directions
    # from the prior (minimum scaled change), then made consistent.
    beta_ols = np.linalg.lstsq(A, b, rcond=None)[0]
    x_change = np.linalg.lstsq(from_full * scale, beta_ols - from_full @ prior, rcond=None)[0]
    phi_ols = prior + scale * x_change

    # The solver sees one coordinate more than theta, whose Jacobian column is zero (see
    # MINPACK_PAD): its step is always zero, and it keeps the solve to the bit whatever the
    # process's memory holds.
    pad_column = np.zeros((G.shape[0] + logs.size, MINPACK_PAD))

    def solve(theta0):
        from scipy.optimize import least_squares  # noqa: PLC0415 (start-up time: see the imports)

        # An overflowing trial step (exp of a large coordinate) is an infinite cost the trust
        # region rejects and shrinks from: not worth a warning.
        with np.errstate(over="ignore", invalid="ignore"):
            result = least_squares(lambda t: residual(t[:-MINPACK_PAD]),
                                   np.concatenate([theta0, np.zeros(MINPACK_PAD)]),
                                   jac=lambda t: np.hstack([jacobian(t[:-MINPACK_PAD]),
                                                            pad_column]),
                                   method="lm", x_scale="jac", ftol=TOL, xtol=TOL, gtol=TOL,
                                   max_nfev=MAX_NFEV)
        result.x = result.x[:-MINPACK_PAD]
        return result

    best = None
    for start in (prior, phi_ols):
        result = solve(_theta_of_phi(blocks, start, scale))
        if best is None or result.cost < best.cost:
            best = result
    iterations = int(best.njev)

    # Proximal rounds: where keeping the undetermined directions at the prior would cost fit
    # (a thin rod's inertia about its axis is not identified, yet bounds the identified one by
    # the triangle inequality), re-centre the regulariser on the current solution and solve
    # again. Each round moves those directions only as far as the data ask, so the base
    # parameters converge to the best consistent fit instead of keeping a bias of order
    # REGULARISATION / (weak singular value)^2.
    typical_base = np.abs(from_full) @ scale
    phi_k = np.asarray(phi_of_theta(best.x)[0]).ravel()
    # An improvement of the fit below this is noise: with noisy data it is a small fraction of
    # the least-squares residual (further rounds would only let the undetermined directions
    # drift for nothing), with exact data a relative 1e-6 of the round's own residual.
    cost_ols = float(np.sum((A @ beta_ols - b) ** 2))
    significant_noise = ROUND_SIGNIFICANCE * cost_ols
    for k in range(1, MAX_PROXIMAL_ROUNDS + 1):
        data_before = float(np.sum(best.fun[:n_data] ** 2))
        if data_before <= 1e-30 * float(c @ c):
            break
        significant = max(significant_noise, 1e-6 * data_before)
        weight = np.sqrt(lam * ROUND_SHRINK ** k)
        G[n_data:] = weight * (N.T / scale)
        h[n_data:] = weight * (N.T @ (phi_k / scale))
        # From the same point made clear of the boundary: there, a coordinate that ran toward
        # minus infinity has lost its gradient and the solver could not bring it back.
        result = solve(_theta_of_phi(blocks, phi_k, scale))
        iterations += int(result.njev)
        phi_next = np.asarray(phi_of_theta(result.x)[0]).ravel()
        moved = np.max(np.abs(from_full @ (phi_next - phi_k)) / typical_base)
        best, phi_k = result, phi_next
        # Settled: the base parameters no longer move (an optimum inside the consistent set,
        # reached), or the fit no longer improves (one on its boundary, crept toward).
        if moved < ROUND_TOLERANCE or \
                data_before - float(np.sum(best.fun[:n_data] ** 2)) <= significant:
            break

    full = np.asarray(phi_of_theta(best.x)[0]).ravel()
    absurd = beyond_description_bounds(model, full)
    if absurd:
        raise ModelError(f"physically consistent fit: the data ask for a body no description "
                         f"can hold ({absurd[0]}); the logs do not determine it: excite the "
                         "robot more (longer, richer trajectories) or keep the ordinary "
                         "least-squares estimate")
    beta = from_full @ full
    cost = float(np.sum((A @ beta - b) ** 2))
    return PhysicalFit(full=full, base=beta, cost=cost, iterations=iterations)
