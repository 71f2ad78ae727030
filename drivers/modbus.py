"""Actuators over Modbus (pymodbus 3.16 async client; TCP, RTU on a serial line, RTU over TCP).

Stale replies. A reply is taken as the answer to a request only when it matches it: function code,
unit id, register count or echoed address/count, and on Modbus TCP the transaction id. A request
that gets no reply in time (or is cancelled, or whose link is cut) leaves its reply possibly still on
the way, so its link is never reused: it is closed and a fresh one opened. On a link with RTU framing
(``rtu``: a serial line; ``rtu-tcp``: a serial device server or gateway) a fresh link leads to the same
wire and an RTU reply names neither a transaction nor an address, so after such a fault the link stays
closed for ``late_reply_guard_s`` (default twice the reply timeout) and the next request waits until
the link has been quiet for ``flush_s``; bytes that arrive while no request is outstanding (a late or
duplicated reply, a reply to another master on a shared line) are counted (``stats["unrequested"]``)
and discarded. Consecutive reads of one unit (a retry included) ask for windows of different lengths
(the read-back window, then widened by an adjacent register of the same axis), so that a late or
duplicated reply to the previous read of that unit has the wrong byte count and is refused
(``stats["stale"]``) rather than taken for the current answer, on RTU framing and behind a Modbus
TCP/RTU gateway alike.

Plausible readings. Every decoded position must lie within the soft limits widened by
``plausibility_margin_m`` and within ``max_speed_m_s`` x the time since the axis' last accepted
reading (+ ``plausibility_slack_m``); otherwise :class:`~drivers.errors.ProtocolError` names the axis,
the value and why, and nothing moves on it (homing, which may re-zero an encoder, is exempt from the
second test).

A move follows one shape: check the targets (per-axis soft limits, then the nominal kinematic
model), compute a timeout from the distances and speeds, write target + speed + start, poll until
every axis is in position, and stop every axis on any error, timeout or cancellation. A stop is sent
to every axis at once (``asyncio.gather``, one request in flight on the link) and is confirmed by
reading every axis back not moving, all within one deadline (``stop_deadline_s``); otherwise
:class:`~drivers.errors.StopNotConfirmedError` says motion may not have stopped. The stop runs in its
own task, so a stop sent while its caller is being cancelled still goes out.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from calib.errors import UnreachableError
from calib.kinematics import dkm
from calib.parameters import I4Parameters

from .errors import (
    AlarmError,
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    LimitError,
    ProtocolError,
    StopNotConfirmedError,
)
from .interfaces import ActuatorStatus, AxisStatus, SoftLimitsM
from .metrics import CountingStats
from .registermap import ALARM_TEXT, DEFAULT_MAP, RegisterMap

log = logging.getLogger(__name__)

#: Modbus exception codes worth retrying (acknowledge, device busy).
RETRYABLE_EXCEPTIONS = {5, 6}
EXCEPTION_TEXT = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "device failure",
    5: "acknowledge",
    6: "device busy",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}


def alarm_message(axis: int, code: int) -> str:
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


RTU_FRAMED = ("rtu", "rtu-tcp")
_FC_READ, _FC_WRITE = 3, 16


class _Link:
    """What the trace hooks of one client connection saw (a dropped client's late callbacks touch only it)."""

    def __init__(self) -> None:
        self.pending = False  # a request is out and not yet answered
        self.sent_tid = 0  # transaction id of the last request (Modbus TCP)
        self.last_rx = 0.0  # monotonic time of the last bytes received
        self.drain = False  # bytes came unrequested (or the link follows a fault): wait for quiet before a request
        self.unrequested = 0  # receptions while no request was outstanding
        self.opened = time.monotonic()


class ModbusActuators:
    """:class:`drivers.interfaces.Actuators` over Modbus.

    Parameters
    ----------
    host, port:
        TCP endpoint (``transport="tcp"`` Modbus TCP, ``"rtu-tcp"`` RTU framing over a TCP socket: a serial
        device server or an RTU gateway).
    serial_port, baudrate:
        Serial device for ``transport="rtu"`` (any pyserial URL works, e.g. ``socket://host:port``).
    speed_m_s, accel_m_s2:
        Move speed of the axis that travels furthest (the others are scaled to arrive together) and the
        drive's acceleration, used only for the move timeout.
    late_reply_guard_s:
        RTU framing (``rtu``, ``rtu-tcp``) only: after a request timed out, was cancelled or lost its link,
        the link stays closed this long (s) before it is reopened, so that the late reply lands on no
        link. ``None``: ``2 * timeout_s`` (a reply up to three timeouts late is discarded).
    flush_s:
        RTU framing only: a link reopened after a fault, or that received unrequested bytes, must have been
        quiet this long (s) before the next request goes out; what arrived meanwhile is discarded.
    vary_reads:
        Alternate the length of consecutive reads of one unit, retries included (an adjacent register of the
        same axis: the control register in the default map) so that a stale reply (RTU framing, or a Modbus
        TCP/RTU gateway that hands a late serial reply to the next request) has the wrong length.
        ``False`` for a drive that refuses to read that register.
    max_speed_m_s:
        Fastest an axis can move (homing, a person guiding a free drive included), for the plausibility of
        readings. ``None``: ``5 * speed_m_s``.
    plausibility_margin_m, plausibility_slack_m:
        A reading must lie within the soft limits widened by the margin (m), and within
        ``max_speed_m_s * dt + slack`` of the axis' previous accepted reading.
    stop_deadline_s:
        One deadline (s) for the whole stop sequence: stop sent to every axis and every axis read back not
        moving.
    workspace_check:
        Refuses joint targets the kinematic model cannot reach by raising :class:`calib.errors.UnreachableError`
        (e.g. another mechanism's DKM at its nominal geometry); default: the nominal I4's DKM when ``nominal``
        is given.

    The number of axes is the register map's (``len(regmap.axes)``, four by default); ``limits`` must have as many
    values (default: -0.10 to 0.80 m on every axis).
    """

    def __init__(
        self,
        *,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        serial_port: str | None = None,
        baudrate: int = 115200,
        regmap: RegisterMap = DEFAULT_MAP,
        limits: SoftLimitsM | None = None,
        nominal: I4Parameters | None = None,
        speed_m_s: float = 0.05,
        accel_m_s2: float = 0.5,
        timeout_s: float = 0.5,
        retries: int = 3,
        backoff_s: float = 0.02,
        backoff_max_s: float = 1.0,
        poll_s: float = 0.002,
        settle_s: float = 0.0,
        in_position_m: float = 2e-5,
        move_timeout_factor: float = 2.0,
        move_timeout_margin_s: float = 1.0,
        home_timeout_s: float = 60.0,
        late_reply_guard_s: float | None = None,
        flush_s: float = 0.01,
        vary_reads: bool = True,
        max_speed_m_s: float | None = None,
        plausibility_margin_m: float = 0.05,
        plausibility_slack_m: float = 1e-3,
        stop_deadline_s: float = 2.0,
        workspace_check: Callable[[np.ndarray], Any] | None = None,
    ) -> None:
        if transport not in ("tcp", "rtu", "rtu-tcp"):
            raise ValueError(f"unknown Modbus transport {transport!r}")
        self.transport = transport
        self.host, self.port = host, int(port)
        self.serial_port, self.baudrate = serial_port, int(baudrate)
        self.map = regmap
        self.n_axes = n = len(regmap.axes)
        if limits is None:
            d = SoftLimitsM()
            limits = d if n == 4 else SoftLimitsM((d.q_min[0],) * n, (d.q_max[0],) * n)
        if len(limits.q_min) != n or len(limits.q_max) != n:
            raise ValueError(
                f"the register map has {n} axes but the soft limits have {len(limits.q_min)} and "
                f"{len(limits.q_max)} values"
            )
        self.limits = limits
        self.nominal = nominal
        self.workspace_check = workspace_check
        self.speed_m_s = float(speed_m_s)
        self.accel_m_s2 = float(accel_m_s2)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.backoff_s, self.backoff_max_s = float(backoff_s), float(backoff_max_s)
        self.poll_s = float(poll_s)
        self.settle_s = float(settle_s)
        self.in_position_m = float(in_position_m)
        self.move_timeout_factor = float(move_timeout_factor)
        self.move_timeout_margin_s = float(move_timeout_margin_s)
        self.home_timeout_s = float(home_timeout_s)
        self.late_reply_guard_s = float(2 * self.timeout_s if late_reply_guard_s is None else late_reply_guard_s)
        self.flush_s = float(flush_s)
        self.vary_reads = bool(vary_reads)
        self.max_speed_m_s = float(5 * self.speed_m_s if max_speed_m_s is None else max_speed_m_s)
        self.plausibility_margin_m = float(plausibility_margin_m)
        self.plausibility_slack_m = float(plausibility_slack_m)
        self.stop_deadline_s = float(stop_deadline_s)
        self._quiet_until = 0.0  # RTU framing: no new link before this monotonic time (a late reply may be on the wire)
        self._reopen_settle = False  # RTU framing: the next link follows a fault; let it be quiet first
        self._client: AsyncModbusTcpClient | AsyncModbusSerialClient | None = None
        self._link = _Link()
        self._lock = asyncio.Lock()
        self._free_bits = [0] * n
        self._homing = False
        self._last_reading: list[tuple[float, float] | None] = [None] * n  # (position m, monotonic s) per axis
        self._read_count: dict[int, int] = {}  # reads per unit (RTU framing: alternate the window length)
        self._windows = [self._read_windows(i) for i in range(n)]
        #: counters of this driver, also summed process-wide for ``GET /metrics`` (drivers.metrics)
        self.stats = CountingStats(
            "modbus", {"requests": 0, "retries": 0, "timeouts": 0, "reconnects": 0, "stale": 0, "unrequested": 0}
        )

    @property
    def endpoint(self) -> str:
        if self.transport == "rtu":
            return f"{self.serial_port} (RTU, {self.baudrate} Bd)"
        return f"{self.host}:{self.port}" + (" (RTU over TCP)" if self.transport == "rtu-tcp" else "")

    # -- connection ---------------------------------------------------------------------------
    def _new_client(self):
        link = _Link()

        def trace_pdu(sending: bool, pdu):
            if sending:
                link.pending = True
                link.sent_tid = int(getattr(pdu, "transaction_id", 0) or 0)
            else:
                link.pending = False
            return pdu

        def trace_packet(sending: bool, data: bytes) -> bytes:
            if sending or not data:
                return data
            link.last_rx = time.monotonic()
            if not link.pending:  # nobody asked: a late or duplicated reply, or another master's
                link.unrequested += 1
                link.drain = True
                self.stats["unrequested"] += 1
                return b""  # not decoded; the next request's send discards it
            return data

        hooks = dict(trace_packet=trace_packet, trace_pdu=trace_pdu)
        if self.transport == "rtu":
            client = AsyncModbusSerialClient(
                self.serial_port,
                framer=FramerType.RTU,
                baudrate=self.baudrate,
                timeout=self.timeout_s,
                retries=0,
                reconnect_delay=0,
                **hooks,
            )
        else:
            framer = FramerType.SOCKET if self.transport == "tcp" else FramerType.RTU
            client = AsyncModbusTcpClient(
                self.host,
                port=self.port,
                framer=framer,
                timeout=self.timeout_s,
                retries=0,
                reconnect_delay=0,
                **hooks,
            )
        return client, link

    async def _open(self) -> None:
        self._drop()
        client, link = self._new_client()
        try:
            ok = await asyncio.wait_for(client.connect(), timeout=max(self.timeout_s, 0.5) * 2)
        except (TimeoutError, OSError, ModbusException):
            ok = False
        except asyncio.CancelledError:
            with contextlib.suppress(Exception):
                client.close()
            raise
        if not ok:
            with contextlib.suppress(Exception):
                client.close()
            raise DeviceConnectionError(f"cannot connect to the Modbus controller at {self.endpoint}")
        link.opened = time.monotonic()
        self._client, self._link = client, link

    def _drop(self) -> None:
        if self._client is not None:
            with contextlib.suppress(Exception):
                self._client.close()
            self._client = None

    def _fault(self, reply_may_come: bool) -> None:
        """Never reuse this link; on RTU framing keep the wire quiet while a late reply may still come."""
        self._drop()
        if reply_may_come and self.transport in RTU_FRAMED:
            self._quiet_until = max(self._quiet_until, time.monotonic() + self.late_reply_guard_s)
            self._reopen_settle = True

    async def _ready_link(self, urgent: bool) -> None:
        """A link fit for the next request. ``urgent`` (a stop): no waiting out the late-reply guard (the
        replies' checks still apply); a link opened that way is replaced before the next non-urgent request."""
        if self._client is not None and not urgent and self._link.opened < self._quiet_until:
            self._drop()  # opened during a guard for a stop: a late reply may still arrive on it
        if self._client is None or not self._client.connected:
            self.stats["reconnects"] += 1
            if not urgent and (quiet := self._quiet_until - time.monotonic()) > 0:
                await asyncio.sleep(quiet)
            await self._open()  # a serial port is flushed when it opens
            if self._reopen_settle and not urgent:
                self._link.last_rx = max(self._link.last_rx, time.monotonic())
                self._link.drain = True
                self._reopen_settle = False
        link = self._link
        if link.drain and self.transport in RTU_FRAMED and not urgent:
            # drain: whatever arrives unrequested (a buffered late reply, a duplicate) must be over first;
            # the request's send then discards it
            deadline = time.monotonic() + max(self.timeout_s, self.flush_s) * 2
            while (wait := link.last_rx + self.flush_s - time.monotonic()) > 0 and time.monotonic() < deadline:
                await asyncio.sleep(wait)
            link.drain = False

    async def connect(self) -> None:
        last: Exception | None = None
        for attempt in range(self.retries + 1):
            try:
                await self._open()
                break
            except DeviceConnectionError as exc:
                last = exc
                await asyncio.sleep(min(self.backoff_s * 2**attempt, self.backoff_max_s))
        else:
            raise last  # type: ignore[misc]
        self._last_reading = [None] * self.n_axes
        await self.status()  # every axis answers, with plausible positions

    async def close(self) -> None:
        self._drop()

    async def __aenter__(self) -> ModbusActuators:
        await self.connect()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    # -- one checked request ----------------------------------------------------------------------
    def _mismatch(self, rr, kind: str, unit: int, address: int, count_or_values: Any) -> str | None:
        """Why a reply is not the answer to this request, or None (an exception reply: header only)."""
        fc = _FC_READ if kind == "read" else _FC_WRITE
        got_fc = int(getattr(rr, "function_code", fc)) & 0x7F
        if got_fc != fc:
            return f"reply with function code {got_fc} to a request with function code {fc}"
        if unit and getattr(rr, "dev_id", unit) != unit:
            return f"reply from unit {rr.dev_id} to a request for unit {unit}"
        if self.transport == "tcp":
            tid = int(getattr(rr, "transaction_id", 0) or 0)
            if tid != self._link.sent_tid:
                return f"reply with transaction id {tid} to request {self._link.sent_tid}"
        if rr.isError():
            return None
        if kind == "read":
            n = len(rr.registers)
            if n != count_or_values:
                return f"reply with {n} registers to a request for {count_or_values}"
            return None
        n = len(count_or_values)
        if getattr(rr, "address", address) != address or getattr(rr, "count", n) != n:
            return f"write echo (address {rr.address}, count {rr.count}) does not match the request ({address}, {n})"
        return None

    async def _request(
        self,
        kind: str,
        unit: int,
        address: int,
        count_or_values: Any,
        *,
        urgent: bool = False,
        windows: list[tuple[int, int]] | None = None,
    ) -> Any:
        """One checked request, retried. ``windows``: a read of any of these (start, count), alternated per unit
        and per attempt (a retry never asks the same as the attempt whose reply may still come); then the
        result is ``(start, registers)``."""
        async with self._lock:
            last: str = ""
            for attempt in range(self.retries + 1):
                if windows:
                    k = self._read_count.get(unit, 0)
                    self._read_count[unit] = k + 1
                    address, count_or_values = windows[k % len(windows)]
                if attempt:
                    self.stats["retries"] += 1
                    await asyncio.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.backoff_max_s))
                try:
                    await self._ready_link(urgent)
                except DeviceConnectionError as exc:
                    last = str(exc)
                    continue
                self.stats["requests"] += 1
                try:
                    if kind == "read":
                        rr = await self._client.read_holding_registers(address, count=count_or_values, device_id=unit)
                    else:
                        rr = await self._client.write_registers(address, list(count_or_values), device_id=unit)
                except asyncio.CancelledError:
                    self._fault(reply_may_come=True)  # the reply may still be on its way
                    raise
                except ConnectionException as exc:
                    last = f"connection lost ({exc})"
                    self._fault(reply_may_come=True)
                    continue
                except (ModbusIOException, TimeoutError) as exc:
                    # no reply in time: never reuse this link, a late reply could pair with the next request
                    last = f"no reply within {self.timeout_s:.3f} s ({type(exc).__name__})"
                    self.stats["timeouts"] += 1
                    self._fault(reply_may_come=True)
                    continue
                except ModbusException as exc:
                    last = f"Modbus error ({exc})"
                    self._fault(reply_may_come=True)
                    continue
                task = asyncio.current_task()
                if task is not None and task.cancelling():
                    # Python 3.11's wait_for (inside pymodbus) returns a reply that lands together with a
                    # cancellation and drops the cancellation (CPython gh-86296): honour it here
                    raise asyncio.CancelledError
                if problem := self._mismatch(rr, kind, unit, address, count_or_values):
                    # a late, duplicated or foreign reply: refuse it, and the link it came on
                    last = f"stale or foreign reply: {problem}"
                    self.stats["stale"] += 1
                    log.warning("Modbus controller at %s, unit %d: %s; link replaced", self.endpoint, unit, last)
                    self._fault(reply_may_come=True)
                    continue
                if rr.isError():
                    code = int(getattr(rr, "exception_code", 0) or 0)
                    msg = (
                        f"unit {unit} register {address}: exception code {code} ({EXCEPTION_TEXT.get(code, 'unknown')})"
                    )
                    if code in RETRYABLE_EXCEPTIONS:
                        last = msg
                        continue
                    raise ProtocolError(msg, exception_code=code)
                if windows:
                    return address, list(rr.registers)
                return list(rr.registers) if kind == "read" else []
            if "connect" in last or "connection" in last:
                raise DeviceConnectionError(
                    f"Modbus controller at {self.endpoint}: {last}, after {self.retries + 1} attempts"
                )
            raise DeviceTimeoutError(
                f"Modbus controller at {self.endpoint}, unit {unit}: {last}, after {self.retries + 1} attempts"
            )

    async def read(self, unit: int, address: int, count: int) -> list[int]:
        return await self._request("read", unit, address, count)

    async def write(self, unit: int, address: int, values: list[int], *, urgent: bool = False) -> None:
        await self._request("write", unit, address, values, urgent=urgent)

    # -- status ------------------------------------------------------------------------------------
    def _read_windows(self, axis: int) -> list[tuple[int, int]]:
        """Contiguous relative windows (start, count) that cover the read-back window, shortest first,
        within the axis' own registers (RTU framing: consecutive reads of a unit differ in length)."""
        m = self.map
        lo, n = m.readback_window()
        own = {m.target, m.target + 1, m.speed, m.speed + 1, m.control, m.status, m.actual, m.actual + 1}
        own.add(m.alarm_code)
        out = [(lo, n)]
        a, b = lo, lo + n  # [a, b)
        while True:
            if a - 1 in own:
                a -= 1
            elif b in own:
                b += 1
            else:
                break
            out.append((a, b - a))
        return out

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
                self._last_reading[axis] = None
                raise ProtocolError(
                    f"axis {axis + 1}: implausible position {position_m * 1e3:.3f} mm read from {self.endpoint}: "
                    f"{abs(position_m - p0) * 1e3:.3f} mm from the reading {now - t0:.3f} s earlier "
                    f"({p0 * 1e3:.3f} mm), more than the axis can travel at {self.max_speed_m_s:g} m/s "
                    f"({reach * 1e3:.3f} mm); nothing moves on it"
                )
        self._last_reading[axis] = (position_m, t_request)

    async def read_axis(self, axis: int) -> AxisStatus:
        m = self.map
        unit, base = m.addr(axis, "status")
        base -= m.status
        windows = [(base + lo, n) for lo, n in self._windows[axis][: 2 if self.vary_reads else 1]]
        t_request = time.monotonic()
        start, regs = await self._request("read", unit, windows[0][0], windows[0][1], windows=windows)
        lo = start - base
        st = regs[m.status - lo]
        enc = m.from_regs32(regs[m.actual - lo : m.actual - lo + 2])
        code = regs[m.alarm_code - lo]
        b = m.status_bits
        position = m.counts_to_m(enc)
        self.check_reading(axis, position, t_request)
        return AxisStatus(
            ready=bool(st >> b.ready & 1),
            moving=bool(st >> b.moving & 1),
            in_position=bool(st >> b.in_position & 1),
            alarm=bool(st >> b.alarm & 1),
            homed=bool(st >> b.homed & 1),
            free=bool(self._free_bits[axis]),
            alarm_code=code,
            position_m=position,
        )

    async def status(self) -> ActuatorStatus:
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
    async def _control(self, axis: int, bit: str | None, *, urgent: bool = False) -> None:
        m = self.map
        unit, addr = m.addr(axis, "control")
        value = (m.bit("control", bit) if bit else 0) | (m.bit("control", "free") if self._free_bits[axis] else 0)
        await self.write(unit, addr, [value], urgent=urgent)

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

        async def one(i: int) -> None:
            while True:
                try:
                    await self._control(i, "stop", urgent=True)
                    break
                except DeviceError as exc:
                    errors[i] = f"stop not sent ({exc})"
                    await asyncio.sleep(self.backoff_s)
            while True:
                try:
                    s = await self.read_axis(i)
                    if not s.moving:
                        confirmed[i] = True
                        return
                    errors[i] = "still reads moving"
                except DeviceError as exc:
                    errors[i] = f"not read back ({exc})"
                await asyncio.sleep(max(self.poll_s, 0.001))

        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.stop_deadline_s):
                await asyncio.gather(*(one(i) for i in range(n)))
        if not all(confirmed):
            axes = tuple(i + 1 for i in range(n) if not confirmed[i])
            why = "; ".join(f"axis {i + 1}: {errors.get(i, 'no answer')}" for i in range(n) if not confirmed[i])
            raise StopNotConfirmedError(
                f"stop NOT confirmed within {self.stop_deadline_s:.1f} s at {self.endpoint} (axes {list(axes)}): "
                f"motion may NOT have stopped; use the emergency stop. {why}",
                axes=axes,
            )
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
            self._free_bits[i] = int(bool(free))
            await self._control(i, None)

    async def _cleanup_stop(self, exc: BaseException) -> None:
        """After a failed or cancelled move or homing: stop; an unconfirmed stop is the error that matters."""
        not_stopped = await self._stop_quietly()
        if not_stopped is not None and not isinstance(exc, asyncio.CancelledError):
            raise StopNotConfirmedError(f"{exc}; then {not_stopped}", axes=not_stopped.axes) from exc

    async def home(self, timeout_s: float | None = None) -> None:
        st = await self.status()
        self._raise_alarms(st)
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
        try:
            await self._start_move(target, speeds)

            def arrived(s: ActuatorStatus) -> bool:
                return s.in_position and bool(np.all(np.abs(s.positions - target) <= self.in_position_m))

            st = await self._wait(arrived, timeout, "move")
            if self.settle_s > 0:
                await asyncio.sleep(self.settle_s)
                st = await self.status()
                self._raise_alarms(st)
            return st.positions
        except BaseException as exc:
            await self._cleanup_stop(exc)
            raise

    async def _start_move(self, target: np.ndarray, speeds: np.ndarray) -> None:
        m = self.map
        for i in range(self.n_axes):
            unit, _ = m.addr(i, "target")
            off = m.axes[i].offset
            tregs = m.to_regs32(m.m_to_counts(target[i]))
            sregs = m.to_regs32(m.speed_to_counts(speeds[i]))
            if m.start_mode == "target_write":
                await self.write(unit, off + m.speed, sregs)
                await self.write(unit, off + m.target, tregs)
            elif m.speed == m.target + 2 and m.control == m.target + 4:
                await self.write(unit, off + m.target, [*tregs, *sregs, m.bit("control", "start")])
            else:
                await self.write(unit, off + m.speed, sregs)
                await self.write(unit, off + m.target, tregs)
                await self._control(i, "start")

    async def _wait(self, done, timeout_s: float, what: str) -> ActuatorStatus:
        t_end = time.monotonic() + timeout_s
        while True:
            st = await self.status()
            self._raise_alarms(st)
            if done(st):
                return st
            if time.monotonic() > t_end:
                raise DeviceTimeoutError(
                    f"{what} did not complete within {timeout_s:.2f} s; axes at "
                    f"{np.round(st.positions * 1e3, 3).tolist()} mm; stopped"
                )
            await asyncio.sleep(self.poll_s)


def _log_unretrieved(task: asyncio.Task) -> None:
    """A stop whose caller was cancelled: log its outcome."""
    if not task.cancelled() and (exc := task.exception()) is not None:
        log.error("stop: %s", exc)
