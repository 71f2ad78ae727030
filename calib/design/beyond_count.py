"""Past the count search's ``n_max`` fit poses: the most poses allowed, then the fewest of them meeting the target.

The design's count search (:func:`.optimize.design_plan`) tries up to ``n_max`` fit poses (60). When that many miss
the target, :func:`past_the_count_search` designs the most allowed (``most``: 200, and within the time allowed) and,
when those meet it, brackets the fewest that do, each count guessed by the trend of the predicted std over the count
(:mod:`.count_trend`); when they miss it too, it says the level the worst combination settles to by that trend.
Units: metres, seconds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

import numpy as np

from calib.design.count_trend import CountTrend, fit_count_trend
from calib.design.predict import Prediction, ratio_to_target
from calib.formats.plan import Plan
from calib.model.parameters import COMBINATION_NAMES

__all__ = ["TREND_ROUNDS", "DesignedCount", "count_std", "past_the_count_search", "trend_summary"]

#: counts designed between the count search's ``n_max`` and the most fit poses, bracketing the fewest meeting a target
TREND_ROUNDS = 4


def count_std(std: dict[str, dict[str, float]], methods: Iterable[str]) -> dict[str, np.ndarray]:
    """Per method of ``methods``, its std per combination (4,) from a prediction's ``std`` (method -> combination ->
    m), m (inf where it has none).

    Parameters
    ----------
    std : dict
        A prediction's ``std``: method -> combination name -> metres.
    methods : iterable of str
        The methods wanted.

    Returns
    -------
    dict of str to ndarray, shape (4,)
        Per method, the std in :data:`~calib.model.parameters.COMBINATION_NAMES` order, metres (inf where missing).
    """
    return {
        m: np.array([(std.get(m) or {}).get(c, np.inf) for c in COMBINATION_NAMES], dtype=np.float64) for m in methods
    }


#: what a method's predicted std keeps however many fit poses: the parts of the plan fit poses do not average
_FLOOR_SOURCES = {"combined": "the sweeps and the camera calibration", "legs": "the lock phases' joints"}


class DesignedCount(NamedTuple):
    """A designed count of fit poses: the count, the chosen candidates, the plan, its motion and its prediction."""

    k: int
    sel: np.ndarray
    plan: Plan
    mt: dict[str, Any]
    pred: Prediction


def past_the_count_search(
    cur: DesignedCount,
    design_at: Callable[[int], DesignedCount],
    worst_of: Callable[[Prediction], float],
    targets: dict[str, np.ndarray],
    max_time_s: float | None,
    most: int,
) -> tuple[DesignedCount, dict[str, Any], str, str] | None:
    """Past the count search's ``n_max`` (``cur``, missing the target): the most fit poses allowed (``most``, and
    within ``max_time_s``); when they meet the target, the fewest between that do, bracketed, each count guessed by the
    trend of the predicted std over the count (:mod:`.count_trend`) through the bracket's ends. Returns the chosen
    count, the trend's summary (``count_trend``), why the target is missed ("" when met) and a note; None when no
    more poses are allowed.

    Parameters
    ----------
    cur : DesignedCount
        The design at the count search's ``n_max``, missing the target.
    design_at : callable
        ``design_at(k)``: the design with ``k`` fit poses.
    worst_of : callable
        ``worst_of(prediction)``: the largest ratio of a predicted std to its target (dimensionless; <= 1 meets it).
    targets : dict of str to ndarray, shape (4,)
        Per method, the target std per combination, metres.
    max_time_s : float or None
        Motion time allowed, seconds (None: no limit).
    most : int
        The most fit poses the design takes.

    Returns
    -------
    tuple of (DesignedCount, dict, str, str) or None
        The chosen design, :func:`trend_summary`, why the target is missed ("" when met) and a note ("" when
        none); None when no more poses than ``cur``'s are allowed.
    """

    def most_within(c: DesignedCount) -> int:
        """The most poses within the time at ``c``'s motion time per pose (a longer tour takes less per pose)."""
        per_pose_s = c.mt["per_phase_s"].get("poses", 0.0) / c.k
        if max_time_s is None or per_pose_s <= 0:
            return most
        return min(most, c.k + int((max_time_s - c.mt["total_s"]) / per_pose_s))

    top: DesignedCount | None = None
    n_try = most_within(cur)
    for _try in range(3):
        if n_try <= (top or cur).k:
            break
        x = design_at(n_try)
        if max_time_s is None or x.mt["total_s"] <= max_time_s:
            top, n_try = x, most_within(x)
        else:  # over: between the last count within the time and this one
            n_try = int(0.95 * n_try) if top is None else (top.k + n_try) // 2
    if top is None:
        return None

    def trend_of(lo: DesignedCount, hi: DesignedCount) -> CountTrend:
        return fit_count_trend(lo.k, count_std(lo.pred.std, targets), hi.k, count_std(hi.pred.std, targets))

    n_most = top.k
    lo, hi = cur, top
    within = "" if max_time_s is None or n_most == most else f" within the {max_time_s / 60:.1f} min allowed"
    if worst_of(hi.pred) > 1.0 + 1e-9:
        trend = trend_of(lo, hi)
        floor = trend.floor_std()
        _r, m, i = max((float(ratio_to_target(floor[m][i], t[i])), m, i) for m, t in targets.items() for i in range(4))
        best = hi if worst_of(hi.pred) < worst_of(lo.pred) else lo
        why = (
            f"with {best.k} fit poses; {hi.k}, the most the design takes{within}, miss it too: by the trend of the "
            f"predicted std from {lo.k} to {hi.k} poses, {m} {COMBINATION_NAMES[i]} levels off near "
            f"{floor[m][i] * 1e3:.3f} mm (what the fit poses do not average: "
            f"{_FLOOR_SOURCES.get(m, _FLOOR_SOURCES['combined'])}); other candidate poses may lower it"
        )
        return best, trend_summary(trend, targets), why, ""
    for _round in range(TREND_ROUNDS):
        if hi.k - lo.k <= max(2, hi.k // 20):
            break
        trend = trend_of(lo, hi)
        # the trend's count, kept in the bracket's middle half so that the bracket shrinks by a quarter at least
        q = (hi.k - lo.k) // 4
        mid = design_at(min(max(trend.needed(targets) or hi.k, lo.k + q), hi.k - q))
        if worst_of(mid.pred) <= 1.0 + 1e-9 and (max_time_s is None or mid.mt["total_s"] <= max_time_s):
            hi = mid
        else:
            lo = mid
    trend = trend_of(lo, hi)
    note = (
        f"{hi.k} fit poses, beyond the {cur.k} the count search tries: {hi.k} meet the target, {lo.k} do not "
        "(the counts between guessed by the trend of the predicted std over the count)"
    )
    return hi, trend_summary(trend, targets), "", note


def trend_summary(trend: CountTrend, targets: dict[str, np.ndarray] | None) -> dict[str, Any]:
    """``count_trend`` of a design: the two counts, the floor std per method and combination (m), the count the
    trend says meets the targets (None: none, or no targets).

    Parameters
    ----------
    trend : CountTrend
        The trend of the predicted std over the count.
    targets : dict of str to ndarray, shape (4,), optional
        Per method, the target std per combination, metres.

    Returns
    -------
    dict
        ``{"n_fit": [n_lo, n_hi], "floor_std_m": {method: {combination: metres}}, "n_fit_needed": int or None}``.
    """
    return {
        "n_fit": list(trend.n),
        "floor_std_m": {m: dict(zip(COMBINATION_NAMES, v.tolist(), strict=True)) for m, v in trend.floor_std().items()},
        "n_fit_needed": None if targets is None else trend.needed(targets),
    }
