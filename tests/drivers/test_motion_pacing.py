"""A move's polls at the pace the Modbus link's guards sustain, one of them at the move's expected end, and a pose's
first reading before its grab the one that found the axes in position: polled as fast as asked, a move's last polls
took every read window of the duplicate-window guard and the readings after the move waited for one to free (the
acquisition's time per pose beyond the motion went from 16 to 30 ms with the guards: docs/benchmarks.md)."""

from __future__ import annotations

import numpy as np
import pytest
from test_acquisition import close, make_acq, small_plan

from calib.formats.plan import Plan
from drivers.devices.axes import next_poll
from drivers.devices.links import SafetySettings
from drivers.devices.modbus import ModbusLink, ModbusLinkSettings
from drivers.devices.registermap import AxisAddress, RegisterMap


def test_no_pace_polls_every_poll_s():
    assert next_poll(10.0, 0.002, 0.0, 10.5) == pytest.approx(10.002)


def test_the_polls_keep_the_pace_and_one_falls_on_the_expected_arrival():
    pace, arrival = 0.02, 0.105
    polls = [0.0]
    while polls[-1] < 0.2:
        polls.append(next_poll(polls[-1], 0.002, pace, arrival))
    gaps = np.diff(polls)
    assert np.all(gaps >= pace - 1e-12) and np.all(gaps < 2 * pace)  # never faster than the link sustains
    assert min(abs(t - arrival) for t in polls) < 1e-12  # a poll when the move should end
    after = [t for t in polls if t > arrival]
    assert np.allclose(np.diff([arrival, *after]), pace)  # then at the pace


def test_poll_s_slower_than_the_pace_is_kept():
    assert next_poll(0.0, 0.05, 0.02, 1.0) >= 0.05


@pytest.mark.parametrize(
    ("axes", "vary", "expected_s"),
    [
        (None, True, 0.06 / (6 - 3)),  # one axis per unit, six windows: three left for the readings after a move
        ([AxisAddress(unit=1, offset=10 * i) for i in range(4)], True, 0.06 * 4 / 6),  # four axes share six
        (None, False, 0.06),  # one window per unit
    ],
)
def test_the_links_pace_follows_its_read_windows(axes, vary, expected_s):
    regmap = RegisterMap() if axes is None else RegisterMap(axes=axes)
    link = ModbusLink(ModbusLinkSettings(regmap=regmap, vary_reads=vary), SafetySettings(duplicate_window_s=0.06))
    assert link.poll_interval_s == pytest.approx(expected_s)


def _recorder(acq):
    """Log the acquisition's calls of its actuators and camera, in order."""
    calls: list[str] = []
    act = acq.actuators
    move, status, read_encoders, grab = act.move, act.status, act.read_encoders, acq._grab

    async def logged_move(*a, **k):
        r = await move(*a, **k)
        calls.append("move")
        return r

    async def logged_status():
        calls.append("status")
        return await status()

    async def logged_read():
        calls.append("read_encoders")
        return await read_encoders()

    async def logged_grab():
        calls.append("grab")
        return await grab()

    act.move, act.status, act.read_encoders, acq._grab = logged_move, logged_status, logged_read, logged_grab
    return calls


def _poses() -> Plan:
    return Plan(name="poses", steps=[s for s in small_plan().steps if s.line is None][:3])


async def _calls_of_a_run(bench, out, **kw) -> str:
    """Run three poses; the acquisition's moves, readings and grabs, in order (comma-separated)."""
    acq = make_acq(bench, _poses(), out, **kw)
    calls = _recorder(acq)
    try:
        res = await acq.run()
    finally:
        await close(acq)
    assert res.frames == 3
    return ",".join(c for c in calls if c in ("move", "status", "grab", "read_encoders"))


async def test_the_first_reading_of_a_frame_is_the_moves_arrival(bench, tmp_path):
    seq = await _calls_of_a_run(bench, tmp_path / "ds")
    assert seq.count("move,grab,read_encoders") == 3, seq  # no reading between the move and the grab
    from calib.formats.dataset import Dataset

    for f in Dataset.open(tmp_path / "ds").frames:  # the q written is the true one
        assert np.max(np.abs(np.asarray(f.q) - np.asarray(f.model_extra["truth"]["q"]))) <= 3e-6


async def test_after_a_settling_wait_the_frame_reads_again(bench, tmp_path):
    seq = await _calls_of_a_run(bench, tmp_path / "ds", settle_s=0.01)
    assert seq.count("move,status,grab,read_encoders") == 3, seq
