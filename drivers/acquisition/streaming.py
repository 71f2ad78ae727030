"""A worker beside the acquisition that measures each frame while the robot moves to the next pose.

The acquisition hands each frame over as soon as it is written (:class:`drivers.acquisition.acquire.Acquisition`'s
``on_frame``, called in its writer thread) with :meth:`FrameStream.submit`: a put on a multiprocessing queue that
never waits for the worker, so a slow or stuck worker never delays a motion or a grab. The worker is a separate
process (the measurement holds the GIL for tens of milliseconds per frame: in a thread it would delay the event
loop that drives the bench), with a lower CPU priority (``nice``) than the acquisition. It measures each frame with
:class:`calib.vision.stream.FrameStreamer` and reports every frame (``on_event``); :meth:`FrameStream.finish` waits
for the frames handed over, then the worker writes what it measured (:class:`calib.vision.stream.StreamedFrames`,
JSON) for the extraction at the end (:func:`calib.vision.extract.extract_dataset`, ``streamed=``).

A frame the worker fails on is reported (``failed``) and measured by the extraction at the end; a worker that dies
loses nothing either (every frame is then measured at the end).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import multiprocessing
import os
import queue as queue_mod
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: ``on_event(kind, data)``: ``frame`` (a frame measured: ``{"frame", "phase", "board", "rods", "measured",
#: "submitted"}``), ``failed`` (``{"frame", "reason", ...}``), ``off`` (``{"reason"}``: nothing is measured during the
#: acquisition, e.g. no intrinsics), ``done`` (the summary of :meth:`FrameStream.finish`)
StreamEvent = Callable[[str, dict[str, Any]], None]


def _json_default(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _finite(x: Any) -> Any:
    """``x`` with non-finite floats as None (strict JSON), numpy values as Python ones."""
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if hasattr(x, "tolist"):
        return _finite(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _stream_main(inq: Any, outq: Any, dataset: str, out: str, nice: int, owner: int) -> None:
    """The worker process: frame indices from ``inq`` until None, reports on ``outq``, the frames to ``out``. It
    ends without writing when its ``owner`` process is gone (a service killed mid-run: nothing waits for it)."""
    from calib.errors import InputError
    from calib.numerics.threads import single_threaded_worker
    from calib.vision.stream import FrameStreamer

    single_threaded_worker()  # one core for the worker, the other for the acquisition and the server
    if nice > 0:
        with contextlib.suppress(OSError):
            os.nice(nice)
    streamer = FrameStreamer(dataset)
    off: str | None = None
    measured = submitted = 0
    idle = True  # between frames: frames measured on an older prediction are measured again on the latest
    while True:
        try:
            i = inq.get_nowait() if idle else inq.get(timeout=1.0)
        except queue_mod.Empty:
            if not _alive(owner):
                return
            if idle:
                try:
                    idle = streamer.idle_step()
                except Exception:  # the frame keeps its older measurement
                    log.exception("measuring a frame again failed")
                    idle = False
            continue
        idle = True
        if i is None:
            break
        submitted += 1
        if off is not None:
            continue
        try:
            info = streamer.add(int(i))
        except InputError as exc:
            if streamer.frames is None:  # no intrinsics: nothing to measure before the end
                off = exc.reason
                outq.put(("off", {"reason": off}))
                continue
            streamer.frames.failed[int(i)] = exc.reason
            outq.put(("failed", {"frame": int(i), "reason": exc.reason, "submitted": submitted}))
            continue
        except Exception as exc:  # measured again at the end; the worker goes on
            reason = f"{type(exc).__name__}: {exc}"
            if streamer.frames is not None:
                streamer.frames.failed[int(i)] = reason
            outq.put(("failed", {"frame": int(i), "reason": reason, "submitted": submitted}))
            continue
        measured += 1
        outq.put(("frame", {**info, "measured": measured, "submitted": submitted}))
    frames = streamer.frames
    if frames is not None:
        tmp = Path(out).with_name(f".{Path(out).name}.tmp")
        tmp.write_text(json.dumps(frames.to_dict(), default=_json_default), encoding="utf-8")
        os.replace(tmp, out)
    outq.put(
        (
            "done",
            {
                "measured": measured,
                "submitted": submitted,
                "failed": {str(k): v for k, v in (frames.failed if frames else {}).items()},
                "rods_frames": len(frames.rods) if frames else 0,
                "refits": streamer.refits,
                "measured_again": streamer.remeasured,
                "off": off,
                "file": out if frames is not None else None,
            },
        )
    )


class FrameStream:
    """Measures the frames of the dataset being recorded at ``dataset`` in a worker process (module docstring).

    Parameters
    ----------
    dataset : path
        The dataset directory the acquisition writes.
    out : path
        Where the worker writes what it measured (:class:`calib.vision.stream.StreamedFrames` as JSON).
    on_event : callable(kind, data), optional
        Called from a reader thread of this process for each report (:data:`StreamEvent`).
    nice : int
        Nice increment of the worker process.
    context : multiprocessing context, optional
        Default ``forkserver`` (this process runs threads and an event loop: it is not forked).
    """

    def __init__(
        self,
        dataset: str | Path,
        out: str | Path,
        *,
        on_event: StreamEvent | None = None,
        nice: int = 5,
        context: Any = None,
    ) -> None:
        self.dataset = str(dataset)
        self.out = str(out)
        self.on_event = on_event
        self.nice = nice
        self.ctx = context or multiprocessing.get_context("forkserver")
        self.inq: Any = None
        self.outq: Any = None
        self.process: Any = None
        self.submitted = 0
        self.measured = 0
        self.failed: dict[int, str] = {}
        self.off: str | None = None
        self.summary: dict[str, Any] | None = None
        self.last_measured_at: float | None = None  # time.monotonic() of the last frame measured
        self._reader: threading.Thread | None = None
        self._done = threading.Event()

    def start(self) -> FrameStream:
        """Start the worker (before the acquisition's first frame)."""
        self.inq, self.outq = self.ctx.Queue(), self.ctx.Queue()
        self.process = self.ctx.Process(
            target=_stream_main,
            args=(self.inq, self.outq, self.dataset, self.out, self.nice, os.getpid()),
            name="i4cal-stream",
            daemon=True,
        )
        self.process.start()
        self._reader = threading.Thread(target=self._read, name="i4cal-stream-reader", daemon=True)
        self._reader.start()
        return self

    def submit_recorded(self) -> int:
        """Hand over the frames already in the dataset (a resumed acquisition's): measured while the bench moves to
        the next pose like the others. Returns how many."""
        from calib.errors import InputError
        from calib.formats.dataset import Dataset

        try:
            n = len(Dataset.open(self.dataset).frames)
        except InputError:  # no dataset yet
            return 0
        for i in range(n):
            self.submit(i)
        return n

    def submit(self, index: int) -> None:
        """Hand frame ``index`` (written to the dataset) over to the worker; never waits for it."""
        if self.inq is None or self._done.is_set():
            return
        self.submitted += 1
        try:
            self.inq.put_nowait(int(index))
        except Exception as exc:  # a queue closed by close(): the frame is measured at the end
            log.warning("frame %d not handed to the stream worker: %s", index, exc)

    def _read(self) -> None:
        while True:
            try:
                kind, data = self.outq.get(timeout=0.5)
            except queue_mod.Empty:
                if self.process is not None and not self.process.is_alive() and self.outq.empty():
                    self._done.set()
                    return
                continue
            except (EOFError, OSError, ValueError):
                self._done.set()
                return
            if kind == "frame":
                self.measured += 1
                self.last_measured_at = time.monotonic()
            elif kind == "failed":
                self.failed[int(data["frame"])] = data["reason"]
            elif kind == "off":
                self.off = data["reason"]
            elif kind == "done":
                self.summary = data
            if self.on_event is not None:
                try:
                    self.on_event(kind, _finite(data))
                except Exception:  # a broken display must not stop the reports
                    log.exception("stream event callback failed")
            if kind == "done":
                self._done.set()
                return

    def finish(self, timeout_s: float | None = None) -> dict[str, Any] | None:
        """Wait until every frame handed over is measured and the worker wrote :attr:`out` (blocking: call it in a
        thread). Returns the worker's summary (``measured``, ``submitted``, ``failed``, ``off``, ``file``: the path
        written, None when nothing was measured), None when the worker died or ``timeout_s`` passed (the extraction
        then measures every frame itself)."""
        if self.inq is None:
            return None
        with contextlib.suppress(Exception):
            self.inq.put(None)
        self._done.wait(timeout_s)
        if self.summary is None:
            log.warning("the stream worker gave no result (exit code %s)", getattr(self.process, "exitcode", None))
        self.close()
        return self.summary

    def close(self) -> None:
        """Stop the worker now (idempotent): an aborted or failed run."""
        p = self.process
        if p is not None:
            p.join(timeout=0 if self.summary is None and not self._done.is_set() else 5)
            if p.is_alive():
                p.kill()
                p.join(5)
        for q in (self.inq, self.outq):
            if q is not None:
                with contextlib.suppress(Exception):
                    q.close()
                    q.cancel_join_thread()
        self._done.set()
        self.process = None


def load_streamed(path: str | Path | None) -> Any:
    """The :class:`calib.vision.stream.StreamedFrames` a worker wrote at ``path`` (None: none, or unreadable: the
    extraction then measures every frame)."""
    if path is None or not Path(path).is_file():
        return None
    from calib.vision.stream import StreamedFrames

    try:
        return StreamedFrames.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("streamed frames at %s not used: %s", path, exc)
        return None
