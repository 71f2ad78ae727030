"""The camera calibration's uncertainty and its first-order effect on what the methods use.

* the 8x8 covariance of (fx, fy, cx, cy, k1, k2, p1, p2) from the calibrateCameraRO bundle: for OpenCV's
  (unweighted) fit its diagonal equals OpenCV's standard deviations; for the calibration's fit (views weighted by
  their noise, calib.camera.bundle) the errors' Mahalanobis distance over seeded rendered camera phases averages
  the number
  of parameters (the covariance is honest, correlations included), and the intrinsics' errors are much smaller than
  the unweighted fit's;
* a board pose's ``d_intrinsics`` predicts how the pose moves when the intrinsics do;
* a rod's planes recomputed from its limb samples for another camera are that camera's planes.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.camera.intrinsics import calibrate_intrinsics, intrinsics_covariance
from calib.identify import intrinsics as intr
from calib.numerics.transforms import matrix_to_rotvec
from calib.vision.board import BoardDetector
from calib.vision.rods import limb_planes
from drivers.sim.render import BenchRenderer, RenderSettings


def _views(seed: int, views: int):
    s = RenderSettings()
    r = BenchRenderer(settings=s, seed=seed)
    rng = np.random.default_rng(seed + 100)
    det = BoardDetector(s.board)
    found = {}
    for i, pose in enumerate(r.random_board_views(views, rng)):
        d = det.detect(r.render_board_view(pose, rng))
        found[i] = (d.ids, d.pixels, None)
    return s, det, found


def _error(s: RenderSettings, res) -> np.ndarray:
    true = np.array([s.fx, s.fy, s.cx, s.cy, *s.dist[:4]])
    K, dist = res.camera.K, res.camera.dist
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist[:4]]) - true


def test_unweighted_covariance_is_opencvs():
    """intrinsics_covariance of OpenCV's own fit: its diagonal is OpenCV's standard deviations."""
    s, det, found = _views(0, 20)
    objp = [det.points_nominal.astype(np.float32).reshape(-1, 1, 3)] * len(found)
    order = [np.argsort(ids) for ids, _p, _ in found.values()]
    imgp = [p[o].astype(np.float32).reshape(-1, 1, 2) for (_i, p, _), o in zip(found.values(), order, strict=True)]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    ret = cv2.calibrateCameraROExtended(
        objp, imgp, (s.width, s.height), 4, None, None, flags=cv2.CALIB_FIX_K3, criteria=crit
    )
    _rms, K, dist, rvecs, tvecs, new_obj, std_int = ret[:7]
    pts = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in imgp]
    cov = intrinsics_covariance(K, dist, np.asarray(new_obj).reshape(-1, 3), pts, rvecs, tvecs, fixed_point=4)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.asarray(std_int).reshape(-1)[:8], rtol=1e-3)
    res = calibrate_intrinsics(found, (s.width, s.height), det.ids_all, det.points_nominal, weight_views=False)
    np.testing.assert_allclose([res.std[k] for k in intr.INTRINSICS_NAMES], np.sqrt(np.diag(cov)), rtol=1e-3)


@pytest.mark.slow
def test_weighted_calibration_is_honest_and_beats_the_unweighted_one():
    """Views weighted by their noise (calib.camera.bundle): honest covariance, smaller errors than OpenCV's plain
    fit.

    Over 24 seeded 20-view camera phases of the image-level twin (whose views' corner noise ranges 0.02-0.2 px RMS)
    the weighted fit's fx, fy, cx, cy errors are well below the plain fit's (measured over 48 phases: mean square
    0.2-0.46 of it in blocks of 12), and its errors' Mahalanobis distance averages chi-square(8)'s mean.
    """
    n = 24
    d2, sq_w, sq_u = [], [], []
    for seed in range(n):
        s, det, found = _views(seed, 20)
        res = calibrate_intrinsics(found, (s.width, s.height), det.ids_all, det.points_nominal)
        plain = calibrate_intrinsics(found, (s.width, s.height), det.ids_all, det.points_nominal, weight_views=False)
        assert "weighted" in res.camera.extra["calibration"]["method"]
        err, err_u = _error(s, res), _error(s, plain)
        cov = np.asarray(res.camera.extra["calibration"]["covariance"])
        d2.append(float(err @ np.linalg.solve(cov, err)))
        sq_w.append(err[:4] ** 2)
        sq_u.append(err_u[:4] ** 2)
    # chi-square(8): mean 8, std of the mean of n draws sqrt(16 / n); 3 of those either side
    tol = 3 * np.sqrt(16 / n)
    ratio = np.mean(sq_w) / np.mean(sq_u)
    print(
        f"mean Mahalanobis distance {np.mean(d2):.2f} (chi-square(8): 8 +/- {tol:.2f}); mean square ratio {ratio:.2f}"
    )
    assert abs(np.mean(d2) - 8) < tol, d2
    assert ratio < 0.6, (np.mean(sq_w, axis=0), np.mean(sq_u, axis=0))


def test_board_pose_sensitivity_predicts_the_change():
    s = RenderSettings()
    r = BenchRenderer(settings=s, seed=3)
    rng = np.random.default_rng(3)
    det = BoardDetector(s.board)
    cam = s.camera()
    img = r.render_board_view(r.random_board_views(1, rng)[0], rng)
    detection = det.detect(img)
    base = det.pose(detection, cam)
    assert not isinstance(base, str) and base.d_intrinsics is not None
    # a quarter of a calibration's typical std each: the first-order regime (at a whole std, fx alone
    # -- a change of aspect ratio -- moves the depth 4% off the tangent: second order, cancelled by
    # the methods' central differences)
    typical = 0.25 * np.array([2.0, 2.0, 4.0, 4.0, 2e-3, 4e-3, 4e-4, 4e-4])
    for j in range(8):
        step = np.zeros(8)
        step[j] = typical[j]
        moved = det.pose(detection, intr.perturbed_camera(cam, step))
        w = matrix_to_rotvec(moved.R @ base.R.T)
        dt = moved.t - base.t
        pred = base.d_intrinsics @ step
        # first order: the prediction's error is second order in the step (a few % of the change)
        assert np.linalg.norm(w - pred[:3]) < 0.05 * np.linalg.norm(w) + 2e-6, (j, w, pred[:3])
        assert np.linalg.norm(dt - pred[3:]) < 0.05 * np.linalg.norm(dt) + 2e-6, (j, dt, pred[3:])


def test_limb_planes_for_another_camera_are_its_planes():
    rng = np.random.default_rng(7)
    cam = RenderSettings().camera()
    other = intr.perturbed_camera(cam, np.array([3.0, -2.0, 5.0, -4.0, 5e-3, -8e-3, 6e-4, -5e-4]))
    for _ in range(20):
        point = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(0.5, 0.9)])
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        hs = np.array(limb_planes(point, u, 0.006))  # (2, 3): the true tangent planes
        # samples of each limb: points of the cylinder's tangent lines, seen through ``other``
        limbs = []
        for h in hs:
            # the limb: the axis moved by -radius along h (h . X = radius on the axis, 0 on the plane)
            pts = (point - 0.006 * h)[None] + np.linspace(-0.05, 0.05, 5)[:, None] * u[None]
            limbs.append(other.project(pts))
        got = intr.limb_planes_for(other, np.asarray(limbs)[None], hs[None])[0]
        for g, h in zip(got, hs, strict=True):
            assert np.linalg.norm(np.cross(g, h)) < 1e-6, (g, h)


def test_linearized_limbs_match_exact_undistortion():
    """The combined fit's fast path (first-order guess + Newton on the exact distortion) gives the same planes as
    the iterative undistortion, for intrinsics moved by up to 5 standard deviations of a calibration."""
    rng = np.random.default_rng(11)
    cam = RenderSettings().camera()
    cov = np.diag([1.0, 1.0, 14.0, 9.0, 4e-6, 1.6e-5, 1.6e-7, 1.7e-7])
    cov[0, 1] = cov[1, 0] = 0.94
    steps = intr.principal_steps(cov)
    limbs, hs = [], []
    for _ in range(40):
        point = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(0.5, 0.9)])
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        h = np.array(limb_planes(point, u, 0.006))
        limbs.append(
            [cam.project((point - 0.006 * hh)[None] + np.linspace(-0.05, 0.05, 5)[:, None] * u[None]) for hh in h]
        )
        hs.append(h)
    limbs, hs = np.asarray(limbs), np.asarray(hs)
    lin = intr.LinearizedLimbs(cam, steps, limbs)
    np.testing.assert_allclose(lin.planes(np.zeros(len(steps)), hs), intr.limb_planes_for(cam, limbs, hs), atol=1e-12)
    for scale in (1.0, 3.0, 5.0):
        z = rng.normal(size=len(steps)) * scale
        exact = intr.limb_planes_for(intr.perturbed_camera(cam, steps.T @ z), limbs, hs)
        np.testing.assert_allclose(lin.planes(z, hs), exact, atol=1e-9)
    sub = lin.subset(np.arange(40) % 2 == 0)
    z = rng.normal(size=len(steps))
    np.testing.assert_allclose(sub.planes(z, hs[::2]), lin.planes(z, hs)[::2], atol=1e-15)
