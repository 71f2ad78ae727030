"""The image-level twin: geometry of what it draws, settable degradations, board manufacturing error."""

from __future__ import annotations

import numpy as np
import pytest

from calib.plan import make_plan
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin


@pytest.fixture(scope="module")
def frames():
    g = BenchGeometry()
    return g, GeometricTwin(g).true_poses(make_plan("rotation-sweep", g.nominal, n_base=3))


def test_image_format_and_determinism(frames):
    g, tp = frames
    _, q, pose = tp[0]
    r = BenchRenderer(g, RenderSettings(), seed=3)
    a = r.render(q, pose, np.random.default_rng(0))
    b = r.render(q, pose, np.random.default_rng(0))
    assert a.shape == (768, 1024) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    c = r.render(q, pose, np.random.default_rng(1))
    assert 1.0 < np.std(a.astype(float) - c.astype(float)) < 4.0  # sensor noise of 2 grey levels, twice


def test_zero_levels_give_a_clean_image(frames):
    g, tp = frames
    _, q, pose = tp[0]
    r = BenchRenderer(g, RenderSettings.clean(), seed=0)
    img = r.render(q, pose)
    bg = img[img == 50]
    assert bg.size > 0.3 * img.size  # flat background where nothing is drawn
    assert np.array_equal(img, r.render(q, pose, np.random.default_rng(5)))  # no noise at all
    assert np.allclose(r.board_points_true, r.board_points_nominal)


def test_rods_drawn_where_the_truth_projects(frames):
    """The rod's axis projects onto bright rod pixels; a point 1.6 radii off the axis does not.

    (Not 3 radii: the two rods of a leg can be close in the image.)
    """
    g, tp = frames
    _, q, pose = tp[1]
    r = BenchRenderer(g, RenderSettings.clean(), seed=0)
    img = r.render(q, pose, board_visible=False)
    top, bot = g.rod_segments_base(q, pose)
    cb = g.camera_from_base
    hit = miss = 0
    for leg in range(4):
        for rod in range(2):
            a, b = cb.apply(top[leg, rod]), cb.apply(bot[leg, rod])
            pts = a + np.linspace(0.6, 0.98, 20)[:, None] * (b - a)
            side = np.cross(b - a, pts[0])
            side = side / np.linalg.norm(side) * 1.6 * g.rod_radius_m
            for P, vals in ((pts, "on"), (pts + side, "off")):
                px = r.camera.project(P)
                ok = (px[:, 0] > 2) & (px[:, 0] < 1021) & (px[:, 1] > 2) & (px[:, 1] < 765)
                v = img[np.rint(px[ok, 1]).astype(int), np.rint(px[ok, 0]).astype(int)]
                if vals == "on":
                    hit += np.sum(v > 120)
                    miss += np.sum(v <= 120)
                else:
                    miss += np.sum(v > 120)
                    hit += np.sum(v <= 120)
    assert hit > 200 and miss <= 0.02 * hit


def test_distortion_is_visible():
    """A straight 3-D line near the image border projects to a curve bowed by several pixels."""
    cam = RenderSettings().camera()
    x = np.linspace(-0.4, 0.4, 50)
    P = np.column_stack([x, np.full_like(x, 0.42), np.ones_like(x)])
    px = cam.project(P)
    chord = px[-1] - px[0]
    n = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
    bow = np.abs((px - px[0]) @ n).max()
    assert bow > 8.0


def test_board_manufacturing_error_has_the_set_rms():
    r = BenchRenderer(BenchGeometry(), RenderSettings(board_error_m=3e-4), seed=1)
    d = r.board_points_true - r.board_points_nominal
    rms = np.sqrt(np.mean(np.sum(d**2, axis=1)))
    assert rms == pytest.approx(3e-4, rel=0.05)
    assert np.abs(d[:, 2]).max() == 0.0


def test_camera_views_see_the_whole_board():
    r = BenchRenderer(BenchGeometry(), RenderSettings(), seed=0)
    views = r.random_board_views(6, np.random.default_rng(0))
    assert len(views) == 6
    for v in views:
        px = r.camera.project(v.apply(r.board_points_nominal))
        assert px.min() > 0 and px[:, 0].max() < 1024 and px[:, 1].max() < 768


def test_rods_without_shading_are_one_grey(frames):
    """``rod_shading=False`` draws every rod one uniform grey (170), to separate what the shading does to the limb
    edges from what the blur and the edge model do; the default shades them (140-250 across a rod)."""
    g, tp = frames
    _, q, pose = tp[0]
    clean = RenderSettings.clean()
    shaded = BenchRenderer(g, clean, seed=0).render(q, pose, board_visible=False)
    uniform = BenchRenderer(g, RenderSettings.clean(rod_shading=False), seed=0).render(q, pose, board_visible=False)
    rods = shaded != 50  # everything drawn over the flat background
    assert rods.sum() > 1000
    inner = uniform[rods]
    # fully covered pixels are 170 exactly; only the anti-aliased rims take values between it and the background
    assert np.mean(inner == 170) > 0.6 and np.all((inner >= 50) & (inner <= 170))
    assert np.ptp(shaded[rods & (uniform == 170)]) > 40  # the same pixels shaded
