"""The axis controller: :class:`drivers.devices.interfaces.Actuators` over any :class:`drivers.devices.links.AxisLink`.

The link speaks the protocol (Modbus, serial ASCII); the controller owns the motion, the same over every link.

Plausible readings. Every decoded position must lie within the soft limits widened by
``plausibility_margin_m`` and within ``max_speed_m_s`` x the time since the axis' last accepted
reading (+ ``plausibility_slack_m``); during a commanded move it must also lie on the commanded move (between its
start and its target), not behind a reading already accepted on it (the move goes one way: an older position is a
stale reply), and no further along than the commanded speed (and ``max_accel_m_s2`` when set) allows since the
command was sent. Otherwise :class:`~drivers.errors.ProtocolError` names the axis, the value and why, and nothing
moves on it (homing, which may re-zero an encoder, and free drives are exempt from the trajectory tests).

After a failure (a stop not confirmed, a motion command whose fate is open on a lost connection) the controller
stops every axis, confirmed, before it reports a status or moves again (``motion_in_doubt``).

A move follows one shape: check the targets (per-axis soft limits, then the kinematic model), compute a timeout
from the distances and speeds, write target + speed + start, poll until every axis is in position, and stop every
axis on any error, timeout or cancellation. A stop is sent to every axis at once (``asyncio.gather``; a link
carries one request at a time) and is confirmed by reading every axis back not moving, all within one deadline
(``stop_deadline_s``); otherwise :class:`~drivers.errors.StopNotConfirmedError` says motion may not have stopped.
The stop runs in its own task, so a stop sent while its caller is being cancelled still goes out.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Callable, MutableMapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from calib.design.motion import MotionSpec, move_time
from calib.errors import UnreachableError
from calib.model.kinematics import dkm
from calib.model.parameters import I4Parameters
from drivers.devices.interfaces import ActuatorStatus, AxisStatus, SoftLimitsM
from drivers.devices.links import AxisLink, Command, SafetySettings
from drivers.devices.registermap import ALARM_TEXT
from drivers.errors import (
    AlarmError,
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    LimitError,
    ProtocolError,
    StopNotConfirmedError,
)

log = logging.getLogger(__name__)


def alarm_message(axis: int, code: int) -> str:
    """``axis 2 in alarm, code 0x30 (soft limit)``: axis 1..n and its alarm code, with the code's meaning if known."""
    text = ALARM_TEXT.get(code)
    return f"axis {axis} in alarm, code 0x{code:02X}" + (f" ({text})" if text else "")


def check_targets(
    q: Any,
    limits: SoftLimitsM,
    nominal: I4Parameters | None,
    workspace_check: Callable[[np.ndarray], Any] | None = None,
) -> np.ndarray:
    """Refuse targets outside the per-axis soft limits, or that the kinematic model cannot reach.

    The axis count is that of the soft limits (four for the I4). The model is ``workspace_check`` (a function of
    the joint targets, metres, that raises :class:`calib.errors.UnreachableError`, e.g. another mechanism's DKM at
    its nominal geometry) when given, else the nominal I4's DKM when ``nominal`` is given.

    Returns the targets, shape ``(n,)``, metres; raises :class:`~drivers.errors.LimitError` (nothing moved).
    """
    n = len(limits.q_min)
    qv = np.asarray(q, dtype=np.float64).reshape(-1)
    if qv.shape != (n,) or not np.all(np.isfinite(qv)):
        raise LimitError(f"a target needs {n} finite values in metres, got {q!r}")
    for i in range(n):
        lo, hi = limits.q_min[i], limits.q_max[i]
        if not lo <= qv[i] <= hi:
            bound = lo if qv[i] < lo else hi
            raise LimitError(
                f"q{i + 1} = {qv[i] * 1e3:.3f} mm is outside the soft limits [{lo * 1e3:.1f}, "
                f"{hi * 1e3:.1f}] mm by {abs(qv[i] - bound) * 1e3:.3f} mm; nothing moved",
                axis=i + 1,
            )
    if workspace_check is None and nominal is not None:
        workspace_check = partial(dkm, nominal)
    if workspace_check is not None:
        try:
            workspace_check(qv)
        except UnreachableError as exc:
            raise LimitError(
                f"target {np.round(qv * 1e3, 3).tolist()} mm is outside the workspace of the "
                f"kinematic model ({exc}); nothing moved"
            ) from None
    return qv


@dataclass(frozen=True)
class AxisSettings:
    """How an :class:`AxisController` moves the axes and judges their readings (the keywords of the same names of
    :class:`AxisController`, documented there): speeds in m/s, accelerations in m/s^2, times in s, lengths in m."""

    speed_m_s: float = 0.05
    accel_m_s2: float = 0.5
    poll_s: float = 0.002
    settle_s: float = 0.0
    in_position_m: float = 2e-5
    move_timeout_factor: float = 2.0
    move_timeout_margin_s: float = 1.0
    home_timeout_s: float = 60.0
    max_speed_m_s: float | None = None
    plausibility_margin_m: float = 0.05
    plausibility_slack_m: float = 1e-3
    stop_deadline_s: float = 2.0


class AxisController:
    """:class:`drivers.devices.interfaces.Actuators` over a :class:`drivers.devices.links.AxisLink`: the motion,
    whatever the protocol.

    Parameters
    ----------
    link:
        The link to the motion controller; the number of axes is ``link.n_axes``.
    limits:
        Per-axis soft limits (m), one value per axis; default -0.10 to 0.80 m on every axis.
    nominal, workspace_check:
        The kinematic model that refuses unreachable targets: ``workspace_check`` (a function of the joint targets,
        m, raising :class:`calib.errors.UnreachableError`) when given, else the nominal I4's DKM when ``nominal`` is.
    speed_m_s, accel_m_s2:
        Move speed of the axis that travels furthest (the others are scaled to arrive together) and the
        drive's acceleration, used only for the move timeout.
    poll_s, settle_s, in_position_m:
        Status polling period (s), pause after arriving (s), and how close (m) every encoder must be to its target.
    move_timeout_factor, move_timeout_margin_s, home_timeout_s:
        A move's timeout is ``factor x max_i(d_i/v_i + v_i/a) + margin`` (s); homing's is ``home_timeout_s``.
    max_speed_m_s:
        Fastest an axis can move (homing, a person guiding a free drive included), for the plausibility of
        readings. ``None``: ``5 * speed_m_s``.
    plausibility_margin_m, plausibility_slack_m:
        A reading must lie within the soft limits widened by the margin (m), and within
        ``max_speed_m_s * dt + slack`` of the axis' previous accepted reading.
    stop_deadline_s:
        One deadline (s) for the whole stop sequence: stop sent to every axis and every axis read back not
        moving.
    backoff_s:
        Pause (s) before a stop that could not be sent is sent again.
    safety:
        :class:`drivers.devices.links.SafetySettings` (here: ``stop_persist_s``, read by the acquisition).

    A stop that was acknowledged but still reads moving once the drive could have braked from full speed
    (``speed_m_s / accel_m_s2`` plus two polls) is sent again, until the deadline: an acknowledgement proves that a
    reply came, not that the drive acted (a lost frame answered by a copy of an earlier stop's echo, a drive busy).
    """

    def __init__(
        self,
        link: AxisLink,
        *,
        limits: SoftLimitsM | None = None,
        nominal: I4Parameters | None = None,
        workspace_check: Callable[[np.ndarray], Any] | None = None,
        speed_m_s: float = 0.05,
        accel_m_s2: float = 0.5,
        poll_s: float = 0.002,
        settle_s: float = 0.0,
        in_position_m: float = 2e-5,
        move_timeout_factor: float = 2.0,
        move_timeout_margin_s: float = 1.0,
        home_timeout_s: float = 60.0,
        max_speed_m_s: float | None = None,
        plausibility_margin_m: float = 0.05,
        plausibility_slack_m: float = 1e-3,
        stop_deadline_s: float = 2.0,
        backoff_s: float = 0.02,
        safety: SafetySettings | None = None,
    ) -> None:
        self.link = link
        self.n_axes = n = link.n_axes
        if limits is None:
            d = SoftLimitsM()
            limits = d if n == 4 else SoftLimitsM((d.q_min[0],) * n, (d.q_max[0],) * n)
        if len(limits.q_min) != n or len(limits.q_max) != n:
            raise ValueError(
                f"the controller at {link.endpoint} has {n} axes but the soft limits have {len(limits.q_min)} and "
                f"{len(limits.q_max)} values"
            )
        self.limits = limits
        self.nominal = nominal
        self.workspace_check = workspace_check
        self.speed_m_s = float(speed_m_s)
        self.accel_m_s2 = float(accel_m_s2)
        self.poll_s = float(poll_s)
        self.settle_s = float(settle_s)
        self.in_position_m = float(in_position_m)
        self.move_timeout_factor = float(move_timeout_factor)
        self.move_timeout_margin_s = float(move_timeout_margin_s)
        self.home_timeout_s = float(home_timeout_s)
        self.max_speed_m_s = float(5 * self.speed_m_s if max_speed_m_s is None else max_speed_m_s)
        self.plausibility_margin_m = float(plausibility_margin_m)
        self.plausibility_slack_m = float(plausibility_slack_m)
        self.stop_deadline_s = float(stop_deadline_s)
        self.backoff_s = float(backoff_s)
        #: a stop still read moving this long (s) after it was sent is sent again: the braking time from full speed
        self.stop_resend_s = self.speed_m_s / max(self.accel_m_s2, 1e-9) + 2 * self.poll_s
        self.safety = safety or SafetySettings()
        #: a failed run keeps stopping this long (s) while the controller is connected but silent
        self.stop_persist_s = self.safety.stop_persist_s
        self.accel_limit_m_s2 = self.safety.max_accel_m_s2 or math.inf
        self._free_bits = [False] * n
        self._homing = False
        self._last_reading: list[tuple[float, float] | None] = [None] * n  # (position m, monotonic s) per axis
        #: per axis, the move commanded last: (start position m, target m, speed m/s, monotonic s when sent), and
        #: the furthest progress (m) read along it; readings are checked against it
        self._commanded: list[_Commanded | None] = [None] * n
        #: a motion may be running that nobody confirmed stopped (a failed stop, a command that may still execute):
        #: the axes are stopped, confirmed, before anything else is reported or moved
        self._unsafe = False

    @property
    def endpoint(self) -> str:
        return self.link.endpoint

    @property
    def stats(self) -> MutableMapping[str, Any]:
        """The link's counters (also summed process-wide for ``GET /metrics``, :mod:`drivers.acquisition.metrics`)."""
        return self.link.stats

    # -- connection ---------------------------------------------------------------------------------
    async def connect(self) -> None:
        await self.link.open()
        self._last_reading = [None] * self.n_axes
        self._commanded = [None] * self.n_axes
        await self.status()  # every axis answers, with plausible positions (after a failure: stopped first)

    @property
    def motion_in_doubt(self) -> bool:
        """``True`` while a motion may run that no stop has been confirmed against (a failed stop; a motion command
        that got no reply and may still execute): :meth:`status`, :meth:`move` and :meth:`home` stop first."""
        return self._unsafe or bool(getattr(self.link, "motion_in_doubt", False))

    async def _stop_first(self) -> None:
        """When the controller answers again after a failure: stop every axis and confirm it before anything else."""
        if self.motion_in_doubt:
            log.warning("%s: a motion may still run after a failure: stopping every axis first", self.endpoint)
            await self.stop()

    async def close(self) -> None:
        await self.link.close()

    async def __aenter__(self) -> AxisController:
        await self.connect()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    # -- status --------------------------------------------------------------------------------------
    def check_reading(self, axis: int, position_m: float, t_request: float, *, homed: bool = True) -> None:
        """Refuse an implausible position of axis 0..n-1 read by a request sent at ``t_request`` (monotonic s):
        outside the soft limits widened by the margin, or further from the last accepted reading than the
        axis can travel at ``max_speed_m_s`` since then. Accepted readings become the reference."""
        now = time.monotonic()
        lo = self.limits.q_min[axis] - self.plausibility_margin_m
        hi = self.limits.q_max[axis] + self.plausibility_margin_m
        if not (math.isfinite(position_m) and lo <= position_m <= hi):
            self._last_reading[axis] = None
            raise ProtocolError(
                f"axis {axis + 1}: implausible position {position_m:.6g} m read from {self.endpoint}: outside the "
                f"soft limits [{self.limits.q_min[axis]:.3f}, {self.limits.q_max[axis]:.3f}] m widened by "
                f"{self.plausibility_margin_m:.3f} m (wrong register map, word order or scale, or a corrupt "
                "reply); nothing moves on it"
            )
        prev = self._last_reading[axis]
        if prev is not None and not self._homing:
            p0, t0 = prev
            reach = self.max_speed_m_s * max(now - t0, 0.0) + self.plausibility_slack_m
            if abs(position_m - p0) > reach:
                self._last_reading[axis] = None  # refused once: the next reading is judged afresh
                self._commanded[axis] = None
                raise ProtocolError(
                    f"axis {axis + 1}: implausible position {position_m * 1e3:.3f} mm read from {self.endpoint}: "
                    f"{abs(position_m - p0) * 1e3:.3f} mm from the reading {now - t0:.3f} s earlier "
                    f"({p0 * 1e3:.3f} mm), more than the axis can travel at {self.max_speed_m_s:g} m/s "
                    f"({reach * 1e3:.3f} mm); nothing moves on it"
                )
        cmd = self._commanded[axis]
        if cmd is not None and not self._homing and not self._free_bits[axis]:  # noqa: SIM102
            if problem := cmd.refuses(position_m, now, self.plausibility_slack_m):
                self._last_reading[axis] = None  # refused once: the next reading is judged afresh
                self._commanded[axis] = None
                raise ProtocolError(
                    f"axis {axis + 1}: implausible position {position_m * 1e3:.3f} mm read from {self.endpoint}: "
                    f"{problem} (a stale reply?); nothing moves on it"
                )
        self._last_reading[axis] = (position_m, t_request)

    async def _read(self, axes: Sequence[int]) -> dict[int, AxisStatus]:
        """The link's readings of (at least) ``axes``, each checked plausible, with the free bits."""
        t_request = time.monotonic()
        got = await self.link.read_axes(axes)
        out = {}
        for i, s in got.items():
            self.check_reading(i, s.position_m, t_request)
            out[i] = dataclasses.replace(s, free=self._free_bits[i])
        return out

    async def read_axis(self, axis: int) -> AxisStatus:
        """Axis ``axis`` (0..n-1) read now (a link that reads every axis at once checks them all)."""
        return (await self._read([axis]))[axis]

    async def status(self) -> ActuatorStatus:
        await self._stop_first()
        if self.link.reads_every_axis:
            got = await self._read(range(self.n_axes))
            return ActuatorStatus(tuple(got[i] for i in range(self.n_axes)))
        return ActuatorStatus(tuple([await self.read_axis(i) for i in range(self.n_axes)]))

    async def read_encoders(self) -> np.ndarray:
        return (await self.status()).positions

    def _raise_alarms(self, st: ActuatorStatus) -> None:
        alarms = st.alarms
        if alarms:
            axis, code = next(iter(alarms.items()))
            more = "" if len(alarms) == 1 else f" (and axes {sorted(set(alarms) - {axis})})"
            raise AlarmError(alarm_message(axis, code) + more, code=code, axis=axis)

    # -- control -------------------------------------------------------------------------------------
    async def _control(self, axis: int, command: Command | None, *, urgent: bool = False) -> None:
        await self.link.control(axis, command, free=self._free_bits[axis], urgent=urgent)

    async def stop(self) -> None:
        """Stop every axis and confirm it by reading every axis back not moving, within ``stop_deadline_s``.

        The stop runs in a task of its own (shielded): it goes out even when the caller is being cancelled.
        Raises :class:`~drivers.errors.StopNotConfirmedError` when it cannot be confirmed in time.
        """
        task = asyncio.ensure_future(self._stop_sequence())
        try:
            await asyncio.shield(task)
        except asyncio.CancelledError:
            task.add_done_callback(_log_unretrieved)  # it goes on; nobody will await its outcome
            raise

    async def _stop_sequence(self) -> None:
        t0 = time.monotonic()
        n = self.n_axes
        confirmed = [False] * n
        errors: dict[int, str] = {}
        reached = [False]  # some request reached a connection (a reply, or none in time): not merely unreachable

        async def send(i: int) -> float:
            while True:
                try:
                    await self._control(i, "stop", urgent=True)
                    reached[0] = True
                    return time.monotonic()
                except DeviceError as exc:
                    reached[0] |= not isinstance(exc, DeviceConnectionError)
                    errors[i] = f"stop not sent ({exc})"
                    await asyncio.sleep(self.backoff_s)

        async def one(i: int) -> None:
            sent = await send(i)
            n_sent = 1
            while True:
                try:
                    s = await self.read_axis(i)
                    if not s.moving:
                        confirmed[i] = True
                        return
                    errors[i] = f"still reads moving (stop sent {n_sent} times)"
                    if time.monotonic() - sent >= self.stop_resend_s:
                        # acknowledged is not obeyed: send it again while the deadline lasts
                        log.warning(
                            "axis %d still moving %.3f s after its stop: stop sent again", i + 1, self.stop_resend_s
                        )
                        sent = await send(i)
                        n_sent += 1
                except DeviceError as exc:
                    reached[0] |= not isinstance(exc, DeviceConnectionError)
                    errors[i] = f"not read back ({exc})"
                await asyncio.sleep(max(self.poll_s, 0.001))

        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.stop_deadline_s):
                await asyncio.gather(*(one(i) for i in range(n)))
        if all(confirmed):
            self._unsafe = False
            if getattr(self.link, "motion_in_doubt", False):
                # the links that track a motion in doubt have the attribute (getattr above)
                self.link.motion_in_doubt = False  # type: ignore[attr-defined]
        else:
            self._unsafe = True
            axes = tuple(i + 1 for i in range(n) if not confirmed[i])
            why = "; ".join(f"axis {i + 1}: {errors.get(i, 'no answer')}" for i in range(n) if not confirmed[i])
            err = StopNotConfirmedError(
                f"stop NOT confirmed within {self.stop_deadline_s:.1f} s at {self.endpoint} (axes {list(axes)}): "
                f"motion may NOT have stopped; use the emergency stop. {why}",
                axes=axes,
            )
            err.reachable = reached[0]  # type: ignore[attr-defined]  # connected but silent: worth trying again
            raise err
        log.debug("stop confirmed in %.3f s", time.monotonic() - t0)

    async def _stop_quietly(self) -> StopNotConfirmedError | None:
        try:
            await self.stop()
        except StopNotConfirmedError as exc:
            log.error("stop after a failed move: %s", exc)
            return exc
        except Exception as exc:  # the original error matters more
            log.error("stop after a failed move also failed: %s", exc)
        return None

    async def reset_alarms(self) -> None:
        for i in range(self.n_axes):
            await self._control(i, "reset")

    async def set_free(self, free: bool) -> None:
        for i in range(self.n_axes):
            self._free_bits[i] = bool(free)
            self._commanded[i] = None  # free: a person moves the axis, no command says where
            await self._control(i, None)

    async def _cleanup_stop(self, exc: BaseException) -> None:
        """After a failed or cancelled move or homing: stop; an unconfirmed stop is the error that matters (and the
        axes are stopped, confirmed, before anything else is reported or moved)."""
        not_stopped = await self._stop_quietly()
        if not_stopped is not None and not isinstance(exc, asyncio.CancelledError):
            err = StopNotConfirmedError(f"{exc}; then {not_stopped}", axes=not_stopped.axes)
            # reachable: set on the error where it is raised (above), not a declared attribute
            err.reachable = getattr(not_stopped, "reachable", False)  # type: ignore[attr-defined]
            raise err from exc

    async def home(self, timeout_s: float | None = None) -> None:
        st = await self.status()
        self._raise_alarms(st)
        self._commanded = [None] * self.n_axes
        self._homing = True
        try:
            for i in range(self.n_axes):
                await self._control(i, "home")
            await self._wait(lambda s: s.homed and not s.moving, timeout_s or self.home_timeout_s, "homing")
        except BaseException as exc:
            await self._cleanup_stop(exc)
            raise
        finally:
            self._homing = False

    def move_timeout(self, distance_m: np.ndarray, speeds_m_s: np.ndarray) -> float:
        """Timeout (s) of a move of ``distance_m`` at ``speeds_m_s`` (shape ``(n,)`` each)."""
        t = [d / v + v / self.accel_m_s2 for d, v in zip(distance_m, speeds_m_s, strict=True) if d > 0]
        return max(t, default=0.0) * self.move_timeout_factor + self.move_timeout_margin_s

    async def move(self, q: Any, timeout_s: float | None = None, speed_m_s: float | None = None) -> np.ndarray:
        target = check_targets(q, self.limits, self.nominal, self.workspace_check)
        st = await self.status()  # every position checked plausible (ProtocolError otherwise): nothing sent yet
        self._raise_alarms(st)
        if any(a.free for a in st.axes):
            raise DeviceError("drives are free (de-energised); re-energise them before a move")
        dist = np.abs(target - st.positions)
        v = float(speed_m_s or self.speed_m_s)
        dmax = float(dist.max())
        speeds = np.full(self.n_axes, v) if dmax == 0 else np.maximum(v * dist / dmax, v * 1e-3)
        timeout = timeout_s if timeout_s is not None else self.move_timeout(dist, speeds)
        t_sent = time.monotonic()
        self._commanded = [
            _Commanded(float(st.positions[i]), float(target[i]), float(speeds[i]), t_sent, self.accel_limit_m_s2)
            for i in range(self.n_axes)
        ]
        try:
            await self.link.start_move(target, speeds)

            def arrived(s: ActuatorStatus) -> bool:
                return s.in_position and bool(np.all(np.abs(s.positions - target) <= self.in_position_m))

            # the axis of the longest travel, at the full speed, is the last to arrive (the others' speeds scale)
            arrival = float(move_time(st.positions, target, MotionSpec(speed_m_s=v, accel_m_s2=self.accel_m_s2)))
            st = await self._wait(arrived, timeout, "move", arrival_s=arrival)
            if self.settle_s > 0:
                await asyncio.sleep(self.settle_s)
                st = await self.status()
                self._raise_alarms(st)
            return st.positions
        except BaseException as exc:
            await self._cleanup_stop(exc)
            raise

    async def _wait(
        self, done: Callable[[ActuatorStatus], bool], timeout_s: float, what: str, arrival_s: float = 0.0
    ) -> ActuatorStatus:
        """Poll every ``poll_s``, and no faster than the link sustains (its optional ``poll_interval_s``: polled
        faster, its guards would make the readings after the move wait), until ``done``; stopped on timeout.
        ``arrival_s``: when the move should end (s from now, the commanded profile's): at the link's pace the polls
        are timed so that one falls then, not up to an interval later."""
        t_end = time.monotonic() + timeout_s
        pace = float(getattr(self.link, "poll_interval_s", 0.0))
        t_arrival = time.monotonic() + arrival_s
        while True:
            t_poll = time.monotonic()
            st = await self.status()
            self._raise_alarms(st)
            if done(st):
                return st
            if time.monotonic() > t_end:
                raise DeviceTimeoutError(
                    f"{what} did not complete within {timeout_s:.2f} s; axes at "
                    f"{np.round(st.positions * 1e3, 3).tolist()} mm; stopped"
                )
            await asyncio.sleep(max(0.0, next_poll(t_poll, self.poll_s, pace, t_arrival) - time.monotonic()))


def next_poll(t_poll: float, poll_s: float, pace_s: float, t_arrival: float) -> float:
    """When (s, the clock of ``t_poll``) to poll a move next, after a poll at ``t_poll``: ``poll_s`` later, and no
    sooner than ``pace_s`` (the link's ``poll_interval_s``). Before the expected arrival ``t_arrival`` (with a
    pace) the polls are shifted so that one falls on it: the first after ``t_poll`` is the latest of
    ``t_arrival - k pace_s`` (k = 0, 1, ...) at least a pace after ``t_poll``."""
    t_next = t_poll + max(poll_s, pace_s)
    if pace_s > 0 and t_next < t_arrival:
        t_next = t_arrival - math.floor((t_arrival - t_next) / pace_s) * pace_s
    return t_next


#: a drive may run this much faster than commanded (its speed loop's overshoot) before a reading is refused
SPEED_TOLERANCE = 1.25


def _reach(speed: float, accel: float, t: float) -> float:
    """Farthest (m) an axis starting from rest travels in ``t`` s at up to ``speed`` m/s, accelerating at up to
    ``accel`` m/s^2 (``inf``: at once)."""
    if not math.isfinite(accel) or accel <= 0:
        return speed * t
    t_acc = speed / accel
    return 0.5 * accel * t * t if t <= t_acc else speed * t - 0.5 * speed * t_acc


@dataclass
class _Commanded:
    """One axis' commanded move: from ``p0`` to ``target`` (m) at up to ``speed`` (m/s), sent at ``t_sent``
    (monotonic s); ``progress``: the furthest (m) an accepted reading showed along it."""

    p0: float
    target: float
    speed: float
    t_sent: float
    accel: float
    progress: float = 0.0

    def refuses(self, position_m: float, now: float, slack_m: float) -> str | None:
        """Why a reading made by ``now`` cannot be this axis on this move (None: it can). The commanded trajectory
        goes one way from ``p0`` to ``target``, no faster than the commanded speed and acceleration allow."""
        length = abs(self.target - self.p0)
        sign = 1.0 if self.target >= self.p0 else -1.0
        s = (position_m - self.p0) * sign
        if s < -slack_m or s > length + slack_m:
            off = -s if s < 0 else s - length
            return (
                f"{off * 1e3:.3f} mm outside the commanded move from {self.p0 * 1e3:.3f} to "
                f"{self.target * 1e3:.3f} mm, more than the axis can travel on it"
            )
        if s < self.progress - slack_m:
            return (
                f"{(self.progress - s) * 1e3:.3f} mm behind a reading already accepted on the commanded move to "
                f"{self.target * 1e3:.3f} mm (which goes one way)"
            )
        dt = max(now - self.t_sent, 0.0)
        reach = _reach(self.speed * SPEED_TOLERANCE, self.accel, dt) + slack_m
        if s > reach:
            return (
                f"{s * 1e3:.3f} mm along the commanded move {dt:.3f} s after it was sent, more than the commanded "
                f"speed {self.speed:g} m/s allows ({reach * 1e3:.3f} mm)"
            )
        self.progress = max(self.progress, s)
        return None


def _log_unretrieved(task: asyncio.Future[Any]) -> None:
    """A stop whose caller was cancelled: log its outcome."""
    if not task.cancelled() and (exc := task.exception()) is not None:
        log.error("stop: %s", exc)


__all__ = ["AxisController", "alarm_message", "check_targets"]
