"""The board searched in a region of the image: the full image's detection to the bit, or the full image searched.

Rendered frames of a line sweep (the board moves a few px a frame, partly hidden by the rods that cross it).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.formats.dataset import CameraSpec, Dataset, DatasetWriter, LegsSpec
from calib.formats.plan import Plan, make_plan
from calib.vision.board import BoardDetection, BoardDetector
from calib.vision.extract import extract_dataset
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin

N_FRAMES = 6


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A dataset of the first frames of a guided line (consecutive poses), true intrinsics known."""
    g = BenchGeometry()
    rs = RenderSettings()
    r = BenchRenderer(g, rs, seed=2)
    plan = make_plan("line", g.nominal)  # 51 samples: a few px between frames
    tp = GeometricTwin(g).true_poses(Plan(name="sweep", steps=plan.steps))
    root = tmp_path_factory.mktemp("sweep")
    cam = r.camera
    w = DatasetWriter(
        root,
        camera=CameraSpec(width=1024, height=768, K=cam.K.tolist(), dist=cam.dist.tolist()),
        board=rs.board.model_copy(update={"height_above_ee_m": 0.035}),
        legs=LegsSpec(rod_radius_m=g.rod_radius_m, rod_spacing_m=g.rod_spacing_m),
        nominal=g.nominal.as_dict(),
    )
    rng = np.random.default_rng(0)
    for ph, q, pose in tp[:N_FRAMES]:
        w.add_frame(ph, q, r.render(q, pose, rng), truth={"q": q.tolist(), "pose": pose.tolist()})
    w.close()
    ds = Dataset.open(root)
    return root, ds, [ds.load_image(i) for i in range(len(ds.frames))]


def _same(a: BoardDetection, b: BoardDetection) -> None:
    assert np.array_equal(a.ids, b.ids)
    assert np.array_equal(a.pixels, b.pixels)  # to the bit
    assert a.n_markers == b.n_markers


def _box(det: BoardDetection, grow: float) -> tuple[int, int, int, int]:
    assert det.outline_px is not None
    lo, hi = det.outline_px.min(axis=0) - grow, det.outline_px.max(axis=0) + grow
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def test_a_region_holding_the_board_gives_the_full_image_detection(sweep):
    _, ds, images = sweep
    for img in images[:3]:
        full = BoardDetector(ds.document.board).detect(img)
        assert full.ids.size >= 6
        det = BoardDetector(ds.document.board)
        _same(det.detect(img, _box(full, 60)), full)
        assert det.region_stats == {"accepted": 1, "fallback": 0}


def test_a_region_cutting_the_board_falls_back_to_the_full_image(sweep):
    _, ds, images = sweep
    img = images[0]
    det = BoardDetector(ds.document.board)
    full = det.detect(img)
    x0, y0, x1, y1 = _box(full, 0)
    cut = (x0, y0, (x0 + x1) // 2, y1)  # the board's left half
    # what the crop alone gives differs: the markers cut by the crop's border are lost
    _ch, ids, _mk, _mi = det.detector.detectBoard(np.ascontiguousarray(img[y0:y1, x0 : cut[2]]))
    assert ids is None or len(ids) < full.ids.size
    _same(det.detect(img, cut), full)
    assert det.region_stats == {"accepted": 0, "fallback": 1}
    # a margin too thin for OpenCV's windows around the markers is refused as well
    tight = _box(full, -0.1 * (x1 - x0))
    _same(det.detect(img, tight), full)
    assert det.region_stats == {"accepted": 0, "fallback": 2}


def test_a_region_without_the_board_falls_back_to_the_full_image(sweep):
    _, ds, images = sweep
    img = images[0]
    det = BoardDetector(ds.document.board)
    full = det.detect(img)
    x0, _, x1, _ = _box(full, 40)
    away = (0, 0, 150, 150) if x0 > 200 else (874, 618, 1024, 768)
    assert away[2] < x0 or away[0] > x1
    _same(det.detect(img, away), full)
    assert det.region_stats == {"accepted": 0, "fallback": 1}


def test_a_tracker_searches_each_frame_where_the_last_one_had_the_board(sweep):
    from calib.vision.board import BoardTracker

    _, ds, images = sweep
    det = BoardDetector(ds.document.board)
    tracker = BoardTracker(det)
    for img in images:
        _same(tracker.detect(img), BoardDetector(ds.document.board).detect(img))
    assert det.region_stats["accepted"] >= len(images) - 2  # every frame after the first, but a jump
    assert det.region_stats["accepted"] + det.region_stats["fallback"] == len(images) - 1


def test_the_extraction_board_stage_searches_a_region_after_the_first_frame(sweep, monkeypatch):
    """The extraction's board stage (one worker: in this process) searches each frame after the first in the region
    of the one before, and gets the full image's detections."""
    root, ds, images = sweep
    calls: list[tuple[tuple | None, bool, BoardDetection]] = []
    detect = BoardDetector.detect

    def spy(self, image, region=None):
        before = dict(getattr(self, "region_stats", {}))
        out = detect(self, image, region) if region is not None else detect(self, image)
        accepted = getattr(self, "region_stats", {}).get("accepted", 0) > before.get("accepted", 0)
        calls.append((region, accepted, out))
        return out

    monkeypatch.setattr(BoardDetector, "detect", spy)
    extract_dataset(root, workers=1)
    monkeypatch.setattr(BoardDetector, "detect", detect)
    assert len(calls) == N_FRAMES  # the board stage, frames in order
    assert calls[0][0] is None
    assert all(region is not None for region, _, _ in calls[1:])
    assert sum(accepted for _, accepted, _ in calls) >= N_FRAMES - 2
    for img, (_, _, out) in zip(images, calls, strict=True):
        _same(out, BoardDetector(ds.document.board).detect(img))


def test_a_crop_keeps_the_full_image_perimeter_limits():
    """The ArUco perimeter limits are relative to the image's size: a crop gets the full image's limits in px."""
    from calib.vision.board import _detector_parameters

    dp = cv2.aruco.DetectorParameters()
    full = int(dp.minMarkerPerimeterRate * 1024), int(dp.maxMarkerPerimeterRate * 1024)
    for crop in [(300, 400), (767, 1023), (97, 51)]:
        c = _detector_parameters(crop, (768, 1024))
        assert int(c.minMarkerPerimeterRate * max(crop)) == full[0]
        assert int(c.maxMarkerPerimeterRate * max(crop)) == full[1]
        assert c.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_NONE
