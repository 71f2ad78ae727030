"""The design bench records how the rods' refined camera errs against the covariance it reports.

On the image-level twin the rods' refinement of the camera (``calibration.covariance_refined``) holds along every
principal direction but the lens's radial distortion, where its error is 1.6-1.7x its std (docs/design.md); the
legs method's L error on the seed-3 paper plan follows it. Each trial now records the refined camera's error in that
covariance (total Mahalanobis distance and per principal direction) and ``i4cal bench design --report`` prints the
means over a plan's trials, which are 1 when the covariance is right.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from calib.camera.intrinsics import intrinsics_vector
from calib.formats.camera import CameraModel
from i4cal.benchmarks._accuracy_trial import _refined_honesty, error_against_covariance
from i4cal.benchmarks.design import _summarize_plans, camera_refined_summary, print_table

NAMES = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]


def _covariance(rng: np.random.Generator) -> np.ndarray:
    """A correlated 9 x 9 covariance with variances spread over eight decades (like a camera's)."""
    Q, _ = np.linalg.qr(rng.normal(size=(9, 9)))
    return Q @ np.diag(10.0 ** rng.uniform(-8, 0, 9)) @ Q.T


def test_errors_drawn_from_the_covariance_give_one_per_direction_and_an_understated_one_shows():
    rng = np.random.default_rng(5)
    C = _covariance(rng)
    w, V = np.linalg.eigh(C)
    n = 800
    right = [error_against_covariance(rng.multivariate_normal(np.zeros(9), C), C) for _ in range(n)]
    z2 = np.array([r["principal_z2"] for r in right])
    se = np.sqrt(2.0 / n)  # a chi-square(1) mean's standard error
    assert np.all(np.abs(z2.mean(axis=0) - 1.0) < 4 * se)
    assert abs(np.mean([r["mahalanobis"] for r in right]) / 9 - 1.0) < 4 * np.sqrt(2.0 / (9 * n))
    # the errors 1.7x their std along the third smallest direction (what the twin's rods do along the radial terms)
    scale = np.ones(9)
    scale[2] = 1.7
    C_true = V @ np.diag(w * scale**2) @ V.T
    wrong = np.array(
        [error_against_covariance(rng.multivariate_normal(np.zeros(9), C_true), C)["principal_z2"] for _ in range(n)]
    )
    means = wrong.mean(axis=0)
    assert abs(means[2] - 1.7**2) < 4 * np.sqrt(2.0 / n) * 1.7**2
    assert np.all(np.abs(np.delete(means, 2) - 1.0) < 4 * se)


def test_a_covariance_that_is_not_positive_definite_or_of_another_size_gives_none():
    assert error_against_covariance([1.0, 2.0], np.diag([1.0, 0.0])) is None
    assert error_against_covariance([1.0, 2.0], np.eye(3)) is None
    assert error_against_covariance([1.0, np.nan], np.eye(2)) is None


def _camera(dist, extra=None) -> CameraModel:
    K = np.array([[775.0, 0, 520.0], [0, 776.0, 380.0], [0, 0, 1]])
    return CameraModel(K, np.asarray(dist, dtype=float), 1024, 768, extra or {})


def test_the_refined_cameras_error_is_taken_in_its_own_parameters():
    true = _camera([-0.30, 0.10, 4e-4, -3e-4])  # no k3 term: 0
    std = np.array([0.2, 0.2, 0.1, 0.1, 1e-4, 5e-4, 2e-5, 2e-5, 1e-3])
    cov = np.diag(std**2)
    err = std * np.array([1.0, -2.0, 0.5, 0.0, 1.0, 0.0, 0.0, 3.0, -1.0])
    refined = SimpleNamespace(
        camera=CameraModel(
            true.K + np.array([[err[0], 0, err[2]], [0, err[1], err[3]], [0, 0, 0]]),
            np.array([-0.30, 0.10, 4e-4, -3e-4, 0.0]) + err[4:][[0, 1, 2, 3, 4]],
            1024,
            768,
            {"calibration": {"covariance_params": NAMES, "covariance_refined": cov.tolist()}},
        )
    )
    assert intrinsics_vector(true, NAMES)[-1] == 0.0
    out = _refined_honesty(refined, true)
    assert out["dof"] == 9
    assert out["mahalanobis"] == pytest.approx(1 + 4 + 0.25 + 1 + 9 + 1, rel=1e-9)
    assert sorted(out["principal_z2"]) == pytest.approx(sorted([1, 4, 0.25, 0, 1, 0, 0, 9, 1]), abs=1e-9)
    # a camera the rods did not refine records nothing
    assert _refined_honesty(SimpleNamespace(camera=_camera([-0.3, 0.1, 0, 0], {"calibration": {}})), true) is None


def test_the_bench_summarises_and_prints_it_per_plan(capsys):
    rng = np.random.default_rng(2)
    C = _covariance(rng)
    records = []
    for k in range(40):
        rec = error_against_covariance(rng.multivariate_normal(np.zeros(9), C) * 2.0, C)  # every error 2x its std
        records.append({"index": k, "methods": {}, "camera": {"intrinsics": {"refined_against_covariance": rec}}})
    records.append({"index": 40, "methods": {}, "camera": None})  # a trial without it is left out
    plans = {
        "paper-20": {
            "records": records,
            "predicted_std_m": {},
            "motion_s": 60.0,
        }
    }
    _summarize_plans(plans)
    cam = plans["paper-20"]["camera_refined"]
    assert cam["n"] == 40 and cam["dof"] == 9
    assert cam["mahalanobis_per_dof_mean"] == pytest.approx(4.0, abs=4 * 4 * np.sqrt(2 / (9 * 40)))
    assert np.all(np.abs(np.array(cam["principal_z2_mean"]) - 4.0) < 4 * 4 * cam["expected_se"])
    assert camera_refined_summary([{"camera_refined": None}]) is None
    doc = {"plans": plans, "checks": {}, "elapsed_s": 1.0, "date": "today"}
    print_table(doc)
    out = capsys.readouterr().out
    assert "paper-20: the rods' refined camera against its covariance over 40 trials" in out
