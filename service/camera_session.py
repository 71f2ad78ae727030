"""The camera's intrinsics from guided hand-held board views: the session behind ``i4cal camera calibrate`` and
``POST /api/v1/camera/calibrations`` (docs/camera.md).

:func:`collect_views` asks the bench's operator (a :class:`drivers.devices.interfaces.BoardPresenter`) for one placement
after another, grabs and checks each view (:class:`calib.camera.views.ViewGuide`) until the views cover the
image,
the tilts and the distances; :func:`calibrate_views` calibrates them with the lens model chosen by the data and
returns the camera file's model (``i4cal.camera/1``) with its evidence under ``acquired``.
"""

from __future__ import annotations

import asyncio
import datetime
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Session:
    """What a board session gave: the guide with its kept views, the image size, the grabs made."""

    guide: Any
    image_size: tuple[int, int]
    grabs: int
    log: list[dict[str, Any]] = field(default_factory=list)


async def collect_views(
    cfg, views: int, max_grabs: int, say: Callable[[str], None], on_view: Callable[[Any, Any], None] | None = None
) -> Session:
    """Ask the bench's operator for board placements, grab and check each view, until the views cover everything.

    ``say(text)``: what to tell the operator (rich markup); ``on_view(guide, verdict)``: after each grab.

    Raises
    ------
    InputError
        The bench's operator cannot hold a board.
    I4calError
        ``max_grabs`` grabs made and something is still missing (named).
    """
    from calib.camera.views import ViewGoals, ViewGuide
    from calib.errors import I4calError, InputError
    from calib.formats.dataset import BoardSpec
    from calib.vision.board import BoardDetector
    from drivers.acquisition.config import open_camera, open_operator
    from drivers.devices.interfaces import BoardPresenter

    operator = open_operator(cfg)
    if not isinstance(operator, BoardPresenter):
        raise InputError(
            f"the bench's operator ({cfg.operator.uri}) cannot hold the calibration board; use 'console' (a person "
            "at the bench) or the simulated bench's sim://HOST:PORT",
            file=cfg.source,
            field="operator.uri",
        )
    board = BoardSpec()  # the board an acquisition records (the end-effector's)
    detector = BoardDetector(board)
    camera = open_camera(cfg)
    guide = None
    grabs = 0
    log: list[dict[str, Any]] = []
    try:
        await camera.open()
        while guide is None or not guide.complete:
            if grabs >= max_grabs:
                raise I4calError(
                    f"{grabs} grabs and the views still miss: "
                    + "; ".join(guide.missing() if guide else ["a board"])
                    + " (more with --max-grabs)"
                )
            placement = guide.next_placement() if guide is not None else ViewGuide.first_placement()
            say(f"[bold]{placement.text}[/]")
            await operator.present_board(placement)
            frame = await camera.grab(cfg.camera.timeout_s)
            grabs += 1
            if guide is None:
                h, w = frame.image.shape[:2]
                guide = ViewGuide(board, (w, h), ViewGoals(views=views))
            det = await asyncio.to_thread(detector.detect, frame.image)
            v = guide.add(grabs, det.ids, det.pixels)
            log.append({"grab": grabs, "asked": placement.to_dict(), "kept": v.kept, "reason": v.reason})
            if v.kept:
                f = v.features
                assert f is not None
                say(
                    f"  grab {grabs}: kept ({len(guide.kept)} views): board spans {100 * f.fill:.0f}% of the width, "
                    f"turned {f.tilt_deg[0]:+.0f} deg (top away) and {f.tilt_deg[1]:+.0f} deg (right away)"
                    + (f", fits the others at {v.rms_px:.2f} px RMS" if v.rms_px is not None else "")
                    + (f"; adds {', '.join(v.added)}" if v.added else "")
                )
            else:
                say(f"  grab {grabs}: [yellow]not kept[/]: {v.reason}")
            if on_view is not None:
                on_view(guide, v)
            missing = guide.missing()
            if missing:
                say("  still missing: " + "; ".join(missing))
    finally:
        try:
            await operator.board_done()
        finally:
            await camera.close()
            close = getattr(operator, "close", None)
            if close is not None:
                await close()
    assert guide is not None
    return Session(guide, (guide.width, guide.height), grabs, log)


def calibrate_views(session: Session, cfg, lens_model: str, bench_file: str | None = None):
    """The intrinsics from a session's views (:func:`calib.camera.intrinsics.calibrate_intrinsics`,
    ``lens_model``: ``auto`` or
    a model): the :class:`calib.camera.intrinsics.IntrinsicsResult` and the camera file's model, with
    ``acquired`` (the bench,
    the board, the grabs, the views' coverage, the views the calibration left out, when, the software)."""
    from calib.camera.intrinsics import calibrate_intrinsics
    from calib.formats.camera import CameraModel
    from service import __version__

    guide = session.guide
    res = calibrate_intrinsics(guide.views(), session.image_size, guide.ids_all, guide.points, lens_model=lens_model)
    cam = res.camera
    acquired = {
        "bench": cfg.name,
        "bench_file": bench_file,
        "camera_uri": cfg.camera.uri,
        "operator_uri": cfg.operator.uri,
        "board": guide.board.model_dump(mode="json"),
        "grabs": session.grabs,
        "grab_log": session.log,
        "coverage": guide.coverage(),
        "rejected_by_calibration": {str(k): r for k, r in res.rejected.items()},
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": f"i4cal {__version__}",
    }
    return res, CameraModel(cam.K, cam.dist, cam.width, cam.height, {**cam.extra, "acquired": acquired})


def check_lens_model(name: str, option: str = "lens_model") -> str:
    """``name`` when it is ``auto`` or a lens model, else :class:`calib.errors.InputError` naming ``option``."""
    from calib.camera.intrinsics import LENS_MODEL_CHOICES
    from calib.errors import InputError

    if name not in LENS_MODEL_CHOICES:
        raise InputError(
            f"unknown lens model {name!r}; lens models are {', '.join(LENS_MODEL_CHOICES)}", field="lens_model"
        )
    return name
