"""A fit that runs out of evaluations at its minimum is converged; one that runs out before it is not.

The combined fit asks Levenberg-Marquardt for 1e-14 tolerances. On a rendered trial of the image twin (seed 1,
designed 12-pose plan, trial 35 of ``i4cal bench design``, one BLAS thread per worker) its joint stage reached its
minimum within 80 evaluations and crawled on, lowering the sum of squares in its eighth digit, until ``max_nfev``
stopped it: the fit was thrown away as "did not converge", and with it the camera's refinement by the rods and every
method's second pass (legs L 3.1 mm off instead of 0.4). Here scipy's stop is imitated on the geometric twin: the
real fit, reported as stopped by ``max_nfev`` where it converged (accepted), or stopped early (refused).
"""

import numpy as np
import pytest
from scipy.optimize import least_squares as scipy_least_squares

import calib.identify.combined as combined_module
from calib.errors import ConvergenceError
from calib.formats.observations import Observations
from calib.identify import calibrate_combined
from calib.identify.stationary import STATIONARY_SHARE, check_converged, gauss_newton_decrease
from drivers.sim.twin import GeometricTwin

RNG = np.random.default_rng(7)
A = RNG.standard_normal((40, 5))
B = RNG.standard_normal(40)
X_BEST = np.linalg.lstsq(A, B, rcond=None)[0]


def linear(x: np.ndarray) -> np.ndarray:
    return A @ x - B


def test_gauss_newton_decrease_is_what_the_step_left_buys_on_a_linear_problem():
    assert gauss_newton_decrease(linear, X_BEST) == pytest.approx(0.0, abs=1e-9)
    dx = np.array([1e-3, -2e-3, 0.0, 5e-4, 1e-3])
    # linear residuals: from X_BEST + dx the step goes back to X_BEST, lowering the sum of squares by |A dx|^2
    assert gauss_newton_decrease(linear, X_BEST + dx) == pytest.approx(float(np.sum((A @ dx) ** 2)), rel=1e-6)


def test_check_converged_accepts_a_stop_at_the_minimum_and_refuses_one_before_it():
    at_min = scipy_least_squares(linear, np.zeros(5), method="lm")
    assert at_min.status > 0 and check_converged(at_min, linear, "fit") is None
    early = scipy_least_squares(linear, np.full(5, 3.0), method="trf", max_nfev=1)
    assert early.status == 0
    with pytest.raises(ConvergenceError, match="fit did not converge.*Gauss-Newton step would lower"):
        check_converged(early, linear, "fit")
    at_min.status = 0  # as if max_nfev had stopped it there
    note = check_converged(at_min, linear, "fit")
    assert note is not None and note["gauss_newton_decrease"] <= STATIONARY_SHARE * max(note["sum_of_squares"], 1.0)
    at_min.x = np.full(5, np.nan)
    with pytest.raises(ConvergenceError, match="non-finite"):
        check_converged(at_min, linear, "fit")


@pytest.fixture(scope="module")
def twin_observations(paper_plan) -> Observations:
    return Observations.from_dict(GeometricTwin().observations(plan=paper_plan, seed=3))


def _patched(monkeypatch, change):
    """The combined fit's least squares, its joint stages' results passed through ``change``; returns the calls'
    ``max_nfev``."""
    calls = []

    def wrapper(fun, x0, **kw):
        calls.append(kw.get("max_nfev"))
        if kw.get("max_nfev") == 500 and calls.count(500) > 1:  # the joint stages (the first 500 is eq. 8's)
            return change(fun, x0, kw)
        return scipy_least_squares(fun, x0, **kw)

    monkeypatch.setattr(combined_module, "least_squares", wrapper)
    return calls


def test_a_joint_fit_stopped_by_max_nfev_at_its_minimum_is_kept(monkeypatch, twin_observations):
    reference = calibrate_combined(twin_observations)

    def at_limit(fun, x0, kw):
        sol = scipy_least_squares(fun, x0, **kw)
        sol.status, sol.message = 0, "The maximum number of function evaluations is exceeded."
        return sol

    calls = _patched(monkeypatch, at_limit)
    result = calibrate_combined(twin_observations)
    assert calls.count(500) >= 2, "the joint stage did not run"
    assert reference.diagnostics["stopped_stationary"] == []
    notes = result.diagnostics["stopped_stationary"]
    assert notes and all(n["stage"] == "combined joint fit" for n in notes)
    for name, value in reference.combinations.items():  # the same fit: the joint stage's result kept as it was
        assert result.combinations[name] == value
        assert result.combinations_std[name] == reference.combinations_std[name]


def test_a_joint_fit_stopped_before_its_minimum_still_fails(monkeypatch, twin_observations):
    def early(fun, x0, kw):
        return scipy_least_squares(fun, x0 + 1e-3, **{**kw, "max_nfev": 2})

    _patched(monkeypatch, early)
    with pytest.raises(ConvergenceError, match="combined joint fit did not converge"):
        calibrate_combined(twin_observations)
