"""Extraction's worker processes: a pool that keeps each frame's decoded image for the later stages.

Workers decode the frames, find the board, pose its corners and measure the rods (:mod:`calib.vision.extract`
orchestrates); images are cached per worker up to :data:`IMAGE_CACHE_BYTES` in all and frames are handed out in
order, results gathered in frame order, so the output does not depend on the worker count.
"""

from __future__ import annotations

import contextlib
import multiprocessing
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as mp_wait
from typing import Any

import numpy as np

from calib.errors import I4calError, InputError
from calib.formats.camera import CameraModel
from calib.formats.dataset import Dataset
from calib.model.parameters import I4Parameters
from calib.numerics.threads import forking_single_threaded, single_threaded_worker
from calib.numerics.transforms import Rigid
from calib.vision.board import BoardDetection, BoardDetector, BoardTracker, to_gray8
from calib.vision.detect import DetectSettings, detect_rods, measure_detected
from calib.vision.rods import RodSettings, image_ideal_bbox, leg_parallelism, measure_rods, predict_rods, rod_name
from calib.vision.rods.reexpress import reexpress_frame
from calib.vision.rods.types import ROD_BOARD_OCCLUDER_M, RodMeasurement

Progress = Callable[[int, int], None]


# ---------------------------------------------------------------------------------------------
# worker side
_W: dict[str, Any] = {}
#: decoded images kept between the board and rods stages (bytes, shared among the workers): each frame's PNG is
#: then decoded once, not twice (decoding a 1024x768 frame costs most of a board detection); 112 MB holds the
#: paper-sized dataset's 121 frames (8-bit mono) and keeps its extract + calibrate under 500 MB
IMAGE_CACHE_BYTES = 112 * 2**20


def _init_worker(
    root: str,
    camera: dict | None,
    refined: tuple[list, list, Any] | None,
    min_corners: int,
    rod_settings: dict | None,
    keep_images: bool = False,
) -> None:
    if _W.get("root") != root:  # a new dataset (the same one is kept from stage to stage, with its images)
        _W.update(root=root, ds=Dataset.open(root), images={}, cached=0, corners={})
    ds = _W["ds"]
    _W["det"] = BoardDetector(ds.document.board, min_corners)
    # the board stages' frames come in order: each searched first where this worker's previous frame had the board
    _W["track"] = BoardTracker(_W["det"])
    if refined is not None:
        _W["det"].use_refined_points(
            np.asarray(refined[0]), np.asarray(refined[1]), None if refined[2] is None else np.asarray(refined[2])
        )
    _W["cam"] = CameraModel.from_dict(camera) if camera is not None else None
    _W["rs"] = RodSettings(**rod_settings) if rod_settings else RodSettings()
    _W["bbox"] = image_ideal_bbox(_W["cam"]) if _W["cam"] is not None else None
    _W["keep"] = keep_images  # the rods stage keeps the images for a second pass


def _clear_worker() -> None:
    _W.clear()


def _load(i: int, keep: bool) -> np.ndarray:
    """Frame ``i``'s image (InputError when unreadable): from this process's cache (then dropped from it unless
    ``keep``), else decoded and, when ``keep``, cached for a later stage (up to :data:`IMAGE_CACHE_BYTES`)."""
    cache: dict[int, np.ndarray] = _W.setdefault("images", {})
    img = cache.get(i) if keep else cache.pop(i, None)
    if img is not None:
        if not keep:
            _W["cached"] -= img.nbytes
        return img
    img = _W["ds"].load_image(i)
    if keep and _W.get("cached", 0) + img.nbytes <= _W.get("cache_bytes", IMAGE_CACHE_BYTES):
        cache[i] = img
        _W["cached"] = _W.get("cached", 0) + img.nbytes
    return img


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = to_gray8(img) if img.dtype == np.uint8 else img[..., :3].mean(axis=2)
    return img


def _task_detect(i: int) -> tuple[int, Any]:
    """Camera-phase frame: ChArUco corners (ids, pixels) or the reason."""
    try:
        img = _load(i, keep=False)
    except InputError as exc:
        return i, exc.reason
    d = _W["track"].detect(img)
    return i, (d.ids.tolist(), d.pixels.tolist())


def _task_corners(i: int) -> int:
    """Frame ``i``'s board detected ahead of its pose (:meth:`_Pool.run_beside`, while the camera is calibrated: the
    detection does not depend on the camera), kept in this worker with the decoded image for :func:`_task_board`.
    An unreadable image is left to that task to report."""
    try:
        img = _load(i, keep=True)
    except InputError:
        return i
    _W["corners"][i] = _W["track"].detect(img)
    return i


def _task_board(i: int) -> tuple[int, Any]:
    det = _W["corners"].pop(i, None)  # detected ahead (_task_corners)
    if det is None:
        try:
            img = _load(i, keep=True)
        except InputError as exc:
            return i, {"image_error": exc.reason}
        det = _W["track"].detect(img)
    return _board_result(i, det)


def _task_board_pose(args: tuple[int, list, list, int]) -> tuple[int, Any]:
    """The board pose from corners detected in an earlier pass (the detection does not depend on the camera)."""
    i, ids, pixels, n_markers = args
    det = BoardDetection(np.asarray(ids, dtype=int), np.asarray(pixels, dtype=np.float64).reshape(-1, 2), n_markers)
    return _board_result(i, det)


def _board_result(i: int, det: BoardDetection) -> tuple[int, Any]:
    res = _W["det"].pose(det, _W["cam"])
    corners = [det.ids.tolist(), det.pixels.tolist(), det.n_markers]
    if isinstance(res, str):
        return i, {"reason": res, "corners": corners}
    return i, {"pose": res.to_dict(), "corners": corners}


def _task_find_rods(args: tuple[int, dict | None, dict]) -> tuple[int, Any]:
    """No placement: the frame's rods found and associated from scratch (:func:`detect_rods`)."""
    i, prior, settings = args
    doc = _W["ds"].document
    try:
        img = _gray(_load(i, keep=True))
    except InputError:
        return i, None
    return i, detect_rods(
        img,
        _W["cam"],
        doc.nominal.parameters(),
        _W["ds"].frames[i].q,
        doc.legs.rod_radius_m,
        doc.legs.rod_spacing_m,
        DetectSettings(**settings),
        Rigid.from_dict(prior) if prior else None,
    )


def _task_rods(args: tuple) -> tuple[int, Any]:
    i, cfb, board = args[:3]
    found = args[3] if len(args) > 3 else None  # a RodDetection when there is no placement
    seven = args[4] if len(args) > 4 else None  # the seven parameters that predict the rods (default: nominal)
    ds: Dataset = _W["ds"]
    cam: CameraModel = _W["cam"]
    fr = ds.frames[i]
    try:
        img = _gray(_load(i, keep=_W.get("keep", False)))
    except InputError as exc:
        return i, {"image_error": exc.reason}
    doc = ds.document
    nominal = doc.nominal.parameters()
    if seven is not None:
        nominal = I4Parameters.from_vector(seven, T_per_rad=nominal.T_per_rad)
    spacing = doc.legs.rod_spacing_m if doc.legs.rod_spacing_m is not None else 0.0
    try:
        preds = predict_rods(nominal, fr.q, Rigid.from_dict(cfb), spacing) if found is None else []
    except I4calError as exc:
        return i, {"reason": f"no rod prediction: {exc}"}
    occ = []
    if board is not None:
        # the board (with its margin) plus ~15 mm so that its edges stay out of the profiles
        oc = _W["det"].outline_camera(np.asarray(board["R"]), np.asarray(board["t"]), margin_m=ROD_BOARD_OCCLUDER_M)
        if np.all(oc[:, 2] > 0):
            occ.append(cam.to_ideal_pixels(oc[:, :2] / oc[:, 2:3]))
    if found is None:
        ms = measure_rods(
            img.astype(np.float32), cam, preds, doc.legs.rod_radius_m, _W["rs"], occ, seed=i, ideal_bbox=_W["bbox"]
        )
    else:
        ms = measure_detected(
            img.astype(np.float32), cam, found, doc.legs.rod_radius_m, _W["rs"], occ, seed=i, ideal_bbox=_W["bbox"]
        )
    return i, rods_result(ms)


def _task_reexpress(args: tuple[int, dict[str, Any]]) -> tuple[int, Any]:
    """A frame's rods result re-expressed for this pass's camera (:func:`calib.vision.rods.reexpress.reexpress_frame`),
    returned without its edges (the caller has them)."""
    i, result = args
    out = reexpress_frame(result, _W["cam"], _W["ds"].document.legs.rod_radius_m, _W["rs"])
    out.pop("edges", None)
    return i, out


def rods_result(ms: list[RodMeasurement]) -> dict[str, Any]:
    """A frame's rods stage result from its measured rods.

    Parameters
    ----------
    ms : list of RodMeasurement
        The frame's rods as :func:`calib.vision.rods.measure_rods` measured them.

    Returns
    -------
    dict
        ``{"rods": {name: dict | reason}, "parallel_mrad": {leg: angle between its rods, mrad}, "edges": {name:
        (limb 0 (N0, 2), limb 1 (N1, 2), middle (2,))}}``: the edge points (distorted px) of the rods measured, from
        which a later pass re-expresses them for another camera (:func:`calib.vision.rods.reexpress.reexpress_frame`).
    """
    rods = {rod_name(m.leg, m.rod): (m.to_dict() if m.ok else m.reason) for m in ms}
    par = {k: v * 1e3 for k, v in leg_parallelism(ms).items()}
    edges = {
        rod_name(m.leg, m.rod): (m.edges_px[0], m.edges_px[1], m.middle_px)
        for m in ms
        if m.ok and m.edges_px is not None and m.middle_px is not None
    }
    return {"rods": rods, "parallel_mrad": par, "edges": edges}


def _worker_main(conn: Connection, init_args: tuple, cache_bytes: int, fresh: bool = False) -> None:
    """A pool worker: ``("init", args)`` re-initialises it, ``("task", fn, item)`` runs ``fn(item)``, None ends it;
    every message is answered with ``("ok", result)`` or ``("error", exception)``. ``fresh``: started as a new
    interpreter (spawn, forkserver), which limits its own threads; a forked one inherited the limits."""
    if fresh:
        single_threaded_worker()
    _W["cache_bytes"] = cache_bytes
    _init_worker(*init_args)
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        try:
            if msg[0] == "init":
                _init_worker(*msg[1])
                r = None
            else:
                r = msg[1](msg[2])
            conn.send(("ok", r))
        except BaseException as exc:  # sent back, raised in the parent
            try:
                conn.send(("error", exc))
            except Exception:  # an exception that does not pickle
                conn.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))


class _Pool:
    """Runs the stages' tasks in ``workers`` processes (in this process when 1), one frame per task.

    Plain processes, each with its own pipe, and no helper thread in this process (forking while threads run
    can leave a lock held in the child), so that a frame can be sent to the worker that decoded its image in an
    earlier stage (it keeps it, :func:`_load`); a worker whose own frames are done takes frames from the longest
    other queue (work stealing: it decodes them again).
    """

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.procs: list[Any] = []
        self.conns: list[Connection] = []
        self.init: tuple | None = None
        self.home: dict[int, int] = {}  # frame index -> worker holding its image

    def __enter__(self) -> _Pool:
        return self

    def __exit__(self, *exc: Any) -> None:
        for c in self.conns:
            with contextlib.suppress(OSError):
                c.send(None)
        for p in self.procs:
            p.join(timeout=5)
            if p.is_alive():
                p.terminate()
                p.join()
        for c in self.conns:
            c.close()
        self.procs, self.conns = [], []
        _clear_worker()  # the in-process path's images and dataset

    def _call(self, w: int, msg: tuple) -> None:
        self.conns[w].send(msg)

    def _answer(self, w: int) -> Any:
        try:
            kind, r = self.conns[w].recv()
        except (EOFError, OSError):
            raise I4calError(f"an extraction worker died (exit code {self.procs[w].exitcode})") from None
        if kind == "error":
            raise r
        return r

    def _configure(self, init_args: tuple) -> None:
        if not self.procs:
            ctx = multiprocessing.get_context()
            fresh = ctx.get_start_method() != "fork"  # a new interpreter limits its own threads
            # the workers run one BLAS and one OpenCV thread each (the pool already uses the cores), set around
            # the fork, never in the child (calib.numerics.threads)
            with forking_single_threaded():
                for _ in range(self.workers):
                    parent, child = ctx.Pipe()
                    p = ctx.Process(
                        target=_worker_main,
                        args=(child, init_args, IMAGE_CACHE_BYTES // self.workers, fresh),
                        name="i4cal-extract",
                    )
                    p.start()
                    child.close()
                    self.procs.append(p)
                    self.conns.append(parent)
        elif init_args != self.init:
            for w in range(len(self.procs)):
                self._call(w, ("init", init_args))
            for w in range(len(self.procs)):
                self._answer(w)
        self.init = init_args

    def run_beside(
        self, side: Callable[[Any], Any], side_arg: Any, fn: Callable[[int], int], frames: list[int], init_args: tuple
    ) -> Any:
        """``side(side_arg)`` on one worker while the others run ``fn(frame)`` for ``frames``, and that one too once
        it is done: returns ``side``'s result. ``fn`` keeps what it finds in the worker for a later stage
        (:func:`_task_corners`; its answers are dropped), which the frames are then sent to (:attr:`home`). With
        one worker (or fewer than 4 frames), ``side`` runs in this process and the frames are left to that stage.

        Used for the camera's calibration, which the boards' detection does not depend on: on 2 cores the two
        fill the cores without a third process contending for them.
        """
        if self.workers <= 1 or len(frames) < 4:
            _init_worker(*init_args)  # side's tasks run in this process (as run's do with one worker)
            return side(side_arg)
        self._configure(init_args)
        todo = deque(frames)
        busy: dict[int, int | None] = {0: None}  # worker -> frame, None: the side task
        self._call(0, ("task", side, side_arg))

        def submit(w: int) -> None:
            if todo:
                i = todo.popleft()
                self._call(w, ("task", fn, i))
                self.home[i] = w
                busy[w] = i

        for w in range(1, len(self.procs)):
            submit(w)
        result: Any = None
        failure: BaseException | None = None
        while busy:
            for c in mp_wait([self.conns[w] for w in busy]):
                w = self.conns.index(c)  # type: ignore[arg-type]
                was = busy.pop(w)
                try:
                    r = self._answer(w)
                except I4calError as exc:  # the side task's (an unreadable frame is fn's to skip): raised below
                    failure = exc
                    todo.clear()
                    continue
                if was is None:
                    result = r
                if failure is None:
                    submit(w)
        if failure is not None:
            raise failure
        return result

    def run(
        self,
        fn: Callable,
        items: list,
        init_args: tuple,
        progress: Progress | None,
        offset: int,
        total: int,
        each: Callable[[Any], None] | None = None,
    ) -> list:
        """``[fn(item) for item in items]``; an item is a frame index or a tuple led by one.

        ``each(result)`` and ``progress`` are called as results come (completion order); the list is in item order,
        so that what follows does not depend on the scheduling.
        """
        out: list = [None] * len(items)
        count = [0]

        def done(k: int, r: Any) -> None:
            out[k] = r
            count[0] += 1
            if each:
                each(r)
            if progress:
                progress(offset + count[0], total)

        if self.workers <= 1 or len(items) < 4:
            _init_worker(*init_args)
            for k, it in enumerate(items):
                done(k, fn(it))
            return out
        self._configure(init_args)
        n = len(self.procs)
        queues: list[deque] = [deque() for _ in range(n)]
        for k, it in enumerate(items):
            queues[self.home.get(_frame_of(it), k % n)].append(k)
        busy: dict[int, int] = {}  # worker -> item position

        def submit(w: int) -> None:
            q = queues[w] if queues[w] else max(queues, key=len)
            if q:
                k = q.popleft() if q is queues[w] else q.pop()
                self._call(w, ("task", fn, items[k]))
                busy[w] = k

        for w in range(n):
            submit(w)
        while busy:
            for c in mp_wait([self.conns[w] for w in busy]):
                # wait() returns the connections it was given (typed as any waitable)
                w = self.conns.index(c)  # type: ignore[arg-type]
                k = busy.pop(w)
                done(k, self._answer(w))
                self.home[_frame_of(items[k])] = w
                submit(w)
        return out


def _frame_of(item: Any) -> int:
    return int(item[0] if isinstance(item, tuple) else item)
