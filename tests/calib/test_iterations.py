"""Per-iteration reports of the fits: every method reports its iterations, and reporting changes nothing."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from calib.identify.iterations import traced, trf_callback
from calib.identify.pipeline import calibrate


def _rosenbrock(x: np.ndarray) -> np.ndarray:
    return np.array([x[0] - 1.0, 10.0 * (x[1] - x[0] ** 2), 0.1 * x[0] * x[1]])


def test_lm_reports_each_accepted_point_without_changing_the_fit():
    kw = dict(method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    plain = least_squares(_rosenbrock, [-1.2, 1.0], **kw)
    reports: list[dict] = []
    sol = least_squares(traced(_rosenbrock, reports.append, "r"), [-1.2, 1.0], **kw)
    np.testing.assert_array_equal(sol.x, plain.x)
    assert len(reports) >= 5
    assert [r["iteration"] for r in reports] == list(range(len(reports)))
    assert reports[0]["cost"] == pytest.approx(0.5 * float(np.sum(_rosenbrock(np.array([-1.2, 1.0])) ** 2)))
    costs = np.array([r["cost"] for r in reports])
    assert np.all(np.diff(costs) <= 0), costs  # accepted steps only
    assert costs[-1] == pytest.approx(sol.cost, rel=1e-9)
    assert len(reports) <= sol.nfev  # never more than one report per MINPACK evaluation


def test_lm_one_parameter_reports_are_monotone():
    reports: list[dict] = []
    sol = least_squares(
        traced(lambda x: np.array([x[0] ** 2 - 2.0, x[0] - 1.4]), reports.append, "1d"),
        [1.0],
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    costs = [r["cost"] for r in reports]
    assert len(costs) >= 3 and costs == sorted(costs, reverse=True)
    assert costs[-1] == pytest.approx(sol.cost, rel=1e-9)


def test_trf_callback_reports_scipy_iterations():
    reports: list[dict] = []
    sol = least_squares(_rosenbrock, [-1.2, 1.0], method="trf", callback=trf_callback(reports.append, "t"))
    assert [r["iteration"] for r in reports] == list(range(1, sol.nfev + 1))[: len(reports)]
    assert reports[-1]["cost"] == pytest.approx(sol.cost)
    assert trf_callback(None, "t") is None and traced(_rosenbrock, None, "r") is _rosenbrock


def test_calibrate_reports_iterations_of_every_method_and_same_result(noisy_obs):
    obs, _ = noisy_obs
    methods = ["combined", "end-effector", "legs"]
    plain = calibrate(obs, methods)
    reports: list[dict] = []
    traced_doc = calibrate(obs, methods, on_iteration=reports.append)
    for m in methods:
        assert traced_doc["methods"][m]["parameters"] == plain["methods"][m]["parameters"], m
        mine = [r for r in reports if r["method"] == m]
        assert len(mine) >= 2, m
        assert all(np.isfinite(r["cost"]) and r["cost"] >= 0 and isinstance(r["iteration"], int) for r in mine)
    stages = {(r["method"], r["stage"]) for r in reports}
    assert ("combined", "eq8") in stages and ("legs", "step 2") in stages and ("legs", "steps 3-4") in stages
    assert any(m == "end-effector" and s.startswith("pass-1") for m, s in stages)
    # within a stage of an lm fit the cost never rises
    for m, s in stages:
        if m != "end-effector":
            c = [r["cost"] for r in reports if (r["method"], r["stage"]) == (m, s)]
            assert c == sorted(c, reverse=True), (m, s)
