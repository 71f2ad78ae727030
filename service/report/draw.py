"""Frames with what extraction found drawn on them (board outline and axes, rod axes): shared by the API's frame
endpoint and the calibration report."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from calib.formats.camera import CameraModel

#: BGR colours of the overlay.
BOARD_COLOUR = (0, 200, 0)
ROD_COLOUR = (255, 120, 0)
LABEL_COLOUR = (0, 220, 255)


def frame_camera(
    dataset_doc: dict[str, Any] | None, observations_doc: dict[str, Any] | None = None
) -> CameraModel | None:
    """The intrinsics that measured the frames: the extraction's (calibrated or given), else the dataset's.

    Parameters
    ----------
    dataset_doc : dict or None
        Parsed ``dataset.json`` (dataset v1).
    observations_doc : dict or None
        Observations v1 with an ``extraction.camera`` section (``i4cal.camera/1``), when extracted.

    Returns
    -------
    CameraModel or None
        None when neither document holds a camera matrix.
    """
    cands = [((observations_doc or {}).get("extraction") or {}).get("camera"), (dataset_doc or {}).get("camera")]
    for c in cands:
        if not isinstance(c, dict) or c.get("K") is None:
            continue
        try:
            return CameraModel(
                np.asarray(c["K"], float), np.asarray(c.get("dist") or [], float), int(c["width"]), int(c["height"])
            )
        except (KeyError, ValueError, TypeError):
            continue
    return None


def _project(cam: CameraModel, pts: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3), metres, in front of the camera -> pixels (M, 2)."""
    pts = np.asarray(pts, float)
    pts = pts[pts[:, 2] > 1e-3]
    return cam.project(pts) if len(pts) else np.zeros((0, 2))


def draw_detections(
    img: np.ndarray,
    frame: dict[str, Any],
    cam: CameraModel | None,
    board: dict[str, Any] | None = None,
    label: str | None = None,
) -> None:
    """Draw a frame's measured board (outline, x/y axes) and rod axes on a BGR image, in place.

    Parameters
    ----------
    img : ndarray, shape (H, W, 3), uint8
        The frame, BGR.
    frame : dict
        The frame of an observations v1 document (``board.R``/``t`` and ``legs`` in the camera frame, metres).
    cam : CameraModel or None
        Intrinsics; nothing but the label is drawn without them.
    board : dict, optional
        Dataset v1 ``board`` (squares, square length in metres) for the outline's size.
    label : str, optional
        Text written top left (default: the frame's phase).
    """
    import cv2

    if cam is not None:
        b = frame.get("board")
        if b:
            board = board or {}
            sx = board.get("squares_x", 6) * board.get("square_length_m", 0.04)
            sy = board.get("squares_y", 4) * board.get("square_length_m", 0.04)
            R, t = np.asarray(b["R"], float), np.asarray(b["t"], float)
            corners = np.array([[0, 0, 0], [sx, 0, 0], [sx, sy, 0], [0, sy, 0]]) @ R.T + t
            uv = _project(cam, corners)
            if len(uv) == 4:
                cv2.polylines(img, [np.round(uv).astype(np.int32)], True, BOARD_COLOUR, 3, cv2.LINE_AA)
            a = _project(cam, np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]]) @ R.T + t)
            if len(a) == 3:
                p0 = tuple(int(v) for v in np.round(a[0]))
                cv2.line(img, p0, tuple(int(v) for v in np.round(a[1])), (0, 0, 255), 2, cv2.LINE_AA)
                cv2.line(img, p0, tuple(int(v) for v in np.round(a[2])), (0, 255, 0), 2, cv2.LINE_AA)
        for rods in (frame.get("legs") or {}).values():
            for r in rods or []:
                if not r or r.get("point") is None:
                    continue
                p, u = np.asarray(r["point"], float), np.asarray(r["u"], float)
                uv = _project(cam, np.array([p + s * u for s in np.linspace(-0.6, 0.6, 25)]))
                if len(uv) == 0:
                    continue
                inside = (uv[:, 0] > -2000) & (uv[:, 0] < 4000) & (uv[:, 1] > -2000) & (uv[:, 1] < 4000)
                if inside.sum() >= 2:
                    cv2.polylines(img, [np.round(uv[inside]).astype(np.int32)], False, ROD_COLOUR, 2, cv2.LINE_AA)
    text = frame.get("phase", "") if label is None else label
    cv2.putText(img, text, (20, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.0, LABEL_COLOUR, 2, cv2.LINE_AA)


def load_bgr(path: Path) -> np.ndarray | None:
    """An image file as 8-bit BGR (16-bit and mono converted), or None when unreadable."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    if img.dtype == np.uint16:
        img = (cast("NDArray[np.uint16]", img) >> 8).astype(np.uint8)  # dtype checked just above
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def fit_width(img: np.ndarray, max_width: int) -> np.ndarray:
    """Downscale (area interpolation) to at most ``max_width`` pixels wide."""
    import cv2

    h, w = img.shape[:2]
    if w <= max_width:
        return img
    return cv2.resize(img, (max_width, round(h * max_width / w)), interpolation=cv2.INTER_AREA)


def annotated_frame(
    dataset_dir: Path,
    dataset_doc: dict[str, Any],
    index: int,
    frame: dict[str, Any] | None,
    cam: CameraModel | None,
    max_width: int = 1024,
    label: str | None = None,
) -> np.ndarray | None:
    """Dataset frame ``index`` as BGR with its detections drawn, or None when its image is missing or unreadable.

    The image path must stay inside ``dataset_dir``.
    """
    frames = dataset_doc.get("frames", [])
    if not 0 <= index < len(frames) or not frames[index].get("image"):
        return None
    root = dataset_dir.resolve()
    path = (root / frames[index]["image"]).resolve()
    if root not in path.parents or not path.is_file():
        return None
    img = load_bgr(path)
    if img is None:
        return None
    if frame is not None:
        draw_detections(img, frame, cam, dataset_doc.get("board"), label)
    return fit_width(img, max_width)
