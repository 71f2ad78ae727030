import numpy as np
import pytest

from calib import (
    NOMINAL,
    I4Parameters,
    UnreachableError,
    dkm,
    identifiable_parameters,
    ikm,
    jacobian,
    joint_points,
    leg_directions,
)
from calib.formats.plan import Workspace, random_poses


def _poses(n: int, seed: int = 0) -> np.ndarray:
    return random_poses(NOMINAL, n, np.random.default_rng(seed), Workspace(min_leg_x_m=0.1))


def test_dkm_inverts_ikm_on_thousands_of_poses():
    X = _poses(5000)
    q = ikm(NOMINAL, X)
    assert q.shape == (5000, 4)
    np.testing.assert_allclose(dkm(NOMINAL, q), X, atol=1e-12, rtol=0)


def test_legs_keep_their_length():
    X = _poses(3000, seed=1)
    A, B = joint_points(NOMINAL, ikm(NOMINAL, X), X)
    np.testing.assert_allclose(np.linalg.norm(B - A, axis=2), NOMINAL.L, atol=1e-12, rtol=0)


def test_legs_hang_below_and_converge():
    X = _poses(500, seed=2)
    u = leg_directions(NOMINAL, X)
    assert np.all(u[:, :, 2] < 0)
    assert np.all(u[:, 0, 0] > 0) and np.all(u[:, 2, 0] > 0)
    np.testing.assert_allclose(u[:, 1, 0], -u[:, 0, 0], atol=1e-14)


def test_jacobian_equals_finite_differences():
    X = _poses(50, seed=3)
    J = jacobian(NOMINAL, X)
    h = 1e-6
    for k in range(4):
        e = np.zeros(4)
        e[k] = h
        col = (ikm(NOMINAL, X + e) - ikm(NOMINAL, X - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], col, atol=1e-8)


def test_jacobian_row2_last_column_is_plus_one():
    J = jacobian(NOMINAL, _poses(1)[0])
    assert J[:, 3].tolist() == [1.0, 1.0, -1.0, -1.0]
    assert J[:, 0].tolist() == [1.0, 1.0, 1.0, 1.0]


def test_single_pose_shapes():
    X = _poses(1)[0]
    assert ikm(NOMINAL, X).shape == (4,)
    assert dkm(NOMINAL, ikm(NOMINAL, X)).shape == (4,)
    assert jacobian(NOMINAL, X).shape == (4, 4)


def test_unreachable_pose_names_leg_and_deficit():
    X = np.array([0.9, 0.0, -1.2, 0.0])  # legs too short to reach 1.2 m down
    with pytest.raises(UnreachableError) as ei:
        ikm(NOMINAL, X)
    assert ei.value.leg in (1, 3)
    assert ei.value.deficit_m > 0
    assert "mm too short" in str(ei.value)


def test_unreachable_joints_never_nan():
    q = np.array([0.0, 2.0, 0.0, 2.0])  # carriages too far apart
    with pytest.raises(UnreachableError, match="too short"):
        dkm(NOMINAL, q)
    q = np.array([0.5, -1.0, 0.0, 0.0])  # legs 1 and 2 would cross
    with pytest.raises(UnreachableError, match="cross"):
        dkm(NOMINAL, q)


def test_bad_shapes_raise_value_error():
    with pytest.raises(ValueError, match=r"shape \(4,\) or \(N, 4\)"):
        ikm(NOMINAL, np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        ikm(NOMINAL, [np.nan, 0, 0, 0])


def test_identifiable_combinations_and_completion():
    c = identifiable_parameters(NOMINAL)
    assert c == pytest.approx({"L": 1.001, "H-D": 0.3464, "S-q02/2": -0.6316, "S-(q04-q03)/2": -0.6304})
    p = I4Parameters.from_combinations({"L": 1.0, "H-D": 0.35, "S-q02/2": -0.62, "S-(q04-q03)/2": -0.63}, NOMINAL)
    assert p.combinations() == pytest.approx({"L": 1.0, "H-D": 0.35, "S-q02/2": -0.62, "S-(q04-q03)/2": -0.63})


def test_jacobian_depends_only_on_the_four_combinations():
    """Changing a non-identifiable direction (H, D together; S with q0i) leaves J(q) unchanged."""
    q = ikm(NOMINAL, _poses(20, seed=4))
    other = NOMINAL.replace(
        H=NOMINAL.H + 0.01, D=NOMINAL.D + 0.01, S=NOMINAL.S + 0.02, q02=NOMINAL.q02 + 0.04, q04=NOMINAL.q04 + 0.04
    )
    np.testing.assert_allclose(jacobian(other, dkm(other, q)), jacobian(NOMINAL, dkm(NOMINAL, q)), atol=1e-12)


def test_parameters_validate():
    with pytest.raises(ValueError, match="L must be positive"):
        NOMINAL.replace(L=-1.0)
    with pytest.raises(ValueError, match="finite"):
        NOMINAL.replace(H=float("nan"))
