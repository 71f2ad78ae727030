"""A measured rod re-expressed for another camera, from its edge points, without measuring the image again.

A rod's measurement (:func:`calib.vision.rods.measure.measure_rod`) finds each limb's edge points in the image and
fits a line to them in ideal (undistorted) pixels, where the limb is straight. Which edge points are found does not
depend on the intrinsics within the search band (a few pixels of camera change against an 18 px band), but the ideal
pixels do. So when the camera is refined by the rods (:mod:`calib.vision.refine`), each rod's inlier edge points
(kept in distorted image pixels, :attr:`RodMeasurement.edges_px`) are undistorted with the refined camera, each
limb's total-least-squares line is fitted to them again, and the axis, its covariance and the limb samples follow
as in the measurement (:func:`calib.vision.rods.measure._axes_from_limbs`): the answer a measurement with that camera
gives, for a fraction of its cost.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.formats.camera import CameraModel

from .cylinder import ROD_KEYS, rod_name
from .linefit import _tls
from .measure import _axes_from_limbs, _IdealToImage, _limb_fits, _limb_quality, _RodJob, leg_parallelism
from .types import RodMeasurement, RodPrediction, RodSettings

Array = NDArray[np.float64]


def _ideal(camera: CameraModel, pixels: Array) -> Array:
    """Distorted image pixels (N, 2) -> ideal pixels (N, 2) of ``camera``."""
    return camera.to_ideal_pixels(camera.undistort_points(pixels))


def _limb_fit(pts: Array, inlier_px: float) -> tuple[Array, Array]:
    """The limb's line through its edge points (ideal px of the new camera) with the measurement's last rejection
    (:func:`calib.vision.rods.linefit.robust_line`: beyond 3 robust std of the residuals, at least 0.3 px, the line
    fitted again): in the new camera's straighter (or more bent) image of the limb, the points its line no longer
    fits are dropped as a measurement with that camera drops them. Returns the points kept and the line."""
    line = np.array(_tls(pts))
    r = np.abs(pts @ line[:2] + line[2])
    near = r < 3.0 * inlier_px
    cut = max(3.0 * 1.4826 * float(np.median(r[near])) if near.any() else inlier_px, 0.3)
    keep = r < cut
    if np.count_nonzero(keep) >= 2 and not keep.all():
        pts = pts[keep]
        line = np.array(_tls(pts))
    return pts, line


def reexpress_rod(
    measured: RodMeasurement,
    camera: CameraModel,
    radius: float,
    settings: RodSettings | None = None,
    projector: _IdealToImage | None = None,
) -> RodMeasurement:
    """A measured rod's axis for ``camera``, from its edge points.

    Parameters
    ----------
    measured : RodMeasurement
        A rod measured with another camera, with its edge points (``edges_px``, ``middle_px``, distorted px) and
        its axis direction ``u`` (camera frame; the re-expressed axis is oriented the same way).
    camera : CameraModel
        The camera to express it for.
    radius : float
        Rod radius (m).
    settings : RodSettings, optional
        Default ``RodSettings()`` (``max_rms_px``, ``min_points``, ``min_plane_angle_rad``, the edge-bias allowance).
    projector : _IdealToImage, optional
        Ideal to image pixels of ``camera``, when already built for the frame.

    Returns
    -------
    RodMeasurement
        ``u``, ``point``, ``h``, ``cov_u``, ``cov_u_own``, ``limbs_px``, quality figures for ``camera`` and the same
        edge points; or ``reason`` when the limbs no longer make an axis (their residual beyond ``max_rms_px``,
        nearly parallel planes).

    Raises
    ------
    ValueError
        ``measured`` carries no edge points or no direction.
    """
    if measured.edges_px is None or measured.middle_px is None or measured.u is None:
        raise ValueError(f"rod {rod_name(measured.leg, measured.rod)} has no edge points to re-express")
    s = settings or RodSettings()
    proj = projector if projector is not None else _IdealToImage(camera)
    out = RodMeasurement(measured.leg, measured.rod, polarity=measured.polarity)
    out.pairs_by_polarity = measured.pairs_by_polarity
    out.edges_px, out.middle_px = measured.edges_px, measured.middle_px
    limbs = [_limb_fit(_ideal(camera, raw), s.inlier_px) for raw in measured.edges_px]
    fits = _limb_fits([limbs])[0]
    out.reason = _limb_quality(out, fits, s)
    if out.reason is not None:
        return out
    middle = _ideal(camera, measured.middle_px[None])
    # the direction only orients the axis (u . pred.u > 0): a prediction along the measured axis
    pred = RodPrediction(measured.leg, measured.rod, np.zeros(3), np.asarray(measured.u, dtype=np.float64))
    pts = (limbs[0][0], limbs[1][0])
    _axes_from_limbs([_RodJob(out, pred, middle, fits.lines[0][:2], pts, fits)], camera, radius, s, proj, edges=False)
    return out


def reexpress_frame(
    result: dict[str, Any], camera: CameraModel, radius: float, settings: RodSettings | None = None
) -> dict[str, Any]:
    """A frame's rods stage result re-expressed for ``camera`` (:func:`reexpress_rod` on each rod with edge points).

    Parameters
    ----------
    result : dict
        The rods stage's result of the frame (:func:`calib.vision.pool.rods_result`): ``{"rods": {name: dict |
        reason}, "parallel_mrad": {...}, "edges": {name: (limb 0 (N0, 2), limb 1 (N1, 2), middle (2,))}}`` (edges in
        distorted px; lists as read back from JSON are taken too).
    camera : CameraModel
    radius : float
        Rod radius (m).
    settings : RodSettings, optional

    Returns
    -------
    dict
        The same layout for ``camera``: a rod without edge points keeps its entry (its reason when not measured); a
        rod whose limbs no longer make an axis gets the reason; ``edges`` kept for a later re-expression.
    """
    proj = _IdealToImage(camera)
    edges = result.get("edges") or {}
    out_rods: dict[str, Any] = {}
    again: list[RodMeasurement] = []
    for leg, rod in ROD_KEYS:
        name = rod_name(leg, rod)
        entry = result["rods"][name]
        e = edges.get(name)
        if e is None or not isinstance(entry, dict):
            out_rods[name] = entry
            continue
        m = RodMeasurement(leg, rod, u=np.asarray(entry["u"], dtype=np.float64))
        m.edges_px = (np.asarray(e[0], dtype=np.float64), np.asarray(e[1], dtype=np.float64))
        m.middle_px = np.asarray(e[2], dtype=np.float64)
        r = reexpress_rod(m, camera, radius, settings, proj)
        out_rods[name] = r.to_dict() if r.ok else r.reason
        if r.ok:
            again.append(r)
    par = {k: v * 1e3 for k, v in leg_parallelism(again).items()}
    kept = {n: e for n, e in edges.items() if isinstance(out_rods.get(n), dict)}
    return {"rods": out_rods, "parallel_mrad": par, "edges": kept}
