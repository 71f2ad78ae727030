"""Accuracy against bench time: one design per fit-pose count, side by side, before any motion.

A calibration engineer deciding how long to keep a robot on the bench asks what each extra minute buys. With a target
and no count, :func:`.optimize.design_plan` answers one question (the smallest count that meets the target); the
trade-off answers the one before it: for each count asked, the designed plan's predicted std per method and
combination and its motion time (``i4cal plan design --tradeoff 8,12,20,30``, ``POST /api/v1/plans/tradeoff``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calib.design.beyond_count import count_std, trend_summary
from calib.design.count_trend import fit_count_trend
from calib.design.optimize import DesignRequest, DesignResult, design_plan, ratio_to_target
from calib.design.scene import Scene
from calib.errors import InputError
from calib.model.parameters import COMBINATION_NAMES, I4Parameters

__all__ = [
    "MAX_TRADEOFF_COUNTS",
    "TradeoffRow",
    "design_tradeoff",
    "parse_counts",
    "recommendation_reason",
    "recommended_count",
    "recommended_design",
    "tradeoff_trend",
]

#: most counts in one trade-off (each is a full design: seconds of CPU)
MAX_TRADEOFF_COUNTS = 8


@dataclass(frozen=True)
class TradeoffRow:
    """One count of a trade-off: what its designed plan is predicted to give, and what it costs.

    Attributes
    ----------
    n_fit : int
        Fit poses.
    motion_s : float
        Motion time of the whole plan (sweeps, fit poses, lock phases, line, validation), seconds.
    std_m : dict
        Predicted std per method and combination, metres (every method the plan feeds, not only the optimised ones).
    worst_ratio : float or None
        The largest predicted std of the optimised methods over its target (None without a target; <= 1: met).
    target_met, time_met : bool or None
        The target (judged on the optimised methods) and the time limit; None when not asked.
    """

    n_fit: int
    motion_s: float
    std_m: dict[str, dict[str, float]]
    worst_ratio: float | None
    target_met: bool | None
    time_met: bool | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_fit": self.n_fit,
            "motion_s": self.motion_s,
            "predicted_std_m": self.std_m,
            "worst_ratio_to_target": self.worst_ratio,
            "target_met": self.target_met,
            "time_met": self.time_met,
        }


def parse_counts(counts: Sequence[int] | str, field: str = "counts") -> list[int]:
    """Fit-pose counts, sorted and unique: from a sequence of ints or ``"8,12,20,30"``.

    Parameters
    ----------
    counts : sequence of int or str
        The counts, or their comma-separated text.
    field : str
        The option or field named in an error.

    Returns
    -------
    list of int
        The counts, increasing, each in 2..200.

    Raises
    ------
    InputError
        Naming ``field``: not integers, none, more than :data:`MAX_TRADEOFF_COUNTS`, or one outside 2..200.
    """
    if isinstance(counts, str):
        try:
            values = [int(c) for c in counts.replace(" ", "").split(",") if c]
        except ValueError:
            why = f"comma-separated fit-pose counts, e.g. 8,12,20,30 (got {counts!r})"
            raise InputError(why, field=field) from None
    else:
        values = [int(c) for c in counts]
    out = sorted(set(values))
    if not out:
        raise InputError("at least one fit-pose count", field=field)
    if len(out) > MAX_TRADEOFF_COUNTS:
        raise InputError(f"at most {MAX_TRADEOFF_COUNTS} counts (got {len(out)})", field=field)
    bad = [c for c in out if not 2 <= c <= 200]
    if bad:
        raise InputError(f"fit-pose counts must be in 2..200 (got {', '.join(map(str, bad))})", field=field)
    return out


def design_tradeoff(
    nominal: I4Parameters,
    scene: Scene,
    request: DesignRequest,
    counts: Sequence[int] | str,
    progress: Callable[[int, int], None] | None = None,
    **kw: Any,
) -> tuple[list[TradeoffRow], list[DesignResult]]:
    """One design per count (``request`` with ``n_fit`` set to it; everything else as asked: criterion, methods,
    target, candidates and their draws, lock frames, line).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the designs are made at (metres).
    scene : Scene
        The camera's and the board's mounting.
    request : DesignRequest
        What is asked (criterion, methods, target std in metres, candidates, ...); its ``n_fit`` is replaced.
    counts : sequence of int or str
        Fit-pose counts (:func:`parse_counts`).
    progress : callable, optional
        Called with (designs done, designs in all) after each.
    **kw
        :func:`.optimize.design_plan`'s keywords (``limits``, ``motion``, ``noise``, ``ws``); the designs share their
        sweeps and candidates (``cache``), which do not depend on the count.

    Returns
    -------
    rows : list of TradeoffRow
        In increasing count.
    results : list of DesignResult
        The designs themselves (their plans, to write the one chosen).
    """
    ns = parse_counts(counts)
    t = request.targets_by_method()
    rows: list[TradeoffRow] = []
    results: list[DesignResult] = []
    cache: dict[Any, Any] = {}  # the sweeps and candidates of each draw, the same for every count
    for i, n in enumerate(ns):
        res = design_plan(nominal, scene, replace(request, n_fit=n), cache=cache, **kw)
        results.append(res)
        rows.append(_row(res, request, t))
        if progress is not None:
            progress(i + 1, len(ns))
    return rows, results


def _row(res: DesignResult, request: DesignRequest, t: dict[str, np.ndarray] | None) -> TradeoffRow:
    std = res.prediction.std
    worst = None
    if t is not None:
        ratios = [
            float(ratio_to_target(std[m][c], t[m][i]))
            for m in request.methods
            if m in std
            for i, c in enumerate(COMBINATION_NAMES)
        ]
        missing = any(m not in std for m in request.methods)
        worst = float("inf") if missing or not ratios else float(max(ratios))
    return TradeoffRow(
        n_fit=res.n_fit,
        motion_s=float(res.motion["total_s"]),
        std_m={m: dict(v) for m, v in std.items()},
        worst_ratio=worst,
        target_met=res.target_met,
        time_met=res.time_met,
    )


def recommended_count(rows: Sequence[TradeoffRow]) -> int | None:
    """The count to run: with a target, the fewest fit poses that meet it (within the time limit when one was asked);
    with a time limit alone, the most that fit in it (the most accurate plan the time allows); None when neither was
    asked or no count qualifies.

    Parameters
    ----------
    rows : sequence of TradeoffRow
        One per count (:func:`design_tradeoff`).

    Returns
    -------
    int or None
        The recommended count of fit poses.
    """
    if any(r.target_met is not None for r in rows):
        ok = [r.n_fit for r in rows if r.target_met and r.time_met is not False]
        return min(ok) if ok else None
    if any(r.time_met is not None for r in rows):
        ok = [r.n_fit for r in rows if r.time_met]
        return max(ok) if ok else None
    return None


def recommended_design(rows: Sequence[TradeoffRow], results: Sequence[DesignResult]) -> DesignResult | None:
    """The design of :func:`recommended_count` among ``results``.

    Parameters
    ----------
    rows : sequence of TradeoffRow
        One per count.
    results : sequence of DesignResult
        :func:`design_tradeoff`'s designs, in the rows' order.

    Returns
    -------
    DesignResult or None
        The recommended count's design; None when no count qualifies.
    """
    best = recommended_count(rows)
    return None if best is None else results[[r.n_fit for r in rows].index(best)]


def recommendation_reason(rows: Sequence[TradeoffRow]) -> str:
    """Why :func:`recommended_count` chose its count (or why none), for display.

    Parameters
    ----------
    rows : sequence of TradeoffRow
        One per count.

    Returns
    -------
    str
        The reason, in words.
    """
    target = any(r.target_met is not None for r in rows)
    timed = any(r.time_met is not None for r in rows)
    if target:
        return "the fewest fit poses that meet the target" + (" within the time" if timed else "")
    if timed:
        return "the most fit poses that fit in the time"
    return "no target or time limit: nothing to recommend"


def tradeoff_trend(rows: Sequence[TradeoffRow], request: DesignRequest) -> dict[str, Any] | None:
    """Past the largest count: the trend of the predicted std over the count (:mod:`.count_trend`) through the two
    largest counts, for the optimised methods: ``{"n_fit": [n1, n2], "floor_std_m": {method: {combination: m}},
    "n_fit_needed": the count it says meets the target (None: none, or no target)}``; None with fewer than two counts
    or an optimised method without a prediction at both.

    Parameters
    ----------
    rows : sequence of TradeoffRow
        One per count (std in m).
    request : DesignRequest
        The optimised methods and their targets (m).

    Returns
    -------
    dict or None
        The trend's summary (lengths in m).
    """
    if len(rows) < 2:
        return None
    a, b = sorted(rows, key=lambda r: r.n_fit)[-2:]
    if any(m not in a.std_m or m not in b.std_m for m in request.methods):
        return None

    trend = fit_count_trend(a.n_fit, count_std(a.std_m, request.methods), b.n_fit, count_std(b.std_m, request.methods))
    return trend_summary(trend, request.targets_by_method())
