"""Execute a motion plan on a bench and record a dataset as it goes.

For every pose: move (the driver checks limits, derives a timeout, stops on error), wait until in
position and settled, read the encoders, grab a frame, write it (:class:`calib.formats.dataset.DatasetWriter`,
crash-safe, one frame at a time) and report progress. A ``line`` step sets the drives free (control
bit 4), asks the operator to guide the end-effector along the ruler and records encoders + frames at
the line's rate.

The run can be paused, resumed and aborted (abort stops the actuators). A fault stops motion, keeps
every frame already written, and raises :class:`AcquisitionError` naming the pose and the cause; a new
run with ``resume=True`` continues from the first pose not yet recorded.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from calib.errors import InputError
from calib.formats.dataset import CameraSpec, Dataset, DatasetWriter
from calib.formats.plan import Plan, SoftLimits, line_poses, validate_plan
from calib.model.kinematics import ikm
from calib.model.parameters import NOMINAL, I4Parameters
from drivers.acquisition.operators import (
    ConsoleOperator as ConsoleOperator,  # where it was before: the console operator
)
from drivers.acquisition.settings import AcquisitionSettings, DatasetHeader
from drivers.acquisition.suspenders import Suspension
from drivers.devices.interfaces import Actuators, Camera, Frame, Operator
from drivers.devices.registermap import ALARM_WATCHDOG
from drivers.errors import (
    AbortedError,
    DeviceError,
    DeviceTimeoutError,
    FrameError,
    ProtocolError,
    StopNotConfirmedError,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Unit:
    """One recorded frame of the plan: a pose, or one sample of a guided line."""

    index: int
    step: int
    phase: str
    q: tuple[float, ...] | None = None
    line_sample: int | None = None


def plan_units(plan: Plan) -> list[Unit]:
    out: list[Unit] = []
    for si, step in enumerate(plan.steps):
        if step.line is not None:
            out += [Unit(len(out) + k, si, step.phase, None, k) for k in range(step.line.samples)]
        else:
            out.append(Unit(len(out), si, step.phase, tuple(step.q) if step.q is not None else None))
    return out


@dataclass
class Progress:
    state: str  # starting, running, paused, suspended (drivers.acquisition.suspenders), done, failed, aborted
    done: int
    total: int
    phase: str = ""
    elapsed_s: float = 0.0
    eta_s: float | None = None
    message: str = ""


@dataclass
class RunResult:
    path: Path
    frames: int
    total: int
    recorded_now: int
    elapsed_s: float
    per_pose_overhead_s: list[float] = field(default_factory=list)


def _not_stopped(exc: BaseException) -> str:
    if isinstance(exc, StopNotConfirmedError):
        return "motion may NOT have stopped (stop not confirmed); use the emergency stop"
    return f"motion may NOT have stopped (stop failed: {exc}); use the emergency stop"


def q_problem(
    q1: np.ndarray, q2: np.ndarray, target: np.ndarray | None, tol_target_m: float, tol_repeat_m: float
) -> str:
    """Why a frame's q (``q1``, read before the grab) cannot be recorded: ``q2`` (read after) differs by more than
    ``tol_repeat_m``, or ``q1`` is off the commanded ``target`` by more than ``tol_target_m`` (all m, shape (n,));
    ``""`` when it can."""
    d = np.abs(np.asarray(q2) - np.asarray(q1))
    if float(d.max()) > tol_repeat_m:
        i = int(d.argmax())
        return (
            f"q{i + 1} read {q1[i] * 1e3:.4f} mm before the grab and {q2[i] * 1e3:.4f} mm after "
            f"(more than {tol_repeat_m * 1e3:.4f} mm apart)"
        )
    if target is not None:
        e = np.abs(np.asarray(q1) - target)
        if float(e.max()) > tol_target_m:
            i = int(e.argmax())
            return (
                f"q{i + 1} read {q1[i] * 1e3:.4f} mm, {e[i] * 1e3:.4f} mm from its commanded target "
                f"{target[i] * 1e3:.4f} mm (more than {tol_target_m * 1e3:.4f} mm)"
            )
    return ""


class AcquisitionError(DeviceError):
    """A run stopped on a fault: names the pose and why; the dataset keeps every frame written before."""

    def __init__(
        self, message: str, *, pose: int, step: int, phase: str, cause: BaseException, frames_kept: int
    ) -> None:
        self.pose, self.step, self.phase, self.cause, self.frames_kept = pose, step, phase, cause, frames_kept
        super().__init__(message)


class Acquisition:
    """Runs ``plan`` on ``actuators`` + ``camera`` into the dataset directory ``out``.

    ``settings``: how it moves, grabs and checks each frame; ``header``: what the dataset records of the bench
    (:mod:`drivers.acquisition.settings`); ``nominal`` and ``limits``: the model and soft limits every pose is
    checked against before anything moves; ``operator``: who does the guided line; ``suspension``: what holds a
    pose's frame while the scene is unfit; ``resume``: go on with the frames of an existing dataset; ``progress``
    and ``on_frame``: observers of the run and of each frame written (neither may wait).
    """

    def __init__(
        self,
        plan: Plan,
        actuators: Actuators,
        camera: Camera,
        out: str | Path,
        *,
        settings: AcquisitionSettings | None = None,
        header: DatasetHeader | None = None,
        nominal: I4Parameters = NOMINAL,
        limits: SoftLimits | None = None,
        operator: Operator | None = None,
        suspension: Suspension | None = None,
        resume: bool = False,
        progress: Callable[[Progress], None] | None = None,
        on_frame: Callable[[int], None] | None = None,
    ) -> None:
        self.plan = plan
        self.actuators = actuators
        self.camera = camera
        self.out = Path(out)
        self.settings = settings or AcquisitionSettings()
        self.header = header or DatasetHeader()
        self.nominal = nominal
        self.limits = limits or SoftLimits()
        self.operator = operator
        self.resume_run = resume
        self.progress_cb = progress
        self.units = plan_units(plan)
        self._go = asyncio.Event()
        self._go.set()
        self._aborting = False
        self._task: asyncio.Task | None = None
        self._writer: DatasetWriter | None = None
        self._t0 = 0.0
        self._done_now = 0
        self.state = "idle"
        self.overheads: list[float] = []
        self.timings: list[tuple[float, float, float]] = []  # (start, in position, written) per pose
        self._record_s: float | None = None  # running estimate of one grab + write
        self._pending: asyncio.Future | None = None
        self.suspension = (
            suspension  # drivers.acquisition.suspenders: a pose's frame waits until the scene is fit to record
        )
        #: called with each frame's dataset index once it is written (in the writer thread): an observer that must
        #: not wait (drivers.acquisition.streaming.FrameStream.submit); one that raises is logged, the run goes on
        self.on_frame = on_frame

    # -- control ----------------------------------------------------------------------------------
    def pause(self) -> None:
        """Stop after the current pose (the mechanism stays where it is); once that pose is written to disk, the
        progress says ``paused`` with the message ``held before pose k/n``."""
        self._go.clear()
        self._emit("paused", "paused")

    def resume(self) -> None:
        self._go.set()
        self._emit("running", "resumed")

    def abort(self) -> None:
        """Stop the actuators now and end the run (frames written so far are kept)."""
        self._aborting = True
        self._go.set()
        if self._task is not None and not self._task.done():
            self._task.cancel()

    # -- progress ---------------------------------------------------------------------------------
    def _emit(self, state: str, message: str = "", phase: str = "") -> None:
        self.state = state
        done = len(self._writer) if self._writer is not None else 0
        elapsed = time.monotonic() - self._t0 if self._t0 else 0.0
        eta = None
        if self._done_now and state == "running":
            eta = elapsed / self._done_now * (len(self.units) - done)
        if self.progress_cb is not None:
            try:
                self.progress_cb(Progress(state, done, len(self.units), phase, elapsed, eta, message))
            except Exception:  # a broken progress display must not break the run
                log.exception("progress callback failed")

    # -- run --------------------------------------------------------------------------------------
    async def run(self) -> RunResult:
        self._task = asyncio.current_task()
        try:
            return await self._run()
        except asyncio.CancelledError:
            stopped = await self._uninterruptible(self._stop_and_flush())
            if self._aborting:
                n = len(self._writer) if self._writer else 0
                self._mark("aborted", None, "aborted on request")
                self._emit("aborted", f"aborted; {stopped}; {n} frames kept in {self.out}")
                raise AbortedError(f"acquisition aborted; {stopped}; {n} frames kept in {self.out}") from None
            raise
        finally:
            self._task = None

    async def _stop_and_flush(self) -> str:
        stopped = await self._safe_stop()
        with contextlib.suppress(Exception):
            await self._flush_writes()
        return stopped

    @staticmethod
    async def _uninterruptible(coro) -> Any:
        """Run ``coro`` to its end even if this task is cancelled again meanwhile (an abort repeated while the stop
        is being confirmed, a shutdown): the stop's read-back and the last frame's write are never cut short."""
        fut = asyncio.ensure_future(coro)
        while True:
            try:
                return await asyncio.shield(fut)
            except asyncio.CancelledError:
                if fut.done():
                    return fut.result()

    async def _safe_stop(self) -> str:
        """Stop the actuators, and keep stopping while the stop is not confirmed and the controller is connected but
        silent (a stalled controller, an overloaded gateway: it may execute buffered commands when it answers
        again), up to the actuators' ``stop_persist_s``. Returns what to tell: "motion stopped" only when a stop
        was confirmed."""
        persist_s = float(getattr(self.actuators, "stop_persist_s", 0.0) or 0.0)
        t0 = time.monotonic()
        attempts = 0
        while True:
            attempts += 1
            try:
                await asyncio.shield(self.actuators.stop())
            except Exception as exc:
                log.error("could not stop the actuators (attempt %d): %s", attempts, exc)
                elapsed = time.monotonic() - t0
                if not getattr(exc, "reachable", False) or elapsed >= persist_s:
                    tried = f" (stop tried {attempts} times over {elapsed:.1f} s)" if attempts > 1 else ""
                    return _not_stopped(exc) + tried
                self._emit(self.state, f"stop not confirmed yet; stopping again ({exc})")
                await asyncio.sleep(0.05)
                continue
            if attempts == 1:
                return "motion stopped"
            return f"motion stopped (confirmed after {attempts} stops, {time.monotonic() - t0:.1f} s after the first)"

    def _mark(self, state: str, pose: int | None, reason: str) -> None:
        """Record the run's state in ``dataset.json`` (``acquisition``); a failure to record it is logged, and the
        run's own outcome (the exception being raised) stands."""
        if self._writer is not None:
            try:
                self._writer.set_extra(
                    "acquisition",
                    {
                        "state": state,
                        "failed_pose": pose,
                        "reason": reason,
                        "frames": len(self._writer),
                        "total": len(self.units),
                    },
                )
            except Exception:
                log.exception("could not record the run's state %r in %s", state, self.out)

    async def _run(self) -> RunResult:
        validate_plan(self.plan, self.nominal, self.limits)  # nothing moves before the whole plan is checked
        self._emit("starting", "connecting")
        await self.camera.open()
        await self.actuators.connect()
        start = self._open_dataset_prefix()
        st = await self.actuators.status()
        if st.alarms and set(st.alarms.values()) == {ALARM_WATCHDOG}:
            # a previous session lost contact mid-move and the drives' watchdog stopped them (and latched the
            # alarm): this run is the explicit request to go on
            self._emit("starting", "clearing the communication-watchdog alarm left by a lost session")
            await self.actuators.reset_alarms()
            st = await self.actuators.status()
        if st.alarms:
            from drivers.devices.modbus import alarm_message

            ax, code = next(iter(st.alarms.items()))
            raise DeviceError(
                f"controller in alarm before the run: {alarm_message(ax, code)}; nothing moved; "
                "clear the cause and reset the alarm"
            )
        if any(a.free for a in st.axes):
            await self.actuators.set_free(False)
        if self.settings.home and not st.homed:
            self._emit("starting", "homing")
            await self.actuators.home()
        t_grab = time.perf_counter()
        first = await self._grab()  # the camera works before anything moves; its size sizes the dataset
        self._note_record_time(time.perf_counter() - t_grab)
        if self._writer is None:
            self._create_dataset(first)
        assert self._writer is not None  # resumed, or created just above
        self._t0 = time.monotonic()
        self._emit("running", f"starting at pose {start + 1}/{len(self.units)}")
        i = start
        while i < len(self.units):
            u = self.units[i]
            if not self._go.is_set():  # paused: the pose in progress is finished and written, nothing moves
                await self._flush_writes()
                self._emit("paused", f"held before pose {i + 1}/{len(self.units)}")
                await self._go.wait()
            if self._aborting:  # a cancellation swallowed inside a device client must not lose the abort
                raise asyncio.CancelledError
            step = self.plan.steps[u.step]
            try:
                if step.line is not None:
                    i = await self._line(i)
                    continue
                await self._pose(u)
            except AcquisitionError:
                raise
            except (DeviceError, InputError, OSError) as exc:
                await self._fail(u, exc)
            i += 1
        await self._flush_writes()
        self._mark("done", None, "")
        self._emit("done", f"{len(self._writer)} frames in {self.out}")
        self._writer.close()
        return RunResult(
            self.out,
            len(self._writer),
            len(self.units),
            self._done_now,
            time.monotonic() - self._t0,
            list(self.overheads),
        )

    async def _fail(self, u: Unit, exc: BaseException) -> None:
        # a stop the driver could not confirm is tried again (the controller may answer again, and execute what it
        # had buffered)
        if isinstance(exc, StopNotConfirmedError) and not getattr(exc, "reachable", False):
            stopped = _not_stopped(exc)  # the driver tried for one deadline and nothing reached the controller
        else:
            stopped = await self._safe_stop()
            if isinstance(exc, StopNotConfirmedError) and exc.__cause__ is not None and stopped.startswith("motion st"):
                # the driver's own stop was not confirmed, this one was: say what failed and how it ended
                exc = exc.__cause__
                stopped = "the first stop was not confirmed; " + stopped
        with contextlib.suppress(Exception):
            await self._flush_writes()
        with contextlib.suppress(Exception):
            if self.plan.steps[u.step].line is not None:
                await self.actuators.set_free(False)
        n = len(self._writer) if self._writer else 0
        where = f"pose {u.index + 1}/{len(self.units)} (plan step {u.step}, phase '{u.phase}'"
        where += (
            f", line sample {u.line_sample})"
            if u.line_sample is not None
            else (f", q = {np.round(np.asarray(u.q) * 1e3, 3).tolist()} mm)" if u.q else ")")
        )
        msg = (
            f"{where} failed: {exc}; {stopped}; {n} frames kept in {self.out}; "
            "resume the run to continue from this pose"
        )
        self._mark("failed", u.index, str(exc))
        self._emit("failed", msg, u.phase)
        raise AcquisitionError(msg, pose=u.index, step=u.step, phase=u.phase, cause=exc, frames_kept=n) from exc

    # -- dataset ----------------------------------------------------------------------------------
    def _open_dataset_prefix(self) -> int:
        meta = self.out / "dataset.json"
        if not meta.exists():
            return 0
        if not self.resume_run:
            raise InputError("dataset already exists; resume it or choose another directory", file=str(self.out))
        ds = Dataset.open(self.out)
        n = len(ds.frames)
        if n > len(self.units):
            raise InputError(f"dataset has {n} frames, more than the plan's {len(self.units)}", file=str(self.out))
        for k in range(n):
            if ds.frames[k].phase != self.units[k].phase:
                raise InputError(
                    f"dataset does not match the plan: frame {k} is '{ds.frames[k].phase}', the "
                    f"plan's pose {k + 1} is '{self.units[k].phase}'",
                    file=str(self.out),
                    frame=k,
                )
        stored = ds.document.model_dump().get("plan")
        if isinstance(stored, dict) and stored.get("name") not in (None, self.plan.name):
            raise InputError(
                f"dataset was recorded with plan {stored.get('name')!r}, not {self.plan.name!r}", file=str(self.out)
            )
        known = self.header.camera.get("intrinsics")
        had = (ds.document.camera.model_extra or {}).get("intrinsics")
        if isinstance(known, dict) and (not isinstance(had, dict) or had.get("sha256") != known.get("sha256")):
            raise InputError(
                "the dataset was recorded with other intrinsics than the bench file's camera file "
                f"({known.get('file')}); resume with the bench file it was recorded with, or start a new dataset",
                file=str(self.out),
                field="camera.intrinsics",
            )
        self._writer = DatasetWriter(
            self.out,
            camera=ds.document.camera,
            board=ds.document.board,
            legs=ds.document.legs,
            nominal=self.nominal.as_dict(),
            resume=True,
        )
        return n

    def _create_dataset(self, first: Frame) -> None:
        h, w = first.image.shape[:2]
        known = self.header.camera.get("intrinsics")
        if isinstance(known, dict) and (known.get("width"), known.get("height")) != (w, h):
            raise InputError(
                f"the camera file was calibrated on {known.get('width')}x{known.get('height')} images, the camera "
                f"delivers {w}x{h}; calibrate this camera (`i4cal camera calibrate`) or name its own file; no pose "
                "of the plan was moved to",
                file=str(known.get("file")),
            )
        cam = CameraSpec(width=w, height=h, **self.header.camera)
        self._writer = DatasetWriter(
            self.out,
            camera=cam,
            board=self.header.board,
            legs=self.header.legs,
            nominal=self.nominal.as_dict(),
            extra={"plan": self.plan.model_dump(mode="json", exclude_none=True), **self.header.extra},
        )

    def _write(self, u: Unit, q: np.ndarray, frame: Frame, **extra: Any) -> None:
        img = frame.image
        if img.dtype not in (np.uint8, np.uint16):
            raise FrameError(f"camera delivered {img.dtype} pixels; the dataset stores 8 or 16 bit")
        meta = frame.meta or {}
        if "q_true" in meta and "pose_true" in meta:
            extra["truth"] = {"q": list(meta["q_true"]), "pose": list(meta["pose_true"])}
        assert self._writer is not None  # created (run) before the first frame is grabbed
        index = self._writer.add_frame(u.phase, q, img, **extra)
        self._done_now += 1
        if self.on_frame is not None:
            try:
                self.on_frame(index)
            except Exception:
                log.exception("frame observer failed on frame %d", index)

    async def _write_behind(self, u: Unit, q: np.ndarray, frame: Frame, **extra: Any) -> None:
        """Write a frame in a worker thread while the next pose's move starts (frames stay in order: one
        write at a time; :meth:`_flush_writes` waits for the last one)."""
        try:
            await self._flush_writes()
        except asyncio.CancelledError:
            # aborted while the previous frame was being written: this frame was grabbed too, it is written after
            # that one (the abort's flush waits for both)
            self._pending = asyncio.ensure_future(self._write_after(self._pending, u, q, frame, extra))
            raise
        self._pending = asyncio.ensure_future(asyncio.to_thread(self._write, u, q, frame, **extra))

    async def _write_after(
        self, previous: asyncio.Future | None, u: Unit, q: np.ndarray, frame: Frame, extra: dict[str, Any]
    ) -> None:
        if previous is not None:
            await previous
        await asyncio.to_thread(self._write, u, q, frame, **extra)

    async def _flush_writes(self) -> None:
        """Wait for the frame being written. The write stays pending until it has finished: a cancellation (an
        abort) that arrives while waiting here leaves it to the abort's own flush, which waits for it before the run
        records its state and returns (a run that has ended never writes again)."""
        p = self._pending
        if p is None:
            return
        try:
            await asyncio.shield(p)
        finally:
            if p.done() and self._pending is p:
                self._pending = None

    # -- steps ------------------------------------------------------------------------------------
    async def _grab(self) -> Frame:
        last: Exception | None = None
        for _ in range(self.settings.grab_retries + 1):
            try:
                return await self.camera.grab(self.settings.grab_timeout_s)
            except (DeviceTimeoutError, FrameError) as exc:
                last = exc
                log.warning("grab failed (%s); retrying", exc)
        # grab_retries >= 0: at least one attempt failed and set last
        raise last  # type: ignore[misc]

    async def _pose(self, u: Unit) -> None:
        t_start = time.perf_counter()
        arrived = None  # the encoders as the move's last poll read them, in position
        if u.q is not None:
            arrived = np.asarray(await self.actuators.move(np.asarray(u.q)), dtype=float)
        t_moved = time.perf_counter()
        if self.settings.settle_s:
            await asyncio.sleep(self.settings.settle_s)
            arrived = None  # read again after the wait
        q, frame = await self._checked_frame(u, arrived)
        await self._write_behind(u, q, frame, q_target=list(u.q) if u.q is not None else None)
        t_end = time.perf_counter()
        self.timings.append((t_start, t_moved, t_end))
        self._note_record_time(t_end - t_moved)
        self._emit("running", "", u.phase)

    async def _read_status(self) -> Any:
        st = await self.actuators.status()
        if st.alarms:
            from drivers.devices.modbus import alarm_message
            from drivers.errors import AlarmError

            ax, code = next(iter(st.alarms.items()))
            raise AlarmError(alarm_message(ax, code), code=code, axis=ax)
        return st

    async def _checked_frame(self, u: Unit, arrived: np.ndarray | None = None) -> tuple[np.ndarray, Frame]:
        """A pose's frame and the q it records: the encoders read, the frame grabbed, the encoders read again. The q
        is kept only when both readings agree (``line_still_m``) and lie at the commanded target (the actuators'
        ``in_position_m``): a stale reading that got past the link's guards is not written. Read again up to
        ``frame_reads`` times, then the frame is refused (:class:`~drivers.errors.ProtocolError`: the run fails on
        it, saying so). ``arrived``: the encoders the move has just read in position (m, shape (n,)), the first
        reading before the grab (no settling wait since): a link that limits how often an axis is read spends no
        read on it."""
        target = np.asarray(u.q, dtype=float) if u.q is not None else None
        tol_target = float(getattr(self.actuators, "in_position_m", 2e-5))
        problem = ""
        for attempt in range(1, self.settings.frame_reads + 1):
            q1 = arrived if attempt == 1 and arrived is not None else (await self._read_status()).positions
            frame = await self._grab()
            if self.suspension is not None:  # held at this pose while the scene is unfit; a frame grabbed after
                frame = await self.suspension.clear(frame, self._grab, self._suspended, self._go)
            q2 = np.asarray(await self.actuators.read_encoders(), dtype=float)
            problem = q_problem(q1, q2, target, tol_target, self.settings.line_still_m)
            if not problem:
                return q1, frame
            log.warning("pose %d: %s (reading %d); read again", u.index + 1, problem, attempt)
            self._emit("running", f"pose {u.index + 1}/{len(self.units)}: {problem}; read again", u.phase)
        raise ProtocolError(
            f"frame refused, not written: {problem}, in {self.settings.frame_reads} readings "
            "(a stale or wrong encoder reading)"
        )

    def _suspended(self, state: str, message: str) -> None:
        self._emit("suspended" if state == "suspended" else "running", message)

    def _note_record_time(self, dt: float) -> None:
        self._record_s = dt if self._record_s is None else 0.7 * self._record_s + 0.3 * dt

    def line_rate(self, requested_hz: float) -> float:
        """The line's sampling rate: as requested, capped to what grab + write sustain (the operator is told)."""
        if self._record_s:
            return min(requested_hz, 0.35 / self._record_s)
        return requested_hz

    async def _line(self, i: int) -> int:
        """Record the guided line whose first not-yet-recorded sample is unit ``i``; returns the next unit."""
        u0 = self.units[i]
        step = self.plan.steps[u0.step]
        line = step.line
        assert line is not None  # called for a guided line's step only (run)
        k0 = u0.line_sample or 0
        rate = self.line_rate(self.settings.line_rate_hz or line.rate_hz)
        poses = line_poses(line)
        if self.operator is None:
            raise DeviceError("a guided line needs an operator (bench [operator] uri)")
        await self._flush_writes()
        # bring the mechanism near the ruler's start (nominal model), then let go
        try:
            await self.actuators.move(ikm(self.nominal, poses[k0]))
            await self.actuators.set_free(True)
            await self.operator.begin_line(poses[k0].tolist(), poses[-1].tolist(), line.samples - k0, rate)
        except (DeviceError, InputError, OSError) as exc:
            await self._fail(u0, exc)
        t0 = time.monotonic()
        t_prev = -math.inf  # when the previous sample's encoders were last read
        try:
            for k in range(k0, line.samples):
                u = self.units[i + (k - k0)]
                if self._aborting:
                    raise asyncio.CancelledError
                try:
                    # on schedule; and, when behind it, never closer than half a period to the previous sample: the
                    # operator moves at the pace they were given, and encoders read back to back while the operator
                    # moves on look like a jump no axis can make (the axes' plausibility check)
                    now = time.monotonic()
                    await asyncio.sleep(max(0.0, t0 + (k - k0 + 0.5) / rate - now, t_prev + 0.5 / rate - now))
                    t_rec = time.perf_counter()
                    for _attempt in range(3):  # the frame must match the encoders (still across the grab)
                        st = await self.actuators.status()
                        if st.alarms:
                            from drivers.devices.modbus import alarm_message
                            from drivers.errors import AlarmError

                            ax, code = next(iter(st.alarms.items()))
                            raise AlarmError(alarm_message(ax, code), code=code, axis=ax)
                        frame = await self._grab()
                        q2 = await self.actuators.read_encoders()
                        t_prev = time.monotonic()
                        spread = float(np.max(np.abs(q2 - st.positions)))
                        if spread <= self.settings.line_still_m:
                            break
                    else:
                        raise FrameError(
                            f"line sample {k}: frame refused, not written: the encoders read {spread * 1e3:.3f} mm "
                            "apart before and after the grab, in 3 readings "
                            f"(more than {self.settings.line_still_m * 1e3:.3f} mm)"
                        )
                    # in a worker thread like a pose's frame: PNG encoding and the fsync'd dataset.json must not
                    # stall the event loop (the service answers requests from it)
                    await self._write_behind(
                        u, st.positions, frame, line_sample=k, line_step=u.step, q_spread_m=spread, line_rate_hz=rate
                    )
                    self._note_record_time(time.perf_counter() - t_rec)
                    self._emit("running", "", u.phase)
                except AcquisitionError:
                    raise
                except (DeviceError, InputError, OSError) as exc:
                    with contextlib.suppress(Exception):
                        await self.operator.end_line()
                    await self._fail(u, exc)
        finally:
            with contextlib.suppress(Exception):
                await self.operator.end_line()
            with contextlib.suppress(Exception):
                await self.actuators.set_free(False)
        return i + (line.samples - k0)


def acquisition_from_config(
    plan: Plan,
    bench_config: Any,
    out: str | Path,
    *,
    resume: bool = False,
    progress: Callable[[Progress], None] | None = None,
    header: DatasetHeader | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> Acquisition:
    """An :class:`Acquisition` on the bench's devices (opened by URI) with the bench file's settings. ``header``:
    what the dataset records besides the bench file's camera fields (its lens model, its camera file's
    intrinsics), which are added to it."""
    from drivers.acquisition.config import open_actuators, open_camera, open_operator

    cfg = bench_config
    header = header or DatasetHeader()
    camera = dict(header.camera)
    if getattr(
        cfg.camera, "lens_model", None
    ):  # the bench file fixes the calibration's lens model: the dataset says so
        camera["lens_model"] = cfg.camera.lens_model
    known = cfg.camera_intrinsics()  # read and checked before anything moves
    if known is not None:  # the bench file names the camera's intrinsics: every dataset carries them
        camera.update(intrinsics_spec(known))
    return Acquisition(
        plan,
        open_actuators(cfg),
        open_camera(cfg),
        Path(out),
        settings=AcquisitionSettings.from_config(cfg),
        header=replace(header, camera=camera),
        nominal=cfg.nominal_parameters(),
        limits=cfg.calib_limits(),
        operator=open_operator(cfg),
        suspension=Suspension.from_config(cfg.suspenders, header.board),
        resume=resume,
        progress=progress,
        on_frame=on_frame,
    )


def intrinsics_spec(known) -> dict[str, Any]:
    """The dataset's camera fields for a known camera (a :class:`drivers.acquisition.config.IntrinsicsFile`): ``K``,
    ``dist``,
    and ``intrinsics`` (the file, its SHA-256, its image size and its ``calibration``: covariance, refined board
    points, lens model; docs/dataset.md)."""
    cam = known.camera
    return {
        "K": cam.K.tolist(),
        "dist": cam.dist.tolist(),
        "intrinsics": {
            "file": str(known.path),
            "sha256": known.sha256,
            "width": int(cam.width),
            "height": int(cam.height),
            **cam.extra,
        },
    }


async def close_devices(acq: Acquisition) -> None:
    """Close an acquisition's devices, ignoring errors (the run's own error is the one that matters)."""
    for dev in (acq.camera, acq.actuators, acq.operator):
        close = getattr(dev, "close", None)
        if close is not None:
            with contextlib.suppress(Exception):
                await close()


async def acquire(
    plan: Plan,
    bench_config: Any,
    out: str | Path,
    *,
    resume: bool = False,
    progress: Callable[[Progress], None] | None = None,
    header: DatasetHeader | None = None,
) -> RunResult:
    """Open the bench's devices (by URI), run ``plan`` into ``out`` and close the devices
    (:func:`acquisition_from_config`)."""
    acq = acquisition_from_config(plan, bench_config, out, resume=resume, progress=progress, header=header)
    try:
        return await acq.run()
    finally:
        await close_devices(acq)
