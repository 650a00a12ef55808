"""Closed-form kinematics of the parallel mechanism in numbers (SI): forward and inverse
kinematics, the mirror rule, the workspace, and the points a drawing needs."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ...errors import KinematicsError
from .description import ParallelJoint, ParallelSystem, Side


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _fmt(point) -> str:
    return "(" + ", ".join(f"{v:.4f}" for v in point) + ") m"


class ParallelGeometry:
    """Closed-form kinematics of the mechanism in numbers (SI), for targets and drawings.

    ``branch`` of a pantograph: its end point C determines the two link directions up to a swap,
    ``{th1, th2} = {psi + delta, psi - delta}`` with ``psi`` the direction of ``C - B`` and
    ``cos(delta) = |C - B| / (2 l_p)``; ``branch = +1`` takes ``th1 = psi + delta`` (so
    ``th1 > th2``), ``-1`` the other. The default is ``+1`` on the left and ``-1`` on the right,
    the mirror image of each other, as in the thesis's configurations (left ``[142, 32.25] deg``,
    right ``[43, 150] deg``).
    """

    def __init__(self, system: ParallelSystem):
        self.system = system
        self.lp = system.link_length
        self.d2 = system.base_offset
        self.d3 = system.rod_length

    # ---- forward ---------------------------------------------------------------------------

    def base(self, side: Side) -> np.ndarray:
        return np.array([side.sign * self.d2, 0.0])

    def _side_q(self, q) -> dict[str, tuple[float, float]]:
        q = np.asarray(q, float).ravel()
        return {"left": (q[0], q[1]), "right": (q[3], q[4])}

    def points(self, q) -> dict[str, np.ndarray]:
        """Named points of the mechanism at q: per side ``B, A1`` (link 1's tip), ``A4`` (link 4's
        tip), ``C``, ``R`` (the rod's free end, ``S + d3 e(phi)``), and ``S``; right-side names
        carry a prime, e.g. ``"C'"``."""
        q = np.asarray(q, float).ravel()
        S = np.array([0.0, q[2]])
        out = {"S": S}
        for side in self.system.sides:
            th1, th2 = self._side_q(q)[side.name]
            mark = "" if side.name == "left" else "'"
            B = self.base(side)
            A1, A4 = B + self.lp * _unit(th1), B + self.lp * _unit(th2)
            C = A1 + self.lp * _unit(th2)
            w = C - S
            out.update({f"B{mark}": B, f"A1{mark}": A1, f"A4{mark}": A4, f"C{mark}": C,
                        f"R{mark}": S + self.d3 * w / max(np.linalg.norm(w), 1e-300)})
        return out

    def fk(self, q) -> np.ndarray:
        """``x_p = [C_u, C_v, phi, C'_u, C'_v, phi']`` (m, m, rad, m, m, rad)."""
        p = self.points(q)
        S = p["S"]
        out = []
        for mark in ("", "'"):
            C = p[f"C{mark}"]
            out += [C[0], C[1], math.atan2(C[1] - S[1], C[0])]
        return np.array(out)

    @staticmethod
    def branches(q) -> tuple[int, int]:
        """The branch of each pantograph at q (see the class docstring)."""
        q = np.asarray(q, float).ravel()
        return (1 if math.sin(q[0] - q[1]) >= 0 else -1, 1 if math.sin(q[3] - q[4]) >= 0 else -1)

    # ---- workspace -------------------------------------------------------------------------

    def violations(self, q) -> list[str]:
        """Why q is outside the workspace (empty when inside): joint limits, and on each side
        ``min_pivot_distance <= |C - S| <= d3`` (the rod must stay in the sleeve, which cannot
        reach the slider's pivot)."""
        q = np.asarray(q, float).ravel()
        problems = []
        for value, joint in zip(q, self.system.joints):
            lo, hi = joint.position_limits
            if not lo <= value <= hi:
                if joint.type == "revolute":
                    problems.append(f"{joint.name} = {math.degrees(value):.3f} deg is outside "
                                    f"[{math.degrees(lo):g}, {math.degrees(hi):g}] deg")
                else:
                    problems.append(f"{joint.name} = {value:.5f} m is outside [{lo:g}, {hi:g}] m")
        p = self.points(q)
        for side, mark in zip(self.system.sides, ("", "'")):
            r = float(np.linalg.norm(p[f"C{mark}"] - p["S"]))
            if not self.system.min_pivot_distance <= r <= self.d3:
                problems.append(f"{side.name}: |C{mark} - S| = {r:.4f} m is outside "
                                f"[{self.system.min_pivot_distance:g}, {self.d3:g}] m")
        return problems

    def in_workspace(self, q) -> bool:
        return not self.violations(q)

    def random_configuration(self, rng: np.random.Generator, tries: int = 10_000) -> np.ndarray:
        """A configuration drawn uniformly from the workspace (rejection sampling in the box of
        joint limits)."""
        lo, hi = np.array([j.position_limits for j in self.system.joints]).T
        for _ in range(tries):
            q = rng.uniform(lo, hi)
            if self.in_workspace(q):
                return q
        raise KinematicsError(f"no configuration in the workspace after {tries} random draws "
                              "within the joint limits: check the description's limits")

    # ---- inverse ---------------------------------------------------------------------------

    def slider_height(self, C, phi: float) -> float:
        """The consistency rule: the slider height ``d1`` for which the rod through ``C`` has
        angle ``phi``, ``d1 = C_v - C_u tan(phi)``.

        Raises :class:`KinematicsError` when no slider height fits: the ray from S at angle
        ``phi`` reaches C only if ``C_u cos(phi) > 0``.
        """
        Cu, Cv = (float(v) for v in np.asarray(C, float).ravel())
        c = math.cos(phi)
        if not (Cu * c > 0.0 and abs(c) > 1e-9):
            raise KinematicsError(
                f"target C = {_fmt((Cu, Cv))}, phi = {math.degrees(phi):.3f} deg is "
                "inconsistent: the rod from the slider (on u = 0) at angle phi reaches C only if "
                "C_u and cos(phi) have the same sign and neither is zero")
        return Cv - Cu * math.tan(phi)

    @staticmethod
    def mirror(C, phi: float) -> tuple[np.ndarray, float]:
        """The mirror rule: the right side's target from the left's, ``C' = (-C_u, C_v)``,
        ``phi' = pi - phi`` (wrapped into (-pi, pi] like the FK's angles)."""
        C = np.asarray(C, float).ravel()
        return np.array([-C[0], C[1]]), math.atan2(math.sin(phi), -math.cos(phi))

    def target(self, C, phi: float) -> np.ndarray:
        """A consistent task-space target ``x_p`` from the left side's ``(C, phi)``, the right
        side by the mirror rule."""
        Cr, phir = self.mirror(C, phi)
        return np.array([*np.asarray(C, float).ravel(), phi, *Cr, phir])

    def _wrap(self, angle: float, joint: ParallelJoint, check: bool) -> float:
        lo, hi = joint.position_limits
        k = math.ceil((lo - angle) / (2 * math.pi) - 1e-12)
        wrapped = angle + 2 * math.pi * k
        if wrapped <= hi + 1e-12:
            return min(max(wrapped, lo), hi) if check else wrapped
        if not check:
            return math.atan2(math.sin(angle), math.cos(angle))
        raise KinematicsError(
            f"{joint.name} = {math.degrees(angle) % 360:.3f} deg (mod 360) needed for this "
            f"target is outside its limits [{math.degrees(lo):g}, {math.degrees(hi):g}] deg")

    def side_ik(self, side: str, C, branch: int | None = None, *,
                check_limits: bool = True) -> tuple[float, float]:
        """Motor angles ``(th1, th2)`` (rad) of one pantograph that put its end point at C (m).

        Raises :class:`KinematicsError` if C is out of reach (``0 < |C - B| <= 2 l_p``) or, with
        ``check_limits``, if the angles fall outside the joint limits.
        """
        if side not in ("left", "right"):
            raise KinematicsError(f"unknown side {side!r}: choose 'left' or 'right'")
        s = self.system.left if side == "left" else self.system.right
        branch = int(s.sign) if branch is None else branch
        if branch not in (1, -1):
            raise KinematicsError(f"branch must be +1 or -1, got {branch!r}")
        C = np.asarray(C, float).ravel()
        if C.shape != (2,) or not np.all(np.isfinite(C)):
            raise KinematicsError(f"target C must be two finite numbers (m), got {C!r}")
        B = self.base(s)
        w = C - B
        r = float(np.hypot(*w))
        reach = 2.0 * self.lp
        if r > reach * (1 + 1e-12) or r < 1e-9 * reach:
            raise KinematicsError(
                f"target C = {_fmt(C)} is out of reach of the {side} pantograph: |C - B| = "
                f"{r:.4f} m from its base B = {_fmt(B)}, but the links reach "
                f"0 < |C - B| <= 2 l_p = {reach:g} m")
        psi = math.atan2(w[1], w[0])
        delta = math.acos(min(1.0, r / reach))
        th1, th2 = psi + branch * delta, psi - branch * delta
        return self._wrap(th1, s.th1, check_limits), self._wrap(th2, s.th2, check_limits)

    def side_ik_symbolic(self, side: str, C, branch: int, offsets=(0.0, 0.0)) -> ca.SX:
        """:meth:`side_ik` as an expression of a symbolic C, on a fixed branch, for desired
        trajectories whose derivatives must be exact. ``offsets`` adds whole turns chosen once.
        Valid only where C is in reach; callers check the trajectory numerically first."""
        s = self.system.left if side == "left" else self.system.right
        B = self.base(s)
        wu, wv = C[0] - B[0], C[1] - B[1]
        psi = ca.atan2(wv, wu)
        delta = ca.acos(ca.sqrt(wu ** 2 + wv ** 2) / (2.0 * self.lp))
        return ca.vertcat(psi + branch * delta + offsets[0], psi - branch * delta + offsets[1])

    def ik(self, x_p, branches: tuple[int, int] | None = None, *, check_limits: bool = True,
           tol: float = 1e-9) -> np.ndarray:
        """Joint coordinates q for a task-space target ``x_p = [C_u, C_v, phi, C'_u, C'_v,
        phi']``.

        The target must be consistent (both sides imply the same slider height, to ``tol`` m;
        build one with :meth:`target`). Raises :class:`KinematicsError`, naming the target and
        the reachable range, when it is inconsistent or outside the workspace (out of reach,
        outside the joint limits or the slider stroke, the rod out of its sleeve); never returns
        NaN.
        """
        x = np.asarray(x_p, float).ravel()
        if x.shape != (6,) or not np.all(np.isfinite(x)):
            raise KinematicsError(f"x_p must be six finite numbers [C_u, C_v, phi, C'_u, C'_v, "
                                  f"phi'] (m, m, rad, ...), got {x_p!r}")
        b_left, b_right = (None, None) if branches is None else branches
        d1 = self.slider_height(x[0:2], x[2])
        d1_right = self.slider_height(x[3:5], x[5])
        if abs(d1 - d1_right) > tol:
            raise KinematicsError(
                f"target x_p is inconsistent: the left side (C = {_fmt(x[0:2])}, phi = "
                f"{math.degrees(x[2]):.3f} deg) needs the slider at d1 = {d1:.6f} m, the right "
                f"side (C' = {_fmt(x[3:5])}, phi' = {math.degrees(x[5]):.3f} deg) at "
                f"{d1_right:.6f} m; see ParallelGeometry.target for the mirror rule")
        lo, hi = self.system.d1.position_limits
        if check_limits and not lo - 1e-12 <= d1 <= hi + 1e-12:
            raise KinematicsError(f"target needs the slider at d1 = {d1:.5f} m, outside its "
                                  f"stroke [{lo:g}, {hi:g}] m")
        th = self.side_ik("left", x[0:2], b_left, check_limits=check_limits)
        th_r = self.side_ik("right", x[3:5], b_right, check_limits=check_limits)
        q = np.array([th[0], th[1], d1, th_r[0], th_r[1]])
        if check_limits:
            r_min = self.system.min_pivot_distance
            for mark, C in (("", x[0:2]), ("'", x[3:5])):
                r = float(np.hypot(C[0], C[1] - d1))
                if not r_min <= r <= self.d3 * (1 + 1e-12):
                    raise KinematicsError(
                        f"target C{mark} = {_fmt(C)} is {r:.4f} m from the slider pivot S = "
                        f"(0, {d1:.4f}) m; the rod reaches {r_min:g} m <= |C - S| <= "
                        f"d3 = {self.d3:g} m")
        return q

    def mirrored(self, q) -> np.ndarray:
        """q with the right side replaced by the mirror rule applied to the left side's pose, on
        the mirror image of the left's branch (joint limits not checked): ``th' = pi - th``."""
        q = np.asarray(q, float).ravel().copy()
        x = self.fk(q)
        Cr, _ = self.mirror(x[0:2], x[2])
        q[3:5] = self.side_ik("right", Cr, -self.branches(q)[0], check_limits=False)
        return q


#: A named configuration: the desired start of the joint-space scenario (thesis 3.67 at t = 0),
#: the right side by the mirror rule ``th' = 180 deg - th``.
SCENARIO_START = np.array([math.radians(142.0), math.radians(32.25), 0.07075,
                           math.radians(180.0 - 142.0), math.radians(180.0 - 32.25)])

