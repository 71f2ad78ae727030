"""``i4cal bench accuracy``: a seeded Monte-Carlo study of the three methods on the image-level twin.

Every trial draws a true geometry around the nominal one (each of the seven parameters with the standard
deviation ``--spread-mm``; default the RMS of the twin's default truth's offsets from nominal, i.e. the few
millimetres that separate the paper's a priori and identified values, Table I), renders the study's plan on it
(``drivers.sim.rendered_dataset.simulate_dataset``: images, not numbers handed over), extracts the images with the
camera the study calibrated once from its own rendered camera phase (as a lab does), and calibrates them with
the three methods. Trials are fanned out over Dask (:mod:`service.fanout`: a local cluster of ``--workers``
processes, default all cores; ``--scheduler tcp://HOST:8786`` for a cluster of machines; ``--workers 1``: in this
process, without Dask), each in a temporary directory deleted afterwards; a trial's truth and seed come from the
study's seed and the trial's index alone, so the numbers are identical whatever the engine or worker count. A
failing method or trial is counted and reported with its error, never the end of the study.

Per method and combination: RMS error against the truth, mean reported standard deviation and their ratio
(honesty; target within 30%), the combined method's Cramer-Rao bound at the noise measured in each run and the
efficiency = bound RMS / error RMS (target >= 0.67 for the combined method); the RMS displacement gap on the
validation poses (the paper's Table II metric) against the a priori one. ``--sweep noise,poses`` adds sweeps
over the renderer's sensor noise (grey levels; the measured edge noise in px is reported) and over the number
of fit poses, ``--sweep lens`` over the rendered camera's lens (:data:`LENSES`, ``--sweep-lenses``: the
trials' images and camera phases rendered through it, the lens model chosen per trial as ``i4cal extract``
does), with ``--sweep-trials`` trials per point; trials with the same index share their truth and
seed across points (common random numbers), and identical trials are run once.

JSON (``--json PATH``, format ``i4cal.bench-accuracy/1``): ``command``, ``argv``, ``version``, ``machine``,
``options``, ``spread_m``, ``plans`` (frames per phase for each fit size), ``notes``, ``cameras`` (per noise
level: the calibrated camera, its reprojection RMS), ``study`` and ``sweeps.noise`` / ``sweeps.poses`` /
``sweeps.lens`` (lists) as points ``{"sweep", "value", "noise_sigma", "n_fit", "lens", "dist", "trials": [per-trial
records], "summary"}`` (``lens``/``dist``: None outside the lens sweep; a trial record's ``camera.lens_model`` is
the lens model its calibration chose),
``workers`` and ``engine`` (what ran the trials), ``elapsed_s`` (wall), ``cpu_s`` (CPU time of the cameras and
trials: divided by the cores, about the wall time
on an idle machine) and ``load_average`` at the start and end. Lengths in metres (``*_m``), gaps in mm
(``*_mm``), edge noise in px.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, Field, field_validator

from calib.errors import InputError
from i4cal.benchmarks._accuracy_report import print_accuracy, summarize
from i4cal.benchmarks._accuracy_trial import CameraTask, TrialTask, calibrate_camera, run_trial

if TYPE_CHECKING:
    from service.fanout import Fanout

FORMAT = "i4cal.bench-accuracy/1"
SWEEPS = ("noise", "poses", "lens")
#: Lenses of ``--sweep lens`` (OpenCV distortion vectors; the renderer's K): the twin's default lens with a
#: sixth-order term of each sign, OpenCV's rational model (about the default lens to fourth order, different
#: beyond) and a near-pinhole lens. ``k3=X`` names any k3 on the default lens.
LENSES: dict[str, tuple[float, ...]] = {
    "k3=0": (-0.30, 0.10, 4e-4, -3e-4, 0.0),
    "k3=-0.012": (-0.30, 0.10, 4e-4, -3e-4, -0.012),
    "k3=-0.01": (-0.30, 0.10, 4e-4, -3e-4, -0.01),
    "k3=+0.01": (-0.30, 0.10, 4e-4, -3e-4, 0.01),
    "rational": (-0.05, 0.02, 4e-4, -3e-4, 0.0, 0.25, 0.0, 0.0),
    "pinhole": (-0.01, 0.002, 1e-4, -1e-4, 0.0),
}


def lens_dist(name: str) -> tuple[float, ...]:
    """The distortion vector of a ``--sweep-lenses`` name (a key of :data:`LENSES` or ``k3=X``)."""
    if name in LENSES:
        return LENSES[name]
    if name.startswith("k3="):
        try:
            return (*LENSES["k3=0"][:4], float(name[3:]))
        except ValueError:
            pass
    raise ValueError(f"unknown lens {name!r}; lenses are {', '.join(LENSES)} or k3=VALUE")


#: The paper-sized plan (``calib.formats.plan.make_plan`` defaults): what a trial renders unless reduced.
PAPER = {"n_base": 10, "n_fit": 20, "n_lock": 5, "n_validation": 10}
QUICK: dict[str, Any] = {
    "trials": 3,
    "n_base": 6,
    "n_fit": 10,
    "n_lock": 3,
    "n_validation": 8,
    "sweep_trials": 2,
    "sweep_noise": [0.0, 4.0],
    "sweep_poses": [8, 12],
}

#: ``on_progress(description, done, total)`` over every task of the study (cameras and trials).
OnProgress = Callable[[str, int, int], None]


class AccuracyOptions(BaseModel):
    """What the study renders and how many times (defaults: the figures reported in the README)."""

    trials: int = Field(50, ge=0, description="trials of the main study (0: sweeps only)")
    seed: int = 0
    workers: int | None = Field(None, ge=1, description="processes (default: all cores; 1: in this process)")
    scheduler: str | None = Field(None, description="a Dask scheduler's address (tcp://HOST:8786); default local")
    spread_mm: float | None = Field(None, ge=0, description="std of each true parameter around nominal, mm")
    noise_sigma: float = Field(2.0, ge=0, description="renderer sensor noise, grey levels")
    n_base: int = Field(PAPER["n_base"], ge=3, description="rotation and translation frames (each)")
    n_fit: int = Field(PAPER["n_fit"], ge=4, description="fit poses")
    n_lock: int = Field(PAPER["n_lock"], ge=2, description="poses per locked actuator")
    n_validation: int = Field(PAPER["n_validation"], ge=2, description="validation poses")
    with_line: bool = Field(False, description="also render the 51-frame guided line")
    camera_views: int = Field(30, ge=5, description="board views of the camera phase")
    camera_poses: int = Field(5, ge=3, description="bench poses rendered with the camera phase")
    camera: str = Field(
        "per-trial",
        pattern="^(per-trial|calibrated|true)$",
        description="intrinsics used for extraction: calibrated in every trial from its own camera "
        "phase (its error is then sampled), once per noise level, or the true ones",
    )
    sweeps: list[str] = Field(default_factory=list)
    sweep_trials: int = Field(10, ge=1)
    sweep_noise: list[float] = Field(default_factory=lambda: [0.0, 1.0, 2.0, 4.0, 8.0])
    sweep_poses: list[int] = Field(default_factory=lambda: [8, 12, 20, 30])
    sweep_lenses: list[str] = Field(default_factory=lambda: ["k3=0", "k3=-0.012", "k3=+0.01", "rational", "pinhole"])
    quick: bool = False

    @field_validator("sweeps")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        bad = [s for s in v if s not in SWEEPS]
        if bad:
            raise ValueError(f"unknown sweep {bad[0]!r}; sweeps are {', '.join(SWEEPS)}")
        return [s for s in SWEEPS if s in v]

    @field_validator("sweep_noise")
    @classmethod
    def _noise(cls, v: list[float]) -> list[float]:
        if not v or min(v) < 0:
            raise ValueError("sweep noise levels must be >= 0 grey levels")
        return v

    @field_validator("sweep_lenses")
    @classmethod
    def _lenses(cls, v: list[str]) -> list[str]:
        if not v:
            raise ValueError("the lens sweep needs at least one lens")
        for name in v:
            lens_dist(name)
        return v

    @field_validator("sweep_poses")
    @classmethod
    def _poses(cls, v: list[int]) -> list[int]:
        if not v or min(v) < 4:
            raise ValueError("sweep pose counts must be >= 4")
        return v


# -- the study's design ----------------------------------------------------------------------------------------
def default_spread_m() -> float:
    """RMS over the seven parameters of the twin's default truth's offsets from nominal (metres, ~5.3 mm)."""
    import numpy as np

    from calib.model.parameters import NOMINAL
    from drivers.sim.twin import DEFAULT_TRUTH

    d = np.asarray(DEFAULT_TRUTH.vector()) - np.asarray(NOMINAL.vector())
    return float(np.sqrt(np.mean(d**2)))


def spread_m(opts: AccuracyOptions) -> float:
    return default_spread_m() if opts.spread_mm is None else opts.spread_mm * 1e-3


def draw_truth(seed: int, index: int, spread: float) -> list[float]:
    """The seven true parameters (metres) of trial ``index``: nominal + N(0, spread^2) each, seeded."""
    import numpy as np

    from calib.model.parameters import NOMINAL

    rng = np.random.default_rng(np.random.SeedSequence([seed, index, 1]))
    return (np.asarray(NOMINAL.vector()) + rng.normal(0.0, spread, 7)).tolist()


def trial_seed(seed: int, index: int) -> int:
    """Seed of trial ``index``'s rendered dataset."""
    import numpy as np

    return int(np.random.SeedSequence([seed, index, 2]).generate_state(1)[0])


def plan_steps(opts: AccuracyOptions, n_fit: int) -> list[dict[str, Any]]:
    """Steps a trial renders: the full plan (study seed) without its guided line unless ``with_line``."""
    from calib.formats.plan import make_plan
    from calib.model.parameters import NOMINAL

    plan = make_plan(
        "full",
        NOMINAL,
        seed=opts.seed,
        n_base=opts.n_base,
        n_fit=n_fit,
        n_lock=opts.n_lock,
        n_validation=opts.n_validation,
    )
    return [s.model_dump(exclude_none=True) for s in plan.steps if opts.with_line or s.phase != "line"]


def plan_counts(steps: list[dict[str, Any]]) -> dict[str, int]:
    from calib.formats.plan import Plan

    return Plan.model_validate({"name": "trial", "steps": steps}).count()


def plan_notes(opts: AccuracyOptions) -> list[str]:
    """How what each trial renders differs from the paper-sized plan (said in the output)."""
    out = []
    changed = [
        f"{k.removeprefix('n_')} {getattr(opts, k)} (paper {v})" for k, v in PAPER.items() if getattr(opts, k) != v
    ]
    if changed:
        out.append("each trial renders a reduced plan: " + ", ".join(changed))
    if not opts.with_line:
        out.append("the guided line (51 frames, straightness only) is not rendered (--with-line)")
    return out


class Point(BaseModel):
    """One study point: the main study or one value of a sweep."""

    sweep: str | None
    value: float | None
    noise_sigma: float
    n_fit: int
    n_trials: int
    lens: str | None = None

    def trial_keys(self) -> list[str]:
        return [trial_key(self.noise_sigma, self.n_fit, k, self.lens) for k in range(self.n_trials)]


def trial_key(noise_sigma: float, n_fit: int, index: int, lens: str | None = None) -> str:
    if lens is None:
        return f"noise={noise_sigma:g},fit={n_fit},k={index}"
    return f"noise={noise_sigma:g},fit={n_fit},lens={lens},k={index}"


def study_points(opts: AccuracyOptions) -> list[Point]:
    pts = [Point(sweep=None, value=None, noise_sigma=opts.noise_sigma, n_fit=opts.n_fit, n_trials=opts.trials)]
    if "noise" in opts.sweeps:
        pts += [
            Point(sweep="noise", value=v, noise_sigma=v, n_fit=opts.n_fit, n_trials=opts.sweep_trials)
            for v in opts.sweep_noise
        ]
    if "poses" in opts.sweeps:
        pts += [
            Point(sweep="poses", value=v, noise_sigma=opts.noise_sigma, n_fit=v, n_trials=opts.sweep_trials)
            for v in opts.sweep_poses
        ]
    if "lens" in opts.sweeps:
        pts += [
            Point(
                sweep="lens",
                value=float(i),
                noise_sigma=opts.noise_sigma,
                n_fit=opts.n_fit,
                n_trials=opts.sweep_trials,
                lens=name,
            )
            for i, name in enumerate(opts.sweep_lenses)
        ]
    return [p for p in pts if p.n_trials > 0]


# -- running -------------------------------------------------------------------------------------------------
def run_accuracy(opts: AccuracyOptions, on_progress: OnProgress | None = None) -> dict[str, Any]:
    """Run the study (cameras, then trials as soon as their camera is calibrated) and return the JSON document
    without ``command``/``argv`` (see the module docstring)."""
    from i4cal.benchmarks.speed import machine_info
    from service.fanout import Fanout, FanoutSettings

    t_start = time.perf_counter()
    load_start = _load()
    points = study_points(opts)
    if not points:
        raise InputError("nothing to run: --trials 0 and no --sweep", field="--trials")
    spread = spread_m(opts)
    fits = sorted({p.n_fit for p in points})
    steps = {n: plan_steps(opts, n) for n in fits}
    trials = trial_tasks(opts, points, steps, spread)
    noises = sorted({t.noise_sigma for t in trials.values()})
    cam_steps = [s for s in steps[fits[-1]] if s["phase"] == "rotation"][: opts.camera_poses]
    cam_tasks = (
        [
            CameraTask(noise_sigma=n, seed=trial_seed(opts.seed, 10**6), views=opts.camera_views, steps=cam_steps)
            for n in noises
        ]
        if opts.camera == "calibrated"
        else []
    )
    pool = Fanout(
        FanoutSettings(workers=opts.workers, scheduler=opts.scheduler), n_tasks=max(len(cam_tasks) + len(trials), 1)
    )
    records, cameras = _run_tasks(pool, opts.camera, trials, cam_tasks, on_progress)
    out_points: list[dict[str, Any]] = [
        {
            "sweep": p.sweep,
            "value": p.value,
            "noise_sigma": p.noise_sigma,
            "n_fit": p.n_fit,
            "lens": p.lens,
            "dist": list(lens_dist(p.lens)) if p.lens is not None else None,
            "trials": [records[k] for k in p.trial_keys()],
        }
        for p in points
    ]
    for p in out_points:
        p["summary"] = summarize(p["trials"])
    study = next((p for p in out_points if p["sweep"] is None), None)
    return {
        "format": FORMAT,
        "version": _version(),
        "machine": machine_info(),
        "options": opts.model_dump(),
        "workers": pool.workers,
        "engine": pool.description,
        "spread_m": spread,
        "plans": {str(n): plan_counts(s) for n, s in steps.items()},
        "notes": plan_notes(opts),
        "cameras": cameras,
        "study": study,
        "sweeps": {s: [p for p in out_points if p["sweep"] == s] for s in opts.sweeps},
        "elapsed_s": time.perf_counter() - t_start,
        "cpu_s": sum(r.get("cpu_s") or 0.0 for r in [*records.values(), *cameras.values()]),
        "load_average": {"start": load_start, "end": _load()},
    }


def trial_tasks(
    opts: AccuracyOptions, points: list[Point], steps: dict[int, list[dict[str, Any]]], spread: float
) -> dict[str, TrialTask]:
    """The distinct trials of the study's points by key (trials shared by several points run once); no camera yet."""
    trials: dict[str, TrialTask] = {}
    for p in points:
        for k, key in enumerate(p.trial_keys()):
            if key not in trials:
                trials[key] = TrialTask(
                    key=key,
                    index=k,
                    seed=trial_seed(opts.seed, k),
                    truth=draw_truth(opts.seed, k, spread),
                    noise_sigma=p.noise_sigma,
                    steps=steps[p.n_fit],
                    camera=None,
                    camera_views=opts.camera_views if opts.camera == "per-trial" else 0,
                    dist=list(lens_dist(p.lens)) if p.lens is not None else None,
                    lens=p.lens,
                )
    return trials


def _run_tasks(
    pool: Fanout,
    camera: str,
    trials: dict[str, TrialTask],
    cam_tasks: list[CameraTask],
    on_progress: OnProgress | None,
) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    """Run the cameras, then each trial as soon as its camera is ready, on ``pool``; the trials' records by key and
    the cameras by noise level."""
    total = len(cam_tasks) + len(trials)
    cameras: dict[str, Any] = {}
    records: dict[str, dict[str, Any]] = {}
    running: dict[Future, tuple[str, Any]] = {}
    done = 0

    def camera_ready(noise: float, cam: dict[str, Any]) -> None:
        nonlocal done
        cameras[f"{noise:g}"] = cam
        for t in trials.values():
            if t.noise_sigma != noise:
                continue
            if cam.get("camera") is None:
                records[t.key] = _failed(t, f"camera calibration failed: {cam.get('error')}")
                done += 1
            else:
                running[pool.submit(run_trial, t.model_copy(update={"camera": cam["camera"]}))] = ("trial", t)

    if on_progress:
        on_progress(f"calibrating the camera ({len(cam_tasks)} camera phase(s))" if cam_tasks else "trials", 0, total)
    with pool:
        if camera == "true":
            for n in sorted({t.noise_sigma for t in trials.values()}):
                camera_ready(n, true_camera(n))
        elif camera == "per-trial":
            for t in trials.values():
                running[pool.submit(run_trial, t)] = ("trial", t)
        for c in cam_tasks:
            running[pool.submit(calibrate_camera, c)] = ("camera", c)
        while running:
            for fut in pool.next_done(list(running)):
                kind, task = running.pop(fut)
                done += 1
                if kind == "camera":
                    camera_ready(task.noise_sigma, _camera_result(fut, task))
                else:
                    records[task.key] = _trial_result(fut, task)
                if on_progress:
                    on_progress(_finished(kind, task, records, cameras, pool), done, total)
    return records, cameras


def _finished(kind: str, task: Any, records: dict[str, Any], cameras: dict[str, Any], pool: Any) -> str:
    """The progress line of a finished task: which one, its error when it failed, where the study is."""
    if kind == "camera":
        cam = cameras.get(f"{task.noise_sigma:g}") or {}
        what = f"camera noise={task.noise_sigma:g}" + (f" FAILED: {cam['error']}" if cam.get("error") else "")
    else:
        err = records[task.key].get("error")
        what = task.key + (f" FAILED: {err}" if err else "")
    return f"{what} ({len(records)} trials done; {pool.description})"


def true_camera(noise_sigma: float) -> dict[str, Any]:
    """The renderer's own intrinsics (``--camera true``): the study without the camera calibration's error."""
    from drivers.sim.render import RenderSettings

    cam = RenderSettings(noise_sigma=noise_sigma).camera().to_dict()
    return {"noise_sigma": noise_sigma, "source": "true", "camera": cam, "true_camera": cam, "intrinsics": None}


def _load() -> list[float] | None:
    """1, 5 and 15-minute load averages (the machine is shared: the figures say how busy it was)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _version() -> str:
    from service import __version__

    return __version__


def _camera_result(fut: Future, task: CameraTask) -> dict[str, Any]:
    try:
        return fut.result()
    except Exception as exc:
        return {
            "noise_sigma": task.noise_sigma,
            "source": "calibrated",
            "camera": None,
            "error": f"{type(exc).__name__}: {exc}",
        }


def _failed(task: TrialTask, error: str) -> dict[str, Any]:
    return {
        "key": task.key,
        "index": task.index,
        "seed": task.seed,
        "noise_sigma": task.noise_sigma,
        "truth": None,
        "error": error,
        "methods": {},
    }


def _trial_result(fut: Future, task: TrialTask) -> dict[str, Any]:
    try:
        return fut.result()
    except Exception as exc:  # the worker died (run_trial itself never raises)
        return _failed(task, f"{type(exc).__name__}: {exc}")


# -- command line ------------------------------------------------------------------------------------------------
def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def register(subparsers: argparse._SubParsersAction) -> None:
    from service.fanout import add_arguments as fanout_arguments

    p = subparsers.add_parser(
        "accuracy",
        help="Monte-Carlo accuracy of the methods on the image-level twin (errors, bound, gaps)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    a = p.add_argument
    a("--trials", type=int, default=None, metavar="N", help="trials of the main study (default 50; 0: sweeps only)")
    a("--seed", type=int, default=None, help="seed of the whole study (default 0)")
    fanout_arguments(p)
    a("--json", metavar="PATH", default=None, help="also write every trial and the summaries as JSON")
    a("--quick", action="store_true", help="3 trials of a small plan; 2 trials per sweep point, 2 points (for tests)")
    a("--with-line", action="store_true", help="also render the guided line (51 frames per trial)")
    a(
        "--spread-mm",
        type=float,
        default=None,
        metavar="MM",
        help="std of each true parameter around nominal (default: the twin's default truth's offsets, RMS)",
    )
    a("--noise", type=float, default=None, metavar="GREY", help="renderer sensor noise, grey levels (default 2)")
    a("--base-poses", type=int, default=None, metavar="N", help="rotation and translation frames (default 10 each)")
    a("--fit-poses", type=int, default=None, metavar="N", help="fit poses (default 20)")
    a("--lock-poses", type=int, default=None, metavar="N", help="poses per locked actuator (default 5)")
    a("--validation-poses", type=int, default=None, metavar="N", help="validation poses (default 10)")
    a("--camera-views", type=int, default=None, metavar="N", help="board views of the camera phase (default 30)")
    a("--sweep", default=None, metavar="LIST", help=f"comma-separated sweeps to add: {','.join(SWEEPS)}")
    a("--sweep-trials", type=int, default=None, metavar="N", help="trials per sweep point (default 10)")
    a("--sweep-noise", type=_floats, default=None, metavar="LIST", help="grey levels (default 0,1,2,4,8)")
    a("--sweep-poses", type=_ints, default=None, metavar="LIST", help="fit pose counts (default 8,12,20,30)")
    a(
        "--sweep-lenses",
        type=_names,
        default=None,
        metavar="LIST",
        help=f"lenses of --sweep lens: {','.join(LENSES)} or k3=VALUE "
        "(default k3=0,k3=-0.012,k3=+0.01,rational,pinhole)",
    )
    a(
        "--camera",
        choices=("per-trial", "calibrated", "true"),
        default=None,
        help="intrinsics for extraction: calibrated in every trial from its own rendered camera phase (default: the "
        "camera calibration's error is sampled like the rest), calibrated once per noise level (one draw of "
        "that error shared by every trial), or the renderer's true ones (isolates the camera's share)",
    )
    a("--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler=run)


_ARGS = {
    "trials": "trials",
    "seed": "seed",
    "workers": "workers",
    "scheduler": "scheduler",
    "spread_mm": "spread_mm",
    "noise": "noise_sigma",
    "base_poses": "n_base",
    "fit_poses": "n_fit",
    "lock_poses": "n_lock",
    "validation_poses": "n_validation",
    "camera_views": "camera_views",
    "sweep_trials": "sweep_trials",
    "sweep_noise": "sweep_noise",
    "sweep_poses": "sweep_poses",
    "sweep_lenses": "sweep_lenses",
    "camera": "camera",
}


def options_from_args(args: argparse.Namespace) -> AccuracyOptions:
    """``--quick`` presets, then every option given explicitly."""
    from pydantic import ValidationError

    from service.fanout import settings_from

    kw: dict[str, Any] = dict(QUICK) if args.quick else {}
    kw.update({field: getattr(args, arg) for arg, field in _ARGS.items() if getattr(args, arg) is not None})
    kw["quick"] = bool(args.quick)
    kw["with_line"] = bool(args.with_line)
    if args.sweep:
        kw["sweeps"] = [s.strip().lower() for s in args.sweep.split(",") if s.strip()]
    settings_from(args.workers, args.scheduler)  # a bad --scheduler or --workers named before anything runs
    try:
        return AccuracyOptions(**kw)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = str(err["loc"][0]) if err["loc"] else ""
        arg = next((a for a, f in _ARGS.items() if f == field), "sweep" if field == "sweeps" else field)
        raise InputError(str(err["msg"]).removeprefix("Value error, "), field="--" + arg.replace("_", "-")) from None


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from calib.identify.pipeline import to_jsonable
    from calib.numerics.jsonio import write_json_atomic
    from service.fanout import progress_display

    opts = options_from_args(args)
    if args.quiet:
        doc = run_accuracy(opts)
    else:
        with progress_display("accuracy study") as shown:
            doc = run_accuracy(opts, shown)
    doc = {"command": command_line(opts), "argv": list(sys.argv), **doc}
    print_accuracy(doc)
    if args.json:
        write_json_atomic(args.json, to_jsonable(doc), indent=1)
        Console(stderr=True).print(f"wrote {args.json}")
    measured = [p for p in ([doc["study"]] if doc["study"] else []) + [q for ps in doc["sweeps"].values() for q in ps]]
    return 0 if any(p["summary"]["trials_failed"] < p["summary"]["trials"] for p in measured) else 1


def command_line(opts: AccuracyOptions) -> str:
    """The ``i4cal bench accuracy`` command that reproduces ``opts`` (every option that is not the default)."""
    default = AccuracyOptions(**(dict(QUICK, quick=True) if opts.quick else {}))
    parts = ["i4cal", "bench", "accuracy"] + (["--quick"] if opts.quick else [])
    for arg, field in _ARGS.items():
        v = getattr(opts, field)
        if v != getattr(default, field) and v is not None:
            text = (
                ",".join(x if isinstance(x, str) else f"{x:g}" for x in v)
                if isinstance(v, list)
                else v
                if isinstance(v, str)
                else f"{v:g}"
            )
            parts += [f"--{arg.replace('_', '-')}", text]
    if opts.with_line:
        parts.append("--with-line")
    if opts.sweeps:
        parts += ["--sweep", ",".join(opts.sweeps)]
    return " ".join(parts)
