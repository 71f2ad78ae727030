"""``i4cal bench design``: designed plans against the paper's plan at equal fit-pose counts, on the image-level twin.

For every fit-pose count (``--counts``, default 8,12,20,30) two plans: the paper's
(``calib.formats.plan.make_plan("full")``)
and a designed one (``calib.design.design_plan`` for the combined method on images: the image-level prediction with
:func:`service.design.twin_image_noise`, the twin's camera and mounting), designed to beat the paper's 20-pose plan
on every combination (criterion ``"target"``, the targets that plan's predicted std: what ``i4cal plan design
--better-than`` does; a D-optimal set traded H-D for the other three); both without the guided line. Each trial
renders the plan for a true geometry drawn around nominal (the accuracy benchmark's trials:
``i4cal.benchmarks.accuracy``, per-trial camera calibration, extraction, the three methods); trial k of every plan
shares its truth and seed (common random numbers).

Per plan and method: RMS error per combination, mean reported std, the std predicted before motion on images
(``predicted_images``: :mod:`calib.design.predict_images` with :func:`service.design.twin_image_noise`), at the
geometric twin's default noise (``predicted``) and at the noise measured in a run (``predicted_run``: the
prediction scaled per method and combination by the paper's 20-pose plan's measured RMS error over its
prediction, i.e. noise levels calibrated by one reference run), and the motion time (trapezoidal profiles,
``--speed``/``--accel``). The issue's check: the designed 12-pose plan's combined RMS error no larger than the
paper's 20-pose plan's for every combination, and each method's prediction within 30% of its RMS error.
``--plans designed-12,paper-20`` runs only those plans; each plan's ``steps`` are the plan itself (its frames, as
``calib.formats.plan.Step``), its ``trials`` list every trial's errors and
reported std per method (and whether the method fell back to its a priori values or its data left a direction to
the a priori tolerance); ``data_pinned`` has each method's RMS error and mean std over the other trials, with the
counts left out, and ``checks.predicted_images_over_rms_data_pinned`` the prediction's ratio to that RMS.

An RMS error over a few tens of trials is itself uncertain (over 50 trials of normal errors, 90% of the time within
-14% and +17% of the true one; heavier-tailed errors make it wider): each ratio of a prediction to an RMS error also
has its 90% bootstrap interval over the trials (``checks.predicted_images_over_rms_interval90``), and
``checks.prediction_within_30pct`` counts the predictions within 30% of their RMS error and lists the others with
their intervals, so that a miss can be told from the Monte-Carlo's own scatter (the table's last lines);
``checks.prediction_within_30pct_per_method`` gives each method's prediction scale, the geometric mean over its four
combinations of predicted / RMS error, with its interval. The
methods' own mean reported std is checked against the RMS error the same way (``checks.reported_std_within_30pct``,
``reported_std_over_rms_interval90``: is each method honest on this plan?), each one outside with its trials' mean
error and that mean's standard error, which tell a bias of the plan's poses from a spread the std misses; and against
the trials' spread about their mean (``checks.reported_std_within_30pct_of_spread``,
``reported_std_over_spread_interval90``): a std within its spread but not within its RMS error misses a bias alone.
``--json PATH`` writes everything (format ``i4cal.bench-design/1``); ``--report PATH`` prints the table and the
checks of a file written so (recomputed with this version), without running anything; with ``--repredict`` the
plans' predictions are recomputed too (the trials kept: a change to the prediction alone, checked in seconds).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

FORMAT = "i4cal.bench-design/1"
#: candidate poses for the designed plans: the exchange finds the workspace's informative extremes (L above all)
#: only among enough of them (designed-12, predicted combined L std: 0.109 mm from 300, 0.099 from 1000, 0.094 from
#: 3000; 30 s of design)
DEFAULT_CANDIDATES = 3000
#: independent draws of those candidates, each designed, the best kept (by the target criterion on the prediction):
#: one draw's exchange stops at a local optimum of its poses (seed 1, worst predicted ratio to the paper's 20: 0.795
#: from the seed's own 3000, 0.724 from another draw of 5000, while at seed 2 the other draw was worse, 0.719
#: against 0.657)
DEFAULT_DRAWS = 3
#: a prediction within this factor of the RMS error either way (1.3: the issue's 30%) counts as within
WITHIN_FACTOR = 1.3
#: bootstrap resamples of the trials for a ratio's interval (seeded: the same file gives the same intervals)
BOOTSTRAP_RESAMPLES = 4000
#: the designed plans' reference: the paper's plan with this many fit poses
REFERENCE_FIT_POSES = 20


def _plans(
    counts: list[int],
    seed: int,
    speed: float,
    accel: float,
    only: list[str] | None = None,
    candidates: int = DEFAULT_CANDIDATES,
    draws: int = 1,
    lock_frames: int = 5,
    design_methods: tuple[str, ...] = ("combined",),
    draws_runner: Any = None,
) -> dict[str, dict[str, Any]]:
    from calib.design import (
        DesignRequest,
        MotionSpec,
        design_plan,
        plan_motion_time,
        targets_from_plan,
    )
    from calib.formats.plan import Plan, make_plan
    from calib.model.parameters import NOMINAL
    from service.design import twin_image_noise, twin_scene

    scene = twin_scene()
    image_noise = twin_image_noise(seed=seed)
    motion = MotionSpec(speed_m_s=speed, accel_m_s2=accel)
    out: dict[str, dict[str, Any]] = {}

    def paper(n: int) -> Plan:
        plan = make_plan("full", NOMINAL, seed=seed, n_fit=n, n_lock=lock_frames)
        return Plan(name=f"paper-{n}", steps=[s for s in plan.steps if s.phase != "line"])

    # every designed plan is asked to beat the paper's 20-pose plan on every combination (the reference) of
    # every method it is designed for: the worst ratio of its predicted std to the paper's, minimised
    ref = paper(REFERENCE_FIT_POSES)
    targets = {m: targets_from_plan(ref, NOMINAL, scene, image_noise, method=m) for m in design_methods}
    # a plan designed for other methods too is named for them (designed-legs-12), apart from the combined-only one
    designed = "-".join(["designed", *(m for m in design_methods if m != "combined")])
    for n in counts:
        wanted = [k for k in ("paper", designed) if not only or f"{k}-{n}" in only]
        for kind in wanted:
            drawn = None
            if kind == "paper":
                plan = paper(n)
            else:
                request = DesignRequest(
                    n_fit=n,
                    with_line=False,
                    seed=seed,
                    n_candidates=candidates,
                    draws=draws,
                    criterion="target",
                    target_std_m=targets[design_methods[0]],
                    method_targets_m=tuple((m, t) for m, t in targets.items() if m != design_methods[0]),
                    methods=design_methods,
                    n_lock=lock_frames,
                )
                res = design_plan(NOMINAL, scene, request, motion=motion, noise=image_noise, draws_runner=draws_runner)
                plan, drawn = res.plan, res.candidates
            out[f"{kind}-{n}"] = {
                "kind": kind,
                "n_fit": n,
                **({"design_methods": list(design_methods)} if kind != "paper" else {}),
                "steps": [s.model_dump(exclude_none=True) for s in plan.steps],
                "counts": plan.count(),
                "motion_s": plan_motion_time(plan, motion, NOMINAL)["total_s"],
                **_predictions(plan, scene, image_noise),
                "candidates": drawn,
            }
    return out


def _predictions(plan: Any, scene: Any, image_noise: Any) -> dict[str, Any]:
    """A plan's predicted std per method (metres): with the geometric twin's noise (``predicted_std_m``) and on
    images (``predicted_images_std_m``)."""
    from calib.design import predict_plan
    from calib.model.parameters import NOMINAL

    return {
        "predicted_std_m": predict_plan(plan, NOMINAL, scene).std,
        "predicted_images_std_m": predict_plan(plan, NOMINAL, scene, image_noise).std,
    }


def repredict(doc: dict[str, Any]) -> dict[str, Any]:
    """``doc`` (a design bench) with every plan's predictions (``predicted_std_m``, ``predicted_images_std_m``)
    recomputed from its steps by the current prediction code, at the bench's seed, and its checks redone.

    The trials are kept as they are: a change to the prediction alone is checked against a saved bench in seconds,
    where running its trials again takes hours. ``repredicted`` records when and what the predictions were before.
    """
    from datetime import UTC, datetime

    from calib.formats.plan import Plan
    from service.design import twin_image_noise, twin_scene

    scene = twin_scene()
    image_noise = twin_image_noise(seed=int((doc.get("options") or {}).get("seed", 0)))
    before = {}
    for name, p in doc["plans"].items():
        before[name] = p.get("predicted_images_std_m")
        p.update(_predictions(Plan(name=name, steps=p["steps"]), scene, image_noise))
    doc["repredicted"] = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "image_noise": image_noise.to_dict(),
        "predicted_images_std_m_before": before,
    }
    doc["checks"] = _checks(doc["plans"])
    return doc


def run_design_bench(opts: argparse.Namespace, progress=None) -> dict[str, Any]:
    """Design the plans, then run every plan's trials, fanned out over Dask (:mod:`service.fanout`: ``opts.workers``
    local processes or ``opts.scheduler``; one worker: in this process); ``progress(description, done, total)`` as
    each trial (or design draw) finishes. A trial that fails is recorded with its error."""
    from service.fanout import Fanout, settings_from

    t0 = time.perf_counter()
    fan = Fanout(settings_from(getattr(opts, "workers", None), getattr(opts, "scheduler", None)))
    with fan:
        plans, records = _run_design_bench(opts, fan, progress)
    for name, p in plans.items():
        p["records"] = [records[f"{name},k={k}"] for k in _trial_indices(opts)]
    _summarize_plans(plans)
    from i4cal.benchmarks.speed import machine_info

    return {
        "format": FORMAT,
        "argv": list(sys.argv),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": machine_info(),
        "options": {k: v for k, v in vars(opts).items() if k != "handler"},
        "engine": fan.description,
        "plans": plans,
        "checks": _checks(plans),
        "elapsed_s": time.perf_counter() - t0,
    }


def _run_design_bench(
    opts: argparse.Namespace, fan: Any, progress: Any
) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, Any]]]:
    """:func:`run_design_bench`'s work on an open fan-out: the plans (their draws fanned out), then the trials."""
    from i4cal.benchmarks._accuracy_trial import TrialTask, run_trial
    from i4cal.benchmarks.accuracy import default_spread_m, draw_truth, trial_seed
    from service.fanout import finished_line

    def drawn(outcome: Any, done: int, total: int) -> None:
        if progress:
            progress(f"designing: {finished_line(outcome)} ({fan.description})", done, total)

    plans = _plans(
        opts.counts,
        opts.seed,
        opts.speed,
        opts.accel,
        opts.plans,
        opts.candidates,
        getattr(opts, "draws", 1),
        getattr(opts, "lock_frames", 5),
        tuple(getattr(opts, "design_methods", None) or ("combined",)),
        draws_runner=fan.index_runner(drawn),
    )
    spread = default_spread_m()
    tasks = [
        TrialTask(
            key=f"{name},k={k}",
            index=k,
            seed=trial_seed(opts.seed, k),
            truth=draw_truth(opts.seed, k, spread),
            noise_sigma=2.0,
            steps=p["steps"],
            camera=None,
            camera_views=30,
        )
        for name, p in plans.items()
        for k in _trial_indices(opts)
    ]

    def tell(outcome: Any, done: int, total: int) -> None:
        if progress:
            progress(f"{finished_line(outcome)} ({fan.description})", done, total)

    records: dict[str, dict[str, Any]] = {}
    for o in fan.map(run_trial, tasks, names=[t.key for t in tasks], on_done=tell):
        t = tasks[o.index]
        # run_trial records a failing method or extraction itself: an error here is a trial that raised or whose
        # worker died, counted and reported, never the end of the bench
        records[t.key] = o.value if o.ok else {"key": t.key, "index": t.index, "error": o.error_text(), "methods": {}}
    return plans, records


def _reduced_record(trial: dict[str, Any]) -> dict[str, Any]:
    """A trial record rebuilt from a bench's per-trial entry (each method's errors and std, no gaps or bounds)."""
    return {
        "index": trial.get("index"),
        "error": trial.get("error"),
        "methods": {m: {**r, "gap_validation_rms_mm": None} for m, r in (trial.get("methods") or {}).items()},
        **{k: trial[k] for k in ("rods_found", "rods_total", "extraction_recovered") if k in trial},
    }


def _trial_indices(opts: argparse.Namespace) -> range:
    """The trials a run renders: ``--trials`` of them from ``--first-trial`` (trial k's truth and seed depend on k
    and ``--seed`` alone, so runs of disjoint ranges merge into one: ``--report A.json B.json``)."""
    first = getattr(opts, "first_trial", 0) or 0
    return range(first, first + opts.trials)


def _summarize_plans(plans: dict[str, dict[str, Any]]) -> None:
    """From each plan's full trial ``records``: its ``summary``, per-trial ``trials`` (each method's errors and
    reported std, metres, to look at the tails), ``data_pinned`` and ``predicted_run_std_m``."""
    from i4cal.benchmarks._accuracy_report import COMBINATIONS, METHODS, summarize

    for p in plans.values():
        recs = p["records"]
        p["summary"] = summarize(recs)
        p["trials"] = [
            {
                "index": r.get("index"),
                "error": r.get("error"),
                "methods": {
                    m: {
                        f: x.get(f)
                        for f in ("ok", "errors", "std", "a_priori_fallback", "unpinned_directions", "noise_levels")
                    }
                    for m, x in (r.get("methods") or {}).items()
                },
                "camera_refined": ((r.get("camera") or {}).get("intrinsics") or {}).get("refined_against_covariance"),
                **{k: r[k] for k in ("rods_found", "rods_total", "extraction_recovered") if k in r},
            }
            for r in recs
        ]
        p["data_pinned"] = _data_pinned(p["trials"])
        p["camera_refined"] = camera_refined_summary(p["trials"])
    ref = plans.get("paper-20")
    for p in plans.values():
        p["predicted_run_std_m"] = {}
        for m in METHODS:
            pr = p["predicted_std_m"].get(m)
            if not pr or not ref or m not in ref["predicted_std_m"]:
                continue
            rms = ref["summary"]["methods"][m]["rms_error_m"]
            p["predicted_run_std_m"][m] = {
                c: (pr[c] * rms[c] / ref["predicted_std_m"][m][c]) if rms.get(c) else None for c in COMBINATIONS
            }


def merge_benches(docs: list[dict[str, Any]], names: list[str]) -> dict[str, Any]:
    """One design bench from runs at the same ``--seed``: a plan in several runs gets the trials of all of them
    (disjoint trial ranges, ``--first-trial``; the same poses), a plan in one run is taken as it is (``--plans``:
    the designed plans run apart from the paper's, say).

    A trial index of a plan in two runs, a plan whose poses differ between runs, or another seed is refused. The
    summaries and checks are recomputed over all the trials; a plan's predictions are those of the first run that
    holds it (the same poses give the same ones). A run written before the trials' full records were kept has only
    each method's errors and std per trial (``trials``): its trials count in every check and in the methods' RMS
    errors and mean std, not in the summaries' bounds, efficiencies, gaps or timings (``records_reduced`` lists such
    files). Each plan lists the files it came from (``sources``).

    Raises
    ------
    InputError
        Naming the file and what does not match.
    """
    import copy

    from calib.errors import InputError

    seed = (docs[0].get("options") or {}).get("seed")
    merged: dict[str, dict[str, Any]] = {}
    seen: dict[str, dict[int, str]] = {}
    reduced: list[str] = []
    for doc, path in zip(docs, names, strict=True):
        if (doc.get("options") or {}).get("seed") != seed:
            raise InputError(f"{path}: --seed {doc.get('options', {}).get('seed')} where {names[0]} has {seed}")
        for name, p in doc["plans"].items():
            p = copy.deepcopy(p)
            if "records" not in p:
                p["records"] = [_reduced_record(t) for t in p.get("trials") or []]
                if path not in reduced:
                    reduced.append(path)
            if name in merged:
                if p["steps"] != merged[name]["steps"]:
                    first = merged[name]["sources"][0]
                    raise InputError(f"{path}: plan {name}'s poses differ from those of {first}")
                merged[name]["records"] += p["records"]
                merged[name]["sources"].append(path)
            else:
                merged[name] = {**p, "sources": [path]}
                seen[name] = {}
            for r in p["records"]:
                k = int(r["index"])
                if k in seen[name]:
                    raise InputError(f"{path}: trial {k} of {name} is in {seen[name][k]} too")
                seen[name][k] = path
    for p in merged.values():
        p["records"] = sorted(p["records"], key=lambda r: int(r["index"]))
    _summarize_plans(merged)
    out = {k: v for k, v in docs[0].items() if k != "plans"}
    out.update(
        plans=merged,
        merged_from=list(names),
        records_reduced=reduced,
        elapsed_s=float(sum(d.get("elapsed_s", 0.0) for d in docs)),
        checks=_checks(merged),
    )
    return out


def _rms(v: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(v))))


def _ratios(pr: dict[str, Any], rms: dict[str, Any]) -> dict[str, float | None]:
    """Per combination, a predicted std over an RMS error (None where either is missing or zero)."""
    from i4cal.benchmarks._accuracy_report import COMBINATIONS

    return {c: (pr[c] / rms[c]) if pr.get(c) and rms.get(c) else None for c in COMBINATIONS}


def _min_trials(about_mean: bool) -> int:
    """The fewest errors a ratio's interval takes: 2 for an RMS, 3 for a spread (its jackknife leaves two)."""
    return 3 if about_mean else 2


def ratio_interval(
    predicted: float,
    errors: np.ndarray,
    level: float = 0.9,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = 0,
    about_mean: bool = False,
) -> tuple[float, float]:
    """Bootstrap interval (BCa, ``scipy.stats.bootstrap``) of ``predicted`` over the RMS of ``errors`` (over their
    sample standard deviation, the spread about their mean, with ``about_mean``).

    Over 50 trials of normal errors it holds the true ratio 87% of the time at ``level`` 0.9, and about 80% for
    errors with Student-t(5) tails (tests/i4cal/test_bench_design_summary.py): a resampling interval is a little
    short at this many trials, never long.

    Parameters
    ----------
    predicted : float
        A predicted standard deviation (m).
    errors : ndarray, shape (n,)
        The trials' errors (m), n >= 2.
    level : float
        Coverage asked of the interval.
    resamples, seed : int
        Bootstrap resamples and their seed (the same errors give the same interval).
    about_mean : bool
        Compare with the errors' spread about their mean (``ddof=1``) instead of their RMS.

    Returns
    -------
    (low, high) : tuple of float
    """
    from scipy.stats import bootstrap

    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    need = _min_trials(about_mean)
    if e.size < need or not np.all(np.isfinite(e)):
        raise ValueError(f"errors must be finite, shape (n,) with n >= {need}, got {e.size} value(s)")
    if not np.any(e):
        raise ValueError("errors are all zero: no RMS error to compare a prediction with")

    def rms(x: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.sqrt(np.mean(x**2, axis=axis))

    def spread(x: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.std(x, axis=axis, ddof=1)

    res = bootstrap(
        (e,),
        spread if about_mean else rms,
        confidence_level=level,
        n_resamples=resamples,
        method="BCa",
        rng=np.random.default_rng(seed),
    )
    ci = res.confidence_interval
    return float(predicted / ci.high), float(predicted / ci.low)


def _trial_errors(trials: list[dict[str, Any]], method: str, combination: str) -> np.ndarray:
    """The errors (m) of ``method`` on ``combination`` over the trials it succeeded in (the summary's RMS set)."""
    vals = []
    for t in trials:
        r = (t.get("methods") or {}).get(method) or {}
        v = (r.get("errors") or {}).get(combination)
        if r.get("ok") and v is not None:
            vals.append(float(v))
    return np.asarray(vals)


def _std_over_rms_intervals(
    plans: dict[str, dict[str, Any]], source: str = "predicted", about_mean: bool = False
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Per plan, method and combination, the 90% bootstrap interval of a std over the RMS error, and the count of
    those within :data:`WITHIN_FACTOR` of their RMS error with the others listed.

    ``about_mean``: over the trials' spread about their mean error instead (their sample std): a std within it
    but not within the RMS error misses only a bias common to the plan's trials.

    ``source``: ``"predicted"``, the plan's image prediction (``predicted_images_std_m``); ``"reported"``, the
    method's mean reported std over the same trials (``summary...mean_std_m``: is the method's own uncertainty
    honest on this plan?). Each one listed outside also has the trials' mean error and its standard error (m): an
    RMS error the std does not cover may be a bias common to the plan's trials (a systematic error of its poses).
    """
    from i4cal.benchmarks._accuracy_report import COMBINATIONS, METHODS

    intervals: dict[str, Any] = {}
    n, outside = 0, []
    for name, p in plans.items():
        intervals[name] = {}
        for m in METHODS:
            s = p["summary"]["methods"][m]
            pr = ((p.get("predicted_images_std_m") or {}).get(m) if source == "predicted" else s["mean_std_m"]) or {}
            rms = s["rms_error_m"]
            intervals[name][m] = {}
            for c in COMBINATIONS:
                e = _trial_errors(p.get("trials") or [], m, c)
                if not pr.get(c) or not rms.get(c) or e.size < _min_trials(about_mean):
                    intervals[name][m][c] = None
                    continue
                lo, hi = ratio_interval(pr[c], e, about_mean=about_mean)
                intervals[name][m][c] = [lo, hi]
                ratio = pr[c] / (float(np.std(e, ddof=1)) if about_mean else rms[c])
                n += 1
                if not 1.0 / WITHIN_FACTOR <= ratio <= WITHIN_FACTOR:
                    outside.append(
                        {
                            "plan": name,
                            "method": m,
                            "combination": c,
                            "ratio": ratio,
                            "interval90": [lo, hi],
                            "interval_reaches_within": bool(hi >= 1.0 / WITHIN_FACTOR and lo <= WITHIN_FACTOR),
                            "mean_error_m": float(np.mean(e)),
                            "mean_error_se_m": float(np.std(e, ddof=1) / np.sqrt(e.size)),
                        }
                    )
    summary = {
        "factor": WITHIN_FACTOR,
        "reference": "spread" if about_mean else "rms",
        "n": n,
        "within": n - len(outside),
        "outside": outside,
    }
    return intervals, summary


def camera_refined_summary(trials: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Over a plan's trials, the rods' refined camera against the covariance it reports (each trial's
    ``camera_refined``, :func:`._accuracy_trial.error_against_covariance`): ``n`` trials, the mean Mahalanobis
    distance per degree of freedom and the mean squared error over the variance along each principal direction,
    smallest variance first (``principal_z2_mean``, trials of the most common size only). Each is 1 when the
    covariance is right, within about ``expected_se`` = sqrt(2 / n) for a direction (sqrt(2 / (n dof)) for the
    distance). None when no trial recorded it (a bench file without ``camera_refined``, or a camera the rods did
    not refine)."""
    rows: list[dict[str, Any]] = [r for t in trials if (r := t.get("camera_refined")) and r.get("dof")]
    if not rows:
        return None
    dofs = [int(r["dof"]) for r in rows]
    dof = max(set(dofs), key=dofs.count)
    same = np.array([r["principal_z2"] for r in rows if int(r["dof"]) == dof], dtype=np.float64)
    n = len(rows)
    return {
        "n": n,
        "mahalanobis_per_dof_mean": float(np.mean([r["mahalanobis"] / r["dof"] for r in rows])),
        "dof": dof,
        "principal_z2_mean": same.mean(axis=0).tolist(),
        "expected_se": float(np.sqrt(2.0 / len(same))),
    }


def _data_pinned(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method, the RMS error and mean reported std (metres) over the trials whose estimate came from the data:
    a trial where the method fell back to the a priori values (its data contradicted them) or where its data knew a
    direction of the seven less well than the a priori tolerance (the rods of a leg hidden in most fit poses, say) is
    left out and counted: the method says so in a warning, with the tolerance in its std. A plan's predicted std is
    for runs whose data pin the estimate, as the plan was designed to."""
    from i4cal.benchmarks._accuracy_report import METHODS

    return {m: _data_pinned_method([t["methods"].get(m) or {} for t in trials]) for m in METHODS}


def _data_pinned_method(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`_data_pinned` for one method, from its record in each trial."""
    from i4cal.benchmarks._accuracy_report import COMBINATIONS

    ok = [r for r in rows if r.get("ok") and r.get("errors") and r.get("std")]
    kept = [r for r in ok if not r.get("a_priori_fallback") and not r.get("unpinned_directions")]
    entry: dict[str, Any] = {
        "n_trials": len(kept),
        "n_a_priori_fallback": sum(1 for r in ok if r.get("a_priori_fallback")),
        "n_unpinned": sum(1 for r in ok if r.get("unpinned_directions") and not r.get("a_priori_fallback")),
    }
    for key, field, stat in (("rms_error_m", "errors", _rms), ("mean_std_m", "std", np.mean)):
        vals = {c: [r[field][c] for r in kept if r[field].get(c) is not None] for c in COMBINATIONS}
        entry[key] = {c: float(stat(v)) if v else None for c, v in vals.items()}
    # the noise levels the method measured, mean over the same trials: what the prediction takes them as
    entry["noise_levels_mean"] = _noise_levels_mean([r.get("noise_levels") or {} for r in kept])
    return entry


def _noise_levels_mean(levels: list[dict[str, Any]]) -> dict[str, float | None]:
    """Each noise level's mean over the trials that measured it (None where none did), by name."""
    names = sorted({k for lv in levels for k in lv})
    return {k: float(np.mean(v)) if (v := [lv[k] for lv in levels if lv.get(k) is not None]) else None for k in names}


def _checks(plans: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The design bench's checks on its plans: designed plans against the paper's 20 poses, the predictions and the
    reported std against the RMS errors (ratios, intervals and counts within)."""
    out: dict[str, Any] = _not_worse_checks(plans)
    out.update(_prediction_ratios(plans))
    if all("trials" in p and "summary" in p for p in plans.values()):
        out["predicted_images_over_rms_interval90"], out["prediction_within_30pct"] = _std_over_rms_intervals(plans)
        out["reported_std_over_rms_interval90"], out["reported_std_within_30pct"] = _std_over_rms_intervals(
            plans, "reported"
        )
        out["reported_std_over_spread_interval90"], out["reported_std_within_30pct_of_spread"] = (
            _std_over_rms_intervals(plans, "reported", about_mean=True)
        )
        out["prediction_within_30pct_per_method"] = _per_method_within(plans)
    return out


def _not_worse(a: dict[str, Any], b: dict[str, Any]) -> dict[str, bool | None]:
    """Per combination, whether the RMS error ``a`` is at most ``b`` (None where either is missing)."""
    from i4cal.benchmarks._accuracy_report import COMBINATIONS

    return {c: (a[c] <= b[c]) if a.get(c) is not None and b.get(c) is not None else None for c in COMBINATIONS}


def _not_worse_checks(plans: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The designed 12-pose plans' RMS errors against the paper's 20-pose plan's: the combined method's for
    ``designed-12``, then each plan designed for other methods on each of its methods."""
    out: dict[str, Any] = {}
    d12, p20 = plans.get("designed-12"), plans.get("paper-20")
    if d12 and p20:
        out["designed12_combined_not_worse_than_paper20"] = _not_worse(
            d12["summary"]["methods"]["combined"]["rms_error_m"], p20["summary"]["methods"]["combined"]["rms_error_m"]
        )
    for name, p in plans.items():  # plans designed for other methods too: each of them against the paper's 20
        if p20 and p.get("n_fit") == 12 and name != "designed-12" and p.get("design_methods"):
            out[f"{name}_not_worse_than_paper20"] = {
                m: _not_worse(p["summary"]["methods"][m]["rms_error_m"], p20["summary"]["methods"][m]["rms_error_m"])
                for m in p["design_methods"]
            }
    return out


def _prediction_ratios(plans: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per plan and method, the predicted std over the RMS error or the mean reported std, per combination."""
    from i4cal.benchmarks._accuracy_report import METHODS

    out: dict[str, Any] = {}
    for key, field, ref in (
        ("predicted_over_rms", "predicted_std_m", "rms_error_m"),
        ("predicted_images_over_rms", "predicted_images_std_m", "rms_error_m"),
        ("predicted_images_over_mean_std", "predicted_images_std_m", "mean_std_m"),
    ):
        out[key] = {
            name: {m: _ratios(p.get(field, {}).get(m) or {}, p["summary"]["methods"][m][ref]) for m in METHODS}
            for name, p in plans.items()
        }
    out["predicted_images_over_rms_data_pinned"] = {
        name: {
            m: _ratios(p.get("predicted_images_std_m", {}).get(m) or {}, p["data_pinned"][m]["rms_error_m"])
            for m in METHODS
            if "data_pinned" in p
        }
        for name, p in plans.items()
    }
    return out


def _per_method_within(plans: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per plan and method, the image prediction's scale over the RMS error: the geometric mean over the method's
    four combinations of predicted std / RMS error (each combination counts alike, whatever its size), with its 90%
    bootstrap interval (BCa, the trials resampled together for the four), and the count within
    :data:`WITHIN_FACTOR`. A method whose prediction is right in scale but off on one combination (a bias of the
    plan's poses there) is within here and listed in ``prediction_within_30pct``."""
    from scipy.stats import bootstrap

    from i4cal.benchmarks._accuracy_report import COMBINATIONS, METHODS

    ratios: dict[str, Any] = {}
    n, outside = 0, []
    for name, p in plans.items():
        ratios[name] = {}
        for m in METHODS:
            pr = (p.get("predicted_images_std_m") or {}).get(m) or {}
            cols = [_trial_errors(p.get("trials") or [], m, c) for c in COMBINATIONS]
            if not all(pr.get(c) for c in COMBINATIONS) or len({e.size for e in cols}) != 1 or cols[0].size < 2:
                ratios[name][m] = None
                continue
            E = np.stack(cols)  # (4, n): the trials the method succeeded in have all four
            if not np.all(np.any(E, axis=1)):
                ratios[name][m] = None
                continue
            logp = np.log([pr[c] for c in COMBINATIONS])

            def scale(*e: np.ndarray, axis: int = -1, logp: np.ndarray = logp) -> np.ndarray:
                rms = np.sqrt(np.mean(np.square(np.stack(e)), axis=axis))
                return np.exp(np.mean(logp.reshape((4,) + (1,) * (rms.ndim - 1)) - np.log(rms), axis=0))

            ratio = float(scale(*E))
            ci = bootstrap(
                tuple(E),
                scale,
                paired=True,
                confidence_level=0.9,
                n_resamples=BOOTSTRAP_RESAMPLES,
                method="BCa",
                rng=np.random.default_rng(0),
            ).confidence_interval
            ratios[name][m] = {"ratio": ratio, "interval90": [float(ci.low), float(ci.high)]}
            n += 1
            if not 1.0 / WITHIN_FACTOR <= ratio <= WITHIN_FACTOR:
                outside.append(
                    {"plan": name, "method": m, "ratio": ratio, "interval90": [float(ci.low), float(ci.high)]}
                )
    return {"factor": WITHIN_FACTOR, "n": n, "within": n - len(outside), "outside": outside, "ratios": ratios}


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v * 1e3:.3f}"


def print_table(doc: dict[str, Any]) -> None:
    """The design bench on the terminal: per plan and method the errors, std and predictions, then the checks."""
    _print_errors(doc["plans"])
    _print_data_pinned(doc["plans"])
    _print_noise_levels(doc["plans"])
    _print_cameras(doc["plans"])
    _print_checks(doc["checks"])
    print(f"elapsed {doc['elapsed_s']:.0f} s, {doc['date']}")


def _print_errors(plans: dict[str, Any]) -> None:
    """Per plan and method, per combination: RMS error / mean std / image prediction / prediction (mm)."""
    from i4cal.benchmarks._accuracy_report import COMBINATIONS, METHODS

    print(f"{'plan':<12} {'motion':>7} {'method':<13} " + " ".join(f"{c:>27}" for c in COMBINATIONS))
    print(f"{'':<12} {'min':>7} {'':<13} " + " ".join(f"{'rms / std / pred_img / pred':>27}" for _ in COMBINATIONS))
    for name, p in plans.items():
        for m in METHODS:
            s = p["summary"]["methods"][m]
            pr = p["predicted_std_m"].get(m, {})
            pri = p.get("predicted_images_std_m", {}).get(m, {})
            cells = [
                f"{_mm(s['rms_error_m'][c])}/{_mm(s['mean_std_m'][c])}/{_mm(pri.get(c))}/{_mm(pr.get(c))}"
                for c in COMBINATIONS
            ]
            print(
                f"{name:<12} {p['motion_s'] / 60:7.2f} {m:<13} "
                + " ".join(f"{x:>27}" for x in cells)
                + f"  ({s['n_ok']} ok)"
            )


def _print_data_pinned(plans: dict[str, Any]) -> None:
    """The trials left out of the data-pinned statistics (:func:`_data_pinned`), per plan and method."""
    from i4cal.benchmarks._accuracy_report import COMBINATIONS

    for name, p in plans.items():
        dp = p.get("data_pinned") or {}
        for m, e in dp.items():
            if e.get("n_a_priori_fallback") or e.get("n_unpinned"):
                print(
                    f"{name}: {m} fell back to its a priori values in {e['n_a_priori_fallback']} trial(s), its data "
                    f"left a direction to the a priori tolerance in {e['n_unpinned']}; over the other "
                    f"{e['n_trials']}: rms "
                    + ", ".join(_mm(e["rms_error_m"][c]) for c in COMBINATIONS)
                    + " mm; std "
                    + ", ".join(_mm(e["mean_std_m"][c]) for c in COMBINATIONS)
                    + " mm"
                )


def _print_noise_levels(plans: dict[str, Any]) -> None:
    """The noise levels the methods measured, mean per plan."""
    for name, p in plans.items():
        levels = {m: e.get("noise_levels_mean") for m, e in (p.get("data_pinned") or {}).items()}
        text = "; ".join(
            f"{m} " + ", ".join(f"{k} {v:.2f}" for k, v in lv.items() if v is not None)
            for m, lv in levels.items()
            if lv
        )
        if text:
            print(f"{name}: noise levels measured (mean): {text}")


def _print_cameras(plans: dict[str, Any]) -> None:
    """The rods' refined camera against its covariance (:func:`camera_refined_summary`), per plan."""
    for name, p in plans.items():
        cam = camera_refined_summary(p.get("trials") or [])
        if cam:
            print(
                f"{name}: the rods' refined camera against its covariance over {cam['n']} trials: Mahalanobis per "
                f"degree of freedom {cam['mahalanobis_per_dof_mean']:.2f}; per principal direction, smallest variance "
                "first: "
                + ", ".join(f"{v:.2f}" for v in cam["principal_z2_mean"])
                + f" (each 1 when it holds, +/- {cam['expected_se']:.2f})"
            )


def _print_checks(checks: dict[str, Any]) -> None:
    """The checks of :func:`_checks`: not worse than the paper's 20 poses, then the counts within."""
    print("checks:", checks.get("designed12_combined_not_worse_than_paper20"))
    for key, v in checks.items():
        if key.endswith("_not_worse_than_paper20") and key != "designed12_combined_not_worse_than_paper20":
            print(f"checks: {key}:", v)
    for key, what in (
        ("prediction_within_30pct", "image predictions"),
        ("reported_std_within_30pct", "the methods' mean reported std"),
        ("reported_std_within_30pct_of_spread", "the methods' mean reported std"),
    ):
        _print_within(checks.get(key), what)
    per = checks.get("prediction_within_30pct_per_method")
    if per and per["n"]:
        rs = [r["ratio"] for pm in per["ratios"].values() for r in pm.values() if r]
        print(
            f"image predictions per method (geometric mean over its four combinations of predicted / RMS error) within "
            f"{100 * (per['factor'] - 1):.0f}%: {per['within']} of {per['n']} ({min(rs):.2f}-{max(rs):.2f})"
        )
        for o in per["outside"]:
            lo, hi = o["interval90"]
            print(f"  {o['plan']} {o['method']}: {o['ratio']:.2f} ({lo:.2f}-{hi:.2f})")


def _print_within(within: dict[str, Any] | None, what: str) -> None:
    """One check of :func:`_std_over_rms_intervals`: the count within, then each one outside with its ratio's 90%
    interval over the trials (and, when recorded, the trials' mean error)."""
    if not within:
        return
    of = "their spread (the trials' std about their mean)" if within.get("reference") == "spread" else "the RMS error"
    print(
        f"{what} within {100 * (within['factor'] - 1):.0f}% of {of}: {within['within']} of {within['n']}"
        + (" (outside, with the ratio's 90% interval over the trials):" if within["outside"] else "")
    )
    for o in within["outside"]:
        lo, hi = o["interval90"]
        bias = ""
        if "mean_error_m" in o:
            bias = f", mean error {o['mean_error_m'] * 1e3:+.3f} +/- {o['mean_error_se_m'] * 1e3:.3f} mm"
        print(f"  {o['plan']} {o['method']} {o['combination']}: {o['ratio']:.2f} ({lo:.2f}-{hi:.2f}){bias}")


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def register(subparsers: argparse._SubParsersAction) -> None:
    from service.fanout import add_arguments as fanout_arguments

    p = subparsers.add_parser(
        "design",
        help="designed plans vs the paper's plan at equal fit-pose counts (image-level twin)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    a = p.add_argument
    a("--trials", type=int, default=5, help="trials per plan (default 5)")
    a(
        "--first-trial",
        type=int,
        default=0,
        help="index of the first trial (default 0): runs of disjoint ranges merge with --report A.json B.json",
    )
    a("--counts", type=_ints, default=[8, 12, 20, 30], help="fit-pose counts (default 8,12,20,30)")
    a("--seed", type=int, default=0)
    fanout_arguments(p, "trials and design draws")
    a("--speed", type=float, default=0.05, help="actuator speed for the motion time, m/s (a bench file's default)")
    a("--accel", type=float, default=0.5, help="acceleration, m/s^2")
    a(
        "--plans",
        type=lambda t: [x.strip() for x in t.split(",") if x.strip()],
        default=None,
        help="only these plans, e.g. designed-12,paper-20 (default: paper and designed at every count)",
    )
    a(
        "--candidates",
        type=int,
        default=DEFAULT_CANDIDATES,
        help=f"candidate poses the designed plans are chosen from (default {DEFAULT_CANDIDATES}; "
        "`i4cal plan design --candidates`)",
    )
    a(
        "--draws",
        type=int,
        default=DEFAULT_DRAWS,
        help=f"draws of the candidates for the designed plans, the best kept (default {DEFAULT_DRAWS}; "
        "`i4cal plan design --draws`)",
    )
    a(
        "--lock-frames",
        type=int,
        default=5,
        help="frames per lock phase of every plan, paper's and designed, 2-50 (default 5, the paper's; "
        "`i4cal plan design --lock-frames`): what the legs method's joints average over",
    )
    a(
        "--design-methods",
        type=lambda t: [x.strip() for x in t.split(",") if x.strip()],
        default=["combined"],
        help="methods the designed plans are designed for, each aimed at the paper's 20-pose plan's own predicted std "
        "(default combined; e.g. combined,legs: `i4cal plan design --methods`)",
    )
    a("--json", default=None, metavar="PATH")
    a(
        "--report",
        default=None,
        nargs="+",
        metavar="PATH",
        help="print the table and checks of a file written by --json (recomputed), without running anything; several "
        "files of disjoint trial ranges (--first-trial) are merged (and written to --json when given)",
    )
    a(
        "--repredict",
        action="store_true",
        help="with --report: recompute every plan's predictions with the current code (the trials kept) before the "
        "checks, and write the result to --json when given",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from calib.errors import InputError
    from calib.identify.pipeline import to_jsonable
    from calib.numerics.jsonio import write_json_atomic

    if args.report:
        import json
        from pathlib import Path

        paths = [args.report] if isinstance(args.report, str) else list(args.report)
        docs = []
        for path in paths:
            try:
                doc = json.loads(Path(path).read_text())
                if doc.get("format") != FORMAT:
                    raise InputError(f"{path}: not an {FORMAT} file (format {doc.get('format')!r})", field="--report")
                if len(paths) == 1:  # several are checked once, merged
                    doc["checks"] = _checks(doc["plans"])
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise InputError(f"{path}: cannot read a design bench: {exc}", field="--report") from exc
            docs.append(doc)
        if len(docs) == 1:
            doc = docs[0]
        else:
            try:
                doc = merge_benches(docs, paths)
            except InputError:
                raise
            except (ValueError, KeyError, TypeError) as exc:
                raise InputError(f"{', '.join(paths)}: cannot merge design benches: {exc}", field="--report") from exc
        if getattr(args, "repredict", False):
            doc = repredict(doc)
        print_table(doc)
        if (len(docs) > 1 or getattr(args, "repredict", False)) and getattr(args, "json", None):
            write_json_atomic(args.json, to_jsonable(doc), indent=1)
        return 0
    if args.trials < 1 or args.first_trial < 0 or not args.counts or min(args.counts) < 4:
        raise InputError("--trials >= 1, --first-trial >= 0 and fit-pose counts >= 4", field="--trials")
    if not 2 <= args.lock_frames <= 50:
        raise InputError(f"must be in 2..50, got {args.lock_frames}", field="--lock-frames")
    from service.fanout import progress_display, settings_from

    settings_from(args.workers, args.scheduler)  # a bad --workers or --scheduler named before the designs run
    with progress_display("design bench") as shown:
        doc = run_design_bench(args, shown)
    print_table(doc)
    if args.json:
        write_json_atomic(args.json, to_jsonable(doc), indent=1)
    return 0
