"""The Modbus driver against the simulated controller over real loopback sockets (TCP, RTU framing)."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from drv_helpers import FAST, TinyRenderer, make_modbus

from calib.model.parameters import NOMINAL
from drivers.devices.axes import AxisSettings
from drivers.devices.modbus import ModbusActuators, ModbusLinkSettings
from drivers.devices.registermap import AxisAddress, RegisterMap
from drivers.errors import AlarmError, DeviceConnectionError, DeviceTimeoutError, LimitError, ProtocolError
from drivers.sim.bench import SimBench
from drivers.sim.faultproxy import FaultProxy
from drivers.sim.mechanism import ALARM_DRIVE_FAULT

Q_A = np.array([0.40, 0.41, 0.42, 0.43])
Q_B = np.array([0.30, 0.31, 0.35, 0.36])


@pytest.mark.parametrize("transport", ["tcp", "rtu-tcp"])
async def test_home_move_read(bench, transport):
    act = make_modbus(bench, transport)
    async with act:
        assert not (await act.status()).homed
        await act.home(timeout_s=5)
        st = await act.status()
        assert st.homed and st.in_position and not st.alarms
        enc = await act.move(Q_A)
        assert np.allclose(enc, Q_A, atol=3e-6)
        assert np.allclose(bench.mechanism.q_true(), Q_A, atol=1e-9)
        enc = await act.move(Q_B)
        assert np.allclose(await act.read_encoders(), Q_B, atol=3e-6)


async def test_limits_refused_before_anything_moves(bench):
    act = make_modbus(bench, nominal=NOMINAL)
    async with act:
        await act.home(timeout_s=5)
        await act.move(Q_A)
        before = bench.controller.requests
        q_before = bench.mechanism.q_true()
        with pytest.raises(LimitError, match="q2 = 900.000 mm is outside the soft limits"):
            await act.move([0.4, 0.9, 0.4, 0.4])
        # reachable per axis, but the kinematic model cannot close the legs
        with pytest.raises(LimitError, match="workspace"):
            await act.move([0.0, 0.78, 0.0, 0.78])
        assert bench.controller.requests == before  # not a single request went out
        assert np.array_equal(bench.mechanism.q_true(), q_before)


async def test_exception_codes(bench):
    act = make_modbus(bench)
    async with act:
        bench.controller.faults.exception_code = 4
        bench.controller.faults.exception_count = 1
        with pytest.raises(ProtocolError, match="exception code 4 \\(device failure\\)") as ei:
            await act.read_encoders()
        assert ei.value.exception_code == 4
        # device busy is retried
        bench.controller.faults.exception_code = 6
        bench.controller.faults.exception_count = 2
        assert np.all(np.isfinite(await act.read_encoders()))
        assert act.stats["retries"] >= 2


async def test_dropped_reply_is_retried_on_a_fresh_link(bench):
    act = make_modbus(bench, timeout_s=0.1)
    async with act:
        r0 = act.stats["reconnects"]
        bench.controller.faults.drop_replies = 1
        q = await act.read_encoders()
        assert np.all(np.isfinite(q))
        assert act.stats["reconnects"] > r0
        bench.controller.faults.drop_replies = 10
        with pytest.raises(DeviceTimeoutError, match="no reply within"):
            await act.read_encoders()
        bench.controller.faults.drop_replies = 0
        await act.read_encoders()


async def test_late_reply_never_answers_another_request(bench):
    proxy = FaultProxy(bench.tcp_address)
    host, port = await proxy.start()
    try:
        act = ModbusActuators(
            ModbusLinkSettings(host=host, port=port, timeout_s=0.1, retries=2, backoff_s=0.01),
            AxisSettings(poll_s=0.001, speed_m_s=2.0, accel_m_s2=40.0),
        )
        async with act:
            await act.home(timeout_s=5)
            await act.move(Q_A)
            # the next reply (axis 1's status/encoder) comes 0.25 s late: after the timeout
            proxy.faults.delay_s, proxy.faults.delay_count = (0.25, 0.25), 1
            unit, addr = act.map.addr(1, "target")
            t0 = time.monotonic()
            regs = await act.read(unit, addr, 2)  # axis 2 target: must be axis 2's answer
            assert act.map.counts_to_m(act.map.from_regs32(regs)) == pytest.approx(Q_A[1])
            assert time.monotonic() - t0 >= 0.1
            await asyncio.sleep(0.3)  # the late reply has arrived (on the dropped link) by now
            for ax in range(4):
                s = await act.read_axis(ax)
                assert s.position_m == pytest.approx(Q_A[ax], abs=3e-6)
    finally:
        await proxy.close()


async def test_cut_connection_reconnects(bench):
    act = make_modbus(bench)
    async with act:
        await act.read_encoders()
        assert bench.controller.cut_connections() >= 1
        await asyncio.sleep(0.01)
        assert np.all(np.isfinite(await act.read_encoders()))


async def test_server_gone_is_a_connection_error():
    b = SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), rtu=False)
    await b.start()
    act = make_modbus(b, retries=1)
    await act.connect()
    await b.stop()
    await asyncio.sleep(0.05)
    with pytest.raises(DeviceConnectionError):
        await act.read_encoders()
    with pytest.raises(DeviceConnectionError, match="cannot connect"):
        await make_modbus(b, retries=1).connect()
    await act.close()


async def test_alarm_mid_move_stops_every_axis(bench):
    act = make_modbus(bench, speed_m_s=0.5)
    async with act:
        await act.home(timeout_s=5)
        bench.mechanism.inject_alarm(2, ALARM_DRIVE_FAULT, at_fraction=0.4)
        with pytest.raises(AlarmError, match="axis 3 in alarm, code 0x10") as ei:
            await act.move(Q_A)
        assert ei.value.code == ALARM_DRIVE_FAULT and ei.value.axis == 3
        q1 = bench.mechanism.q_true()
        await asyncio.sleep(0.05)
        assert np.array_equal(bench.mechanism.q_true(), q1)  # stopped
        assert not any(a.moving for a in bench.mechanism.axes)
        assert np.all(np.abs(q1 - Q_A) > 1e-4)
        # a controller in alarm refuses the next move with the code; reset clears it
        with pytest.raises(AlarmError, match="0x10"):
            await act.move(Q_B)
        await act.reset_alarms()
        assert np.allclose(await act.move(Q_B), Q_B, atol=3e-6)


async def test_move_timeout_stops(bench):
    act = make_modbus(bench, speed_m_s=0.2)
    async with act:
        await act.home(timeout_s=5)
        with pytest.raises(DeviceTimeoutError, match="did not complete within 0.05 s"):
            await act.move(Q_A, timeout_s=0.05)
        q1 = bench.mechanism.q_true()
        await asyncio.sleep(0.05)
        assert np.array_equal(bench.mechanism.q_true(), q1)
        assert act.move_timeout(np.array([0.1, 0, 0, 0]), np.array([0.05, 1, 1, 1])) > 2.0


async def test_cancelled_move_stops(bench):
    act = make_modbus(bench, speed_m_s=0.3)
    async with act:
        await act.home(timeout_s=5)
        task = asyncio.create_task(act.move(Q_A))
        await asyncio.sleep(0.1)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        q1 = bench.mechanism.q_true()
        await asyncio.sleep(0.05)
        assert np.array_equal(bench.mechanism.q_true(), q1)


async def test_controller_refuses_moves_when_not_homed(bench):
    act = make_modbus(bench)
    async with act:
        with pytest.raises(AlarmError, match="not homed"):
            await act.move(Q_A)


async def test_free_drives_still_read_encoders(bench):
    act = make_modbus(bench)
    async with act:
        await act.home(timeout_s=5)
        await act.set_free(True)
        st = await act.status()
        assert all(a.free for a in st.axes) and not any(a.ready for a in st.axes)
        bench.mechanism.axes[0].pos = 0.123  # someone pushes the free axis (0.18 m in 50 ms: 3.6 m/s, plausible)
        await asyncio.sleep(0.05)
        assert (await act.read_encoders())[0] == pytest.approx(0.123, abs=3e-6)
        with pytest.raises(Exception, match="free"):
            await act.move(Q_A)
        await act.set_free(False)
        assert np.allclose(await act.move(Q_A), Q_A, atol=3e-6)


async def test_other_register_map():
    """All axes on one unit id at offsets 0/10/20/30, low word first, 0.1 um counts, start by writing the target."""
    m = RegisterMap(
        axes=[AxisAddress(unit=7, offset=10 * i) for i in range(4)],
        word_order="little",
        counts_per_m=1e7,
        start_mode="target_write",
    )
    async with SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), regmap=m, rtu=False) as b:
        host, port = b.tcp_address
        act = ModbusActuators(
            ModbusLinkSettings(host=host, port=port, regmap=m, timeout_s=0.2),
            AxisSettings(speed_m_s=2.0, accel_m_s2=40.0, poll_s=0.001, in_position_m=1e-6),
        )
        async with act:
            await act.home(timeout_s=5)
            q = np.array([-0.05, 0.41, 0.42, 0.43])
            assert np.allclose(await act.move(q), q, atol=3e-7)
            assert np.allclose(b.mechanism.q_true(), q)
            regs = await act.read(7, 10 + m.actual, 2)
            assert regs == m.to_regs32(round(q[1] * 1e7)) or abs(m.from_regs32(regs) - q[1] * 1e7) <= 15


def test_register_words():
    m = RegisterMap()
    assert m.to_regs32(-2) == [0xFFFF, 0xFFFE]
    assert m.from_regs32([0xFFFF, 0xFFFE]) == -2
    assert m.from_regs32(m.to_regs32(123456789)) == 123456789
    lm = RegisterMap(word_order="little")
    assert lm.to_regs32(0x12345678) == [0x5678, 0x1234]


async def test_watchdog_stops_a_move_when_the_master_goes_silent(bench):
    act = make_modbus(bench)
    async with act:
        await act.home(timeout_s=5)
        regs = act.map.to_regs32(700000) + act.map.to_regs32(100000)  # 0.7 m at 0.1 m/s: 7 s
        await act.write(1, 0, [*regs, 1])
        await act.close()  # the master dies mid-move
        await asyncio.sleep(bench.controller.watchdog_s + 0.2)
        assert not bench.mechanism.axes[0].moving
        assert bench.mechanism.axes[0].pos < 0.2
