"""Robust chi-square gating shared by the identification methods.

A residual block ``k`` with ``dof_k`` degrees of freedom and squared whitened norm ``d2_k`` is an outlier when
``d2_k > chi2.ppf(GATE_QUANTILE, dof_k) * s``, where ``s`` is the robust noise factor: the median of
``d2_k / chi2.median(dof_k)`` over the blocks (1 when the assumed noise is right, whatever a few outliers do).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammaincinv

#: Quantile of the chi-square gate: 1 good block in 1000 is rejected.
GATE_QUANTILE = 0.999


def _chi2_ppf(q: ArrayLike, dof: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.chi2.ppf(q, dof)``, the same numbers (its formula, ``2 gammaincinv(dof / 2, q)``, with its
    NaN outside ``dof > 0``, ``0 <= q <= 1``), without importing ``scipy.stats``: ~1 s of CPU in every process that
    imports the methods (the CLI, the service's fit and extraction processes, the benchmarks' workers)."""
    qa, da = np.asarray(q, dtype=np.float64), np.asarray(dof, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        x = 2 * gammaincinv(da / 2, qa)
    return np.asarray(np.where((da > 0) & (qa >= 0) & (qa <= 1), x, np.nan), dtype=np.float64)


def chi2_gate(dof: ArrayLike, quantile: float = GATE_QUANTILE) -> NDArray[np.float64]:
    """The gate ``chi2.ppf(quantile, dof)``, shape of ``dof`` (an unscaled threshold on a squared norm).

    Parameters
    ----------
    dof : array_like, shape (N,) or scalar
        Degrees of freedom of each residual block.
    quantile : float, optional
        Probability a good block falls below the gate (dimensionless, :data:`GATE_QUANTILE` by default).

    Returns
    -------
    ndarray, shape of ``dof``
        The gate on the squared whitened norm (dimensionless; NaN where ``dof <= 0``).
    """
    return _chi2_ppf(quantile, dof)


def robust_chi2_scale(d2: ArrayLike, dof: ArrayLike) -> float:
    """Median of ``d2 / chi2.median(dof)``: the noise factor (squared) the blocks show, robust to outliers.

    Parameters
    ----------
    d2 : array_like, shape (N,)
        Squared whitened residual norms (dimensionless).
    dof : array_like, shape (N,) or scalar
        Their degrees of freedom.

    Returns
    -------
    float
        The squared noise factor ``s`` (dimensionless; 1 when the assumed noise is right).

    Raises
    ------
    ValueError
        If ``d2`` is empty.
    """
    d2a = np.asarray(d2, dtype=np.float64)
    if d2a.size == 0:
        raise ValueError("robust_chi2_scale needs at least one residual block, got none")
    return float(np.median(d2a / _chi2_ppf(0.5, dof)))


def chi2_outliers(d2: ArrayLike, dof: ArrayLike, scale: float | None = None) -> NDArray[np.bool_]:
    """Blocks (bool, shape of ``d2``) beyond the gate at the noise factor ``scale`` (default: the robust one).

    Parameters
    ----------
    d2 : array_like, shape (N,)
        Squared whitened residual norms (dimensionless).
    dof : array_like, shape (N,) or scalar
        Their degrees of freedom.
    scale : float, optional
        Squared noise factor (dimensionless); :func:`robust_chi2_scale` of the blocks by default.

    Returns
    -------
    ndarray of bool, shape (N,)
        True for an outlier block.
    """
    d2a = np.asarray(d2, dtype=np.float64)
    s = robust_chi2_scale(d2a, dof) if scale is None else scale
    return np.asarray(d2a > chi2_gate(dof) * s)
