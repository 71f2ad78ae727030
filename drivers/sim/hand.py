"""The simulated operator's hand: holds the calibration board where it is asked, as a person would.

A :class:`calib.camera.views.BoardPlacement` (as a dict: ``centre`` fractions of the image, ``fill`` of the image
width, ``tilt_deg`` about the image's horizontal and vertical axes) becomes a true board pose in the camera frame:
the distance from the fill and the true focal length, the centre on the ray through the asked pixel, the tilts as
asked; then a hand's imprecision (a few degrees, a few per cent, a turn about the optical axis) and, like a person
watching the screen, the board moved towards the image centre until all of it is in view.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.numerics.transforms import Rigid, rotvec_to_matrix


def _rot(axis: int, angle_rad: float) -> np.ndarray:
    v = np.zeros(3)
    v[axis] = angle_rad
    return rotvec_to_matrix(v)


def held_board_pose(placement: dict[str, Any], renderer: Any, rng: np.random.Generator) -> Rigid:
    """``camera_from_board`` for a placement request, drawn with a hand's imprecision, the whole board in view.

    Parameters
    ----------
    placement : dict
        ``centre`` (2,) fractions of the image width and height, ``fill`` (fraction of the image width the board
        spans), ``tilt_deg`` (2,): + top edge away from the camera, + right edge away, degrees.
    renderer : drivers.sim.render.BenchRenderer
        Its true camera and board.
    rng : numpy.random.Generator
    """
    cam = renderer.camera
    W, H = renderer.settings.board.size_m
    m = renderer.settings.board_margin_m
    outline = np.array([[-m, -m, 0], [W + m, -m, 0], [W + m, H + m, 0], [-m, H + m, 0]], dtype=np.float64)
    cx, cy = (float(v) for v in placement.get("centre", (0.5, 0.5)))
    fill = float(np.clip(placement.get("fill", 0.45), 0.15, 0.9))
    th, tv = (np.radians(float(v)) for v in placement.get("tilt_deg", (0.0, 0.0)))
    margin_px = 12.0
    pose = None
    for attempt in range(200):
        shrink = min(attempt // 10, 9) / 10.0  # keep moving towards the image centre while part of it is out
        jitter = np.radians(rng.normal(0.0, 3.0, 2))
        R = (
            _rot(0, -(th + jitter[0]))  # top edge away: the board's normal leans to +y
            @ _rot(1, -(tv + jitter[1]))  # right edge away: the normal leans to -x
            @ _rot(2, np.radians(rng.normal(0.0, 6.0)))
        )
        z = cam.fx * W / (fill * (1.0 + rng.normal(0.0, 0.05)) * cam.width)
        u = (0.5 + (cx - 0.5) * (1.0 - shrink) + rng.normal(0.0, 0.015)) * cam.width
        v = (0.5 + (cy - 0.5) * (1.0 - shrink) + rng.normal(0.0, 0.015)) * cam.height
        xn = cam.undistort_points(np.array([[u, v]]))[0]
        centre = np.array([xn[0] * z, xn[1] * z, z])
        pose = Rigid(R, centre - R @ np.array([W / 2, H / 2, 0.0]))
        pc = pose.apply(outline)
        if np.any(pc[:, 2] < 0.1):
            continue
        px = cam.project(pc)
        if (
            np.all(px >= margin_px)
            and np.all(px[:, 0] <= cam.width - 1 - margin_px)
            and np.all(px[:, 1] <= cam.height - 1 - margin_px)
        ):
            return pose
    assert pose is not None
    return pose  # the last try: part of the board out of view (the guide says so)
