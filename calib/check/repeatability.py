"""Repeatability and the measurement floor from revisited poses (``i4cal check --repeat N``, docs/check.md).

A check with ``--repeat N`` visits each fit pose ``N`` times (the first visit in the ``poses`` phase, the others in
``validation`` steps after a tour of the other poses) and, on the first revisit, takes a second frame without
moving. The board's position measured by the camera (``camera_from_board`` ``t``, metres) then gives:

* the **measurement floor**: the spread of two frames with no motion between them (the camera, the board pose's
  extraction): ``var = mean |t_2 - t_1|^2 / 2`` (a 3-D RMS);
* the **repeatability**: the spread of the revisits of each pose about their mean, with ``n - 1`` degrees of freedom
  per pose (3-D RMS), the floor included;
* the **robot's repeatability**: ``sqrt(repeatability^2 - floor^2)`` (0 when the floor explains it all);
* **outliers**: a revisit whose deviation from the mean of its pose's other visits passes the chi-square gate (3
  degrees of freedom, probability ``1e-3``) against a robust scale (the deviations' median), flagged one at a time,
  the worst first, and left out of the repeatability (poses visited at least 3 times).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from calib.errors import InputError

Array = NDArray[np.float64]

#: the probability with which a revisit of an unchanged robot is flagged as an outlier
OUTLIER_PROBABILITY = 1e-3

__all__ = ["OUTLIER_PROBABILITY", "Repeatability", "repeat_groups", "repeatability"]


@dataclass
class Repeatability:
    """What revisiting the poses showed (metres, 3-D RMS of one frame's position).

    Attributes
    ----------
    poses : int
        Poses revisited at least twice.
    visits : int
        Visits in all (frames of the revisit statistics).
    repeatability_m : float or None
        Spread of the revisits about each pose's mean (floor included); None with no pose visited twice.
    floor_m : float or None
        Spread of two frames with no motion between them; None with no such pair.
    robot_m : float or None
        ``sqrt(repeatability^2 - floor^2)``, 0 when negative; None when either is missing.
    outliers : list of dict
        ``{"pose", "frame", "deviation_m"}`` per flagged revisit (``frame``: the index given).
    """

    poses: int
    visits: int
    repeatability_m: float | None
    floor_m: float | None
    robot_m: float | None
    outliers: list[dict[str, float | int]] = field(default_factory=list)

    def to_dict(self) -> dict[str, object]:
        return {
            "poses": self.poses,
            "visits": self.visits,
            "repeatability_m": self.repeatability_m,
            "measurement_floor_m": self.floor_m,
            "robot_repeatability_m": self.robot_m,
            "outliers": self.outliers,
        }


def repeat_groups(q: Array, poses_q: Array, tol_m: float = 1e-4) -> NDArray[np.int64]:
    """Which commanded pose each frame was taken at: the index in ``poses_q`` (k, 4) of the nearest joint vector to
    each frame's encoders ``q`` (n, 4), metres, or -1 when none is within ``tol_m`` in every joint.

    Parameters
    ----------
    q : ndarray, shape (n, 4)
        Encoder values of the frames, metres.
    poses_q : ndarray, shape (k, 4)
        Commanded joint vectors, metres.
    tol_m : float, optional
        Largest per-joint distance to the nearest pose, metres (0.1 mm by default).

    Returns
    -------
    ndarray of int, shape (n,)
        Index into ``poses_q`` per frame, -1 for none.
    """
    q = np.asarray(q, dtype=np.float64)
    poses_q = np.asarray(poses_q, dtype=np.float64)
    d = np.abs(q[:, None, :] - poses_q[None, :, :]).max(axis=2)
    idx = d.argmin(axis=1)
    return np.where(d[np.arange(len(q)), idx] <= tol_m, idx, -1)


def repeatability(
    t: Array, group: NDArray[np.int64], still: NDArray[np.bool_], frame: NDArray[np.int64]
) -> Repeatability:
    """Repeatability, floor and outliers from the board positions of revisited poses.

    Parameters
    ----------
    t : ndarray, shape (n, 3)
        Board positions (camera frame), metres.
    group : ndarray of int, shape (n,)
        The pose each frame was taken at (-1: none; left out).
    still : ndarray of bool, shape (n,)
        True for the second frame of a pair taken without moving; it pairs with the frame before it (same group).
    frame : ndarray of int, shape (n,)
        Each frame's index, to name the outliers.

    Returns
    -------
    Repeatability
    """
    t = np.asarray(t, dtype=np.float64)
    group = np.asarray(group)
    still = np.asarray(still, dtype=bool)
    if t.ndim != 2 or t.shape[1] != 3 or len(group) != len(t) or len(still) != len(t) or len(frame) != len(t):
        raise InputError("t (n, 3), group, still and frame (n,) must agree", field="repeatability")
    pairs = [i for i in range(1, len(t)) if still[i] and group[i] >= 0 and group[i - 1] == group[i]]
    floor = None
    if pairs:
        d = np.array([t[i] - t[i - 1] for i in pairs])
        floor = float(np.sqrt(np.mean(np.sum(d * d, axis=1)) / 2.0))
    moved = (~still) & (group >= 0)
    outliers = _outliers(t, group, moved, frame)
    kept = moved.copy()
    for o in outliers:
        kept[int(o.pop("_row"))] = False
    ss, dof, poses = 0.0, 0, 0
    for g in np.unique(group[kept]):
        idx = np.flatnonzero(kept & (group == g))
        if len(idx) < 2:
            continue
        poses += 1
        dev = t[idx] - t[idx].mean(axis=0)
        ss += float(np.sum(dev * dev))
        dof += len(idx) - 1
    rep = float(np.sqrt(ss / dof)) if dof else None
    robot = None if rep is None or floor is None else float(np.sqrt(max(rep * rep - floor * floor, 0.0)))
    visits = int(kept.sum()) if dof else 0
    return Repeatability(poses, visits, rep, floor, robot, outliers)


#: the median of a chi-square variable with 3 degrees of freedom
_CHI2_3_MEDIAN = float(chi2.median(3))


def _outliers(t: Array, group: NDArray, moved: NDArray[np.bool_], frame: NDArray) -> list[dict]:
    """Revisits flagged one at a time, the worst first: its deviation from the mean of its pose's other visits (leave
    one out, variance ``s^2 n / (n - 1)`` per axis), gated at :data:`OUTLIER_PROBABILITY` against a robust per-axis
    scale ``s`` (the median of those deviations, chi-square with 3 degrees of freedom)."""
    live = moved.copy()

    def loo() -> tuple[NDArray, NDArray, NDArray]:
        rows, m2, dist = [], [], []
        for g in np.unique(group[live]):
            idx = np.flatnonzero(live & (group == g))
            n = len(idx)
            if n < 3:  # two visits: which one is off cannot be told
                continue
            total = t[idx].sum(axis=0)
            for i in idx:
                e = t[i] - (total - t[i]) / (n - 1)
                rows.append(i)
                m2.append(float(e @ e) * (n - 1) / n)
                dist.append(float(np.linalg.norm(e)))
        return np.array(rows, dtype=np.int64), np.array(m2), np.array(dist)

    rows, m2, dist = loo()
    if not len(rows):
        return []
    s2 = float(np.median(m2)) / _CHI2_3_MEDIAN  # per-axis variance of one visit
    if s2 <= 1e-18:  # below a nanometre: identical frames (a simulator's), nothing to flag
        return []
    gate = float(chi2.isf(OUTLIER_PROBABILITY, 3))
    out: list[dict] = []
    while len(rows):
        k = int(np.argmax(m2))
        if m2[k] / s2 <= gate:
            break
        i = int(rows[k])
        out.append({"pose": int(group[i]), "frame": int(frame[i]), "deviation_m": float(dist[k]), "_row": i})
        live[i] = False
        rows, m2, dist = loo()
    return out
