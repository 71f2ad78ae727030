"""The board-view guide of `i4cal camera calibrate`: what it keeps, what it says is missing, where it asks the board
next, and that the views it asks for calibrate the camera. Board views are exact projections of the board by a known
lens (no rendering), with 0.05 px corner noise; the hand is the simulated operator's (drivers.sim.hand)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from calib.camera.charuco import board_corners
from calib.camera.intrinsics import calibrate_intrinsics
from calib.camera.views import CORNERS, TILTS, ViewGoals, ViewGuide
from calib.formats.camera import CameraModel
from calib.formats.dataset import BoardSpec
from calib.numerics.transforms import Rigid, rotvec_to_matrix
from drivers.sim.hand import held_board_pose

K_TRUE = np.array([[774.2, 0.0, 515.3], [0.0, 774.2, 380.6], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.30, 0.10, 4e-4, -3e-4, 0.0])
SIZE = (1024, 768)
NOISE_PX = 0.05


@pytest.fixture(scope="module")
def scene():
    board = BoardSpec()
    cam = CameraModel(K_TRUE, DIST_TRUE, *SIZE)
    ids, pts = board_corners(board)
    hand = SimpleNamespace(camera=cam, settings=SimpleNamespace(board=board, board_margin_m=0.012))
    return board, cam, ids, pts, hand


def _view(scene, pose: Rigid, rng) -> np.ndarray:
    _board, cam, _ids, pts, _hand = scene
    return cam.project(pose.apply(pts)) + rng.normal(0.0, NOISE_PX, (pts.shape[0], 2))


def test_the_guide_asks_until_the_views_cover_everything_and_they_calibrate_the_camera(scene):
    board, _cam, ids, _pts, hand = scene
    rng = np.random.default_rng(3)
    guide = ViewGuide(board, SIZE)
    kinds = {k for k, _ in guide.missing_items()}
    assert kinds == {*(f"corner:{c}" for c in CORNERS), *(f"tilt:{t}" for t in TILTS), "near", "far", "count"}
    words = " ".join(guide.missing())
    assert "top-left corner" in words and "top edge away from the camera" in words and "near view" in words
    placement = guide.first_placement()
    asked = []
    for grab in range(1, 40):
        pose = held_board_pose(placement.to_dict(), hand, rng)
        v = guide.add(grab, ids, _view(scene, pose, rng))
        assert v.kept, v.reason
        if guide.complete:
            break
        placement = guide.next_placement()
        asked.append(guide.missing_items()[0][0])
    assert guide.complete and guide.missing() == []
    assert len(guide.kept) == ViewGoals().views  # every placement asked for filled something: none wasted
    cov = guide.coverage()
    assert min(cov["corner_reach"].values()) >= ViewGoals().corner_reach
    assert min(cov["tilt_deg"].values()) >= ViewGoals().tilt_deg
    assert cov["fill"][0] <= ViewGoals().far_fill and cov["fill"][1] >= ViewGoals().near_fill
    res = calibrate_intrinsics(guide.views(), SIZE, guide.ids_all, guide.points, lens_model="auto")
    for name, true in (("fx", K_TRUE[0, 0]), ("fy", K_TRUE[1, 1]), ("cx", K_TRUE[0, 2]), ("cy", K_TRUE[1, 2])):
        got = {"fx": res.camera.K[0, 0], "fy": res.camera.K[1, 1], "cx": res.camera.K[0, 2], "cy": res.camera.K[1, 2]}
        assert abs(got[name] - true) < 3 * res.std[name], (name, got[name], true, res.std[name])


@pytest.mark.parametrize(
    ("tilt", "axis"),
    [((30.0, 0.0), 0), ((-30.0, 0.0), 0), ((0.0, 30.0), 1), ((0.0, -30.0), 1)],
)
def test_tilts_are_measured_with_the_sign_the_words_say(scene, tilt, axis):
    """A board whose top (right) edge is truly farther from the camera than its bottom (left) edge reads a positive
    turn about the horizontal (vertical) axis, the direction the guide names 'top (right) edge away'."""
    board, _cam, _ids, _pts, _hand = scene
    rng = np.random.default_rng(5)
    guide = ViewGuide(board, SIZE)
    guide.K, guide.dist = K_TRUE.copy(), DIST_TRUE.copy()
    R = rotvec_to_matrix(np.array([-math.radians(tilt[0]), -math.radians(tilt[1]), 0.0]))
    W, H = board.size_m
    pose = Rigid(R, np.array([0.0, 0.0, 0.45]) - R @ np.array([W / 2, H / 2, 0.0]))
    corners_cam = pose.apply(np.array([[0, 0, 0], [W, 0, 0], [0, H, 0], [W, H, 0]], dtype=np.float64))
    if axis == 0:  # top edge (board y = 0, image top) against bottom edge
        farther = corners_cam[:2, 2].mean() - corners_cam[2:, 2].mean()
    else:  # right edge (board x = W) against left edge
        farther = corners_cam[[1, 3], 2].mean() - corners_cam[[0, 2], 2].mean()
    feat = guide._features(_view(scene, pose, rng))
    measured = feat.tilt_deg[axis]
    assert np.sign(measured) == np.sign(farther) and abs(abs(measured) - 30.0) < 1.0, (feat.tilt_deg, farther)
    assert abs(feat.tilt_deg[1 - axis]) < 1.0
    assert abs(feat.distance_m - 0.45) < 0.01


def test_a_partial_board_a_repeat_a_blank_image_and_a_moved_board_are_not_kept(scene):
    board, _cam, ids, _pts, hand = scene
    rng = np.random.default_rng(11)
    guide = ViewGuide(board, SIZE)
    v = guide.add(1, [], np.zeros((0, 2)))
    assert not v.kept and v.reason.startswith("no board found")
    pose = held_board_pose({"centre": (0.5, 0.5), "fill": 0.45, "tilt_deg": (0, 0)}, hand, rng)
    px = _view(scene, pose, rng)
    v = guide.add(2, ids[:-3], px[:-3])
    assert not v.kept and f"{ids.size - 3} of its {ids.size} corners" in v.reason
    assert guide.add(3, ids, px).kept
    v = guide.add(4, ids, px + 0.3)
    assert not v.kept and "repeat of view 3" in v.reason
    placements = [((0.3, 0.3), (25, 0)), ((0.7, 0.7), (0, 25)), ((0.7, 0.3), (-25, 0)), ((0.3, 0.7), (0, -25))]
    for k, (centre, tilt) in enumerate(placements, start=5):
        p = held_board_pose({"centre": centre, "fill": 0.4, "tilt_deg": tilt}, hand, rng)
        assert guide.add(k, ids, _view(scene, p, rng)).kept
    assert len(guide.kept) == 5 and guide.quick_rms_px  # from five views, each new one is checked against the rest
    moved = held_board_pose({"centre": (0.5, 0.4), "fill": 0.5, "tilt_deg": (15, 15)}, hand, rng)
    blurred = _view(scene, moved, rng) + rng.normal(0.0, 3.0, (ids.size, 2))  # a board moved during the exposure
    v = guide.add(10, ids, blurred)
    assert not v.kept and "fit the other views' calibration" in v.reason and v.rms_px > 1.0
    assert set(guide.rejected) == {1, 2, 4, 10} and len(guide.kept) == 5
