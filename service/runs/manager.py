"""The run manager: creates runs, moves them through the lifecycle (:mod:`service.runs.lifecycle`), and controls
them (pause, resume, abort). The stages themselves are in :mod:`service.runs.stages`.

One run at a time holds the bench; offline runs (from an uploaded dataset) never touch it. Every state change goes
through :meth:`RunManager._transition`, a compare-and-set on the run's row that the lifecycle's table allows, and
is persisted as an event pushed to the live subscribers.

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
from pathlib import Path
from typing import Any

from sqlalchemy import or_, select, update

from calib.errors import InputError

from .. import failpoints
from ..db import Calibration, Database, DatasetRecord, Run
from ..jobs import HEAVY_NICE_ABOVE_RUN, HeavyPool
from ..settings import Settings
from ..timefmt import now_utc as now
from . import calibrations
from .bench import Bench
from .events import EventBus, Subscription
from .lifecycle import (
    ACTIVE,
    FINAL,
    IllegalTransitionError,
    Remaining,
    RunConflictError,
    RunEvent,
    RunNotFoundError,
    RunState,
    next_state,
    remaining_stages,
)
from .stages import Stages

log = logging.getLogger("i4cal.service")

ACTIVE_STATES = tuple(s.value for s in RunState if s in ACTIVE)
#: runs that ended (a failed run can still be resumed, but it ended)
TERMINAL_STATES = tuple(s.value for s in RunState if s in FINAL or s is RunState.FAILED)
STATES = tuple(s.value for s in RunState)


def new_id() -> str:
    return uuid.uuid4().hex


@dataclass
class ActiveRun:
    id: str
    remaining: Remaining
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
        #: the devices are being probed (GET /devices?probe=true): no run starts meanwhile (a second Modbus master)
        self.probing = False
        self.bus = EventBus(db)
        self.data_dir = settings.data_dir.resolve()
        #: this service's name in a shared database: its bench's (None: no bench and no bench_name)
        self.name: str | None = bench.name if bench is not None else settings.bench_name
        self.stages = Stages(self)
        #: the CPU-heavy requests' pool (plan design, prediction, trade-off, report): child processes niced below the
        #: run's, a bounded queue (429 beyond)
        self.heavy = HeavyPool(nice=min(19, settings.job_niceness + HEAVY_NICE_ABOVE_RUN))

    def owns(self, run: Run) -> bool:
        """Whether this service executes ``run`` (runs of services sharing the database are theirs to control)."""
        return run.service is None or run.service == self.name

    # -- events (the routers' view) ------------------------------------------------------------------
    def emit(self, run_id: str, type_: str, data: dict[str, Any]) -> None:
        self.bus.emit(run_id, type_, data)

    def subscribe(self, run_id: str) -> Subscription:
        return self.bus.subscribe(run_id)

    def unsubscribe(self, run_id: str, q: Subscription) -> None:
        self.bus.unsubscribe(run_id, q)

    def events(self, run_id: str, after: int = 0) -> list[dict[str, Any]]:
        return self.bus.events(run_id, after)

    # -- life --------------------------------------------------------------------------------------
    def recover(self) -> list[str]:
        """Runs left active by a crash become ``interrupted`` (their frames are kept)."""
        with self.db.session() as s:
            mine = Run.service.is_(None) if self.name is None else or_(Run.service == self.name, Run.service.is_(None))
            ids = list(s.scalars(select(Run.id).where(Run.state.in_(ACTIVE_STATES), mine)))
        for rid in ids:
            with contextlib.suppress(IllegalTransitionError):
                self._transition(
                    rid, RunEvent.INTERRUPT, error="the service stopped during the run; resume it to continue"
                )
        return ids

    async def shutdown(self) -> None:
        for a in list(self.active.values()):
            if a.task is not None and not a.task.done():
                a.task.cancel()
        for a in list(self.active.values()):
            if a.task is not None:
                with contextlib.suppress(BaseException):
                    await asyncio.wait_for(a.task, 10)

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

    def update(self, run_id: str, **values: Any) -> None:
        """Set fields of the run's row other than its state (the state moves only by :meth:`_transition`)."""
        if "state" in values:
            raise ValueError("the state changes only through a lifecycle transition")
        with self.db.session() as s:
            s.execute(update(Run).where(Run.id == run_id).values(**values))

    def _transition(self, run_id: str, event: RunEvent, **values: Any) -> RunState:
        """Move the run by ``event`` (compare-and-set on its current state) with ``values``; emit the state event.

        Raises
        ------
        IllegalTransitionError
            The lifecycle does not allow ``event`` in the run's state, or another request moved it meanwhile; the
            run is left as it was.
        """
        with self.db.session() as s:
            cur = s.scalar(select(Run.state).where(Run.id == run_id))
            if cur is None:
                raise RunNotFoundError(run_id)
            new = next_state(cur, event)
            res = s.execute(update(Run).where(Run.id == run_id, Run.state == cur).values(state=new.value, **values))
            if res.rowcount != 1:
                raise IllegalTransitionError(cur, event)
        err = values.get("error")
        self.bus.emit(run_id, "state", {"state": new.value, **({"error": err} if err else {})})
        failpoints.hit(f"state:{new.value}")
        return new

    def bench_busy(self) -> str | None:
        """Why the bench cannot be taken now (a run holds it, or its devices are being probed); None: it is free."""
        if self.bench_holder is not None:
            return f"run {self.bench_holder} holds the bench"
        if self.probing:
            return "the bench's devices are being probed (GET /devices?probe=true); try again in a few seconds"
        return None

    async def probe(self) -> None:
        """Connect to the bench's devices briefly and record their state, only while no run holds the bench; no run
        starts meanwhile (its connections would be a second master on the devices' line).

        Raises
        ------
        RunConflictError
            A run holds the bench, or another probe is under way.
        """
        if self.bench is None:
            return
        busy = self.bench_busy()
        if busy is not None:
            raise RunConflictError(busy)
        self.probing = True
        try:
            await self.bench.probe()
        finally:
            self.probing = False

    def run_dir(self, run: Run) -> Path:
        return self.data_dir / "runs" / run.id

    def dataset_path(self, run: Run) -> Path:
        return self.data_dir / run.dataset_dir

    # -- what is on disk -----------------------------------------------------------------------------
    def frames_on_disk(self, run: Run) -> int:
        """Frames of the run's dataset written so far (0 without a readable ``dataset.json``)."""
        meta = self.dataset_path(run) / "dataset.json"
        try:
            return len(json.loads(meta.read_text(encoding="utf-8")).get("frames", []))
        except (OSError, ValueError, AttributeError):
            return 0

    def remaining(self, run: Run) -> Remaining:
        """What is left of ``run``, decided from its files (:func:`service.runs.lifecycle.remaining_stages`)."""
        offline = run.source_dataset is not None or run.plan is None
        plan_frames = 0
        if not offline:
            from calib.plan import Plan

            plan_frames = len(plan_units(Plan.model_validate(run.plan)))
        return remaining_stages(
            offline=offline,
            plan_frames=plan_frames,
            frames_on_disk=0 if offline else self.frames_on_disk(run),
            methods=len(run.methods or []),
            observations_on_disk=run.extraction is not None and (self.run_dir(run) / "observations.json").is_file(),
            result_on_disk=run.result is not None,
        )

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
            if (busy := self.bench_busy()) is not None:
                raise RunConflictError(busy)
            ds_dir = f"runs/{rid}/dataset"
        run_bench = (bench or self.name) if dataset_id else self.bench.name  # type: ignore[union-attr]
        run = Run(
            id=rid,
            state=RunState.QUEUED.value,
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
        self.bus.emit(rid, "state", {"state": RunState.QUEUED.value})
        failpoints.hit("state:queued")
        self._start(run, self.remaining(run))
        return run

    def _start(self, run: Run, remaining: Remaining) -> None:
        """Start executing ``run`` (its state is ``queued``; the caller checked the bench is free if it acquires)."""
        a = ActiveRun(run.id, remaining)
        if remaining.acquire:
            self.bench_holder = run.id
            a.holds_bench = True
        self.active[run.id] = a
        a.task = asyncio.get_running_loop().create_task(self.stages.execute(run.id, a), name=f"run-{run.id}")

    def resume(self, run_id: str) -> Run:
        """Resume a paused acquisition in place, or a failed or interrupted run from what is on disk.

        Everything is checked before the run changes: a refused resume leaves it as it was. A run whose frames are
        all on disk does not acquire again (nothing moves).
        """
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is not None:
            if a.acq is None or run.state != RunState.ACQUIRING:
                raise RunConflictError(f"run is {run.state}; only an acquisition can be paused and resumed")
            if not a.paused:  # a duplicate resume: nothing to do, and no second 'resumed' event
                raise RunConflictError("run is acquiring and not paused; nothing to resume")
            a.acq.resume()
            a.paused = False
            self.emit(run_id, "resumed", {})
            return self.get(run_id)
        if not self.owns(run):
            raise RunConflictError(f"run belongs to the service of bench {run.service!r}; resume it there")
        next_state(run.state, RunEvent.RESUME)  # only checks: raises before anything changes
        todo = self.remaining(run)
        if todo.acquire:
            if self.bench is None:
                raise RunConflictError("this service has no bench; the run's acquisition cannot continue here")
            if (busy := self.bench_busy()) is not None:
                raise RunConflictError(busy)
        self._transition(run_id, RunEvent.RESUME, error=None, finished_at=None)
        self._start(run, todo)
        return self.get(run_id)

    def pause(self, run_id: str) -> Run:
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is None or a.acq is None or run.state != RunState.ACQUIRING:
            raise RunConflictError(f"run is {run.state}; only an acquisition can be paused")
        if a.paused:  # a duplicate pause: no second 'paused' event
            raise RunConflictError("run is already paused")
        a.acq.pause()
        a.paused = True
        self.emit(run_id, "paused", {})
        return self.get(run_id)

    def abort(self, run_id: str) -> Run:
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is None:
            if not self.owns(run) and run.state not in FINAL:
                raise RunConflictError(f"run belongs to the service of bench {run.service!r}; abort it there")
            with contextlib.suppress(IllegalTransitionError):  # a final run: abort is a no-op
                self._transition(run_id, RunEvent.ABORT, finished_at=now(), error="aborted on request")
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

    def release(self, a: ActiveRun) -> None:
        if a.holds_bench and self.bench_holder == a.id:
            self.bench_holder = None
        a.holds_bench = False
        a.acq = None

    def live_detections(self, run_id: str, index: int | None) -> tuple[int | None, dict[str, Any] | None]:
        """While a run extracts: the frame ``index`` (None: the last extracted one) and its detections, if any."""
        a = self.active.get(run_id)
        if a is None or a.last_extracted is None:
            return index, None
        i = a.last_extracted if index is None else index
        return i, a.detections.get(i)

    # -- calibration -------------------------------------------------------------------------------
    def apply(self, run_id: str, method: str | None) -> Calibration:
        cal = calibrations.store(self.db, calibrations.calibration_from_run(self.get(run_id), method, self.name))
        self.emit(run_id, "applied", {"method": cal.method})
        return cal

    def current_calibration(self, bench: str | None = None) -> Calibration | None:
        """The newest calibration applied to ``bench`` (default: this service's bench; without one: any bench)."""
        return calibrations.current(self.db, bench or self.name)

    def calibration_history(self, limit: int = 100, offset: int = 0, bench: str | None = None) -> list[Calibration]:
        """Applied calibrations, newest first: of ``bench``, or of every bench."""
        return calibrations.history(self.db, limit, offset, bench)

    # -- datasets ----------------------------------------------------------------------------------
    def delete_tree(self, path: Path) -> None:
        path = path.resolve()
        if self.data_dir in path.parents:
            shutil.rmtree(path, ignore_errors=True)


def plan_units(plan) -> list:
    from drivers.acquisition import plan_units as pu

    return pu(plan)
