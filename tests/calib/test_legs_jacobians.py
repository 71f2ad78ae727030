"""The legs method's analytic Jacobians (steps 2 and 3-4) against central differences, and the iteration reports
of a fit that is given its Jacobian (no difference steps to recognise the iterations by)."""

import numpy as np

from calib.identify.iterations import traced_jac
from calib.identify.legs.steps import LegsModel, _step2_gram, _step2_gram_jacobian
from calib.model.parameters import NOMINAL
from calib.numerics.numdiff import central_jacobian


def test_step2_jacobian_is_the_derivative_of_the_gram_entries():
    x = np.array([NOMINAL.q02, NOMINAL.q03, NOMINAL.q04, NOMINAL.H]) + np.array([0.003, -0.002, 0.001, 0.004])
    num = central_jacobian(_step2_gram, x, 1e-6)
    np.testing.assert_allclose(_step2_gram_jacobian(x), num, rtol=0, atol=1e-9 * np.abs(num).max())


def test_steps34_jacobian_is_the_derivative_of_the_residuals_with_missing_legs():
    rng = np.random.default_rng(7)
    n = 12
    q_fit = rng.uniform(-0.05, 0.05, (n, 4))
    U = rng.normal(size=(n, 4, 3))
    U /= np.linalg.norm(U, axis=2, keepdims=True)
    has_leg = rng.random((n, 4)) > 0.2
    pipe = LegsModel(np.zeros(4), q_fit, np.full((n, 4, 3), np.nan), has_leg, np.zeros((n, 4, 3, 3)), NOMINAL)
    Aq = rng.normal(scale=0.2, size=(n, 4, 3))
    y = np.array([0.0, 1.0, 0.0])
    theta = np.array([NOMINAL.L, NOMINAL.S, NOMINAL.D])
    J = pipe.jacobian(theta, Aq, U, y)
    num = central_jacobian(lambda t: pipe.residuals(t, Aq, U, y).ravel(), theta, 1e-7).reshape(n, 4, 3)
    np.testing.assert_allclose(J, num, rtol=0, atol=1e-7)
    assert np.all(J[~pipe.mask] == 0.0) and (~pipe.mask).any()  # a missing equation has no derivative
    pipe.W = rng.normal(size=(n, 4, 4))
    numw = central_jacobian(lambda t: pipe.whitened(t, Aq, U, y).ravel(), theta, 1e-7).reshape(n, 4, 3)
    np.testing.assert_allclose(pipe.whitened_jacobian(theta, Aq, U, y), numw, rtol=0, atol=1e-6)


def test_traced_jac_reports_every_jacobian_point_with_its_cost():
    from scipy.optimize import least_squares

    target = np.array([1.0, 2.0, 3.0])

    def fun(x):
        return np.array([x[0] ** 2 - target[0], x[0] * x[1] - target[1], x[1] + x[0] - target[2]])

    def jac(x):
        return np.array([[2 * x[0], 0.0], [x[1], x[0]], [1.0, 1.0]])

    reports = []
    f, j = traced_jac(fun, jac, reports.append, "toy")
    sol = least_squares(f, np.array([3.0, -1.0]), jac=j, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert [r["iteration"] for r in reports] == list(range(len(reports))) and len(reports) >= 3
    assert {r["stage"] for r in reports} == {"toy"}
    assert reports[0]["cost"] == 0.5 * float(np.sum(fun(np.array([3.0, -1.0])) ** 2))
    assert reports[-1]["cost"] <= reports[0]["cost"] and np.isclose(reports[-1]["cost"], sol.cost, rtol=1e-6)
    assert traced_jac(fun, jac, None, "toy") == (fun, jac)
