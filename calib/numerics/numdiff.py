"""Central finite-difference Jacobians of vector functions."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def central_jacobian(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """``d fun / d x`` by central differences.

    Parameters
    ----------
    fun : callable
        Maps shape (n,) to shape (m,).
    x : ndarray, shape (n,)
    h : float
        Step, in the units of ``x``.

    Returns
    -------
    ndarray, shape (m, n)
    """
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((np.asarray(fun(x + e)) - np.asarray(fun(x - e))) / (2 * h))
    return np.column_stack(cols)
