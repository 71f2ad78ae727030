"""Plans: experiment design before motion (``POST /api/v1/plans/design``, ``/tradeoff``) and what a plan you have
will buy (``POST /api/v1/plans/predict``); calib.design, docs/design.md."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Request, status
from pydantic import BaseModel, ConfigDict, Field

from calib.design.tradeoff import MAX_TRADEOFF_COUNTS
from calib.errors import I4calError, InputError
from service.api.deps import Manager, RequestBody, SettingsDep, unprocessable
from service.auth import Writer
from service.jobs import JobError, PoolBusyError

router = APIRouter(prefix="/api/v1/plans", tags=["plans"])

PlanName = Literal["full", "rotation-sweep", "equal-translation", "pose-set", "lock-actuator", "line", "validation"]


def resolve_plan(spec: str | dict[str, Any] | None, manager: Any) -> Any:
    """The plan a request names (default ``full``, at this service's plan sizes) or holds inline, validated against
    the bench's soft limits and nominal model: the plan a run executes and a prediction is made for. Called in a
    worker thread: a plan at its size bounds (``calib.formats.plan.MAX_PLAN_FRAMES``) is checked without holding up the
    event loop.

    Raises
    ------
    HTTPException
        422 naming the field (e.g. ``["body", "plan", "steps", 3, "line", "samples"]``).
    """
    from calib.formats.plan import Plan, make_plan, validate_plan

    bench = manager.bench
    if bench is None:
        raise unprocessable(InputError("this service has no bench configured; upload a dataset instead", field="bench"))
    nominal = bench.config.nominal_parameters()
    try:
        if spec is None or isinstance(spec, str):
            sz = manager.settings.plan_sizes
            plan = make_plan(
                spec or "full",
                nominal,
                seed=sz.seed,
                n_base=sz.n_base,
                n_fit=sz.n_fit,
                n_lock=sz.n_lock,
                n_validation=sz.n_validation,
                line_samples=sz.line_samples,
                limits=bench.config.calib_limits(),
            )
        else:
            plan = Plan.from_dict(spec)
            if len(plan.steps) == 0:
                raise InputError("a plan needs at least one step", field="steps")
        validate_plan(plan, nominal, bench.config.calib_limits())
    except InputError as exc:
        raise unprocessable(exc, ("body", "plan")) from None
    return plan


class DesignBody(RequestBody):
    """What to design; every input bounded (a design takes seconds of CPU)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"target_std_m": 5e-5, "max_minutes": 10}, {"n_fit": 12, "criterion": "d"}]},
    )
    target_std_m: float | None = Field(None, gt=0, lt=0.1, description="wanted std of every combination, m")
    better_than: dict[str, Any] | None = Field(
        None,
        description="a reference plan (i4cal.plan/1, e.g. the routine in use): the target is its predicted combined "
        "std on every combination, the criterion 'target' (not with target_std_m)",
    )
    max_minutes: float | None = Field(None, gt=0, le=24 * 60, description="longest motion time of the plan")
    n_fit: int | None = Field(None, ge=2, le=100, description="fit poses (default: the smallest meeting the target)")
    criterion: Literal["d", "a", "target"] | None = Field(None, description="default: target with a target, else d")
    methods: list[Literal["combined", "end-effector", "legs"]] = Field(["combined"], min_length=1, max_length=3)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    candidates: int = Field(300, ge=20, le=1000, description="candidate poses drawn")
    draws: int = Field(1, ge=1, le=5, description="independent draws of the candidates, each designed, the best kept")
    with_line: bool = Field(True, description="include the guided line (straightness)")
    lock_frames: int = Field(
        5,
        ge=2,
        le=50,
        description="frames per lock phase (lock-1..4): the legs method's joints, its S and H-D (predicted_parts_std_m "
        "says when they limit it)",
    )


class PredictBody(RequestBody):
    """A plan to predict: a name (at this service's plan sizes, as a run would execute it) or an inline plan."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"plan": "full"}, {"plan": "full", "methods": ["combined", "legs"]}]},
    )
    plan: PlanName | dict[str, Any] | None = Field(
        None, description="a plan name, or an inline plan (i4cal.plan/1); default 'full'"
    )
    methods: list[Literal["combined", "end-effector", "legs"]] = Field(
        ["combined", "end-effector", "legs"], min_length=1, max_length=3
    )


class UnseenStep(BaseModel):
    step: int = Field(description="index of the step in the plan")
    phase: str
    board: bool = Field(description="the board wholly in view, its margin included (facing the camera)")
    board_corners: int = Field(
        description="the board's inner corners in the image (fewer than 6: no board pose, left out of the prediction)"
    )
    rods_hidden: list[str] = Field(description="rods ('leg.rod', from 1) shorter than the extraction's 40 px")


class PredictOut(BaseModel):
    plan: str = Field(description="plan name")
    counts: dict[str, int] = Field(description="frames per phase as planned")
    measured_counts: dict[str, int] = Field(
        description="frames per phase the prediction counts: the board phases without their steps out of view"
    )
    predicted_std_m: dict[str, dict[str, float]] = Field(description="per method and combination, metres")
    predicted_parts_std_m: dict[str, dict[str, dict[str, float]]] = Field(
        default_factory=dict, description="per method, the std (m) per combination each source of error contributes"
    )
    legs_seven_std_m: dict[str, float] | None
    prediction_errors: dict[str, str] = Field(description="methods the plan cannot feed, and why")
    motion_time_s: float
    motion_per_phase_s: dict[str, float]
    unseen: list[UnseenStep] = Field(description="steps the camera will not see in full")
    notes: list[str]


class CountTrendOut(BaseModel):
    """How the predicted std falls with the number of fit poses, fitted through two designed counts."""

    n_fit: list[int] = Field(description="the two fit-pose counts the trend was fitted from")
    floor_std_m: dict[str, dict[str, float]] = Field(
        description="per method and combination, the std (m) no number of such fit poses goes below"
    )
    n_fit_needed: int | None = Field(description="the fewest fit poses the trend says meet the target; null: none")


class DesignOut(BaseModel):
    plan: dict[str, Any] = Field(
        description="the plan (i4cal.plan/1, its 'design' field the summary): POST it to /api/v1/runs as an inline plan"
    )
    counts: dict[str, int] = Field(description="frames per phase")
    n_fit: int
    predicted_std_m: dict[str, dict[str, float]] = Field(description="per method and combination, metres")
    predicted_parts_std_m: dict[str, dict[str, dict[str, float]]] = Field(
        default_factory=dict,
        description="per method (end-effector, legs), the std (m) per combination each independent source of error "
        "contributes (their squares add up to predicted_std_m): which phase limits a combination",
    )
    legs_seven_std_m: dict[str, float] | None
    prediction_errors: dict[str, str]
    motion_time_s: float
    motion_per_phase_s: dict[str, float]
    sweeps: dict[str, float]
    target_met: bool | None
    time_met: bool | None
    notes: list[str]
    count_trend: CountTrendOut | None = Field(
        default=None,
        description="when the target is missed with the most fit poses the count search tries: how the predicted std "
        "falls with the count (var = floor + slope / N through two counts)",
    )


def _lock(request: Request, name: str = "design_lock") -> asyncio.Lock:
    """The app's lock ``name``: one design (or trade-off) at a time."""
    lock = getattr(request.app.state, name, None)
    if lock is None:
        lock = asyncio.Lock()
        setattr(request.app.state, name, lock)
    return lock


def busy(exc: PoolBusyError) -> HTTPException:
    """429 with Retry-After: the heavy-request pool's queue is full."""
    return HTTPException(
        status.HTTP_429_TOO_MANY_REQUESTS, detail=str(exc), headers={"Retry-After": str(exc.retry_after_s)}
    )


async def heavy(manager: Any, task: str, **kwargs: Any) -> Any:
    """``task`` (:data:`service.jobs.HEAVY_TASKS`) in the heavy-request pool (a child process, niced below the run);
    429 with Retry-After when its queue is full."""
    try:
        return await manager.heavy.run(task, **kwargs)
    except PoolBusyError as exc:
        raise busy(exc) from None


class TradeoffBody(DesignBody):
    """A design per fit-pose count (``n_fit`` is each of ``counts`` in turn); everything else as for a design."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"counts": [8, 12, 20, 30], "target_std_m": 5e-5, "max_minutes": 10}]},
    )
    counts: list[Annotated[int, Field(ge=2, le=100)]] = Field(
        min_length=1,
        max_length=MAX_TRADEOFF_COUNTS,
        description="fit-pose counts, each 2..100 (one full design each: seconds of CPU)",
    )
    n_fit: None = Field(None, description="not used: the counts are the trade-off's")


class TradeoffRowOut(BaseModel):
    n_fit: int
    motion_s: float = Field(description="motion time of the whole plan, seconds")
    predicted_std_m: dict[str, dict[str, float]] = Field(description="per method and combination, metres")
    worst_ratio_to_target: float | None = Field(description="largest predicted std of the optimised methods / target")
    target_met: bool | None
    time_met: bool | None


class TradeoffOut(BaseModel):
    rows: list[TradeoffRowOut] = Field(description="one designed plan per count, in increasing count")
    recommended_n_fit: int | None = Field(
        description="with a target, the fewest fit poses that meet it within max_minutes; with max_minutes alone, the "
        "most that fit in it (null: neither asked, or no count qualifies)"
    )
    recommendation: str = Field(description="why that count (or why none)")
    recommended_plan: dict[str, Any] | None = Field(
        description="that count's plan (i4cal.plan/1): POST it to /api/v1/runs as an inline plan"
    )
    notes: list[str]
    count_trend: CountTrendOut | None = Field(
        default=None,
        description="past the largest count: the trend of the optimised methods' predicted std through the two largest "
        "counts (the level each combination settles to, the count it says meets the target)",
    )


_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"description": "no or wrong bearer token"},
    422: {"description": "invalid request, or no bench configured: the field is named"},
    429: {
        "description": "another design is being computed, or the heavy requests' queue is full (Retry-After: "
        "seconds to wait)"
    },
}


def _design_request(body: DesignBody, targets: dict[str, Any], settings: Any) -> Any:
    from calib.design import DesignRequest

    return DesignRequest(
        n_fit=body.n_fit,
        **targets,
        max_time_s=None if body.max_minutes is None else body.max_minutes * 60.0,
        criterion=body.criterion
        or (
            "target"
            if body.better_than is not None or (targets["target_std_m"] is not None and body.n_fit is None)
            else "d"
        ),
        methods=tuple(dict.fromkeys(body.methods)),
        seed=body.seed,
        n_candidates=min(body.candidates, settings.design_max_candidates),
        draws=body.draws,
        n_lock=body.lock_frames,
        with_line=body.with_line,
    )


async def _designed(body: DesignBody, request: Request, manager: Any, settings: Any, task: str, **kwargs: Any) -> Any:
    """The heavy task ``task`` (``design`` or ``tradeoff``) for the body, in the heavy-request pool, one design at a
    time, and the ``DesignRequest`` the body became: the reference plan read and its targets predicted, input
    errors as 422 naming the field, 429 while another design runs or when the pool's queue is full."""
    from calib.formats.plan import Plan
    from service.design import better_than_request

    bench = manager.bench
    if bench is None:
        raise unprocessable(InputError("this service has no bench configured", field="bench"))
    ref = None
    if body.better_than is not None:
        if body.target_std_m is not None:
            raise unprocessable(InputError("give target_std_m or better_than, not both", field="better_than"))
        try:
            ref = Plan.from_dict(body.better_than, source="better_than")
        except InputError as exc:
            raise unprocessable(exc, prefix=("body", "better_than")) from None
    lock = _lock(request)
    if lock.locked():
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            detail="another design is being computed",
            headers={"Retry-After": str(manager.heavy.retry_after_s())},
        )
    async with lock:
        try:
            targets: dict[str, Any] = {"target_std_m": body.target_std_m}
            if ref is not None:
                methods = tuple(dict.fromkeys(body.methods))
                refs = await heavy(
                    manager, "reference", config=bench.config, plan=ref, methods=methods, camera=bench.camera_model
                )
                targets = better_than_request(refs)
            req = _design_request(body, targets, settings)
            res = await heavy(manager, task, config=bench.config, request=req, camera=bench.camera_model, **kwargs)
            return res, req
        except InputError as exc:
            raise unprocessable(exc) from None
        except JobError:
            raise  # the computation's process crashed: not the request's fault (500, in the log)
        except I4calError as exc:
            raise unprocessable(InputError(str(exc), field="plan")) from None


def _predicted(pred: Any, motion: dict[str, Any]) -> dict[str, Any]:
    """The prediction and motion-time fields a design and a plan's prediction answer alike."""
    return {
        "predicted_std_m": pred.std,
        "predicted_parts_std_m": pred.parts,
        "legs_seven_std_m": pred.legs_seven_std,
        "prediction_errors": pred.errors,
        "motion_time_s": motion["total_s"],
        "motion_per_phase_s": motion["per_phase_s"],
    }


def _capped(body: DesignBody, settings: Any) -> list[str]:
    if body.candidates > settings.design_max_candidates:
        return [f"candidates: {settings.design_max_candidates} drawn, the service's limit (asked {body.candidates})"]
    return []


@router.post("/design", response_model=DesignOut, responses=_ERRORS)
async def design(body: DesignBody, request: Request, manager: Manager, settings: SettingsDep, _: Writer) -> DesignOut:
    """Design a plan for this service's bench: fit poses, sweeps, order; predicted std and motion time.

    Computed in a child process niced below the run's, one design at a time (the run's processes keep their
    cores)."""
    res, _req = await _designed(body, request, manager, settings, "design")
    return DesignOut(
        plan=res.plan.model_dump(mode="json", exclude_none=True),
        counts=res.plan.count(),
        n_fit=res.n_fit,
        **_predicted(res.prediction, res.motion),
        sweeps=res.sweeps,
        target_met=res.target_met,
        time_met=res.time_met,
        notes=res.notes + _capped(body, settings),
        count_trend=res.count_trend,
    )


@router.post("/predict", response_model=PredictOut, responses=_ERRORS)
async def predict(body: PredictBody, manager: Manager, _: Writer) -> PredictOut:
    """What a plan will buy on this service's bench, before anything moves: each method's predicted std per
    combination, the motion time, the steps the camera will not see (the prediction counts only what will be
    measured). Computed in a child process niced below the run's, one heavy request at a time (429 with
    Retry-After when too many wait)."""
    plan = await asyncio.to_thread(resolve_plan, body.plan, manager)
    bench = manager.bench
    assert bench is not None  # resolve_plan refused a service without a bench (422)
    try:
        check = await heavy(
            manager,
            "predict",
            config=bench.config,
            plan=plan,
            methods=tuple(dict.fromkeys(body.methods)),
            camera=bench.camera_model,
        )
    except InputError as exc:
        raise unprocessable(exc, ("body", "plan")) from None
    except JobError:
        raise  # the computation's process crashed: not the request's fault (500, in the log)
    except I4calError as exc:
        raise unprocessable(InputError(str(exc), field="plan")) from None
    return PredictOut(
        plan=check.plan_name,
        counts=check.counts,
        measured_counts=check.measured_counts,
        **_predicted(check.prediction, check.motion),
        unseen=[UnseenStep(**u) for u in check.unseen],
        notes=check.notes,
    )


@router.post("/tradeoff", response_model=TradeoffOut, responses=_ERRORS)
async def tradeoff(
    body: TradeoffBody, request: Request, manager: Manager, settings: SettingsDep, _: Writer
) -> TradeoffOut:
    """Accuracy against bench time: a designed plan per fit-pose count, its predicted std and motion time, and the
    fewest poses that meet the target within the time (calib.design.design_tradeoff)."""
    from calib.design import (
        parse_counts,
        recommendation_reason,
        recommended_count,
        recommended_design,
        tradeoff_trend,
    )

    try:
        counts = parse_counts(body.counts)
        designs = len(counts) * body.draws
        if designs > settings.design_max_tradeoff_designs:
            raise InputError(
                f"at most {settings.design_max_tradeoff_designs} designs per trade-off on this service "
                f"(counts x draws = {len(counts)} x {body.draws})",
                field="counts",
            )
    except InputError as exc:
        raise unprocessable(exc, prefix=("body",)) from None
    (rows, results), asked = await _designed(body, request, manager, settings, "tradeoff", counts=counts)
    best = recommended_count(rows)
    chosen = recommended_design(rows, results)
    plan = None if chosen is None else chosen.plan
    return TradeoffOut(
        rows=[TradeoffRowOut(**r.to_dict()) for r in rows],
        recommended_n_fit=best,
        recommendation=recommendation_reason(rows),
        recommended_plan=None if plan is None else plan.model_dump(mode="json", exclude_none=True),
        notes=_capped(body, settings),
        # pydantic validates the trend's dict into CountTrendOut (the plugin's typed __init__ wants the model)
        count_trend=tradeoff_trend(rows, asked),  # type: ignore[arg-type]
    )
