"""Whether a least-squares fit that ran out of evaluations stands at its minimum anyway.

Levenberg-Marquardt with tolerances near machine precision (the combined fit asks for 1e-14, so that noise-free data
give back the truth to 1e-8 m) can reach the minimum and then keep taking steps that lower the sum of squares in its
eighth digit (the residuals carry rounding-level noise from the inner solves), until ``max_nfev`` stops it
(``status`` 0), possibly hundreds of evaluations after it reached the minimum. Failing such a fit would throw away a
converged fit, and with it the camera's refinement by the rods and every method's second pass. What decides is the
step that is left: one Gauss-Newton step from the stopping point would lower the sum of squares by ``||J dx||^2``,
at a fit scipy calls converged a share of the sum of order 1e-8 to 1e-7 (the finite-difference Jacobian sees the
same rounding noise), and no more where such a fit stops at its minimum.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from calib.errors import ConvergenceError
from calib.numerics.numdiff import central_jacobian

#: a Gauss-Newton step that would lower the sum of squares by at most this share of it (and of 1) is no step: with
#: whitened residuals a decrease d of the chi-square is a move of sqrt(d) standard deviations, at chi-squares of tens
#: to hundreds (the combined fit's) a few hundredths of a standard deviation at most
STATIONARY_SHARE = 1e-6


def gauss_newton_decrease(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray) -> float:
    """The decrease of the sum of squares one Gauss-Newton step from ``x`` would give, ``||J dx||^2``.

    Parameters
    ----------
    fun : callable
        The residuals, shape (n,) -> shape (m,).
    x : ndarray, shape (n,)
        Where the fit stopped.

    Returns
    -------
    float
        In the residuals' units squared (the sum of squares, not scipy's half of it).
    """
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(fun(x), dtype=np.float64)
    J = central_jacobian(fun, x)
    step = np.linalg.lstsq(J, -r, rcond=None)[0]
    return float(np.sum((J @ step) ** 2))


def check_converged(sol: Any, fun: Callable[[np.ndarray], np.ndarray], what: str) -> dict[str, Any] | None:
    """Raise :class:`ConvergenceError` unless ``sol`` (scipy's ``least_squares``) is a converged fit of ``fun``.

    Parameters
    ----------
    sol : scipy.optimize.OptimizeResult
        ``status`` > 0: converged by scipy's tolerances. ``status`` 0 (``max_nfev`` reached): converged when one
        Gauss-Newton step would lower the sum of squares by at most :data:`STATIONARY_SHARE` of it (and of 1).
    fun : callable
        The residuals the fit minimised.
    what : str
        Names the fit in the error.

    Returns
    -------
    dict or None
        None when scipy's tolerances were met; else a note for the method's diagnostics: ``stage``, ``nfev``,
        ``sum_of_squares`` and ``gauss_newton_decrease``.
    """
    if not np.all(np.isfinite(sol.x)):
        raise ConvergenceError(f"{what} did not converge: non-finite parameters")
    if sol.status > 0:
        return None
    if sol.status == 0:
        ss = 2.0 * float(sol.cost)
        dec = gauss_newton_decrease(fun, sol.x)
        if np.isfinite(dec) and dec <= STATIONARY_SHARE * max(ss, 1.0):
            return {"stage": what, "nfev": int(sol.nfev), "sum_of_squares": ss, "gauss_newton_decrease": dec}
        raise ConvergenceError(
            f"{what} did not converge: {sol.message} (one more Gauss-Newton step would lower the sum of squares "
            f"{ss:.6g} by {dec:.3g})"
        )
    raise ConvergenceError(f"{what} did not converge: {sol.message}")
