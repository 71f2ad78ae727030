"""Motion time of a plan: trapezoidal velocity profiles per axis, and a cheap tour of the fit poses.

Each move starts every axis at once; an axis travelling ``d`` metres at top speed ``v`` (m/s) and
acceleration ``a`` (m/s^2) takes ``d/v + v/a`` when it reaches its top speed (``d > v^2/a``), else
``2 sqrt(d/a)`` (triangular profile); the move lasts as long as its slowest axis, then the bench settles
(``settle_s``) and grabs (``frame_s``). A guided line is followed at its rate (``samples / rate_hz``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.errors import InputError
from calib.formats.plan import Plan, line_poses
from calib.model.parameters import I4Parameters

__all__ = ["MotionSpec", "move_time", "order_tour", "plan_motion_time"]


@dataclass(frozen=True)
class MotionSpec:
    """The bench's motion figures (a bench file's ``[actuators]`` speed and acceleration)."""

    speed_m_s: float = 0.05
    accel_m_s2: float = 0.5
    settle_s: float = 0.0  #: after every move (actuators' and acquisition's settle times)
    frame_s: float = 0.0  #: grab and write per frame
    start_q: tuple[float, float, float, float] | None = None  #: where the bench starts (default: the first step)
    line_rate_hz: float | None = None  #: overrides a guided line's sampling rate (a bench's acquisition setting)

    def __post_init__(self) -> None:
        if not (self.speed_m_s > 0 and self.accel_m_s2 > 0 and np.isfinite(self.speed_m_s + self.accel_m_s2)):
            raise InputError("motion: speed and acceleration must be finite and > 0", field="speed_m_s")
        if self.settle_s < 0 or self.frame_s < 0:
            raise InputError("motion: settle and frame times must be >= 0", field="settle_s")


def move_time(q_from: np.ndarray, q_to: np.ndarray, spec: MotionSpec) -> np.ndarray:
    """Duration (s) of moves between joint vectors, trapezoidal profile per axis, slowest axis.

    Parameters
    ----------
    q_from, q_to : ndarray, shape (..., 4)
        Joint values, metres (broadcast against each other).
    spec : MotionSpec
        Speed (m/s) and acceleration (m/s^2) of the axes.

    Returns
    -------
    ndarray, shape (...)
        Move durations, seconds.
    """
    d = np.abs(np.asarray(q_to, dtype=np.float64) - np.asarray(q_from, dtype=np.float64))
    v, a = spec.speed_m_s, spec.accel_m_s2
    t = np.where(d > v * v / a, d / v + v / a, 2.0 * np.sqrt(d / a))
    return t.max(axis=-1)


def order_tour(q: np.ndarray, spec: MotionSpec, start: np.ndarray | None = None) -> np.ndarray:
    """Visiting order of poses: nearest neighbour in move time from ``start``, then 2-opt.

    Parameters
    ----------
    q : ndarray, shape (N, 4)
        The poses' joint values, m.
    spec : MotionSpec
        Speeds, accelerations (the move times).
    start : ndarray, shape (4,), optional
        Where the bench is before the first pose, m (None: anywhere, the tour starting at any pose).

    Returns
    -------
    ndarray of int, shape (N,)
        Indices into ``q`` in visiting order.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    n = len(q)
    if n <= 2:
        return np.arange(n)
    D = move_time(q[:, None, :], q[None, :, :], spec)
    d0 = move_time(np.asarray(start, dtype=np.float64), q, spec) if start is not None else np.zeros(n)
    order = [int(np.argmin(d0))]
    left = set(range(n)) - set(order)
    while left:
        last = order[-1]
        nxt = min(left, key=lambda j: D[last, j])
        order.append(nxt)
        left.remove(nxt)
    route = np.array(order)

    def cost(r: np.ndarray) -> float:
        return float(d0[r[0]] + D[r[:-1], r[1:]].sum())

    best = cost(route)
    improved = True
    while improved:
        improved = False
        for i in range(0, n - 1):
            for j in range(i + 1, n):
                cand = np.concatenate([route[:i], route[i : j + 1][::-1], route[j + 1 :]])
                c = cost(cand)
                if c < best - 1e-12:
                    route, best, improved = cand, c, True
    return route


def plan_motion_time(plan: Plan, spec: MotionSpec, nominal: I4Parameters | None = None) -> dict[str, Any]:
    """Motion time of a plan executed in its order, per phase and in total.

    Parameters
    ----------
    plan : Plan
        The steps, in their order.
    spec : MotionSpec
        Speeds (m/s), accelerations (m/s^2), settle and frame times (s), the line's rate (Hz).
    nominal : I4Parameters, optional
        The nominal geometry: a guided line's poses turned into joint values for the move to its start (needed when
        the plan has a line).

    Returns
    -------
    dict
        ``{"total_s": float, "per_phase_s": {phase: float}}``, seconds.
    """
    from calib.model.kinematics import ikm

    per: dict[str, float] = {}
    cur = None if spec.start_q is None else np.asarray(spec.start_q, dtype=np.float64)
    for step in plan.steps:
        if step.line is not None:
            if nominal is None:
                raise InputError("the motion time of a guided line needs the nominal geometry", field="line")
            qs = ikm(nominal, line_poses(step.line))
            t = (0.0 if cur is None else float(move_time(cur, qs[0], spec))) + step.line.samples / (
                spec.line_rate_hz or step.line.rate_hz
            )
            cur = qs[-1]
        elif step.q is not None:
            q = np.asarray(step.q, dtype=np.float64)
            t = (0.0 if cur is None else float(move_time(cur, q, spec))) + spec.settle_s + spec.frame_s
            cur = q
        else:
            continue
        per[step.phase] = per.get(step.phase, 0.0) + t
    return {"total_s": float(sum(per.values())), "per_phase_s": per}
