"""The run manager: creates runs, moves them through the lifecycle (:mod:`service.runs.lifecycle`), and controls
them (pause, resume, abort). The stages themselves are in :mod:`service.runs.stages`.

One run at a time holds the bench; offline runs (from an uploaded dataset) never touch it. Every state change goes
through :meth:`RunManager.transition`, a compare-and-set on the run's row that the lifecycle's table allows, and
is persisted as an event pushed to the live subscribers.

No HTTP here: errors are :class:`RunConflictError` / :class:`RunNotFoundError` / :class:`calib.errors.InputError`,
turned into status codes by the routers.
"""

from __future__ import annotations

import asyncio
import builtins
import contextlib
import json
import logging
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from sqlalchemy import CursorResult, and_, delete, or_, select, update

from calib.errors import InputError
from service import failpoints
from service.db import Calibration, Database, DatasetRecord, Event, Run
from service.jobs import HEAVY_NICE_ABOVE_RUN, HeavyPool
from service.runs import calibrations
from service.runs.active import ActiveRun
from service.runs.bench import Bench
from service.runs.disk import DiskGuard, StorageError, data_usage_bytes, is_disk_full
from service.runs.events import EventBus, Subscription
from service.runs.lifecycle import (
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
from service.runs.stages import Stages
from service.settings import Settings
from service.timefmt import now_utc as now

log = logging.getLogger("i4cal.service")

ACTIVE_STATES = tuple(s.value for s in RunState if s in ACTIVE)
#: runs that ended (a failed run can still be resumed, but it ended)
TERMINAL_STATES = tuple(s.value for s in RunState if s in FINAL or s is RunState.FAILED)
#: seconds between two attempts to record the end of a run the database could not take (disk full)
HELD_RETRY_S = 0.5
STATES = tuple(s.value for s in RunState)


def new_id() -> str:
    return uuid.uuid4().hex


@dataclass
class HeldEnd:
    """A run's last transition that the database refused for want of space, recorded as soon as it takes it: until
    then the service reports the run in its ``target`` state (it is no longer executing)."""

    event: RunEvent
    values: dict[str, Any]
    target: RunState


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
        self.disk = DiskGuard(settings, self.data_dir)
        #: run id -> its end, not yet in the database (disk full); retried every HELD_RETRY_S
        self.held: dict[str, HeldEnd] = {}
        self._held_task: asyncio.Task | None = None
        failpoints.install()
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
                self.transition(
                    rid, RunEvent.INTERRUPT, error="the service stopped during the run; resume it to continue"
                )
        return ids

    async def shutdown(self) -> None:
        if self._held_task is not None:
            self._held_task.cancel()  # ends not recorded: the runs are marked interrupted at the next start
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
        return self._as_held(run)

    def _state_is(self, state: str) -> Any:
        """The condition "the run is in ``state``" as this service reports it (held ends included)."""
        cond: Any = Run.state == state
        here = [rid for rid, h in self.held.items() if h.target.value == state]
        gone = [rid for rid, h in self.held.items() if h.target.value != state]
        if here:
            cond = or_(cond, Run.id.in_(here))
        if gone:
            cond = and_(cond, Run.id.not_in(gone))
        return cond

    def _as_held(self, run: Run) -> Run:
        """The run as this service reports it: a run whose end the database could not take yet is in its end state
        (the detached row is changed, never written back)."""
        h = self.held.get(run.id)
        if h is not None:
            run.state = h.target.value
            for k, v in h.values.items():
                setattr(run, k, v)
        return run

    def list(self, limit: int = 100, offset: int = 0, state: str | None = None, bench: str | None = None) -> list[Run]:
        with self.db.session() as s:
            q = select(Run).order_by(Run.created_at.desc()).limit(limit).offset(offset)
            if state:
                q = q.where(self._state_is(state))
            if bench:
                q = q.where(Run.bench == bench)
            rows = list(s.scalars(q))
        return [self._as_held(r) for r in rows]

    def update(self, run_id: str, **values: Any) -> None:
        """Set fields of the run's row other than its state (the state moves only by :meth:`transition`)."""
        if "state" in values:
            raise ValueError("the state changes only through a lifecycle transition")
        with self.db.session() as s:
            s.execute(update(Run).where(Run.id == run_id).values(**values))

    def transition(self, run_id: str, event: RunEvent, **values: Any) -> RunState:
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
            # an UPDATE's result is a CursorResult (rowcount); Session.execute is typed for any statement
            res = cast(
                "CursorResult[Any]",
                s.execute(update(Run).where(Run.id == run_id, Run.state == cur).values(state=new.value, **values)),
            )
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
            from calib.formats.plan import Plan

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
        methods: builtins.list[str],  # builtins: the class's own list() shadows the name
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
        # without dataset_id, self.bench was checked above
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
        try:
            (self.data_dir / "runs" / rid).mkdir(parents=True, exist_ok=True)
            with self.db.session() as s:
                s.add(run)
            self.bus.emit(rid, "state", {"state": RunState.QUEUED.value})
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            self._forget(rid)
            raise StorageError(
                f"disk full: the data disk ({self.data_dir}) refused to record the new run; free space "
                "(DELETE /api/v1/runs/ID, /api/v1/datasets/ID)",
                "disk full",
            ) from None
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
            try:
                self.emit(run_id, "resumed", {})
            except Exception as exc:
                if not is_disk_full(exc):
                    raise
                raise StorageError(
                    f"disk full: the data disk ({self.data_dir}) refuses to write; the acquisition stays paused: "
                    "free space and resume again",
                    "disk full",
                ) from None
            a.acq.resume()
            a.paused = False
            return self.get(run_id)
        if not self.owns(run):
            raise RunConflictError(f"run belongs to the service of bench {run.service!r}; resume it there")
        next_state(run.state, RunEvent.RESUME)  # only checks: raises before anything changes
        if run_id in self.held and not self._record_held(run_id):
            raise StorageError(
                f"disk full: the database on the data disk ({self.data_dir}) cannot record the run's end yet; "
                "free space and resume again",
                "disk full",
            )
        todo = self.remaining(run)
        if todo.acquire:
            if self.bench is None:
                raise RunConflictError("this service has no bench; the run's acquisition cannot continue here")
            if (busy := self.bench_busy()) is not None:
                raise RunConflictError(busy)
        self.transition(run_id, RunEvent.RESUME, error=None, finished_at=None)
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
        try:
            self.emit(run_id, "paused", {})
        except Exception as exc:  # a full disk does not keep the bench from pausing
            if not is_disk_full(exc):
                raise
            log.error("run %s paused; its 'paused' event not recorded (disk full)", run_id)
        return self.get(run_id)

    def abort(self, run_id: str) -> Run:
        run = self.get(run_id)
        a = self.active.get(run_id)
        if a is None:
            if not self.owns(run) and run.state not in FINAL:
                raise RunConflictError(f"run belongs to the service of bench {run.service!r}; abort it there")
            with contextlib.suppress(IllegalTransitionError):  # a final run: abort is a no-op
                self.transition(run_id, RunEvent.ABORT, finished_at=now(), error="aborted on request")
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

    def calibration_history(
        self, limit: int = 100, offset: int = 0, bench: str | None = None
    ) -> builtins.list[Calibration]:
        """Applied calibrations, newest first: of ``bench``, or of every bench."""
        return calibrations.history(self.db, limit, offset, bench)

    # -- disk ------------------------------------------------------------------------------------------
    def hold_end(self, run_id: str, event: RunEvent, values: dict[str, Any]) -> None:
        """Keep the run's end the database refused (disk full) and record it as soon as the database takes it."""
        cur = self.get(run_id).state
        self.held[run_id] = HeldEnd(event, dict(values), next_state(cur, event))
        if self._held_task is None or self._held_task.done():
            self._held_task = asyncio.get_running_loop().create_task(self._retry_held(), name="record-held-ends")

    def _record_held(self, run_id: str) -> bool:
        """Write a held end (its transition, or only its ``state`` event if the transition went through before the
        event was refused); False while the database still refuses."""
        h = self.held.get(run_id)
        if h is None:
            return True
        try:
            with self.db.session() as s:
                cur = s.scalar(select(Run.state).where(Run.id == run_id))
            if cur is None or cur == h.target.value:
                if cur is not None:
                    err = h.values.get("error")
                    self.bus.emit(run_id, "state", {"state": h.target.value, **({"error": err} if err else {})})
            else:
                self.held.pop(run_id)  # transition computes from the row, not from the overlay
                try:
                    self.transition(run_id, h.event, **h.values)
                except BaseException:
                    self.held[run_id] = h
                    raise
        except IllegalTransitionError as exc:
            log.warning("run %s: held end not recorded: %s", run_id, exc)
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            return False
        self.held.pop(run_id, None)
        return True

    def flush_held(self) -> bool:
        """Try to record every held end; whether none is left."""
        return all([self._record_held(rid) for rid in list(self.held)])

    async def _retry_held(self) -> None:
        while self.held:
            await asyncio.sleep(HELD_RETRY_S)
            try:
                self.flush_held()
            except Exception:
                log.exception("recording a held run end failed")

    def _space_check_held(self, what: str) -> None:
        """Refuse while an end is held (the database refused it; the event loop retries it every HELD_RETRY_S).
        Only reads: called from a worker thread, it writes nothing (the events reach the loop's subscribers)."""
        if self.held:
            raise StorageError(
                f"disk full: the database on the data disk ({self.data_dir}) refuses to write (the end of run(s) "
                f"{', '.join(sorted(self.held))} is not recorded yet); {what} cannot start: free space",
                "disk full",
            )

    def check_space_for_run(self, plan: Any | None) -> None:
        """Before a run: its plan's frames (none for an offline run, ``plan`` None) times the expected frame size,
        with margin, must fit in the quota and the free space, and the disk must take a write (:class:`StorageError`
        otherwise). Walks the data directory: call it off the event loop."""
        self._space_check_held("a new run")
        frames = 0 if plan is None else len(plan_units(plan))
        need = self.disk.run_bytes(frames, self.disk.frame_bytes(self.bench))
        self.disk.check(need, f"the run ({frames} frames)")

    def check_space_for_resume(self, run_id: str) -> None:
        """Before a resume: the frames still to acquire (or a little for the observations and the result) must fit,
        and the run's end must be recorded (not held). Call it off the event loop."""
        run = self.get(run_id)
        if run_id in self.held:
            raise StorageError(
                f"disk full: the database on the data disk ({self.data_dir}) cannot record the run's end yet; "
                "free space and resume again",
                "disk full",
            )
        if run.state not in (RunState.FAILED.value, RunState.INTERRUPTED.value) or not self.owns(run):
            return  # resume refuses it (or resumes a pause in place): nothing to write
        frames = 0
        if run.plan is not None and run.source_dataset is None:
            frames = max(0, (run.total or 0) - self.frames_on_disk(run))
        need = self.disk.run_bytes(frames, self.disk.frame_bytes(self.bench))
        self.disk.check(need, f"the resumed run ({frames} frames to acquire)")

    def _forget(self, run_id: str) -> None:
        """Remove a run that was never recorded (its directory)."""
        self.delete_tree(self.data_dir / "runs" / run_id)

    # -- retention ------------------------------------------------------------------------------------
    def delete_run(self, run_id: str) -> tuple[Path, int]:
        """Delete a run that is not executing: its row, its events, its files (``runs/<id>``: dataset,
        observations, result). Returns the directory to remove and its size; the caller removes it
        (:meth:`delete_tree`, off the event loop).

        Raises
        ------
        RunNotFoundError
        RunConflictError
            The run is executing or holds the bench, belongs to another service (its files are on that service's
            disk), or its result was applied (the current calibration or the history refer to it).
        """
        run = self.get(run_id)
        if run_id in self.held:
            raise RunConflictError("the run's end is not recorded yet (the disk is full); free space first")
        if run_id in self.active or run.state in ACTIVE_STATES:
            holds = " and holds the bench" if self.bench_holder == run_id else ""
            raise RunConflictError(f"run is {run.state}{holds}; abort it first (POST /api/v1/runs/{run_id}/abort)")
        if not self.owns(run):
            raise RunConflictError(
                f"run belongs to the service of bench {run.service!r} (its files are on that service's disk); "
                "delete it there"
            )
        with self.db.session() as s:
            cals = list(s.scalars(select(Calibration).where(Calibration.run_id == run_id)))
        if cals:
            cur = calibrations.current(self.db, run.bench)
            if cur is not None and cur.run_id == run_id:
                raise RunConflictError(
                    f"run's result is bench {run.bench!r}'s current calibration (calibration {cur.id}, "
                    f"{cur.method}); apply another run's result first"
                )
            raise RunConflictError(
                f"run's result was applied (calibration {', '.join(str(c.id) for c in cals)} in "
                f"bench {run.bench!r}'s history, which names the run as its provenance); it is kept"
            )
        path = self.data_dir / "runs" / run_id
        size = data_usage_bytes(path)

        def remove_rows() -> None:
            with self.db.session() as s:
                s.execute(delete(Event).where(Event.run_id == run_id))
                # a DELETE's result is a CursorResult (rowcount); Session.execute is typed for any statement
                res = cast("CursorResult[Any]", s.execute(delete(Run).where(Run.id == run_id, Run.state == run.state)))
                if res.rowcount != 1:
                    raise IllegalTransitionError(run.state, RunEvent.ABORT)

        try:
            remove_rows()
        except IllegalTransitionError:
            raise RunConflictError("the run changed meanwhile; try again") from None
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            # the database needs room to delete: the run's files go first, then its rows
            self.delete_tree(path)
            try:
                remove_rows()
            except Exception as exc2:
                if not is_disk_full(exc2):
                    raise
                raise StorageError(
                    f"disk full: the run's files were removed but the database on the data disk ({self.data_dir}) "
                    "cannot record it; free space and delete it again",
                    "disk full",
                ) from None
        self.bus.forget(run_id)
        return path, size

    def delete_dataset(self, dataset_id: str) -> tuple[Path, int] | None:
        """Delete an uploaded dataset (row and files) that no run may still read. Returns its directory and size
        (None: no such dataset); the caller removes the directory (:meth:`delete_tree`, off the event loop).

        Raises
        ------
        RunConflictError
            A run that is not ``done`` or ``aborted`` calibrates it (it may still read it), or it is not on this
            service's disk.
        """
        with self.db.session() as s:
            rec = s.get(DatasetRecord, dataset_id)
            if rec is None:
                return None
            users = list(
                s.execute(
                    select(Run.id, Run.state).where(
                        Run.source_dataset == dataset_id, Run.state.not_in(("done", "aborted"))
                    )
                )
            )
        if users:
            named = ", ".join(f"{rid} ({st})" for rid, st in users[:5])
            raise RunConflictError(
                f"dataset is calibrated by run(s) that may still read it: {named}; let them finish, or abort or "
                "delete them first"
            )
        path = self.data_dir / "datasets" / dataset_id
        if not path.is_dir():
            raise RunConflictError(
                "dataset is not on this service's disk (uploaded to another service sharing the database?); "
                "delete it there"
            )
        size = data_usage_bytes(path)
        try:
            with self.db.session() as s:
                s.execute(delete(DatasetRecord).where(DatasetRecord.id == dataset_id))
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            self.delete_tree(path)  # the database needs room to delete: the files go first
            try:
                with self.db.session() as s:
                    s.execute(delete(DatasetRecord).where(DatasetRecord.id == dataset_id))
            except Exception as exc2:
                if not is_disk_full(exc2):
                    raise
                raise StorageError(
                    f"disk full: the dataset's files were removed but the database on the data disk ({self.data_dir}) "
                    "cannot record it; free space and delete it again",
                    "disk full",
                ) from None
        return path, size

    # -- datasets ----------------------------------------------------------------------------------
    def delete_tree(self, path: Path) -> None:
        path = path.resolve()
        if self.data_dir in path.parents:
            shutil.rmtree(path, ignore_errors=True)


def plan_units(plan) -> list:
    from drivers.acquisition.acquire import plan_units as pu

    return pu(plan)
