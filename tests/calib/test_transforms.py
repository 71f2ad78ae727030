"""Shared rotation numerics: ``kabsch`` (weighted Wahba fit), ``kabsch_points`` and ``tangent_basis``."""

from __future__ import annotations

import numpy as np
import pytest

from calib.numerics.transforms import cross, kabsch, kabsch_points, matrix_to_rotvec, rotvec_to_matrix, tangent_basis


def test_kabsch_points_recovers_a_rigid_map() -> None:
    rng = np.random.default_rng(0)
    R = rotvec_to_matrix(rng.normal(size=3))
    P = rng.normal(size=(12, 3))
    np.testing.assert_allclose(kabsch_points(P @ R.T + [0.1, -0.2, 0.3], P), R, atol=1e-12)


def test_weighted_kabsch_follows_the_weights() -> None:
    """A vector with a large weight is matched almost exactly, one with a tiny weight is ignored."""
    rng = np.random.default_rng(1)
    R = rotvec_to_matrix([0.2, -0.1, 0.3])
    U = rng.normal(size=(4, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    D = U @ R.T
    D[3] = rotvec_to_matrix([0.0, 0.0, 0.5]) @ D[3]  # one vector disagrees
    R_heavy = kabsch(D, U, [1.0, 1.0, 1.0, 1e6])
    R_light = kabsch(D, U, [1.0, 1.0, 1.0, 1e-9])
    assert np.linalg.norm(R_heavy @ U[3] - D[3]) < 1e-3
    np.testing.assert_allclose(R_light, R, atol=1e-6)
    assert np.isclose(np.linalg.det(R_heavy), 1.0)


def test_kabsch_names_a_bad_shape() -> None:
    with pytest.raises(ValueError, match=r"\(N, 3\).*\(4, 3\) and \(4, 2\)"):
        kabsch(np.zeros((4, 3)), np.zeros((4, 2)))


@pytest.mark.parametrize("u", [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.3, -0.4, 0.87], [1e-9, 1.0, 0.0]])
def test_tangent_basis_is_orthonormal_and_right_handed(u: list[float]) -> None:
    T = tangent_basis(u)
    n = np.asarray(u) / np.linalg.norm(u)
    assert T.shape == (3, 2)
    np.testing.assert_allclose(T.T @ T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(T.T @ n, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(T[:, 0], T[:, 1]), n, atol=1e-12)


def test_tangent_basis_batches() -> None:
    rng = np.random.default_rng(2)
    U = rng.normal(size=(5, 4, 3))
    T = tangent_basis(U)
    assert T.shape == (5, 4, 3, 2)
    np.testing.assert_allclose(T[2, 3], tangent_basis(U[2, 3]), atol=0)


def test_matrix_to_rotvec_is_scipys_conversion_bit_for_bit() -> None:
    """The fast path (SciPy's ``assume_valid`` after one vectorised check) gives SciPy's own answer, for exact
    rotations (products included, angles up to pi) and for matrices SciPy must first project to a rotation."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    rv = rng.normal(size=(200, 3))
    rv[:5] *= np.pi / np.linalg.norm(rv[:5], axis=1, keepdims=True)  # half-turns
    R = rotvec_to_matrix(rv)
    R = R @ R[::-1]
    assert np.array_equal(matrix_to_rotvec(R), Rotation.from_matrix(R).as_rotvec())
    assert matrix_to_rotvec(R.reshape(20, 10, 3, 3)).shape == (20, 10, 3) and matrix_to_rotvec(R[0]).shape == (3,)
    scaled = R[:4] * 1.001  # not a rotation: projected as SciPy does
    assert np.array_equal(matrix_to_rotvec(scaled), Rotation.from_matrix(scaled).as_rotvec())
    with pytest.raises(ValueError):
        matrix_to_rotvec(-R[:2])  # a reflection is refused, as by SciPy


@pytest.mark.parametrize("scale", [0.0, 1e-7, 0.3, 2.8])
def test_so3_left_jacobians_are_the_derivatives_of_exp_and_log(scale: float) -> None:
    """``exp(phi + d) = exp(J_l d) exp(phi)`` and ``log(exp(d) exp(phi)) = phi + J_l^-1 d`` to first order, from
    zero (the series) to near a half-turn."""
    from calib.numerics.transforms import so3_left_jacobian, so3_left_jacobian_inverse

    phi = scale * np.array([0.36, -0.48, 0.8])
    E = rotvec_to_matrix(phi)
    h = 1e-7
    num = np.column_stack(
        [
            (
                matrix_to_rotvec(rotvec_to_matrix(phi + h * e) @ E.T)
                - matrix_to_rotvec(rotvec_to_matrix(phi - h * e) @ E.T)
            )
            / (2 * h)
            for e in np.eye(3)
        ]
    )
    num_inv = np.column_stack(
        [
            (matrix_to_rotvec(rotvec_to_matrix(h * e) @ E) - matrix_to_rotvec(rotvec_to_matrix(-h * e) @ E)) / (2 * h)
            for e in np.eye(3)
        ]
    )
    np.testing.assert_allclose(so3_left_jacobian(phi), num, atol=1e-8)
    np.testing.assert_allclose(so3_left_jacobian_inverse(phi), num_inv, atol=1e-8)
    np.testing.assert_allclose(so3_left_jacobian(phi) @ so3_left_jacobian_inverse(phi), np.eye(3), atol=1e-12)
    assert so3_left_jacobian(np.tile(phi, (4, 2, 1))).shape == (4, 2, 3, 3)


def test_cross_is_numpys_cross_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    for sa, sb in [((3,), (3,)), ((7, 3), (7, 3)), ((4, 2, 3), (2, 3)), ((5, 3), (3,)), ((3,), (5, 3))]:
        a, b = rng.normal(size=sa), rng.normal(size=sb)
        assert np.array_equal(cross(a, b), np.cross(a, b)), (sa, sb)
    assert np.array_equal(cross([1.0, 0, 0], [0, 1.0, 0]), [0.0, 0.0, 1.0])  # lists too
    with pytest.raises(ValueError, match=r"\(2,\)"):
        cross(np.ones(2), np.ones(3))
