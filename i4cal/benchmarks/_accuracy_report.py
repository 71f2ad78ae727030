"""Summaries and terminal tables of ``i4cal bench accuracy`` (pure functions of the trial records)."""

from __future__ import annotations

import math
import statistics
from collections import Counter
from typing import Any

from i4cal.benchmarks._accuracy_trial import METHODS

COMBINATIONS: tuple[str, ...] = ("L", "H-D", "S-q02/2", "S-(q04-q03)/2")
EFFICIENCY_TARGET = 0.67  #: the combined method's bound RMS / error RMS at least this: near its Cramer-Rao bound
HONESTY_TOLERANCE = 0.30  #: mean reported std / RMS error within 1 -/+ this


def _rms(xs: list[float]) -> float | None:
    return math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else None


def _mean(xs: list[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def _short(msg: str) -> str:
    return msg.splitlines()[0][:160] if msg else "unknown"


def method_summary(trials: list[dict[str, Any]], name: str) -> dict[str, Any]:
    """One method over the trials of a study point (metres; gaps in mm).

    Returns
    -------
    dict
        ``n_ok``, ``n_failed``, ``failures`` (message -> count), and per combination ``rms_error_m``,
        ``mean_std_m``, ``std_over_error`` (honesty: 1 is perfect), ``bound_rms_m`` (RMS over the same trials
        of the combined method's Cramer-Rao bound) and ``efficiency`` (bound RMS / error RMS); then
        ``within_2_std`` (fraction of the trials whose error is within 2 reported std),
        ``gap_validation_rms_mm`` (RMS over trials of each trial's validation gap RMS) and
        ``gap_below_a_priori`` (trials whose gap is below their a priori gap).
    """
    ok = [t for t in trials if _method_record(t, name).get("ok")]
    failures = Counter(_failure_message(t, name) for t in trials if not _method_record(t, name).get("ok"))
    out: dict[str, Any] = {"n_ok": len(ok), "n_failed": len(trials) - len(ok), "failures": dict(failures)}
    for field in ("rms_error_m", "mean_std_m", "std_over_error", "bound_rms_m", "efficiency", "within_2_std"):
        out[field] = {}
    for c in COMBINATIONS:
        for field, value in _combination_stats(ok, name, c).items():
            out[field][c] = value
    out.update(_gap_stats(ok, name))
    return out


def _method_record(trial: dict[str, Any], name: str) -> dict[str, Any]:
    """One method's record in a trial (empty when the trial failed before the method ran)."""
    return (trial.get("methods") or {}).get(name) or {}


def _failure_message(trial: dict[str, Any], name: str) -> str:
    """Why a method has no estimate in a trial: the trial's error, else the method's, else ``not run``."""
    return _short(trial["error"] if trial.get("error") else _method_record(trial, name).get("error") or "not run")


def _combination_stats(ok: list[dict[str, Any]], name: str, c: str) -> dict[str, float | None]:
    """One method's statistics on one combination over the trials it succeeded in (metres, or ratios)."""
    errs = [t["methods"][name]["errors"][c] for t in ok]
    stds = [s[c] for t in ok if (s := t["methods"][name]["std"]) and s.get(c) is not None]
    err_rms, std_mean = _rms(errs), _mean(stds)
    with_bound = [t for t in ok if t.get("bound_std") and t["bound_std"].get(c) is not None]
    b_rms = _rms([t["bound_std"][c] for t in with_bound])
    e_rms_b = _rms([t["methods"][name]["errors"][c] for t in with_bound])
    z = [
        abs(t["methods"][name]["errors"][c]) / sd
        for t in ok
        if (sd := (t["methods"][name]["std"] or {}).get(c)) and t["methods"][name]["errors"][c] is not None
    ]
    return {
        "rms_error_m": err_rms,
        "mean_std_m": std_mean,
        "std_over_error": _ratio(std_mean, err_rms),
        "bound_rms_m": b_rms,
        "efficiency": _ratio(b_rms, e_rms_b),
        "within_2_std": sum(1 for v in z if v <= 2.0) / len(z) if z else None,
    }


def _gap_stats(ok: list[dict[str, Any]], name: str) -> dict[str, Any]:
    """One method's validation gaps over the trials it succeeded in (mm) against their a priori gaps."""
    pairs = [(t["methods"][name]["gap_validation_rms_mm"], t.get("gap_a_priori_rms_mm")) for t in ok]
    gaps = [(g, a) for g, a in pairs if g is not None]
    return {
        "gap_validation_rms_mm": _rms([g for g, _ in gaps]),
        "gap_below_a_priori": sum(1 for g, a in gaps if a is not None and g < a),
        "gap_trials": len(gaps),
    }


def summarize(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Summary of the trials of one study point: per method (:func:`method_summary`), gaps, noise, timing, targets."""
    done = [t for t in trials if not t.get("error")]
    edge = [t["edge_noise_px"] for t in done if t.get("edge_noise_px") is not None]
    methods = {m: method_summary(trials, m) for m in METHODS}
    timing = {
        k: _mean([t[k] for t in done if t.get(k) is not None])
        for k in ("render_s", "extract_s", "calibrate_s", "cpu_s")
    }
    rods = sum(t.get("rods_found", 0) for t in done), sum(t.get("rods_total", 0) for t in done)
    summary = {
        "trials": len(trials),
        "trials_failed": len(trials) - len(done),
        "a_priori_rms_error_m": a_priori_errors(trials),
        "trial_errors": dict(Counter(_short(t["error"]) for t in trials if t.get("error"))),
        "edge_noise_px_median": statistics.median(edge) if edge else None,
        "rods_found_fraction": rods[0] / rods[1] if rods[1] else None,
        "trials_extraction_recovered": sum(bool((t.get("extraction_recovered") or {}).get("applied")) for t in done),
        "gap_a_priori_rms_mm": _rms(
            [t["gap_a_priori_rms_mm"] for t in done if t.get("gap_a_priori_rms_mm") is not None]
        ),
        "gap_truth_rms_mm": _rms([t["gap_truth_rms_mm"] for t in done if t.get("gap_truth_rms_mm") is not None]),
        "methods": methods,
        "timing_mean_s": timing,
    }
    summary["targets"] = targets(summary)
    return summary


def a_priori_errors(trials: list[dict[str, Any]]) -> dict[str, float | None]:
    """RMS over the trials of nominal - truth per combination (metres): what calibration has to remove."""
    from calib.model.parameters import NOMINAL

    nom = NOMINAL.combinations()
    truths = [t["truth_combinations"] for t in trials if t.get("truth_combinations")]
    return {c: _rms([nom[c] - tc[c] for tc in truths]) for c in COMBINATIONS}


def targets(summary: dict[str, Any]) -> dict[str, Any]:
    """The issue's targets checked on a summary: combined efficiency, std honesty, gaps below the a priori one."""
    comb = summary["methods"]["combined"]
    eff = [v for v in comb["efficiency"].values() if v is not None]
    hon = {m: [v for v in s["std_over_error"].values() if v is not None] for m, s in summary["methods"].items()}
    apriori = summary["gap_a_priori_rms_mm"]
    gaps = {m: s["gap_validation_rms_mm"] for m, s in summary["methods"].items()}
    worst = {m: max((abs(v - 1) for v in vs), default=None) for m, vs in hon.items()}
    return {
        "efficiency_combined": {
            "target": f">= {EFFICIENCY_TARGET}",
            "min": min(eff, default=None),
            "met": bool(eff) and len(eff) == len(COMBINATIONS) and min(eff) >= EFFICIENCY_TARGET,
        },
        "std_honesty": {
            "target": f"mean std / RMS error within {HONESTY_TOLERANCE:.0%} of 1",
            "worst_deviation": worst,
            "met": {m: w is not None and w <= HONESTY_TOLERANCE for m, w in worst.items()},
        },
        "gap_below_a_priori": {
            "target": "every method's validation gap below the a priori gap",
            "a_priori_mm": apriori,
            "gaps_mm": gaps,
            "met": {m: g is not None and apriori is not None and g < apriori for m, g in gaps.items()},
        },
    }


# -- terminal ------------------------------------------------------------------------------------------------
def _mm(v: float | None, digits: int = 3) -> str:
    return "-" if v is None else f"{v * 1e3:.{digits}f}"


def _x(v: float | None, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt)


def _met(ok: bool) -> str:
    return "[green]met[/green]" if ok else "[red]not met[/red]"


def study_tables(point: dict[str, Any], title: str) -> list[Any]:
    """Rich tables of one study point: accuracy vs the truth per method and combination, then the gaps."""
    from rich.table import Table

    s = point["summary"]
    t = Table(title=title, title_justify="left")
    for col in ("method", "combination", "RMS error mm", "mean std mm", "std/error", "bound mm", "efficiency", "ok"):
        t.add_column(col, justify="left" if col in ("method", "combination") else "right")
    for i, c in enumerate(COMBINATIONS):
        t.add_row(
            "[dim]a priori (nominal)[/dim]" if i == 0 else "",
            f"[dim]{c}[/dim]",
            f"[dim]{_mm(s['a_priori_rms_error_m'][c])}[/dim]",
            "",
            "",
            "",
            "",
            "",
            end_section=i == len(COMBINATIONS) - 1,
        )
    for m in METHODS:
        ms = s["methods"][m]
        for i, c in enumerate(COMBINATIONS):
            ratio = ms["std_over_error"][c]
            style = "" if ratio is None or abs(ratio - 1) <= HONESTY_TOLERANCE else "[yellow]"
            eff = ms["efficiency"][c]
            est = "" if m != "combined" or eff is None else ("[green]" if eff >= EFFICIENCY_TARGET else "[red]")
            t.add_row(
                m if i == 0 else "",
                c,
                _mm(ms["rms_error_m"][c]),
                _mm(ms["mean_std_m"][c]),
                style + _x(ratio),
                _mm(ms["bound_rms_m"][c]),
                est + _x(eff),
                f"{ms['n_ok']}/{s['trials']}" if i == 0 else "",
                end_section=i == len(COMBINATIONS) - 1,
            )
    g = Table(
        title="displacement gap on the validation poses (RMS over trials of each trial's RMS, mm; Table II)",
        title_justify="left",
    )
    for col in ("parameters", "gap mm", "below a priori", "failures"):
        g.add_column(col, justify="left" if col in ("parameters", "failures") else "right")
    g.add_row("a priori (nominal)", _x(s["gap_a_priori_rms_mm"], ".3f"), "", "")
    for m in METHODS:
        ms = s["methods"][m]
        fails = "; ".join(f"{n}x {msg}" for msg, n in ms["failures"].items())
        g.add_row(
            m,
            _x(ms["gap_validation_rms_mm"], ".3f"),
            f"{ms['gap_below_a_priori']}/{ms['gap_trials']}",
            f"[red]{fails}[/red]" if fails else "",
        )
    g.add_row("[dim]truth (vision's own error)[/dim]", f"[dim]{_x(s['gap_truth_rms_mm'], '.3f')}[/dim]", "", "")
    return [t, g]


def target_lines(summary: dict[str, Any]) -> list[str]:
    """One line per target of the issue, met or not."""
    tg = summary["targets"]
    eff = tg["efficiency_combined"]
    hon = tg["std_honesty"]
    gap = tg["gap_below_a_priori"]
    lines = [
        f"combined efficiency (bound RMS / error RMS) min {_x(eff['min'])}, target {eff['target']}: {_met(eff['met'])}"
    ]
    lines.append(
        "std honesty (mean std / RMS error within 30%): "
        + ", ".join(f"{m} worst {_x(hon['worst_deviation'][m], '.0%')} off {_met(hon['met'][m])}" for m in METHODS)
    )
    lines.append(
        f"validation gap below the a priori {_x(gap['a_priori_mm'], '.3f')} mm: "
        + ", ".join(f"{m} {_x(gap['gaps_mm'][m], '.3f')} mm {_met(gap['met'][m])}" for m in METHODS)
    )
    return lines


def sweep_table(name: str, points: list[dict[str, Any]]) -> Any:
    """Rich table of one sweep: per point, edge noise, the combined method's errors per combination, bound and
    efficiency, the other methods' errors (RMS over the four combinations) and the gaps."""
    from rich.table import Table

    label = {"noise": "sensor noise grey", "poses": "fit poses"}.get(name, name)
    t = Table(
        title=f"sweep over {label.removesuffix(' grey')} - RMS errors mm: the combined method's per combination, "
        "its bound and efficiency; the other methods' over the four (e-e: end-effector); gaps mm",
        title_justify="left",
    )
    cols = [label, "ok", "edge px", *COMBINATIONS, "bound", "eff. min", "e-e", "legs", "gap comb.", "gap a priori"]
    for col in cols:
        t.add_column(col, justify="right")
    for p in points:
        s = p["summary"]
        cm = s["methods"]["combined"]
        bound = [v for v in cm["bound_rms_m"].values() if v is not None]
        eff = [v for v in cm["efficiency"].values() if v is not None]
        others = []
        for m in METHODS[1:]:
            errs = [v for v in s["methods"][m]["rms_error_m"].values() if v is not None]
            others.append(_mm(_rms(errs)) if len(errs) == len(COMBINATIONS) else "-")
        t.add_row(
            f"{p['value']:g}",
            f"{cm['n_ok']}/{s['trials']}",
            _x(s["edge_noise_px_median"], ".3f"),
            *[_mm(cm["rms_error_m"][c]) for c in COMBINATIONS],
            _mm(_rms(bound)) if len(bound) == len(COMBINATIONS) else "-",
            _x(min(eff, default=None)),
            *others,
            _x(cm["gap_validation_rms_mm"], ".3f"),
            _x(s["gap_a_priori_rms_mm"], ".3f"),
        )
    return t


def lens_table(points: list[dict[str, Any]]) -> Any:
    """Rich table of the lens sweep: per lens and method, per combination the RMS error, the mean reported std and
    their ratio (std / error: 1 is honest), the validation gap against the a priori one, and the lens models the
    trials' calibrations chose."""
    from rich.table import Table

    t = Table(
        title="sweep over the lens - per combination: RMS error / mean std mm (std/error; trials within 2 std); "
        "validation gap RMS mm (trials below their a priori gap)",
        title_justify="left",
    )
    for col in ("lens", "method", "ok", *COMBINATIONS, "gap", "gap a priori", "lens models chosen"):
        t.add_column(col, justify="right")
    for p in points:
        s = p["summary"]
        chosen = Counter(
            ((t.get("camera") or {}).get("lens_model") or {}).get("chosen") or "given" for t in p["trials"] if t
        )
        for i, m in enumerate(METHODS):
            ms = s["methods"][m]
            t.add_row(
                str(p.get("lens") or p.get("value")) if i == 0 else "",
                m,
                f"{ms['n_ok']}/{s['trials']}",
                *[
                    f"{_mm(ms['rms_error_m'][c])} / {_mm(ms['mean_std_m'][c])} ({_x(ms['std_over_error'][c])}; "
                    f"{_x(ms['within_2_std'][c], '.0%')} in 2 std)"
                    for c in COMBINATIONS
                ],
                f"{_x(ms['gap_validation_rms_mm'], '.3f')} ({ms['gap_below_a_priori']}/{ms['gap_trials']} below)",
                _x(s["gap_a_priori_rms_mm"], ".3f") if i == 0 else "",
                ", ".join(f"{k} x{n}" for k, n in sorted(chosen.items())) if i == 0 else "",
            )
    return t


# -- the whole study on the terminal ------------------------------------------------------------------------
def print_accuracy(doc: dict[str, Any], console: Any = None) -> None:
    """The study's tables, the targets, the sweeps and the notes."""
    from service.cli._output import make_console

    con = console or make_console()
    study = doc.get("study")
    if study:
        _print_study(con, doc, study)
    for name, points in doc["sweeps"].items():
        con.print(lens_table(points) if name == "lens" else sweep_table(name, points))
    for cam_noise, cam in doc["cameras"].items():
        if cam.get("camera") is None:
            con.print(f"[red]camera phase at noise {cam_noise}: {cam.get('error')}[/red]")
    o = doc["options"]
    counts = (
        ", ".join(f"{k} {v}" for k, v in doc["plans"][str(o["n_fit"])].items())
        if str(o["n_fit"]) in doc["plans"]
        else ""
    )
    con.print(f"[dim]per trial: {counts}; {camera_text(doc)}[/dim]")
    for note in doc["notes"]:
        con.print(f"[dim]note: {note}[/dim]")
    load = doc.get("load_average") or {}
    con.print(
        f"[dim]{doc['elapsed_s']:.0f} s in all ({doc['cpu_s']:.0f} CPU s in the workers; load average "
        f"{_load_text(load.get('start'))} at the start, {_load_text(load.get('end'))} at the end)[/dim]"
    )


def _print_study(con: Any, doc: dict[str, Any], study: dict[str, Any]) -> None:
    """The main study's tables, its targets and its failed trials."""
    m = doc["machine"]
    o = doc["options"]
    where = f"{m['cpu']}, {m['cores']} cores, {doc.get('engine') or str(doc['workers']) + ' worker(s)'}, {m['date']}"
    s = study["summary"]
    title = (
        f"i4cal bench accuracy - {s['trials']} trials, sensor noise {study['noise_sigma']:g} grey "
        f"(edge noise {_px(s['edge_noise_px_median'])} px), {study['n_fit']} fit poses, truth spread "
        f"{doc['spread_m'] * 1e3:.2f} mm, seed {o['seed']} - {where}"
    )
    for table in study_tables(study, title):
        con.print(table)
    for line in target_lines(s):
        con.print(line)
    if s["trials_failed"]:
        con.print(
            f"[red]{s['trials_failed']} trial(s) failed: "
            + "; ".join(f"{n}x {e}" for e, n in s["trial_errors"].items())
            + "[/red]"
        )


def camera_text(doc: dict[str, Any]) -> str:
    """How the study's extraction got its intrinsics (``--camera``), with the calibrated cameras' errors."""
    o = doc["options"]
    if o["camera"] == "true":
        return "extraction with the renderer's true intrinsics (--camera true)"
    if o["camera"] == "per-trial":
        points = [doc.get("study") or {}, *(pt for pts in (doc.get("sweeps") or {}).values() for pt in pts)]
        cams = list({t["key"]: t["camera"] for pt in points for t in pt.get("trials", []) if t.get("camera")}.values())
        return (
            f"camera calibrated in every trial from its own {o['camera_views']} rendered board views; "
            "intrinsics error RMS / mean reported std over the trials: "
            + ", ".join(f"{k} {_intr_rms(cams, k)}" for k in ("fx", "cx", "cy", "k1"))
            + "; after the rods' refinement, error RMS: "
            + ", ".join(f"{k} {_intr_rms(cams, k, 'refined_error_vs_true')}" for k in ("fx", "cx", "cy", "k1"))
        )
    return (
        f"camera calibrated once per noise level from {o['camera_views']} rendered board views ("
        + ", ".join(
            f"noise {n}: fx {_dpx(c, 'fx')}, cx {_dpx(c, 'cx')}, cy {_dpx(c, 'cy')} px"
            for n, c in doc["cameras"].items()
            if c.get("camera")
        )
        + " off the truth)"
    )


def _load_text(v: list[float] | None) -> str:
    return "-" if not v else "/".join(f"{x:.1f}" for x in v)


def _dpx(cam: dict[str, Any], key: str) -> str:
    v = ((cam.get("intrinsics") or {}).get("error_vs_true") or {}).get(key)
    return "-" if v is None else f"{v:+.1f}"


def _intr_rms(cams: list[dict[str, Any]], key: str, field: str = "error_vs_true") -> str:
    """RMS error (/ mean std for the calibration's) of one intrinsic over per-trial cameras (px, or dimensionless)."""
    errs = [e for c in cams if (e := ((c.get("intrinsics") or {}).get(field) or {}).get(key)) is not None]
    stds = [e for c in cams if (e := ((c.get("intrinsics") or {}).get("std") or {}).get(key)) is not None]
    if not errs or not stds:
        return "-"
    fmt = ".2f" if key in ("fx", "fy", "cx", "cy") else ".4f"
    return f"{_rms(errs):{fmt}}" + ("" if field != "error_vs_true" else f"/{_mean(stds):{fmt}}")


def _px(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"
