"""Which method's result to load, and why: one rule for the demo, ``i4cal calibrate``, the report and the dashboard.

The rule (:func:`verdict`), applied to a result document (:class:`calib.formats.resultdoc.ResultDocument`, or its JSON):

1. Candidates are the methods whose fit converged and that have the four combinations with their std.
2. A candidate must improve the validation gap (RMS of the displacement gaps on the validation poses) on the a priori
   geometry's; without validation poses the fit poses' gap is used, and said.
3. Among the candidates, those whose gap is within the gap's own sampling uncertainty of the smallest (the RMS of
   ``n`` gaps is known to about ``1/sqrt(2 n)`` of itself) are equally good on the validation; of these the one with
   the smallest largest std of the four combinations is chosen (ties: the methods' apply order).
4. No candidate: nothing to load (the a priori stays); the reason says why.

The uncertainty convention everywhere is **± 1 standard deviation** (:data:`UNCERTAINTY`); the report may add the
expanded uncertainty U (k = 2) beside it.

The measurement floor is the gap the true geometry leaves (the vision's own noise): known on a simulated bench (the
result's ``truth`` validation), else estimated as the smallest fit-pose gap RMS of the converged methods (a model
fitted to those poses cannot do better than the noise on them).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from calib.formats.resultdoc import Gaps, MethodEntry, ResultDocument, ValidationEntry

#: the uncertainty convention of every std shown by the CLI, the dashboard and the report
UNCERTAINTY = "± 1 std"
#: the four identifiable combinations, spelled once for every table
COMBINATIONS = ("L", "H-D", "S-q02/2", "S-(q04-q03)/2")
#: the command that writes the file a controller loads (RESULT: a result file or a run id)
EXPORT_COMMAND = "i4cal export {result} -o calibration.json --method {method}"


@dataclass(frozen=True)
class Verdict:
    """The outcome of :func:`verdict` (lengths in mm, for display).

    Attributes
    ----------
    method : str or None
        The method whose result to load; None: none (keep the a priori).
    reason : str
        One line: why (or why none).
    gap_mm, a_priori_gap_mm, floor_mm : float or None
        The chosen method's validation gap RMS, the a priori's, the measurement floor.
    gap_kind : str
        ``validation`` or ``fit poses`` (which gaps were compared).
    floor_source : str or None
        ``true geometry`` (simulated bench) or ``best fit-pose gap`` (an estimate).
    std_max_mm : float or None
        The chosen method's largest std of the four combinations.
    failed : dict
        Methods whose fit failed -> the reason (once per method).
    next_command : str or None
        The next command to run.
    """

    method: str | None
    reason: str
    gap_mm: float | None = None
    a_priori_gap_mm: float | None = None
    floor_mm: float | None = None
    gap_kind: str = "validation"
    floor_source: str | None = None
    std_max_mm: float | None = None
    failed: Mapping[str, str] | None = None
    next_command: str | None = None
    uncertainty: str = UNCERTAINTY

    def lines(self) -> list[str]:
        """The verdict in one or two lines: what to load and why, then the next command."""
        out = [("verdict: " if self.method else "verdict: nothing to load: ") + self.reason]
        if self.next_command:
            out.append(f"next: {self.next_command}")
        return out

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["failed"] = dict(self.failed or {})
        d["lines"] = self.lines()
        return d


def _gap(validation: Mapping[str, ValidationEntry], name: str, part: str) -> tuple[float | None, int]:
    """The RMS gap (mm) of parameter set ``name`` on ``part`` (``validation`` or ``poses``), and its pose pairs."""
    v = validation.get(name)
    g = (v.gaps(part) if v is not None else None) or Gaps()
    return g.rms_finite_mm(), g.count()


def _std_max_mm(entry: MethodEntry) -> float | None:
    std = entry.values_std or {}
    vals = [float(v) for k in COMBINATIONS if (v := std.get(k)) is not None]
    if len(vals) != len(COMBINATIONS) or not all(math.isfinite(v) for v in vals):
        return None
    return 1e3 * max(vals)


def _std_or_inf(entry: MethodEntry) -> float:
    std = _std_max_mm(entry)
    return math.inf if std is None else std


def _floor(
    validation: Mapping[str, ValidationEntry], converged: Sequence[str], part: str
) -> tuple[float | None, str | None]:
    truth, _ = _gap(validation, "truth", part)
    if truth is not None:
        return truth, "true geometry"
    fits = [g for g in (_gap(validation, m, "poses")[0] for m in converged) if g is not None]
    return (min(fits), "best fit-pose gap") if fits else (None, None)


def verdict(
    doc: ResultDocument | Mapping[str, Any], result: str = "RESULT", order: Sequence[str] | None = None
) -> Verdict:
    """Which method's result to load from a result document, why, and the next command.

    Parameters
    ----------
    doc : ResultDocument or mapping
        A result document (its ``methods`` and ``validation``; :mod:`calib.formats.resultdoc`).
    result : str
        How the next command names the result (a result file, a run id); ``RESULT`` when there is none yet.
    order : sequence of str, optional
        Methods by preference on a tie (default: :func:`calib.identify.registry.apply_order`).

    Returns
    -------
    Verdict
    """
    if order is None:
        from calib.identify.registry import apply_order

        order = apply_order()
    document = ResultDocument.of(doc)
    methods, validation = document.methods, document.validation
    failed = {m: f for m, e in methods.items() if (f := e.failure) is not None}
    converged = [m for m, e in methods.items() if m not in failed and _std_max_mm(e) is not None]
    if not methods:
        return Verdict(None, "no method was run", failed=failed)
    if not converged:
        return Verdict(
            None,
            f"no fit converged ({', '.join(failed)}: the reasons under Table I); the a priori geometry stays",
            failed=failed,
        )
    part, kind = "validation", "validation"
    if all(_gap(validation, m, part)[0] is None for m in converged):
        part, kind = "poses", "fit poses"
    prior, _ = _gap(validation, "a priori", part)
    floor, floor_source = _floor(validation, converged, part)
    gaps = {m: _gap(validation, m, part) for m in converged}
    scored = {m: g for m, (g, _) in gaps.items() if g is not None}
    if not scored:
        return Verdict(None, "no validation gaps to judge the fits by (no validation poses)", failed=failed)
    better = {m: g for m, g in scored.items() if prior is None or g < prior}
    if not better:
        return Verdict(
            None,
            f"no method improves the {kind} gap on the a priori's ({prior:.3f} mm RMS); check the data and the "
            "bench file before loading anything",
            a_priori_gap_mm=prior,
            floor_mm=floor,
            gap_kind=kind,
            floor_source=floor_source,
            failed=failed,
        )
    chosen, tie = _choose(methods, better, gaps, order)
    gap, std = scored[chosen], _std_max_mm(methods[chosen])
    against = f"against the a priori's {prior:.3f} mm" if prior is not None else "(no a priori gap)"
    floor_txt = f" (floor {floor:.3f} mm, {floor_source})" if floor is not None else ""
    why_std = "; the smallest std of the methods as good on the validation" if tie else ""
    reason = (
        f"load {chosen}: {kind} gap RMS {gap:.3f} mm {against}{floor_txt}; largest std {std:.3f} mm "
        f"({UNCERTAINTY}){why_std}"
    )
    return Verdict(
        chosen,
        reason,
        gap_mm=gap,
        a_priori_gap_mm=prior,
        floor_mm=floor,
        gap_kind=kind,
        floor_source=floor_source,
        std_max_mm=std,
        failed=failed,
        next_command=EXPORT_COMMAND.format(result=result, method=chosen),
    )


def _choose(
    methods: Mapping[str, MethodEntry],
    better: Mapping[str, float],
    gaps: Mapping[str, tuple[float | None, int]],
    order: Sequence[str],
) -> tuple[str, bool]:
    """Of the methods that improve on the a priori (gap RMS in ``better``, mm), the one to load: among those within
    the gap's sampling uncertainty of the smallest, the smallest largest std (ties: ``order``); and whether the std
    decided (several tied on the gap)."""
    best = min(better.values())
    n = max(1, min(gaps[m][1] for m in better))
    tied = [m for m, g in better.items() if g <= best * (1.0 + 1.0 / math.sqrt(2.0 * n))]
    rank = {m: i for i, m in enumerate(order)}
    chosen = min(tied, key=lambda m: (_std_or_inf(methods[m]), rank.get(m, len(rank))))
    return chosen, len(tied) > 1
