"""Independent tasks (a study's trials, a design's candidate draws) fanned out over Dask (``dask.distributed``).

One engine for every study: ``i4cal bench accuracy``, ``i4cal bench design`` and ``i4cal plan design --draws``.

* :class:`FanoutSettings` says where the tasks run: a Dask ``LocalCluster`` of ``workers`` processes on this
  machine (one thread each; default: all cores), the cluster behind ``scheduler`` (``tcp://HOST:8786``: a
  ``dask scheduler`` with ``dask worker`` processes on other machines, each with this project installed at the same
  version), or, with ``workers=1`` and no scheduler, this process without Dask (for debugging: breakpoints and
  tracebacks where the task runs).
* :class:`Fanout` (a context manager) starts that engine and closes it; :meth:`Fanout.submit` returns a
  ``concurrent.futures.Future`` whatever the engine, :meth:`Fanout.map` runs a list of tasks and returns one
  :class:`Outcome` per task, in the tasks' order: its value, or the exception it raised (reported, never the end
  of the others).
* :func:`progress_display` shows tasks as they finish: a rich bar on a terminal, one plain line per finished
  task otherwise (a log file, CI).

Every task runs with one BLAS and one OpenCV thread (:func:`calib.numerics.threads.single_threaded_worker`), in a worker
or in this process alike: a task's numbers do not depend on how many threads its libraries had. Each task must
draw its random numbers from its own seed (derived from the study's seed and the task's index, never from the
worker): then the numbers are identical whatever the worker count or engine.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import functools
import os
import sys
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, Field, field_validator

from calib.errors import InputError

#: ``on_done(outcome, done, total)``: called in the calling process as each task of :meth:`Fanout.map` finishes.
OnDone = Callable[["Outcome", int, int], None]

#: set in a worker process once its libraries run one thread
_single_threaded_process = False


class FanoutSettings(BaseModel):
    """Where a study's tasks run (``--workers`` and ``--scheduler`` of the commands that fan out)."""

    workers: int | None = Field(
        None, ge=1, description="local worker processes (default: all cores); 1 and no scheduler: this process"
    )
    scheduler: str | None = Field(None, description="address of a running Dask scheduler, tcp://HOST:8786")

    @field_validator("scheduler")
    @classmethod
    def _address(cls, v: str | None) -> str | None:
        if v is None:
            return v
        proto, sep, rest = v.partition("://")
        host, _, port = rest.rpartition(":")
        if not sep or proto not in ("tcp", "tls", "ucx", "inproc") or not host or not port.isdigit():
            raise ValueError(f"{v!r} is not a scheduler address (tcp://HOST:PORT, e.g. tcp://10.0.0.5:8786)")
        return v


def settings_from(workers: int | None, scheduler: str | None) -> FanoutSettings:
    """:class:`FanoutSettings` from a command's ``--workers`` and ``--scheduler``; a bad value is an
    :class:`~calib.errors.InputError` naming the option."""
    from pydantic import ValidationError

    try:
        return FanoutSettings(workers=workers, scheduler=scheduler)
    except ValidationError as exc:
        err = exc.errors()[0]
        option = "--" + str(err["loc"][0]) if err["loc"] else "--workers"
        raise InputError(str(err["msg"]).removeprefix("Value error, "), field=option) from None


def add_arguments(parser: Any, what: str = "trials") -> None:
    """``--workers N`` and ``--scheduler ADDRESS`` on a command that fans ``what`` out."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help=f"run the {what} on a local Dask cluster of N processes, one thread each (default: all cores); "
        "1: in this process, without Dask (for debugging)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help=f"run the {what} on the Dask cluster of this scheduler (tcp://HOST:8786; its workers need this "
        "project installed at the same version) instead of a local one",
    )


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@dataclass(frozen=True)
class Outcome:
    """One task's end: its ``value``, or the ``error`` it raised (``value`` then None)."""

    index: int
    name: str
    value: Any = None
    error: BaseException | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    def error_text(self) -> str | None:
        """``"TypeName: message"`` of the error (None when the task succeeded)."""
        return None if self.error is None else describe_error(self.error)


def describe_error(exc: BaseException) -> str:
    """``"TypeName: message"``: how a failed task is reported in a study's results."""
    return f"{type(exc).__name__}: {exc}"


def _single_threaded(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in a Dask worker process whose libraries run one thread (set at its first task)."""
    global _single_threaded_process
    if not _single_threaded_process:
        from calib.numerics.threads import single_threaded_worker

        single_threaded_worker()
        _single_threaded_process = True
    return fn(*args)


class _InProcess(cf.Executor):
    """The executor interface in this process (``--workers 1``): a task runs when :meth:`run_next` is called (by
    :meth:`Fanout.next_done`), in submission order, so that progress is shown as each one finishes."""

    def __init__(self) -> None:
        self._queue: collections.deque[tuple[cf.Future, Callable[..., Any], tuple[Any, ...]]] = collections.deque()

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> cf.Future:
        f: cf.Future = cf.Future()
        self._queue.append((f, functools.partial(fn, **kwargs) if kwargs else fn, args))
        return f

    def run_next(self) -> bool:
        """Run the oldest waiting task (with one BLAS and one OpenCV thread, as in a worker; this process's own
        settings restored after it); False when none waits."""
        from calib.numerics.threads import forking_single_threaded

        if not self._queue:
            return False
        f, fn, args = self._queue.popleft()
        if f.set_running_or_notify_cancel():
            try:
                with forking_single_threaded():
                    value = fn(*args)
            except Exception as exc:  # handed over like a pool's future (an interrupt goes on up)
                f.set_exception(exc)
            else:
                f.set_result(value)
        return True

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        while self._queue:
            self._queue.popleft()[0].cancel()


class Fanout:
    """The engine of :class:`FanoutSettings`, open while the ``with`` block runs.

    ``n_tasks``: how many tasks the study has (a local cluster starts no more workers than that). ``description``
    says which engine runs them and ``workers`` how many worker processes it has (1 in this process).
    """

    def __init__(self, settings: FanoutSettings | None = None, n_tasks: int | None = None) -> None:
        self.settings = settings or FanoutSettings()
        s = self.settings
        wanted = s.workers or cores()
        self.workers = max(1, min(wanted, n_tasks) if n_tasks else wanted)
        self.in_process = s.scheduler is None and self.workers == 1
        self.description = "in this process (no Dask)" if self.in_process else ""
        self._stack = contextlib.ExitStack()
        self._executor: cf.Executor | None = None

    def __enter__(self) -> Fanout:
        try:
            if self.in_process:
                self._executor = _InProcess()
            else:
                self._executor = self._dask_executor()
        except BaseException:
            self._stack.close()
            raise
        return self

    def _dask_executor(self) -> cf.Executor:
        import logging

        from distributed import Client, LocalCluster

        # the engine's own news (workers started, connections closed) stays out of the command's output
        log = logging.getLogger("distributed")
        self._stack.callback(log.setLevel, log.level)
        log.setLevel(logging.WARNING)
        s = self.settings
        if s.scheduler is not None:
            try:
                client = self._stack.enter_context(Client(s.scheduler, timeout="20s"))
            except OSError as exc:
                raise InputError(
                    f"cannot reach the Dask scheduler at {s.scheduler}: {exc}", field="--scheduler"
                ) from exc
            self.workers = len(client.nthreads())
            self.description = f"Dask scheduler {s.scheduler} ({self.workers} workers)"
        else:
            cluster = self._stack.enter_context(
                LocalCluster(
                    n_workers=self.workers,
                    threads_per_worker=1,
                    processes=True,
                    memory_limit=0,  # like a process pool: a large trial is not paused or killed for its memory
                    dashboard_address=None,  # no fixed port to clash with another study on the machine
                    silence_logs=logging.WARNING,
                )
            )
            client = self._stack.enter_context(Client(cluster))
            self.description = f"Dask LocalCluster ({self.workers} workers, 1 thread each)"
        # pure=False: two identical tasks (the same trial in two sweep points) are two tasks, not one cached result
        return client.get_executor(pure=False)

    def __exit__(self, *exc: Any) -> None:
        ex, self._executor = self._executor, None
        try:
            if ex is not None:
                ex.shutdown(wait=False)  # cancels what still runs or waits (an interrupted study)
        finally:
            self._stack.close()

    def submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future:
        """Run ``fn(*args)`` (picklable, with a module-level ``fn``) on the engine; a ``concurrent.futures`` future."""
        if self._executor is None:
            raise RuntimeError("Fanout.submit outside its with block")
        if self.in_process:  # each task single-threaded while it runs (_InProcess.run_next)
            return self._executor.submit(fn, *args)
        return self._executor.submit(_single_threaded, fn, *args)

    def next_done(self, futures: Collection[cf.Future]) -> set[cf.Future]:
        """Those of ``futures`` that are done, waiting until at least one is (``concurrent.futures.wait``'s
        ``FIRST_COMPLETED``; in this process: the waiting tasks run one by one until one of them is done)."""
        if isinstance(self._executor, _InProcess):
            while not any(f.done() for f in futures) and self._executor.run_next():
                pass
            done = {f for f in futures if f.done()}
            if not done and futures:
                raise RuntimeError("waiting for futures that were not submitted to this Fanout")
            return done
        return cf.wait(futures, return_when=cf.FIRST_COMPLETED).done

    def map(
        self,
        fn: Callable[[Any], Any],
        items: Sequence[Any],
        names: Sequence[str] | None = None,
        on_done: OnDone | None = None,
    ) -> list[Outcome]:
        """``fn(item)`` for every item, fanned out; one :class:`Outcome` per item in ``items``' order. A task that
        raises (or whose worker died) gives an outcome with its error; the others run on."""
        labels = list(names) if names is not None else [str(i) for i in range(len(items))]
        running = {self.submit(fn, item): i for i, item in enumerate(items)}
        out: list[Outcome] = []
        while running:
            for fut in self.next_done(running):
                i = running.pop(fut)
                try:
                    res = Outcome(i, labels[i], value=fut.result())
                except Exception as exc:
                    res = Outcome(i, labels[i], error=exc)
                out.append(res)
                if on_done is not None:
                    on_done(res, len(out), len(items))
        return sorted(out, key=lambda o: o.index)

    def index_runner(self, on_done: OnDone | None = None) -> Callable[[Callable[[int], Any], int], list[Any]]:
        """A runner for calib's fan-out points (``calib.design.design_plan``'s ``draws_runner``): ``run(fn, n)`` is
        ``[fn(0), ..., fn(n - 1)]`` fanned out, each entry its value or the exception it raised."""

        def run(fn: Callable[[int], Any], n: int) -> list[Any]:
            outcomes = self.map(fn, list(range(n)), names=[f"draw {k}" for k in range(n)], on_done=on_done)
            return [o.value if o.ok else o.error for o in outcomes]

        return run


@contextlib.contextmanager
def progress_display(label: str, stream: Any = None) -> Iterator[Callable[[str, int, int | None], None]]:
    """``update(description, done, total)`` shown as tasks finish: a rich bar (transient) when ``stream`` (default
    stderr) is a terminal, else one plain line ``label: done/total description`` per call (a log, CI)."""
    from rich.console import Console

    out = stream if stream is not None else sys.stderr
    console = Console(file=out)
    if not console.is_terminal:

        def line(description: str, done: int, total: int | None) -> None:
            print(f"{label}: {done}/{total if total is not None else '?'} {description}".rstrip(), file=out, flush=True)

        yield line
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=None)

        def update(description: str, done: int, total: int | None) -> None:
            bar.update(task, description=f"{label}: {description}", completed=done, total=total)

        yield update


def finished_line(outcome: Outcome) -> str:
    """How a finished task is shown in the progress: its name, and its error when it failed."""
    return f"{outcome.name} done" if outcome.ok else f"{outcome.name} FAILED: {outcome.error_text()}"
