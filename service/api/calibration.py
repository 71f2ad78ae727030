"""The bench's current calibration and its history: what a robot controller loads."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from pydantic import BaseModel, Field

from ..auth import Reader
from ..settings import BENCH_NAME_PATTERN
from .deps import Manager, not_found

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


@router.get(
    "/current",
    response_model=CalibrationOut,
    responses={
        401: {"description": "reads are closed and no valid token"},
        404: {"description": "no calibration applied yet"},
    },
)
async def current_calibration(
    manager: Manager, _: Reader, bench: Annotated[str | None, Query(pattern=BENCH_NAME_PATTERN)] = None
) -> CalibrationOut:
    """The calibration a controller loads: the newest applied to ``bench`` (default: this service's bench)."""
    cal = manager.current_calibration(bench)
    if cal is None:
        raise not_found(f"calibration of bench {bench or manager.name!r}" if bench or manager.name else "calibration")
    return calibration_out(cal)


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
