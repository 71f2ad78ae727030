"""How a plan's predicted std falls with its fit-pose count: the level it settles to and the count a target needs.

Each fit pose adds about the same information, and the rest of a plan (the sweeps, the lock phases, the camera's
calibration) a fixed part, so a combination's predicted variance over the count ``N`` of fit poses drawn from one
candidate set follows ``var(N) = floor + slope / N``: ``floor`` the part no number of such poses reduces, ``slope / N``
the part they average. Two predictions, at ``n_lo`` and ``n_hi`` poses, give both; between them, the trend gives a
count's std to within a few per cent of the design's own prediction at that count. Units: metres (std), m^2
(variance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CountTrend", "fit_count_trend"]


def _std_array(std: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for m, v in std.items():
        a = np.asarray(v, dtype=np.float64)
        if a.ndim != 1 or a.size == 0:
            raise ValueError(f"{m}: the std per combination must have shape (k,), got {a.shape}")
        out[m] = a
    return out


@dataclass(frozen=True)
class CountTrend:
    """``var(N) = floor_var + slope / N`` per method and combination.

    Attributes
    ----------
    n : tuple of int
        The two counts the trend was fitted from.
    floor_var : dict of str to ndarray, shape (k,)
        Per method, the variance no count of these fit poses reduces, m^2 (>= 0).
    slope : dict of str to ndarray, shape (k,)
        Per method, the part the fit poses average, m^2 times poses (>= 0).
    """

    n: tuple[int, int]
    floor_var: dict[str, np.ndarray]
    slope: dict[str, np.ndarray]

    def floor_std(self) -> dict[str, np.ndarray]:
        """Per method (k,): the std the combinations settle to with ever more such fit poses, m."""
        return {m: np.sqrt(v) for m, v in self.floor_var.items()}

    def std_at(self, n: int) -> dict[str, np.ndarray]:
        """Per method (k,): the std the trend gives ``n`` fit poses, m.

        Parameters
        ----------
        n : int
            Count of fit poses, >= 1.

        Returns
        -------
        dict of str to ndarray, shape (k,)
            Per method, the std per combination, metres.

        Raises
        ------
        ValueError
            If ``n < 1``.
        """
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        return {m: np.sqrt(self.floor_var[m] + self.slope[m] / n) for m in self.floor_var}

    def needed(self, targets: dict[str, np.ndarray]) -> int | None:
        """The fewest fit poses at which the trend puts every combination of every method in ``targets`` (m, (k,)
        each) at or under its target; None when a combination's floor is at or over its target (no count reaches
        it).

        Parameters
        ----------
        targets : dict of str to ndarray, shape (k,)
            Per method, the target std per combination, metres.

        Returns
        -------
        int or None
            The count of fit poses, or None when no count reaches a target.
        """
        n = 1
        for m, t in targets.items():
            t2 = np.asarray(t, dtype=np.float64) ** 2
            floor, slope = self.floor_var[m], self.slope[m]
            if np.any(floor >= t2):
                return None
            need = np.where(slope > 0, slope / (t2 - floor), 1.0)
            n = max(n, math.ceil(float(np.max(need)) * (1 - 1e-12)))
        return n


def fit_count_trend(n_lo: int, std_lo: dict[str, np.ndarray], n_hi: int, std_hi: dict[str, np.ndarray]) -> CountTrend:
    """The trend through the predicted std (m, per method (k,)) at ``n_lo`` and ``n_hi`` fit poses (n_lo < n_hi).

    A combination whose variance does not fall from ``n_lo`` to ``n_hi`` gets its variance at ``n_hi`` as its
    floor and no slope; a variance that falls faster than ``1 / N`` (the larger count also bought better poses)
    gets a floor of 0 and the slope through the ``n_hi`` point.

    Parameters
    ----------
    n_lo, n_hi : int
        The two counts of fit poses, ``1 <= n_lo < n_hi``.
    std_lo, std_hi : dict of str to ndarray, shape (k,)
        Per method (the same methods in both), the predicted std per combination at each count, metres.

    Returns
    -------
    CountTrend
        Floor (m^2) and slope (m^2 times poses) per method and combination.

    Raises
    ------
    ValueError
        Bad counts, different methods, or shapes that differ.
    """
    if not (1 <= n_lo < n_hi):
        raise ValueError(f"need 1 <= n_lo < n_hi, got {n_lo}, {n_hi}")
    lo, hi = _std_array(std_lo), _std_array(std_hi)
    if set(lo) != set(hi):
        raise ValueError(f"the two predictions name different methods: {sorted(lo)} and {sorted(hi)}")
    floor, slope = {}, {}
    for m in hi:
        if lo[m].shape != hi[m].shape:
            raise ValueError(f"{m}: std shapes differ, {lo[m].shape} and {hi[m].shape}")
        v_lo, v_hi = lo[m] ** 2, hi[m] ** 2
        b = np.maximum((v_lo - v_hi) / (1.0 / n_lo - 1.0 / n_hi), 0.0)
        a = v_hi - b / n_hi
        neg = a < 0  # steeper than 1/N: through the n_hi point with no floor
        b = np.where(neg, v_hi * n_hi, b)
        floor[m] = np.where(neg, 0.0, a)
        slope[m] = b
    return CountTrend((int(n_lo), int(n_hi)), floor, slope)
