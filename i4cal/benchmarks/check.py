"""``i4cal bench check``: how often a check of a calibration raises a false alarm, and how often it catches a drift.

On the simulated bench (the image-level twin, in this process), each trial: a calibration in force drawn from what
a full calibration of this bench knows (the true combinations plus a draw of the full plan's predicted combined
covariance: a full run's estimate), the bench drifted (or not), one check (the bench's designed check plan,
acquired, extracted, fitted, tested by ``calib.check.drift``). Cases: ``none`` (no drift: every ``drifted`` is a false
alarm), ``L`` (the legs grow), ``H-D`` (``D`` shrinks), ``q03`` (an encoder offset jumps: ``S-(q04-q03)/2`` moves),
each drift ``--drift-std`` predicted std of the check's change on that combination. Reported per case: the verdicts,
the detection rate naming the combination, the estimated change within 3 std of the truth, the update's error
against the truth beside a full recalibration's predicted std, the check's motion and its result's delay after
the last frame.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

#: case -> (parameter drifted, the combination it moves, d(combination)/d(parameter))
CASES: dict[str, tuple[str | None, str | None, float]] = {
    "none": (None, None, 0.0),
    "L": ("L", "L", 1.0),
    "H-D": ("D", "H-D", -1.0),
    "q03": ("q03", "S-(q04-q03)/2", 0.5),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "check",
        help="false alarms and detections of i4cal check on the simulated bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--trials", type=int, default=40, metavar="N", help="checks per case (default 40)")
    p.add_argument("--cases", default=",".join(CASES), help=f"cases to run (default {','.join(CASES)})")
    p.add_argument("--drift-std", type=float, default=4.0, help="drift in predicted std of the check (default 4)")
    p.add_argument("--max-seconds", type=float, default=60.0, help="the check plan's motion budget (default 60 s)")
    p.add_argument("--seed", type=int, default=0, help="first seed of the trials")
    p.add_argument(
        "--speeds",
        metavar="BENCH_FILE",
        default=None,
        help="design the check plan for this bench file's speeds, accelerations, settle times and soft limits, and "
        "run the simulated axes at them (e.g. deploy/bench-real.example.toml): the check's motion as measured on "
        "that bench (default: the simulated bench's)",
    )
    p.add_argument("--json", metavar="PATH", default=None, help="also write the figures as JSON")
    p.set_defaults(handler=_run)


def motion_overrides(path: str | None) -> dict[str, Any]:
    """The bench file's motion settings (speed, acceleration, settle times, soft limits) as overrides of the
    simulated bench's configuration (:meth:`drivers.sim.bench.SimBench.bench_config`); ``{}`` without a file."""
    if path is None:
        return {}
    from drivers.acquisition.config import load_bench

    real = load_bench(path)
    a = real.actuators
    return {
        "actuators": {
            "speed_m_s": a.speed_m_s,
            "accel_m_s2": a.accel_m_s2,
            "settle_s": a.settle_s,
            "limits": {"q_min": list(a.limits.q_min), "q_max": list(a.limits.q_max)},
        },
        "acquisition": {"line_rate_hz": 50.0, "settle_s": real.acquisition.settle_s},
    }


def _in_force_document(combos: dict[str, float], cov, truth, nominal) -> Any:
    """An ``i4cal.calibration/1`` document of ``combos`` with covariance ``cov`` (completed with the true H, S, q03)."""
    from calib.identify.export import COMPLETION_RULES, CalibrationDocument, Completion
    from calib.model.parameters import COMBINATION_NAMES, I4Parameters

    params = I4Parameters.from_combinations(combos, truth)
    std = [math.sqrt(cov[i][i]) for i in range(4)]
    return CalibrationDocument(
        bench="simulated",
        method="combined",
        method_choice="a full calibration's estimate, drawn from its predicted covariance (benchmark)",
        software_version="benchmark",
        seven=params.seven(),
        seven_std=dict.fromkeys(params.seven()),
        identified=["q02", "q04", "D", "L"],
        fixed_at_nominal=["H", "S", "q03"],
        completion=Completion(rule="combinations+nominal", text=COMPLETION_RULES["combinations+nominal"]),
        T_per_rad=params.T_per_rad,
        combinations=combos,
        combinations_std=dict(zip(COMBINATION_NAMES, std, strict=True)),
        covariance=[list(r) for r in cov],
        nominal=nominal.as_dict(),
        nominal_combinations=nominal.combinations(),
    )


async def _trial(case: str, k: int, drift_m: float, ctx: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    from calib.model.parameters import COMBINATION_NAMES
    from drivers.sim.bench import SimBench
    from service.checks.run import run_check

    param, combo, gain = CASES[case]
    seed = ctx["seed"] + k
    drift = {param: drift_m / gain} if param else {}
    rng = np.random.default_rng([seed, 11])
    truth = ctx["truth"]
    drawn = rng.multivariate_normal([truth.combinations()[n] for n in COMBINATION_NAMES], ctx["cov_full"])
    doc = _in_force_document(
        dict(zip(COMBINATION_NAMES, map(float, drawn), strict=True)), ctx["cov_full"], truth, ctx["nominal"]
    )
    from calib.errors import I4calError

    over = ctx["overrides"]
    axes = None
    if over:  # the simulated axes at the bench file's speeds: the check's motion takes what it would there
        from drivers.sim.mechanism import AxisConfig

        act = over["actuators"]
        axes = AxisConfig(default_speed=act["speed_m_s"], accel=act["accel_m_s2"], home_speed=10.0)
    sim = SimBench(port=0, seed=seed, drift_m=drift, axis_config=axes)
    await sim.start()
    try:
        cfg = sim.bench_config(
            **{
                "acquisition": {"line_rate_hz": 50.0},
                **over,
                "camera": {"timeout_s": 10.0},
                "actuators": {**over.get("actuators", {}), "timeout_s": 2.0},
            }
        )
        with tempfile.TemporaryDirectory(prefix="i4cal-bench-check-") as tmp:
            out = await run_check(cfg, ctx["plan"], doc, Path(tmp) / "ds", camera=ctx["camera"])
        now = sim.geometry.truth.combinations()
    except I4calError as exc:  # a trial that could not acquire: counted apart, the others go on
        return {"case": case, "seed": seed, "verdict": "failed", "error": str(exc), "drifted": [], "timing_s": {}}
    finally:
        await sim.stop()
    row: dict[str, Any] = {
        "case": case,
        "seed": seed,
        "verdict": out.verdict,
        "drifted": list(out.drifted),
        "timing_s": out.timing_s,
    }
    if combo is not None:
        row["named"] = combo in out.drifted
        row["named_alone"] = list(out.drifted) == [combo]
        row["change_m"] = out.change_m[combo]
        row["change_std_m"] = out.change_std_m[combo]
        row["within_3_std"] = abs(out.change_m[combo] - drift_m) < 3 * out.change_std_m[combo]
    if out.update.get("accepted"):
        upd = out.update["combinations_m"]
        row["update_error_m"] = {n: upd[n] - now[n] for n in COMBINATION_NAMES}
    return row


def _summary(all_rows: list[dict[str, Any]], ctx: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    from calib.model.parameters import COMBINATION_NAMES

    rows = [r for r in all_rows if r["verdict"] != "failed"]
    if not rows:
        return {"trials": 0, "failed": len(all_rows), "verdicts": {}, "drifted_rate": float("nan")}
    n = len(rows)
    out: dict[str, Any] = {
        "trials": n,
        "failed": len(all_rows) - n,
        "verdicts": {v: sum(r["verdict"] == v for r in rows) for v in ("holds", "drifted", "inconclusive")},
        "drifted_rate": sum(r["verdict"] == "drifted" for r in rows) / n,
        "result_after_last_frame_s_max": max(r["timing_s"]["result_after_last_frame"] for r in rows),
        "result_after_last_frame_s_median": float(np.median([r["timing_s"]["result_after_last_frame"] for r in rows])),
        "acquisition_s_median": float(np.median([r["timing_s"]["acquisition"] for r in rows])),
        "motion_s_median": float(np.median([r["timing_s"]["motion"] for r in rows])),
        "approach_s_median": float(np.median([r["timing_s"]["approach"] for r in rows])),
        "result_cpu_s_median": float(np.median([r["timing_s"]["result_cpu"] for r in rows])),
    }
    if "named" in rows[0]:
        out["detected_naming_it"] = sum(r["named"] for r in rows) / n
        out["named_alone"] = sum(r["named_alone"] for r in rows) / n
        out["change_within_3_std"] = sum(r["within_3_std"] for r in rows) / n
    errs = [r["update_error_m"] for r in rows if "update_error_m" in r]
    if errs:
        full = np.sqrt(np.diag(ctx["cov_full"]))
        rms = {c: float(np.sqrt(np.mean([e[c] ** 2 for e in errs]))) for c in COMBINATION_NAMES}
        out["updates"] = len(errs)
        out["update_rms_error_m"] = rms
        out["update_rms_over_full_std"] = {c: rms[c] / float(full[i]) for i, c in enumerate(COMBINATION_NAMES)}
    return out


def _context(args: argparse.Namespace) -> dict[str, Any]:
    import numpy as np

    from calib.formats.plan import make_plan
    from drivers.sim.bench import SimBench
    from drivers.sim.render import RenderSettings
    from service.checks.plan import check_plan_for_bench
    from service.checks.run import predicted_check_std
    from service.design import check_for_bench, motion_spec

    probe = SimBench(port=0, renderer=object())
    probe.tcp_address, probe.frame_address = ("127.0.0.1", 1), ("127.0.0.1", 3)  # never connected: the design needs
    overrides = motion_overrides(args.speeds)
    cfg = probe.bench_config(**{"acquisition": {"line_rate_hz": 50.0}, **overrides})  # geometry, limits, speeds
    nominal = cfg.nominal_parameters()
    full = make_plan("full", nominal, seed=0, limits=cfg.calib_limits())
    pred_full = check_for_bench(cfg, full, None, ("combined",)).prediction
    cache = Path(tempfile.gettempdir()) / "i4cal-bench-check-plans"
    plan, n_fit, _ = check_plan_for_bench(cfg, args.max_seconds, cache)
    from calib.design.motion import plan_motion_time
    from drivers.sim.twin import BenchGeometry

    return {
        "overrides": overrides,
        "seed": args.seed,
        "truth": BenchGeometry().truth,
        "nominal": nominal,
        "cov_full": np.asarray(pred_full.covariance["combined"]),
        "full_std_m": pred_full.std["combined"],
        "plan": plan,
        "n_fit": n_fit,
        "motion_s": float(plan_motion_time(plan, motion_spec(cfg), nominal)["total_s"]),
        "predicted_check_std_m": predicted_check_std(cfg, plan, RenderSettings().camera()),
        "camera": RenderSettings().camera(),
    }


def _run(args: argparse.Namespace) -> int:
    from calib.errors import InputError

    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad or not cases:
        raise InputError(f"{', '.join(bad) or 'none given'}: cases are {', '.join(CASES)}", field="--cases")
    if not 1 <= args.trials <= 10000:
        raise InputError("must be in 1..10000", field="--trials")
    if not (math.isfinite(args.drift_std) and args.drift_std > 0):
        raise InputError("must be > 0", field="--drift-std")
    t0 = time.monotonic()
    ctx = _context(args)
    figures: dict[str, Any] = {
        "check_plan": {"fit_poses": ctx["n_fit"], "motion_s": ctx["motion_s"], "budget_s": args.max_seconds},
        "predicted_check_std_m": ctx["predicted_check_std_m"],
        "full_calibration_std_m": ctx["full_std_m"],
        "drift_std": args.drift_std,
        "cases": {},
    }
    for case in cases:
        _, combo, _ = CASES[case]
        drift_m = 0.0
        if combo is not None:
            i = ["L", "H-D", "S-q02/2", "S-(q04-q03)/2"].index(combo)
            drift_m = args.drift_std * math.hypot(ctx["predicted_check_std_m"][combo], math.sqrt(ctx["cov_full"][i][i]))
        rows = [asyncio.run(_trial(case, k, drift_m, ctx)) for k in range(args.trials)]
        figures["cases"][case] = {"drift_m": drift_m, "combination": combo, **_summary(rows, ctx), "rows": rows}
        s = figures["cases"][case]
        line = f"{case:5s} drift {drift_m * 1e3:6.3f} mm: {s['verdicts']}, {s['failed']} failed"
        if not s["trials"]:
            print(line, flush=True)
            continue
        if combo is not None:
            line += (
                f", detected naming {combo} {s['detected_naming_it']:.0%}, alone {s['named_alone']:.0%}, "
                f"change within 3 std {s['change_within_3_std']:.0%}"
            )
            if "update_rms_over_full_std" in s:
                line += f", update RMS error / full std on {combo}: {s['update_rms_over_full_std'][combo]:.2f}"
        else:
            line += f", false alarms {s['drifted_rate']:.0%}"
        line += (
            f"; motion {s['motion_s_median']:.1f} s (+ {s['approach_s_median']:.1f} s to the first pose), "
            f"acquisition {s['acquisition_s_median']:.1f} s (median); result "
            f"{s['result_after_last_frame_s_median']:.1f} s (median), <= {s['result_after_last_frame_s_max']:.1f} s "
            f"after the last frame ({s['result_cpu_s_median']:.1f} s of CPU, median)"
        )
        print(line, flush=True)
    figures["elapsed_s"] = time.monotonic() - t0
    ratios = [v for s in figures["cases"].values() for v in (s.get("update_rms_over_full_std") or {}).values()]
    if ratios:
        print(f"updates: RMS error / a full recalibration's std at most {max(ratios):.2f} (1.5 asked)")
    where = args.speeds or "the simulated bench"
    print(
        f"check plan: {ctx['n_fit']} fit poses, {ctx['motion_s']:.1f} s of motion predicted at the speeds of {where}; "
        f"{figures['elapsed_s']:.0f} s in all"
    )
    figures["speeds"] = where
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1, default=float), encoding="utf-8")
    return 0
