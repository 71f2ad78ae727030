"""The Modbus driver against the simulated controller with RTU framing over real ptys (a null-modem link).

Two pty pairs are made in the test; a relay thread copies bytes between their masters, so the two slave
paths behave like the two ends of a serial cable. The simulated controller's ``ModbusSerialServer`` opens
one slave, the driver opens the other through ``modbus+rtu:///dev/pts/N?baudrate=115200``. The relay can
hold back a reply from the controller (a late reply) without reordering the line.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import threading
import time
import tty

import numpy as np
import pytest
from drv_helpers import FAST, TinyRenderer, make_modbus

from drivers.acquisition.config import open_actuators
from drivers.devices.modbus import ModbusActuators
from drivers.errors import DeviceTimeoutError, ProtocolError
from drivers.sim.bench import SimBench

Q_A = np.array([0.40, 0.41, 0.42, 0.43])
Q_B = np.array([0.30, 0.31, 0.35, 0.36])


class PtyLink:
    """Two linked ptys: bytes written to one slave path are read from the other (a relay thread in between).

    Server -> client chunks can be delayed: the next ``hold_count`` by ``hold_s`` (a late reply; the
    server's later replies are not queued behind it, only that one is late), every other by
    ``latency_s`` (a device that takes its time to answer).
    """

    def __init__(self) -> None:
        self._masters: list[int] = []
        self._slaves: list[int] = []
        self.paths: list[str] = []
        for _ in range(2):
            m, s = os.openpty()
            tty.setraw(s)  # no echo, no line editing: a serial line, before anyone opens it
            os.set_blocking(m, False)
            self._masters.append(m)
            self._slaves.append(s)  # kept open: the master never sees EIO while an end reopens its port
            self.paths.append(os.ttyname(s))
        self.server_path, self.client_path = self.paths
        self.hold_s = 0.0
        self.hold_count = 0
        self.latency_s = 0.0
        self.bytes_relayed = 0
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="pty-relay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        m_server, m_client = self._masters
        held: list[tuple[float, bytes]] = []  # (release time, chunk) server -> client
        while not self._stop:
            now = time.monotonic()
            while held and held[0][0] <= now:
                os.write(m_client, held.pop(0)[1])
            wait = max(0.0, held[0][0] - now) if held else None
            ready, _, _ = select.select([m_server, m_client, self._wake_r], [], [], wait)
            for fd in ready:
                if fd == self._wake_r:
                    continue
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, OSError):
                    continue
                self.bytes_relayed += len(data)
                if fd == m_client:
                    os.write(m_server, data)
                elif self.hold_count > 0 or self.latency_s > 0:
                    delay = self.latency_s
                    if self.hold_count > 0:
                        self.hold_count -= 1
                        delay = self.hold_s
                    held.append((time.monotonic() + delay, data))
                    held.sort(key=lambda x: x[0])
                else:
                    os.write(m_client, data)

    def close(self) -> None:
        self._stop = True
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=2.0)
        for fd in (*self._masters, *self._slaves, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
async def rtu_bench():
    """A simulated bench whose controller serves RTU on one end of a pty link; yields (bench, client path)."""
    link = PtyLink()
    b = SimBench(port=0, axis_config=FAST, renderer=TinyRenderer(), seed=1, rtu=False)
    await b.start()
    try:
        assert await b.controller.serve_rtu(link.server_path, baudrate=115200) == link.server_path
        b.link = link  # type: ignore[attr-defined]
        yield b
    finally:
        await b.stop()
        link.close()


def rtu(bench: SimBench, **kw) -> ModbusActuators:
    return make_modbus(bench, "rtu", serial_port=bench.link.client_path, **kw)


async def test_move_and_encoders_through_the_uri(rtu_bench):
    cfg = rtu_bench.bench_config(
        actuators={
            "uri": f"modbus+rtu://{rtu_bench.link.client_path}?baudrate=115200",
            "timeout_s": 0.2,
            "speed_m_s": 2.0,
            "accel_m_s2": 40.0,
        }
    )
    act = open_actuators(cfg)
    assert isinstance(act, ModbusActuators) and act.transport == "rtu" and act.baudrate == 115200
    assert act.serial_port == rtu_bench.link.client_path
    async with act:
        assert not (await act.status()).homed
        await act.home(timeout_s=5)
        st = await act.status()
        assert st.homed and st.in_position and not st.alarms
        assert np.allclose(await act.move(Q_A), Q_A, atol=3e-6)
        assert np.allclose(rtu_bench.mechanism.q_true(), Q_A, atol=1e-9)
        await act.move(Q_B)
        assert np.allclose(await act.read_encoders(), Q_B, atol=3e-6)
        assert np.allclose(await act.read_encoders(), rtu_bench.mechanism.q_true(), atol=3e-6)
    assert rtu_bench.link.bytes_relayed > 0
    assert act.stats["retries"] == 0


async def test_exception_code_reply(rtu_bench):
    act = rtu(rtu_bench)
    async with act:
        rtu_bench.controller.faults.exception_code = 2
        rtu_bench.controller.faults.exception_count = 1
        with pytest.raises(ProtocolError, match="exception code 2 \\(illegal data address\\)") as ei:
            await act.read_encoders()
        assert ei.value.exception_code == 2
        rtu_bench.controller.faults.exception_code = 6  # device busy: retried
        rtu_bench.controller.faults.exception_count = 2
        assert np.all(np.isfinite(await act.read_encoders()))
        assert act.stats["retries"] >= 2


async def test_dropped_reply_times_out_then_retries(rtu_bench):
    act = rtu(rtu_bench, timeout_s=0.1, late_reply_guard_s=0.05)
    async with act:
        r0, t0 = act.stats["retries"], act.stats["reconnects"]
        rtu_bench.controller.faults.drop_replies = 1
        assert np.allclose(await act.read_encoders(), rtu_bench.mechanism.q_true(), atol=3e-6)
        assert act.stats["retries"] == r0 + 1 and act.stats["reconnects"] > t0
        rtu_bench.controller.faults.drop_replies = 10
        with pytest.raises(DeviceTimeoutError, match="no reply within 0.100 s"):
            await act.read_encoders()
        rtu_bench.controller.faults.drop_replies = 0
        assert np.all(np.isfinite(await act.read_encoders()))


async def test_late_reply_never_answers_another_request(rtu_bench):
    """RTU replies carry no transaction id nor address: a reply to "target of axis 2" that comes late is
    byte-for-byte a valid answer to "speed of axis 2". The driver must not take one for the other."""
    act = rtu(rtu_bench, timeout_s=0.1, retries=2, late_reply_guard_s=0.5)
    async with act:
        await act.home(timeout_s=5)
        await act.move(Q_A, speed_m_s=2.0)
        m = act.map
        unit, addr = m.addr(1, "target")
        speed_addr = addr + m.speed - m.target
        speed_regs = await act.read(unit, speed_addr, 2)
        assert m.from_regs32(speed_regs) != m.from_regs32(await act.read(unit, addr, 2))
        link = rtu_bench.link
        # every reply takes 30 ms (so a request is almost always waiting), the next one 250 ms: it lands
        # 150 ms after its request timed out, in the middle of the requests that follow
        link.latency_s = 0.03
        link.hold_s, link.hold_count = 0.25, 1
        t0 = time.monotonic()
        regs = await act.read(unit, addr, 2)  # axis 2 target
        assert m.counts_to_m(m.from_regs32(regs)) == pytest.approx(Q_A[1])
        assert act.stats["retries"] >= 1
        # same unit, function and register count as the late reply, other registers: keep asking while it lands
        n = 0
        while time.monotonic() - t0 < 0.9:
            assert await act.read(unit, speed_addr, 2) == speed_regs, f"stale reply taken at {n}"
            n += 1
        assert n > 5 and link.hold_count == 0
        for ax in range(4):
            assert (await act.read_axis(ax)).position_m == pytest.approx(Q_A[ax], abs=3e-6)


async def test_move_survives_a_late_reply(rtu_bench):
    act = rtu(rtu_bench, timeout_s=0.1, late_reply_guard_s=0.3)
    async with act:
        await act.home(timeout_s=5)
        rtu_bench.link.hold_s, rtu_bench.link.hold_count = 0.2, 1
        assert np.allclose(await act.move(Q_A), Q_A, atol=3e-6)
        await asyncio.sleep(0.05)
        assert np.allclose(await act.read_encoders(), Q_A, atol=3e-6)
