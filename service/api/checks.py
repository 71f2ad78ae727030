"""Checks of the bench's calibration in force (docs/check.md): start one, list them, read one, apply its update."""

from __future__ import annotations

import asyncio
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request, status
from pydantic import BaseModel, Field

from calib.errors import InputError
from service.api.calibration import CalibrationOut, calibration_out, current_document
from service.api.deps import ID_PATTERN, Manager, RequestBody, conflict, not_found, unprocessable
from service.auth import Reader, Writer
from service.checks.manager import CheckManager, CheckNotFoundError
from service.runs import RunConflictError

router = APIRouter(prefix="/checks", tags=["checks"])
CheckId = Annotated[str, Path(pattern=ID_PATTERN, description="check id (32 hex digits)")]


def checks(request: Request) -> CheckManager:
    """The app's check manager (made on first use, beside the run manager)."""
    cm = getattr(request.app.state, "checks", None)
    if cm is None:
        cm = request.app.state.checks = CheckManager(request.app.state.manager)
    return cm


class CheckCreate(RequestBody):
    calibration: dict[str, Any] | None = Field(
        None,
        description="the calibration in force (i4cal.calibration/1); default: the bench's current calibration "
        "(GET /api/v1/calibration/current)",
    )
    plan: dict[str, Any] | None = Field(
        None,
        description="your own check plan (i4cal.plan/1 with phases rotation, translation, poses); default: designed "
        "for the bench within max_seconds and cached",
    )
    max_seconds: float = Field(60.0, gt=0, lt=1e5, description="motion budget of the designed check plan, s")
    alpha: float = Field(0.05, gt=0, lt=0.5, description="false-alarm probability when nothing drifted")
    repeat: int | None = Field(
        None,
        ge=2,
        le=20,
        description="revisit each fit pose this many times: repeatability, measurement floor, outliers "
        "(the document's repeatability)",
    )


class CheckOut(BaseModel):
    id: str
    state: str = Field(description="running, done or failed")
    verdict: str | None = Field(None, description="holds, drifted or inconclusive (when done)")
    created_at: datetime
    finished_at: datetime | None = None
    bench: str | None = None
    calibration_id: int | None = Field(None, description="the applied calibration tested (null: one given)")
    result: dict[str, Any] | None = Field(
        None, description="the check's document (i4cal.check/1): verdict, drifted, changes, update, predicted std"
    )
    update: dict[str, Any] | None = Field(None, description="the proposed update (i4cal.calibration/1), if any")
    applied_calibration_id: int | None = None
    error: str | None = None
    suspended: str | None = Field(
        None,
        description="why the running check holds the robot by itself (dark image, board unseen); null: it does not",
    )


def check_out(row, cm: CheckManager | None = None) -> CheckOut:
    return CheckOut(
        suspended=(cm.suspended.get(row.id) or None) if cm is not None else None,
        id=row.id,
        state=row.state,
        verdict=row.verdict,
        created_at=row.created_at,
        finished_at=row.finished_at,
        bench=row.bench,
        calibration_id=row.calibration_id,
        result=row.result,
        update=row.update,
        applied_calibration_id=row.applied_calibration_id,
        error=row.error,
    )


ERRORS: dict[int | str, dict[str, Any]] = {401: {"description": "no or wrong bearer token"}}


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=CheckOut,
    responses={
        **ERRORS,
        409: {"description": "a run or another check holds the bench, or no calibration to check"},
        422: {"description": "invalid request: the field is named"},
    },
)
async def create_check(body: CheckCreate, request: Request, manager: Manager, _: Writer) -> CheckOut:
    """Check the calibration in force: the plan validated before anything moves, then acquired, fitted, tested."""
    from calib.formats.plan import Plan
    from calib.identify.export import load_calibration
    from service.checks.run import CheckSettings

    cm = checks(request)
    busy = cm.holder()
    if busy is not None:  # said first: whatever else the request holds, the bench cannot be checked now
        raise conflict(f"{busy} holds the bench")
    cal_id = run_id = None
    try:
        if body.calibration is not None:
            in_force = load_calibration(body.calibration)
        else:
            cal = manager.current_calibration()
            if cal is None:
                raise conflict("no calibration applied to this bench: give one (calibration) or apply a run's")
            in_force = await asyncio.to_thread(current_document, manager, cal)
            cal_id, run_id = cal.id, cal.run_id
        plan = None if body.plan is None else Plan.from_dict(body.plan)
    except InputError as exc:
        prefix = ("body", "calibration") if body.calibration is not None and exc.frame is None else ("body", "plan")
        raise unprocessable(exc, prefix) from None
    try:
        cm.require_free_bench(in_force)
        plan, source = await asyncio.to_thread(cm.prepare_plan, plan, body.max_seconds, body.repeat)
        row = cm.create(
            in_force,
            calibration_id=cal_id,
            calibration_run_id=run_id,
            plan=plan,
            plan_source=source,
            settings=CheckSettings(alpha=body.alpha),
        )
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    except InputError as exc:
        raise unprocessable(exc) from None
    return check_out(row, cm)


@router.get("", response_model=list[CheckOut], responses=ERRORS)
async def list_checks(
    request: Request,
    _: Reader,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    bench: Annotated[str | None, Query(max_length=64)] = None,
) -> list[CheckOut]:
    """Every check, newest first (``bench``: only that bench's)."""
    cm = checks(request)
    return [check_out(r, cm) for r in cm.list(limit, offset, bench)]


@router.get("/schedule", responses=ERRORS)
async def check_schedule(request: Request, _: Reader) -> dict[str, Any]:
    """The scheduled checks (service setting ``check_schedule``): the schedule, when the next is due, a check
    deferred while a run holds the bench, and what the scheduler did (``events``); ``{"schedule": null}`` without
    one."""
    sch = getattr(request.app.state, "check_scheduler", None)
    return {"schedule": None} if sch is None else sch.status()


def _get(cm: CheckManager, check_id: str):
    try:
        return cm.get(check_id)
    except CheckNotFoundError:
        raise not_found("check") from None


@router.get("/{check_id}", response_model=CheckOut, responses={**ERRORS, 404: {"description": "no such check"}})
async def get_check(check_id: CheckId, request: Request, _: Reader) -> CheckOut:
    """One check: its state, verdict, document and proposed update."""
    cm = checks(request)
    return check_out(_get(cm, check_id), cm)


@router.post(
    "/{check_id}/apply",
    response_model=CalibrationOut,
    status_code=status.HTTP_201_CREATED,
    responses={**ERRORS, 404: {"description": "no such check"}, 409: {"description": "no update to apply (why)"}},
)
async def apply_check(check_id: CheckId, request: Request, _: Writer) -> CalibrationOut:
    """Make the check's proposed update the bench's current calibration (as a run's apply)."""
    cm = checks(request)
    _get(cm, check_id)
    try:
        cal = cm.apply(check_id)
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    return calibration_out(cal)


__all__ = ["router"]
