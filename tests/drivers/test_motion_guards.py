"""The driver's guards on the way to a frame: the drives' watchdog survives a timeout, a device that comes back
after a failure is stopped before anything else, readings are checked against the commanded move, and every
frame's q is cross-checked before it is written.

Real parts: the simulated controller (a pymodbus server on loopback, its communication watchdog on); where a
reading has to be wrong on purpose (a stale one that got past the link's guards: a gateway that forwards
another master's identical reply, which no master can tell apart), the test replaces the value the driver
returns, and says so.
"""

from __future__ import annotations

import asyncio
import dataclasses

import numpy as np
import pytest
from drv_helpers import make_modbus
from test_acquisition import close, make_acq, small_plan

from calib.formats.plan import Plan
from drivers.acquisition.acquire import AcquisitionError
from drivers.devices.interfaces import ActuatorStatus
from drivers.devices.registermap import ALARM_WATCHDOG
from drivers.errors import ProtocolError

Q_A = np.array([0.40, 0.41, 0.42, 0.43])
Q_FAR = np.array([0.70, 0.71, 0.72, 0.73])


@pytest.mark.parametrize("transport", ["rtu-tcp", "tcp"])
async def test_one_timeout_mid_move_does_not_trip_the_drives_watchdog(bench, transport):
    """Default settings (reply timeout 0.5 s, the late-reply guard's default), the drives' watchdog 0.5 s: one
    reply lost mid-move. The old driver kept an RTU link closed for the guard (1 s) after the timeout, the watchdog
    stopped the move in alarm 0x50 and the move failed. Now the guard never silences the link (it only keeps the
    lost reply's shape out of use) and the reply timeout is capped below the watchdog (0.38 s): the move ends."""
    assert bench.controller.watchdog_s == 0.5
    act = make_modbus(bench, transport, timeout_s=0.5, retries=3, backoff_s=0.02, speed_m_s=0.25)
    async with act:
        await act.home(timeout_s=5)
        move = asyncio.create_task(act.move(Q_FAR))  # about 1.2 s
        await asyncio.sleep(0.3)
        assert any(ax.moving for ax in bench.mechanism.axes)
        bench.controller.faults.drop_replies = 1
        q = await move
        assert act.stats["timeouts"] == 1, dict(act.stats)
        assert np.allclose(q, Q_FAR, atol=3e-6)
        assert not any(ax.alarm_code == ALARM_WATCHDOG for ax in bench.mechanism.axes)


async def test_a_device_that_comes_back_is_stopped_before_anything_is_reported(bench):
    """A stop that could not be confirmed (the controller stopped answering mid-move) leaves a motion nobody
    stopped. When the controller answers again, the driver's next status sends stop to every axis and confirms
    them still before it reports a position: here the axes were still moving when it came back."""
    act = make_modbus(bench, speed_m_s=0.1, stop_deadline_s=0.3, timeout_s=0.05, retries=1)
    async with act:
        await act.home(timeout_s=5)
        move = asyncio.create_task(act.move(Q_FAR))
        await asyncio.sleep(0.2)
        bench.controller.faults.drop_replies = 10**6  # silent: requests arrive, no reply leaves
        with pytest.raises(Exception, match="motion may NOT have stopped"):
            await move
        bench.controller.faults.drop_replies = 0
        # the stops did reach the controller (only replies were dropped): make the axes move again, as a
        # command buffered somewhere and executed late would
        for i, ax in enumerate(bench.mechanism.axes):
            ax.start(Q_FAR[i], 0.1, bench.mechanism.clock())
        st = await act.status()
        assert not any(s.moving for s in st.axes)
        assert not any(ax.moving for ax in bench.mechanism.axes)
        assert not act.motion_in_doubt


async def test_a_reading_behind_the_commanded_move_is_refused(bench):
    """On a commanded move the axis goes one way: a reading behind one already accepted on this move is an older
    position (a stale reply), refused by name; the old check (5 x speed x dt) accepted it."""
    act = make_modbus(bench, speed_m_s=0.2)
    async with act:
        await act.home(timeout_s=5)
        await act.move(Q_A)
        move = asyncio.create_task(act.move(Q_FAR))
        await asyncio.sleep(0.25)
        move.cancel()  # stopped part-way (its own stop on cancellation); the commanded move is still the reference
        with pytest.raises(asyncio.CancelledError):
            await move
        q_now = await act.read_encoders()
        assert np.all(q_now > Q_A + 0.02) and np.all(q_now < Q_FAR - 0.02)
        await asyncio.sleep(0.02)  # 5 x speed x dt now allows 21 mm
        with pytest.raises(ProtocolError, match="axis 1: implausible position .* behind a reading already accepted"):
            act.check_reading(0, float(q_now[0] - 0.003), 0.0)  # 3 mm back: where the axis was 15 ms before
        assert not any(ax.moving for ax in bench.mechanism.axes)


def frames_plan() -> Plan:
    p = small_plan()
    return Plan(name="frames", steps=[s for s in p.steps if s.line is None][:4])


class StaleStatus:
    """The acquisition's actuators, except that its k-th reading (and ``times - 1`` more) reads axis 2 ``offset_m``
    off: a stale reading past the link's guards, which cannot be made on the wire on purpose. The acquisition's
    readings are its ``status()`` calls and the encoders a move returns (read in position by the move's last poll:
    a pose's first reading before its grab). The driver's own calls inside a move are untouched."""

    def __init__(self, act, k: int, offset_m: float, times: int) -> None:
        self._act, self.k, self.offset_m, self.times = act, k, offset_m, times
        self.n = self.faked = 0

    def __getattr__(self, name: str):
        return getattr(self._act, name)

    def _stale(self) -> bool:
        self.n += 1
        if self.k <= self.n < self.k + self.times:
            self.faked += 1
            return True
        return False

    async def status(self) -> ActuatorStatus:
        st = await self._act.status()
        if self._stale():
            axes = list(st.axes)
            axes[1] = dataclasses.replace(axes[1], position_m=axes[1].position_m + self.offset_m)
            return ActuatorStatus(tuple(axes))
        return st

    async def move(self, q, *args, **kwargs) -> np.ndarray:
        positions = np.array(await self._act.move(q, *args, **kwargs), dtype=float)
        if self._stale():
            positions[1] += self.offset_m
        return positions


async def test_a_frame_whose_q_disagrees_is_read_again(bench, tmp_path):
    """One stale reading (4 mm off on axis 2) right when a pose's frame is recorded: the frame's q is cross-checked
    with the commanded target and a second reading; it is read again and the frame records the truth. The old run
    wrote the stale q."""
    acq = make_acq(bench, frames_plan(), tmp_path / "ds", home=True)
    messages: list[str] = []
    acq.progress_cb = lambda p: messages.append(p.message)
    acq.actuators = seen = StaleStatus(acq.actuators, k=3, offset_m=0.004, times=1)  # pose 2's frame
    try:
        res = await acq.run()
    finally:
        await close(acq)
    assert seen.faked == 1 and res.frames == 4
    from calib.formats.dataset import Dataset

    ds = Dataset.open(tmp_path / "ds")
    for f in ds.frames:
        truth = np.asarray(f.model_extra["truth"]["q"])
        assert np.max(np.abs(np.asarray(f.q) - truth)) <= 3e-6, (f.q, truth)
    assert any("read again" in m and "q2" in m for m in messages), messages


async def test_a_frame_whose_q_keeps_disagreeing_is_refused(bench, tmp_path):
    acq = make_acq(bench, frames_plan(), tmp_path / "ds", home=True)
    acq.actuators = StaleStatus(acq.actuators, k=3, offset_m=0.004, times=10)
    try:
        with pytest.raises(AcquisitionError, match=r"frame refused, not written: q2 read .* in 3 readings") as ei:
            await acq.run()
    finally:
        await close(acq)
    assert "motion stopped" in str(ei.value)
    from calib.formats.dataset import Dataset

    ds = Dataset.open(tmp_path / "ds")
    assert len(ds.frames) == ei.value.frames_kept == 1
    for f in ds.frames:
        assert np.max(np.abs(np.asarray(f.q) - np.asarray(f.model_extra["truth"]["q"]))) <= 3e-6


def test_bench_file_motion_safety_keys_reach_the_driver(bench):
    from drivers.acquisition.config import open_actuators

    cfg = bench.bench_config(
        actuators={
            "duplicate_window_s": 0.08,
            "motion_confirm_s": 1.5,
            "watchdog_s": 1.0,
            "stop_persist_s": 12.0,
            "max_accel_m_s2": 900.0,
        }
    )
    act = open_actuators(cfg)
    assert act.stop_persist_s == 12.0 and act.accel_limit_m_s2 == 900.0
    link = act.link
    assert link.safety.duplicate_window_s == 0.08 and link.motion_confirm_s == 1.5
    assert link.reply_timeout_s == 0.5  # bench timeout 0.5 s, under 0.8 x 1.0 s - backoff
    defaults = open_actuators(bench.bench_config())
    assert defaults.link.reply_timeout_s == pytest.approx(0.38)  # capped below the drives' 0.5 s watchdog
    assert defaults.stop_persist_s == 30.0 and defaults.link.safety.duplicate_window_s == 0.06
    with pytest.raises(Exception, match="stop_persist_s"):
        bench.bench_config(actuators={"stop_persist_s": -1})
