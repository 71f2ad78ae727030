"""The camera's intrinsics calibrated on the service's bench: the guided board session of ``i4cal camera calibrate``
as a job (docs/camera.md)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request, status
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from calib.errors import InputError
from service.api.deps import ID_PATTERN, Manager, RequestBody, conflict, not_found, unprocessable
from service.auth import Reader, Writer
from service.runs import RunConflictError
from service.runs.cameras import CameraCalibrationJob, CameraCalibrations

router = APIRouter(prefix="/camera/calibrations", tags=["camera"])
JobId = Annotated[str, Path(pattern=ID_PATTERN, description="camera calibration id (32 hex digits)")]


class CameraCalibrationIn(RequestBody):
    views: int = Field(15, ge=5, le=100, description="full-board views to keep, at least")
    lens_model: str | None = Field(
        None, description="auto (chosen by BIC), k1k2, k1k2k3, rational[-radial]; default: the bench's, else auto"
    )
    max_grabs: int | None = Field(None, ge=1, le=1000, description="give up after this many grabs (3 x views + 20)")


class CameraCalibrationOut(BaseModel):
    id: str
    state: str = Field(description="running, done or failed")
    created: datetime
    views: int
    lens_model: str
    grabs: int
    kept: int
    missing: list[str] = Field(description="what the views still lack, in words")
    messages: list[str] = Field(description="what the operator was told and each grab's verdict, in order")
    result: dict[str, Any] | None = Field(
        None, description="once done: K, dist (pixels; OpenCV's order), std, rms_px, n_views, lens_model, warnings"
    )
    camera_file: str | None = Field(None, description="once done: the i4cal.camera/1 file's URL")
    error: str | None = None


def _cameras(request: Request, manager: Manager) -> CameraCalibrations:
    st = request.app.state
    if getattr(st, "camera_calibrations", None) is None:
        st.camera_calibrations = CameraCalibrations(manager)
    return st.camera_calibrations


def _out(job: CameraCalibrationJob) -> CameraCalibrationOut:
    return CameraCalibrationOut(
        id=job.id,
        state=job.state,
        created=job.created,
        views=job.views,
        lens_model=job.lens_model,
        grabs=job.grabs,
        kept=job.kept,
        missing=job.missing,
        messages=job.messages,
        result=job.result,
        camera_file=f"/api/v1/camera/calibrations/{job.id}/camera.json" if job.file is not None else None,
        error=job.error,
    )


ERRORS: dict[int | str, dict[str, Any]] = {401: {"description": "no or wrong bearer token"}}


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=CameraCalibrationOut,
    responses={
        **ERRORS,
        409: {"description": "no bench, the bench is held, or its operator needs a terminal (console)"},
        422: {"description": "invalid request: the field is named"},
    },
)
async def start_camera_calibration(
    body: CameraCalibrationIn, request: Request, manager: Manager, _: Writer
) -> CameraCalibrationOut:
    """Start the guided board session on the bench (it holds the bench until done); poll ``GET .../{id}``."""
    cams = _cameras(request, manager)
    try:
        job = cams.start(body.views, body.lens_model, body.max_grabs)
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    except InputError as exc:
        raise unprocessable(exc) from None
    return _out(job)


@router.get("/{job_id}", response_model=CameraCalibrationOut, responses={**ERRORS, 404: {"description": "no such id"}})
async def get_camera_calibration(job_id: JobId, request: Request, manager: Manager, _: Reader) -> CameraCalibrationOut:
    """The session's state, what was said, what is missing, and once done the result."""
    job = _cameras(request, manager).get(job_id)
    if job is None:
        raise not_found("camera calibration")
    return _out(job)


@router.get(
    "/{job_id}/camera.json",
    response_class=FileResponse,
    responses={**ERRORS, 404: {"description": "no such id"}, 409: {"description": "not done"}},
)
async def get_camera_file(job_id: JobId, request: Request, manager: Manager, _: Reader) -> FileResponse:
    """The camera file (i4cal.camera/1, docs/camera.md): name it in the bench file's ``[camera] intrinsics``."""
    job = _cameras(request, manager).get(job_id)
    if job is None:
        raise not_found("camera calibration")
    if job.file is None:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=f"camera calibration is {job.state}: no camera file")
    return FileResponse(job.file, media_type="application/json", filename="camera.json")
