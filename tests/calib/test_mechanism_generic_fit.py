"""The generic end-effector identification (any Mechanism) on the linear Delta: a seeded Monte-Carlo shows the
reported standard deviations match the spread of the estimates, and the estimate recovers a perturbed truth."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import IdentifiabilityError, InputError
from calib.mechanisms import get_mechanism
from calib.mechanisms.linear_delta import DeltaWorkspace
from calib.methods.generic_end_effector import fit_end_effector
from drivers.sim.delta_twin import DEFAULT_TRUTH, DeltaNoise, DeltaTwin

DELTA = get_mechanism("linear-delta")
POSES = DeltaWorkspace().grid()  # 39 poses
Q_TARGETS = DELTA.ikm(DELTA.nominal(), POSES)  # computed with the nominal model, as a bench does
N_DRAWS = 200


def _truth_combos() -> np.ndarray:
    return np.array(list(DELTA.identifiable_combinations(DEFAULT_TRUTH).values()))


def test_noise_free_data_give_back_the_truth_and_name_the_unidentifiable_direction() -> None:
    d = DeltaTwin(noise=DeltaNoise(camera_m=(0.0, 0.0, 0.0), encoder_m=0.0)).acquire(Q_TARGETS)
    res = fit_end_effector(DELTA, d["q"], d["points"], 1e-4)
    np.testing.assert_allclose(list(res.combinations.values()), _truth_combos(), atol=1e-9)
    assert res.rank == 12 and res.dof == 3 * len(POSES) - 12
    # the plate radius trades against the columns: with the column angles off the plate's joint angles (the
    # truth's are, by 2.5-4 mrad), r -> r + e moves each R_i u(theta_i) by e u(phi_i): R_i mostly, theta_i a little
    assert [k for k, v in res.identifiable.items() if not v] == ["R1", "R2", "R3", "theta1", "theta2", "theta3", "r"]
    assert np.isnan(res.std["r"]) and np.isnan(res.std["theta1"]) and np.isfinite(res.std["L1"])
    (null,) = res.null_directions
    assert {k for k, v in null.items() if abs(v) > 0.01} == {"R1", "R2", "R3", "r"}
    assert np.allclose([null[k] for k in ("R1", "R2", "R3", "r")], 0.5, atol=0.01)
    d_theta = np.asarray(DEFAULT_TRUTH.theta) - np.asarray(DEFAULT_TRUTH.phi)
    R = np.asarray(DEFAULT_TRUTH.R)  # R u(theta) + e u(phi): d theta = -e (theta - phi) / R to first order
    np.testing.assert_allclose([null[f"theta{i}"] for i in (1, 2, 3)], -0.5 * d_theta / R, rtol=0.02)
    # the parameters identifiable one by one are the truth's
    for name in ("L1", "L2", "L3", "z01", "z02", "z03"):
        k = DELTA.parameter_names.index(name)
        assert res.parameters[name] == pytest.approx(DELTA.to_vector(DEFAULT_TRUTH)[k], abs=1e-9)
    np.testing.assert_allclose(res.residuals_m, 0.0, atol=1e-9)


def test_one_noisy_fit_recovers_a_perturbed_truth_within_its_std() -> None:
    d = DeltaTwin(seed=123).acquire(Q_TARGETS)
    res = fit_end_effector(DELTA, d["q"], d["points"], d["points_std"])
    err = np.array(list(res.combinations.values())) - _truth_combos()
    std = np.array(list(res.combinations_std.values()))
    start_err = np.array(list(DELTA.identifiable_combinations(DELTA.nominal()).values())) - _truth_combos()
    assert np.all(np.abs(err) < 4.5 * std), err / std  # 4.5 sigma: 12 combinations, a 1e-4 chance of a false alarm
    assert np.max(np.abs(start_err) / std) > 5  # the truth is far from the start, in std units
    assert 0.7 < res.sigma0 < 1.3  # the residuals match the twin's camera noise (dof = 105)


def test_monte_carlo_reported_std_matches_the_spread() -> None:
    truth = _truth_combos()
    errs, stds, z2 = [], [], []
    for k in range(N_DRAWS):
        d = DeltaTwin(seed=1000 + k).acquire(Q_TARGETS)
        res = fit_end_effector(DELTA, d["q"], d["points"], d["points_std"])
        e = np.array(list(res.combinations.values())) - truth
        errs.append(e)
        stds.append(list(res.combinations_std.values()))
        z2.append(e @ np.linalg.solve(res.combinations_covariance, e))
    E, S = np.array(errs), np.array(stds)
    n = N_DRAWS
    # unbiased: each mean error within 4 standard errors of zero
    assert np.all(np.abs(E.mean(axis=0)) < 4 * S.mean(axis=0) / np.sqrt(n))
    # spread vs reported std, per combination: the sample std's relative std is 1/sqrt(2(n-1)); 4 of them
    ratio = E.std(axis=0, ddof=1) / S.mean(axis=0)
    tol = 4 / np.sqrt(2 * (n - 1))
    assert np.all(np.abs(ratio - 1) < tol), (ratio, tol)
    # the full covariance: e^T C^-1 e is chi-square with 12 dof (mean 12, variance 24, plus the scaling by sigma0)
    assert abs(np.mean(z2) - 12) < 4 * np.sqrt(2 * 24 / n)


def test_bad_inputs_are_named() -> None:
    with pytest.raises(InputError, match="3 joint readings but 2 measured points"):
        fit_end_effector(DELTA, Q_TARGETS[:3], POSES[:2], 1e-4)
    with pytest.raises(InputError, match="std"):
        fit_end_effector(DELTA, Q_TARGETS, POSES, 0.0)
    with pytest.raises(IdentifiabilityError, match="more poses needed"):
        fit_end_effector(DELTA, Q_TARGETS[:4], POSES[:4], 1e-4)
