"""The calibration bundle (calib/camera/bundle.py) on synthetic corners with known per-view noise.

* the unknowns' vector round-trips through ``with_vector``;
* the Jacobian is the residuals' (central differences);
* ``refine_weighted`` finds each view's noise level (the views' true std range 0.02-0.2 px, as on the image-level
  twin) and its intrinsics' errors are covered by the weighted covariance.
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.camera.bundle import Bundle, bundle_covariance, refine_weighted, view_dof
from calib.camera.charuco import board_corners
from calib.numerics.numdiff import central_jacobian
from calib.numerics.transforms import matrix_to_rotvec
from drivers.sim.render import BenchRenderer, RenderSettings

NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")


def _synthetic(seed: int, views: int = 20):
    rs = RenderSettings()
    cam = rs.camera()
    poses = BenchRenderer(settings=rs, seed=seed).random_board_views(views, np.random.default_rng(seed))
    _, pts = board_corners(rs.board)
    rng = np.random.default_rng([seed, 1])
    sigma = np.exp(rng.uniform(np.log(0.02), np.log(0.2), views))
    imgs = [cam.project(p.apply(pts)) + rng.normal(0.0, s, (len(pts), 2)) for p, s in zip(poses, sigma, strict=True)]
    ncols = int(np.sum(np.isclose(pts[:, 1], pts[0, 1])))
    truth = Bundle.of(
        cam.K, cam.dist, pts, imgs, [matrix_to_rotvec(p.R) for p in poses], [p.t for p in poses], ncols - 1, NAMES
    )
    return truth, sigma


def test_vector_round_trip_and_jacobian():
    b, _ = _synthetic(1, 6)
    x = b.vector()
    assert x.size == b.n_params
    np.testing.assert_array_equal(b.with_vector(x).vector(), x)
    _rs, Js = b.jacobian()
    J = np.vstack(Js)
    num = central_jacobian(lambda v: np.concatenate(b.with_vector(v).residuals()), x, 1e-7)
    np.testing.assert_allclose(J, num, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("seed", [2, 3])
def test_refine_weighted_finds_the_view_noise_and_is_covered(seed):
    truth, sigma = _synthetic(seed)
    assert view_dof(truth) > 10
    rng = np.random.default_rng(seed)
    start = truth.with_vector(
        truth.vector()
        + np.r_[rng.normal(0, [2, 2, 3, 3, 1e-3, 1e-3, 1e-4, 1e-4]), np.zeros(truth.n_params - len(NAMES))]
    )
    refined, var, converged = refine_weighted(start)
    assert converged
    ratio = np.sqrt(var) / sigma
    # each view's std from its ~22 degrees of freedom: within 40% of the truth for most views
    assert np.median(np.abs(np.log(ratio))) < np.log(1.4), ratio
    cov, _ = bundle_covariance(refined, var)
    e = refined.vector()[: len(NAMES)] - truth.vector()[: len(NAMES)]
    d2 = float(e @ np.linalg.solve(cov, e))
    assert d2 < 26.1, d2  # chi-square(8) 99.9 %


def test_spd_inverse_of_a_nearly_singular_information_is_never_negative():
    """A lens model the views barely determine (OpenCV's rational one on the image twin's 30 views) gives an
    information matrix whose unknowns span many orders of scale and two near-collinear directions; ``np.linalg.inv``
    returned variances below zero there (a NaN std in the camera file)."""
    from calib.camera.bundle import spd_inverse

    rng = np.random.default_rng(3)
    n = 12
    V, _ = np.linalg.qr(rng.standard_normal((n, n)))
    w = np.logspace(0, -14, n)
    w[-1] = -1e-12  # the Schur complement's cancellation leaves the undetermined direction a hair below zero
    scale = np.logspace(3, -3, n)  # px-sized and dimensionless unknowns together
    S = (V * w) @ V.T * np.outer(scale, scale)
    naive = np.linalg.inv(S)
    inv = spd_inverse(S)
    assert np.all(np.diag(inv) > 0)
    assert np.all(np.linalg.eigvalsh(inv / np.sqrt(np.outer(np.diag(inv), np.diag(inv)))) > -1e-9)
    assert np.any(np.diag(naive) < 0), "the case no longer shows the failure it guards against"
    # a well-conditioned information is inverted as np.linalg.inv does
    S2 = (V * np.linspace(1.0, 2.0, n)) @ V.T * np.outer(scale, scale)
    np.testing.assert_allclose(spd_inverse(S2), np.linalg.inv(S2), rtol=1e-9)
