"""Interpretation planes, axis recovery and robust line fitting (no images)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.vision.rods import axis_from_planes, limb_planes, robust_line


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
