"""The stages of a run: acquisition (async, in the event loop), extraction and fits (child processes,
:mod:`service.jobs`), executed in the order :class:`service.runs.lifecycle.Remaining` gives; each stage starts with
its lifecycle transition.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import TYPE_CHECKING, Any, Protocol

from calib.errors import I4calError
from calib.numerics.jsonio import write_json_atomic
from service import failpoints
from service.db import Run
from service.jobs import merge_method, one_line, run_job
from service.runs.active import ActiveRun
from service.runs.disk import disk_full_reason, is_disk_full
from service.runs.lifecycle import IllegalTransitionError, RunEvent
from service.timefmt import now_utc as _now

if TYPE_CHECKING:
    from pathlib import Path

    from drivers.acquisition.streaming import FrameStream
    from service.jobs import HeavyPool
    from service.runs.bench import Bench
    from service.runs.events import EventBus
    from service.runs.lifecycle import RunState
    from service.settings import Settings

log = logging.getLogger("i4cal.service")

#: the longest the end of a run waits for the stream worker's last frames (s); beyond, extraction measures them
STREAM_FINISH_TIMEOUT_S = 60.0


class RunControl(Protocol):
    """What the stages need of the run manager (:class:`service.runs.manager.RunManager`): the run's row, its
    events, its state's transitions, its files, the bench it holds."""

    active: dict[str, ActiveRun]
    bench: Bench | None
    bus: EventBus
    data_dir: Path
    settings: Settings
    heavy: HeavyPool

    def get(self, run_id: str) -> Run: ...
    def update(self, run_id: str, **values: Any) -> None: ...
    def emit(self, run_id: str, type_: str, data: dict[str, Any]) -> None: ...
    def transition(self, run_id: str, event: RunEvent, **values: Any) -> RunState: ...
    def run_dir(self, run: Run) -> Path: ...
    def dataset_path(self, run: Run) -> Path: ...
    def release(self, a: ActiveRun) -> None: ...
    def hold_end(self, run_id: str, event: RunEvent, values: dict[str, Any]) -> None: ...


class Stages:
    """Executes runs for a :class:`RunControl` (the run manager)."""

    def __init__(self, manager: RunControl) -> None:
        self.m = manager

    async def execute(self, run_id: str, a: ActiveRun) -> None:
        m, todo = self.m, a.remaining
        t0 = time.monotonic()
        run = m.get(run_id)
        # the timings of every stage of every attempt (a resumed run adds to what its earlier attempts took); stored
        # as each stage ends, so a crash (SIGKILL) loses only the stage under way
        timings: dict[str, float] = dict(run.timings or {})
        total0 = timings.get("total_s", 0.0)

        def stage_done(key: str, since: float) -> None:
            timings[key] = timings.get(key, 0.0) + time.monotonic() - since
            timings["total_s"] = total0 + time.monotonic() - t0
            m.update(run_id, timings=dict(timings))

        predicting = None
        stage = "start"
        if run.plan is not None and run.prediction is None and m.bench is not None:
            predicting = asyncio.create_task(self.predict(run_id, run))
        try:
            if run.started_at is None:
                m.update(run_id, started_at=_now())
            if todo.acquire:
                stage = "acquisition"
                ts = time.monotonic()
                stream = self.start_stream(run_id, run) if todo.extract else None
                try:
                    await self.acquire(run_id, a, stream)
                except BaseException:
                    if stream is not None:
                        stream.close()
                    raise
                stage_done("acquisition_s", ts)
                m.release(a)
                failpoints.hit("stage:acquired")
                if stream is not None:
                    a.streamed = await self.finish_stream(run_id, stream)
            run = m.get(run_id)
            if todo.extract:
                stage = "extraction"
                ts = time.monotonic()
                m.transition(run_id, RunEvent.EXTRACT, phase="extraction", done=0, total=0)
                await self.extract(run_id, run)
                stage_done("extraction_s", ts)
            if todo.calibrate:
                stage = "calibration"
                ts = time.monotonic()
                m.transition(run_id, RunEvent.CALIBRATE, phase="calibration", done=0, total=len(run.methods))
                doc = await self.calibrate(run_id, run)
                stage_done("calibration_s", ts)
                await asyncio.to_thread(write_json_atomic, m.run_dir(run) / "result.json", doc)
                m.update(run_id, result=doc)
            if predicting is not None:  # computed while the bench moved: done long before a run's end
                await predicting
            stage = "end of the run"
            timings["total_s"] = total0 + time.monotonic() - t0
            m.transition(run_id, RunEvent.FINISH, finished_at=_now(), timings=timings, phase="")
        except asyncio.CancelledError:
            # the service stops or the run is aborted: nobody waits for the prediction (a resumed run predicts again)
            if predicting is not None:
                predicting.cancel()
            timings["total_s"] = total0 + time.monotonic() - t0
            if a.aborting:
                self._end(run_id, RunEvent.ABORT, finished_at=_now(), timings=timings, error="aborted on request")
            else:  # service shutting down: the run can be resumed on the next start
                self._end(
                    run_id,
                    RunEvent.INTERRUPT,
                    timings=timings,
                    error="the service stopped during the run; resume it to continue",
                )
                raise
        except Exception as exc:
            from drivers.errors import AbortedError

            timings["total_s"] = total0 + time.monotonic() - t0
            if isinstance(exc, AbortedError) or a.aborting:
                self._end(run_id, RunEvent.ABORT, finished_at=_now(), timings=timings, error="aborted on request")
            elif is_disk_full(exc):  # resumable from what is on disk once there is room again
                reason = disk_full_reason(exc, m.data_dir, stage)
                log.error("run %s: %s", run_id, reason)
                self._end(run_id, RunEvent.FAIL, finished_at=_now(), timings=timings, error=reason)
            elif isinstance(exc, I4calError):
                self._end(run_id, RunEvent.FAIL, finished_at=_now(), timings=timings, error=one_line(str(exc)))
            else:
                log.exception("run %s failed", run_id)
                self._end(
                    run_id,
                    RunEvent.FAIL,
                    finished_at=_now(),
                    timings=timings,
                    error=one_line(f"internal error: {type(exc).__name__}: {exc}"),
                )
        finally:
            m.release(a)
            m.active.pop(run_id, None)
            m.bus.close_subscribers(run_id)

    def _end(self, run_id: str, event: RunEvent, **values: Any) -> None:
        """The run's last transition; a run another request already ended stays as it is. A database that refuses
        it for want of space: the end is held and recorded as soon as it can be (:meth:`RunManager.hold_end`)."""
        try:
            self.m.transition(run_id, event, **values)
        except IllegalTransitionError as exc:
            log.warning("run %s: %s", run_id, exc)
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            log.error("run %s: the database cannot record its end (disk full); held until it can", run_id)
            self.m.hold_end(run_id, event, values)

    async def predict(self, run_id: str, run: Run) -> None:
        """The plan's prediction before motion (:func:`service.design.run_prediction`: predicted std per method and
        combination, motion time), computed in a child process (niced as the run's other jobs: the server's event
        loop keeps its CPU) while the bench moves and stored with the run as soon as it is ready (event
        ``prediction``). A prediction that fails is stored as its error; it never fails the run."""
        m = self.m
        assert m.bench is not None
        try:
            doc = await m.heavy.run_now(
                "run_prediction",
                m.settings.job_niceness,
                config=m.bench.config,
                plan=run.plan,
                methods=list(run.methods or []),
                camera=m.bench.camera_model,
            )
        except Exception as exc:  # the prediction is advice: the run goes on without it
            log.warning("run %s: no prediction: %s", run_id, exc)
            doc = {"error": one_line(f"{type(exc).__name__}: {exc}")}
        if doc is None:
            return
        try:
            m.update(run_id, prediction=doc)
            m.emit(run_id, "prediction", {"predicted_std_m": doc.get("predicted_std_m"), "error": doc.get("error")})
        except Exception as exc:  # e.g. the service closed its database while the prediction was computed
            log.warning("run %s: prediction not stored: %s", run_id, exc)

    # -- acquisition ---------------------------------------------------------------------------------
    # -- streaming: each frame measured while the bench moves to the next pose ------------------------------
    def start_stream(self, run_id: str, run: Run) -> FrameStream | None:
        """The worker that measures each frame as the acquisition writes it (:mod:`drivers.acquisition.streaming`); its
        reports
        are the run's ``streamed`` events (batched). None when the service does not stream (``stream_extraction``)."""
        from drivers.acquisition.streaming import FrameStream

        m = self.m
        if not m.settings.stream_extraction:
            return None
        loop = asyncio.get_running_loop()

        def on_event(kind: str, data: dict[str, Any]) -> None:  # the stream's reader thread
            loop.call_soon_threadsafe(self._stream_event, run_id, kind, data)

        stream = FrameStream(
            m.dataset_path(run), m.run_dir(run) / "streamed.json", on_event=on_event, nice=m.settings.job_niceness
        ).start()
        stream.submit_recorded()  # a resumed run's frames already on disk
        return stream

    def _stream_event(self, run_id: str, kind: str, data: dict[str, Any]) -> None:
        m = self.m
        if run_id not in m.active:
            return
        if kind == "frame":
            m.bus.queue_live(run_id, "streamed", data)
        elif kind == "failed":
            m.bus.queue_live(run_id, "streamed", {**data, "failed": data["reason"]})
        elif kind == "off":
            m.emit(run_id, "streaming", {"state": "off", "reason": data["reason"]})

    async def finish_stream(self, run_id: str, stream: FrameStream) -> str | None:
        """Wait for the worker's last frames (seconds at most: it measured while the bench moved); the file of the
        frames it measured, for the extraction."""
        m = self.m
        summary = await asyncio.to_thread(stream.finish, STREAM_FINISH_TIMEOUT_S)
        with contextlib.suppress(Exception):
            m.bus.flush_live(run_id)
        data = {"state": "done", **(summary or {"measured": stream.measured, "submitted": stream.submitted})}
        data.pop("file", None)
        if summary is None:
            data["reason"] = "the stream worker gave no result: every frame is measured now"
        m.emit(run_id, "streaming", data)
        return None if summary is None else summary.get("file")

    async def acquire(self, run_id: str, a: ActiveRun, stream: FrameStream | None = None) -> None:
        from calib.formats.plan import Plan
        from drivers.acquisition.acquire import AcquisitionError, acquisition_from_config, close_devices, plan_units
        from drivers.acquisition.settings import DatasetHeader
        from drivers.errors import FrameError

        m = self.m
        assert m.bench is not None
        bench = m.bench
        run = m.get(run_id)
        plan = Plan.model_validate(run.plan)
        out = m.dataset_path(run)
        out.parent.mkdir(parents=True, exist_ok=True)
        units = plan_units(plan)
        m.transition(run_id, RunEvent.ACQUIRE, phase="connecting", total=len(units))

        def on_progress(p) -> None:
            a.last_frame = p.done - 1 if p.done else None
            nxt = units[p.done] if p.done < len(units) else None
            a.pose = list(nxt.q) if nxt is not None and nxt.q is not None else None
            m.update(run_id, done=p.done, total=p.total, phase=p.phase or p.state)
            suspension = getattr(a.acq, "suspension", None)
            if (
                p.state == "suspended"
            ):  # drivers.acquisition.suspenders: held at the pose; why, in the event and the status
                a.suspended = p.message
                a.paused = a.paused or bool(suspension and suspension.waits_for_user)  # POST .../resume resumes it
                m.emit(run_id, "suspended", {"reason": p.message, "frame": p.done})
            elif a.suspended and p.state == "running" and not (suspension and suspension.reason):
                a.suspended, a.paused = "", False
                m.emit(run_id, "suspension_cleared", {"message": p.message, "frame": p.done})
            if p.state == "running":
                for d in bench.devices.values():
                    d.ok()
            m.emit(
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
            bench.config,
            out,
            resume=out.joinpath("dataset.json").exists(),
            progress=on_progress,
            header=DatasetHeader(camera=dict(bench.camera_spec), extra={"service_run": run_id}),
            on_frame=None if stream is None else stream.submit,
        )
        if a.aborting:
            a.acq.abort()
        try:
            await a.acq.run()
        except AcquisitionError as exc:
            if is_disk_full(exc):  # the data disk, not a device
                raise
            dev = "camera" if isinstance(exc.cause, FrameError) or "grab" in str(exc.cause).lower() else "actuators"
            bench.devices[dev].fail(str(exc.cause))
            raise
        finally:
            await close_devices(a.acq)

    # -- extraction and fits: child processes ---------------------------------------------------------
    async def extract(self, run_id: str, run: Run) -> dict[str, Any]:
        """Extract the run's dataset in a child process into ``observations.json``; return the summary."""
        m = self.m
        path = m.dataset_path(run)
        a = m.active[run_id]

        def on_event(kind: str, data: dict[str, Any]) -> None:
            if m.active.get(run_id) is not a:
                return
            if kind == "progress":
                m.bus.queue_live(run_id, "progress", {"stage": "extraction", **data})
            elif kind == "frame":
                det = data.pop("detections", None)
                if det is not None:
                    a.detections[data["frame"]] = {"phase": data["phase"], **det}
                    a.last_extracted = a.last_frame = data["frame"]
                m.bus.queue_live(run_id, "frames", data)

        try:
            summary = await run_job(
                "extract",
                {
                    "dataset": str(path),
                    "out": str(m.run_dir(run) / "observations.json"),
                    "workers": m.settings.extraction_workers,
                    "streamed": a.streamed,
                },
                on_event,
                nice=m.settings.job_niceness,
                on_job=lambda j: setattr(a, "job", j),
            )
        finally:
            m.bus.end_live(run_id)
        m.update(run_id, extraction=summary)
        m.emit(
            run_id,
            "extraction",
            {
                "phases": summary.get("phases", {}),
                "frames_with_missing": len(summary.get("frames", {})),
                "placement": summary.get("placement"),
                "streamed": summary.get("streamed"),
            },
        )
        return summary

    async def calibrate(self, run_id: str, run: Run) -> dict[str, Any]:
        """The methods, each in its own child process (the fits hold the GIL), ``fit_workers`` at once; return the
        merged result (the document of the methods one after the other: each method's fit is independent of the
        others, :func:`service.jobs.merge_method`)."""
        m = self.m
        a = m.active[run_id]
        methods = list(run.methods)
        n = len(methods)
        jobs = _Jobs()
        a.job = jobs
        done = [0]
        gate = asyncio.Semaphore(max(1, min(m.settings.fit_workers, n)))

        async def one(k: int, method: str) -> dict[str, Any]:
            def on_event(kind: str, data: dict[str, Any]) -> None:
                if m.active.get(run_id) is not a:
                    return
                if kind == "iteration":
                    m.bus.queue_live(run_id, "iterations", data)
                elif kind == "fit" and data["state"] != "start":  # its start: said when its place was given
                    m.bus.flush_live(run_id)  # the iterations of a method come before its end
                    m.emit(run_id, "fit", {**data, "index": k, "count": n})
                    done[0] += 1
                    m.update(run_id, done=done[0], total=n)
                    m.emit(run_id, "progress", {"stage": "calibration", "done": done[0], "total": n})

            async with gate:
                # the fit starts when it has a place (its process is launched now): a fit short next to a process's
                # start-up must not look as if the fits ran one after the other
                m.emit(run_id, "fit", {"method": method, "state": "start", "index": k, "count": n})
                return await run_job(
                    "fit",
                    {"observations": str(m.run_dir(run) / "observations.json"), "methods": [method]},
                    on_event,
                    nice=m.settings.job_niceness,
                    on_job=jobs.add,
                )

        try:
            parts = await asyncio.gather(*(one(k, method) for k, method in enumerate(methods)))
        except BaseException:
            jobs.kill()
            raise
        finally:
            with contextlib.suppress(Exception):
                m.bus.end_live(run_id)
        if not parts:
            raise I4calError("no method to fit")
        doc = parts[0]
        for method, part in zip(methods[1:], parts[1:], strict=True):
            doc = merge_method(doc, method, part)
        return doc


class _Jobs:
    """The fit processes of a run (:attr:`ActiveRun.job` while it calibrates): ``kill`` ends them all."""

    def __init__(self) -> None:
        self.jobs: list[Any] = []

    def add(self, job: Any) -> None:
        self.jobs.append(job)

    def kill(self) -> None:
        for j in self.jobs:
            j.kill()
