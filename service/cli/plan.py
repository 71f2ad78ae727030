"""``i4cal plan design`` and ``plan predict``: experiment design before motion (calib.design; docs/design.md)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

_CAMERA_HELP = (
    "the bench's own camera (i4cal.camera/1: intrinsics, lens, image size; e.g. the camera file of i4cal camera "
    "calibrate) in place of the simulated bench's, at its mounting: what is in view, and the image-level noise "
    "model; default: the bench file's [camera] intrinsics when it names one"
)


def _camera(path: str | None, cfg: Any = None):
    """``--camera``: the camera model of a camera file; without it, the bench file's own camera file (``[camera]
    intrinsics``, as ``acquire`` records it); else None (the simulated bench's camera), with a warning when the bench
    file names a camera file that does not exist yet."""
    from calib.formats.camera import CameraModel

    if path is not None:
        return CameraModel.load(path)
    if cfg is None or cfg.intrinsics_path() is None:
        return None
    if not cfg.intrinsics_path().exists():  # planning may come before the camera step: say so, predict anyway
        print(
            f"warning: the bench file's camera file {cfg.intrinsics_path()} does not exist yet: predicting with the "
            "simulated bench's camera (write it with `i4cal camera calibrate`, or give --camera FILE)",
            file=sys.stderr,
        )
        return None
    return cfg.camera_intrinsics().camera


def _warn_scene(cfg: Any, camera: Any) -> None:
    """On stderr, what of the camera the design takes from the simulated bench for want of the bench's own
    (``service.design.bench_scene``: the mounting, the intrinsics)."""
    from service.design import bench_scene

    for line in bench_scene(cfg, camera).warnings:
        print(f"warning: {line}", file=sys.stderr)


def register(subparsers: argparse._SubParsersAction) -> None:
    from service.fanout import add_arguments as fanout_arguments

    p = subparsers.add_parser("plan", help="plans: design one before motion (predicted accuracy, motion time)")
    sub = p.add_subparsers(dest="plan_command", metavar="SUBCOMMAND")
    d = sub.add_parser(
        "design",
        help="choose the fit poses and sweeps for a target accuracy and time; predict every method's std",
        description="Draws reachable, visible candidate poses, selects the fit poses (greedy + exchange) for the "
        "criterion, picks the sweeps' extents, orders the poses, and prints the plan's pose counts, the "
        "predicted std per method and combination (mm) and the motion time. Lengths: 0.05mm, 50um or metres.",
    )
    a = d.add_argument
    a("--bench", required=True, help="bench configuration (TOML): nominal geometry, soft limits, speeds")
    a("--target-std", default=None, help="wanted std of every combination (0.05mm, 50um, or metres)")
    a(
        "--better-than",
        default=None,
        metavar="PLAN",
        help="a plan file (i4cal.plan/1, e.g. the routine in use): the target is its predicted combined std on "
        "every combination (the shortest plan at least as accurate, or the most accurate relative to it with "
        "--n-fit)",
    )
    a("--max-minutes", type=float, default=None, help="longest motion time of the whole plan, minutes")
    a("--n-fit", type=int, default=None, help="fit poses (default: the smallest count meeting the target)")
    a("--criterion", choices=("d", "a", "target"), default=None, help="d (default), a, or target (worst std/target)")
    a(
        "--methods",
        default="combined",
        help="methods the selection optimises, any of combined,end-effector,legs (legs: its joints' gain and leg "
        "directions, with the image-level noise model; with --better-than each method aims at the plan's own std)",
    )
    a("--seed", type=int, default=0, help="seed of the candidate poses")
    a("--candidates", type=int, default=300, help="candidate poses drawn (default 300)")
    a(
        "--draws",
        type=int,
        default=1,
        help="independent draws of the candidates, each designed, the best kept (default 1; the exchange finds a "
        "local optimum of the poses drawn)",
    )
    fanout_arguments(d, "candidate draws (--draws 2 or more)")
    a("--no-line", action="store_true", help="leave out the guided line (straightness)")
    a(
        "--lock-frames",
        type=int,
        default=5,
        help="frames per lock phase, 2-50 (default 5): the legs method's joints; --breakdown says when they limit it",
    )
    a("--camera", default=None, metavar="FILE", help=_CAMERA_HELP)
    a(
        "--noise-from",
        default=None,
        help="JSON with the noise levels (an observations file's 'noise', or the keys "
        "of calib.design.DesignNoise); default: the image-level model of the simulated bench's camera",
    )
    a(
        "--breakdown",
        action="store_true",
        help="under each method, the std (mm) that each source of error contributes (which phase limits a "
        "combination: fit poses, lock phases, camera calibration); always in --json as prediction.parts_std_m",
    )
    a(
        "--tradeoff",
        default=None,
        metavar="COUNTS",
        help="e.g. 8,12,20,30: design a plan for each fit-pose count and print them side by side (predicted std per "
        "method and combination, motion time, the target's worst ratio), recommending the fewest poses that meet "
        "the target within --max-minutes (with --max-minutes alone: the most that fit in it); -o then writes that "
        "plan (not with --n-fit)",
    )
    a("--json", action="store_true", help="print the design summary as JSON")
    a("-o", "--out", default=None, help="write the plan (i4cal.plan/1) for i4cal acquire --plan / POST /api/v1/runs")
    d.set_defaults(handler=_design)
    c = sub.add_parser(
        "predict",
        help="what a plan you already have will buy: predicted std per method and combination, motion time, the "
        "steps the camera will not see",
        description="Predicts, before motion, each method's std per combination (mm) for a plan as it is (a plan "
        "name or an i4cal.plan/1 file, e.g. the routine in use), its motion time on the bench, and the steps whose "
        "board or rods the camera will not see (the prediction counts only what will be measured).",
    )
    c.add_argument("plan", metavar="PLAN", help="a plan name (full, pose-set, ...) or a plan JSON file")
    c.add_argument("--bench", required=True, help="bench configuration (TOML): nominal geometry, soft limits, speeds")
    c.add_argument("--seed", type=int, default=0, help="seed of a generated plan (a plan name)")
    c.add_argument(
        "--methods",
        default="combined,end-effector,legs",
        help="methods to predict, any of combined,end-effector,legs (default: all three)",
    )
    c.add_argument("--camera", default=None, metavar="FILE", help=_CAMERA_HELP)
    c.add_argument(
        "--noise-from",
        default=None,
        help="JSON with the noise levels (as plan design's); default: the image-level model of the simulated "
        "bench's camera",
    )
    c.add_argument("--breakdown", action="store_true", help="under each method, the std each source contributes")
    c.add_argument("--json", action="store_true", help="print the check as JSON (metres, seconds)")
    c.set_defaults(handler=_predict)
    p.set_defaults(handler=lambda args: (p.print_help(), 1)[1])


def _noise_from(path: str | None):
    """``--noise-from``: the noise levels of a JSON file (an observations file's ``noise`` or DesignNoise's keys)."""
    from calib.design import DesignNoise
    from calib.numerics.jsonio import read_json

    if not path:
        return None
    doc = read_json(path, "noise file")
    return DesignNoise.from_mapping(doc.get("noise", doc) if isinstance(doc, dict) else None)


def _methods(text: str, field: str) -> tuple[str, ...]:
    """A ``--methods`` list, each a method the design predicts."""
    from calib.design import METHODS
    from calib.errors import InputError

    methods = tuple(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise InputError(f"{', '.join(bad) or 'none given'}: methods are {', '.join(METHODS)}", field=field)
    return methods


def _predict(args: argparse.Namespace) -> int:
    from calib.formats.plan import validate_plan
    from calib.identify.pipeline import to_jsonable
    from drivers.acquisition.config import load_bench
    from service.cli._args import load_plan
    from service.design import check_for_bench, check_lines

    cfg = load_bench(args.bench)
    methods = _methods(args.methods, "--methods")
    plan = load_plan(args.plan, cfg, args.seed)
    validate_plan(plan, cfg.nominal_parameters(), cfg.calib_limits())
    camera = _camera(args.camera, cfg)
    _warn_scene(cfg, camera)
    check = check_for_bench(cfg, plan, _noise_from(args.noise_from), methods, camera)
    if args.json:
        print(json.dumps(to_jsonable(check.summary()), indent=1))
    else:
        print("\n".join(check_lines(check, breakdown=args.breakdown)))
    return 0


def _design(args: argparse.Namespace) -> int:
    from calib.design import DesignRequest
    from calib.errors import InputError
    from calib.formats.plan import Plan, validate_plan
    from calib.identify.pipeline import to_jsonable
    from calib.model.parameters import COMBINATION_NAMES
    from drivers.acquisition.config import load_bench
    from service.design import (
        better_than_request,
        design_for_bench,
        parse_length,
        reference_targets,
        summary_lines,
    )

    cfg = load_bench(args.bench)
    if args.target_std is not None and args.better_than is not None:
        raise InputError("give --target-std or --better-than, not both", field="--better-than")
    target = None if args.target_std is None else parse_length(args.target_std, "--target-std")
    if args.tradeoff is not None and args.n_fit is not None:
        raise InputError("give --tradeoff COUNTS or --n-fit, not both", field="--tradeoff")
    if not 2 <= args.lock_frames <= 50:
        raise InputError(f"must be in 2..50, got {args.lock_frames}", field="--lock-frames")
    if args.max_minutes is not None and not (0 < args.max_minutes < 1e5):
        raise InputError("must be > 0", field="--max-minutes")
    noise = _noise_from(args.noise_from)
    camera = _camera(args.camera, cfg)
    _warn_scene(cfg, camera)
    methods = tuple(dict.fromkeys(m.strip() for m in args.methods.split(",") if m.strip()))
    targets: dict[str, Any] = {"target_std_m": target}
    if args.better_than is not None:
        refs = reference_targets(cfg, Plan.load(args.better_than), noise, methods, camera)
        targets = better_than_request(refs)
        if not args.json:
            for m, ref in refs.items():
                print(
                    f"target: the predicted {m} std of {args.better_than}: "
                    + ", ".join(f"{k} {v * 1e3:.3f}" for k, v in zip(COMBINATION_NAMES, ref, strict=True))
                    + " mm"
                )
    req = DesignRequest(
        n_fit=args.n_fit,
        **targets,
        max_time_s=None if args.max_minutes is None else args.max_minutes * 60.0,
        criterion=args.criterion
        or ("target" if args.better_than is not None or (target is not None and args.n_fit is None) else "d"),
        methods=methods,
        seed=args.seed,
        n_candidates=args.candidates,
        draws=args.draws,
        with_line=not args.no_line,
        n_lock=args.lock_frames,
    )
    if args.tradeoff is not None:
        return _tradeoff(args, cfg, req, noise, camera)
    from service.cli._output import LongStep, make_console
    from service.fanout import Fanout, finished_line, settings_from

    settings = settings_from(args.workers, args.scheduler)
    # a design takes seconds to minutes (up to 200 fit poses, several candidate draws): say what it is doing, on a
    # terminal or not
    with LongStep(make_console(stderr=True), "designing the plan") as shown:
        if req.draws > 1:  # the draws are independent designs: fanned out (in this process with --workers 1)
            with Fanout(settings, n_tasks=req.draws) as fan:
                shown.update(f"{req.draws} candidate draws, {fan.description}")
                runner = fan.index_runner(lambda o, done, n: shown.update(f"{done}/{n} draws, {finished_line(o)}"))
                res = design_for_bench(cfg, req, noise, camera=camera, draws_runner=runner)
        else:
            res = design_for_bench(cfg, req, noise, status=lambda line: shown.update(line), camera=camera)
    validate_plan(res.plan, cfg.nominal_parameters(), cfg.calib_limits())
    if args.json:
        print(json.dumps(to_jsonable(res.summary()), indent=1))
    else:
        print("\n".join(summary_lines(res, breakdown=args.breakdown)))
    if args.out:
        res.plan.save(args.out)
        if not args.json:
            print(f"wrote {args.out}")
    return _warn_not_predicted(res.prediction.errors, args.n_fit)


def _warn_not_predicted(errors: dict[str, str], n_fit: int | None) -> int:
    """A method the designed plan cannot feed: a warning on stderr saying what it means and what to change, exit 1."""
    import sys

    if not errors:
        return 0
    for method, why in errors.items():
        why = why.removeprefix(f"{method}: ")
        print(
            f"warning: {method}: not predicted: {why}; a run of this plan gives {method} no result"
            + (f" (--n-fit {n_fit} is too few fit poses for it: give more, or leave --n-fit out)" if n_fit else ""),
            file=sys.stderr,
        )
    return 1


def _tradeoff(args: argparse.Namespace, cfg, req, noise, camera=None) -> int:
    """``plan design --tradeoff``: one design per count, printed side by side; ``-o`` writes the recommended one."""
    from calib.design import (
        parse_counts,
        recommendation_reason,
        recommended_count,
        recommended_design,
        tradeoff_trend,
    )
    from calib.errors import InputError
    from calib.formats.plan import validate_plan
    from calib.identify.pipeline import to_jsonable
    from service.cli._output import LongStep, make_console
    from service.design import tradeoff_for_bench, tradeoff_lines

    counts = parse_counts(args.tradeoff, "--tradeoff")
    with LongStep(make_console(stderr=True), "designing", total=len(counts)) as bar:
        rows, results = tradeoff_for_bench(
            cfg, req, counts, noise, progress=lambda done, tot: bar.update(done=done, total=tot), camera=camera
        )
    best = recommended_count(rows)
    if args.json:
        doc = {
            "tradeoff": [r.to_dict() for r in rows],
            "recommended_n_fit": best,
            "recommendation": recommendation_reason(rows),
            "methods": list(req.methods),
            "count_trend": tradeoff_trend(rows, req),
        }
        print(json.dumps(to_jsonable(doc), indent=1))
    else:
        print("\n".join(tradeoff_lines(rows, req)))
    if args.out:
        res = recommended_design(rows, results)
        if res is None:
            raise InputError(
                "no count of the trade-off qualifies (a target met within the time, or with a time limit alone one "
                "that fits in it; neither given: nothing to choose): nothing to write; pick a count and run with "
                "--n-fit N -o PLAN",
                field="--out",
            )
        validate_plan(res.plan, cfg.nominal_parameters(), cfg.calib_limits())
        res.plan.save(args.out)
        if not args.json:
            print(f"wrote {args.out} ({best} fit poses)")
    return 0
