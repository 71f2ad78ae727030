"""The linear Delta: closed-form IKM/DKM, analytic Jacobian, refusals, and which parameters end-effector data
identify (rank of the identification Jacobian over a pose set, and the unidentifiable direction named)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import UnreachableError
from calib.mechanisms.linear_delta import COMBINATION_NAMES, PARAMETER_NAMES, DeltaWorkspace, LinearDelta
from calib.numdiff import central_jacobian

DELTA = LinearDelta()


def _perturbed(seed: int = 1):
    rng = np.random.default_rng(seed)
    v = DELTA.to_vector(DELTA.nominal())
    scale = np.array([2e-3] * 3 + [5e-3] * 3 + [2e-3] * 3 + [3e-3] * 3 + [1e-3])  # m, rad, m, m, m
    return DELTA.from_vector(v + rng.normal(0, 1, v.size) * scale)


@pytest.mark.parametrize("params", [DELTA.nominal(), _perturbed()], ids=["nominal", "perturbed"])
def test_dkm_inverts_ikm_over_the_workspace(params) -> None:
    P = DeltaWorkspace().sample(400, np.random.default_rng(5))
    q = DELTA.ikm(params, P)
    np.testing.assert_allclose(DELTA.dkm(params, q), P, atol=1e-12)
    np.testing.assert_allclose(DELTA.ikm(params, P[7]), q[7])  # one row: shape (3,)
    A, B = DELTA.leg_rods(params, q, P)
    np.testing.assert_allclose(np.linalg.norm(B - A, axis=2), np.broadcast_to(params.L, (len(P), 3)), atol=1e-12)
    assert np.all(B[:, :, 2] < A[:, :, 2])  # the plate hangs below the carriages


def test_jacobian_matches_numerical_differences() -> None:
    params = _perturbed(2)
    for pose in DeltaWorkspace().grid():
        J = DELTA.jacobian(params, pose)
        Jn = central_jacobian(lambda x: DELTA.ikm(params, x), pose, h=1e-6)
        np.testing.assert_allclose(J, Jn, atol=1e-8)
        # and it inverts the DKM's Jacobian: d P / d q
        q = DELTA.ikm(params, pose)
        Jd = central_jacobian(lambda x: DELTA.dkm(params, x), q, h=1e-6)
        np.testing.assert_allclose(J @ Jd, np.eye(3), atol=1e-6)


def test_unreachable_poses_and_joint_vectors_are_named() -> None:
    p = DELTA.nominal()
    P = np.array([[0.0, 0.0, -0.3], [0.40, 0.0, -0.3]])
    # columns 1 (90 deg) and 2 (210 deg) are out of reach of x = 0.4 m, column 3 (330 deg) is not
    with pytest.raises(
        UnreachableError, match=r"pose #1 \[400.0, 0.0, -300.0\] mm is unreachable: leg 1 .*and 1 more"
    ) as ei:
        DELTA.ikm(p, P)
    assert ei.value.index == 1 and ei.value.leg == 1
    assert ei.value.deficit_m == pytest.approx(np.hypot(np.hypot(0.4, 0.15), 0.02) - 0.3)
    q = DELTA.ikm(p, [0.0, 0.0, -0.3])
    with pytest.raises(UnreachableError, match=r"joint vector #0 .* the three legs cannot meet"):
        DELTA.dkm(p, q + np.array([0.8, 0.0, 0.0]))


def _identification_jacobian(params, poses: np.ndarray) -> np.ndarray:
    """d (observed plate centres) / d (13 parameters) at the joint values of ``poses``, shape (3N, 13)."""
    q = DELTA.ikm(params, poses)
    v0 = DELTA.to_vector(params)
    return central_jacobian(
        lambda v: DELTA.ee_point(DELTA.from_vector(v), DELTA.dkm(DELTA.from_vector(v), q)).ravel(), v0
    )


def test_end_effector_data_identify_twelve_combinations_not_the_plate_radius() -> None:
    params = DELTA.nominal()
    J = _identification_jacobian(params, DeltaWorkspace().grid())
    Js = J / np.linalg.norm(J, axis=0)
    s = np.linalg.svd(Js, compute_uv=False)
    rank = int(np.sum(s > 1e-7 * s[0]))
    assert len(PARAMETER_NAMES) == 13 and rank == 12 == len(COMBINATION_NAMES)
    assert s[-2] / s[0] > 1e-3  # the twelve are well conditioned, the thirteenth is numerically zero
    # the unidentifiable direction: r with every R_i (at theta_i = phi_i), nothing else
    null = np.linalg.svd(J)[2][-1]
    expected = np.zeros(13)
    expected[[0, 1, 2, 12]] = 1.0
    assert abs(null @ expected) / np.linalg.norm(expected) > 1 - 1e-8
    # the combinations do not move along it: they are functions of the identifiable part only
    c0 = np.array(list(DELTA.identifiable_combinations(params).values()))
    Jc = central_jacobian(
        lambda v: np.array(list(DELTA.identifiable_combinations(DELTA.from_vector(v)).values())),
        DELTA.to_vector(params),
    )
    assert np.linalg.norm(Jc @ null) < 1e-8
    assert np.linalg.matrix_rank(Jc) == 12 and c0.shape == (12,)


def test_at_a_perturbed_geometry_the_rank_is_still_twelve() -> None:
    J = _identification_jacobian(_perturbed(3), DeltaWorkspace().grid())
    s = np.linalg.svd(J / np.linalg.norm(J, axis=0), compute_uv=False)
    assert int(np.sum(s > 1e-7 * s[0])) == 12


def test_analytic_identification_jacobian_matches_numerical_differences() -> None:
    params = _perturbed(4)
    q = DELTA.ikm(params, DeltaWorkspace().grid())
    Ja = DELTA.ee_parameter_jacobian(params, q)
    Jn = central_jacobian(lambda v: DELTA.dkm(DELTA.from_vector(v), q).ravel(), DELTA.to_vector(params), h=1e-6)
    np.testing.assert_allclose(Ja.reshape(-1, 13), Jn, atol=1e-7)
