"""Dataset v1 -> observations v1: intrinsics, board poses and rods for every frame.

Stages (each over a process pool when ``workers > 1``, with ``progress(done, total)`` callbacks):

1. Intrinsics: given (argument), else from the dataset's ``camera`` (K, dist), else calibrated
   from the ``camera`` phase with :func:`calib.camera.calibrate_intrinsics` (calibrateCameraRO);
   the refined board geometry is then used for every board pose.
2. Board poses (ChArUco) for every non-``camera`` frame.
3. Coarse camera placement: ``camera_from_base`` and ``ee_from_board`` fitted to all board poses
   with the *nominal* model's end-effector poses (hand-eye least squares; the rotation about z_B is
   initialised by a 1-D search). This is the prior that predicts every rod's image; it needs board
   poses in at least 3 frames with some rotation of the end-effector (the ``rotation`` phase).
   Without it, each frame's rods are found and associated from scratch (:mod:`calib.vision.detect`,
   ``ExtractOptions.camera_prior`` or the frames' consensus resolving near-symmetric frames).
4. Rods: the eight rods of every frame, predicted from the nominal model, the encoder values and
   the coarse placement, then measured (:mod:`calib.vision.rods`); the board (measured, or
   predicted when missing) is an occluder.
5. Rods again, where the nominal prediction was off: the seven parameters, ``camera_from_base`` and
   ``ee_from_board`` refitted to the rods and boards the first pass measured (robust least squares,
   :mod:`calib.vision.repredict`); the frames whose prediction that moves by more than
   ``ExtractOptions.repredict_px`` are measured again on the refitted prediction. On a bench some 15 mm
   off nominal the first prediction is 15-30 px off (the search band is 18 px): without this, rods are
   lost or taken for another edge pair. The refit only says where to look (``summary.repredicted``).
6. Rods once more, when more than ``ExtractOptions.recover_lost_share`` of those looked for were lost in their search
   bands (:mod:`calib.vision.recover`): the prediction refitted robustly (each measured line its own rod, its leg's
   other rod or the gap between them; several starts) and every frame measured again, kept when it loses fewer rods
   (``summary.recovered``). A bench some 16 mm off nominal whose prediction falls between the rods of most legs.

A frame whose image is missing or unreadable, a hidden board, a rod that leaves the image: each is
reported per frame (``missing`` in the frame, ``summary`` per phase) and the rest goes on.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..camera import CameraModel, IntrinsicsResult, calibrate_intrinsics
from ..dataset import Dataset
from ..errors import I4calError, InputError
from ..kinematics import base_from_ee, dkm
from ..observations import FORMAT
from ..parameters import I4Parameters
from ..transforms import Rigid
from .board import BoardDetector
from .detect import DetectSettings, resolve_frames
from .placement import fit_placement
from .pool import (
    _Pool,
    _task_board,
    _task_board_pose,
    _task_detect,
    _task_find_rods,
    _task_rods,
)
from .recover import STARTS as RECOVERY_STARTS
from .recover import lost_in_search, measured_lines
from .repredict import MeasuredRod, Repredicted, prediction_shift_px, refit_prediction, rod_ends_camera
from .rods import ROD_KEYS, RodSettings, rod_name

if TYPE_CHECKING:
    from .stream import StreamedFrames

Progress = Callable[[int, int], None]
FrameCallback = Callable[[dict[str, Any]], None]


#: What a dataset with neither intrinsics nor a ``camera`` phase says: how to get the intrinsics.
NO_INTRINSICS = (
    "no intrinsics: the dataset has neither camera.K/dist nor a 'camera' phase. Calibrate the camera once: "
    "`i4cal camera calibrate --bench BENCH.toml -o camera.json` (hand-held board views, docs/camera.md), then name it "
    'in the bench file (`[camera] intrinsics = "camera.json"`) so that `i4cal acquire` records it in every dataset, '
    "or give it to this dataset with `--camera camera.json` (i4cal extract, i4cal calibrate)"
)


@dataclass
class ExtractOptions:
    """Settings of :func:`extract_dataset`."""

    min_corners: int = 6
    rods: RodSettings | None = None
    min_placement_frames: int = 3
    max_placement_rms_m: float = 0.02
    #: without a placement, find the rods from scratch in each frame (calib.vision.detect)
    detect_fallback: bool = True
    detect: DetectSettings | None = None
    #: coarse camera_from_base known from the bench's mounting: resolves near-symmetric frames
    camera_prior: Rigid | None = None
    #: when the camera carries its calibration's covariance, let the rods refine it (the combined
    #: fit's intrinsics refinement) and, if it moves by more than ``refine_min_shift`` of its
    #: standard deviations (Mahalanobis), measure the frames a second time with the refined camera
    refine_camera: bool = True
    refine_min_shift: float = 0.5
    #: after the rods' first pass, refit the prediction (seven parameters, placement) to the rods and boards it
    #: measured (:mod:`calib.vision.repredict`) and measure again the frames whose prediction moved by more than
    #: this (px); None: one pass, on the nominal model's prediction
    repredict_px: float | None = 3.0
    #: the camera calibration's lens model (:data:`calib.camera.LENS_MODEL_CHOICES`): ``"auto"`` chooses it from
    #: the ``camera`` phase's board views (:func:`calib.camera.calibrate_intrinsics`); None: the dataset's
    #: ``camera.lens_model`` (the bench file's), else ``"auto"``; a given camera keeps its own
    lens_model: str | None = None
    #: when more than this share of the rods looked for are lost in their search bands (:mod:`.recover`), refit the
    #: prediction robustly and measure every frame again (kept when it loses fewer); None: never (nor with
    #: ``repredict_px=None``: one pass on the nominal prediction)
    recover_lost_share: float | None = 0.05


@dataclass
class ExtractionResult:
    """What :func:`extract_dataset` found.

    Attributes
    ----------
    observations : dict
        An observations v1 document (validates with :meth:`calib.observations.Observations.from_dict`).
    summary : dict
        ``{"phases": {phase: {...counts, "missing": {reason: count}}}, "frames": {index: [reasons]}, ...}``.
    camera : CameraModel
    intrinsics : IntrinsicsResult or None
        When calibrated from the ``camera`` phase.
    camera_from_base : Rigid or None
        The coarse placement used to predict the rods.
    """

    observations: dict[str, Any]
    summary: dict[str, Any]
    camera: CameraModel
    intrinsics: IntrinsicsResult | None
    camera_from_base: Rigid | None
    ee_from_board: Rigid | None
    #: the rods' prediction refitted to the first pass (:mod:`calib.vision.repredict`), when used
    repredicted: Repredicted | None = None


def _short(reason: str) -> str:
    return reason.split(":")[0].split("(")[0].strip()


def extract_dataset(
    dataset: str | Path | Dataset,
    *,
    camera: CameraModel | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
    options: ExtractOptions | None = None,
    on_frame: FrameCallback | None = None,
    streamed: StreamedFrames | None = None,
) -> ExtractionResult:
    """Extract observations v1 from a dataset v1 directory.

    Parameters
    ----------
    dataset : path or Dataset
    camera : CameraModel, optional
        Known intrinsics; default: the dataset's, else calibrated from its ``camera`` phase. A camera
        calibrated by :func:`calib.camera.calibrate_intrinsics` carries the board corners it refined
        (``calibration.board_points``): they are used for the board poses when the board has as many corners.
    workers : int, optional
        Processes (default: ``os.cpu_count()``); 1 runs in this process.
    progress : callable(done, total), optional
        Called after every frame of every stage (``total`` counts all stages).
    on_frame : callable(info), optional
        Called with what was found in each non-``camera`` frame, once after the board stage and once after the
        rods stage (:func:`frame_info`).
    streamed : StreamedFrames, optional
        Frames measured during the acquisition (:mod:`calib.vision.stream`): the passes take their boards and rods
        from it where they hold the frame's answer, and measure the others.

    Raises
    ------
    InputError
        No intrinsics can be had (none given, none in the dataset, the ``camera`` phase too poor).
    """
    ds = dataset if isinstance(dataset, Dataset) else Dataset.open(dataset)
    workers = max(1, int(workers or os.cpu_count() or 1))
    opts = options or ExtractOptions()
    base = [0, 0]  # the frames counted by the passes before this one, and this pass's total

    def pass_progress(done: int, tot: int) -> None:
        base[1] = tot
        if progress:
            progress(base[0] + done, base[0] + tot)

    def next_pass() -> None:
        base[0], base[1] = base[0] + base[1], 0

    # -- streaming hook: frames measured during the acquisition answer from the pool (calib.vision.stream) --
    with _Pool(workers) if streamed is None else streamed.pool(workers, ds) as pool:
        corners: dict[int, list] = {}
        res = _extract(pool, ds, camera, pass_progress, opts, on_frame, keep_images=opts.refine_camera, corners=corners)
        if opts.refine_camera:
            refined, info = refined_camera(res, opts.refine_min_shift)
            if refined is None:
                res.summary["camera"]["refined_by_rods"] = info
            else:
                next_pass()
                first = res
                res = _extract(
                    pool,
                    ds,
                    refined,
                    pass_progress,
                    opts,
                    on_frame,
                    corners=corners,
                    predict_with=first.repredicted,
                    predicted_from=first.camera_from_base,
                )
                _carry_over(ds, first, res, {**first.summary["camera"], "refined_by_rods": info})
        res = _recover(pool, ds, res, opts, on_frame, corners, pass_progress, next_pass)
    return res


def _carry_over(ds: Dataset, earlier: ExtractionResult, later: ExtractionResult, camera: dict) -> None:
    """A later pass re-measured the frames: the camera's calibration (summary ``camera``, the ``camera`` phase's
    frames, the intrinsics) stays the earlier pass's, and so do the figures of the nominal prediction's refit
    (``repredicted.first_camera_pass``)."""
    later.summary["camera"] = camera
    before = earlier.summary.get("repredicted")
    if later.summary.get("repredicted") is not None:
        later.summary["repredicted"]["first_camera_pass"] = (before or {}).get("first_camera_pass") or before
    cam_frames = {str(i) for i, f in enumerate(ds.frames) if f.phase == "camera"}
    later.summary["frames"] = dict(
        sorted(
            {
                **{k: v for k, v in earlier.summary["frames"].items() if k in cam_frames},
                **later.summary["frames"],
            }.items(),
            key=lambda kv: int(kv[0]),
        )
    )
    later.observations["extraction"]["summary"] = later.summary
    later.intrinsics = earlier.intrinsics


def _recover(
    pool: _Pool,
    ds: Dataset,
    res: ExtractionResult,
    opts: ExtractOptions,
    on_frame: FrameCallback | None,
    corners: dict[int, list],
    progress: Progress,
    next_pass: Callable[[], None],
) -> ExtractionResult:
    """When more than ``opts.recover_lost_share`` of the rods looked for were lost in their search bands
    (:func:`.recover.lost_in_search`): the prediction refitted robustly to every line measured (each may be its own
    rod, its leg's other rod or the gap between them; :data:`.recover.STARTS` more starting points) and every frame
    measured again on it. The new pass is kept when it loses fewer rods. Recorded in ``summary["recovered"]``."""
    if res.camera_from_base is None or res.ee_from_board is None or opts.recover_lost_share is None:
        return res
    if opts.repredict_px is None:  # asked for one pass on the nominal prediction
        return res
    lost, looked = lost_in_search(res.observations)
    if looked == 0 or lost <= opts.recover_lost_share * looked:
        return res
    info: dict[str, Any] = {"lost_before": lost, "looked_for_before": looked, "share": opts.recover_lost_share}
    q, lines, boards = measured_lines(res.observations)
    start = res.repredicted
    C0, E0 = (start.camera_from_base, start.ee_from_board) if start else (res.camera_from_base, res.ee_from_board)
    nominal, f_px, spacing, height = _refit_inputs(ds, res.camera)
    try:
        fit = refit_prediction(
            nominal, q, lines, boards, C0, E0, f_px, spacing, height, mixture=True, starts=RECOVERY_STARTS
        )
    except (I4calError, np.linalg.LinAlgError, ValueError) as exc:
        res.summary["recovered"] = {**info, "applied": False, "reason": f"robust refit failed: {exc}"}
        return res
    if fit is None:
        res.summary["recovered"] = {
            **info,
            "applied": False,
            "reason": "the robust refit did not bring the lines closer",
        }
        return res
    info["refit"] = fit.summary()
    next_pass()
    again = _extract(
        pool,
        ds,
        res.camera,
        progress,
        opts,
        on_frame,
        corners=corners,
        predict_with=fit,
        predicted_from=res.camera_from_base,
    )
    lost_after, looked_after = lost_in_search(again.observations)
    info.update(lost_after=lost_after, looked_for_after=looked_after)
    if lost_after >= lost:
        res.summary["recovered"] = {**info, "applied": False, "reason": "measured again, as many rods were lost"}
        return res
    _carry_over(ds, res, again, res.summary["camera"])
    again.summary["recovered"] = {**info, "applied": True, "repredicted_before": res.summary.get("repredicted")}
    return again


def refined_camera(res: ExtractionResult, min_shift: float = 0.5) -> tuple[CameraModel | None, dict[str, Any]]:
    """The camera refined by the rods of an extraction, or None with the reason.

    The combined method (:func:`calib.methods.combined.calibrate_combined`) treats the intrinsics as
    nuisance unknowns with the calibration's covariance as prior; the rods, many and spread over the
    image, determine them several times better than the board views did (on the image twin the
    intrinsics' error falls from ~1.3 to ~0.2 of their calibration std). The rods' measurement
    itself depends on the camera (which edge points are fitted), so the frames are worth measuring
    again with the refined camera: :func:`extract_dataset` does when the shift exceeds ``min_shift``
    standard deviations (Mahalanobis). The refined camera keeps the calibration's covariance (the
    combined method's prior when it uses the rods again), adds the fit's posterior one
    (``calibration.covariance_refined``, for the methods that do not use the rods) and records the
    shift under ``calibration.refined_by_rods``.

    Returns
    -------
    (CameraModel or None, dict)
        The dict: ``applied``, ``shift`` (per intrinsic: px for fx, fy, cx, cy), ``mahalanobis`` or ``reason``.
    """
    from ..camera import intrinsics_names
    from ..methods.combined import calibrate_combined
    from ..methods.intrinsics import perturbed_camera
    from ..observations import Observations

    calib = res.camera.extra.get("calibration") or {}
    if calib.get("covariance") is None:
        return None, {"applied": False, "reason": "the camera has no calibration covariance"}
    try:
        fit = calibrate_combined(Observations.from_dict(res.observations))
    except I4calError as exc:
        return None, {"applied": False, "reason": f"combined fit failed: {exc}"}
    shift = fit.diagnostics.get("intrinsics_refinement")
    if not shift:
        return None, {"applied": False, "reason": "the observations carry no limb samples (limbs_px)"}
    d = np.array([shift[k] for k in intrinsics_names(res.camera)])
    m = float(np.sqrt(d @ np.linalg.solve(np.asarray(calib["covariance"], dtype=np.float64), d)))
    info: dict[str, Any] = {"shift": shift, "mahalanobis": m}
    if m < min_shift:
        return None, {"applied": False, **info, "reason": f"shift {m:.2f} std < {min_shift}"}
    moved = perturbed_camera(res.camera, d)
    new_calib = {**calib, "refined_by_rods": info}
    if fit.diagnostics.get("intrinsics_posterior_covariance") is not None:
        new_calib["covariance_refined"] = fit.diagnostics["intrinsics_posterior_covariance"]
    bp = calib.get("board_points") or {}
    if bp.get("d_intrinsics") is not None:  # the board geometry moves with the intrinsics (their correlation)
        pts = np.asarray(bp["points_m"], dtype=np.float64) + np.asarray(bp["d_intrinsics"], dtype=np.float64) @ d
        new_calib["board_points"] = {**bp, "points_m": pts.tolist()}
    extra = {**res.camera.extra, "calibration": new_calib}
    return CameraModel(moved.K, moved.dist, moved.width, moved.height, extra), {"applied": True, **info}


def _extract(
    pool: _Pool,
    ds: Dataset,
    camera: CameraModel | None,
    progress: Progress | None,
    opts: ExtractOptions,
    on_frame: FrameCallback | None,
    keep_images: bool = False,
    corners: dict[int, list] | None = None,
    predict_with: Repredicted | None = None,
    predicted_from: Rigid | None = None,
) -> ExtractionResult:
    """One pass over the dataset. ``keep_images``: the workers keep the decoded images after the rods stage (a
    second pass follows); ``corners``: filled with each frame's ChArUco corners when empty, reused (the pose
    only) when not."""
    reported = [-1]  # the last count reported: the end is reported once, whatever the stages reported
    if progress is not None:
        user_progress = progress

        def progress(done: int, tot: int) -> None:
            reported[0] = done
            user_progress(done, tot)

    doc = ds.document
    frames = ds.frames
    cam_idx = [i for i, f in enumerate(frames) if f.phase == "camera"]
    obs_idx = [i for i, f in enumerate(frames) if f.phase != "camera"]
    rs = opts.rods or RodSettings()
    rs_dict = dict(rs.__dict__)
    root = str(ds.root)
    intr: IntrinsicsResult | None = None
    refined = None
    per_frame: dict[int, list[str]] = {}
    need_calib = camera is None and (doc.camera.K is None or doc.camera.dist is None)
    total = (len(cam_idx) if need_calib else 0) + 2 * len(obs_idx)
    done = 0
    if camera is None and not need_calib:
        camera = doc.camera.camera_model()  # with the camera file's calibration when the acquisition recorded one
    if need_calib:
        if not cam_idx:
            raise InputError(NO_INTRINSICS, file=root, field="camera")
        det = pool.run(_task_detect, cam_idx, (root, None, None, opts.min_corners, rs_dict), progress, done, total)
        done += len(cam_idx)
        views = {}
        for i, r in det:
            if isinstance(r, str):
                per_frame.setdefault(i, []).append(f"image: {r}")
            else:
                views[i] = (np.asarray(r[0], dtype=int), np.asarray(r[1]).reshape(-1, 2), None)
        ids_all, pts = BoardDetector(doc.board).ids_all, BoardDetector(doc.board).points_nominal
        intr = calibrate_intrinsics(
            views,
            (doc.camera.width, doc.camera.height),
            ids_all,
            pts,
            lens_model=opts.lens_model or (doc.camera.model_extra or {}).get("lens_model") or "auto",
        )
        for i, reason in intr.rejected.items():
            per_frame.setdefault(i, []).append(f"camera view rejected: {reason}")
        camera = intr.camera
    assert camera is not None
    # the camera's calibration carries the board geometry it refined (calibrateCameraRO) and how that
    # geometry moves with the intrinsics (their correlation in the calibration)
    bp = (camera.extra.get("calibration") or {}).get("board_points") or {}
    if bp.get("ids") is not None and len(bp["ids"]) == BoardDetector(doc.board).ids_all.size:
        refined = (list(bp["ids"]), list(bp["points_m"]), bp.get("d_intrinsics"))
    init = (root, camera.to_dict(), refined, opts.min_corners, rs_dict, keep_images)
    board_cb = None if on_frame is None else (lambda r: on_frame(frame_info(r[0], frames[r[0]].phase, r[1])))
    if corners:  # a second pass: the corners found in the first, posed with this camera
        again = [i for i in obs_idx if i in corners]
        boards = dict(
            pool.run(_task_board_pose, [(i, *corners[i]) for i in again], init, progress, done, total, board_cb)
        )
        rest = [i for i in obs_idx if i not in corners]
        boards.update(pool.run(_task_board, rest, init, progress, done + len(again), total, board_cb))
    else:
        boards = dict(pool.run(_task_board, obs_idx, init, progress, done, total, board_cb))
    if corners is not None:
        corners.update({i: b["corners"] for i, b in boards.items() if "corners" in b})
    done += len(obs_idx)
    good = [i for i in obs_idx if "pose" in boards[i]]
    C = E = None
    placement_rms = None
    placement_reason = None
    if len(good) >= opts.min_placement_frames:
        qk = np.array([frames[i].q for i in good])
        bR = np.array([boards[i]["pose"]["R"] for i in good])
        bt = np.array([boards[i]["pose"]["t"] for i in good])
        try:
            height = float((doc.board.model_extra or {}).get("height_above_ee_m", 0.0))
            C, E, placement_rms = fit_placement(qk, bR, bt, doc.nominal.parameters(), height)
            if placement_rms > opts.max_placement_rms_m:
                placement_reason = (
                    f"coarse camera placement inconsistent: board residual RMS "
                    f"{placement_rms * 1e3:.1f} mm > {opts.max_placement_rms_m * 1e3:.0f} mm "
                    "(too few board poses, or too little motion among them)"
                )
                C = E = None
        except (I4calError, np.linalg.LinAlgError, ValueError) as exc:
            placement_reason = f"coarse camera placement failed: {exc}"
    else:
        placement_reason = (
            f"no coarse camera placement: board poses in {len(good)} frames, need {opts.min_placement_frames}"
        )
    if predict_with is not None and predicted_from is not None and C is not None:
        # an earlier pass's refit, moved with the camera frame (another camera moves the board poses, hence the
        # coarse placement, by the same transform)
        predict_with = replace(
            predict_with, camera_from_base=C @ predicted_from.inverse() @ predict_with.camera_from_base
        )
    found: dict[int, Any] = {}
    fallback = None
    if C is None and opts.detect_fallback:  # no placement: the rods are found from scratch in each frame
        dset = opts.detect or DetectSettings()
        prior = opts.camera_prior.to_dict() if opts.camera_prior is not None else None
        items: list[tuple] = [(i, prior, dict(dset.__dict__)) for i in obs_idx if "image_error" not in boards[i]]
        total += len(items)
        found = {i: d for i, d in pool.run(_task_find_rods, items, init, progress, done, total) if d is not None}
        done += len(items)
        found, placed, anchor = resolve_frames(
            found,
            camera,
            doc.nominal.parameters(),
            {i: frames[i].q for i in found},
            doc.legs.rod_radius_m,
            doc.legs.rod_spacing_m or 0.0,
            opts.camera_prior,
            dset,
        )
        fallback = {
            "frames": len(found),
            "associated": sum(d.ok for d in found.values()),
            "ambiguous": sum(d.ambiguous for d in found.values()),
            "anchor": anchor,
            "camera_from_base": placed.to_dict() if placed is not None else None,
        }
    rod_items: list[tuple] = []
    rods: dict[int, Any] = {}
    for i in obs_idx:
        if i in found:
            cfb = found[i].camera_from_base
            rod_items.append((i, cfb.to_dict() if cfb is not None else None, boards[i].get("pose"), found[i]))
            continue
        if "image_error" in boards[i] or C is None:
            continue
        b = boards[i].get("pose")
        if b is None and E is not None:
            try:
                nom = doc.nominal.parameters()
                nb = C @ Rigid(*base_from_ee(nom, dkm(nom, np.asarray(frames[i].q)))) @ E
                b = {"R": nb.R.tolist(), "t": nb.t.tolist()}
            except I4calError:
                b = None
        if predict_with is not None:  # the refit of an earlier pass
            rod_items.append((i, predict_with.camera_from_base.to_dict(), b, None, predict_with.parameters.vector()))
        else:
            rod_items.append((i, C.to_dict(), b))
    rods_cb = (
        None if on_frame is None else (lambda r: on_frame(frame_info(r[0], frames[r[0]].phase, boards[r[0]], r[1])))
    )
    rods = dict(pool.run(_task_rods, rod_items, init, progress, done, total, rods_cb))
    repredicted: dict[str, Any] | None = None
    fit: Repredicted | None = None
    if C is not None and E is not None and not found and opts.repredict_px is not None:
        repredicted, redo, fit = _repredict(ds, camera, boards, rods, C, E, opts.repredict_px, predict_with)
        if fit is not None and redo:
            total += len(redo)
            items = [
                (i, fit.camera_from_base.to_dict(), b, None, fit.parameters.vector())
                for i, _cfb, b in (it[:3] for it in rod_items)
                if i in redo
            ]
            rods.update(pool.run(_task_rods, items, init, progress, done + len(rod_items), total, rods_cb))
        repredicted["first_prediction"] = "nominal" if predict_with is None else "an earlier pass's refit"
    fit = fit or predict_with
    if on_frame is not None:  # frames whose rods could not be looked for
        for i in obs_idx:
            if i not in rods:
                on_frame(frame_info(i, frames[i].phase, boards[i], {"reason": placement_reason or "no prediction"}))
    if progress and reported[0] < total:
        progress(total, total)
    # -- assemble --------------------------------------------------------------------------------
    out_frames = []
    phases: dict[str, dict[str, Any]] = {}
    for i in obs_idx:
        f = frames[i]
        ph = phases.setdefault(
            f.phase, {"frames": 0, "board": 0, "rods": 0, "rods_total": 0, "corners_rejected": 0, "missing": {}}
        )
        ph["frames"] += 1
        ph["rods_total"] += 8
        missing: dict[str, str] = {}
        b = boards[i]
        board = None
        if "image_error" in b:
            missing["image"] = b["image_error"]
        elif "pose" in b:
            board = b["pose"]
            ph["board"] += 1
            ph["corners_rejected"] += int(board.get("corners_rejected") or 0)
        else:
            missing["board"] = b["reason"]
        legs: dict[str, list] = {str(k): [None, None] for k in range(1, 5)}
        r = rods.get(i)
        par = {}
        for leg, rod in ROD_KEYS:
            key = rod_name(leg, rod)
            if "image" in missing:
                missing[key] = "image unreadable"
            elif r is None:
                missing[key] = placement_reason or "no prediction"
            elif "reason" in r:
                missing[key] = r["reason"]
            else:
                v = r["rods"][key]
                if isinstance(v, str):
                    missing[key] = v
                else:
                    legs[str(leg + 1)][rod] = v
                    ph["rods"] += 1
        if r is not None and "parallel_mrad" in r:
            par = r["parallel_mrad"]
        for k, v in missing.items():
            kind = "board" if k == "board" else ("image" if k == "image" else "rod")
            label = f"{kind}: {_short(v)}"
            ph["missing"][label] = ph["missing"].get(label, 0) + 1
            per_frame.setdefault(i, []).append(f"{k}: {v}")
        fr: dict[str, Any] = {
            "phase": f.phase,
            "q": list(f.q),
            "board": board,
            "legs": legs,
            "missing": missing,
            "image": f.image,
            "dataset_frame": i,
            "leg_parallel_mrad": par,
        }
        extra = f.model_extra or {}
        if "truth" in extra:
            fr["truth"] = extra["truth"]
        out_frames.append(fr)
    summary = {
        "phases": phases,
        "frames": {str(k): v for k, v in sorted(per_frame.items())},
        "camera": intr.summary() if intr else {"source": "given" if not need_calib else "dataset"},
        "placement": {"ok": C is not None, "rms_m": placement_rms, "reason": placement_reason, "detected": fallback},
        "repredicted": repredicted,
    }
    extraction = {
        "camera": camera.to_dict(),
        "summary": summary,
        "camera_from_base_coarse": C.to_dict() if C else None,
        "ee_from_board_coarse": E.to_dict() if E else None,
        "rod_settings": rs_dict,
        "min_corners": opts.min_corners,
    }
    obs = {"format": FORMAT, "nominal": doc.nominal.model_dump(), "frames": out_frames, "extraction": extraction}
    dextra = doc.model_extra or {}
    if "truth" in dextra:
        obs["truth"] = dextra["truth"]
    return ExtractionResult(obs, summary, camera, intr, C, E, fit)


def _refit_inputs(ds: Dataset, camera: CameraModel) -> tuple[I4Parameters, float, float, float]:
    """What a refit of the rods' prediction takes from the dataset and camera: the nominal parameters, the focal
    length (px), the rods' spacing (m) and the board's height above the end-effector (m)."""
    doc = ds.document
    spacing = doc.legs.rod_spacing_m if doc.legs.rod_spacing_m is not None else 0.0
    height = float((doc.board.model_extra or {}).get("height_above_ee_m", 0.0))
    return doc.nominal.parameters(), float(np.sqrt(camera.K[0, 0] * camera.K[1, 1])), spacing, height


def _repredict(
    ds: Dataset,
    camera: CameraModel,
    boards: dict[int, dict[str, Any]],
    rods: dict[int, Any],
    C: Rigid,
    E: Rigid,
    min_shift_px: float,
    start: Repredicted | None = None,
) -> tuple[dict[str, Any], set[int], Repredicted | None]:
    """The rods' prediction refitted to the first pass (:func:`.repredict.refit_prediction`) and the frames whose
    prediction it moved by more than ``min_shift_px`` (to be measured again). Returns the summary's
    ``repredicted`` entry (``applied``: whether the refit is used), those frames and the refit. ``start``: the
    refit the frames were first measured with (an earlier pass's), else the nominal model with ``C``."""
    nominal, f_px, spacing, height = _refit_inputs(ds, camera)
    idx = sorted(rods)
    q = np.array([ds.frames[i].q for i in idx], dtype=np.float64).reshape(-1, 4)
    measured: list[MeasuredRod] = []
    poses: dict[int, Rigid] = {}
    for k, i in enumerate(idx):
        pose = boards.get(i, {}).get("pose")
        if pose is not None:
            poses[k] = Rigid(np.asarray(pose["R"]), np.asarray(pose["t"]))
        found_rods = rods[i].get("rods") or {}
        for leg, rod in ROD_KEYS:
            v = found_rods.get(rod_name(leg, rod))
            if isinstance(v, dict) and v.get("point") is not None:
                measured.append(MeasuredRod(k, leg, rod, np.asarray(v["point"]), np.asarray(v["u"])))
    try:
        C0, E0 = (start.camera_from_base, start.ee_from_board) if start is not None else (C, E)
        fit = refit_prediction(
            nominal, q, measured, poses, C0, E0, f_px, spacing, height, start=start.parameters if start else None
        )
    except (I4calError, np.linalg.LinAlgError, ValueError) as exc:
        return {"applied": False, "reason": f"refit failed: {exc}"}, set(), None
    if fit is None:
        return {"applied": False, "reason": "too few rods, or the refit did not bring them closer"}, set(), None
    try:
        first = rod_ends_camera(start.parameters if start else nominal, q, C0, spacing)[:2]
        second = rod_ends_camera(fit.parameters, q, fit.camera_from_base, spacing)[:2]
    except I4calError as exc:
        return {"applied": False, "reason": f"refitted model cannot close: {exc}"}, set(), None
    shift = prediction_shift_px(camera.K, (camera.width, camera.height), first, second)
    redo = {i for i, d in zip(idx, shift, strict=True) if d > min_shift_px}
    info = {
        "applied": bool(redo) or start is not None,
        **fit.summary(),
        "frames_measured_again": len(redo),
        "min_shift_px": min_shift_px,
    }
    info["max_shift_px"] = float(shift.max()) if shift.size else 0.0
    return info, redo, fit


def frame_info(i: int, phase: str, board: dict[str, Any], rods: dict[str, Any] | None = None) -> dict[str, Any]:
    """What extraction found in frame ``i`` (the ``on_frame`` report of :func:`extract_dataset`).

    Parameters
    ----------
    i : int
        Dataset frame index.
    phase : str
    board : dict
        The board stage's result: ``{"pose": {...}}``, ``{"reason": str}`` or ``{"image_error": str}``.
    rods : dict, optional
        The rods stage's result (``{"rods": {name: dict | reason}, ...}`` or ``{"reason" | "image_error": str}``);
        None after the board stage.

    Returns
    -------
    dict
        ``{"frame", "phase", "stage": "board" | "rods", "board": bool, "corners", "rms_px", "rods": int | None,
        "rods_total": 8, "missing": {what: reason}, "detections": {"board": {"R", "t"} | None, "legs": {...}}}``;
        ``detections`` has the observations v1 frame layout (camera frame, metres).
    """
    pose = board.get("pose")
    missing: dict[str, str] = {}
    if "image_error" in board:
        missing["image"] = board["image_error"]
    elif pose is None:
        missing["board"] = board.get("reason", "board not found")
    legs: dict[str, list] = {str(k): [None, None] for k in range(1, 5)}
    found = None
    if rods is not None:
        found = 0
        for leg, rod in ROD_KEYS:
            key = rod_name(leg, rod)
            if "image" in missing:
                missing[key] = "image unreadable"
            elif "rods" not in rods:
                missing[key] = rods.get("reason") or rods.get("image_error") or "no prediction"
            elif isinstance(rods["rods"][key], str):
                missing[key] = rods["rods"][key]
            else:
                legs[str(leg + 1)][rod] = rods["rods"][key]
                found += 1
    return {
        "frame": int(i),
        "phase": phase,
        "stage": "board" if rods is None else "rods",
        "board": pose is not None,
        "corners": None if pose is None else pose.get("n_corners"),
        "rms_px": None if pose is None else pose.get("rms_px"),
        "rods": found,
        "rods_total": len(ROD_KEYS),
        "missing": missing,
        "detections": {"board": None if pose is None else {"R": pose["R"], "t": pose["t"]}, "legs": legs},
    }
