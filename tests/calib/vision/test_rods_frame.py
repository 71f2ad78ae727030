"""The rods of a frame measured together (``measure_rods``) give the per-rod numbers (``measure_rod``), bit for bit.

``measure_rods`` finds the visible profiles, the sub-pixel edges and the edge pairs of all the frame's rods in one
pass (``_profile_frame``); these tests pin that pass, and the whole frame's result, to the per-rod path on rendered
frames (rods occluded by the board, rods leaving the image).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib.formats.plan import make_plan
from calib.vision.board import BoardDetector
from calib.vision.rods import RodSettings, image_ideal_bbox, measure_rod, measure_rods, predict_rods
from calib.vision.rods.linefit import _inlier_counts
from calib.vision.rods.measure import (
    _IdealToImage,
    _limb_pairs,
    _predicted_segment,
    _profile_frame,
    _silhouette,
    _visible_centres,
)
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin


@pytest.fixture(scope="module")
def frames():
    """Three rendered frames of the paper's pose set: image, camera, predictions, rod radius, board occluder."""
    g = BenchGeometry()
    r = BenchRenderer(g, RenderSettings(), seed=3)
    cam = r.camera
    det = BoardDetector(r.settings.board)
    det.use_refined_points(np.arange(len(r.board_points_true)), r.board_points_true)
    rng = np.random.default_rng(1)
    out = []
    for _, q, pose in GeometricTwin(g).true_poses(make_plan("pose-set", g.nominal, n_fit=3, seed=4))[:3]:
        img = r.render(q, pose, rng).astype(np.float32)
        if img.ndim == 3:
            img = img.mean(axis=2, dtype=np.float32)
        bp = det.measure(img.astype(np.uint8), cam)
        assert not isinstance(bp, str), bp
        oc = det.outline_camera(bp.R, bp.t, margin_m=0.028)
        # the predictions: the truth, and 2 mm off it as a coarse placement gives
        preds = [predict_rods(g.nominal, q + dq, g.camera_from_base, g.rod_spacing_m) for dq in (0.0, 0.002)]
        out.append((img, cam, preds, g.rod_radius_m, [cam.to_ideal_pixels(oc[:, :2] / oc[:, 2:3])]))
    return out


def _same(a, b) -> bool:
    """Two values of a RodMeasurement or _LimbPairs field equal, bit for bit (NaN equal to NaN)."""
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if a is None or b is None or isinstance(a, str):
        return type(a) is type(b) and a == b
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


def test_frame_profiles_equal_the_per_rod_ones(frames):
    s = RodSettings()
    n_pairs = n_leaving = 0
    for img, cam, both, radius, occ in frames:
        for preds in both:
            box, proj = image_ideal_bbox(cam), _IdealToImage(cam)
            segs = [_predicted_segment(cam, p, radius, s.near_m, box) for p in preds]
            _profile_frame(img, cam, segs, s, box, proj, occ)
            for p, seg in zip(preds, segs, strict=True):
                if isinstance(seg, str):
                    continue
                alone = _predicted_segment(cam, p, radius, s.near_m, box)
                assert not isinstance(alone, str)
                vis = _visible_centres(cam, alone, s, box, proj, occ)
                assert _same(seg.vis, vis)
                if isinstance(vis, str):
                    continue
                pairs = _limb_pairs(img, cam, alone, s, proj, *vis)
                assert seg.pairs is not None
                for f in dataclasses.fields(pairs):
                    assert _same(getattr(seg.pairs, f.name), getattr(pairs, f.name)), f.name
                n_pairs += len(pairs.k)
                # profiles reaching beyond the image (their edges there dropped or left uncorrected)
                offs = np.array([pairs.o1.min(), pairs.o2.max()])
                ends = proj.points(vis[1][[0, -1]][:, None, :] + offs[None, :, None] * seg.n_dir)
                n_leaving += bool(np.any((ends < 0) | (ends > [cam.width - 1, cam.height - 1])))
    assert n_pairs > 1000  # the rods were found
    assert n_leaving > 0  # and the samples beyond the image were exercised


def test_measure_rods_equals_measure_rod_rod_by_rod(frames):
    """With the rods' polarity given no rod is measured again (predicted at the truth): measure_rods is then
    measure_rod on each rod in turn (the frame's random generator shared in that order, the other rods' silhouettes
    their neighbours). Each polarity finds the rods of that brightness against their background."""
    found = set()
    for polarity in (1, -1):
        s = RodSettings(polarity=polarity)
        for seed, (img, cam, (preds, _), radius, occ) in enumerate(frames):
            together = measure_rods(img, cam, preds, radius, s, occ, seed=seed)
            box, proj = image_ideal_bbox(cam), _IdealToImage(cam)
            segs = [_predicted_segment(cam, p, radius, s.near_m, box) for p in preds]
            sil = [None if isinstance(g, str) else _silhouette(g) for g in segs]
            rng = np.random.default_rng(seed)
            for i, (p, m) in enumerate(zip(preds, together, strict=True)):
                nb = [x for j, x in enumerate(sil) if j != i and x is not None]
                alone = measure_rod(
                    img, cam, p, radius, s, occ, rng, box, neighbours=nb, segment=segs[i], projector=proj
                )
                for f in dataclasses.fields(m):
                    assert _same(getattr(m, f.name), getattr(alone, f.name)), (i, f.name)
                if m.ok:
                    found.add((seed, i))
    # the comparison covers measured rods, not only the reasons of missing ones (a leg of these views is found by
    # neither given polarity)
    assert len(found) >= 0.5 * 8 * len(frames)


def test_inlier_counts_blocked_equal_the_whole():
    """The RANSAC scoring in blocks of points counts what one product over all points and lines counts."""
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(1000, 2)) * [300.0, 2.0] + [500.0, 400.0]
    ang = rng.uniform(-0.02, 0.02, 150)
    nx, ny = -np.sin(ang), np.cos(ang)
    c = -(nx * 500.0 + ny * rng.normal(400.0, 2.0, 150))
    whole = np.count_nonzero(np.abs(np.outer(pts[:, 0], nx) + np.outer(pts[:, 1], ny) + c) < 1.0, axis=0)
    assert np.array_equal(_inlier_counts(pts, nx, ny, c, 1.0), whole)
    assert whole.max() > 100  # lines through the points
