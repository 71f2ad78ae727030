"""Motion safety of the Modbus driver and the simulated controller: limits, stops, cancellation.

Real parts: the simulated controller is a pymodbus server on loopback; the wire is checked byte for byte
with a raw socket where a third-party client's strictness matters (the FC6 echo).
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time

import numpy as np
import pytest
from drv_helpers import FAST, TinyRenderer, make_modbus
from pymodbus.client import AsyncModbusTcpClient

from drivers.acquisition.acquire import AcquisitionError
from drivers.devices.registermap import ALARM_TEXT, ALARM_WATCHDOG, RegisterMap
from drivers.errors import ProtocolError, StopNotConfirmedError
from drivers.sim.bench import SimBench

Q_A = np.array([0.40, 0.41, 0.42, 0.43])
Q_FAR = np.array([0.60, 0.61, 0.62, 0.63])


def raw_transaction(address: tuple[str, int], pdu: bytes, unit: int, tid: int = 7) -> bytes:
    """One Modbus TCP request on a raw socket; returns the whole reply frame (MBAP + PDU)."""
    frame = struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu
    with socket.create_connection(address, timeout=2) as s:
        s.sendall(frame)
        head = b""
        while len(head) < 6:
            head += s.recv(6 - len(head))
        n = struct.unpack(">H", head[4:6])[0]
        body = b""
        while len(body) < n:
            body += s.recv(n - len(body))
    return head + body


# -- finding 8: the simulator as strict as a real drive ----------------------------------------------------
async def test_fc6_write_is_echoed_exactly(bench):
    """A write of one register is answered with the request itself (pyModbusTCP and minimalmodbus check it).
    Register 4 is the self-clearing control register: pymodbus read it back (0) into the reply."""
    request = struct.pack(">BHH", 6, 4, 4)  # FC6, register 4 (control), value 4 (home)
    frame = struct.pack(">HHHB", 7, 0, len(request) + 1, 1) + request
    reply = await asyncio.to_thread(raw_transaction, bench.tcp_address, request, 1)
    assert reply == frame
    await asyncio.sleep(0.1)
    bench.mechanism.update()
    assert bench.mechanism.axes[0].homed  # and the write did its job


@pytest.mark.parametrize("unit", [0, 5, 7, 247])
async def test_unknown_unit_is_exception_0x0B_without_traceback(bench, unit, capsys, caplog):
    for framer, port in (("socket", bench.tcp_address[1]), ("rtu", int(bench.rtu_url.rsplit(":", 1)[1]))):
        c = AsyncModbusTcpClient("127.0.0.1", port=port, framer=framer, timeout=1, retries=0)
        await c.connect()
        try:
            rr = await c.read_holding_registers(5, count=4, device_id=unit)
            assert rr.isError() and rr.exception_code == 0x0B, (framer, rr)
            rr = await c.write_register(4, 1, device_id=unit)
            assert rr.isError() and rr.exception_code == 0x0B, (framer, rr)
            rr = await c.read_holding_registers(5, count=4, device_id=1)  # the real units still answer
            assert not rr.isError() and len(rr.registers) == 4
        finally:
            c.close()
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err + caplog.text


async def test_watchdog_stop_sets_an_alarm(bench):
    """A one-shot client starts a long move and goes silent: the watchdog stops it AND says so (alarm bit,
    code 0x50), rather than reading in position, no alarm, at a position that is not the target."""
    act = make_modbus(bench)
    async with act:
        await act.home(timeout_s=5)
    m = RegisterMap()
    c = AsyncModbusTcpClient(*bench.tcp_address[:1], port=bench.tcp_address[1], timeout=1)
    await c.connect()
    regs = m.to_regs32(700000) + m.to_regs32(100000)  # 0.7 m at 0.1 m/s: 7 s
    assert not (await c.write_registers(0, [*regs, 1], device_id=1)).isError()
    c.close()  # the one-shot client is gone
    await asyncio.sleep(bench.controller.watchdog_s + 0.2)
    c = AsyncModbusTcpClient(*bench.tcp_address[:1], port=bench.tcp_address[1], timeout=1)
    await c.connect()
    st, _, _, code = (await c.read_holding_registers(5, count=4, device_id=1)).registers
    c.close()
    b = m.status_bits
    assert not st >> b.moving & 1 and st >> b.alarm & 1 and not st >> b.in_position & 1
    assert code == ALARM_WATCHDOG and "watchdog" in ALARM_TEXT[code]
    assert bench.mechanism.axes[0].pos < 0.2
    async with act:  # the driver names it and an alarm reset clears it
        with pytest.raises(Exception, match="0x50 \\(communication watchdog"):
            await act.move(Q_A)
        await act.reset_alarms()
        assert np.allclose(await act.move(Q_A), Q_A, atol=3e-6)


async def test_watchdog_off():
    async with SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), rtu=False, watchdog_s=0) as b:
        act = make_modbus(b)
        async with act:
            await act.home(timeout_s=5)
            regs = act.map.to_regs32(700000) + act.map.to_regs32(100000)
            await act.write(1, 0, [*regs, 1])
        await asyncio.sleep(0.7)
        assert b.mechanism.axes[0].moving and not b.mechanism.axes[0].alarm_code
    with pytest.raises(ValueError, match="watchdog_s"):
        SimBench(port=0, renderer=TinyRenderer(), watchdog_s=-1)


def test_sim_bench_cli_has_the_watchdog_flag():
    import argparse

    from service.cli import sim_bench

    p = argparse.ArgumentParser()
    sim_bench.register(p.add_subparsers())
    assert p.parse_args(["sim-bench", "--watchdog-s", "0"]).watchdog_s == 0.0
    assert p.parse_args(["sim-bench"]).watchdog_s == 0.5


# -- finding 9: a decoded position must be plausible -------------------------------------------------------
async def test_wrong_word_order_never_moves(bench):
    """Low word first on a drive that sends the high word first: positions decode to thousands of metres.
    The driver refuses them by name and never writes a target."""
    act = make_modbus(bench, regmap=RegisterMap(word_order="little"))
    with pytest.raises(ProtocolError, match=r"axis 1: implausible position -?\d+(\.\d+)? m .*outside the soft limits"):
        await act.connect()
    with pytest.raises(ProtocolError, match="implausible position"):
        await act.move(Q_A)
    await act.close()
    assert bench.controller.writes == 0
    assert not any(a.moving for a in bench.mechanism.axes)


async def test_a_jump_faster_than_the_axis_is_refused(bench):
    act = make_modbus(bench, max_speed_m_s=1.0)
    async with act:
        await act.home(timeout_s=5)
        await act.move(Q_A, speed_m_s=0.5)
        writes = bench.controller.writes
        bench.mechanism.axes[2].pos += 0.05  # 50 mm between two readings a few ms apart: not a real motion
        with pytest.raises(ProtocolError, match="axis 3: implausible position 470.000 mm .* more than the axis"):
            await act.move(Q_A + 0.01)
        assert bench.controller.writes == writes  # no target sent
        # a reading that the axis could have reached is accepted again afterwards
        assert np.allclose(await act.read_encoders(), bench.mechanism.q_true(), atol=3e-6)


# -- finding 5: a stop confirmed by read-back, within one deadline ----------------------------------------------
async def test_stop_is_confirmed_by_read_back(bench):
    act = make_modbus(bench, speed_m_s=0.2)
    async with act:
        await act.home(timeout_s=5)
        task = asyncio.create_task(act.move(Q_FAR, timeout_s=1.5))
        await asyncio.sleep(0.1)
        assert bench.mechanism.axes[0].moving
        r0 = act.stats["requests"]
        await act.stop()  # from another task, while the move polls
        assert not any(a.moving for a in bench.mechanism.axes)  # when stop returns, every axis has stopped
        assert act.stats["requests"] - r0 >= 8  # four stop writes and four read-backs at least
        with pytest.raises(Exception):  # noqa: B017 - the move ends one way or another, never at its target
            await asyncio.wait_for(task, 5)
        assert np.all(np.abs(bench.mechanism.q_true() - Q_FAR) > 1e-3)


async def test_stop_refused_by_the_drive_is_not_confirmed(bench):
    act = make_modbus(bench, speed_m_s=0.2, stop_deadline_s=0.6)
    async with act:
        await act.home(timeout_s=5)
        bench.controller.faults.exception_code, bench.controller.faults.exception_count = 4, 10**6
        t0 = time.monotonic()
        with pytest.raises(StopNotConfirmedError, match="motion may NOT have stopped; use the emergency stop") as ei:
            await act.stop()
        assert 0.6 <= time.monotonic() - t0 < 1.6  # one deadline (+ scheduling on a loaded machine)
        assert ei.value.axes == (1, 2, 3, 4)


async def test_stop_when_the_bench_dies_fails_fast_and_says_so():
    b = SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), rtu=False)
    await b.start()
    act = make_modbus(b, speed_m_s=0.2, timeout_s=0.5, retries=3)
    try:
        await act.connect()
        await act.home(timeout_s=5)
        await act.write(1, 0, [*act.map.to_regs32(700000), *act.map.to_regs32(100000), 1])
    finally:
        await b.stop()  # the controller is gone mid-move
    t0 = time.monotonic()
    with pytest.raises(StopNotConfirmedError, match="may NOT have stopped"):
        await act.stop()
    elapsed = time.monotonic() - t0
    print(f"stop with the bench gone: StopNotConfirmedError after {elapsed:.2f} s (deadline {act.stop_deadline_s} s)")
    assert act.stop_deadline_s <= elapsed < act.stop_deadline_s + 1.0  # was 19.4 s (4 axes x 4 attempts, twice)
    await act.close()


async def test_acquisition_says_motion_may_not_have_stopped(tmp_path):
    from test_acquisition import close, make_acq, small_plan

    b = SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), seed=1, rtu=False)
    await b.start()
    acq = make_acq(b, small_plan(), tmp_path / "ds")
    seen = {"n": 0, "t_kill": 0.0}
    orig_move = acq.actuators.move

    async def move(q, *a, **k):
        seen["n"] += 1
        if seen["n"] == 4:
            await b.stop()  # the bench dies (power, cable, process) just before the 4th move
            seen["t_kill"] = time.monotonic()
        return await orig_move(q, *a, **k)

    acq.actuators.move = move
    try:
        with pytest.raises(AcquisitionError) as ei:
            await acq.run()
    finally:
        await close(acq)
    elapsed = time.monotonic() - seen["t_kill"]
    msg = str(ei.value)
    print(f"acquisition with the bench gone failed after {elapsed:.2f} s: {msg[:160]}")
    assert "motion may NOT have stopped" in msg and "emergency stop" in msg
    assert "motion stopped;" not in msg
    assert elapsed < acq.actuators.stop_deadline_s + 3.0


# -- cancellation: Python 3.11's wait_for must not swallow a cancel that lands with a reply --------------------------
@pytest.mark.parametrize("k", [5, 6, 7, 9, 12])
async def test_cancel_landing_with_a_reply_still_stops(bench, k):
    """The cancel is delivered from inside the client's receive path, right before the k-th reply after the
    move starts completes its request's future: exactly the race of CPython gh-86296."""
    act = make_modbus(bench, speed_m_s=0.3)
    async with act:
        await act.home(timeout_s=5)
        task = None
        count = {"n": 0}
        ctx = act._client.ctx
        orig = ctx.trace_pdu

        def trace_pdu(sending, pdu):
            out = orig(sending, pdu)
            if not sending and task is not None:
                count["n"] += 1
                if count["n"] == k:
                    task.cancel()
            return out

        ctx.trace_pdu = trace_pdu
        task = asyncio.create_task(act.move(Q_FAR))
        with pytest.raises(asyncio.CancelledError):
            await asyncio.wait_for(asyncio.shield(task), 5)
        assert count["n"] >= k
        await asyncio.sleep(0.05)
        q1 = bench.mechanism.q_true()
        await asyncio.sleep(0.05)
        assert np.array_equal(bench.mechanism.q_true(), q1)  # stopped
        assert np.all(np.abs(q1 - Q_FAR) > 0.05)  # far from the target


async def test_a_run_clears_the_watchdog_alarm_of_a_lost_session(bench, tmp_path):
    """A previous host died mid-move; the drives' watchdog stopped them in alarm 0x50. Starting (or resuming) a
    run is the explicit request to go on: it resets that alarm, and only that one."""
    from test_acquisition import close, make_acq, small_plan

    from drivers.sim.mechanism import ALARM_DRIVE_FAULT

    for ax in bench.mechanism.axes[:2]:
        ax.alarm_code = ALARM_WATCHDOG
    messages = []
    acq = make_acq(bench, small_plan(), tmp_path / "ds", progress=lambda p: messages.append(p.message))
    try:
        res = await acq.run()
    finally:
        await close(acq)
    assert res.frames == res.total
    assert any("communication-watchdog alarm" in m for m in messages)
    bench.mechanism.axes[0].alarm_code = ALARM_DRIVE_FAULT  # any other alarm still stops the run before it moves
    acq = make_acq(bench, small_plan(), tmp_path / "ds2")
    try:
        with pytest.raises(Exception, match="in alarm before the run"):
            await acq.run()
    finally:
        await close(acq)
