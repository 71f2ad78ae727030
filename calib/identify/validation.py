"""Validation figures of a parameter set (the paper's Tables II and III).

* Displacement gaps: for consecutive pose pairs, the vision-measured end-effector displacement
  length minus the model-predicted one (DKM of the encoder values), in mm: mean and RMS.
  The end-effector point measured by vision is a board point on the rotation axis (found from the
  rotation phase), so that displacements do not depend on where the board sits on the end-effector.
  Vision's displacements are divided by the translation phase's measured displacement per encoder metre
  (``vision_scale``, :attr:`calib.identify.baseframe.BaseFrameResult.translation_scale`): a board printed 0.2% large, or
  a
  camera whose calibration fixes the board's scale by two of its points, measures every displacement 0.2% long,
  about 0.6 mm on a 300 mm move, which no parameter set should be judged by. The equal-actuator translation moves
  the end-effector by exactly the encoder increment whatever the geometry, so it calibrates vision's scale against
  the encoders.
* Straightness: RMS distance (mm) of the DKM positions of the ``line`` phase to their
  least-squares line.
"""

from __future__ import annotations

import numpy as np

from calib.errors import I4calError
from calib.formats.observations import Observations
from calib.identify.baseframe import BaseFrameResult, base_frame_from_observations, rotation_axis_point
from calib.model.kinematics import dkm
from calib.model.parameters import I4Parameters


def ee_points_from_board(obs: Observations, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera-frame positions of the board point on the end-effector axis, shape (N, 3), metres.

    Parameters
    ----------
    obs : Observations
        The observations; their ``rotation`` phase locates the axis point on the board (origin if fewer than 3).
    R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations of the frames (dimensionless).
    t : ndarray, shape (N, 3)
        ``camera_from_board`` translations, metres.

    Returns
    -------
    ndarray, shape (N, 3)
        The axis point in the camera frame, metres.
    """
    rot = obs.arrays("rotation")
    rot = rot.subset(rot.has_board)
    p = rotation_axis_point(rot.board_R, rot.board_t) if len(rot) >= 3 else np.zeros(3)
    return np.einsum("nij,j->ni", R, p) + t


def displacement_gaps(
    obs: Observations, params: I4Parameters, phases: tuple[str, ...] = ("poses",), vision_scale: float = 1.0
) -> dict:
    """Gaps between vision-measured and model-predicted end-effector displacements.

    Parameters
    ----------
    obs : Observations
        Encoder values (metres) and board poses of the frames.
    params : I4Parameters
        The parameter set judged (metres).
    phases : tuple of str
        The consecutive poses compared.
    vision_scale : float
        Vision's measured displacement per true metre (dimensionless, > 0): its displacements are divided by it.

    Returns
    -------
    dict
        ``{"mean_mm", "rms_mm", "max_abs_mm", "n_pairs", "gaps_mm", "vision_scale"}``.
    """
    if not (np.isfinite(vision_scale) and vision_scale > 0):
        raise ValueError(f"vision_scale must be finite and > 0, got {vision_scale}")
    d = obs.arrays(*phases)
    d = d.subset(d.has_board)
    if len(d) < 2:
        return {
            "mean_mm": None,
            "rms_mm": None,
            "max_abs_mm": None,
            "n_pairs": 0,
            "gaps_mm": [],
            "vision_scale": vision_scale,
        }
    m = ee_points_from_board(obs, d.board_R, d.board_t) / vision_scale
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
        "vision_scale": vision_scale,
    }


def straightness(obs: Observations, params: I4Parameters) -> dict:
    """RMS distance (mm) of the DKM positions of the ``line`` phase to their least-squares line.

    Parameters
    ----------
    obs : Observations
        Encoder values of the ``line`` phase, metres.
    params : I4Parameters
        The parameter set judged (metres).

    Returns
    -------
    dict
        ``{"rms_mm", "n", "length_mm"}``: RMS distance and line length in millimetres (None with fewer than 3
        frames), the frame count.
    """
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


#: a vision scale further than this from 1 is reported with a warning (a board printed or configured wrong, encoders
#: in other units): the twin's boards measure within 0.3%
VISION_SCALE_WARN = 0.005


def vision_scale(obs: Observations, base_frame: BaseFrameResult | None = None) -> dict:
    """Vision's displacement per encoder metre from the translation phase (:mod:`calib.identify.baseframe`).

    Parameters
    ----------
    obs : Observations
        The observations, with their ``translation`` phase.
    base_frame : BaseFrameResult, optional
        The base frame already fitted from ``obs`` (fitted here when not given).

    Returns
    -------
    dict
        ``{"scale", "std", "n_poses", "source"}`` and ``"warning"`` when the scale is more than
        :data:`VISION_SCALE_WARN` from 1; scale 1 (std None) with the reason in ``source`` when the translation
        phase cannot tell (fewer than 3 board poses, or a base frame that cannot be fitted).
    """
    try:
        bf = base_frame if base_frame is not None else base_frame_from_observations(obs)
    except I4calError as exc:
        return {"scale": 1.0, "std": None, "n_poses": 0, "source": f"none ({exc})"}
    if bf.n_translation < 3 or not np.isfinite(bf.translation_scale) or bf.translation_scale <= 0:
        return {"scale": 1.0, "std": None, "n_poses": bf.n_translation, "source": "none (fewer than 3 poses)"}
    out: dict = {
        "scale": float(bf.translation_scale),
        "std": float(bf.translation_scale_std),
        "n_poses": bf.n_translation,
        "source": "translation phase",
    }
    if abs(bf.translation_scale - 1.0) > VISION_SCALE_WARN:
        out["warning"] = (
            f"vision measures the translation phase {(bf.translation_scale - 1.0) * 100:+.2f}% against the encoders "
            f"(beyond {VISION_SCALE_WARN * 100:.1f}%): check the board's square length and the encoders' scale"
        )
    return out


def validate(obs: Observations, params: I4Parameters, scale: dict | None = None) -> dict:
    """Both validation figures, on the fit poses and (when present) on separate validation poses.

    Parameters
    ----------
    obs : Observations
        The observations.
    params : I4Parameters
        The parameter set judged (metres).
    scale : dict, optional
        :func:`vision_scale`'s answer (computed when not given), recorded as ``vision_scale``.

    Returns
    -------
    dict
        ``{"vision_scale", "gaps_poses", "gaps_validation", "straightness"}``: :func:`displacement_gaps` of each
        phase and :func:`straightness` (millimetres), each ``{"error": message}`` when it cannot be computed.
    """
    scale = vision_scale(obs) if scale is None else scale
    out: dict = {"vision_scale": scale}
    for name, phases in (("poses", ("poses",)), ("validation", ("validation",))):
        try:
            out[f"gaps_{name}"] = displacement_gaps(obs, params, phases, vision_scale=scale["scale"])
        except I4calError as exc:
            out[f"gaps_{name}"] = {"error": str(exc)}
    try:
        out["straightness"] = straightness(obs, params)
    except I4calError as exc:
        out["straightness"] = {"error": str(exc)}
    return out


def vision_scale_ppm(scale: dict) -> str:
    """A measured :func:`vision_scale` as "+1234 +/- 56 ppm" (its departure from 1 and its std).

    Parameters
    ----------
    scale : dict
        :func:`vision_scale`'s answer, with a numeric ``std``.

    Returns
    -------
    str
        The departure and its std, parts per million.
    """
    return f"{(scale['scale'] - 1.0) * 1e6:+.0f} +/- {scale['std'] * 1e6:.0f} ppm"
