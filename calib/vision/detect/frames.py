"""Detection's decision and use: ``detect_rods`` on one frame, the priors it hands to ``measure_rod``, the frames'
consensus placement (``resolve_frames``) and ``measure_detected``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.errors import I4calError
from calib.formats.camera import CameraModel
from calib.model.kinematics import dkm
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import Rigid
from calib.vision.detect.association import _differences, associate
from calib.vision.detect.candidates import find_legs, find_rods
from calib.vision.detect.hypotheses import DetectSettings, Hypothesis, LegCandidate, RodCandidate, RodDetection
from calib.vision.detect.rays import _rotation_angle
from calib.vision.detect.segments import detect_segments, merge_lines, merge_segments, refine_lines, undistorted_canvas
from calib.vision.rods import ROD_KEYS, RodMeasurement, RodPrediction, RodSettings, measure_rods, predict_rods, rod_name

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
def detect_rods(
    image: np.ndarray,
    camera: CameraModel,
    nominal: I4Parameters,
    q: ArrayLike,
    rod_radius_m: float,
    rod_spacing_m: float | None,
    settings: DetectSettings | None = None,
    prior: Rigid | None = None,
) -> RodDetection:
    """Find the eight rods in one frame with no prior pose and associate them to the legs.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The (distorted) image, 8-bit or float, single channel (BGR is converted).
    camera : CameraModel
        Intrinsics (the detection works in its ideal pixels).
    nominal : I4Parameters
        The nominal geometry.
    q : array_like, shape (4,)
        Encoder values, metres.
    rod_radius_m, rod_spacing_m : float
        Rod radius and distance between the two rods of a leg (along x_B), metres.
    settings : DetectSettings, optional
    prior : Rigid, optional
        A coarse ``camera_from_base`` (bench mounting, other frames): hypotheses rotated more than
        ``settings.prior_tol_rad`` from it are dropped. Needed for near-symmetric poses.

    Returns
    -------
    RodDetection
        Priors for the rods of the associated legs (``predict_rods`` structure, None elsewhere),
        the fitted ``camera_from_base``, and the reasons for what was not found.
    """
    s = settings or DetectSettings()
    qv = np.asarray(q, dtype=np.float64).reshape(4)
    if not rod_spacing_m or rod_spacing_m <= 0:
        return _nothing("no rod detection: the rod spacing is not known (dataset legs.rod_spacing_m)")
    try:
        dkm(nominal, qv)
    except I4calError as exc:
        return _nothing(f"no rod detection: {exc}")
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    canvas, scale, origin, valid = undistorted_canvas(gray, camera)
    seg, con, ln = detect_segments(canvas, valid, scale, origin, s)
    # only lines long enough to bound a rod are refined and paired
    lines = [li for li in merge_segments(seg, con, ln, s) if li.s1 - li.s0 >= s.min_rod_px]
    lines = merge_lines(refine_lines(lines, canvas, scale, origin, s, np.random.default_rng(0)), s)
    rods = find_rods(lines, canvas, scale, origin, camera, rod_radius_m, s)
    legs_c = find_legs(rods, rod_radius_m, rod_spacing_m, s)
    counts = {"segments": len(seg), "lines": len(lines), "rod_candidates": len(rods), "leg_candidates": len(legs_c)}
    return _decide(rods, legs_c, counts, camera, nominal, qv, rod_radius_m, rod_spacing_m, s, prior)


def _nothing(reason: str, **kw) -> RodDetection:
    return RodDetection([None] * 8, {rod_name(lg, r): reason for lg, r in ROD_KEYS}, reason=reason, **kw)


def _decide(
    rods: list[RodCandidate],
    legs_c: list[LegCandidate],
    counts: dict[str, int],
    camera: CameraModel,
    nominal: I4Parameters,
    q: Array,
    radius: float,
    spacing: float,
    s: DetectSettings,
    prior: Rigid | None,
) -> RodDetection:
    kw: dict[str, Any] = {"rods": rods, "leg_candidates": legs_c, "counts": counts}  # RodDetection's fields
    if len(legs_c) < s.min_legs:
        return _nothing(
            f"rods not detected: {len(legs_c)} rod pairs found ({len(rods)} rods), need {s.min_legs} legs", **kw
        )
    hyps, rivals = associate(rods, legs_c, nominal, q, radius, spacing, camera.K, s, prior)
    if not hyps:
        why = "within the placement prior and " if prior is not None else ""
        return _nothing(
            f"rods not associated: no assignment of the {len(legs_c)} rod pairs to the legs fits "
            f"{why}the nominal model within {s.max_rms_px:.0f} px",
            **kw,
        )
    best = hyps[0]
    unsure: dict[int, str] = {}
    for rival in rivals:
        swapped, orders = _differences(best, rival)
        if swapped:
            lab = rival.labels()
            mine = "-".join(str(lg + 1) for lg in sorted(best.legs))
            other = "-".join(
                str(lab[best.legs[lg][0]][0] + 1) if best.legs[lg][0] in lab else "?" for lg in sorted(best.legs)
            )
            reason = (
                f"ambiguous leg association: legs {mine} fit as well as {other} ({best.rms_px:.1f} px vs "
                f"{rival.rms_px:.1f} px); a near-symmetric pose needs a placement prior"
            )
            return RodDetection(
                [None] * 8,
                {rod_name(lg, r): reason for lg, r in ROD_KEYS},
                None,
                best.rms_px,
                True,
                hyps,
                reason=reason,
                **kw,
            )
        for lg in orders:
            unsure[lg] = (
                f"leg {lg + 1}: which of its two rods is which is ambiguous (both orders fit, "
                f"{best.rms_px:.1f} px vs {rival.rms_px:.1f} px)"
            )
    reasons: dict[str, str] = {}
    for leg, rod in ROD_KEYS:
        if leg not in best.legs or leg in unsure:
            reasons[rod_name(leg, rod)] = unsure.get(leg) or (
                f"leg {leg + 1} not detected: no rod pair in the image matches it (hidden or out of view)"
            )
    model = predict_rods(nominal, q, best.camera_from_base, spacing)
    dirs: list[Array | None] = [None] * 8
    for k, p in enumerate(model):
        if rod_name(p.leg, p.rod) not in reasons:
            lc = next(lc for lc in legs_c if set(lc.rods) == set(best.legs[p.leg]))
            dirs[k] = _leg_direction(lc, p.u, s.model_direction_rad)
    preds = _priors(rods, best, model, dirs, radius, np.ones(8))
    # a width read off a candidate with one wrong limb puts its prior at a wrong depth: each rod's
    # depth over the model's (the fitted placement's depth error is common to the frame) must agree
    # with the frame's median; the outliers are moved to the median ratio
    ratio = np.array(
        [
            _depth_ratio(p, m, rods[best.legs[m.leg][m.rod]], camera.K) if p is not None else np.nan
            for p, m in zip(preds, model, strict=True)
        ]
    )
    if np.sum(np.isfinite(ratio)) >= 4:
        med = float(np.nanmedian(ratio))
        off = np.isfinite(ratio) & (np.abs(ratio / med - 1.0) > s.depth_tolerance)
        if off.any():
            preds = _priors(rods, best, model, dirs, radius, np.where(off, med / ratio, 1.0))
    return RodDetection(preds, reasons, best.camera_from_base, best.rms_px, False, hyps, dirs, **kw)


def _priors(
    rods: list[RodCandidate],
    best: Hypothesis,
    model: list[RodPrediction],
    dirs: list[Array | None],
    radius: float,
    depth_scale: Array,
) -> list[RodPrediction | None]:
    """The associated rods' priors (None where ``dirs`` is None), in ``ROD_KEYS`` order."""
    preds: list[RodPrediction | None] = []
    for k, p in enumerate(model):
        d = dirs[k]
        if d is None:
            preds.append(None)
            continue
        rc = rods[best.legs[p.leg][p.rod]]
        p0 = preds[k - 1] if p.rod == 1 else None
        if p0 is not None:
            # rod 1 beside rod 0's prior: the leg's two priors stay one rod spacing apart
            m0 = model[k - 1]
            p = RodPrediction(p.leg, 1, p0.top + (p.top - m0.top), p0.bottom + (p.bottom - m0.bottom))
        preds.append(_prior_from_candidate(rc, d, p, radius, float(depth_scale[k])))
    return preds


def _depth_ratio(prior: RodPrediction, model: RodPrediction, rc: RodCandidate, K: Array) -> float:
    """Depth of the prior's axis over the model's, where the ray through the rod's image middle meets them."""
    ray = np.linalg.solve(K, np.append(0.5 * (rc.centre[0] + rc.centre[1]), 1.0))
    ray = ray / np.linalg.norm(ray)

    def along(a: Array, u: Array) -> float:
        A2 = np.array([[u @ u, -u @ ray], [u @ ray, -1.0]])
        try:
            return float(np.linalg.solve(A2, np.array([-(a @ u), -(a @ ray)]))[1])
        except np.linalg.LinAlgError:
            return float("nan")

    zp, zm = along(prior.top, prior.u), along(model.top, model.u)
    return zp / zm if zm > 0 and zp > 0 else float("nan")


def _leg_direction(lc: LegCandidate, u_model: Array, sigma_model: float) -> Array:
    """A leg's direction (camera frame, oriented like ``u_model``): the image's, weighted with the model's.

    The image gives it as the intersection of the two rods' axis planes, ill-conditioned when they
    are nearly the same plane (the leg seen edge-on, ``lc.sigma`` large) and wrong when a limb of
    either rod is; the nominal model at the fitted placement gives ``u_model`` to ``sigma_model``.
    Inverse-variance mean of the two; the model's alone when they disagree by more than 3 sigma.
    """
    d = lc.d if lc.d @ u_model >= 0 else -lc.d
    if np.arccos(np.clip(d @ u_model, -1.0, 1.0)) > 3.0 * np.hypot(lc.sigma, sigma_model):
        return u_model
    v = d / lc.sigma**2 + u_model / sigma_model**2
    return v / np.linalg.norm(v)


def _prior_from_candidate(
    rc: RodCandidate, d: Array, model: RodPrediction, radius: float, depth_scale: float = 1.0
) -> RodPrediction:
    """The rod's prior for measure_rod: its detected axis, over the model's extent.

    The axis lies in the candidate's axis plane (through the camera centre, bisecting its limb
    planes), along the leg's detected direction ``d`` projected into that plane (the two rods of a
    leg stay parallel), at the depth where both limb planes are tangent to a cylinder of the rod's
    radius (times ``depth_scale``, which moves the axis along the rays: same image, other width):
    its image is the detected rod to a pixel or so. The nominal model, centimetres off, only gives
    the extent: the end points are the points of the axis nearest to ``model``'s (oriented actuator
    to plate like ``d``). Falls back to ``model`` when the planes are degenerate.
    """
    u = d - (d @ rc.m) * rc.m
    n = float(np.linalg.norm(u))
    if n < 1e-9:
        return model
    u = u / n
    try:
        X = depth_scale * np.linalg.solve(np.vstack([rc.h[0], rc.h[1], u]), np.array([radius, radius, 0.0]))
    except np.linalg.LinAlgError:
        return model
    top = X + ((model.top - X) @ u) * u
    bottom = X + ((model.bottom - X) @ u) * u
    return RodPrediction(model.leg, model.rod, top, bottom)


def resolve(
    detection: RodDetection,
    camera: CameraModel,
    nominal: I4Parameters,
    q: ArrayLike,
    rod_radius_m: float,
    rod_spacing_m: float,
    prior: Rigid,
    settings: DetectSettings | None = None,
) -> RodDetection:
    """Associate a detection's rod candidates again, keeping only placements near ``prior``.

    For a frame that was ambiguous alone, once other frames (or the bench's mounting) fix the
    placement; the image is not read again.

    Parameters
    ----------
    detection : RodDetection
        The frame's detection (:func:`detect_rods`).
    camera : CameraModel
        The camera that took the frame.
    nominal : I4Parameters
        The nominal model (metres, radians).
    q : array_like, shape (4,)
        Encoder values of the frame (metres).
    rod_radius_m : float
        Rod radius (metres).
    rod_spacing_m : float
        Distance between the axes of a leg's two rods (metres).
    prior : Rigid
        ``camera_from_base`` the placements must lie near (metres, radians).
    settings : DetectSettings, optional
        Default: ``DetectSettings()``.

    Returns
    -------
    RodDetection
        The detection with its association decided near ``prior`` (or the reason it is not).
    """
    s = settings or DetectSettings()
    return _decide(
        detection.rods,
        detection.leg_candidates,
        detection.counts,
        camera,
        nominal,
        np.asarray(q, dtype=np.float64).reshape(4),
        rod_radius_m,
        rod_spacing_m,
        s,
        prior,
    )


def consensus_placement(placements: Sequence[Rigid], tol_rad: float = 0.1) -> Rigid | None:
    """The placement most frames agree on: the largest group within ``tol_rad`` of one of them.

    Its rotation is the chordal mean of the group's, its translation the median. None when there
    are no placements or when another, disjoint group is as large (frames disagree).

    Parameters
    ----------
    placements : sequence of Rigid
        Per frame, a ``camera_from_base`` (metres, radians).
    tol_rad : float
        Largest rotation angle between two placements of one group (radians).

    Returns
    -------
    Rigid or None
    """
    if not placements:
        return None
    Rs = [p.R for p in placements]
    groups = [[j for j in range(len(Rs)) if _rotation_angle(Rs[i], Rs[j]) <= tol_rad] for i in range(len(Rs))]
    best = max(groups, key=len)
    if any(len(g) == len(best) and not set(g) & set(best) for g in groups):
        return None
    U, _, Vt = np.linalg.svd(np.mean([Rs[j] for j in best], axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return Rigid(R, np.median([placements[j].t for j in best], axis=0))


def resolve_frames(
    detections: Mapping[int, RodDetection],
    camera: CameraModel,
    nominal: I4Parameters,
    q: Mapping[int, ArrayLike],
    rod_radius_m: float,
    rod_spacing_m: float,
    prior: Rigid | None = None,
    settings: DetectSettings | None = None,
) -> tuple[dict[int, RodDetection], Rigid | None, str]:
    """Frames of one camera: frames that were ambiguous alone are associated again near the placement
    that the unambiguous frames agree on (or near ``prior`` when given).

    Parameters
    ----------
    detections : mapping frame -> RodDetection
        From :func:`detect_rods` (with ``prior`` when there is one).
    camera : CameraModel
        The camera that took the frames.
    nominal : I4Parameters
        The nominal model (metres, radians).
    q : mapping frame -> array_like, shape (4,)
        Encoder values (metres).
    rod_radius_m : float
        Rod radius (metres).
    rod_spacing_m : float
        Distance between the axes of a leg's two rods (metres).
    prior : Rigid, optional
        A known ``camera_from_base`` (metres, radians); default: the frames' consensus.
    settings : DetectSettings, optional
        Default: ``DetectSettings()``.

    Returns
    -------
    detections : dict frame -> RodDetection
    placement : Rigid or None
        The consensus ``camera_from_base`` (coarse) of the associated frames.
    source : str
        ``"prior"``, ``"consensus of N frames"`` (the frames associated alone) or ``"none"``.
    """
    s = settings or DetectSettings()
    solved = [d.camera_from_base for d in detections.values() if d.camera_from_base is not None]
    anchor = prior if prior is not None else consensus_placement(solved, s.prior_tol_rad / 2)
    n = len(solved)
    source = "prior" if prior is not None else (f"consensus of {n} frame{'s' if n != 1 else ''}" if anchor else "none")
    out = dict(detections)
    if anchor is not None and prior is None:  # (with a prior the detections already used it)
        for i, d in detections.items():
            if d.ambiguous:
                out[i] = resolve(d, camera, nominal, q[i], rod_radius_m, rod_spacing_m, anchor, s)
    placed = consensus_placement(
        [d.camera_from_base for d in out.values() if d.camera_from_base is not None], s.prior_tol_rad / 2
    )
    return out, placed, source


def measure_detected(
    gray: np.ndarray,
    camera: CameraModel,
    detection: RodDetection,
    radius: float,
    settings: RodSettings | None = None,
    occluders: list[Array] | None = None,
    seed: int = 0,
    ideal_bbox: Array | None = None,
) -> list[RodMeasurement]:
    """Measure the rods a detection found (:func:`calib.vision.rods.measure_rods`), the others missing.

    Parameters
    ----------
    gray : ndarray, shape (H, W), float32 or uint8
        The (distorted) image, single channel.
    camera : CameraModel
        The camera that took it.
    detection : RodDetection
        The frame's detection; its associated rods carry the predictions measured.
    radius : float
        Rod radius (metres).
    settings : RodSettings, optional
        Default: ``RodSettings()``.
    occluders : list of ndarray, shape (M, 2), optional
        Convex polygons in ideal pixels that hide the rods (e.g. the board).
    seed : int
        Seed of the robust line fits' random sampling.
    ideal_bbox : ndarray, shape (4,), optional
        :func:`calib.vision.rods.image_ideal_bbox` of the camera (px; computed when not given).

    Returns
    -------
    list of RodMeasurement
        Eight measurements in ``ROD_KEYS`` order; a rod not associated carries the reason.
    """
    found = [p for p in detection.predictions if p is not None]
    meas = (
        {(m.leg, m.rod): m for m in measure_rods(gray, camera, found, radius, settings, occluders, seed, ideal_bbox)}
        if found
        else {}
    )
    out = []
    for leg, rod in ROD_KEYS:
        m = meas.get((leg, rod))
        if m is None:
            m = RodMeasurement(leg, rod, reason=detection.reasons.get(rod_name(leg, rod), "not detected"))
        out.append(m)
    return out
