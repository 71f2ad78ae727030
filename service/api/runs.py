"""Runs: start (on the bench, or offline from an uploaded dataset), watch, control, results, data."""

from __future__ import annotations

import asyncio
import json
import tempfile
import zipfile
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, HTTPException, Query, Request, status
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.background import BackgroundTask

from calib.errors import InputError
from calib.formats.resultdoc import ResultDocument
from calib.identify.export import CalibrationDocument
from calib.identify.registry import method_names
from calib.identify.verdict import verdict
from service.api.calibration import CalibrationOut, calibration_out
from service.api.deps import ID_PATTERN, Manager, RequestBody, RunId, conflict, get_run, not_found, unprocessable
from service.api.methods import MethodName
from service.api.plans import PlanName, heavy, resolve_plan
from service.auth import Reader, Writer
from service.hardening import ParsedJSONRoute
from service.runs import STATES, RunConflictError, RunManager
from service.runs.disk import StorageError
from service.settings import BENCH_NAME_PATTERN

#: ParsedJSONRoute: a request's JSON (an inline plan: up to ~1 MB at the plan's size bounds) is parsed once, in a
#: worker thread, by the strict-JSON middleware (service/hardening.py), not again in the event loop
router = APIRouter(prefix="/runs", tags=["runs"], route_class=ParsedJSONRoute)


class RunCreate(RequestBody):
    """Start a run: a plan on the bench (named or inline), or an uploaded dataset calibrated offline."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"plan": "full", "methods": ["combined", "end-effector", "legs"], "note": "weekly check"},
                {"dataset": "0123456789abcdef0123456789abcdef", "methods": ["combined"]},
            ]
        },
    )
    plan: PlanName | dict[str, Any] | None = Field(
        None, description="a plan name, or an inline plan (i4cal.plan/1); default 'full' unless a dataset is given"
    )
    methods: list[MethodName] = Field(
        default_factory=lambda: list(method_names()),
        max_length=32,
        description="methods to identify with (GET /api/v1/methods; default: all); [] records the dataset only",
    )
    bench: str | None = Field(
        None,
        pattern=BENCH_NAME_PATTERN,
        description="the bench the run belongs to (default: this service's bench; a plan runs "
        "only on this service's bench, an uploaded dataset can be of any bench)",
    )
    note: str = Field("", max_length=2000)
    dataset: str | None = Field(None, pattern=ID_PATTERN, description="calibrate this uploaded dataset offline")


class Progress(BaseModel):
    done: int
    total: int
    phase: str
    paused: bool = False
    suspended: str | None = Field(
        None, description="why the acquisition holds the robot by itself (dark image, board unseen); null: it does not"
    )
    pose: list[float] | None = Field(None, description="joint targets of the pose being executed, m")
    last_frame: int | None = None


class RunPrediction(BaseModel):
    """What the run's plan was predicted to buy before motion (the image-level model of the simulated bench's
    camera; docs/design.md): after the fits, set it beside each method's reported std."""

    predicted_std_m: dict[str, dict[str, float]] = Field(
        default_factory=dict, description="per method and combination, metres"
    )
    prediction_errors: dict[str, str] = Field(
        default_factory=dict, description="methods of the run the plan cannot feed, and why"
    )
    motion_time_s: float | None = Field(None, description="predicted motion time of the whole plan, seconds")
    unseen: list[dict[str, Any]] = Field(
        default_factory=list,
        description="steps the camera will not see in full: step, phase, board (in view), rods_hidden",
    )
    notes: list[str] = Field(default_factory=list)
    noise: str | None = Field(
        None, description="the noise model the prediction assumes (the camera's placement is the simulated bench's)"
    )
    error: str | None = Field(None, description="why there is no prediction (it never fails the run)")


class RunOut(BaseModel):
    id: str
    # STATES: the run states' values, a tuple built at import (pydantic reads it; mypy needs literals)
    state: Literal[STATES]  # type: ignore[valid-type]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    bench: str | None = Field(description="the bench the run's data and results belong to")
    service: str | None = Field(
        None,
        description="the service executing the run, named by its bench (a database "
        "can be shared by the services of several benches)",
    )
    note: str
    plan: str | None = Field(description="plan name")
    methods: list[str]
    dataset: str | None = Field(description="source dataset of an offline run")
    progress: Progress
    timings: dict[str, float]
    error: str | None
    has_result: bool
    prediction: RunPrediction | None = Field(
        None,
        description="the plan's predicted std per method and combination and its motion time, computed as the run "
        "starts (null: not yet, or an offline run)",
    )
    verdict: dict[str, Any] | None = Field(
        None,
        description="which method's result to load and why, the next command (calib.identify.verdict; "
        "null: no result yet)",
    )


def run_out(manager: RunManager, run) -> RunOut:
    a = manager.active.get(run.id)
    return RunOut(
        id=run.id,
        state=run.state,
        created_at=run.created_at,
        started_at=run.started_at,
        finished_at=run.finished_at,
        bench=run.bench,
        service=run.service,
        note=run.note or "",
        plan=run.plan_name,
        methods=list(run.methods or []),
        dataset=run.source_dataset,
        progress=Progress(
            done=run.done or 0,
            total=run.total or 0,
            phase=run.phase or "",
            paused=bool(a and a.paused),
            suspended=(a.suspended or None) if a else None,
            pose=a.pose if a else None,
            last_frame=a.last_frame if a else None,
        ),
        timings=run.timings or {},
        error=run.error,
        has_result=run.result is not None,
        prediction=None if run.prediction is None else RunPrediction.model_validate(run.prediction),
        verdict=None if run.result is None else verdict(run.result, run.id).to_dict(),
    )


class ApplyBody(RequestBody):
    model_config = ConfigDict(extra="forbid")
    method: MethodName | None = Field(
        None, description="default: the first converged in GET /api/v1/methods' apply order (combined, legs, ...)"
    )


ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"description": "no or wrong bearer token"},
    404: {"description": "no such run"},
}


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=RunOut,
    responses={
        **ERRORS,
        409: {"description": "another run holds the bench"},
        422: {"description": "invalid request: the field is named"},
        507: {"description": "the plan's frames do not fit (data_quota_bytes, min_free_bytes) or the disk is full"},
    },
)
async def create_run(body: RunCreate, manager: Manager, _: Writer) -> RunOut:
    """Validate the request and the whole plan before anything moves, then start the run."""
    if body.dataset is not None and body.plan is not None:
        raise unprocessable(InputError("give a plan or a dataset, not both", field="plan"))
    plan = None
    plan_name = None
    if body.dataset is None:
        if (busy := manager.bench_busy()) is not None:
            raise conflict(busy)
        plan = await asyncio.to_thread(resolve_plan, body.plan, manager)
        plan_name = plan.name
    await _check_space(manager.check_space_for_run, plan)
    try:
        run = manager.create(
            plan=plan,
            plan_name=plan_name,
            methods=list(dict.fromkeys(body.methods)),
            note=body.note,
            bench=body.bench,
            dataset_id=body.dataset,
        )
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    except StorageError as exc:
        raise insufficient_storage(exc) from None
    except InputError as exc:
        raise unprocessable(exc) from None
    return run_out(manager, manager.get(run.id))


@router.get("", response_model=list[RunOut], responses={401: ERRORS[401]})
async def list_runs(
    manager: Manager,
    _: Reader,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    # STATES: a tuple built at import (pydantic reads it; mypy needs literals)
    state: Annotated[Literal[STATES] | None, Query()] = None,  # type: ignore[valid-type]
    bench: Annotated[str | None, Query(pattern=BENCH_NAME_PATTERN)] = None,
) -> list[RunOut]:
    """Runs, newest first; ``bench``: only that bench's."""
    return [run_out(manager, r) for r in manager.list(limit, offset, state, bench)]


@router.get("/{run_id}", response_model=RunOut, responses=ERRORS)
async def read_run(run_id: RunId, manager: Manager, _: Reader) -> RunOut:
    return run_out(manager, get_run(manager, run_id))


def _sse(ev: dict[str, Any]) -> str:
    return f"id: {ev['seq']}\nevent: {ev['type']}\ndata: {json.dumps(ev)}\n\n"


def _overflow(last: int) -> str:
    """The ``overflow`` event (no ``id``: the client's Last-Event-ID stays the last event it received): this stream
    fell behind and ends; reconnect with Last-Event-ID (an EventSource does so by itself) to read every event
    after ``last`` from the database."""
    data = {"type": "overflow", "data": {"last_seq": last, "reconnect": "with Last-Event-ID (or ?after=last_seq)"}}
    return f"event: overflow\ndata: {json.dumps(data)}\n\n"


@router.get(
    "/{run_id}/events",
    responses={**ERRORS, 200: {"content": {"text/event-stream": {}}, "description": "Server-Sent Events"}},
)
async def run_events(
    run_id: RunId,
    manager: Manager,
    _: Reader,
    request: Request,
    last_event_id: Annotated[str | None, Header(max_length=20)] = None,
    after: Annotated[int, Query(ge=0, le=2**31)] = 0,
    follow: bool = True,
) -> StreamingResponse:
    """State changes, acquisition progress (pose i/N), extraction progress, fits: past events, then live ones
    until the run ends. Resumes after ``Last-Event-ID`` (or ``after``). A client that falls more than
    ``SUBSCRIBER_QUEUE_MAX`` events behind gets an ``overflow`` event and the stream ends: reconnect with
    Last-Event-ID, nothing is lost."""
    get_run(manager, run_id)
    start = after
    if last_event_id and last_event_id.isdigit():
        start = max(start, int(last_event_id))

    async def gen():
        q = manager.subscribe(run_id)
        last = start
        try:
            for ev in manager.events(run_id, last):
                last = ev["seq"]
                yield _sse(ev)
            if not follow or run_id not in manager.active:
                return
            while True:
                try:
                    ev = await asyncio.wait_for(q.get(), 15.0)
                except TimeoutError:
                    if await request.is_disconnected():
                        return
                    yield ": keep-alive\n\n"
                    continue
                if q.overflowed:  # events were dropped for this slow client: tell it to reconnect from `last`
                    yield _overflow(last)
                    return
                if ev is None:
                    return
                if ev["seq"] <= last:
                    continue
                last = ev["seq"]
                yield _sse(ev)
        finally:
            manager.unsubscribe(run_id, q)

    return StreamingResponse(
        gen(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    )


def _control(manager: RunManager, run_id: str, what: str) -> RunOut:
    get_run(manager, run_id)
    try:
        run = getattr(manager, what)(run_id)
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    return run_out(manager, run)


@router.post("/{run_id}/abort", response_model=RunOut, status_code=status.HTTP_202_ACCEPTED, responses=ERRORS)
async def abort_run(run_id: RunId, manager: Manager, _: Writer) -> RunOut:
    """Stop the actuators now and end the run (frames kept). Always accepted from a token holder."""
    return _control(manager, run_id, "abort")


@router.post("/{run_id}/pause", response_model=RunOut, responses={**ERRORS, 409: {"description": "not acquiring"}})
async def pause_run(run_id: RunId, manager: Manager, _: Writer) -> RunOut:
    """Stop after the current pose."""
    return _control(manager, run_id, "pause")


@router.post(
    "/{run_id}/resume",
    response_model=RunOut,
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        **ERRORS,
        409: {"description": "not paused, failed or interrupted, or the bench is held (the run is left as it was)"},
        507: {"description": "what is left of the run does not fit, or the disk is full (the run is left as it was)"},
    },
)
async def resume_run(run_id: RunId, manager: Manager, _: Writer) -> RunOut:
    """Resume a paused acquisition in place, or a failed or interrupted run from what is on disk: the acquisition
    from its first missing frame (nothing moves when every frame is written), then extraction and fits if their
    output is missing."""
    get_run(manager, run_id)
    await _check_space(manager.check_space_for_resume, run_id)
    try:
        return _control(manager, run_id, "resume")
    except StorageError as exc:
        raise insufficient_storage(exc) from None


# -- disk and retention ----------------------------------------------------------------------------------
def insufficient_storage(exc: StorageError) -> HTTPException:
    """507 naming the limit (a setting, or ``disk full``) and the cause."""
    return HTTPException(507, detail={"limit": exc.limit, "msg": str(exc)})


async def _check_space(check, *args: Any) -> None:
    """A space check (it walks the data directory) off the event loop; 507 when it refuses."""
    try:
        await asyncio.to_thread(check, *args)
    except StorageError as exc:
        raise insufficient_storage(exc) from None


class Deleted(BaseModel):
    id: str
    freed_bytes: int = Field(description="bytes of the files removed")


@router.delete(
    "/{run_id}",
    response_model=Deleted,
    responses={
        **ERRORS,
        409: {
            "description": "the run is executing or holds the bench, belongs to another service, or its result was "
            "applied (current calibration or history)"
        },
        507: {"description": "the disk is full and the database cannot record the deletion"},
    },
)
async def delete_run(run_id: RunId, manager: Manager, _: Writer) -> Deleted:
    """Delete a run that is not executing (done, failed, aborted or interrupted) with its files: dataset,
    observations, result, events. A run whose result was applied is kept (409): the calibrations name it."""
    get_run(manager, run_id)
    try:
        path, size = manager.delete_run(run_id)
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    except StorageError as exc:
        raise insufficient_storage(exc) from None
    await asyncio.to_thread(manager.delete_tree, path)
    return Deleted(id=run_id, freed_bytes=size)


@router.get(
    "/{run_id}/result",
    response_model=ResultDocument,
    response_model_exclude_unset=True,  # the stored document as it is (keys a document lacks are not added)
    responses={**ERRORS, 409: {"description": "no result (yet)"}},
)
async def run_result(run_id: RunId, manager: Manager, _: Reader) -> dict[str, Any]:
    """Per method: the four combinations with standard deviations (``combinations``, ``combinations_std``; also as
    ``parameters``, ``std``), the seven parameters when identified (``seven``), residuals, identifiability,
    validation (the JSON of ``i4cal calibrate --json``; :mod:`calib.formats.resultdoc`)."""
    run = get_run(manager, run_id)
    if run.result is None:
        raise conflict(f"run is {run.state}; no result")
    return run.result


@router.get(
    "/{run_id}/report",
    response_class=HTMLResponse,
    responses={
        **ERRORS,
        409: {"description": "no result (yet)"},
        429: {"description": "the heavy requests' queue is full (Retry-After: seconds to wait)"},
        200: {"content": {"text/html": {}}, "description": "one self-contained HTML file"},
    },
)
async def run_report(
    run_id: RunId, manager: Manager, _: Reader, methods: Annotated[list[MethodName] | None, Query()] = None
) -> HTMLResponse:
    """The calibration report (parameters, uncertainties, bound, validation, residuals, identifiability, camera
    calibration, worst frames, hashes) as one HTML file that opens offline (``i4cal report``). Built in the
    heavy-request pool (a child process niced below the run's; 429 with Retry-After when its queue is full)."""
    from sqlalchemy import inspect as sa_inspect

    run = get_run(manager, run_id)
    if run.result is None:
        raise conflict(f"run is {run.state}; no result")
    row = {a.key: getattr(run, a.key) for a in sa_inspect(run).mapper.column_attrs}
    html = await heavy(manager, "report", data_dir=str(manager.data_dir), run=row, methods=methods)
    return HTMLResponse(html, headers={"Content-Disposition": f'inline; filename="i4cal-report-{run_id}.html"'})


@router.get(
    "/{run_id}/export",
    response_model=CalibrationDocument,
    responses={
        **ERRORS,
        200: {
            "content": {"application/yaml": {}},
            "description": "i4cal.calibration/1 (JSON, or YAML with format=yaml)",
        },
        409: {"description": "no result (yet), or the method did not converge"},
        422: {"description": "the result has no such method"},
    },
)
async def export_run(
    run_id: RunId,
    manager: Manager,
    _: Reader,
    method: Annotated[MethodName | None, Query(description="default: the recommended method (docs/export.md)")] = None,
    format: Annotated[Literal["json", "yaml"], Query(description="json (default) or yaml")] = "json",
) -> Any:
    """The run's result as the document a robot controller loads (``i4cal.calibration/1``, ``i4cal export RUN``)."""
    from service.export import dumps, run_document

    run = get_run(manager, run_id)
    if run.result is None:
        raise conflict(f"run is {run.state}; no result")
    if method and method not in ResultDocument.from_dict(run.result).methods:
        raise unprocessable(InputError(f"the run has no result for method {method!r}", field="method"), ("query",))
    try:
        doc = await asyncio.to_thread(run_document, manager.data_dir, run, method)
    except InputError as exc:  # not converged, or none converged
        raise conflict(str(exc)) from None
    if format == "yaml":
        return Response(dumps(doc, "yaml"), media_type="application/yaml")
    return doc


@router.post(
    "/{run_id}/apply",
    response_model=CalibrationOut,
    status_code=status.HTTP_201_CREATED,
    responses={**ERRORS, 409: {"description": "no converged result"}},
)
async def apply_run(run_id: RunId, manager: Manager, _: Writer, body: ApplyBody | None = None) -> CalibrationOut:
    """Make this run's result (one method) the bench's current calibration."""
    get_run(manager, run_id)
    try:
        cal = manager.apply(run_id, body.method if body else None)
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    except InputError as exc:
        raise unprocessable(exc) from None
    return calibration_out(cal)


# -- data ------------------------------------------------------------------------------------------
def _dataset_dir(manager: RunManager, run) -> Path:
    p = manager.dataset_path(run).resolve()
    if manager.data_dir not in p.parents or not (p / "dataset.json").is_file():
        raise not_found("dataset of this run")
    return p


def _zip_dir(src: Path) -> Path:
    fd, name = tempfile.mkstemp(suffix=".zip")
    import os

    os.close(fd)
    with zipfile.ZipFile(name, "w", zipfile.ZIP_STORED) as zf:
        for f in sorted(src.rglob("*")):
            if f.is_file() and not f.is_symlink() and not f.name.endswith(".tmp"):
                zf.write(f, f"dataset/{f.relative_to(src).as_posix()}")
    return Path(name)


@router.get(
    "/{run_id}/dataset", responses={**ERRORS, 200: {"content": {"application/zip": {}}}}, response_class=FileResponse
)
async def download_dataset(run_id: RunId, manager: Manager, _: Reader) -> FileResponse:
    """The run's dataset (dataset v1: dataset.json + PNG frames) as a zip archive."""
    src = _dataset_dir(manager, get_run(manager, run_id))
    path = await asyncio.to_thread(_zip_dir, src)
    return FileResponse(
        path,
        media_type="application/zip",
        filename=f"i4cal-{run_id}.zip",
        background=BackgroundTask(path.unlink, missing_ok=True),
    )


class FrameInfo(BaseModel):
    index: int
    phase: str
    q: list[float]
    board: bool | None = None
    rods: int | None = None
    missing: dict[str, str] | None = None


def _observations_doc(manager: RunManager, run) -> dict[str, Any] | None:
    p = manager.run_dir(run) / "observations.json"
    if not p.is_file():
        return None
    return json.loads(p.read_text(encoding="utf-8"))


def _observations(manager: RunManager, run) -> dict[int, dict[str, Any]]:
    doc = _observations_doc(manager, run) or {}
    return {int(f["dataset_frame"]): f for f in doc.get("frames", []) if "dataset_frame" in f}


@router.get("/{run_id}/frames", response_model=list[FrameInfo], responses=ERRORS)
async def list_frames(run_id: RunId, manager: Manager, _: Reader) -> list[FrameInfo]:
    """The run's frames, with what extraction found in each (once extracted)."""
    run = get_run(manager, run_id)
    src = _dataset_dir(manager, run)
    doc = json.loads((src / "dataset.json").read_text(encoding="utf-8"))
    obs = await asyncio.to_thread(_observations, manager, run)
    out = []
    for i, f in enumerate(doc.get("frames", [])):
        o = obs.get(i)
        rods = None
        if o is not None:
            rods = sum(1 for leg in (o.get("legs") or {}).values() for r in leg if r)
        out.append(
            FrameInfo(
                index=i,
                phase=f.get("phase", ""),
                q=f.get("q", []),
                board=None if o is None else o.get("board") is not None,
                rods=rods,
                missing=None if o is None else o.get("missing"),
            )
        )
    return out


@router.get(
    "/{run_id}/frames/{index}", responses={**ERRORS, 200: {"content": {"image/png": {}}}}, response_class=Response
)
async def frame_image(
    run_id: RunId,
    manager: Manager,
    _: Reader,
    index: Annotated[str, PathParam(pattern=r"^(latest|[0-9]{1,7})$")],
    annotate: bool = True,
    max_width: Annotated[int, Query(ge=64, le=8192)] = 1024,
) -> Response:
    """A frame as PNG with the detected board outline and rod lines drawn (``latest``: the last frame acquired, or,
    while the run extracts, the last frame extracted)."""
    run = get_run(manager, run_id)
    src = _dataset_dir(manager, run)
    png = await asyncio.to_thread(_render_frame, manager, run, src, index, annotate, max_width)
    if png is None:
        raise not_found("frame")
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})


def _render_frame(manager: RunManager, run, src: Path, index: str, annotate: bool, max_width: int) -> bytes | None:
    import cv2

    from service.report.draw import annotated_frame, frame_camera

    doc = json.loads((src / "dataset.json").read_text(encoding="utf-8"))
    frames = doc.get("frames", [])
    if not frames:
        return None
    i = len(frames) - 1 if index == "latest" else int(index)
    # while the run extracts: 'latest' is the last frame extracted, drawn with what was found in it
    live_i, live = manager.live_detections(run.id, None if index == "latest" else i)
    i = live_i if live_i is not None else i
    obs_doc = _observations_doc(manager, run) if annotate else None
    o = next((f for f in (obs_doc or {}).get("frames", []) if f.get("dataset_frame") == i), None)
    o = live if o is None and annotate else o
    img = annotated_frame(src, doc, i, o, frame_camera(doc, obs_doc), max_width)
    if img is None:
        return None
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes() if ok else None
