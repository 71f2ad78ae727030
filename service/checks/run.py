"""One check: the check plan acquired on the bench (the drivers' acquisition, the same motion safety as a run), its
frames extracted and fitted by the combined method (the pipeline of ``i4cal acquire`` + ``i4cal calibrate``), the
estimate tested against the calibration in force (:func:`calib.check.drift.check_drift`) and, where it drifted, the
update proposed (:func:`calib.check.drift.update_from_check`) or refused with the reason."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calib.model.parameters import COMBINATION_NAMES

#: the format of a check's JSON document (``i4cal check --json``, ``GET /api/v1/checks/{id}``)
CHECK_FORMAT = "i4cal.check/1"
#: the identification method a check fits (its estimate and covariance are tested)
CHECK_METHOD = "combined"


@dataclass(frozen=True)
class CheckSettings:
    """How a check decides.

    Attributes
    ----------
    alpha : float
        Family-wise false-alarm probability over the four combinations (:class:`calib.check.drift.DriftSettings`).
    max_check_std_m : float
        A combination the check pins worse than this (m) makes it inconclusive.
    """

    alpha: float = 0.05
    max_check_std_m: float = 1e-3

    def drift(self):
        from calib.check.drift import DriftSettings

        return DriftSettings(alpha=self.alpha, max_check_std_m=self.max_check_std_m)


@dataclass
class CheckOutcome:
    """What a check found (its JSON document: :meth:`to_dict`)."""

    verdict: str
    change_m: dict[str, float]
    change_std_m: dict[str, float]
    z: dict[str, float]
    threshold: float
    statistic: float
    drifted: tuple[str, ...]
    reasons: list[str]
    check_m: dict[str, float]
    check_std_m: dict[str, float]
    converged: bool
    update: dict[str, Any]
    predicted_std_m: dict[str, float] | None = None
    timing_s: dict[str, float] = field(default_factory=dict)
    dataset: str | None = None
    plan: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    #: the proposed update's ``i4cal.calibration/1`` document, when accepted
    update_document: dict[str, Any] | None = None
    #: with revisited poses (``--repeat``): :meth:`calib.check.repeatability.Repeatability.to_dict`
    repeatability: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The check's document: ``verdict``, ``drifted`` (combination -> ``{change_m, std_m}``), every
        combination's ``changes``, the update (or the refusal's reason), the check's predicted std."""
        return {
            "format": CHECK_FORMAT,
            "verdict": self.verdict,
            "drifted": {
                k: {"change_m": self.change_m[k], "std_m": self.change_std_m[k], "z": self.z[k]} for k in self.drifted
            },
            "changes": {
                k: {"change_m": self.change_m[k], "std_m": self.change_std_m[k], "z": self.z[k]}
                for k in COMBINATION_NAMES
            },
            "threshold": self.threshold,
            "statistic": self.statistic,
            "reasons": self.reasons,
            "check": {"method": CHECK_METHOD, "converged": self.converged, "combinations_m": self.check_m},
            "check_std_m": self.check_std_m,
            "predicted_std_m": self.predicted_std_m,
            "update": self.update,
            "timing_s": self.timing_s,
            "dataset": self.dataset,
            "plan": self.plan,
            "calibration": self.calibration,
            "repeatability": self.repeatability,
        }


def predicted_check_std(cfg, plan, camera=None) -> dict[str, float] | None:
    """The check plan's predicted combined std per combination (m): the prediction of ``plan predict`` (with
    ``camera``, else the bench file's camera file, else the simulated bench's camera)."""
    from service.design import check_for_bench

    intr = cfg.camera_intrinsics()
    camera = camera if camera is not None else (None if intr is None else intr.camera)
    check = check_for_bench(cfg, plan, None, ("combined",), camera)
    std = check.prediction.std.get(CHECK_METHOD)
    return None if std is None else {k: float(std[k]) for k in COMBINATION_NAMES}


async def acquire_check(
    cfg, plan, out: Path, progress: Callable[[Any], None] | None = None, camera_spec: dict[str, Any] | None = None
):
    """Acquire the check plan into ``out`` (a dataset v1 directory); the acquisition's result and its motion time
    (s: ``motion``, the moves from the first pose on, command to in position, and the settle times, not the grabs
    and writes; ``approach``, the move to the first pose). ``camera_spec``: what
    the dataset records of the camera (a service's camera file: ``service.runs.Bench.camera_spec``)."""
    from drivers.acquisition.acquire import acquisition_from_config, close_devices
    from drivers.acquisition.settings import DatasetHeader

    acq = acquisition_from_config(plan, cfg, out, progress=progress, header=DatasetHeader(camera=camera_spec or {}))
    try:
        res = await acq.run()
    finally:
        await close_devices(acq)
    # the motion as measured: each pose's move (command to in position) and its settle time, the approach to the
    # first pose (from wherever the robot was: home after a homing) apart
    moves = [moved - start for start, moved, _ in acq.timings]
    return res, {
        "approach": moves[0] if moves else 0.0,
        "motion": sum(moves[1:]) + acq.settings.settle_s * len(moves),
    }


def fit_check(dataset_dir: Path, camera=None) -> tuple[dict[str, Any], Any]:
    """The combined method's entry of the check's result document (extraction, then the fit), and the
    observations."""
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate, to_jsonable
    from calib.vision.extract import extract_dataset

    obs = Observations.from_dict(extract_dataset(dataset_dir, camera=camera).observations, source=str(dataset_dir))
    doc = to_jsonable(calibrate(obs, [CHECK_METHOD]))
    return doc["methods"][CHECK_METHOD], obs


def repeat_figures(obs, plan) -> dict[str, Any]:
    """Repeatability, measurement floor and outliers of a check plan with revisits (``with_repeats``): the board
    positions of the ``poses`` and ``validation`` frames grouped by the fit pose they were taken at."""
    import numpy as np

    from calib.check.repeatability import repeat_groups, repeatability

    poses_q = np.array([s.q for s in plan.steps if s.phase == "poses"])
    rows = [(i, f) for i, f in enumerate(obs.frames) if f.phase in ("poses", "validation") and f.board is not None]
    if not rows or not len(poses_q):
        return repeatability(np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, bool), np.zeros(0, int)).to_dict()
    idx = np.array([i for i, _ in rows])
    q = np.array([f.q for _, f in rows])
    t = np.array([f.board.t for _, f in rows])
    group = repeat_groups(q, poses_q)
    val = np.array([f.phase == "validation" for _, f in rows])
    still = np.zeros(len(rows), bool)
    for k in range(1, len(rows)):  # the second of two frames in a row at one pose (no motion between them)
        still[k] = val[k] and val[k - 1] and idx[k] == idx[k - 1] + 1 and group[k] == group[k - 1] and not still[k - 1]
    return repeatability(t, group, still, idx).to_dict()


def evaluate_check(
    entry: dict[str, Any], in_force_doc, settings: CheckSettings, *, software_version: str = "", date: str | None = None
) -> CheckOutcome:
    """Test the check's combined fit (``entry``, a result's method entry) against the calibration in force (an
    ``i4cal.calibration/1`` document) and propose the update."""
    import numpy as np

    from calib.check.drift import (
        CombinationEstimate,
        check_drift,
        in_force_estimate,
        update_from_check,
        updated_calibration,
    )

    prior = in_force_estimate(in_force_doc)
    converged = bool(entry.get("converged")) and entry.get("covariance") is not None
    if entry.get("combinations") and entry.get("covariance") is not None:
        check = CombinationEstimate.from_dicts(entry["combinations"], entry["covariance"], converged=converged)
    else:  # the fit failed: nothing to test
        check = CombinationEstimate(prior.value_m.copy(), np.eye(4), converged=False)
    ds = settings.drift()
    r = check_drift(prior, check, ds)
    if not converged and entry.get("error"):
        r.reasons.append(f"the fit: {entry['error']}")
    u = update_from_check(prior, check, r, ds)
    update: dict[str, Any] = {"accepted": u.accepted, "reason": u.reason, "reestimated": list(u.reestimated)}
    doc = None
    if u.accepted:
        update["combinations_m"] = {k: float(v) for k, v in zip(COMBINATION_NAMES, u.estimate.value_m, strict=True)}
        update["combinations_std_m"] = {k: float(v) for k, v in zip(COMBINATION_NAMES, u.estimate.std_m(), strict=True)}
        doc = updated_calibration(in_force_doc, u, software_version=software_version, date=date).model_dump(mode="json")
    elif r.verdict == "drifted":
        update["recommend"] = "a full calibration run"
    return CheckOutcome(
        verdict=r.verdict,
        change_m=r.change_m,
        change_std_m=r.change_std_m,
        z=r.z,
        threshold=float(r.threshold),
        statistic=r.statistic,
        drifted=r.drifted,
        reasons=r.reasons,
        check_m={k: float(v) for k, v in zip(COMBINATION_NAMES, check.value_m, strict=True)},
        check_std_m={k: float(v) for k, v in zip(COMBINATION_NAMES, check.std_m(), strict=True)},
        converged=converged,
        update=update,
        update_document=doc,
    )


def _cpu_s() -> float:
    """CPU time (s) of this process and its finished children (extraction's worker processes)."""
    import resource

    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


async def run_check(
    cfg,
    plan,
    in_force_doc,
    out: Path,
    settings: CheckSettings | None = None,
    *,
    camera=None,
    camera_spec: dict[str, Any] | None = None,
    progress: Callable[[Any], None] | None = None,
    software_version: str = "",
    now: Callable[[], str] | None = None,
) -> CheckOutcome:
    """Acquire, fit and test one check; its outcome with the timing (``acquisition``: the motion and frames,
    ``result_after_last_frame``: extraction, fit and test)."""
    import asyncio

    settings = settings or CheckSettings()
    t0 = time.monotonic()
    res, motion = await acquire_check(cfg, plan, out, progress, camera_spec)
    t1, c1 = time.monotonic(), _cpu_s()
    entry, obs = await asyncio.to_thread(fit_check, Path(res.path), camera)
    outcome = evaluate_check(
        entry, in_force_doc, settings, software_version=software_version, date=now() if now else None
    )
    if any(s.phase == "validation" for s in plan.steps):
        outcome.repeatability = repeat_figures(obs, plan)
    t2 = time.monotonic()
    outcome.timing_s = {
        "acquisition": t1 - t0,
        **motion,
        "result_after_last_frame": t2 - t1,
        "result_cpu": _cpu_s() - c1,
    }
    outcome.dataset = str(res.path)
    return outcome
