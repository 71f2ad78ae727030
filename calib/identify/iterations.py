"""Per-iteration reports of the methods' least-squares fits (live progress of a calibration).

A report is a dict ``{"stage": str, "iteration": int, "cost": float}``: ``stage`` names the fit within the method
(a method may solve several problems in turn), ``iteration`` counts the accepted steps of that fit from 0 (the
starting point) and ``cost`` is scipy's ``0.5 * sum(residuals ** 2)`` at that point (units of the residuals,
squared). Reporting never changes what the fit computes.

``scipy.optimize.least_squares`` calls a ``callback`` after every iteration of ``trf`` and ``dogbox``
(:func:`trf_callback`) but not for ``lm`` (MINPACK). For ``lm``, :func:`traced` wraps the residual function
instead and recognises the iteration boundaries from the calls: MINPACK asks for the Jacobian at every accepted
point, and scipy evaluates it by forward differences, whose first call moves only ``x[0]``, by
``sqrt(eps) * max(1, |x[0]|)``, away from that point.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

IterationCallback = Callable[[dict[str, Any]], None]

#: Largest relative move of ``x[0]`` still taken for a forward-difference step (scipy uses ``sqrt(eps)``).
_FD_REL_STEP = 1e-6


def trf_callback(on_iteration: IterationCallback | None, stage: str) -> Callable[..., None] | None:
    """A ``least_squares(..., method="trf", callback=...)`` callback forwarding each iteration, or None.

    Parameters
    ----------
    on_iteration : callable or None
        Receives ``{"stage", "iteration", "cost"}``.
    stage : str
        Name of this fit within the method.

    Returns
    -------
    callable or None
        The callback, None when ``on_iteration`` is None.
    """
    if on_iteration is None:
        return None

    def callback(intermediate_result: Any) -> None:  # the name tells scipy to pass the OptimizeResult
        on_iteration(
            {"stage": stage, "iteration": int(intermediate_result.nit), "cost": float(intermediate_result.cost)}
        )

    return callback


def _is_difference_step(prev: np.ndarray, x: np.ndarray) -> bool:
    """True when ``x`` is ``prev`` with only ``x[0]`` moved by a finite-difference step."""
    if prev.shape != x.shape or x.size == 0:
        return False
    d = x - prev
    if d[0] == 0.0 or np.any(d[1:] != 0.0):
        return False
    return bool(abs(d[0]) <= _FD_REL_STEP * max(1.0, abs(float(prev[0]))))


def traced(
    fun: Callable[[np.ndarray], np.ndarray], on_iteration: IterationCallback | None, stage: str
) -> Callable[[np.ndarray], np.ndarray]:
    """Wrap the residual function of an ``lm`` fit so that each accepted point is reported.

    Parameters
    ----------
    fun : callable
        Residuals, shape (n,) -> (m,); called exactly as before, its values returned unchanged.
    on_iteration : callable or None
        Receives ``{"stage", "iteration", "cost"}``; None returns ``fun`` itself.
    stage : str
        Name of this fit within the method.

    Returns
    -------
    callable
        The residual function to give ``least_squares``.
    """
    if on_iteration is None:
        return fun
    prev_x: np.ndarray | None = None
    prev_cost = 0.0
    last_reported = np.inf
    iteration = 0

    def wrapped(x: np.ndarray) -> np.ndarray:
        nonlocal prev_x, prev_cost, last_reported, iteration
        r = fun(x)
        xc = np.array(x, dtype=np.float64, copy=True).ravel()
        # an accepted step lowers the cost: a higher one is a trial step that only looks like a difference step
        # (one parameter, converged)
        if prev_x is not None and _is_difference_step(prev_x, xc) and prev_cost <= last_reported:
            on_iteration({"stage": stage, "iteration": iteration, "cost": prev_cost})
            last_reported = prev_cost
            iteration += 1
        rr = np.asarray(r, dtype=np.float64).ravel()
        prev_x, prev_cost = xc, 0.5 * float(rr @ rr)
        return r

    return wrapped


def traced_jac(
    fun: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], np.ndarray],
    on_iteration: IterationCallback | None,
    stage: str,
) -> tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]:
    """:func:`traced` for an ``lm`` fit given its Jacobian: each Jacobian call is an accepted point.

    Parameters
    ----------
    fun : callable
        Residuals, shape (n,) -> (m,).
    jac : callable
        Their Jacobian, shape (n,) -> (m, n).
    on_iteration : callable or None
        Receives ``{"stage", "iteration", "cost"}``; None returns ``fun`` and ``jac`` themselves.
    stage : str
        Name of this fit within the method.

    Returns
    -------
    (callable, callable)
        The residual function and the Jacobian to give ``least_squares``.
    """
    if on_iteration is None:
        return fun, jac
    last: dict[str, Any] = {"x": None, "cost": 0.0}
    iteration = 0

    def wrapped_fun(x: np.ndarray) -> np.ndarray:
        r = fun(x)
        rr = np.asarray(r, dtype=np.float64).ravel()
        last["x"], last["cost"] = np.array(x, dtype=np.float64, copy=True), 0.5 * float(rr @ rr)
        return r

    def wrapped_jac(x: np.ndarray) -> np.ndarray:
        nonlocal iteration
        if last["x"] is None or not np.array_equal(last["x"], x):
            wrapped_fun(x)
        on_iteration({"stage": stage, "iteration": iteration, "cost": last["cost"]})
        iteration += 1
        return jac(x)

    return wrapped_fun, wrapped_jac
