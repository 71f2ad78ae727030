"""Dataset v1 -> observations v1: intrinsics, board poses and rods for every frame.

Stages (each over a process pool when ``workers > 1``, with ``progress(done, total)`` callbacks):

1. Intrinsics: given (argument), else from the dataset's ``camera`` (K, dist), else calibrated
   from the ``camera`` phase with :func:`calib.camera.intrinsics.calibrate_intrinsics` (calibrateCameraRO);
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
6. The camera refined by the rods (:func:`calib.vision.refine.refine_camera_by_rods`, a stage of its own run by
   :func:`extract_dataset` after the first pass) when it carries its calibration's covariance; then every frame is
   measured again with it (the board corners and the refitted prediction of the first pass reused), and the first
   pass measures on its refitted prediction only the frames the refinement uses (the ``poses`` phase). With the frames
   streamed during the acquisition, the second pass re-expresses them for the refined camera from the edge points the
   stream found (:mod:`calib.vision.rods.reexpress`: their images not measured again). When the camera did not move
   by ``ExtractOptions.refine_min_shift``, that second pass runs with the same camera.
7. Rods once more, when more than ``ExtractOptions.recover_lost_share`` of those looked for were lost in their search
   bands (:mod:`calib.vision.recover`): the prediction refitted robustly (each measured line its own rod, its leg's
   other rod or the gap between them; several starts) and every frame measured again, kept when it loses fewer rods
   (``summary.recovered``). This is for a bench so far off nominal that the prediction falls between the rods of
   most legs, where the refit of stage 5 can settle on a wrong geometry.

A frame whose image is missing or unreadable, a hidden board, a rod that leaves the image: each is
reported per frame (``missing`` in the frame, ``summary`` per phase) and the rest goes on.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from calib.camera.intrinsics import IntrinsicsResult, calibrate_intrinsics
from calib.errors import I4calError, InputError
from calib.formats.camera import CameraModel
from calib.formats.dataset import Dataset
from calib.formats.observations import FORMAT
from calib.model.kinematics import base_from_ee, dkm
from calib.model.parameters import I4Parameters
from calib.numerics.threads import single_threaded
from calib.numerics.transforms import Rigid
from calib.vision.board import BoardDetector
from calib.vision.detect import DetectSettings, resolve_frames
from calib.vision.handeye import fit_placement
from calib.vision.pool import (
    _Pool,
    _task_board,
    _task_board_pose,
    _task_corners,
    _task_detect,
    _task_find_rods,
    _task_reexpress,
    _task_rods,
)
from calib.vision.recover import STARTS as RECOVERY_STARTS
from calib.vision.recover import lost_in_search, measured_lines
from calib.vision.refine import REFINEMENT_PHASES, CameraRefinement, can_refine, refine_camera_by_rods
from calib.vision.repredict import MeasuredRod, Repredicted, prediction_shift_px, refit_prediction, rod_ends_camera
from calib.vision.rods import ROD_KEYS, RodSettings, rod_name

if TYPE_CHECKING:
    from calib.vision.stream import StreamedFrames

Progress = Callable[[int, int], None]
#: the reason of a frame's rods in a first pass that leaves them to the second (:func:`_extract`'s ``for_refinement``)
DEFERRED = "measured in the second pass, with the camera the rods refined"
FrameCallback = Callable[[dict[str, Any]], None]


#: What a dataset with neither intrinsics nor a ``camera`` phase says: how to get the intrinsics.
NO_INTRINSICS = (
    "no intrinsics: the dataset has neither camera.K/dist nor a 'camera' phase. Calibrate the camera once: "
    "`i4cal camera calibrate --bench BENCH.toml -o camera.json` (hand-held board views, docs/camera.md), then name it "
    'in the bench file (`[camera] intrinsics = "camera.json"`) so that `i4cal acquire` records it in every dataset, '
    "or give it to this dataset with `--camera camera.json` (i4cal extract, i4cal calibrate)"
)


#: the phases whose rods something reads (docs/observations.md): the methods (``poses``, the lock phases) and the
#: report's leg residuals (``poses``, ``validation``); the others' frames need their boards (``rotation``,
#: ``translation``) or their encoders only (``line``)
ROD_PHASES: tuple[str, ...] = ("poses", "lock-1", "lock-2", "lock-3", "lock-4", "validation")
#: why a frame of another phase carries no rods (its ``missing["rods"]``)
RODS_NOT_READ = "not measured: no method reads the rods of this phase (extract --rod-phases all measures them)"


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
    #: the camera calibration's lens model (:data:`calib.camera.intrinsics.LENS_MODEL_CHOICES`): ``"auto"``
    #: chooses it from
    #: the ``camera`` phase's board views (:func:`calib.camera.intrinsics.calibrate_intrinsics`); None: the
    #: dataset's
    #: ``camera.lens_model`` (the bench file's), else ``"auto"``; a given camera keeps its own
    lens_model: str | None = None
    #: when more than this share of the rods looked for are lost in their search bands (:mod:`.recover`), refit the
    #: prediction robustly and measure every frame again (kept when it loses fewer); None: never (nor with
    #: ``repredict_px=None``: one pass on the nominal prediction)
    recover_lost_share: float | None = 0.05
    #: the rods' first pass, on the nominal prediction, measures one frame in ``first_pass_every`` (at least
    #: ``first_pass_min_frames`` of them, spread evenly; every frame when there are no more): enough to refit the
    #: prediction (on the paper's 121 frames, 25 of them refit it as closely as 41: 0.20 px median from the rods they
    #: measured), on which the other frames are then measured once (and the sampled ones again where it moved by more
    #: than ``repredict_px``)
    first_pass_every: int = 5
    first_pass_min_frames: int = 24
    #: the phases whose rods the observations carry (None: every phase): the rods of the others' frames are
    #: measured only where the first pass samples them to refit the prediction, and left out of the observations
    #: (``missing["rods"]``: :data:`RODS_NOT_READ`)
    rod_phases: tuple[str, ...] | None = ROD_PHASES


@dataclass
class ExtractionResult:
    """What :func:`extract_dataset` found.

    Attributes
    ----------
    observations : dict
        An observations v1 document (validates with :meth:`calib.formats.observations.Observations.from_dict`).
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
    #: the camera's refinement by the rods (:func:`.refine.refine_camera_by_rods`), when asked for
    camera_refinement: CameraRefinement | None = None
    #: frames whose rods this pass left to the next one (measured only where the camera's refinement needs them)
    deferred: int = 0
    #: the rods stage's results of the frames measured on this pass's final prediction (each with its measured rods
    #: and their edge points, ``"edges"``): the next pass re-expresses them for its camera
    #: (:mod:`calib.vision.rods.reexpress`) instead of measuring them again
    rods: dict[int, Any] | None = None


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
        calibrated by :func:`calib.camera.intrinsics.calibrate_intrinsics` carries the board corners it refined
        (``calibration.board_points``): they are used for the board poses when the board has as many corners.
    workers : int, optional
        Processes (default: ``os.cpu_count()``); 1 runs in this process.
    progress : callable(done, total), optional
        Called after every frame of every stage (``total`` counts all stages).
    options : ExtractOptions, optional
        Settings of the stages (board corners, rods, placement, passes); default ``ExtractOptions()``.
    on_frame : callable(info), optional
        Called with what was found in each non-``camera`` frame, once after the board stage and once after the
        rods stage (:func:`frame_info`).
    streamed : StreamedFrames, optional
        Frames measured during the acquisition (:mod:`calib.vision.stream`): the passes take their boards and rods
        from it where they hold the frame's answer, and measure the others.

    Returns
    -------
    ExtractionResult
        The observations v1 document (board poses and rod axes in the camera frame, metres and radians), the
        summary, the camera used (refined by the rods when that applied) and the coarse ``camera_from_base``.

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

    from threadpoolctl import threadpool_limits

    # one BLAS thread in this process, as in the workers (calib.numerics.threads): the extraction's matrices are small,
    # more
    # threads only spin (a quarter more CPU with one worker, for the same result within float rounding).
    # Streaming: frames measured during the acquisition answer from the pool (calib.vision.stream)
    pool_cm = _Pool(workers) if streamed is None else streamed.pool(workers, ds)
    # one worker is this process alone: one OpenCV thread too, as each worker of a pool runs
    limits = single_threaded() if workers == 1 else threadpool_limits(limits=1)
    with pool_cm as pool, limits:
        corners: dict[int, list] = {}
        # 1. the boards and rods measured with the camera given, the dataset's or calibrated
        res = _extract(
            pool,
            ds,
            camera,
            pass_progress,
            opts,
            on_frame,
            keep_images=opts.refine_camera,
            corners=corners,
            # streaming measured every frame already, on the nominal prediction and on a refit: the first pass refits
            # to all of them (as the stream did, so that its refitted measurements are taken), and the refined
            # camera's pass re-expresses them all
            for_refinement=opts.refine_camera and streamed is None,
            sample=streamed is None,
        )
        if opts.refine_camera:
            # 2. the camera refined by those rods, 3. the frames measured again with it
            refinement = refine_camera_by_rods(res.observations, res.camera, opts.refine_min_shift)
            # streamed, every frame is re-expressed for it from its edge points, which keeps the result seconds after
            # the motion; measured here, the frames are measured again with it (the fit poses' limb-line scatter then
            # matches the design's prediction: tests/calib/test_design.py)
            res = _measure_with_refined_camera(
                pool, ds, res, refinement, opts, on_frame, corners, pass_progress, next_pass, streamed is not None
            )
        # 4. the rods lost in their search bands recovered
        res = _recover(pool, ds, res, opts, on_frame, corners, pass_progress, next_pass)
    return res


def _measure_with_refined_camera(
    pool: _Pool,
    ds: Dataset,
    first: ExtractionResult,
    refinement: CameraRefinement,
    opts: ExtractOptions,
    on_frame: FrameCallback | None,
    corners: dict[int, list],
    progress: Progress,
    next_pass: Callable[[], None],
    reexpress: bool = False,
) -> ExtractionResult:
    """The frames measured again with the refined camera, on the first pass's refitted prediction and board corners
    (``reexpress``: the first pass's rods re-expressed for it where they carry their edge points, the rest measured);
    the first pass when the camera was not refined. The refinement is recorded in the summary
    (``camera.refined_by_rods``) and kept in the result (``camera_refinement``)."""
    if refinement.camera is None and not first.deferred:
        first.summary["camera"]["refined_by_rods"] = refinement.info
        first.camera_refinement = refinement
        return first
    # the refined camera, or the same when the refinement was not applied and the first pass left frames to this one
    next_pass()
    res = _extract(
        pool,
        ds,
        refinement.camera or first.camera,
        progress,
        opts,
        on_frame,
        corners=corners,
        predict_with=first.repredicted,
        predicted_from=first.camera_from_base,
        reexpress=first.rods if reexpress else None,
    )
    _carry_over(ds, first, res, {**first.summary["camera"], "refined_by_rods": refinement.info})
    res.camera_refinement = refinement
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


@dataclass
class _Ticker:
    """A pass's progress: frames done and the pass's total (both grow as stages are added), and the last count
    reported (the end is reported once, whatever the stages reported)."""

    progress: Progress | None
    done: int = 0
    total: int = 0
    reported: int = -1

    def report(self, done: int, tot: int) -> None:
        self.reported = done
        if self.progress is not None:
            self.progress(done, tot)

    @property
    def callback(self) -> Progress | None:
        """What the pool calls: None without a progress callback."""
        return self.report if self.progress is not None else None

    def finish(self) -> None:
        if self.progress is not None and self.reported < self.total:
            self.report(self.total, self.total)


@dataclass
class CameraStage:
    """The camera a pass measures with: given, the dataset's, or calibrated from its ``camera`` phase.

    Attributes
    ----------
    camera : CameraModel
    intrinsics : IntrinsicsResult or None
        When calibrated from the ``camera`` phase.
    summary : dict
        The summary's ``camera`` entry.
    """

    camera: CameraModel
    intrinsics: IntrinsicsResult | None
    summary: dict[str, Any]


@dataclass
class Placement:
    """The coarse camera placement fitted to the board poses (:func:`.placement.fit_placement`).

    Attributes
    ----------
    camera_from_base, ee_from_board : Rigid or None
        None when there are too few board poses or the fit is inconsistent (``reason`` says).
    rms_m : float or None
        The board poses' residual RMS (m).
    reason : str or None
    """

    camera_from_base: Rigid | None
    ee_from_board: Rigid | None
    rms_m: float | None
    reason: str | None


@dataclass
class _Pass:
    """What one pass over the dataset works with: the pool, the dataset, the settings, the frames measured (not the
    ``camera`` phase), the workers' initialisation (root, camera, refined board points, min corners, rod settings,
    keep images), the per-frame reasons and the progress."""

    pool: _Pool
    ds: Dataset
    opts: ExtractOptions
    obs_idx: list[int]
    rs_dict: dict[str, Any]
    per_frame: dict[int, list[str]]
    ticker: _Ticker
    on_frame: FrameCallback | None
    init: tuple = ()
    #: the phases whose frames the rods stage measures on the refitted prediction (None: all); the others are left
    #: for the next pass, which measures every frame again with the camera the rods refined
    measure_phases: tuple[str, ...] | None = None
    deferred: int = 0
    #: the frames whose rods were measured (or re-expressed) on the pass's final prediction
    on_final: set[int] = field(default_factory=set)
    #: frames whose rods the pass measured in their images (each time), and re-expressed from an earlier pass
    measured: int = 0
    reexpressed: int = 0

    def rods_read(self, i: int) -> bool:
        """Whether frame ``i``'s rods go into the observations (its phase in ``opts.rod_phases``)."""
        phases = self.opts.rod_phases
        return phases is None or self.ds.frames[i].phase in phases


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
    for_refinement: bool = False,
    reexpress: dict[int, Any] | None = None,
    sample: bool = True,
) -> ExtractionResult:
    """One pass over the dataset. ``keep_images``: the workers keep the decoded images after the rods stage (a
    second pass follows); ``corners``: filled with each frame's ChArUco corners when empty, reused (the pose
    only) when not. ``for_refinement``: a second pass follows in any case when the camera can be refined by the rods
    (it carries its calibration's covariance): after the refit, only the frames of the phases the refinement uses
    (:data:`.refine.REFINEMENT_PHASES`) are measured (``ExtractionResult.deferred`` counts the others).
    ``sample``: the rods' first pass on the nominal prediction measures a sample of the frames
    (:func:`_first_sample`), else all of them. ``reexpress``: an earlier pass's rods results on its final prediction
    (``ExtractionResult.rods``), re-expressed for this pass's camera instead of measured again
    (:func:`_reexpress_stage`).

    Stages: the camera (:func:`_camera_stage`), the boards (:func:`_board_stage`), the coarse placement
    (:func:`_placement_stage`), the rods found from scratch without one (:func:`_detect_stage`), the rods measured
    on the prediction (:func:`_rods_stage`) and again on its refit (:func:`_repredict_stage`), the observations
    assembled (:func:`_assemble`).
    """
    frames = ds.frames
    rs = opts.rods or RodSettings()
    ps = _Pass(
        pool,
        ds,
        opts,
        [i for i, f in enumerate(frames) if f.phase != "camera"],
        dict(rs.__dict__),
        {},
        _Ticker(progress),
        on_frame,
    )
    cam = _camera_stage(ps, camera, prefetch_boards=not corners)
    if for_refinement and can_refine(cam.camera):
        ps.measure_phases = REFINEMENT_PHASES
    ps.init = (str(ds.root), cam.camera.to_dict(), _refined_points(ds, cam.camera), opts.min_corners, ps.rs_dict)
    ps.init = (*ps.init, keep_images)
    boards = _board_stage(ps, corners)
    place = _placement_stage(ps, boards)
    C, E = place.camera_from_base, place.ee_from_board
    if predict_with is not None and predicted_from is not None and C is not None:
        # an earlier pass's refit, moved with the camera frame (another camera moves the board poses, hence the
        # coarse placement, by the same transform)
        predict_with = replace(
            predict_with, camera_from_base=C @ predicted_from.inverse() @ predict_with.camera_from_base
        )
    found: dict[int, Any] = {}
    fallback = None
    if C is None and opts.detect_fallback:  # no placement: the rods are found from scratch in each frame
        found, fallback = _detect_stage(ps, cam.camera, boards)
    rod_items = _rod_items(ps, boards, place, found, predict_with)
    refit = C is not None and E is not None and not found and opts.repredict_px is not None
    if refit and predict_with is None:  # the first pass: its rods refit the prediction, whatever their phase
        first = _first_sample(rod_items, opts) if sample else rod_items
    else:  # measured for the observations only
        first = [it for it in rod_items if ps.rods_read(it[0])]
    rods = _rods_stage(ps, boards, first, reexpress)
    if not refit or predict_with is not None:  # measured on the pass's final prediction (unless the refit moves it)
        ps.on_final.update(rods)
    repredicted: dict[str, Any] | None = None
    fit: Repredicted | None = None
    if refit:
        repredicted, fit = _repredict_stage(ps, cam.camera, boards, rods, rod_items, len(first), place, predict_with)
    fit = fit or predict_with
    if on_frame is not None:  # frames whose rods are not read, or could not be looked for
        for i in ps.obs_idx:
            if not ps.rods_read(i):
                on_frame(frame_info(i, frames[i].phase, boards[i], {"not_read": True}))
            elif i not in rods:
                on_frame(frame_info(i, frames[i].phase, boards[i], {"reason": place.reason or "no prediction"}))
    ps.ticker.finish()
    return _assemble(ps, cam, boards, rods, place, fallback, repredicted, fit)


def _camera_stage(ps: _Pass, camera: CameraModel | None, prefetch_boards: bool = False) -> CameraStage:
    """The camera given, else the dataset's, else calibrated from the ``camera`` phase's board views (their
    rejections recorded in ``ps.per_frame``). Sets the pass's progress total (camera views, boards, rods).
    ``prefetch_boards``: while one worker calibrates the camera, the others detect the other frames' boards (the
    detection does not depend on the camera), which :func:`_board_stage` then poses."""
    doc, frames, opts = ps.ds.document, ps.ds.frames, ps.opts
    cam_idx = [i for i, f in enumerate(frames) if f.phase == "camera"]
    root = str(ps.ds.root)
    intr: IntrinsicsResult | None = None
    need_calib = camera is None and (doc.camera.K is None or doc.camera.dist is None)
    ps.ticker.total = (len(cam_idx) if need_calib else 0) + 2 * len(ps.obs_idx)
    if camera is None and not need_calib:
        camera = doc.camera.camera_model()  # with the camera file's calibration when the acquisition recorded one
    if need_calib:
        if not cam_idx:
            raise InputError(NO_INTRINSICS, file=root, field="camera")
        t = ps.ticker
        init = (root, None, None, opts.min_corners, ps.rs_dict)
        board = BoardDetector(doc.board)
        fit_args = (
            cam_idx,
            (doc.camera.width, doc.camera.height),
            board.ids_all,
            board.points_nominal,
            opts.lens_model or (doc.camera.model_extra or {}).get("lens_model") or "auto",
        )
        boards_beside = ps.obs_idx if prefetch_boards else []
        det, intr = ps.pool.run_beside(_detect_and_calibrate, fit_args, _task_corners, boards_beside, init)
        t.done += len(cam_idx)
        t.report(t.done, t.total)
        for i, r in det:
            if isinstance(r, str):
                ps.per_frame.setdefault(i, []).append(f"image: {r}")
        for i, reason in intr.rejected.items():
            ps.per_frame.setdefault(i, []).append(f"camera view rejected: {reason}")
        camera = intr.camera
    assert camera is not None
    return CameraStage(camera, intr, intr.summary() if intr else {"source": "given" if not need_calib else "dataset"})


def _detect_and_calibrate(args: tuple) -> tuple[list[tuple[int, Any]], IntrinsicsResult]:
    """The ``camera`` phase's board views detected (:func:`.pool._task_detect`: corners, or why none) and the camera
    calibrated from those found (:func:`calib.camera.intrinsics.calibrate_intrinsics`), from ``(view frames, image
    size, board ids, board points, lens model)``: one task, which a worker runs while the others detect the other
    frames' boards (:meth:`calib.vision.pool._Pool.run_beside`). Returns each view's detection and the calibration."""
    cam_idx, size, ids_all, points, lens_model = args
    det = [_task_detect(i) for i in cam_idx]
    views = {
        i: (np.asarray(r[0], dtype=int), np.asarray(r[1]).reshape(-1, 2), None)
        for i, r in det
        if not isinstance(r, str)
    }
    return det, calibrate_intrinsics(views, size, ids_all, points, lens_model=lens_model)


def _refined_points(ds: Dataset, camera: CameraModel) -> tuple[list, list, Any] | None:
    """The board geometry the camera's calibration refined (calibrateCameraRO: ids, points (m), and how they move
    with the intrinsics), when it has as many corners as the board; else None (the nominal geometry)."""
    bp = (camera.extra.get("calibration") or {}).get("board_points") or {}
    if bp.get("ids") is not None and len(bp["ids"]) == BoardDetector(ds.document.board).ids_all.size:
        return (list(bp["ids"]), list(bp["points_m"]), bp.get("d_intrinsics"))
    return None


def _board_stage(ps: _Pass, corners: dict[int, list] | None) -> dict[int, dict[str, Any]]:
    """Every measured frame's board: ``{"pose": ...}``, ``{"reason": ...}`` or ``{"image_error": ...}``. The corners
    of an earlier pass (``corners`` not empty) are posed again with this camera; ``corners`` is filled."""
    frames, obs_idx, t = ps.ds.frames, ps.obs_idx, ps.ticker
    on_frame = ps.on_frame
    board_cb = None if on_frame is None else (lambda r: on_frame(frame_info(r[0], frames[r[0]].phase, r[1])))
    if corners:  # a second pass: the corners found in the first, posed with this camera
        again = [i for i in obs_idx if i in corners]
        items = [(i, *corners[i]) for i in again]
        boards = dict(ps.pool.run(_task_board_pose, items, ps.init, t.callback, t.done, t.total, board_cb))
        rest = [i for i in obs_idx if i not in corners]
        boards.update(ps.pool.run(_task_board, rest, ps.init, t.callback, t.done + len(again), t.total, board_cb))
    else:
        boards = dict(ps.pool.run(_task_board, obs_idx, ps.init, t.callback, t.done, t.total, board_cb))
    if corners is not None:
        corners.update({i: b["corners"] for i, b in boards.items() if "corners" in b})
    t.done += len(obs_idx)
    return boards


def _placement_stage(ps: _Pass, boards: dict[int, dict[str, Any]]) -> Placement:
    """The coarse placement fitted to the board poses with the nominal model, or why there is none."""
    doc, frames, opts = ps.ds.document, ps.ds.frames, ps.opts
    good = [i for i in ps.obs_idx if "pose" in boards[i]]
    if len(good) < opts.min_placement_frames:
        return Placement(
            None,
            None,
            None,
            f"no coarse camera placement: board poses in {len(good)} frames, need {opts.min_placement_frames}",
        )
    qk = np.array([frames[i].q for i in good])
    bR = np.array([boards[i]["pose"]["R"] for i in good])
    bt = np.array([boards[i]["pose"]["t"] for i in good])
    try:
        height = float((doc.board.model_extra or {}).get("height_above_ee_m", 0.0))
        C, E, rms = fit_placement(qk, bR, bt, doc.nominal.parameters(), height)
    except (I4calError, np.linalg.LinAlgError, ValueError) as exc:
        return Placement(None, None, None, f"coarse camera placement failed: {exc}")
    if rms > opts.max_placement_rms_m:
        reason = (
            f"coarse camera placement inconsistent: board residual RMS "
            f"{rms * 1e3:.1f} mm > {opts.max_placement_rms_m * 1e3:.0f} mm "
            "(too few board poses, or too little motion among them)"
        )
        return Placement(None, None, rms, reason)
    return Placement(C, E, rms, None)


def _detect_stage(
    ps: _Pass, camera: CameraModel, boards: dict[int, dict[str, Any]]
) -> tuple[dict[int, Any], dict[str, Any]]:
    """No placement: each frame's rods found and associated from scratch (:mod:`calib.vision.detect`), the frames
    resolved together. Returns the detections by frame and the summary's ``placement.detected``."""
    doc, frames, opts, t = ps.ds.document, ps.ds.frames, ps.opts, ps.ticker
    dset = opts.detect or DetectSettings()
    prior = opts.camera_prior.to_dict() if opts.camera_prior is not None else None
    items: list[tuple] = [(i, prior, dict(dset.__dict__)) for i in ps.obs_idx if "image_error" not in boards[i]]
    t.total += len(items)
    found = {
        i: d for i, d in ps.pool.run(_task_find_rods, items, ps.init, t.callback, t.done, t.total) if d is not None
    }
    t.done += len(items)
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
    return found, fallback


def _nominal_board(ps: _Pass, i: int, place: Placement) -> dict[str, Any] | None:
    """Frame ``i``'s board pose predicted by the nominal model and the coarse placement (an occluder where the board
    was not measured), or None."""
    C, E = place.camera_from_base, place.ee_from_board
    if C is None or E is None:
        return None
    try:
        nom = ps.ds.document.nominal.parameters()
        nb = C @ Rigid(*base_from_ee(nom, dkm(nom, np.asarray(ps.ds.frames[i].q)))) @ E
    except I4calError:
        return None
    return {"R": nb.R.tolist(), "t": nb.t.tolist()}


def _rod_items(
    ps: _Pass,
    boards: dict[int, dict[str, Any]],
    place: Placement,
    found: dict[int, Any],
    predict_with: Repredicted | None,
) -> list[tuple]:
    """The rods stage's tasks: (frame, camera_from_base, board occluder[, detection | None, seven parameters])."""
    C = place.camera_from_base
    rod_items: list[tuple] = []
    for i in ps.obs_idx:
        if i in found:
            cfb = found[i].camera_from_base
            rod_items.append((i, cfb.to_dict() if cfb is not None else None, boards[i].get("pose"), found[i]))
            continue
        if "image_error" in boards[i] or C is None:
            continue
        b = boards[i].get("pose")
        if b is None:
            b = _nominal_board(ps, i, place)
        if predict_with is not None:  # the refit of an earlier pass
            rod_items.append((i, predict_with.camera_from_base.to_dict(), b, None, predict_with.parameters.vector()))
        else:
            rod_items.append((i, C.to_dict(), b))
    return rod_items


def _rods_cb(ps: _Pass, boards: dict[int, dict[str, Any]]) -> Callable[[Any], None] | None:
    """The rods stage's per-frame report (``on_frame``), or None."""
    on_frame, frames = ps.on_frame, ps.ds.frames
    if on_frame is None:
        return None
    # a frame whose rods are not read is reported once, at the pass's end (_extract)
    return lambda r: on_frame(frame_info(r[0], frames[r[0]].phase, boards[r[0]], r[1])) if ps.rods_read(r[0]) else None


def _rods_stage(
    ps: _Pass, boards: dict[int, dict[str, Any]], items: list[tuple], reexpress: dict[int, Any] | None
) -> dict[int, Any]:
    """The rods of the frames in ``items``: re-expressed from an earlier pass's results where it has them
    (:func:`_reexpress_stage`), measured in the images otherwise (:func:`calib.vision.pool._task_rods`)."""
    rods = _reexpress_stage(ps, boards, items, reexpress) if reexpress else {}
    measure = [it for it in items if it[0] not in rods]
    ps.reexpressed, ps.measured = len(rods), len(measure)
    t = ps.ticker
    rods.update(
        ps.pool.run(_task_rods, measure, ps.init, t.callback, t.done + len(rods), t.total, _rods_cb(ps, boards))
    )
    return rods


def _reexpress_stage(
    ps: _Pass,
    boards: dict[int, dict[str, Any]],
    items: list[tuple],
    earlier: dict[int, Any],
) -> dict[int, Any]:
    """The rods of the frames in ``items`` re-expressed for the pass's camera from an earlier pass's results (their
    edge points, :func:`calib.vision.rods.reexpress.reexpress_frame`, over the pool) where it has them; the other frames
    are left out, for the rods stage to measure."""
    t = ps.ticker
    todo = [(it[0], earlier[it[0]]) for it in items if (earlier.get(it[0]) or {}).get("edges")]
    done = ps.pool.run(_task_reexpress, todo, ps.init, t.callback, t.done, t.total, _rods_cb(ps, boards))
    out: dict[int, Any] = {}
    for i, r in done:
        kept = {n: e for n, e in earlier[i]["edges"].items() if isinstance(r["rods"].get(n), dict)}
        out[i] = {**r, "edges": kept}
    return out


def _repredict_stage(
    ps: _Pass,
    camera: CameraModel,
    boards: dict[int, dict[str, Any]],
    rods: dict[int, Any],
    rod_items: list[tuple],
    n_first: int,
    place: Placement,
    predict_with: Repredicted | None,
) -> tuple[dict[str, Any], Repredicted | None]:
    """The prediction refitted to the rods measured (:func:`_repredict`), the frames it moved measured again on it
    and the frames not measured yet (``rod_items`` beyond the ``n_first`` of the first sample) measured on it, else
    on the first prediction when there is no refit (``rods`` updated). Returns the summary's ``repredicted`` entry
    and the refit."""
    assert place.camera_from_base is not None and place.ee_from_board is not None
    t = ps.ticker
    repredicted, redo, fit = _repredict(
        ps.ds,
        camera,
        boards,
        rods,
        place.camera_from_base,
        place.ee_from_board,
        cast("float", ps.opts.repredict_px),
        predict_with,
    )
    redo = {i for i in redo if ps.rods_read(i)}  # a frame whose rods only refit the prediction is not measured again
    if "frames_measured_again" in repredicted:
        repredicted["frames_measured_again"] = len(redo)
    moved = set(redo)
    # not in the first sample: measured once, on the refit (the frames whose rods go into the observations)
    later = {it[0] for it in rod_items if ps.rods_read(it[0])} - set(rods)
    if fit is not None and ps.measure_phases is not None:  # the others: by the next pass, with the refined camera
        left = {i for i in later if ps.ds.frames[i].phase not in ps.measure_phases}
        rods.update({i: {"reason": DEFERRED} for i in sorted(left)})
        later -= left
        # the sampled frames of those phases keep their first measurement (the refinement does not use it)
        kept = {i for i in redo if ps.ds.frames[i].phase not in ps.measure_phases}
        redo = redo - kept
        ps.deferred = len(left) + len(kept)
        repredicted["frames_measured_again"] = len(redo)
    items = [
        it if fit is None else (it[0], fit.camera_from_base.to_dict(), it[2], None, fit.parameters.vector())
        for it in rod_items
        if it[0] in later or (fit is not None and it[0] in redo)
    ]
    if items:
        ps.measured += len(items)
        t.total += len(items) - len(later)
        rods.update(
            ps.pool.run(_task_rods, items, ps.init, t.callback, t.done + n_first, t.total, _rods_cb(ps, boards))
        )
    if fit is None:  # the first prediction is the final one
        ps.on_final.update(rods)
    else:  # the frames it did not move and those measured on it
        ps.on_final.update(i for i in rods if i not in moved)
        ps.on_final.difference_update(moved)
        ps.on_final.update(it[0] for it in items)
    repredicted["first_prediction"] = "nominal" if predict_with is None else "an earlier pass's refit"
    if later:
        repredicted["first_sample_frames"] = n_first
        repredicted["frames_measured_on_the_refit_only"] = len(later) if fit is not None else 0
        repredicted["applied"] = repredicted["applied"] or fit is not None
    return repredicted, fit


def _first_sample(rod_items: list[tuple], opts: ExtractOptions) -> list[tuple]:
    """The frames measured on the first (nominal) prediction, to refit it: one in ``opts.first_pass_every``, and at
    least ``opts.first_pass_min_frames``, spread evenly over the frames (all of them when there are no more)."""
    n = len(rod_items)
    k = max(int(opts.first_pass_min_frames), -(-n // max(1, int(opts.first_pass_every))))
    if k >= n:
        return rod_items
    return [rod_items[i] for i in sorted({round(j * (n - 1) / (k - 1)) for j in range(k)})]


def _frame_record(
    ps: _Pass,
    i: int,
    board_res: dict[str, Any],
    r: dict[str, Any] | None,
    placement_reason: str | None,
    ph: dict[str, Any],
) -> dict[str, Any]:
    """Frame ``i``'s observations v1 record from its board and rods results; counts it in its phase's ``ph``."""
    f = ps.ds.frames[i]
    ph["frames"] += 1
    read = ps.rods_read(i)
    ph["rods_total"] += 8 if read else 0
    missing: dict[str, str] = {}
    board = None
    if "image_error" in board_res:
        missing["image"] = board_res["image_error"]
    elif "pose" in board_res:
        board = board_res["pose"]
        ph["board"] += 1
        ph["corners_rejected"] += int(board.get("corners_rejected") or 0)
    else:
        missing["board"] = board_res["reason"]
    if read:
        legs = _frame_legs(r, missing, placement_reason, ph)
        par = r["parallel_mrad"] if r is not None and "parallel_mrad" in r else {}
    else:  # (a first-pass measurement, on a prediction and camera not final, is not kept)
        legs, par = {str(k): [None, None] for k in range(1, 5)}, {}
        ph["rods_not_read"] += 8
    for k, v in missing.items():
        kind = "board" if k == "board" else ("image" if k == "image" else "rod")
        label = f"{kind}: {_short(v)}"
        ph["missing"][label] = ph["missing"].get(label, 0) + 1
        ps.per_frame.setdefault(i, []).append(f"{k}: {v}")
    if not read:  # said in the frame, not counted as missing
        missing["rods"] = RODS_NOT_READ
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
    return fr


def _frame_legs(
    r: dict[str, Any] | None, missing: dict[str, str], placement_reason: str | None, ph: dict[str, Any]
) -> dict[str, list]:
    """A frame's rods by leg (``{"1": [rod0, rod1], ...}``, None where missing, the reason in ``missing``)."""
    legs: dict[str, list] = {str(k): [None, None] for k in range(1, 5)}
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
    return legs


def _assemble(
    ps: _Pass,
    cam: CameraStage,
    boards: dict[int, dict[str, Any]],
    rods: dict[int, Any],
    place: Placement,
    fallback: dict[str, Any] | None,
    repredicted: dict[str, Any] | None,
    fit: Repredicted | None,
) -> ExtractionResult:
    """The pass's observations v1 document, summary and result."""
    doc = ps.ds.document
    out_frames = []
    phases: dict[str, dict[str, Any]] = {}
    for i in ps.obs_idx:
        ph = phases.setdefault(
            ps.ds.frames[i].phase,
            {
                "frames": 0,
                "board": 0,
                "rods": 0,
                "rods_total": 0,
                "rods_not_read": 0,
                "corners_rejected": 0,
                "missing": {},
            },
        )
        out_frames.append(_frame_record(ps, i, boards[i], rods.get(i), place.reason, ph))
    C, E = place.camera_from_base, place.ee_from_board
    summary = {
        "phases": phases,
        "frames": {str(k): v for k, v in sorted(ps.per_frame.items())},
        "camera": cam.summary,
        "placement": {"ok": C is not None, "rms_m": place.rms_m, "reason": place.reason, "detected": fallback},
        "repredicted": repredicted,
        "rods_frames": {"measured": ps.measured, "reexpressed": ps.reexpressed},
    }
    extraction = {
        "camera": cam.camera.to_dict(),
        "summary": summary,
        "camera_from_base_coarse": C.to_dict() if C else None,
        "ee_from_board_coarse": E.to_dict() if E else None,
        "rod_settings": ps.rs_dict,
        "min_corners": ps.opts.min_corners,
    }
    obs = {"format": FORMAT, "nominal": doc.nominal.model_dump(), "frames": out_frames, "extraction": extraction}
    dextra = doc.model_extra or {}
    if "truth" in dextra:
        obs["truth"] = dextra["truth"]
    final = {i: r for i, r in rods.items() if i in ps.on_final and r.get("edges") and ps.rods_read(i)}
    return ExtractionResult(obs, summary, cam.camera, cam.intrinsics, C, E, fit, deferred=ps.deferred, rods=final)


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
        The rods stage's result (``{"rods": {name: dict | reason}, ...}`` or ``{"reason" | "image_error": str}``;
        ``{"not_read": True}`` for a frame of a phase whose rods the observations do not carry); None after the
        board stage.

    Returns
    -------
    dict
        ``{"frame", "phase", "stage": "board" | "rods", "board": bool, "corners", "rms_px", "rods": int | None,
        "rods_total": 8 (0 when not read), "missing": {what: reason}, "detections": {"board": {"R", "t"} | None,
        "legs": {...}}}``;
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
    total = len(ROD_KEYS)
    if rods is not None and rods.get("not_read"):  # a phase whose rods nothing reads (ExtractOptions.rod_phases)
        found, total = 0, 0
        missing["rods"] = RODS_NOT_READ
    elif rods is not None:
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
        "rods_total": total,
        "missing": missing,
        "detections": {"board": None if pose is None else {"R": pose["R"], "t": pose["t"]}, "legs": legs},
    }
