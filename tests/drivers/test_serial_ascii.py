"""The serial ASCII driver against the simulated controller's ASCII front end (pyserial socket:// URL)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from drivers.acquisition.config import BenchConfig, open_actuators
from drivers.errors import AlarmError, DeviceTimeoutError, LimitError
from drivers.sim.controller import AsciiServer
from drivers.sim.mechanism import ALARM_DRIVE_FAULT


@pytest.fixture
async def ascii_act(bench):
    srv = AsciiServer(bench.mechanism)
    host, port = await srv.start()
    cfg = BenchConfig.model_validate(
        {
            "actuators": {
                "uri": f"serial+tcp://{host}:{port}?timeout=0.2",
                "speed_m_s": 10.0,
                "accel_m_s2": 1000.0,
                "retries": 2,
                "poll_s": 0.001,
            },
            "camera": {"uri": bench.camera_uri},
        }
    )
    act = open_actuators(cfg)
    await act.connect()
    try:
        yield act, srv
    finally:
        await act.close()
        await srv.close()


async def test_ascii_home_move(bench, ascii_act):
    act, _ = ascii_act
    await act.home(timeout_s=5)
    q = np.array([0.40, 0.41, 0.42, 0.43])
    assert np.allclose(await act.move(q), q, atol=3e-6)
    assert np.allclose(bench.mechanism.q_true(), q)
    with pytest.raises(LimitError):
        await act.move([0.4, 0.4, 0.4, 2.0])


async def test_ascii_faults(bench, ascii_act):
    act, srv = ascii_act
    await act.home(timeout_s=5)
    srv.drop_replies = 1  # a lost reply: retried; the late one never answers another request
    assert np.all(np.isfinite(await act.read_encoders()))
    srv.garble_replies = 2  # line noise before the reply
    assert np.all(np.isfinite(await act.read_encoders()))
    assert act.stats["stale"] + act.stats["framing"] >= 1
    srv.drop_replies = 10
    with pytest.raises(DeviceTimeoutError, match="no reply"):
        await act.read_encoders()
    srv.drop_replies = 0
    bench.mechanism.inject_alarm(0, ALARM_DRIVE_FAULT, 0.3)
    with pytest.raises(AlarmError, match="axis 1 in alarm, code 0x10"):
        await act.move([0.2, 0.2, 0.2, 0.2])
    q1 = bench.mechanism.q_true()
    await asyncio.sleep(0.03)
    assert np.array_equal(q1, bench.mechanism.q_true())


async def test_ascii_move_whose_reply_is_lost_is_not_sent_again(bench, ascii_act):
    """The MOVE executed but its reply was lost: STAT? proves it was taken; the MOVE is never sent twice."""
    act, srv = ascii_act
    await act.home(timeout_s=5)
    before = srv.executed["MOVE"]
    srv.drop_replies = 1
    q = np.array([0.30, 0.31, 0.32, 0.33])
    assert np.allclose(await act.move(q), q, atol=3e-6)
    assert srv.executed["MOVE"] - before == 1


async def test_ascii_move_lost_on_the_way_is_sent_again_once_proven_not_taken(bench, ascii_act):
    """The MOVE line never reached the controller: every axis idle away from its target, so it is sent again once."""
    act, srv = ascii_act
    await act.home(timeout_s=5)
    before = srv.executed["MOVE"]
    srv.drop_requests = 1
    q = np.array([0.35, 0.36, 0.37, 0.38])
    assert np.allclose(await act.move(q), q, atol=3e-6)
    assert srv.executed["MOVE"] - before == 1
    assert np.allclose(bench.mechanism.q_true(), q)


async def test_ascii_move_whose_fate_cannot_be_read_is_not_sent_again(bench, ascii_act):
    """No reply to the MOVE nor to the STAT? that follows: the move fails saying it may still execute (and, the
    controller silent, that the stop could not be confirmed either); the MOVE is not sent again."""
    from drivers.devices.links import MotionNotConfirmedError
    from drivers.errors import StopNotConfirmedError

    act, srv = ascii_act
    await act.home(timeout_s=5)
    before = srv.executed["MOVE"]
    srv.mute_after = "MOVE"
    with pytest.raises((MotionNotConfirmedError, StopNotConfirmedError), match="may still execute"):
        await act.move([0.25, 0.26, 0.27, 0.28])
    srv.mute_after, srv.drop_replies = None, 0
    assert srv.executed["MOVE"] - before == 1
