"""The camera refined by the rods: a stage between the rods' measurement and the identification.

The combined method (:func:`calib.identify.combined.calibrate_combined`) treats the intrinsics as nuisance unknowns
with the calibration's covariance as prior; the rods, many and spread over the image, determine them several times
better than the board views did. The rods' measurement itself depends on the camera (which edge points are fitted),
so :func:`calib.vision.extract.extract_dataset` measures the frames again with the refined camera when it moved by
more than a given number of its standard deviations (Mahalanobis).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from calib.errors import I4calError
from calib.formats.camera import CameraModel

if TYPE_CHECKING:
    from calib.identify.result import MethodResult


#: the phases whose rods the refinement uses (the combined fit's poses; the other phases give it their boards)
REFINEMENT_PHASES: tuple[str, ...] = ("poses",)
#: the phases whose board poses give the combined fit its base frame
BASE_FRAME_PHASES: tuple[str, ...] = ("rotation", "translation")


def can_refine(camera: CameraModel) -> bool:
    """Whether the rods can refine this camera: it carries its calibration's covariance.

    Parameters
    ----------
    camera : CameraModel
        The camera the rods were measured with.

    Returns
    -------
    bool
        True when ``camera.extra["calibration"]["covariance"]`` is present.
    """
    return (camera.extra.get("calibration") or {}).get("covariance") is not None


@dataclass
class CameraRefinement:
    """What :func:`refine_camera_by_rods` found.

    Attributes
    ----------
    camera : CameraModel or None
        The refined camera; None when not refined (``info["reason"]`` says why).
    info : dict
        ``applied`` (bool), ``shift`` (per intrinsic: px for fx, fy, cx, cy), ``mahalanobis`` (standard deviations
        of the calibration) or ``reason``; the extraction summary's ``camera.refined_by_rods``.
    fit : MethodResult or None
        The combined fit that refined it (on the observations it was given), when it ran.
    """

    camera: CameraModel | None
    info: dict[str, Any] = field(default_factory=dict)
    fit: MethodResult | None = None

    @property
    def applied(self) -> bool:
        return self.camera is not None


def refine_camera_by_rods(
    observations: dict[str, Any], camera: CameraModel, min_shift: float = 0.5
) -> CameraRefinement:
    """The camera refined by the rods of an extraction's observations, or the reason it is not.

    Parameters
    ----------
    observations : dict
        An observations v1 document measured with ``camera`` (with the rods' limb samples, ``limbs_px``).
    camera : CameraModel
        The camera the rods were measured with; refined only when it carries its calibration's covariance
        (``calibration.covariance``).
    min_shift : float
        The refinement is applied when the intrinsics move by at least this many standard deviations of the
        calibration (Mahalanobis distance).

    Returns
    -------
    CameraRefinement
        The refined camera keeps the calibration's covariance (the combined method's prior when it uses the rods
        again), adds the fit's posterior one (``calibration.covariance_refined``, for the methods that do not use
        the rods), records the shift under ``calibration.refined_by_rods`` and moves the calibration's refined
        board points with the intrinsics (their correlation, ``board_points.d_intrinsics``).
    """
    from calib.camera.intrinsics import intrinsics_names
    from calib.formats.observations import Observations
    from calib.identify.combined import calibrate_combined
    from calib.identify.intrinsics import perturbed_camera

    calib = camera.extra.get("calibration") or {}
    if not can_refine(camera):
        return CameraRefinement(None, {"applied": False, "reason": "the camera has no calibration covariance"})
    try:
        fit = calibrate_combined(Observations.from_dict(_fit_frames(observations)), phases=REFINEMENT_PHASES)
    except I4calError as exc:
        return CameraRefinement(None, {"applied": False, "reason": f"combined fit failed: {exc}"})
    shift = fit.diagnostics.get("intrinsics_refinement")
    if not shift:
        return CameraRefinement(
            None, {"applied": False, "reason": "the observations carry no limb samples (limbs_px)"}, fit
        )
    d = np.array([shift[k] for k in intrinsics_names(camera)])
    m = float(np.sqrt(d @ np.linalg.solve(np.asarray(calib["covariance"], dtype=np.float64), d)))
    info: dict[str, Any] = {"shift": shift, "mahalanobis": m}
    if m < min_shift:
        return CameraRefinement(None, {"applied": False, **info, "reason": f"shift {m:.2f} std < {min_shift}"}, fit)
    moved = perturbed_camera(camera, d)
    new_calib = {**calib, "refined_by_rods": info}
    if fit.diagnostics.get("intrinsics_posterior_covariance") is not None:
        new_calib["covariance_refined"] = fit.diagnostics["intrinsics_posterior_covariance"]
    bp = calib.get("board_points") or {}
    if bp.get("d_intrinsics") is not None:  # the board geometry moves with the intrinsics (their correlation)
        pts = np.asarray(bp["points_m"], dtype=np.float64) + np.asarray(bp["d_intrinsics"], dtype=np.float64) @ d
        new_calib["board_points"] = {**bp, "points_m": pts.tolist()}
    extra = {**camera.extra, "calibration": new_calib}
    return CameraRefinement(
        CameraModel(moved.K, moved.dist, moved.width, moved.height, extra), {"applied": True, **info}, fit
    )


def _fit_frames(observations: dict[str, Any]) -> dict[str, Any]:
    """The observations document with only the frames the refinement's fit reads (the base frame's phases and
    :data:`REFINEMENT_PHASES`): the others' records are not validated for nothing."""
    keep = (*BASE_FRAME_PHASES, *REFINEMENT_PHASES)
    return {**observations, "frames": [f for f in observations["frames"] if f.get("phase") in keep]}
