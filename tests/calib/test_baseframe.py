import numpy as np
import pytest

from calib.errors import IdentifiabilityError
from calib.formats.observations import Observations
from calib.identify.baseframe import base_frame_from_observations, estimate_base_frame, fit_rotation_axis
from calib.numerics.transforms import matrix_to_rotvec, rot_z
from drivers.sim.twin import GeometricTwin


def test_noise_free_base_frame_is_exact(noise_free_obs):
    obs, twin = noise_free_obs
    bf = base_frame_from_observations(obs)
    err = matrix_to_rotvec(twin.geometry.camera_from_base.R @ bf.camera_from_base_R.T)
    assert np.linalg.norm(err) < 1e-10
    assert bf.translation_scale == pytest.approx(1.0, abs=1e-9)
    assert bf.orthogonality_error_deg < 1e-8


def test_base_frame_covariance_matches_monte_carlo(paper_plan):
    twin = GeometricTwin()
    errs, covs = [], []
    for seed in range(60):
        bf = base_frame_from_observations(Observations.from_dict(twin.observations(plan=paper_plan, seed=seed)))
        errs.append(matrix_to_rotvec(twin.geometry.camera_from_base.R @ bf.camera_from_base_R.T))
        covs.append(np.diag(bf.cov_rotvec))
    ratio = np.std(errs, axis=0, ddof=1) / np.sqrt(np.mean(covs, axis=0))
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio


def test_rotation_axis_sign_follows_T():
    z = np.array([0.1, -0.2, 0.97])
    z /= np.linalg.norm(z)
    from calib.numerics.transforms import rotvec_to_matrix

    T = np.linspace(-0.05, 0.05, 8)
    R = np.array([rotvec_to_matrix(z * t / 0.02) for t in T]) @ rot_z(0.3)
    zf, *_ = fit_rotation_axis(R, T)
    np.testing.assert_allclose(zf, z, atol=1e-12)
    zf2, *_ = fit_rotation_axis(R, -T)
    np.testing.assert_allclose(zf2, -z, atol=1e-12)


def test_no_rotation_is_an_identifiability_error(noise_free_obs):
    obs = noise_free_obs[0]
    rot = obs.arrays("rotation")
    still = rot.subset(np.zeros(len(rot), dtype=bool) | True)
    Rs = np.repeat(still.board_R[:1], len(still), axis=0)
    from dataclasses import replace

    with pytest.raises(IdentifiabilityError, match="z_B is not excited"):
        estimate_base_frame(replace(still, board_R=Rs), obs.arrays("translation"))
    tr = obs.arrays("translation")
    with pytest.raises(IdentifiabilityError, match="x_B"):
        estimate_base_frame(rot, replace(tr, q=np.repeat(tr.q[:1], len(tr), axis=0)))


def test_start_from_a_previous_estimate_follows_a_moved_rig(noise_free_obs):
    """``estimate_base_frame(..., start=)`` (the combined fit's propagation of the intrinsics through the base
    frame: one linear step from the converged fit) follows a small rotation of the whole rig exactly."""
    from dataclasses import replace

    from calib.numerics.transforms import rotvec_to_matrix

    obs = noise_free_obs[0]
    rot, tra = obs.arrays("rotation"), obs.arrays("translation")
    rng = np.random.default_rng(3)
    noisy = replace(rot, board_R=rotvec_to_matrix(rng.normal(scale=2e-4, size=(len(rot), 3))) @ rot.board_R)
    bf = estimate_base_frame(noisy, tra)
    assert bf.axis_state is not None and "J" in bf.axis_state
    w = np.array([2e-4, -1e-4, 3e-4])
    Q = rotvec_to_matrix(w)
    moved = estimate_base_frame(
        replace(noisy, board_R=Q @ noisy.board_R, board_t=noisy.board_t @ Q.T),
        replace(tra, board_R=Q @ tra.board_R, board_t=tra.board_t @ Q.T),
        start=bf,
    )
    err = matrix_to_rotvec(moved.camera_from_base_R @ (Q @ bf.camera_from_base_R).T)
    assert np.linalg.norm(err) < 1e-8, err
    cold = estimate_base_frame(
        replace(noisy, board_R=Q @ noisy.board_R, board_t=noisy.board_t @ Q.T),
        replace(tra, board_R=Q @ tra.board_R, board_t=tra.board_t @ Q.T),
    )
    assert np.linalg.norm(matrix_to_rotvec(cold.camera_from_base_R @ moved.camera_from_base_R.T)) < 1e-6


@pytest.mark.parametrize("weighted", [False, True])
def test_axis_fit_jacobian_is_the_derivative_of_its_residuals(weighted):
    """The rotation-axis fit is given its analytic Jacobian (SO(3) left Jacobians): it must be the residuals'
    derivative, whitened or not, away from the solution (large residuals) as well as near it."""
    from calib.identify.baseframe import _axis_jacobian, _axis_residuals
    from calib.numerics.numdiff import central_jacobian
    from calib.numerics.transforms import rotvec_to_matrix, unit

    rng = np.random.default_rng(2)
    n = 8
    z0 = unit(rng.normal(size=3))
    e1 = unit(np.cross(z0, [1.0, 0.0, 0.0]))
    axes = (z0, e1, np.cross(z0, e1))
    R = rotvec_to_matrix(rng.normal(size=(n, 3)))
    x = np.concatenate([[0.01, -0.02], 0.05 * rng.normal(size=3), rng.uniform(-0.5, 0.5, n)])
    W = rng.normal(size=(3, 3)) if weighted else None
    num = central_jacobian(lambda v: _axis_residuals(R, axes, v, W), x, 1e-7)
    np.testing.assert_allclose(_axis_jacobian(R, axes, x, W), num, rtol=0, atol=1e-7 * np.abs(num).max())
