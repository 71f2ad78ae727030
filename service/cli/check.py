"""``i4cal check``: does the calibration in force still hold? A short plan acquired, fitted, tested (docs/check.md)."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

#: exit status per verdict (2: a usage error)
EXIT = {"holds": 0, "drifted": 1, "inconclusive": 3}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "check",
        help="check the calibration in force: a short plan, its combined fit tested against the calibration",
        description=(
            "Acquires a short check plan (designed for the bench within --max-seconds of motion and cached, or "
            "--plan), extracts and fits it with the combined method, and tests the four combinations against the "
            "calibration in force (an i4cal.calibration/1 file). Verdict holds / drifted (which combinations, the "
            "change and its std) / inconclusive (why); where it drifted, the update proposed (--update-out) or "
            "refused with the reason. Exit 0 holds, 1 drifted, 3 inconclusive, 2 usage error."
        ),
    )
    p.add_argument("--bench", required=True, help="bench configuration file (TOML)")
    p.add_argument(
        "--calibration", required=True, metavar="FILE", help="the calibration in force (i4cal.calibration/1)"
    )
    p.add_argument(
        "--plan",
        default=None,
        help="your own check plan (a plan file or name; it needs the phases rotation, translation, poses); default: "
        "designed for the bench within --max-seconds and cached",
    )
    p.add_argument(
        "--max-seconds",
        type=float,
        default=60.0,
        metavar="S",
        help="motion budget of the designed check plan at the bench's speeds, seconds (default 60)",
    )
    p.add_argument("--out", default=None, metavar="DIR", help="the check's dataset directory (default: a new temp dir)")
    p.add_argument(
        "--update-out",
        default=None,
        metavar="FILE",
        help="write the proposed update (i4cal.calibration/1, JSON or YAML by the suffix) when the check proposes one",
    )
    p.add_argument("--camera", default=None, metavar="JSON", help="the camera file when the bench file names none")
    p.add_argument(
        "--alpha", type=float, default=0.05, help="false-alarm probability when nothing drifted (default 0.05)"
    )
    p.add_argument(
        "--repeat",
        type=int,
        default=None,
        metavar="N",
        help="revisit each fit pose N times (2..20; the first revisit takes two frames without moving): the robot's "
        "repeatability, the measurement floor and the outliers, beside the verdict (more motion than the budget)",
    )
    p.add_argument("--plan-cache", default=None, metavar="DIR", help="where designed check plans are kept")
    p.add_argument("--seed", type=int, default=0, help="seed of the designed plan's candidate poses")
    p.add_argument("--json", action="store_true", help="print one JSON object (metres, seconds)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_run)


def _inputs(args: argparse.Namespace):
    from calib.errors import InputError
    from drivers.acquisition.config import load_bench
    from service.cli.calibrate import check_output_file
    from service.export import loads

    if not (math.isfinite(args.max_seconds) and 0 < args.max_seconds < 1e5):
        raise InputError(f"must be in (0, 1e5) seconds, got {args.max_seconds}", field="--max-seconds")
    if args.repeat is not None and not 2 <= args.repeat <= 20:
        raise InputError(f"must be in 2..20, got {args.repeat}", field="--repeat")
    if not 0 < args.alpha < 0.5:
        raise InputError(f"must be in (0, 0.5), got {args.alpha}", field="--alpha")
    if args.update_out:
        check_output_file(args.update_out, "--update-out")
    cfg = load_bench(args.bench)
    path = Path(args.calibration)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(
            f"cannot read the calibration: {exc.strerror}", file=str(path), field="--calibration"
        ) from None
    doc = loads(text, source=str(path))
    from calib.check.drift import in_force_estimate

    try:
        in_force_estimate(doc)
    except InputError as exc:
        raise InputError(exc.reason, file=str(path), field=exc.field) from None
    return cfg, doc


def _plan(args: argparse.Namespace, cfg):
    from calib.design.drift_check import with_repeats
    from service.checks.plan import check_plan_for_bench, require_check_phases
    from service.cli._args import load_plan

    if args.plan is not None:
        plan = load_plan(args.plan, cfg, args.seed)
        require_check_phases(plan, args.plan)
        source = f"given: {args.plan}"
    else:
        cache = Path(args.plan_cache) if args.plan_cache else None
        plan, n_fit, source = check_plan_for_bench(cfg, args.max_seconds, cache, args.seed)
        source = f"{source} ({n_fit} fit poses)"
    if args.repeat is not None:
        plan = with_repeats(plan, args.repeat)
        source += f", each fit pose visited {args.repeat} times"
    return plan, source


def _run(args: argparse.Namespace) -> int:
    from calib.design.motion import plan_motion_time
    from calib.formats.camera import CameraModel
    from calib.formats.plan import validate_plan
    from service import __version__
    from service.checks.run import CheckSettings, predicted_check_std, run_check
    from service.cli._output import make_console
    from service.design import motion_spec
    from service.export import dumps
    from service.timefmt import iso_utc

    cfg, in_force = _inputs(args)
    camera = CameraModel.load(args.camera) if args.camera else None
    err = make_console(stderr=True)
    with err.status("the check plan") if not args.no_progress else _Null():
        plan, plan_source = _plan(args, cfg)
    validate_plan(plan, cfg.nominal_parameters(), cfg.calib_limits())  # before any motion
    predicted = predicted_check_std(cfg, plan)
    motion_s = float(plan_motion_time(plan, motion_spec(cfg), cfg.nominal_parameters())["total_s"])
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="i4cal-check-"))

    def on_progress(p) -> None:
        if not args.no_progress and p.state in ("paused", "failed", "aborted") and p.message:
            err.print(f"[yellow]{p.state}[/]: {p.message}")

    with err.status("checking: acquiring, extracting, fitting") if not args.no_progress else _Null():
        outcome = asyncio.run(
            run_check(
                cfg,
                plan,
                in_force,
                out,
                CheckSettings(alpha=args.alpha),
                camera=camera,
                progress=on_progress,
                software_version=__version__,
                now=lambda: iso_utc(datetime.now(UTC)),
            )
        )
    outcome.predicted_std_m = predicted
    outcome.plan = {"source": plan_source, "frames": len(plan.steps), "motion_time_s": motion_s, **plan.count()}
    outcome.calibration = {"file": str(Path(args.calibration).resolve()), "run": in_force.run, "date": in_force.date}
    doc = outcome.to_dict()
    if args.update_out and outcome.update_document is not None:
        from calib.identify.export import CalibrationDocument

        fmt = "yaml" if Path(args.update_out).suffix.lower() in (".yaml", ".yml") else "json"
        Path(args.update_out).write_text(
            dumps(CalibrationDocument.model_validate(outcome.update_document), fmt), encoding="utf-8"
        )
        doc["update"]["file"] = str(Path(args.update_out).resolve())
    doc["alpha"] = args.alpha
    doc["next"] = _next(args, outcome)
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
    else:
        _print(doc, make_console())
    return EXIT[outcome.verdict]


def _next(args: argparse.Namespace, outcome) -> str:
    """The command to run next, in words."""
    base = f"i4cal check --bench {args.bench}"
    if outcome.verdict == "holds":
        return f"nothing to do; check again later: {base} --calibration {args.calibration}"
    if outcome.verdict == "inconclusive":
        return f"check again (longer: --max-seconds {2 * args.max_seconds:g}) or run a full calibration"
    if outcome.update.get("accepted"):
        if args.update_out:
            return f"load {args.update_out} into the controller, then confirm: {base} --calibration {args.update_out}"
        return f"write the proposed update: {base} --calibration {args.calibration} --update-out NEW.json"
    return f"run a full calibration (i4cal acquire --bench {args.bench} --plan full; i4cal calibrate): the update " + (
        f"was refused: {outcome.update.get('reason')}"
    )


def _print(doc: dict, con) -> None:
    from rich.table import Table

    from calib.model.parameters import COMBINATION_NAMES

    colour = {"holds": "green", "drifted": "red", "inconclusive": "yellow"}[doc["verdict"]]
    named = ", ".join(doc["drifted"]) if doc["drifted"] else ""
    line = f"[bold {colour}]{doc['verdict']}[/]"
    if named:
        line += f": {named} moved"
    if doc["reasons"]:
        line += f" ({'; '.join(doc['reasons'])})"
    con.print(line)
    t = Table(title="change since the calibration in force (mm; ± one standard deviation)", title_justify="left")
    for c in ("combination", "change", "std", "|z|", "check's predicted std"):
        t.add_column(c, justify="left" if c == "combination" else "right")
    pred = doc.get("predicted_std_m") or {}
    for k in COMBINATION_NAMES:
        c = doc["changes"][k]
        mark = " *" if k in doc["drifted"] else ""
        t.add_row(
            k + mark,
            f"{c['change_m'] * 1e3:+.4f}",
            f"{c['std_m'] * 1e3:.4f}",
            f"{abs(c['z']):.2f}",
            "-" if k not in pred else f"{pred[k] * 1e3:.4f}",
        )
    con.print(t)
    con.print(
        f"drifted where |z| > {doc['threshold']:.2f} (false-alarm probability {doc['alpha']:g} when nothing moved)"
    )
    u = doc["update"]
    if u.get("accepted"):
        con.print(
            "update proposed: "
            + ", ".join(f"{k} {v * 1e3:.4f} mm" for k, v in u["combinations_m"].items())
            + (f" -> {u['file']}" if u.get("file") else "")
        )
    elif doc["verdict"] == "drifted":
        con.print(f"[red]update refused[/]: {u['reason']}")
    rp = doc.get("repeatability")
    if rp:

        def mm(v):
            return "-" if v is None else f"{v * 1e3:.4f} mm"

        con.print(
            f"revisits ({rp['poses']} poses, {rp['visits']} visits): repeatability {mm(rp['repeatability_m'])}, "
            f"measurement floor {mm(rp['measurement_floor_m'])}, the robot's own {mm(rp['robot_repeatability_m'])} "
            "(3-D RMS of the board's position)"
        )
        for o in rp["outliers"]:
            con.print(f"[yellow]outlier[/]: frame {o['frame']} (pose {o['pose']}) {o['deviation_m'] * 1e3:.4f} mm off")
    tm = doc["timing_s"]
    con.print(
        f"motion {doc['plan'].get('motion_time_s', 0):.1f} s planned, {tm.get('motion', 0):.1f} s measured, "
        f"acquisition {tm.get('acquisition', 0):.1f} s, "
        f"result {tm.get('result_after_last_frame', 0):.1f} s after the last frame; dataset {doc['dataset']}"
    )
    con.print(f"next: {doc['next']}")


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False
