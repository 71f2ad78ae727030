"""Link faults between the Modbus driver and the simulated controller, on every transport: 0 stale readings.

Real sockets all the way: the simulated controller (pymodbus server), a fault proxy or a gateway from
``drivers.sim.faultproxy`` in between, the driver over Modbus TCP, RTU over TCP, or RTU on a serial port:
a pty whose other end is relayed to the gateway's TCP port (the virtual COM port of a serial device
server; pyserial's ``socket://`` handler sleeps 0.3 s in ``close()``, blocking the event loop).
Transports: Modbus TCP (a TCP device behind a fault proxy), RTU on a serial port, RTU over TCP (a serial device
server) and ``gateway``: Modbus TCP to a TCP/RTU gateway whose serial response timeout is shorter than the late
replies, so that a reply arriving after the gateway gave up is handed to the next request on the line with that
request's transaction id. Scenarios: replies delayed past the timeout, dropped, duplicated up to 50 ms later,
connections cut, and a gateway sharing one serial line with a second master.

A reading is *stale* when the position it reports is not one the axis had while the reading was being
made: every ``read_axis`` is bracketed by the true position of the simulated mechanism just before the
request and just after the reply; during a monotonic move (homing, moves between two poses) the reading
must lie between the two (within the encoder's quantisation and noise, 3 um). The proxies' faults are
seeded; each scenario asserts that faults were really injected and that the driver still got its moves done.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
import tty

import numpy as np
import pytest
from drv_helpers import make_modbus

from drivers.devices.modbus import ModbusActuators, ModbusLink, ModbusLinkSettings
from drivers.errors import DeviceError
from drivers.sim.faultproxy import FaultProxy, SerialGateway, cancel_and_wait

Q_A = np.array([0.40, 0.41, 0.42, 0.43])
Q_B = np.array([0.30, 0.31, 0.35, 0.36])
TOL_M = 3e-6  # 1 um counts + 0.3 um encoder noise, 10 sigma: a stale reading is mm away at these speeds
TIMEOUT_S = 0.08  # reply timeout; injected delays are 1.2-2.2 timeouts (as 250-450 ms with 200 ms)
DELAYS = (0.1, 0.18)

SCENARIOS = {
    "delay": dict(delay_prob=0.03, delay_s=DELAYS),
    "drop": dict(drop_prob=0.03),
    "cut": dict(cut_prob=0.02),
    "duplicate": dict(duplicate_prob=0.2, duplicate_after_s=(0.0003, 0.05)),
    "gateway": dict(delay_prob=0.03, delay_s=DELAYS),
}
FAULTS = ("delayed", "dropped", "duplicated", "cuts")


class StaleCounter:
    """Wraps ``act.read_axis``: every reading checked against the true positions around it."""

    def __init__(self, act: ModbusActuators, mechanism) -> None:
        self.readings = 0
        self.stale: list[tuple[int, float, float, float]] = []
        orig = act.read_axis

        async def read_axis(axis: int):
            before = mechanism.q_true()[axis]
            s = await orig(axis)
            after = mechanism.q_true()[axis]
            self.readings += 1
            lo, hi = min(before, after) - TOL_M, max(before, after) + TOL_M
            if not lo <= s.position_m <= hi:
                self.stale.append((axis, s.position_m, before, after))
            return s

        act.read_axis = read_axis  # type: ignore[method-assign]


class PtyToTcp:
    """A serial port (pty) whose bytes are relayed to and from a TCP connection, reconnected when cut: the
    virtual COM port of a serial device server."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.address = address
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self._slave)  # the slave stays open: no EIO while the driver reopens the port
        self._task: asyncio.Task | None = None

    async def start(self) -> str:
        reader, self._writer = await asyncio.open_connection(*self.address)
        loop = asyncio.get_running_loop()

        def from_pty() -> None:
            with contextlib.suppress(BlockingIOError, OSError):
                data = os.read(self.master, 4096)
                if not self._writer.is_closing():
                    self._writer.write(data)  # bytes sent while the link is down are lost, as on a cut line

        loop.add_reader(self.master, from_pty)

        async def to_pty(reader: asyncio.StreamReader) -> None:
            while True:
                with contextlib.suppress(ConnectionError, OSError):
                    while data := await reader.read(4096):
                        with contextlib.suppress(BlockingIOError, OSError):
                            os.write(self.master, data)
                await asyncio.sleep(0.01)
                with contextlib.suppress(OSError):
                    reader, self._writer = await asyncio.open_connection(*self.address)

        self._task = asyncio.create_task(to_pty(reader))
        return self.path

    async def close(self) -> None:
        asyncio.get_running_loop().remove_reader(self.master)
        if self._task is not None:
            await cancel_and_wait([self._task])
        self._writer.close()
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


async def open_link(bench, transport: str, scenario: str, seed: int):
    """The proxy or gateway for a scenario, and the driver's connection keywords through it."""
    rtu_line = ("127.0.0.1", int(bench.rtu_url.rsplit(":", 1)[1]))
    if transport == "tcp" and scenario != "gateway":
        proxy = FaultProxy(bench.tcp_address, seed=seed)  # a Modbus TCP device
    else:  # one serial line: a serial device server (RTU clients) or a Modbus TCP/RTU gateway (TCP clients)
        framing = "tcp" if transport in ("tcp", "gateway") else "rtu"
        if scenario == "gateway":  # two masters: a gateway whose response timeout outlasts the late replies
            proxy = SerialGateway(rtu_line, client_framing=framing, line_timeout_s=0.25, route="requester", seed=seed)
        else:  # one master behind a serial device server that gives up on the line before the late replies
            proxy = SerialGateway(rtu_line, client_framing=framing, line_timeout_s=TIMEOUT_S / 2, seed=seed)
    host, port = await proxy.start()
    ptys = []
    if transport == "rtu":
        ptys = [PtyToTcp((host, port)) for _ in range(2 if scenario == "gateway" else 1)]
        kws = [dict(serial_port=await p.start()) for p in ptys]
    else:
        kws = [dict(host=host, port=port)] * 2
    return proxy, kws, ptys


def driver(bench, transport: str, kw: dict) -> ModbusActuators:
    wire = "tcp" if transport == "gateway" else transport  # the driver speaks Modbus TCP to a gateway
    act = make_modbus(bench, wire, timeout_s=TIMEOUT_S, retries=4, poll_s=0.002, **kw)
    return act


async def run_scenario(bench, transport: str, scenario: str, seed: int = 1) -> dict:
    proxy, kws, ptys = await open_link(bench, transport, scenario, seed)
    other_task = None
    done = asyncio.Event()
    try:
        act = driver(bench, transport, kws[0])
        counter = StaleCounter(act, bench.mechanism)
        await act.connect()
        for k, v in SCENARIOS[scenario].items():
            setattr(proxy.faults, k, v)
        if scenario == "gateway":  # a second master polls the same units through the same serial line
            other = driver(bench, transport, kws[1])

            async def poll() -> None:
                with contextlib.suppress(Exception):
                    await other.connect()
                while not done.is_set():  # a flag too: a dropped cancellation must not keep the poller alive
                    with contextlib.suppress(DeviceError):
                        await other.status()
                    await asyncio.sleep(0.001)

            other_task = asyncio.create_task(poll())
        moves = failures = 0
        t_end = time.monotonic() + 8.0
        with contextlib.suppress(DeviceError):
            await act.home(timeout_s=3)
        k = 0

        def enough() -> bool:
            injected = sum(proxy.stats.get(f, 0) for f in FAULTS)
            return counter.readings >= 120 and moves >= 3 and injected >= 3

        while time.monotonic() < t_end and not enough():
            try:
                if not (await act.status()).homed:
                    await act.home(timeout_s=3)
                await act.move(Q_A if k % 2 == 0 else Q_B)
                moves += 1
            except DeviceError:
                failures += 1
                with contextlib.suppress(DeviceError):
                    await act.reset_alarms()
            k += 1
        await act.close()
        return dict(
            readings=counter.readings,
            stale=counter.stale,
            moves=moves,
            failures=failures,
            driver=dict(act.stats),
            proxy=dict(proxy.stats),
        )
    finally:
        if other_task is not None:
            done.set()
            other_task.cancel()
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(other_task, 10)
        for p in ptys:
            await p.close()
        await proxy.close()


MATRIX = [
    (t, s) for s in SCENARIOS for t in ("tcp", "rtu", "rtu-tcp", "gateway") if (t, s) != ("gateway", "gateway")
]  # the gateway scenario of tcp already is a TCP/RTU gateway (two masters)


@pytest.mark.parametrize(("transport", "scenario"), MATRIX)
async def test_no_stale_reading(bench, transport, scenario):
    r = await run_scenario(bench, transport, scenario)
    print(transport, scenario, {k: v for k, v in r.items() if k != "stale"}, "stale:", len(r["stale"]))
    assert r["stale"] == [], f"{len(r['stale'])} stale readings of {r['readings']}: {r['stale'][:5]}"
    assert sum(r["proxy"].get(f, 0) for f in FAULTS) >= 3, r["proxy"]  # the scenario really happened
    assert r["readings"] >= 120 and r["moves"] >= 3, r


class ScriptedRtuDevice:
    """A Modbus RTU device behind a serial device server (RTU framing over a real TCP socket) whose replies follow a
    script: reply k (1-based) is sent ``reply_after_s[k]`` after its request, and a copy of reply k goes out again
    ``duplicate_after_s[k]`` after the original. Each reply's registers all hold the request's number k, so a
    reading names the request it answers."""

    def __init__(
        self, reply_after_s: dict[int, float], duplicate_after_s: dict[int, float], default_after_s: float = 0.0
    ) -> None:
        self.reply_after_s, self.duplicate_after_s = reply_after_s, duplicate_after_s
        self.default_after_s = default_after_s
        self.requests = 0
        self._server: asyncio.Server | None = None

    async def start(self) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return self._server.sockets[0].getsockname()[:2]

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        from pymodbus.framer import FramerRTU

        loop = asyncio.get_running_loop()
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                req = await reader.readexactly(8)  # unit, 3, address (2), count (2), CRC (2)
                assert req[1] == 3, f"only reads are scripted, got function {req[1]}"
                self.requests += 1
                k, count = self.requests, int.from_bytes(req[4:6], "big")
                body = bytes([req[0], 3, 2 * count]) + b"".join(k.to_bytes(2, "big") for _ in range(count))
                frame = body + FramerRTU.compute_CRC(body).to_bytes(2, "big")
                delay = self.reply_after_s.get(k, self.default_after_s)
                loop.call_later(delay, writer.write, frame)
                if k in self.duplicate_after_s:
                    loop.call_later(delay + self.duplicate_after_s[k], writer.write, frame)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()


async def test_a_duplicate_never_answers_a_later_request_of_the_same_shape():
    """A reply duplicated on its way lands while a later request of the same shape (unit, register count) waits.

    RTU replies name neither register nor transaction; the driver alternates two read lengths per unit so that a
    duplicate of the previous read has the wrong length, but the read before that has the same. Script: read 1
    (4 registers) is answered at once and duplicated 6 ms later; read 2 (5 registers) at once; read 3 (4 registers,
    out ~1 ms after read 1's reply) 15 ms after it arrives, so read 1's duplicate lands while read 3 waits. The
    driver took it for read 3's answer (CI: test_no_stale_reading[duplicate-rtu-tcp], an axis read 11 mm from where
    it was). Now a request waits until ``flush_s`` after the last reply to a request of its shape: the duplicate
    comes while nothing is asked, and is discarded."""
    device = ScriptedRtuDevice(reply_after_s={3: 0.015}, duplicate_after_s={1: 0.006})
    host, port = await device.start()
    link = ModbusLink(
        ModbusLinkSettings(transport="rtu-tcp", host=host, port=port, timeout_s=0.5, retries=0, flush_s=0.05)
    )
    try:
        got = [await link.read(1, 5, 4), await link.read(1, 4, 5), await link.read(1, 5, 4)]
    finally:
        await link.close()
        await device.close()
    assert [g[0] for g in got] == [1, 2, 3], f"read 3 answered by reply {got[2][0]}: {got}"
    assert link.stats["unrequested"] == 1, dict(link.stats)  # the duplicate came, and was discarded


def request_number(status) -> int:
    """The request a ScriptedRtuDevice reply answers: every register holds it, the position's low word too."""
    return round(status.position_m * 1e6) & 0xFFFF


async def test_a_gateway_hands_a_late_reply_to_the_next_request_with_its_transaction_id():
    """Modbus TCP to a TCP/RTU gateway whose serial response timeout (50 ms) is shorter than the drive's late
    replies: replies 1, 11, 21, 31 come 250 ms after their request (2.5 driver timeouts), the others after 20 ms.
    The gateway has moved on and hands each late reply to the request then on the line, with that request's
    transaction id: only its shape can betray it. The old driver trusted the transaction id and alternated two
    read windows: a late reply landed on a read of the same window (reply 1 answered request 7, reply 11 request
    17, ...). Now no request of a shape whose reply may still come goes out within the guard: every reading
    answers the request it was made by."""
    device = ScriptedRtuDevice(
        reply_after_s=dict.fromkeys((1, 11, 21, 31), 0.25), duplicate_after_s={}, default_after_s=0.02
    )
    line = await device.start()
    gateway = SerialGateway(line, client_framing="tcp", line_timeout_s=0.05, route="requester")
    host, port = await gateway.start()
    link = ModbusLink(ModbusLinkSettings(transport="tcp", host=host, port=port, timeout_s=0.1, retries=3))
    wrong = []
    try:
        await link.open()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.5:
            k = request_number(await link.read_axis(0))
            if k != device.requests:
                wrong.append((k, device.requests))
    finally:
        await link.close()
        await gateway.close()
        await device.close()
    assert wrong == [], f"readings answered by earlier requests (reply, latest request): {wrong}"
    assert device.requests > 31 and link.stats["timeouts"] >= 4, (device.requests, dict(link.stats))


async def test_an_rtu_duplicate_50_ms_late_never_answers_a_later_read():
    """RTU over TCP (a serial device server) that duplicates a reply 40 ms later, default settings: the old
    driver waited 10 ms (``flush_s``) after a reply of the same shape, and read the same window two reads later
    (every 2 x 15 ms): the copy answered it. Now a copy is awaited for ``duplicate_window_s`` (0.1 s) and the reads
    rotate through every window of the axis' registers meanwhile."""
    device = ScriptedRtuDevice(
        reply_after_s={}, duplicate_after_s={k: 0.04 for k in range(1, 200)}, default_after_s=0.015
    )
    host, port = await device.start()
    link = ModbusLink(ModbusLinkSettings(transport="rtu-tcp", host=host, port=port, timeout_s=0.2, retries=2))
    wrong = []
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:
            k = request_number(await link.read_axis(0))
            if k != device.requests:
                wrong.append((k, device.requests))
    finally:
        await link.close()
        await device.close()
    assert wrong == [], f"readings answered by earlier requests (reply, latest request): {wrong}"
    assert device.requests > 10, device.requests


FRAME_FAULTS = dict(delay_prob=0.03, delay_s=DELAYS, duplicate_prob=0.2, duplicate_after_s=(0.0003, 0.05))


@pytest.mark.parametrize("transport", ["tcp", "rtu", "rtu-tcp", "gateway"])
async def test_no_frame_off_the_truth(bench, tmp_path, transport):
    """A run through the faulty link (late replies, duplicates up to 50 ms late): every frame written records a q
    within the encoder's noise of the true joints at the frame (the simulated camera reports them). A run that
    fails on a fault is resumed, as an operator would."""
    from test_acquisition import small_plan

    from calib.formats.dataset import Dataset
    from calib.formats.plan import Plan
    from calib.model.parameters import NOMINAL
    from drivers.acquisition.acquire import Acquisition, AcquisitionError
    from drivers.acquisition.config import open_camera

    p = small_plan()
    plan = Plan(name="faults", steps=[s for s in p.steps if s.line is None])
    proxy, kws, ptys = await open_link(bench, transport, "delay", seed=3)
    cfg = bench.bench_config()
    failures = 0
    try:
        for k, v in FRAME_FAULTS.items():
            setattr(proxy.faults, k, v)
        for attempt in range(4):
            acq = Acquisition(
                plan,
                driver(bench, transport, kws[0]),
                open_camera(cfg),
                tmp_path / "ds",
                nominal=NOMINAL,
                limits=cfg.calib_limits(),
                resume=attempt > 0,
            )
            try:
                await acq.run()
                break
            except AcquisitionError:
                failures += 1
            finally:
                await acq.actuators.close()
                await acq.camera.close()
    finally:
        for pt in ptys:
            await pt.close()
        await proxy.close()
    ds = Dataset.open(tmp_path / "ds")
    print(transport, "frames", len(ds.frames), "failed runs", failures, dict(proxy.stats))
    assert len(ds.frames) == len(plan.steps), (len(ds.frames), failures)
    assert proxy.stats["delayed"] + proxy.stats["duplicated"] >= 3, dict(proxy.stats)
    off = [
        (k, np.max(np.abs(np.asarray(f.q) - np.asarray(f.model_extra["truth"]["q"])))) for k, f in enumerate(ds.frames)
    ]
    assert all(d <= TOL_M for _, d in off), [o for o in off if o[1] > TOL_M]
