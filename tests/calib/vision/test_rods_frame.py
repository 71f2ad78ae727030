"""The rods of a frame measured together (``measure_rods``) give the per-rod numbers (``measure_rod``), bit for bit.

``measure_rods`` finds the visible profiles, the sub-pixel edges and the edge pairs of all the frame's rods in one
pass (``_profile_frame``), then runs each later stage (limb points, limb fits, axes) for all rods at once
(``_measure_frame``); these tests pin those passes, the generator's draws, and the whole frame's result, to the
per-rod path on rendered frames (rods occluded by the board, rods leaving the image).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib.formats.plan import make_plan
from calib.vision.board import BoardDetector
from calib.vision.rods import (
    RodPrediction,
    RodSettings,
    image_ideal_bbox,
    measure_rod,
    measure_rods,
    predict_rods,
    robust_line,
)
from calib.vision.rods import measure as measure_mod
from calib.vision.rods.linefit import _inlier_counts, ransac_start, refine_lines
from calib.vision.rods.measure import (
    _fit_limb_points,
    _fit_limbs_frame,
    _FrameRods,
    _IdealToImage,
    _limb_pairs,
    _measure_frame,
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


def _frame_rods(img, cam, preds, radius, s, occ, seed):
    """The frame's rods as measure_rods sets them up (profiles of all rods found together)."""
    box, proj = image_ideal_bbox(cam), _IdealToImage(cam)
    segs = [_predicted_segment(cam, p, radius, s.near_m, box) for p in preds]
    _profile_frame(img, cam, segs, s, box, proj, occ)
    sil = [None if isinstance(g, str) else _silhouette(g) for g in segs]
    return _FrameRods(img, cam, list(preds), radius, s, occ, np.random.default_rng(seed), box, proj, segs, sil)


def test_frame_stages_equal_the_rods_measured_in_turn(frames, monkeypatch):
    """The first pass of measure_rods (each stage for all rods at once) gives what measuring the rods one after the
    other gives, bit for bit, and leaves the frame's generator where the rods in turn leave it; on frames with rods
    hidden by an occluder, rods with too few limb points and limbs whose points near another rod are dropped."""
    dropped = []
    clear_of = measure_mod._clear_of

    def spy(pts, nb, margin):
        keep = clear_of(pts, nb, margin)
        dropped.append(int(np.count_nonzero(~keep)))
        return keep

    monkeypatch.setattr(measure_mod, "_clear_of", spy)
    reasons = []
    n_ok = 0
    s = RodSettings(polarity=1)
    for seed, (img, cam, both, radius, occ) in enumerate(frames):
        for preds in both:
            # one more rod, beside the second (the limb points of each near the other's silhouette dropped)
            side = np.array([0.004, 0.0, 0.0])  # m
            near = RodPrediction(9, 0, preds[1].top + side, preds[1].bottom + side)
            preds = [*preds, near]
            # one more occluder, hiding the first rod whole
            seg = _predicted_segment(cam, preds[0], radius, s.near_m, image_ideal_bbox(cam))
            assert not isinstance(seg, str)
            ends = np.array([seg.a, seg.a + seg.length * seg.t_dir])
            hide = np.array([ends[0] - 80 * seg.t_dir, ends[1] + 80 * seg.t_dir])
            poly = np.array(
                [hide[0] - 60 * seg.n_dir, hide[1] - 60 * seg.n_dir, hide[1] + 60 * seg.n_dir, hide[0] + 60 * seg.n_dir]
            )
            occ2 = [*occ, poly]
            together = _frame_rods(img, cam, preds, radius, s, occ2, seed)
            in_turn = _frame_rods(img, cam, preds, radius, s, occ2, seed)
            got = _measure_frame(together)
            want = [in_turn.measure(i, p, in_turn.segs[i]) for i, p in enumerate(preds)]
            for i, (m, w) in enumerate(zip(got, want, strict=True)):
                for f in dataclasses.fields(m):
                    assert _same(getattr(m, f.name), getattr(w, f.name)), (i, f.name)
                reasons.append(m.reason or "")
                n_ok += m.ok
            assert together.rng.bit_generator.state == in_turn.rng.bit_generator.state
    assert n_ok >= 15  # measured rods compared, not only reasons
    assert any(r.startswith("not enough of the rod visible") for r in reasons)
    assert any(r.startswith("too few limb edge points") for r in reasons)
    assert sum(dropped) > 0  # limb points near another rod dropped


def _limb(rng, n, outliers=0):
    """n edge points (px) along a line (0.2 px noise) and ``outliers`` points 5-20 px off it, (n + outliers, 2)."""
    t = np.linspace(0.0, 300.0, n + outliers)
    off = rng.normal(0.0, 0.2, n + outliers)
    bad = rng.choice(n + outliers, outliers, replace=False)
    off[bad] += rng.uniform(5.0, 20.0, outliers) * rng.choice([-1.0, 1.0], outliers)
    return np.column_stack([100.0 + t, 200.0 + 0.3 * t + off])


@pytest.mark.parametrize("first_fails", [False, True])
def test_frame_limb_fits_draw_as_the_rods_in_turn(first_fails):
    """The frame's limb fits give each rod's fits in turn and consume the generator as they do: a rod with too few
    points on its first limb draws nothing, one with too few on its second draws for its first only, and a rod whose
    first limb has enough points but too few inliers (then the rods are fitted in turn) draws nothing for its second."""
    rng = np.random.default_rng(5)
    s = RodSettings(min_points=50)
    rods = [
        (_limb(rng, 80), _limb(rng, 90, 10)),
        (_limb(rng, 30), _limb(rng, 80)),  # too few points on the first limb
        (_limb(rng, 80), _limb(rng, 40)),  # too few on the second
        (_limb(rng, 40, 20) if first_fails else _limb(rng, 70), _limb(rng, 80)),  # 60 points, 40 inliers: fails
        (_limb(rng, 120, 30), _limb(rng, 100)),
    ]
    r_frame, r_turn = np.random.default_rng(9), np.random.default_rng(9)
    got = _fit_limbs_frame(rods, s, r_frame)
    want = [_fit_limb_points(p, s, r_turn) for p in rods]
    assert r_frame.bit_generator.state == r_turn.bit_generator.state
    for g, w in zip(got, want, strict=True):
        assert type(g) is type(w)
        if isinstance(w, str):
            assert g == w
        else:
            for f in dataclasses.fields(w):
                assert _same(getattr(g, f.name), getattr(w, f.name)), f.name
    assert [isinstance(x, str) for x in got] == [False, True, True, first_fails, False]
    if first_fails:
        assert isinstance(got[3], str) and got[3].startswith("limb line fit failed")
    # the draws: the pairs of each limb fitted, in turn (none for a limb not reached)
    drawn = np.random.default_rng(9)
    for n in (80, 100, 80, *((60,) if first_fails else (70, 80)), 150, 100):
        drawn.integers(0, n, size=(s.ransac_iters, 2))
    assert drawn.bit_generator.state == r_frame.bit_generator.state


def test_refine_lines_each_set_alone_or_together():
    """A set's refined line and inliers are robust_line's, bit for bit, whether refined alone or with other sets
    (the per-rod and frame paths share them)."""
    rng = np.random.default_rng(2)
    sets = [_limb(rng, n, k) for n, k in ((60, 5), (200, 30), (25, 0), (90, 40))]
    starts = [ransac_start(p, np.random.default_rng(j), 150, 1.0) for j, p in enumerate(sets)]
    together = refine_lines(sets, starts, 1.0)
    for j, p in enumerate(sets):
        line, inl = refine_lines([p], [starts[j]], 1.0)[0]
        assert np.array_equal(line, together[j][0]) and np.array_equal(inl, together[j][1])
        ref, ref_inl = robust_line(p, np.random.default_rng(j), 150, 1.0)
        assert np.array_equal(inl, ref_inl) and np.array_equal(line, ref)
        assert 0 < np.count_nonzero(inl) < len(p) or j == 2  # outliers dropped (the third set has none)
