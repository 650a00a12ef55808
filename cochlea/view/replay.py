"""A run folder's log as the frames of a 3-D replay (SI: m, s), decimated for a browser.

What a replay holds (``build_replay``; ``cochlea-view`` puts it in its page as JSON):

* ``times``: the kept rows' ``time_s`` (s): the first row, then the first row at or after
  every ``1 / rate`` step (50 Hz, or lower for a run longer than :data:`MAX_FRAMES` / 50 Hz =
  10 min: ``rate_hz`` says which), and the last row;
* per unit, ``frames``: every body frame's origin (m, world frame) at the measured ``q`` of
  each kept row, by the robot's own kinematics (``RobotAdapter.link_frames``, composed along
  ``parents``); ``null`` for a row whose ``q`` is not finite; ``edges``: the links drawn, pairs
  of frame indices (a frame and its parent frame; in a closed chain, whose frames all sit in
  the world, a frame and the nearest other frame on its x axis, found at the first pose);
* per unit, ``tools``: the actual and desired tool points (m, world frame) per kept row: a
  unit with ``UNIT/tool`` frames (a serial arm) takes their origin at ``q`` (actual) and at the
  desired joints (joint space), or the desired task point (task space: its u, v, and z where
  the task has one, else the actual tool's z); a unit without (the parallel mechanism, whose
  plane is the world's x-y plane) takes its tool points of ``fk_world`` at ``q`` and at the
  desired joints, or of the desired task pose, at z = 0;
* ``keep_out``: the description's keep-out spheres (``[[keep_out]]``), or else the
  supervisor's keep-out circle of radius ``keep_out_radius_m`` around the unit's centre in the
  world's x-y plane (the parallel mechanism's follows its slider, S = (0, d1));
* ``stop``: the supervisor's stop of a real-time run (``summary.json``'s ``stop``) or the
  verdict of an as-fast run (``supervisor``) when a rule stopped or would have stopped it:
  rule, time (s), detail.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import CochleaError
from ..export.run_log import COMPILED_IN, RunFolderError, RunLog
from ..sim.scenario import load as load_scenario

#: Rows kept per second of run (Hz).
DEFAULT_RATE_HZ = 50.0
#: At most about this many rows are kept: a longer run is kept at a lower rate (a 1 h run at
#: 8 Hz), so the page stays a few megabytes per unit.
MAX_FRAMES = 30_000
#: Positions are rounded to this many decimals of a metre (0.1 um) in the page.
DECIMALS = 7
#: Rules of ``stop`` that are not a supervisor's stop.
CLEAN_STOPS = ("completed", "user-stop", "none")


#: Beyond this magnitude a float64 has no decimals to round (and rounding it to DECIMALS
#: overflows: np.round(1e305, 7) is inf).
NO_DECIMALS = 2.0**53


def _round(a) -> list | float | None:
    """``a`` as nested lists rounded to :data:`DECIMALS`, non-finite values as None (strict
    JSON has no infinity); a finite value too large to round (1e305 in a cell) as it is."""
    a = np.asarray(a, float)
    if a.ndim == 0:
        if not math.isfinite(a):
            return None
        return float(a) if abs(a) >= NO_DECIMALS else float(np.round(a, DECIMALS))
    return [_round(x) for x in a]


def decimate(run: RunLog, rate_hz: float) -> np.ndarray:
    """The kept rows of ``run``'s log (read chunk by chunk, so the whole log is checked):
    the first, the first at or after each ``1 / rate_hz`` step, and the last."""
    kept, step, next_t, last = [], 1.0 / rate_hz, -math.inf, None
    for rows in run.chunks():
        for row in rows:
            if row[0] >= next_t - 1e-12:
                kept.append(row)
                next_t = row[0] + step
                last = None
            else:
                last = row
    if last is not None:
        kept.append(last)
    return np.array(kept)


def world_frames(function, names, parents, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, p)``: every frame's rotation ``(n, k, 3, 3)`` and origin ``(n, k, 3)`` in the world
    at the ``n`` joint positions ``q`` (``(n, joints)``), composing each frame with its
    parent's."""
    n, k = len(q), len(names)
    values = np.array(function.map(n)(q.T)).reshape(12, n, k)
    R_local = values[:9].reshape(3, 3, n, k).transpose(2, 3, 1, 0)  # column-major entries
    p_local = values[9:].transpose(1, 2, 0)
    R, p = np.empty_like(R_local), np.empty_like(p_local)
    index = {name: i for i, name in enumerate(names)}
    for i, parent in enumerate(parents):
        if parent == "world":
            R[:, i], p[:, i] = R_local[:, i], p_local[:, i]
        else:
            j = index[parent]  # an earlier frame of the list (LinkFrames)
            R[:, i] = R[:, j] @ R_local[:, i]
            p[:, i] = p[:, j] + np.einsum("nab,nb->na", R[:, j], p_local[:, i])
    return R, p


def link_edges(names, parents, R: np.ndarray, p: np.ndarray) -> list[list[int]]:
    """The links to draw, as pairs of frame indices, from one pose (``R (k, 3, 3)``,
    ``p (k, 3)``): each frame to its parent; a world frame with no child frame (a closed chain's
    body) to the nearest other frame origin on its positive x axis, if any."""
    index = {name: i for i, name in enumerate(names)}
    edges = [[index[par], i] for i, par in enumerate(parents) if par != "world"]
    has_child = {index[par] for par in parents if par != "world"}
    for i, par in enumerate(parents):
        if par != "world" or i in has_child:
            continue
        axis, best = R[i][:, 0], None
        for j in range(len(names)):
            d = p[j] - p[i]
            dist = float(np.linalg.norm(d))
            if j == i or dist < 1e-9:
                continue
            if float(d @ axis) > dist * (1 - 1e-9) and (best is None or dist < best[0]):
                best = (dist, j)
        if best is not None:
            edges.append([i, best[1]])
    return edges


def _scenario(run: RunLog):
    source = run.summary["scenario_file"]
    if source.startswith(COMPILED_IN) and isinstance(run.summary.get("scenario"), str):
        source = run.summary["scenario"]
    try:
        return load_scenario(source)
    except CochleaError as exc:  # open_run loaded it a moment ago
        raise RunFolderError(f"{run.folder}: its scenario cannot be loaded: {exc}") from None


def _number(v) -> float | None:
    """A summary's number as a finite float, or None (a damaged field: text, NaN, an integer
    no float holds)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        v = float(v)
    except OverflowError:
        return None
    return v if math.isfinite(v) else None


def _text(v) -> str | None:
    return v if isinstance(v, str) else None


def _stop(summary: dict) -> dict | None:
    for key, kind in (("stop", "stopped"), ("supervisor", "would have stopped")):
        entry = summary.get(key)
        if isinstance(entry, dict) and isinstance(entry.get("rule"), str) \
                and entry["rule"] not in CLEAN_STOPS:
            return {"rule": entry["rule"], "kind": kind,
                    "time_s": _number(entry.get("time_s")),
                    "detail": str(entry.get("detail", ""))}
    return None


def build_replay(run: RunLog, rate_hz: float = DEFAULT_RATE_HZ) -> dict:
    """The replay of ``run`` (see the module's docstring): a JSON-able dict."""
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise CochleaError(f"the replay rate must be a positive number of Hz, not {rate_hz}")
    duration = _number(run.summary.get("duration_s"))
    if duration is not None and duration > 0:
        rate_hz = min(rate_hz, MAX_FRAMES / duration)
    rows = decimate(run, rate_hz)
    scenario = _scenario(run)
    plans = {p.name: p for p in run.adapter.unit_plans(run.system, scenario)}
    units, keep_out = [], []
    for unit in run.units:
        frames = run.adapter.link_frames(run.system, unit.name)
        q = rows[:, unit.groups["q"].columns]
        finite = np.isfinite(q).all(axis=1)
        R, p = world_frames(frames.function, frames.names, frames.parents,
                            np.where(finite[:, None], q, 0.0))
        first = int(np.argmax(finite)) if finite.any() else 0
        edges = link_edges(frames.names, frames.parents, R[first], p[first])
        plan = plans[unit.name]
        actual, desired = tool_paths(run, unit, plan, frames, rows, p, finite)
        positions = [None if not finite[r] else _round(p[r]) for r in range(len(rows))]
        units.append({"name": unit.name, "frame_names": list(frames.names), "edges": edges,
                      "frames": positions, "tool_names": [t[0] for t in plan.tool_points],
                      "actual": actual, "desired": desired})
        keep_out += [r for r in keep_out_regions(run, unit, plan, rows) if r not in keep_out]
    return {"robot": run.adapter.name, "description": getattr(run.system, "name", ""),
            "scenario": _text(run.summary.get("scenario")),
            "space": _text(run.summary.get("space")),
            "controller": _text(run.summary.get("controller")), "rate_hz": rate_hz,
            "periods": _number(run.summary.get("periods")),
            "times": [float(t) for t in rows[:, 0]], "units": units, "keep_out": keep_out,
            "stop": _stop(run.summary)}


def tool_paths(run: RunLog, unit, plan, frames, rows: np.ndarray, p: np.ndarray,
               finite: np.ndarray) -> tuple[list, list | None]:
    """Per tool, the actual and desired points (``(n, 3)`` lists, m, world frame)."""
    g = unit.groups
    joints = g["q"].elements
    desired = g.get("desired")
    tool_frames = [i for i, name in enumerate(frames.names) if name.endswith("/tool")]
    n_tools = len(plan.tool_points)
    fk = plan.fk_world.map(len(rows))

    def planar(pose: np.ndarray, z: np.ndarray) -> list:
        return [np.column_stack([pose[:, u], pose[:, v], z]) for _, (u, v) in plan.tool_points]

    if tool_frames and len(tool_frames) == n_tools:
        actual = [p[:, i] for i in tool_frames]
    else:
        pose = np.array(fk(np.where(finite[:, None], rows[:, g["q"].columns], 0.0).T)).T
        actual = planar(pose, np.zeros(len(rows)))
    actual = [np.where(finite[:, None], a, np.nan) for a in actual]
    wanted = None
    if desired is not None and desired.elements == joints:  # joint space: the desired joints
        qd = rows[:, desired.columns]
        ok = np.isfinite(qd).all(axis=1)
        qd = np.where(ok[:, None], qd, 0.0)
        if tool_frames and len(tool_frames) == n_tools:
            _, pd = world_frames(frames.function, frames.names, frames.parents, qd)
            wanted = [pd[:, i] for i in tool_frames]
        else:
            wanted = planar(np.array(fk(qd.T)).T, np.zeros(len(rows)))
        wanted = [np.where(ok[:, None], w, np.nan) for w in wanted]
    elif desired is not None and len(desired.columns) == len(plan.task_names):  # task space
        pose = rows[:, desired.columns]
        wanted = []
        for k, (_, (u, v)) in enumerate(plan.tool_points):
            if "z" in plan.task_names:
                z = pose[:, plan.task_names.index("z")]
            elif tool_frames and len(tool_frames) == n_tools:
                z = actual[k][:, 2]
            else:
                z = np.zeros(len(rows))
            wanted.append(np.column_stack([pose[:, u], pose[:, v], z]))
    return ([_round(a) for a in actual],
            None if wanted is None else [_round(w) for w in wanted])


def keep_out_regions(run: RunLog, unit, plan, rows: np.ndarray) -> list[dict]:
    """The unit's keep-out region: the description's spheres, or the keep-out circle (whose
    centre moves with a joint where the robot's plan says so: ``plan.keep_out_centre``)."""
    volumes = getattr(run.system, "keep_out_volumes", None)
    if volumes is not None:
        if unit is not run.units[0]:  # the system's spheres, once
            return []
        return [{"kind": "sphere", "name": v.name, "radius": float(v.radius),
                 "centre": _round(np.asarray(v.centre, float)), "moving": None}
                for v in volumes]
    radius = float(getattr(run.system, "keep_out_radius", 0.0) or 0.0)
    if radius <= 0:
        return []
    # The supervisor's own rule (the robot adapter's): a centre that rides on a joint is a
    # column, drawn frame by frame ("moving" replaces the centre's v).
    u, v = plan.keep_out_centre(rows[:, unit.groups["q"].columns])
    moving = None if np.ndim(v) == 0 else _round(v)
    centre = [float(u), 0.0 if moving is not None else float(v), 0.0]
    region = {"kind": "circle", "name": "keep-out", "radius": radius,
              "centre": centre, "moving": moving}
    return [region]
