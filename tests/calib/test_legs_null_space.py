"""The directions of the seven parameters that the four combinations do not see, and the legs method's a priori
values along them on images (:func:`calib.identify.legs.uncertainty.null_space_to_prior`)."""

from __future__ import annotations

import numpy as np

from calib.identify.legs import combinations_null_space, null_space_to_prior
from calib.model.parameters import NOMINAL, SEVEN_TO_FOUR


def test_null_space_is_orthonormal_and_invisible_to_the_combinations():
    N = combinations_null_space()
    assert N.shape == (7, 3)
    assert np.allclose(N.T @ N, np.eye(3), atol=1e-12)
    assert np.allclose(SEVEN_TO_FOUR @ N, 0.0, atol=1e-12)
    # with the four combinations' rows it spans all seven parameters
    assert np.linalg.matrix_rank(np.vstack([SEVEN_TO_FOUR, N.T])) == 7


def test_a_priori_along_the_null_space_keeps_the_combinations_and_their_covariance():
    rng = np.random.default_rng(3)
    nominal = np.asarray(NOMINAL.vector())
    N = combinations_null_space()
    off_null = rng.normal(0.0, 1e-3, 7)
    off_null -= N @ (N.T @ off_null)  # a move the combinations see
    seven = nominal + off_null + N @ np.array([0.004, 0.02, 0.012])  # plus the data's error along the null space
    A = rng.normal(0.0, 1e-3, (7, 7))
    parts = {"joint_centres": A @ A.T, "leg_directions": 1e-7 * np.eye(7)}
    total = sum(parts.values())
    out, cov, out_parts, dirs = null_space_to_prior(seven, parts, NOMINAL, 0.01)
    # the combinations and their covariance are the data's
    assert np.allclose(SEVEN_TO_FOUR @ out, SEVEN_TO_FOUR @ seven, atol=1e-15)
    assert np.allclose(SEVEN_TO_FOUR @ cov @ SEVEN_TO_FOUR.T, SEVEN_TO_FOUR @ total @ SEVEN_TO_FOUR.T, rtol=1e-12)
    # along the null space: the nominal geometry, the tolerance's variance, nothing of the data's
    assert np.allclose(N.T @ (out - nominal), 0.0, atol=1e-15)
    assert np.allclose(N.T @ cov @ N, 1e-4 * np.eye(3), rtol=1e-12)
    assert np.allclose(cov, sum(out_parts.values()))
    assert [round(d["data_estimate_m"], 6) for d in dirs] == [0.004, 0.02, 0.012]
