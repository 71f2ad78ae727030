"""Runs: the bench, the run manager and the run pipeline (acquire -> extract -> calibrate).

Acquisition is async and runs in the event loop; extraction and fitting run in child processes
(:mod:`service.jobs`), so status and health keep answering while a run goes on. One run at a time holds the
bench; offline runs (from an uploaded dataset) never touch it. Every state change and progress report is
persisted as an event and pushed to the live subscribers (Server-Sent Events); the high-rate reports (extraction
progress, per-frame results, fit iterations) are batched: at most one event of each kind per
:data:`LIVE_INTERVAL_S` and run.

No HTTP here: errors are :class:`RunConflictError` / :class:`RunNotFoundError` / :class:`calib.errors.InputError`,
turned into status codes by the routers.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import shutil
import time
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import func, or_, select, update

from calib.errors import I4calError, InputError
from calib.jsonio import write_json_atomic

from .db import Calibration, Database, DatasetRecord, Event, Run
from .jobs import clean_json, run_job
from .settings import Settings

log = logging.getLogger("i4cal.service")

ACTIVE_STATES = ("queued", "acquiring", "extracting", "calibrating")
TERMINAL_STATES = ("done", "failed", "aborted")
STATES = (*ACTIVE_STATES, *TERMINAL_STATES, "interrupted")
#: Seconds between two batches of high-rate events of a run (progress, frames, iterations): with at most two kinds
#: at a time (progress + frames, or iterations), a run writes at most ~10 such events per second.
LIVE_INTERVAL_S = 0.2


class RunConflictError(Exception):
    """The request conflicts with the current state (bench held, run not active...)."""


class RunNotFoundError(Exception):
    pass


def new_id() -> str:
    return uuid.uuid4().hex


def now() -> datetime:
    return datetime.now(UTC)


# ---------------------------------------------------------------------------------------------
@dataclass
class DeviceState:
    name: str
    uri: str
    state: str = "unknown"  # unknown, connected, idle, error
    last_error: str | None = None
    last_seen: datetime | None = None

    def ok(self) -> None:
        self.state, self.last_seen = "connected", now()

    def fail(self, msg: str) -> None:
        self.state, self.last_error = "error", msg


class Bench:
    """The bench this service drives: a configuration, optionally an in-process simulated bench."""

    def __init__(self, name: str, config: Any, *, sim: Any = None, camera_spec: dict | None = None) -> None:
        self.name = name
        self.config = config  # drivers.config.BenchConfig
        self.sim = sim
        self.camera_spec = camera_spec or {}
        self.devices = {k: DeviceState(k, getattr(config, k).uri) for k in ("actuators", "camera", "operator")}

    @classmethod
    async def from_settings(cls, settings: Settings) -> Bench | None:
        from drivers.config import BenchConfig, load_bench

        camera_spec: dict[str, Any] = {}
        if settings.camera_file:
            from calib.camera import CameraModel

            cam = CameraModel.load(settings.camera_file)
            camera_spec = {"K": cam.K.tolist(), "dist": cam.dist.tolist()}
        if settings.sim_bench:
            from .simproc import SimBenchProcess

            # its own process, as hardware would be: its rendering does not compete with requests for the GIL
            sim = await SimBenchProcess(
                settings.sim_port,
                settings.sim_fast_renderer,
                name=settings.bench_name or "sim",
                acquisition={"line_rate_hz": 50.0},
                camera={"timeout_s": 10.0},
            ).start()
            cfg = BenchConfig.model_validate(sim.config)
            if sim.camera is not None and not camera_spec:
                camera_spec = sim.camera
            return cls(bench_name(settings, cfg), cfg, sim=sim, camera_spec=camera_spec)
        if settings.bench is not None:
            cfg = BenchConfig.model_validate(settings.bench)
        elif settings.bench_file is not None:
            cfg = load_bench(settings.bench_file)
        else:
            return None
        return cls(bench_name(settings, cfg), cfg, camera_spec=camera_spec)

    async def close(self) -> None:
        if self.sim is not None:
            await self.sim.stop()

    def preload(self) -> None:
        """Import the acquisition and the device backends now (blocking: in a thread at start-up), so that the first
        run does not import them in the event loop."""
        import drivers.acquisition  # noqa: F401
        from drivers.config import open_actuators, open_camera

        with contextlib.suppress(I4calError):
            open_actuators(self.config)  # constructed, not connected: imports the backend's module
        with contextlib.suppress(I4calError):
            open_camera(self.config)

    async def probe(self, timeout_s: float = 3.0) -> None:
        """Connect to each device briefly and record its state (only while no run holds the bench)."""
        from drivers.config import open_actuators, open_camera

        act = open_actuators(self.config)
        try:
            await asyncio.wait_for(act.connect(), timeout_s)
            await asyncio.wait_for(act.status(), timeout_s)
            self.devices["actuators"].ok()
        except (I4calError, OSError, TimeoutError) as exc:
            self.devices["actuators"].fail(str(exc) or type(exc).__name__)
        finally:
            with contextlib.suppress(Exception):
                await act.close()
        cam = open_camera(self.config)
        try:
            await asyncio.wait_for(cam.open(), timeout_s)
            self.devices["camera"].ok()
        except (I4calError, OSError, TimeoutError) as exc:
            self.devices["camera"].fail(str(exc) or type(exc).__name__)
        finally:
            with contextlib.suppress(Exception):
                await cam.close()


def bench_name(settings: Settings, cfg: Any) -> str:
    """The bench's name: ``bench_name`` of the settings, else the bench configuration's ``name``.

    Raises
    ------
    InputError
        A name that cannot identify a bench (see :data:`service.settings.BENCH_NAME_PATTERN`).
    """
    import re

    from .settings import BENCH_NAME_PATTERN

    name = settings.bench_name or str(getattr(cfg, "name", "") or "bench")
    if not re.fullmatch(BENCH_NAME_PATTERN, name):
        raise InputError(
            f"bench name {name!r} must be 1-64 letters, digits, spaces, '.', '_' or '-' "
            "(set bench_name in the service configuration)",
            field="bench_name",
        )
    return name


# ---------------------------------------------------------------------------------------------
@dataclass
class ActiveRun:
    id: str
    task: asyncio.Task | None = None
    acq: Any = None
    holds_bench: bool = False
    aborting: bool = False
    paused: bool = False
    last_frame: int | None = None
    pose: list[float] | None = None
    started: float = field(default_factory=time.monotonic)
    #: extraction's detections per dataset frame (observations v1 frame layout), while the run is active
    detections: dict[int, dict[str, Any]] = field(default_factory=dict)
    last_extracted: int | None = None
    job: Any = None  # service.jobs.Job: the extraction or fit process


class RunManager:
    def __init__(self, settings: Settings, db: Database, bench: Bench | None) -> None:
        self.settings = settings
        self.db = db
        self.bench = bench
        self.active: dict[str, ActiveRun] = {}
        self.bench_holder: str | None = None
        self._subs: dict[str, set[asyncio.Queue]] = {}
        self._seq: dict[str, int] = {}
        self._live: dict[str, dict[str, Any]] = {}  # run id -> kind -> pending batch
        self._live_timer: dict[str, asyncio.TimerHandle] = {}
        self._live_last: dict[str, float] = {}
        self.data_dir = settings.data_dir.resolve()
        #: this service's name in a shared database: its bench's (None: no bench and no bench_name)
        self.name: str | None = bench.name if bench is not None else settings.bench_name

    def owns(self, run: Run) -> bool:
        """Whether this service executes ``run`` (runs of services sharing the database are theirs to control)."""
        return run.service is None or run.service == self.name

    # -- life --------------------------------------------------------------------------------------
    def recover(self) -> list[str]:
        """Runs left active by a crash become ``interrupted`` (their frames are kept)."""
        with self.db.session() as s:
            mine = Run.service.is_(None) if self.name is None else or_(Run.service == self.name, Run.service.is_(None))
            ids = list(s.scalars(select(Run.id).where(Run.state.in_(ACTIVE_STATES), mine)))
        for rid in ids:
            self._set(rid, state="interrupted", error="the service stopped during the run; resume it to continue")
        return ids

    async def shutdown(self) -> None:
        for a in list(self.active.values()):
            if a.task is not None and not a.task.done():
                a.task.cancel()
        for a in list(self.active.values()):
            if a.task is not None:
                with contextlib.suppress(BaseException):
                    await asyncio.wait_for(a.task, 10)

    # -- events ------------------------------------------------------------------------------------
    def _next_seq(self, run_id: str) -> int:
        if run_id not in self._seq:
            with self.db.session() as s:
                self._seq[run_id] = int(s.scalar(select(func.max(Event.seq)).where(Event.run_id == run_id)) or 0)
        self._seq[run_id] += 1
        return self._seq[run_id]

    def emit(self, run_id: str, type_: str, data: dict[str, Any]) -> None:
        data = clean_json(data)
        seq = self._next_seq(run_id)
        t = now()
        with self.db.session() as s:
            s.add(Event(run_id=run_id, seq=seq, t=t, type=type_, data=data))
        ev = {"seq": seq, "t": t.isoformat(), "type": type_, "data": data}
        for q in list(self._subs.get(run_id, ())):
            with contextlib.suppress(asyncio.QueueFull):
                q.put_nowait(ev)

    def subscribe(self, run_id: str) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(maxsize=10_000)
        self._subs.setdefault(run_id, set()).add(q)
        return q

    def unsubscribe(self, run_id: str, q: asyncio.Queue) -> None:
        subs = self._subs.get(run_id)
        if subs is not None:
            subs.discard(q)
            if not subs:
                self._subs.pop(run_id, None)

    def _close_subscribers(self, run_id: str) -> None:
        for q in list(self._subs.get(run_id, ())):
            with contextlib.suppress(asyncio.QueueFull):
                q.put_nowait(None)

    def events(self, run_id: str, after: int = 0) -> list[dict[str, Any]]:
        with self.db.session() as s:
            rows = s.scalars(select(Event).where(Event.run_id == run_id, Event.seq > after).order_by(Event.seq))
            return [{"seq": e.seq, "t": e.t.isoformat(), "type": e.type, "data": e.data} for e in rows]

    # -- rows --------------------------------------------------------------------------------------
    def get(self, run_id: str) -> Run:
        with self.db.session() as s:
            run = s.get(Run, run_id)
            if run is None:
                raise RunNotFoundError(run_id)
            return run

    def list(self, limit: int = 100, offset: int = 0, state: str | None = None, bench: str | None = None) -> list[Run]:
        with self.db.session() as s:
            q = select(Run).order_by(Run.created_at.desc()).limit(limit).offset(offset)
            if state:
                q = q.where(Run.state == state)
            if bench:
                q = q.where(Run.bench == bench)
            return list(s.scalars(q))

    def _set(self, run_id: str, **values: Any) -> None:
        state = values.get("state")
        with self.db.session() as s:
            s.execute(update(Run).where(Run.id == run_id).values(**values))
        if state is not None:
            self.emit(run_id, "state", {"state": state, **({"error": values["error"]} if values.get("error") else {})})

    def run_dir(self, run: Run) -> Path:
        return self.data_dir / "runs" / run.id

    def dataset_path(self, run: Run) -> Path:
        return self.data_dir / run.dataset_dir

    # -- create / control --------------------------------------------------------------------------
    def create(
        self,
        *,
        plan: Any,
        plan_name: str | None,
        methods: list[str],
        note: str,
        bench: str | None,
        dataset_id: str | None,
    ) -> Run:
        rid = new_id()
        if dataset_id is not None:
            with self.db.session() as s:
                ds = s.get(DatasetRecord, dataset_id)
                if ds is None:
                    raise InputError(f"no dataset {dataset_id!r}", field="dataset")
                ds_dir = ds.path
            if not (self.data_dir / ds_dir / "dataset.json").is_file():
                raise InputError(
                    f"dataset {dataset_id!r} is not on this service's disk (uploaded to another "
                    "service sharing the database?)",
                    field="dataset",
                )
            if not methods:
                raise InputError("an offline run needs at least one method", field="methods")
        else:
            if self.bench is None:
                raise InputError("this service has no bench configured; upload a dataset instead", field="bench")
            if bench not in (None, self.bench.name):
                raise InputError(f"unknown bench {bench!r}; this service drives {self.bench.name!r}", field="bench")
            if self.bench_holder is not None:
                raise RunConflictError(f"run {self.bench_holder} holds the bench")
            ds_dir = f"runs/{rid}/dataset"
        run_bench = (bench or self.name) if dataset_id else self.bench.name
        run = Run(
            id=rid,
            state="queued",
            created_at=now(),
            bench=run_bench,
            service=self.name,
            note=note,
            plan_name=plan_name,
            plan=plan.model_dump(mode="json", exclude_none=True) if plan else None,
            methods=methods,
            source_dataset=dataset_id,
            dataset_dir=ds_dir,
            timings={},
            total=len(plan_units(plan)) if plan else 0,
        )
        (self.data_dir / "runs" / rid).mkdir(parents=True, exist_ok=True)
        with self.db.session() as s:
            s.add(run)
        self.emit(rid, "state", {"state": "queued"})
        self._start(run, resume=False)
        return run

    def _start(self, run: Run, *, resume: bool) -> None:
        a = ActiveRun(run.id)
        acquire = run.source_dataset is None and not self._acquisition_complete(run)
        if acquire:
            if self.bench_holder is not None:
                raise RunConflictError(f"run {self.bench_holder} holds the bench")
            self.bench_holder = run.id
            a.holds_bench = True
        self.active[run.id] = a
        a.task = asyncio.get_running_loop().create_task(self._execute(run.id, acquire, resume), name=f"run-{run.id}")

    def _acquisition_complete(self, run: Run) -> bool:
        if run.source_dataset is not None or run.plan is None:
            return True
        meta = self.dataset_path(run) / "dataset.json"
        if not meta.exists():
            return False
        try:
            n = len(json.loads(meta.read_text(encoding="utf-8")).get("frames", []))
        except (OSError, ValueError):
            return False
        return n >= run.total

    def resume(self, run_id: str) -> Run:
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is not None:
            if a.acq is None or run.state != "acquiring":
                raise RunConflictError(f"run is {run.state}; only an acquisition can be paused and resumed")
            a.acq.resume()
            a.paused = False
            self.emit(run_id, "resumed", {})
            return self.get(run_id)
        if not self.owns(run):
            raise RunConflictError(f"run belongs to the service of bench {run.service!r}; resume it there")
        if run.state != "interrupted":
            raise RunConflictError(f"run is {run.state}; only a paused or interrupted run can be resumed")
        self._set(run_id, state="queued", error=None)
        self._start(run, resume=True)
        return self.get(run_id)

    def pause(self, run_id: str) -> Run:
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is None or a.acq is None or run.state != "acquiring":
            raise RunConflictError(f"run is {run.state}; only an acquisition can be paused")
        a.acq.pause()
        a.paused = True
        self.emit(run_id, "paused", {})
        return self.get(run_id)

    def abort(self, run_id: str) -> Run:
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is None:
            if not self.owns(run) and run.state not in TERMINAL_STATES:
                raise RunConflictError(f"run belongs to the service of bench {run.service!r}; abort it there")
            if run.state in ("interrupted", "queued"):
                self._set(run_id, state="aborted", finished_at=now(), error="aborted on request")
            return self.get(run_id)
        first = not a.aborting
        a.aborting = True
        if a.acq is not None:
            a.acq.abort()  # stops the actuators, keeps the frames
            if first:
                asyncio.get_running_loop().create_task(self._insist_abort(a))
        elif a.task is not None:
            if a.job is not None:
                a.job.kill()
            a.task.cancel()
        return self.get(run_id)

    async def _insist_abort(self, a: ActiveRun) -> None:
        """Repeat the abort until the run ends: a cancellation delivered while a device request is in flight can be
        absorbed by the device client (the request is retried), so one cancel is not always enough."""
        for _ in range(600):
            await asyncio.sleep(0.05)
            if a.task is None or a.task.done():
                return
            acq = a.acq
            if acq is not None:
                acq.abort()
            else:
                a.task.cancel()

    async def wait(self, run_id: str) -> None:
        a = self.active.get(run_id)
        if a is not None and a.task is not None:
            with contextlib.suppress(BaseException):
                await asyncio.shield(a.task)

    # -- pipeline ----------------------------------------------------------------------------------
    async def _execute(self, run_id: str, acquire: bool, resume: bool) -> None:
        a = self.active[run_id]
        t0 = time.monotonic()
        timings: dict[str, float] = dict(self.get(run_id).timings or {})
        try:
            self._set(run_id, started_at=now())
            if acquire:
                ts = time.monotonic()
                await self._acquire(run_id, a, resume)
                timings["acquisition_s"] = timings.get("acquisition_s", 0.0) + time.monotonic() - ts
                self._release(a)
            run = self.get(run_id)
            if run.methods:
                ts = time.monotonic()
                self._set(run_id, state="extracting", phase="extraction", done=0, total=0)
                await self._extract(run_id, run)
                timings["extraction_s"] = time.monotonic() - ts
                ts = time.monotonic()
                self._set(run_id, state="calibrating", phase="calibration", done=0, total=len(run.methods))
                doc = await self._calibrate(run_id, run)
                timings["calibration_s"] = time.monotonic() - ts
                await asyncio.to_thread(write_json_atomic, self.run_dir(run) / "result.json", doc)
                with self.db.session() as s:
                    s.execute(update(Run).where(Run.id == run_id).values(result=doc))
            timings["total_s"] = timings.get("total_s", 0.0) + time.monotonic() - t0
            self._set(run_id, state="done", finished_at=now(), timings=timings, phase="")
        except asyncio.CancelledError:
            timings["total_s"] = timings.get("total_s", 0.0) + time.monotonic() - t0
            if a.aborting:
                self._set(run_id, state="aborted", finished_at=now(), timings=timings, error="aborted on request")
            else:  # service shutting down: the run can be resumed on the next start
                self._set(
                    run_id,
                    state="interrupted",
                    timings=timings,
                    error="the service stopped during the run; resume it to continue",
                )
                raise
        except Exception as exc:
            from drivers.errors import AbortedError

            timings["total_s"] = timings.get("total_s", 0.0) + time.monotonic() - t0
            if isinstance(exc, AbortedError) or a.aborting:
                self._set(run_id, state="aborted", finished_at=now(), timings=timings, error="aborted on request")
            elif isinstance(exc, I4calError):
                self._set(run_id, state="failed", finished_at=now(), timings=timings, error=str(exc))
            else:
                log.exception("run %s failed", run_id)
                self._set(
                    run_id,
                    state="failed",
                    finished_at=now(),
                    timings=timings,
                    error=f"internal error: {type(exc).__name__}: {exc}",
                )
        finally:
            self._release(a)
            self.active.pop(run_id, None)
            self._close_subscribers(run_id)

    def _release(self, a: ActiveRun) -> None:
        if a.holds_bench and self.bench_holder == a.id:
            self.bench_holder = None
        a.holds_bench = False
        a.acq = None

    async def _acquire(self, run_id: str, a: ActiveRun, resume: bool) -> None:
        from calib.plan import Plan
        from drivers.acquisition import AcquisitionError, acquisition_from_config, close_devices
        from drivers.errors import FrameError

        assert self.bench is not None
        run = self.get(run_id)
        plan = Plan.model_validate(run.plan)
        cfg = self.bench.config
        out = self.dataset_path(run)
        out.parent.mkdir(parents=True, exist_ok=True)
        units = plan_units(plan)
        self._set(run_id, state="acquiring", phase="connecting", total=len(units))
        last_state = [""]

        def on_progress(p) -> None:
            a.last_frame = p.done - 1 if p.done else None
            nxt = units[p.done] if p.done < len(units) else None
            a.pose = list(nxt.q) if nxt is not None and nxt.q is not None else None
            with self.db.session() as s:
                s.execute(
                    update(Run).where(Run.id == run_id).values(done=p.done, total=p.total, phase=p.phase or p.state)
                )
            if p.state == "running":
                for d in self.bench.devices.values():
                    d.ok()
            if p.state != last_state[0] or p.message:
                last_state[0] = p.state
            self.emit(
                run_id,
                "progress",
                {
                    "stage": "acquisition",
                    "state": p.state,
                    "done": p.done,
                    "total": p.total,
                    "phase": p.phase,
                    "eta_s": p.eta_s,
                    "elapsed_s": p.elapsed_s,
                    "message": p.message,
                    "pose": a.pose,
                },
            )

        a.acq = acquisition_from_config(
            plan,
            cfg,
            out,
            resume=resume or out.joinpath("dataset.json").exists(),
            progress=on_progress,
            camera_spec=dict(self.bench.camera_spec),
            extra={"service_run": run_id},
        )
        if a.aborting:
            a.acq.abort()
        try:
            await a.acq.run()
        except AcquisitionError as exc:
            dev = "camera" if isinstance(exc.cause, FrameError) or "grab" in str(exc.cause).lower() else "actuators"
            self.bench.devices[dev].fail(str(exc.cause))
            raise
        finally:
            await close_devices(a.acq)

    # -- high-rate reports: batched ------------------------------------------------------------------
    def _queue_live(self, run_id: str, kind: str, data: dict[str, Any]) -> None:
        """Queue a high-rate report; :meth:`_flush_live` writes the batch at most every :data:`LIVE_INTERVAL_S`.

        ``kind``: ``progress`` (the latest replaces the previous), ``frames`` or ``iterations`` (appended).
        """
        pending = self._live.setdefault(run_id, {})
        if kind == "progress":
            pending["progress"] = data
        else:
            pending.setdefault(kind, []).append(data)
        if run_id not in self._live_timer:
            loop = asyncio.get_running_loop()
            delay = max(0.0, self._live_last.get(run_id, 0.0) + LIVE_INTERVAL_S - time.monotonic())
            self._live_timer[run_id] = loop.call_later(delay, self._flush_live, run_id)

    def _flush_live(self, run_id: str) -> None:
        timer = self._live_timer.pop(run_id, None)
        if timer is not None:
            timer.cancel()
        pending = self._live.pop(run_id, None)
        if not pending:
            return
        self._live_last[run_id] = time.monotonic()
        p = pending.pop("progress", None)
        if p is not None:
            with self.db.session() as s:
                s.execute(update(Run).where(Run.id == run_id).values(done=p["done"], total=p["total"]))
            self.emit(run_id, "progress", p)
        for kind, items in pending.items():
            self.emit(run_id, kind, {"count": len(items), "items": items})

    def _end_live(self, run_id: str) -> None:
        self._flush_live(run_id)
        self._live_last.pop(run_id, None)

    def _stage_progress(self, run_id: str, stage: str, done: int, total: int) -> None:
        with self.db.session() as s:
            s.execute(update(Run).where(Run.id == run_id).values(done=done, total=total))
        self.emit(run_id, "progress", {"stage": stage, "done": done, "total": total})

    # -- extraction and fits: child processes ---------------------------------------------------------
    async def _extract(self, run_id: str, run: Run) -> dict[str, Any]:
        """Extract the run's dataset in a child process into ``observations.json``; return the summary."""
        path = self.dataset_path(run)
        a = self.active[run_id]

        def on_event(kind: str, data: dict[str, Any]) -> None:
            if self.active.get(run_id) is not a:
                return
            if kind == "progress":
                self._queue_live(run_id, "progress", {"stage": "extraction", **data})
            elif kind == "frame":
                det = data.pop("detections", None)
                if det is not None:
                    a.detections[data["frame"]] = {"phase": data["phase"], **det}
                    a.last_extracted = a.last_frame = data["frame"]
                self._queue_live(run_id, "frames", data)

        try:
            summary = await run_job(
                "extract",
                {
                    "dataset": str(path),
                    "out": str(self.run_dir(run) / "observations.json"),
                    "workers": self.settings.extraction_workers,
                },
                on_event,
                nice=self.settings.job_niceness,
                on_job=lambda j: setattr(a, "job", j),
            )
        finally:
            self._end_live(run_id)
        with self.db.session() as s:
            s.execute(update(Run).where(Run.id == run_id).values(extraction=summary))
        self.emit(
            run_id,
            "extraction",
            {
                "phases": summary.get("phases", {}),
                "frames_with_missing": len(summary.get("frames", {})),
                "placement": summary.get("placement"),
            },
        )
        return summary

    async def _calibrate(self, run_id: str, run: Run) -> dict[str, Any]:
        """The methods one after the other in a child process (the fits hold the GIL); return the result."""
        a = self.active[run_id]
        n = len(run.methods)

        def on_event(kind: str, data: dict[str, Any]) -> None:
            if self.active.get(run_id) is not a:
                return
            if kind == "iteration":
                self._queue_live(run_id, "iterations", data)
            elif kind == "fit":
                self._flush_live(run_id)  # the iterations of a method come before its end
                self.emit(run_id, "fit", data)
                if data["state"] != "start":
                    self._stage_progress(run_id, "calibration", data["index"] + 1, n)

        try:
            return await run_job(
                "fit",
                {"observations": str(self.run_dir(run) / "observations.json"), "methods": list(run.methods)},
                on_event,
                nice=self.settings.job_niceness,
                on_job=lambda j: setattr(a, "job", j),
            )
        finally:
            self._end_live(run_id)

    def live_detections(self, run_id: str, index: int | None) -> tuple[int | None, dict[str, Any] | None]:
        """While a run extracts: the frame ``index`` (None: the last extracted one) and its detections, if any."""
        a = self.active.get(run_id)
        if a is None or a.last_extracted is None:
            return index, None
        i = a.last_extracted if index is None else index
        return i, a.detections.get(i)

    # -- calibration -------------------------------------------------------------------------------
    def apply(self, run_id: str, method: str | None) -> Calibration:
        from service import __version__

        run = self.get(run_id)
        if run.state != "done" or not run.result:
            raise RunConflictError(f"run is {run.state} without a result; nothing to apply")
        methods = run.result.get("methods", {})
        if method is None:
            method = next(
                (m for m in ("combined", "legs", "end-effector") if methods.get(m, {}).get("converged")), None
            )
            if method is None:
                raise RunConflictError("no method of this run converged; nothing to apply")
        entry = methods.get(method)
        if entry is None:
            raise InputError(f"run has no result for method {method!r}", field="method")
        if not entry.get("converged") or not entry.get("parameters"):
            raise RunConflictError(f"method {method!r} did not converge in this run; nothing to apply")
        bench = run.bench or self.name or "bench"
        payload = {
            "bench": bench,
            "run_id": run.id,
            "method": method,
            "software_version": __version__,
            "combinations": entry["parameters"],
            "combinations_std": entry.get("std"),
            "parameters": entry.get("seven"),
            "parameters_std": entry.get("seven_std"),
            "nominal": run.result.get("nominal"),
        }
        cal = Calibration(
            bench=bench,
            run_id=run.id,
            method=method,
            software_version=__version__,
            applied_at=now(),
            payload=clean_json(payload),
        )
        with self.db.session() as s:
            s.add(cal)
        self.emit(run_id, "applied", {"method": method})
        return cal

    def current_calibration(self, bench: str | None = None) -> Calibration | None:
        """The newest calibration applied to ``bench`` (default: this service's bench; without one: any bench)."""
        bench = bench or self.name
        with self.db.session() as s:
            q = select(Calibration).order_by(Calibration.applied_at.desc(), Calibration.id.desc()).limit(1)
            if bench:
                q = q.where(Calibration.bench == bench)
            return s.scalar(q)

    def calibration_history(self, limit: int = 100, offset: int = 0, bench: str | None = None) -> list[Calibration]:
        """Applied calibrations, newest first: of ``bench``, or of every bench."""
        with self.db.session() as s:
            q = select(Calibration).order_by(Calibration.applied_at.desc(), Calibration.id.desc())
            if bench:
                q = q.where(Calibration.bench == bench)
            return list(s.scalars(q.limit(limit).offset(offset)))

    # -- datasets ----------------------------------------------------------------------------------
    def delete_tree(self, path: Path) -> None:
        path = path.resolve()
        if self.data_dir in path.parents:
            shutil.rmtree(path, ignore_errors=True)


def plan_units(plan) -> list:
    from drivers.acquisition import plan_units as pu

    return pu(plan)
