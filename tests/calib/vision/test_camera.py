"""Camera model and intrinsic calibration (calibrateCameraRO) on synthetic corner data."""

from __future__ import annotations

import json

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from calib.camera.charuco import board_corners
from calib.camera.intrinsics import calibrate_intrinsics
from calib.errors import InputError
from calib.formats.camera import CameraModel
from calib.formats.dataset import BoardSpec
from calib.numerics.transforms import rotvec_to_matrix

K = np.array([[774.2, 0.0, 515.3], [0.0, 774.2, 380.6], [0.0, 0.0, 1.0]])
DIST = np.array([-0.30, 0.10, 4e-4, -3e-4, 0.0])


def test_project_undistort_round_trip():
    cam = CameraModel(K, DIST, 1024, 768)
    rng = np.random.default_rng(0)
    px = rng.uniform([0, 0], [1023, 767], size=(200, 2))
    xn = cam.undistort_points(px)
    back = cam.distort_normalized(xn)
    assert np.abs(back - px).max() < 1e-6
    pts = np.column_stack([xn * 0.7, np.full(len(xn), 0.7)])
    assert np.abs(cam.project(pts) - px).max() < 1e-6
    assert np.allclose(cam.from_ideal_pixels(cam.to_ideal_pixels(xn)), xn)


def test_json_round_trip(tmp_path):
    cam = CameraModel(K, DIST, 1024, 768, {"note": "x"})
    cam.save(tmp_path / "cam.json")
    back = CameraModel.load(tmp_path / "cam.json")
    assert np.allclose(back.K, K) and np.allclose(back.dist, DIST) and back.size == (1024, 768)
    assert back.extra["note"] == "x"


def test_validation_names_the_shape(tmp_path):
    with pytest.raises(ValueError, match=r"K must have shape \(3, 3\)"):
        CameraModel(np.eye(2), DIST, 10, 10)
    with pytest.raises(ValueError, match="dist must have"):
        CameraModel(K, np.zeros(3), 10, 10)
    (tmp_path / "bad.json").write_text('{"K": [[1,0,0],[0,1,0],[0,0,1]], "width": 4}')
    with pytest.raises(InputError, match="height"):
        CameraModel.load(tmp_path / "bad.json")


def _views(n, rng, noise_px, board_points):
    cam = CameraModel(K, DIST, 1024, 768)
    views = {}
    for i in range(n):
        R = rotvec_to_matrix(rng.normal(0, 0.35, 3))
        z = rng.uniform(0.3, 0.55)
        c = np.array([rng.uniform(-0.2, 0.2) * z, rng.uniform(-0.15, 0.15) * z, z])
        t = c - R @ np.array([0.12, 0.08, 0.0])
        px = cam.project(board_points @ R.T + t) + rng.normal(0, noise_px, (len(board_points), 2))
        views[i] = (np.arange(len(board_points)), px, None)
    return views


def test_calibrate_ro_recovers_intrinsics_and_rejects_views():
    ids, pts = board_corners(BoardSpec())
    rng = np.random.default_rng(1)
    # a slightly wrong board (manufacturing error): the nominal points are given to the calibration
    true_pts = pts.copy()
    true_pts[:, :2] += rng.normal(0, 2e-4, (len(pts), 2))
    views = _views(15, rng, 0.05, true_pts)
    views[100] = (ids[:7], views[0][1][:7], None)  # partial board
    bad = views[3][1].copy()
    bad[5] += 6.0  # one grossly wrong corner
    views[101] = (ids, bad, None)
    res = calibrate_intrinsics(views, (1024, 768), ids, pts)
    assert "partial board" in res.rejected[100]
    assert "outlier view" in res.rejected[101]
    # within 4 of the reported standard deviations
    Kc = res.camera.K
    for name, est, true in (
        ("fx", Kc[0, 0], K[0, 0]),
        ("fy", Kc[1, 1], K[1, 1]),
        ("cx", Kc[0, 2], K[0, 2]),
        ("cy", Kc[1, 2], K[1, 2]),
    ):
        assert abs(est - true) < 4 * res.std[name], (name, est, true, res.std[name])
        assert res.std[name] < 3.0
    assert np.abs(res.camera.dist[:2] - DIST[:2]).max() < 0.01
    assert res.rms_px < 0.1
    assert set(res.std) >= {"fx", "fy", "cx", "cy", "k1"}
    assert len(res.per_view_rms_px) == 15


def test_calibrate_needs_enough_views():
    ids, pts = board_corners(BoardSpec())
    views = _views(3, np.random.default_rng(2), 0.05, pts)
    with pytest.raises(InputError, match="at least 5"):
        calibrate_intrinsics(views, (1024, 768), ids, pts)


def test_as_many_outlier_views_as_passes_are_all_rejected_and_the_rest_fitted():
    """Each pass rejects the worst view; when the last allowed pass still rejects one, the views left are fitted
    again (the camera and the poses are those of the kept views, not of a fit that still had the rejected one)."""
    ids, pts = board_corners(BoardSpec())
    rng = np.random.default_rng(4)
    views = _views(12, rng, 0.05, pts)
    for key in range(5):  # five views whose corners are off by 2-4 px (a moving board), each worse than the last
        views[key] = (ids, views[key][1] + rng.normal(0.0, 2.0 + 0.5 * key, (len(pts), 2)), None)
    res = calibrate_intrinsics(views, (1024, 768), ids, pts)
    assert sorted(res.rejected) == [0, 1, 2, 3, 4]
    assert sorted(res.per_view_rms_px) == list(range(5, 12))
    assert res.rms_px < 0.1  # the fit of the clean views: noise 0.05 px
    for name, i, j in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2)):
        assert abs(res.camera.K[i, j] - K[i, j]) < 4 * res.std[name], name


def _calibration_bytes(res):
    return json.dumps({"camera": res.camera.to_dict(), "summary": res.summary()}, sort_keys=True).encode()


def test_the_stages_called_one_by_one_give_what_calibrate_intrinsics_gives():
    from calib.camera import intrinsics as cm

    ids, pts = board_corners(BoardSpec())
    views = _views(12, np.random.default_rng(6), 0.05, pts)
    settings = cm.IntrinsicsSettings(lens_model="auto")
    whole = calibrate_intrinsics(views, (1024, 768), ids, pts, settings)
    with threadpool_limits(limits=1):
        board = cm.select_board_views(views, ids, pts, (1024, 768), settings.refine_object)
        board, first = cm.reject_outlier_views(board, "k1k2k3", settings)
        fits = cm.fit_lens_candidates(board, list(cm.LENS_MODELS), {"k1k2k3": first}, start=first)
        choice = cm.choose_lens_model("auto", fits, board)
        refined = cm.refine_intrinsics(fits[choice.chosen], board, settings.weight_views)
        staged = cm.intrinsics_result(board, choice, refined, "auto")
    assert [e["model"] for e in choice.evidence] == list(cm.LENS_MODELS)
    assert _calibration_bytes(staged) == _calibration_bytes(whole)


def test_a_settings_object_and_keywords_agree_and_an_unknown_setting_is_named():
    from calib.camera.intrinsics import IntrinsicsSettings

    ids, pts = board_corners(BoardSpec())
    views = _views(8, np.random.default_rng(7), 0.05, pts)
    by_object = calibrate_intrinsics(views, (1024, 768), ids, pts, IntrinsicsSettings(lens_model="k1k2k3"))
    by_keyword = calibrate_intrinsics(views, (1024, 768), ids, pts, lens_model="k1k2k3")
    assert by_object.lens_model["chosen"] == "k1k2k3"
    assert _calibration_bytes(by_object) == _calibration_bytes(by_keyword)
    with pytest.raises(TypeError, match="lens_modle"):
        calibrate_intrinsics(views, (1024, 768), ids, pts, lens_modle="k1k2")


def test_the_calibration_does_not_depend_on_the_blas_thread_count():
    """Its small matrices are solved with one BLAS thread whatever the process runs with (more threads changed the
    last digits of the covariance, so the camera file's bytes depended on the machine's core count)."""
    ids, pts = board_corners(BoardSpec())
    views = _views(12, np.random.default_rng(8), 0.05, pts)
    with threadpool_limits(limits=1):
        one = calibrate_intrinsics(views, (1024, 768), ids, pts, lens_model="auto")
    with threadpool_limits(limits=2):
        two = calibrate_intrinsics(views, (1024, 768), ids, pts, lens_model="auto")
    assert _calibration_bytes(one) == _calibration_bytes(two)
