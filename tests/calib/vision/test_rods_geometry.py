"""Interpretation planes, axis recovery and robust line fitting (no images)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.formats.camera import CameraModel
from calib.identify import intrinsics as intr
from calib.vision.rods import axis_from_planes, limb_planes, robust_line
from calib.vision.rods.measure import _limb_samples
from drivers.sim.render import RenderSettings


def test_planes_then_axis_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        P = rng.normal(size=3) * 0.3 + np.array([0, 0, 0.7])
        r = 0.008
        h1, h2 = limb_planes(P, u, r)
        assert abs(h1 @ u) < 1e-12 and abs(h2 @ u) < 1e-12
        assert np.isclose(h1 @ P, r) and np.isclose(h2 @ P, r)
        uu, X = axis_from_planes(h1, h2, r)
        assert min(np.linalg.norm(uu - u), np.linalg.norm(uu + u)) < 1e-9
        foot = P - (P @ u) * u
        assert np.linalg.norm(X - foot) < 1e-9


def test_camera_inside_cylinder_rejected():
    with pytest.raises(ValueError, match="inside the cylinder"):
        limb_planes([0.001, 0, 0.5], [0, 0, 1.0], 0.008)


def test_robust_line_rejects_outliers():
    rng = np.random.default_rng(3)
    x = np.linspace(0, 300, 120)
    y = 0.2 * x + 10 + rng.normal(0, 0.05, x.size)
    pts = np.column_stack([x, y])
    pts[::7, 1] += rng.uniform(3, 20, pts[::7].shape[0])  # background edges
    line, inl = robust_line(pts, rng, 150, 1.0)
    assert inl.sum() >= 100 and not inl[::7].any()
    n = np.array([-0.2, 1.0]) / np.hypot(0.2, 1.0)
    assert abs(abs(line[:2] @ n) - 1) < 1e-5


def test_limb_samples_follow_the_edge_points_not_the_extraction_camera():
    """A limb extracted through intrinsics a few standard deviations off (profiles and line fit in that camera's
    ideal pixels): its five samples, undistorted by the true camera, give the true interpretation plane within
    2e-5 rad on a strongly distorted lens (k3 = -0.012, limbs anywhere in the image). Samples on the line the
    extraction camera fitted carried that camera's distortion: up to 5e-5 rad off (the rods' recomputed
    directions then tilted together)."""
    true = RenderSettings(dist=(-0.3, 0.1, 0.0004, -0.0003, -0.012)).camera()
    ext = CameraModel(
        true.K + np.array([[1.0, 0.0, 1.5], [0.0, 1.0, -1.5], [0.0, 0.0, 0.0]]),
        np.asarray(true.dist) + np.array([0.002, -0.01, 2e-4, -2e-4, 0.015]),
        true.width,
        true.height,
    )
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(20):
        point = np.array([rng.uniform(-0.35, 0.35), rng.uniform(-0.25, 0.25), rng.uniform(0.6, 0.9)])
        u = rng.normal(size=3)
        u[2] *= 0.3
        u /= np.linalg.norm(u)
        hs = np.array(limb_planes(point, u, 0.008))
        fits = []
        for h in hs:
            X = (point - 0.008 * h)[None] + np.linspace(-0.15, 0.15, 200)[:, None] * u[None]
            px = true.project(X)  # the limb's edge points where the image shows them
            ok = (px[:, 0] > 0) & (px[:, 0] < true.width - 1) & (px[:, 1] > 0) & (px[:, 1] < true.height - 1)
            ideal = ext.to_ideal_pixels(ext.undistort_points(px[ok]))  # where the extraction camera puts them
            c = ideal.mean(axis=0)
            td = np.linalg.eigh(np.cov((ideal - c).T))[1][:, 1]
            fits.append((c, td, 0.0, ideal))
        got = intr.limb_planes_for(true, _limb_samples(ext, fits)[None], hs[None])[0]
        worst = max(worst, *(float(np.linalg.norm(np.cross(g, h))) for g, h in zip(got, hs, strict=True)))
    assert worst < 2e-5, worst
