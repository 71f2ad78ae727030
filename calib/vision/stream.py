"""Frames measured one by one as an acquisition records them, for the extraction at the end (``streamed=``).

During an acquisition, each frame written to the dataset can be measured while the robot moves to the next pose
(:class:`FrameStreamer`, fed one frame index at a time by a worker beside the acquisition:
``drivers.acquisition.streaming``):

* the board (ChArUco corners and pose) exactly as extraction's board stage measures it (same detector, same camera,
  same refined board points), so that the final extraction takes it as it is;
* the eight rods on the nominal model's prediction, placed with the coarse camera placement
  (:func:`calib.vision.handeye.fit_placement`) fitted to the board poses measured so far (from
  ``ExtractOptions.min_placement_frames`` board poses on): extraction's first pass;
* the eight rods again on the prediction refitted to the rods and boards measured so far
  (:func:`calib.vision.repredict.refit_prediction`, every :data:`REFIT_EVERY` frames): extraction's later pass, which
  measures every frame again on a bench far from its nominal geometry;
* between frames (nothing waiting), the frames measured on an older placement or refit, measured again on the latest.

Each frame keeps its latest measurement of each kind. The final extraction fits the placement and the refit to every
frame: a frame's rods are taken from the measurement whose prediction lies nearest the extraction's, when within
:attr:`StreamedFrames.reuse_px` (:func:`calib.vision.repredict.prediction_shift_px`), else measured again.

What is not measured during the acquisition (the frames before the placement exists, a frame the worker failed on,
``camera`` phase frames, a dataset without intrinsics) is measured by the extraction at the end, as without
streaming. :class:`StreamedFrames` is what the worker hands over (JSON: :meth:`StreamedFrames.to_dict`);
:meth:`StreamedFrames.pool` is the extraction's process pool answering from it.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.errors import I4calError, InputError
from calib.formats.camera import CameraModel
from calib.formats.dataset import Dataset
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import Rigid
from calib.vision import pool as _pool
from calib.vision.board import BoardDetection, BoardDetector, BoardTracker, to_gray8
from calib.vision.handeye import fit_placement
from calib.vision.repredict import MeasuredRod, Repredicted, prediction_shift_px, refit_prediction
from calib.vision.rods import (
    ROD_KEYS,
    RodSettings,
    image_ideal_bbox,
    measure_rods,
    predict_rods,
    rod_name,
)
from calib.vision.rods.types import ROD_BOARD_OCCLUDER_M, rod_ends_camera

#: a rod measured on a provisional prediction is taken when the final prediction of its frame lies within this
#: (ideal px, :func:`calib.vision.repredict.prediction_shift_px`) of it: half the shift beyond which extraction's
#: own later pass measures a frame again (``ExtractOptions.repredict_px``, 3 px), well inside the rods' 18 px search
#: band. 0: only rods measured on the very prediction are taken (the extraction's bytes, rods measured again)
REUSE_PX = 1.5
#: the rods' prediction is refitted to what was measured (:func:`calib.vision.repredict.refit_prediction`) once
#: this many frames have rods, and again after as many more
REFIT_EVERY = 10
#: between frames, a frame is measured again when the latest placement or refit moves its prediction by more than
#: this (px)
REMEASURE_PX = 0.5


def _packed(measurement: dict[str, Any]) -> dict[str, Any]:
    """A streamed rods measurement with its edge points as base64 float64 (exact, a third of JSON lists' size)."""
    result = measurement.get("result") or {}
    edges = result.get("edges")
    if not edges:
        return measurement
    packed = {
        name: {
            "limbs_f8": [base64.b64encode(np.ascontiguousarray(a, "<f8").tobytes()).decode() for a in e[:2]],
            "middle": e[2],
        }
        for name, e in edges.items()
    }
    return {**measurement, "result": {**result, "edges": packed}}


def _unpacked(measurement: dict[str, Any]) -> dict[str, Any]:
    """:func:`_packed`'s measurement with its edge points as arrays again."""
    result = measurement.get("result") or {}
    edges = result.get("edges")
    if not edges:
        return measurement
    unpacked = {
        name: (
            *(np.frombuffer(base64.b64decode(b), "<f8").reshape(-1, 2) for b in e["limbs_f8"]),
            np.asarray(e["middle"], dtype=np.float64),
        )
        for name, e in edges.items()
    }
    return {**measurement, "result": {**result, "edges": unpacked}}


def _canon(x: Any) -> str:
    """A canonical text of a JSON-like value (numpy arrays as lists): equal texts, equal values."""
    return json.dumps(x, sort_keys=True, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


@dataclass
class StreamSettings:
    """What the per-frame measurement must share with the extraction that takes it (its ``ExtractOptions``)."""

    min_corners: int = 6
    rods: RodSettings | None = None
    min_placement_frames: int = 3
    max_placement_rms_m: float = 0.02
    reuse_px: float = REUSE_PX


@dataclass
class StreamedFrames:
    """What was measured during an acquisition, for :func:`calib.vision.extract.extract_dataset` (``streamed=``).

    Attributes
    ----------
    camera : dict
        The camera the frames were measured with (:meth:`CameraModel.to_dict`).
    refined : list or None
        The refined board points the board poses used (``[ids, points_m, d_intrinsics]``), as extraction passes them.
    min_corners : int
    rod_settings : dict
    boards : dict
        Frame index -> the board stage's result (``{"pose" | "reason", "corners"}`` or ``{"image_error"}``).
    rods : dict
        Frame index -> ``{kind: {"cfb": camera_from_base (dict), "seven": the seven parameters of the prediction
        (None: nominal), "board": board pose dict or None, "result": rods result}}``, ``kind`` ``"nominal"`` (the
        placement's prediction) or ``"refit"``.
    failed : dict
        Frame index -> why the worker could not measure it (measured at the end).
    reuse_px : float
    """

    camera: dict[str, Any]
    refined: list | None
    min_corners: int
    rod_settings: dict[str, Any]
    boards: dict[int, dict[str, Any]] = field(default_factory=dict)
    rods: dict[int, dict[str, Any]] = field(default_factory=dict)
    failed: dict[int, str] = field(default_factory=dict)
    reuse_px: float = REUSE_PX
    #: counts of what the extraction took from here (filled by :meth:`pool`'s runs)
    used: dict[str, int] = field(default_factory=lambda: {"boards": 0, "rods": 0, "rods_measured_again": 0})

    def to_dict(self) -> dict[str, Any]:
        """The frames as JSON values (floats keep every bit through Python's ``json``).

        Returns
        -------
        dict
            ``camera``, ``refined``, the measured boards and rods per frame (px, metres, radians as measured).
        """
        return {
            "camera": self.camera,
            "refined": self.refined,
            "min_corners": self.min_corners,
            "rod_settings": self.rod_settings,
            "boards": {str(k): v for k, v in self.boards.items()},
            "rods": {str(k): {kind: _packed(m) for kind, m in v.items()} for k, v in self.rods.items()},
            "failed": {str(k): v for k, v in self.failed.items()},
            "reuse_px": self.reuse_px,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StreamedFrames:
        """The frames :meth:`to_dict` wrote.

        Parameters
        ----------
        d : dict
            :meth:`to_dict`'s answer (read back from JSON).

        Returns
        -------
        StreamedFrames
        """
        return cls(
            camera=d["camera"],
            refined=d.get("refined"),
            min_corners=int(d["min_corners"]),
            rod_settings=dict(d["rod_settings"]),
            boards={int(k): v for k, v in d.get("boards", {}).items()},
            rods={int(k): {kind: _unpacked(m) for kind, m in v.items()} for k, v in d.get("rods", {}).items()},
            failed={int(k): str(v) for k, v in d.get("failed", {}).items()},
            reuse_px=float(d.get("reuse_px", REUSE_PX)),
        )

    def matches(self, init_args: tuple) -> bool:
        """Whether the extraction pool's worker settings are those the frames were measured with.

        Parameters
        ----------
        init_args : tuple
            The pool's worker settings ``(root, camera, refined, min_corners, rod_settings, keep)``.

        Returns
        -------
        bool
        """
        _root, camera, refined, min_corners, rod_settings = init_args[:5]
        return (
            _canon(camera) == _canon(self.camera)
            and _canon(refined) == _canon(self.refined)
            and int(min_corners) == self.min_corners
            and _canon(rod_settings) == _canon(self.rod_settings)
        )

    def pool(self, workers: int, dataset: Dataset) -> StreamedPool:
        """The extraction's pool (:class:`calib.vision.pool._Pool`) answering from these frames.

        Parameters
        ----------
        workers : int
            Worker processes for what the frames do not answer.
        dataset : Dataset
            The dataset being extracted.

        Returns
        -------
        StreamedPool
        """
        return StreamedPool(workers, self, dataset)


class StreamedPool(_pool._Pool):
    """Extraction's pool, answering the board stage and the rods stage from :class:`StreamedFrames` where they hold
    the frame's answer (same camera and settings; for the rods, a prediction within ``reuse_px``), the other frames
    measured as without it. Results, ``each`` callbacks and progress are given as :meth:`_Pool.run` gives them."""

    def __init__(self, workers: int, streamed: StreamedFrames, dataset: Dataset) -> None:
        super().__init__(workers)
        self.streamed = streamed
        self.dataset = dataset
        self._ends: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {}

    def run(
        self,
        fn: Callable,
        items: list,
        init_args: tuple,
        progress: _pool.Progress | None,
        offset: int,
        total: int,
        each: Callable[[Any], None] | None = None,
    ) -> list:
        """The pool's :meth:`calib.vision.pool._Pool.run`, answering boards and rods from the streamed frames where
        they hold the answer to the task's request (same camera and settings, prediction within ``reuse_px``).

        Parameters
        ----------
        fn : callable
            The task (``_task_board``, ``_task_rods``; any other runs in the pool).
        items : list
            The task's items.
        init_args : tuple
            The workers' settings.
        progress : callable(done, total), optional
            Progress over the whole extraction.
        offset, total : int
            Items done before this stage, and in all.
        each : callable(result), optional
            Called with each result as it comes.

        Returns
        -------
        list
            ``(frame index, answer)`` per item.
        """
        s = self.streamed
        if fn not in (_pool._task_board, _pool._task_rods) or not s.matches(init_args):
            return super().run(fn, items, init_args, progress, offset, total, each)
        known: dict[int, Any] = {}
        if fn is _pool._task_board:
            known = {k: (it, s.boards[it]) for k, it in enumerate(items) if it in s.boards}
            s.used["boards"] += len(known)
        else:
            known = self._rods_known(items)
        for n, r in enumerate(known.values(), start=1):
            if each:
                each(r)
            if progress:
                progress(offset + n, total)
        rest = [k for k in range(len(items)) if k not in known]
        measured = super().run(fn, [items[k] for k in rest], init_args, progress, offset + len(known), total, each)
        out: list = [None] * len(items)
        for k, r in known.items():
            out[k] = r
        for k, r in zip(rest, measured, strict=True):
            out[k] = r
        return out

    def _rods_known(self, items: list) -> dict[int, Any]:
        """The rods items answered from the stream: ``(i, cfb, board[, None, seven])`` whose frame was measured with
        the same board on a prediction within ``reuse_px`` (the nearest of its measurements)."""
        s = self.streamed
        doc = self.dataset.document
        nominal = doc.nominal.parameters()
        spacing = doc.legs.rod_spacing_m if doc.legs.rod_spacing_m is not None else 0.0
        cam = CameraModel.from_dict(s.camera)
        size = (cam.width, cam.height)
        out: dict[int, Any] = {}
        for k, it in enumerate(items):
            i = int(it[0])
            if i not in s.rods or (len(it) > 3 and it[3] is not None):  # rods found from scratch: not streamed
                continue
            q = np.asarray(self.dataset.frames[i].q, dtype=np.float64).reshape(1, 4)
            board = _canon(it[2])
            best: tuple[float, Any] | None = None
            try:
                now = _ends(nominal, q, spacing, it[1], None if len(it) < 5 else it[4])
            except I4calError:
                continue
            for kind, cand in s.rods[i].items():
                if _canon(cand["board"]) != board:
                    continue
                key = (i, kind)
                if key not in self._ends:  # the same measurement is looked up by every pass
                    try:
                        self._ends[key] = _ends(nominal, q, spacing, cand["cfb"], cand.get("seven"))
                    except I4calError:
                        continue
                shift = float(prediction_shift_px(cam.K, size, now, self._ends[key])[0])
                if shift <= s.reuse_px and (best is None or shift < best[0]):
                    best = (shift, cand["result"])
            if best is not None:
                out[k] = (i, best[1])
            else:
                s.used["rods_measured_again"] += 1
        s.used["rods"] += len(out)
        return out


def _ends(nominal: I4Parameters, q: np.ndarray, spacing: float, cfb: Any, seven: Any) -> tuple[np.ndarray, np.ndarray]:
    """The rod ends (camera frame, m) of the frame at ``q`` (shape (1, 4)) predicted by ``seven`` (None: nominal)
    placed with ``cfb`` (a dict or a Rigid)."""
    C = cfb if isinstance(cfb, Rigid) else Rigid.from_dict(cfb)
    top, bottom, _ = rod_ends_camera(_params(nominal, seven), q, C, spacing)
    return top, bottom


def _params(nominal: I4Parameters, seven: Any) -> I4Parameters:
    return nominal if seven is None else I4Parameters.from_vector(np.asarray(seven), T_per_rad=nominal.T_per_rad)


def _shift_px(
    cam: CameraModel, nominal: I4Parameters, q: np.ndarray, spacing: float, a: tuple[Any, Any], b: tuple[Any, Any]
) -> float:
    """How far (ideal px) prediction ``b`` (``(camera_from_base dict or Rigid, seven or None)``) moves the rods of the
    frame at ``q`` (shape (1, 4)) from prediction ``a``."""
    first, second = _ends(nominal, q, spacing, *a), _ends(nominal, q, spacing, *b)
    return float(prediction_shift_px(cam.K, (cam.width, cam.height), first, second)[0])


class FrameStreamer:
    """Measures a dataset's frames one at a time as they are written (:meth:`add`), keeping :class:`StreamedFrames`.

    Parameters
    ----------
    dataset : path
        The dataset v1 directory being written (re-read at each frame: its ``dataset.json`` grows).
    settings : StreamSettings, optional
        Those of the extraction that will take the frames (default: extraction's defaults).

    Raises
    ------
    InputError
        (from :meth:`add`) The dataset carries no intrinsics: nothing can be measured before the ``camera`` phase is
        calibrated, at the end.
    """

    def __init__(self, dataset: str, settings: StreamSettings | None = None) -> None:
        self.root = str(dataset)
        self.settings = settings or StreamSettings()
        self.frames: StreamedFrames | None = None
        self._camera: CameraModel | None = None
        self._det: BoardDetector | None = None
        self._track: BoardTracker | None = None  # frames arrive in order: each searched where the last had the board
        self._bbox: np.ndarray | None = None
        self._good: list[int] = []  # frames with a board pose, in order
        self._placed_with = 0  # board poses the current placement was fitted to
        self._placement: Rigid | None = None
        self._ee_from_board: Rigid | None = None
        self.placement_reason = "not fitted yet"
        self._refit: Repredicted | None = None
        self._refit_with = 0  # frames with rods the current refit was fitted to
        self.refits = 0
        self.remeasured = 0

    def _setup(self, ds: Dataset) -> StreamedFrames:
        doc = ds.document
        camera = doc.camera.camera_model()
        if camera is None:
            raise InputError(
                "the dataset has no intrinsics (camera.K/dist): its frames are measured after the 'camera' phase's "
                "calibration, at the end of the acquisition",
                file=self.root,
                field="camera",
            )
        s = self.settings
        det = BoardDetector(doc.board, s.min_corners)
        refined = None
        # as calib.vision.extract does: the board geometry the camera's calibration refined
        bp = (camera.extra.get("calibration") or {}).get("board_points") or {}
        if bp.get("ids") is not None and len(bp["ids"]) == det.ids_all.size:
            refined = [list(bp["ids"]), list(bp["points_m"]), bp.get("d_intrinsics")]
            det.use_refined_points(
                np.asarray(refined[0]),
                np.asarray(refined[1]),
                None if refined[2] is None else np.asarray(refined[2]),
            )
        rs = s.rods or RodSettings()
        self._camera, self._det, self._bbox = camera, det, image_ideal_bbox(camera)
        self._track = BoardTracker(det)
        self.frames = StreamedFrames(
            camera=camera.to_dict(),
            refined=refined,
            min_corners=s.min_corners,
            rod_settings=dict(rs.__dict__),
            reuse_px=s.reuse_px,
        )
        return self.frames

    def add(self, i: int) -> dict[str, Any]:
        """Measure frame ``i`` (written to the dataset): its board, then its rods when a placement exists.

        Parameters
        ----------
        i : int
            The frame's index in the dataset.

        Returns
        -------
        dict
            ``{"frame", "phase", "board": bool, "rods": int | None (found; None: not measured yet)}``.

        Raises
        ------
        InputError
            No intrinsics in the dataset, or frame ``i`` not in it.
        """
        ds = Dataset.open(self.root)
        frames = self.frames or self._setup(ds)
        if not 0 <= i < len(ds.frames):
            raise InputError(f"frame {i} is not in the dataset ({len(ds.frames)} frames)", file=self.root, frame=i)
        fr = ds.frames[i]
        info: dict[str, Any] = {"frame": int(i), "phase": fr.phase, "board": False, "rods": None}
        if fr.phase == "camera":  # the intrinsics' views: calibrated at the end (when they are not known)
            return info
        try:
            img = ds.load_image(i)
        except InputError as exc:
            frames.boards[i] = {"image_error": exc.reason}
            return info
        board = self._board(img)
        frames.boards[i] = board
        info["board"] = "pose" in board
        if "pose" in board:
            self._good.append(i)
        placement = self._provisional_placement(ds)
        if placement is None:
            return info
        result = self._measure(ds, i, img, "nominal", placement, None)
        if self._refit is not None:
            result = self._measure(ds, i, img, "refit", self._refit.camera_from_base, self._refit.parameters)
        found = result.get("rods") or {}
        info["rods"] = sum(not isinstance(v, str) for v in found.values())
        self._maybe_refit(ds)
        return info

    def _measure(
        self, ds: Dataset, i: int, img: np.ndarray, kind: str, C: Rigid, params: I4Parameters | None
    ) -> dict[str, Any]:
        """Frame ``i``'s rods on the prediction (``C``, ``params``; None: nominal), kept as its ``kind``."""
        assert self.frames is not None
        board = self.frames.boards[i].get("pose")
        result = self._rods(ds, i, img, C, board, params)
        self.frames.rods.setdefault(i, {})[kind] = {
            "cfb": C.to_dict(),
            "seven": None if params is None else [float(v) for v in params.vector()],
            "board": board,
            "result": result,
        }
        return result

    def _maybe_refit(self, ds: Dataset) -> None:
        """The rods' prediction refitted to every frame's rods so far, every :data:`REFIT_EVERY` frames (as
        extraction's :func:`calib.vision.repredict.refit_prediction`, started from the nominal model)."""
        assert self.frames is not None and self._camera is not None
        n = len(self.frames.rods)
        if n < REFIT_EVERY or n - self._refit_with < REFIT_EVERY or self._ee_from_board is None:
            return
        doc = ds.document
        idx = sorted(self.frames.rods)
        q = np.array([ds.frames[i].q for i in idx], dtype=np.float64).reshape(-1, 4)
        measured: list[MeasuredRod] = []
        poses: dict[int, Rigid] = {}
        for k, i in enumerate(idx):
            pose = self.frames.boards[i].get("pose")
            if pose is not None:
                poses[k] = Rigid(np.asarray(pose["R"]), np.asarray(pose["t"]))
            found = self.frames.rods[i]["nominal"]["result"].get("rods") or {}
            for leg, rod in ROD_KEYS:
                v = found.get(rod_name(leg, rod))
                if isinstance(v, dict) and v.get("point") is not None:
                    measured.append(MeasuredRod(k, leg, rod, np.asarray(v["point"]), np.asarray(v["u"])))
        spacing = doc.legs.rod_spacing_m if doc.legs.rod_spacing_m is not None else 0.0
        height = float((doc.board.model_extra or {}).get("height_above_ee_m", 0.0))
        f_px = float(np.sqrt(self._camera.K[0, 0] * self._camera.K[1, 1]))
        assert self._placement is not None
        try:
            C0, E0 = self._placement, self._ee_from_board
            fit = refit_prediction(doc.nominal.parameters(), q, measured, poses, C0, E0, f_px, spacing, height)
        except (I4calError, np.linalg.LinAlgError, ValueError):
            fit = None
        self._refit_with = n
        if fit is not None:
            self._refit, self.refits = fit, self.refits + 1

    def idle_step(self) -> bool:
        """Measure again one frame whose kept measurement's prediction is more than :data:`REMEASURE_PX` from the
        latest placement's or refit's (between frames, nothing waiting).

        Returns
        -------
        bool
            Whether there was one.
        """
        if self.frames is None or self._camera is None:
            return False
        ds: Dataset | None = None
        doc_nominal = None
        for i in sorted(self.frames.rods, reverse=False):
            kinds = self.frames.rods[i]
            latest: list[tuple[str, Rigid | None, I4Parameters | None]] = [("nominal", self._placement, None)]
            if self._refit is not None:
                latest.append(("refit", self._refit.camera_from_base, self._refit.parameters))
            for kind, C, params in latest:
                if C is None:
                    continue
                if ds is None:
                    ds = Dataset.open(self.root)
                    doc_nominal = ds.document.nominal.parameters()
                assert doc_nominal is not None
                spacing = ds.document.legs.rod_spacing_m or 0.0
                q = np.asarray(ds.frames[i].q, dtype=np.float64).reshape(1, 4)
                cand = kinds.get(kind)
                try:
                    stale = (
                        cand is None
                        or _shift_px(
                            self._camera,
                            doc_nominal,
                            q,
                            spacing,
                            (C, None if params is None else params.vector()),
                            (cand["cfb"], cand.get("seven")),
                        )
                        > REMEASURE_PX
                    )
                except I4calError:
                    stale = False
                if stale:
                    self._measure(ds, i, ds.load_image(i), kind, C, params)
                    self.remeasured += 1
                    return True
        return False

    def _board(self, img: np.ndarray) -> dict[str, Any]:
        """The board stage's result for one image (as extraction's: corners, then the pose with this camera)."""
        assert self._det is not None and self._track is not None and self._camera is not None
        det: BoardDetection = self._track.detect(img)
        res = self._det.pose(det, self._camera)
        corners = [det.ids.tolist(), det.pixels.tolist(), det.n_markers]
        if isinstance(res, str):
            return {"reason": res, "corners": corners}
        return {"pose": res.to_dict(), "corners": corners}

    def _provisional_placement(self, ds: Dataset) -> Rigid | None:
        """``camera_from_base`` fitted to the board poses so far (fitted again at each new one), None before enough."""
        s, n = self.settings, len(self._good)
        if n < s.min_placement_frames:
            self.placement_reason = f"board poses in {n} frames, need {s.min_placement_frames}"
            return None
        if n == self._placed_with:
            return self._placement
        assert self.frames is not None
        doc = ds.document
        poses = [self.frames.boards[i]["pose"] for i in self._good]
        try:
            height = float((doc.board.model_extra or {}).get("height_above_ee_m", 0.0))
            C, E, rms = fit_placement(
                np.array([ds.frames[i].q for i in self._good]),
                np.array([p["R"] for p in poses]),
                np.array([p["t"] for p in poses]),
                doc.nominal.parameters(),
                height,
            )
        except (I4calError, np.linalg.LinAlgError, ValueError) as exc:
            self.placement_reason = f"placement failed: {exc}"
            return self._placement
        self._placed_with = n
        if rms > s.max_placement_rms_m:
            self.placement_reason = f"placement inconsistent: RMS {rms * 1e3:.1f} mm"
            self._placement = self._ee_from_board = None
        else:
            self._placement, self._ee_from_board = C, E
        return self._placement

    def _rods(
        self, ds: Dataset, i: int, img: np.ndarray, C: Rigid, board: dict | None, params: I4Parameters | None = None
    ) -> dict[str, Any]:
        """The rods stage's result for frame ``i`` on the prediction of ``params`` (None: the nominal model) placed
        with ``C`` (as extraction's)."""
        assert self._camera is not None and self._det is not None and self.frames is not None
        cam, doc = self._camera, ds.document
        if img.ndim == 3:
            img = to_gray8(img) if img.dtype == np.uint8 else img[..., :3].mean(axis=2)
        spacing = doc.legs.rod_spacing_m if doc.legs.rod_spacing_m is not None else 0.0
        try:
            preds = predict_rods(params or doc.nominal.parameters(), ds.frames[i].q, C, spacing)
        except I4calError as exc:
            return {"reason": f"no rod prediction: {exc}"}
        occ = []
        if board is not None:
            oc = self._det.outline_camera(np.asarray(board["R"]), np.asarray(board["t"]), margin_m=ROD_BOARD_OCCLUDER_M)
            if np.all(oc[:, 2] > 0):
                occ.append(cam.to_ideal_pixels(oc[:, :2] / oc[:, 2:3]))
        rs = RodSettings(**self.frames.rod_settings)
        ms = measure_rods(
            img.astype(np.float32), cam, preds, doc.legs.rod_radius_m, rs, occ, seed=i, ideal_bbox=self._bbox
        )
        return _pool.rods_result(ms)
