"""The long computations of a run (extraction, fits) in child processes, so that the server stays responsive.

Why processes: extraction and the fits hold the GIL for most of their time; in a thread of the server process they
delay every request (tens to hundreds of ms). And forking the server process itself (a process pool started from
it) copies a large address space while holding the GIL. So a run's extraction and its fits each run in one child
process forked by a *forkserver*: a small process that imported numpy, scipy, OpenCV and ``calib`` once
(:func:`warm_up`, at service start-up), so that starting a job costs the server neither an import nor a fork of
itself. Children run with a lower CPU priority (``nice``) than the server and lead their own process group (the
extraction's own worker pool included), which is killed as a whole when the run is aborted or the service stops.

A child reports through a pipe: ``("event", kind, data)`` messages (progress, per-frame results, fit iterations)
and one final ``("result", value)`` or ``("error", kind, message)``. Large documents go through files: extraction
writes ``observations.json`` itself, and the fit reads it.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

from calib.errors import I4calError, InputError

_CTX = multiprocessing.get_context("forkserver")
#: Modules the forkserver imports once; every job child starts with them loaded.
PRELOAD = [
    "numpy",
    "scipy.optimize",
    "cv2",
    "calib.identify.pipeline",
    "calib.vision.extract",
    "calib.vision.stream",
    "drivers.acquisition.streaming",
    "calib.design",
    "service.design",
    "service.report",
    "service.jobs",
]
_warm_lock = threading.Lock()
_warm = False

Emit = Callable[[str, dict[str, Any]], None]


class JobError(I4calError):
    """A job's child process failed without a result (crashed, killed, internal error)."""


def clean_json(x: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None."""
    import numpy as np

    if isinstance(x, dict):
        return {str(k): clean_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean_json(v) for v in x]
    if isinstance(x, np.ndarray):
        return clean_json(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def warm_up() -> None:
    """Start the forkserver with :data:`PRELOAD` imported and wait until it forks (blocking: call it in a thread).

    Idempotent; the forkserver lives as long as this process.
    """
    global _warm
    with _warm_lock:
        if _warm:
            return
        _CTX.set_forkserver_preload(PRELOAD)
        p = _CTX.Process(target=_noop, name="i4cal-warm-up")
        p.start()
        p.join(120)
        _warm = True


def _noop() -> None:
    return None


# -- the child side --------------------------------------------------------------------------------
def _child_main(
    conn: Any,
    target: str,
    kwargs: dict[str, Any],
    nice: int,
    method_modules: tuple[str, ...] = (),
    disk_full_flag: str | None = None,
) -> None:
    """Entry point of a job child: run ``JOBS[target](emit=..., **kwargs)`` and send back the outcome.

    ``method_modules``: the modules that registered methods in the server (:func:`calib.identify.registry.
    plugin_modules`), imported first so that the child knows the same methods. ``disk_full_flag``: the server's
    ``I4CAL_DISK_FULL`` (:mod:`service.failpoints`; None in production).
    """
    if disk_full_flag:
        from service import failpoints

        failpoints.install(disk_full_flag)
    with contextlib.suppress(OSError):
        os.setpgid(0, 0)  # its own process group: abort kills the extraction's pool with it
    # a forkserver's child would start the extraction's pool through a forkserver of its own (a fresh interpreter
    # importing numpy, OpenCV, calib: ~1 s per extraction); this child is single-threaded: fork it directly
    multiprocessing.set_start_method("fork", force=True)
    if nice > 0:
        with contextlib.suppress(OSError):
            os.nice(nice)

    def emit(kind: str, data: dict[str, Any]) -> None:
        conn.send(("event", kind, data))

    try:
        if method_modules:
            from calib.identify.registry import load_modules

            load_modules(method_modules)
        result = JOBS[target](emit=emit, **kwargs)
        conn.send(("result", result))
    except I4calError as exc:
        fields = (
            {k: getattr(exc, k) for k in ("reason", "file", "frame", "field")} if isinstance(exc, InputError) else {}
        )
        conn.send(("error", "input", str(exc), fields))
    except BrokenPipeError:
        pass  # the server went away
    except BaseException as exc:  # reported to the server, which fails the run with it
        # the traceback goes to the service's log (this process's stderr), the run's error is one line
        traceback.print_exc()
        with contextlib.suppress(BrokenPipeError):
            conn.send(("error", "internal", one_line(f"{type(exc).__name__}: {exc}"), {}))
    finally:
        conn.close()


def one_line(text: str, limit: int = 500) -> str:
    """``text`` on one line (its lines joined by "; "), at most ``limit`` characters: a run's error message."""
    line = "; ".join(part.strip() for part in str(text).splitlines() if part.strip())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def check_frame_numbers(dataset: str | os.PathLike[str]) -> None:
    """Every frame's ``q`` (and ``t``) of a dataset finite: a NaN or an infinity (``dataset.json`` is written by
    Python's ``json``, which writes them) would fail deep in the extraction or the fit.

    Raises
    ------
    InputError
        Names ``dataset.json``, the frame and the field (``q[1]``).
    """
    from calib.formats.dataset import Dataset

    ds = Dataset.open(dataset)
    for i, f in enumerate(ds.frames):
        for k, v in enumerate(f.q):
            if not math.isfinite(v):
                raise InputError(f"{v} is not a finite number", file="dataset.json", frame=i, field=f"q[{k}]")
        if not math.isfinite(f.t):
            raise InputError(f"{f.t} is not a finite number", file="dataset.json", frame=i, field="t")


def extract_job(*, emit: Emit, dataset: str, out: str, workers: int, streamed: str | None = None) -> dict[str, Any]:
    """Extract ``dataset`` (dataset v1) into ``out`` (observations v1); return the extraction summary.

    Events: ``progress`` ``{"done", "total"}`` (at most 10/s) and ``frame`` (:func:`calib.vision.extract.frame_info`,
    one per frame and stage). ``streamed``: the file of the frames measured during the acquisition
    (:mod:`drivers.acquisition.streaming`), taken where they hold the frame's answer; the summary's ``streamed`` says
    how many.
    """
    from calib.formats.observations import Observations
    from calib.numerics.jsonio import write_json_atomic
    from calib.vision.extract import extract_dataset
    from drivers.acquisition.streaming import load_streamed

    check_frame_numbers(dataset)
    last = [0.0]

    def progress(done: int, total: int) -> None:
        t = time.monotonic()
        if done < total and t - last[0] < 0.1:
            return
        last[0] = t
        emit("progress", {"done": done, "total": total})

    frames = load_streamed(streamed)
    res = extract_dataset(
        dataset,
        workers=workers,
        progress=progress,
        on_frame=lambda info: emit("frame", clean_json(info)),
        streamed=frames,
    )
    doc = clean_json(res.observations)
    Observations.from_dict(doc, dataset)  # a run fails here, naming the field, rather than in the fit
    write_json_atomic(out, doc, indent=None)
    summary = clean_json(res.summary)
    if frames is not None:
        summary["streamed"] = {**frames.used, "failed": len(frames.failed)}
    return summary


def fit_job(*, emit: Emit, observations: str, methods: list[str]) -> dict[str, Any]:
    """Identify with each method in turn; return the merged result document (``i4cal calibrate --json``).

    Events: ``fit`` ``{"method", "state": "start" | "done" | "failed", ...}`` and ``iteration``
    ``{"method", "stage", "iteration", "cost"}`` (every iteration of every fit).
    """
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate_document

    obs = Observations.load(observations)
    doc = None
    for k, method in enumerate(methods):
        emit("fit", {"method": method, "state": "start", "index": k, "count": len(methods)})
        part = calibrate_document(obs, [method], on_iteration=lambda info: emit("iteration", info))
        entry = part.methods[method]
        emit(
            "fit",
            {
                "method": method,
                "state": "done" if entry.converged else "failed",
                "index": k,
                "count": len(methods),
                "iterations": entry.iterations,
                "residual_rms": clean_json(entry.residual_rms),
                "error": entry.error,
            },
        )
        doc = part if doc is None else doc.merge(part, method)
    if doc is None:
        raise I4calError("no method to fit")
    return clean_json(doc.to_dict())


def merge_method(doc: dict[str, Any], method: str, part: dict[str, Any]) -> dict[str, Any]:
    """``doc`` (a result document) with ``method``'s entry, validation and truth errors from ``part`` (the result
    document of that method alone: :func:`fit_job`). Each method's fit is its own ``calibrate(obs, [method])``: the
    parts do not depend on one another, so they can be fitted in any order or at once."""
    from calib.formats.resultdoc import ResultDocument

    merged = ResultDocument.from_dict(doc).merge(ResultDocument.from_dict(part), method)
    return clean_json(merged.to_dict())


def _heavy_predict(noise: Any, *, config: Any, plan: Any, methods: tuple[str, ...], camera: Any) -> Any:
    from service.design import check_for_bench

    return check_for_bench(config, plan, noise, methods, camera)


def _heavy_design(noise: Any, *, config: Any, request: Any, camera: Any) -> Any:
    from service.design import design_for_bench

    return design_for_bench(config, request, noise, camera=camera)


def _heavy_tradeoff(noise: Any, *, config: Any, request: Any, counts: list[int], camera: Any) -> Any:
    from service.design import tradeoff_for_bench

    return tradeoff_for_bench(config, request, counts, noise, camera=camera)


def _heavy_reference(noise: Any, *, config: Any, plan: Any, methods: tuple[str, ...], camera: Any) -> Any:
    from service.design import reference_targets

    return reference_targets(config, plan, noise, methods, camera)


def _heavy_run_prediction(noise: Any, *, config: Any, plan: dict[str, Any], methods: list[str], camera: Any) -> Any:
    from service.design import run_prediction

    return run_prediction(config, plan, methods, camera, noise=noise)


def _heavy_report(noise: Any, *, data_dir: str, run: dict[str, Any], methods: list[str] | None) -> Any:
    from types import SimpleNamespace

    from service.report import build_report, inputs_from_run

    return build_report(inputs_from_run(data_dir, SimpleNamespace(**run), methods))


#: the CPU-heavy computations of requests (:class:`HeavyPool`) and of a run's prediction, by name; each takes the
#: prediction noise (None: computed here) and its keywords
HEAVY_TASKS: dict[str, Callable[..., Any]] = {
    "predict": _heavy_predict,
    "design": _heavy_design,
    "tradeoff": _heavy_tradeoff,
    "reference": _heavy_reference,
    "run_prediction": _heavy_run_prediction,
    "report": _heavy_report,
}
#: the tasks that use the prediction noise (the image-level model of the bench's camera: ~0.5-4 s of CPU to make)
NOISE_TASKS = ("predict", "design", "tradeoff", "reference", "run_prediction")


def _predicts(methods: list[str]) -> bool:
    from calib.design import METHODS

    return any(m in METHODS for m in methods)


def heavy_job(*, emit: Emit, task: str, noise: Any = None, camera: Any = None, **kwargs: Any) -> tuple[Any, Any]:
    """One CPU-heavy computation (:data:`HEAVY_TASKS`) in a job child: ``(result, noise)``, the noise (computed here
    when not given) sent back so that the server passes it to the next job instead of computing it again."""
    if task == "run_prediction" and not _predicts(kwargs["methods"]):
        return None, noise  # a run that only records, or with methods the design does not predict: no prediction
    if task in NOISE_TASKS and noise is None:
        from service.design import twin_image_noise

        noise = twin_image_noise(camera=camera)
    if task != "report":
        kwargs["camera"] = camera
    return HEAVY_TASKS[task](noise, **kwargs), noise


JOBS: dict[str, Callable[..., Any]] = {"extract": extract_job, "fit": fit_job, "heavy": heavy_job}


# -- the server side -------------------------------------------------------------------------------
class Job:
    """One child process running ``JOBS[target]``; :meth:`run` blocks (call it in a thread), :meth:`kill` doesn't."""

    def __init__(
        self, target: str, kwargs: dict[str, Any], on_event: Callable[[str, dict[str, Any]], object], nice: int = 5
    ) -> None:
        if target not in JOBS:
            raise ValueError(f"unknown job {target!r}")
        self.target = target
        self.on_event = on_event
        self._recv, self._send = _CTX.Pipe(duplex=False)
        from calib.identify.registry import plugin_modules

        self.process = _CTX.Process(
            target=_child_main,
            args=(self._send, target, kwargs, nice, plugin_modules(), os.environ.get("I4CAL_DISK_FULL")),
            name=f"i4cal-{target}",
        )
        self.killed = False
        self._ended = False

    def run(self) -> Any:
        """Start the child, forward its events to ``on_event`` (from this thread), return its result.

        Raises
        ------
        I4calError
            The job refused its input (the message of the child's error).
        JobError
            The child crashed, was killed, or failed with an internal error.
        """
        warm_up()
        if self.killed:
            raise JobError(f"{self.target} job cancelled")
        self.process.start()
        self._send.close()
        if self.killed:  # kill() ran while the child was starting
            self.kill()
        try:
            while True:
                try:
                    msg = self._recv.recv()
                except (EOFError, OSError):
                    break
                if msg[0] == "event":
                    self.on_event(msg[1], msg[2])
                elif msg[0] == "result":
                    return msg[1]
                elif msg[0] == "error":
                    if msg[1] == "input":
                        fields = msg[3] if len(msg) > 3 else {}
                        if fields:
                            reason = fields.pop("reason")
                            raise InputError(reason, **fields)
                        raise I4calError(msg[2])
                    raise JobError(f"{self.target} failed: {msg[2]}")
        finally:
            self._recv.close()
            self.process.join(10)
            self._ended = True
        if self.killed:
            raise JobError(f"{self.target} job cancelled")
        raise JobError(f"the {self.target} process ended without a result (exit code {self.process.exitcode})")

    def kill(self) -> None:
        """Kill the child and its process group now (idempotent; safe before, during and after the start)."""
        self.killed = True
        pid = self.process.pid
        if pid is None or self._ended:
            return
        try:
            os.killpg(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


async def run_job(
    target: str,
    kwargs: dict[str, Any],
    on_event: Callable[[str, dict[str, Any]], None],
    nice: int = 5,
    on_job: Callable[[Job], None] | None = None,
) -> Any:
    """Run a job in a child process; ``on_event(kind, data)`` is called in the event loop for each event.

    Cancelling the awaiting task kills the child (and its process group). ``on_job`` receives the :class:`Job`
    before it starts (its ``process.pid`` is set once started).
    """
    import asyncio

    loop = asyncio.get_running_loop()
    job = Job(target, kwargs, lambda kind, data: loop.call_soon_threadsafe(on_event, kind, data), nice)
    if on_job is not None:
        on_job(job)
    fut = loop.run_in_executor(None, job.run)
    fut.add_done_callback(lambda f: f.cancelled() or f.exception())  # consumed even when nobody awaits it
    try:
        return await asyncio.shield(fut)
    except asyncio.CancelledError:
        job.kill()
        raise


# -- the pool of CPU-heavy requests ----------------------------------------------------------------------------------
#: heavy requests computed at once (2 cores: one is the run's)
HEAVY_WORKERS = 1
#: heavy requests waiting for their turn beyond the running ones; one more gets 429
HEAVY_MAX_WAITING = 4
#: nice increment of the heavy requests' processes above the run's extraction and fits (``job_niceness``)
HEAVY_NICE_ABOVE_RUN = 5


class PoolBusyError(Exception):
    """The heavy-request pool is full (:data:`HEAVY_MAX_WAITING` waiting): the request is refused, to retry after
    ``retry_after_s`` seconds."""

    def __init__(self, retry_after_s: int) -> None:
        super().__init__(f"the service is busy with {HEAVY_MAX_WAITING} heavy requests waiting; retry later")
        self.retry_after_s = retry_after_s


class HeavyPool:
    """The CPU-heavy requests (plan design, prediction, trade-off, report) run here, outside the server process:
    each in a job child of the forkserver (:class:`Job`), at most ``workers`` at once, ``max_waiting`` more waiting
    their turn (beyond: :class:`PoolBusyError`, a 429 with Retry-After), with the niceness ``nice`` (higher than the
    run's processes: a run's extraction and fits get the CPU first, and the server's event loop before both). A
    request abandoned by its client kills its child. The prediction noise the children compute is kept for the
    next ones (:func:`heavy_job`)."""

    def __init__(self, nice: int, workers: int = HEAVY_WORKERS, max_waiting: int = HEAVY_MAX_WAITING) -> None:
        self.nice = nice
        self.workers = workers
        self.max_waiting = max_waiting
        self.pending = 0  # running + waiting
        self.running: list[Job] = []
        self.noise: Any = None
        self._sem: Any = None
        self._durations: list[float] = []

    def retry_after_s(self) -> int:
        """Seconds until a place is likely free: the mean duration of the last jobs times the queue ahead."""
        mean = sum(self._durations) / len(self._durations) if self._durations else 5.0
        return max(1, math.ceil(mean * (self.pending - self.workers + 1) / self.workers))

    async def run(self, task: str, **kwargs: Any) -> Any:
        """The result of ``HEAVY_TASKS[task](noise, **kwargs)`` computed in a child process.

        Raises
        ------
        PoolBusyError
            ``max_waiting`` requests are already waiting.
        I4calError
            The computation refused its input (an :class:`calib.errors.InputError` keeps its field).
        """
        import asyncio

        if self.pending >= self.workers + self.max_waiting:
            raise PoolBusyError(self.retry_after_s())
        if self._sem is None:
            self._sem = asyncio.Semaphore(self.workers)
        self.pending += 1
        try:
            async with self._sem:
                return await self._run(task, kwargs, self.nice)
        finally:
            self.pending -= 1

    async def run_now(self, task: str, nice: int, **kwargs: Any) -> Any:
        """:meth:`run` for a run's own computation (its plan's prediction): started at once with the niceness of the
        run's processes, not queued behind requests; the cached noise shared."""
        return await self._run(task, kwargs, nice, track=False)

    async def _run(self, task: str, kwargs: dict[str, Any], nice: int, track: bool = True) -> Any:
        job: list[Job] = []

        def on_job(j: Job) -> None:
            if track:
                job.append(j)
                self.running.append(j)

        t0 = time.monotonic()
        try:
            args = {"task": task, **kwargs, **({"noise": self.noise} if task in NOISE_TASKS else {})}
            result, noise = await run_job("heavy", args, lambda kind, data: None, nice=nice, on_job=on_job)
        finally:
            for j in job:
                self.running.remove(j)
        if track:
            self._durations = [*self._durations[-9:], time.monotonic() - t0]
        if noise is not None:
            self.noise = noise
        return result
