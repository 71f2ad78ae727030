"""The check's drift test and update (calib.check.drift), by seeded Monte-Carlo on Gaussian estimates: the false-alarm
rate is the family-wise alpha, a drift of 4 std on one combination is found and named, the update's std covers its
error, and updates that must not be applied are refused."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from calib.check.drift import (
    CombinationEstimate,
    DriftSettings,
    check_drift,
    max_abs_z_threshold,
    update_from_check,
)
from calib.errors import InputError
from calib.model.parameters import COMBINATION_NAMES

TRUTH_M = np.array([1.0, 0.35, -0.63, -0.63])
_A = np.random.default_rng(0).normal(size=(4, 4))
#: a check's covariance, correlated, std 38-92 um; the calibration in force knows 10x more (in variance)
CHECK_COV = (_A @ _A.T + np.eye(4)) * 1e-9
IN_FORCE_COV = 0.1 * CHECK_COV
N_DRAWS = 1500


def _binomial_bound(p: float, n: int, sigmas: float = 4.0) -> float:
    return sigmas * np.sqrt(p * (1 - p) / n)


def _draw(rng, truth_in_force, truth_now):
    in_force = CombinationEstimate(rng.multivariate_normal(truth_in_force, IN_FORCE_COV), IN_FORCE_COV)
    check = CombinationEstimate(rng.multivariate_normal(truth_now, CHECK_COV), CHECK_COV)
    return in_force, check


def test_threshold_is_sidak_for_independent_and_single_test_for_identical():
    alpha = 0.05
    sidak = norm.isf((1 - (1 - alpha) ** 0.25) / 2)
    assert max_abs_z_threshold(np.eye(4), alpha) == pytest.approx(sidak, abs=2e-3)
    assert max_abs_z_threshold(np.ones((4, 4)), alpha) == pytest.approx(norm.isf(alpha / 2), abs=2e-3)


def test_false_alarms_at_the_family_wise_alpha_when_nothing_drifted():
    rng = np.random.default_rng(1)
    alarms = 0
    for _ in range(N_DRAWS):
        r = check_drift(*_draw(rng, TRUTH_M, TRUTH_M))
        assert r.verdict in ("holds", "drifted")
        alarms += r.verdict == "drifted"
    rate = alarms / N_DRAWS
    assert abs(rate - 0.05) < _binomial_bound(0.05, N_DRAWS), rate


@pytest.mark.parametrize("k", range(4))
def test_a_drift_of_four_std_is_found_and_named(k):
    rng = np.random.default_rng(10 + k)
    name = COMBINATION_NAMES[k]
    step = 4.0 * np.sqrt(CHECK_COV[k, k] + IN_FORCE_COV[k, k])
    now = TRUTH_M + step * np.eye(4)[k]
    detected = named_alone = 0
    z_updates = []
    for _ in range(N_DRAWS // 3):
        in_force, check = _draw(rng, TRUTH_M, now)
        r = check_drift(in_force, check)
        detected += name in r.drifted
        named_alone += r.drifted == (name,)
        if r.drifted == (name,):
            assert r.change_m[name] == pytest.approx(step, abs=5 * r.change_std_m[name])
            u = update_from_check(in_force, check, r)
            assert u.accepted, u.reason
            assert u.reestimated == (name,)
            z_updates.append((u.estimate.value_m - now) / u.estimate.std_m())
    n = N_DRAWS // 3
    # P(|N(4, 1)| > t) for t the family-wise threshold (about 2.5): 0.93
    expected = norm.sf(max_abs_z_threshold(np.eye(4), 0.05) - 4.0)
    assert detected / n > expected - _binomial_bound(expected, n), detected / n
    assert named_alone / n > 0.85
    z = np.array(z_updates)
    # the update's reported std matches its spread (chi-square bound on the spread of ~460 draws: +/-10%)
    assert np.all(np.abs(z.std(axis=0) - 1.0) < 0.12), z.std(axis=0)
    assert np.all(np.abs(z.mean(axis=0)) < 4.0 / np.sqrt(len(z)) + 0.15), z.mean(axis=0)


def test_update_keeps_the_prior_where_nothing_drifted():
    rng = np.random.default_rng(5)
    step = 4.0 * np.sqrt(CHECK_COV[0, 0] + IN_FORCE_COV[0, 0])
    in_force, check = _draw(rng, TRUTH_M, TRUTH_M + step * np.eye(4)[0])
    r = check_drift(in_force, check)
    assert r.drifted == ("L",)
    u = update_from_check(in_force, check, r)
    std = u.estimate.std_m()
    # L decided by the check alone (its std no smaller than the check's marginal given the rest); the others keep
    # the calibration in force's knowledge (std no larger than its own)
    assert std[0] <= np.sqrt(CHECK_COV[0, 0]) + 1e-12
    assert std[0] > 2 * np.sqrt(IN_FORCE_COV[0, 0])
    assert np.all(std[1:] <= np.sqrt(np.diag(IN_FORCE_COV))[1:] + 1e-12)


def test_no_update_when_it_holds_or_the_check_did_not_converge():
    rng = np.random.default_rng(6)
    in_force, check = _draw(rng, TRUTH_M, TRUTH_M)
    r = check_drift(in_force, check)
    assert r.verdict == "holds"
    assert not update_from_check(in_force, check, r).accepted
    stalled = CombinationEstimate(check.value_m + 0.01, CHECK_COV, converged=False)
    r = check_drift(in_force, stalled)
    assert r.verdict == "inconclusive"
    assert "did not converge" in " ".join(r.reasons)
    u = update_from_check(in_force, stalled, r)
    assert not u.accepted and "did not converge" in u.reason


def test_an_update_that_contradicts_its_prior_is_refused():
    # one combination flagged, but the data also pull a strongly correlated one the test found unchanged
    cov = np.diag([1e-10, 1e-10, 1e-10, 1e-10])
    cov[0, 1] = cov[1, 0] = 0.99e-10
    in_force = CombinationEstimate(TRUTH_M, cov * 0.01)
    check = CombinationEstimate(TRUTH_M + np.array([3e-4, 0.0, 0.0, 0.0]), cov)
    r = check_drift(in_force, check)
    assert r.drifted == ("L",)
    u = update_from_check(in_force, check, r)
    assert u.accepted  # H-D is held by its prior, L re-estimated: consistent
    forced = type(r)(**{**r.__dict__, "drifted": ("H-D",), "verdict": "drifted"})
    refused = update_from_check(in_force, check, forced)
    assert not refused.accepted and "contradict" in refused.reason and "L" in refused.reason


def test_a_combination_the_check_cannot_pin_makes_it_inconclusive():
    rng = np.random.default_rng(7)
    in_force, check = _draw(rng, TRUTH_M, TRUTH_M)
    loose = check.covariance_m2.copy()
    loose[3, 3] = (5e-3) ** 2
    r = check_drift(in_force, CombinationEstimate(check.value_m, loose))
    assert r.verdict == "inconclusive"
    assert "S-(q04-q03)/2" in r.reasons[0]


def test_bad_input_names_the_field():
    good = CombinationEstimate(TRUTH_M, CHECK_COV)
    with pytest.raises(InputError, match="check"):
        check_drift(good, CombinationEstimate(np.array([np.nan, 0, 0, 0]), CHECK_COV))
    with pytest.raises(InputError, match="alpha"):
        DriftSettings(alpha=0.7)


def _document(values_m, cov):
    from calib.identify.export import COMPLETION_RULES, CalibrationDocument, Completion
    from calib.model.parameters import NOMINAL, I4Parameters

    combos = dict(zip(COMBINATION_NAMES, map(float, values_m), strict=True))
    p = I4Parameters.from_combinations(combos, NOMINAL)
    return CalibrationDocument(
        method="combined",
        method_choice="test",
        software_version="test",
        run="r" * 32,
        seven=p.seven(),
        seven_std=dict.fromkeys(p.seven()),
        identified=["q02", "q04", "D", "L"],
        fixed_at_nominal=["H", "S", "q03"],
        completion=Completion(rule="combinations+nominal", text=COMPLETION_RULES["combinations+nominal"]),
        T_per_rad=p.T_per_rad,
        combinations=combos,
        combinations_std=dict(zip(COMBINATION_NAMES, np.sqrt(np.diag(IN_FORCE_COV)).tolist(), strict=True)),
        covariance=None if cov is None else cov.tolist(),
        nominal=NOMINAL.as_dict(),
        nominal_combinations=NOMINAL.combinations(),
    )


def test_the_update_document_reproduces_its_combinations_and_keeps_the_free_offsets():
    from calib.check.drift import in_force_estimate, updated_calibration
    from calib.identify.export import REPRODUCE_TOL_M, load_calibration

    doc = _document(TRUTH_M, IN_FORCE_COV)
    prior = in_force_estimate(doc)
    assert np.array_equal(prior.value_m, TRUTH_M) and np.array_equal(prior.covariance_m2, IN_FORCE_COV)
    step = 4.0 * np.sqrt(CHECK_COV[0, 0] + IN_FORCE_COV[0, 0])
    check = CombinationEstimate(TRUTH_M + step * np.eye(4)[0], CHECK_COV)
    r = check_drift(prior, check)
    u = update_from_check(prior, check, r)
    new = load_calibration(updated_calibration(doc, u, software_version="x").model_dump(mode="json"))
    got = new.to_parameters().combinations()
    assert all(abs(got[k] - new.combinations[k]) < REPRODUCE_TOL_M for k in COMBINATION_NAMES)
    assert np.allclose([new.combinations[k] for k in COMBINATION_NAMES], u.estimate.value_m, rtol=0, atol=1e-15)
    assert (new.seven["H"], new.seven["S"], new.seven["q03"]) == (doc.seven["H"], doc.seven["S"], doc.seven["q03"])
    assert new.completion.rule == "combinations+in-force" and "L" in new.method_choice
    assert new.source.model_extra["updated_from"]["run"] == "r" * 32
    refused = update_from_check(prior, CombinationEstimate(TRUTH_M, CHECK_COV), check_drift(prior, prior))
    with pytest.raises(InputError, match="refused"):
        updated_calibration(doc, refused, software_version="x")


def test_a_calibration_without_covariance_cannot_be_checked():
    from calib.check.drift import in_force_estimate

    with pytest.raises(InputError, match="covariance"):
        in_force_estimate(_document(TRUTH_M, None))
