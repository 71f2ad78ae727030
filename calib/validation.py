"""Validation figures of a parameter set (the paper's Tables II and III).

* Displacement gaps: for consecutive pose pairs, the vision-measured end-effector displacement
  length minus the model-predicted one (DKM of the encoder values), in mm: mean and RMS.
  The end-effector point measured by vision is a board point on the rotation axis (found from the
  rotation phase), so that displacements do not depend on where the board sits on the end-effector.
* Straightness: RMS distance (mm) of the DKM positions of the ``line`` phase to their
  least-squares line.
"""

from __future__ import annotations

import numpy as np

from .baseframe import rotation_axis_point
from .errors import I4calError
from .kinematics import dkm
from .observations import Observations
from .parameters import I4Parameters


def ee_points_from_board(obs: Observations, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera-frame positions of the board point on the end-effector axis, shape (N, 3), metres."""
    rot = obs.arrays("rotation")
    rot = rot.subset(rot.has_board)
    p = rotation_axis_point(rot.board_R, rot.board_t) if len(rot) >= 3 else np.zeros(3)
    return np.einsum("nij,j->ni", R, p) + t


def displacement_gaps(obs: Observations, params: I4Parameters, phases: tuple[str, ...] = ("poses",)) -> dict:
    """Gaps between vision-measured and model-predicted end-effector displacements.

    Returns
    -------
    dict
        ``{"mean_mm", "rms_mm", "max_abs_mm", "n_pairs", "gaps_mm"}``.
    """
    d = obs.arrays(*phases)
    d = d.subset(d.has_board)
    if len(d) < 2:
        return {"mean_mm": None, "rms_mm": None, "max_abs_mm": None, "n_pairs": 0, "gaps_mm": []}
    m = ee_points_from_board(obs, d.board_R, d.board_t)
    P = dkm(params, d.q)[:, :3]
    dm = np.linalg.norm(np.diff(m, axis=0), axis=1)
    dp = np.linalg.norm(np.diff(P, axis=0), axis=1)
    g = (dm - dp) * 1e3
    return {
        "mean_mm": float(g.mean()),
        "rms_mm": float(np.sqrt(np.mean(g**2))),
        "max_abs_mm": float(np.abs(g).max()),
        "n_pairs": int(g.size),
        "gaps_mm": g.tolist(),
    }


def straightness(obs: Observations, params: I4Parameters) -> dict:
    """RMS distance (mm) of the DKM positions of the ``line`` phase to their least-squares line."""
    d = obs.arrays("line")
    if len(d) < 3:
        return {"rms_mm": None, "n": len(d), "length_mm": None}
    P = dkm(params, d.q)[:, :3]
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P - c)
    axis = Vt[0]
    rel = P - c
    dist = np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)
    s = rel @ axis
    return {
        "rms_mm": float(np.sqrt(np.mean(dist**2)) * 1e3),
        "n": len(d),
        "length_mm": float((s.max() - s.min()) * 1e3),
    }


def validate(obs: Observations, params: I4Parameters) -> dict:
    """Both validation figures, on the fit poses and (when present) on separate validation poses."""
    out: dict = {}
    for name, phases in (("poses", ("poses",)), ("validation", ("validation",))):
        try:
            out[f"gaps_{name}"] = displacement_gaps(obs, params, phases)
        except I4calError as exc:
            out[f"gaps_{name}"] = {"error": str(exc)}
    try:
        out["straightness"] = straightness(obs, params)
    except I4calError as exc:
        out["straightness"] = {"error": str(exc)}
    return out
