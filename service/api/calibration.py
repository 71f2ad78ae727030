"""The bench's current calibration and its history: what a robot controller loads."""

from __future__ import annotations

import asyncio
from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query
from fastapi.responses import Response
from pydantic import BaseModel, Field

from calib.errors import InputError
from calib.formats.resultdoc import ResultDocument
from calib.identify.export import CalibrationDocument, ExportContext, build_calibration
from service.api.deps import Manager, conflict, not_found
from service.auth import Reader
from service.runs import RunNotFoundError
from service.settings import BENCH_NAME_PATTERN

router = APIRouter(prefix="/calibration", tags=["calibration"])


class CalibrationOut(BaseModel):
    """The identified geometry a controller loads, with its provenance."""

    id: int
    bench: str
    applied_at: datetime
    run_id: str
    method: str
    software_version: str
    combinations: dict[str, float | None] = Field(description="L, H-D, S-q02/2, S-(q04-q03)/2 (m): always")
    combinations_std: dict[str, float | None] | None = None
    parameters: dict[str, float | None] | None = Field(
        None, description="the seven parameters H, q02, q03, q04, S, D, L (m) where the method identifies them"
    )
    parameters_std: dict[str, float | None] | None = None
    nominal: dict[str, Any] | None = None


def calibration_out(cal) -> CalibrationOut:
    p = cal.payload or {}
    return CalibrationOut(
        id=cal.id,
        bench=cal.bench,
        applied_at=cal.applied_at,
        run_id=cal.run_id,
        method=cal.method,
        software_version=cal.software_version,
        combinations=p.get("combinations") or {},
        combinations_std=p.get("combinations_std"),
        parameters=p.get("parameters"),
        parameters_std=p.get("parameters_std"),
        nominal=p.get("nominal"),
    )


class CurrentCalibrationOut(CalibrationDocument):
    """The current calibration: an ``i4cal.calibration/1`` document (docs/export.md: the seven parameters with which
    were identified and which fixed at nominal, the four combinations with std and covariance, units, provenance),
    with the calibration record's keys (``id``, ``applied_at``, ``run_id``, ``parameters``, ``parameters_std``)."""

    bench: str = Field(description="the bench the calibration is applied to")
    id: int
    applied_at: datetime
    run_id: str
    parameters: dict[str, float | None] | None = Field(
        None, description="the seven parameters H, q02, q03, q04, S, D, L (m) where the method identifies them"
    )
    parameters_std: dict[str, float | None] | None = None


def current_document(manager, cal) -> CalibrationDocument:
    """The document of an applied calibration: from its run's result (covariance, identifiability, warnings,
    dataset hash), or, when the run's result is no longer stored, from the record alone (no covariance then)."""
    from service.export import payload_result, run_document

    try:
        run = manager.get(cal.run_id)
    except RunNotFoundError:
        run = None
    choice = f"applied to bench {cal.bench} (POST /api/v1/runs/{{id}}/apply)"
    if (cal.payload or {}).get("document"):  # a check's update (POST /api/v1/checks/{id}/apply): its own document
        doc = CalibrationDocument.model_validate(cal.payload["document"])
        why = f"applied to bench {cal.bench} (POST /api/v1/checks/{{id}}/apply): {doc.method_choice}"
        return doc.model_copy(update={"method_choice": why, "bench": cal.bench})
    if run is not None and run.result and cal.method in ResultDocument.from_dict(run.result).methods:
        doc = run_document(manager.data_dir, run, cal.method, software_version=cal.software_version, bench=cal.bench)
    else:
        ctx = ExportContext(software_version=cal.software_version, bench=cal.bench, run=cal.run_id)
        doc = build_calibration(payload_result(cal.payload or {}), ctx, cal.method)
    return doc.model_copy(update={"method_choice": choice})


@router.get(
    "/current",
    response_model=CurrentCalibrationOut,
    responses={
        200: {"content": {"application/yaml": {}}, "description": "the document (JSON, or YAML with format=yaml)"},
        401: {"description": "reads are closed and no valid token"},
        404: {"description": "no calibration applied yet"},
        409: {"description": "the applied record cannot be made a document (said why)"},
    },
)
async def current_calibration(
    manager: Manager,
    _: Reader,
    bench: Annotated[str | None, Query(pattern=BENCH_NAME_PATTERN)] = None,
    format: Annotated[Literal["json", "yaml"], Query(description="json (default) or yaml")] = "json",
) -> Any:
    """The calibration a controller loads: the newest applied to ``bench`` (default: this service's bench), as an
    ``i4cal.calibration/1`` document with the record's keys."""
    from service.export import dumps

    cal = manager.current_calibration(bench)
    if cal is None:
        raise not_found(f"calibration of bench {bench or manager.name!r}" if bench or manager.name else "calibration")
    try:
        doc = await asyncio.to_thread(current_document, manager, cal)
    except InputError as exc:  # a record that cannot be made a document: say what is wrong with it
        raise conflict(f"the current calibration of bench {cal.bench!r} cannot be made a document: {exc}") from None
    record = calibration_out(cal).model_dump(include={"id", "applied_at", "run_id", "parameters", "parameters_std"})
    out = CurrentCalibrationOut.model_validate({**doc.model_dump(), **record})
    if format == "yaml":
        return Response(dumps(out, "yaml"), media_type="application/yaml")
    return out


@router.get(
    "/history",
    response_model=list[CalibrationOut],
    responses={401: {"description": "reads are closed and no valid token"}},
)
async def calibration_history(
    manager: Manager,
    _: Reader,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    bench: Annotated[str | None, Query(pattern=BENCH_NAME_PATTERN)] = None,
) -> list[CalibrationOut]:
    """Every applied calibration, newest first (``bench``: only that bench's; default: every bench)."""
    return [calibration_out(c) for c in manager.calibration_history(limit, offset, bench)]
