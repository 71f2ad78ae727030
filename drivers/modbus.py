"""Actuators over Modbus (pymodbus 3.16 async client; TCP, RTU on a serial line, RTU over TCP).

:class:`ModbusLink` is the :class:`drivers.links.AxisLink` that speaks Modbus (register map
:class:`drivers.registermap.RegisterMap`); :class:`ModbusActuators` is the axis controller
(:class:`drivers.axes.AxisController`: limits, move timeouts, plausible readings, confirmed stop, cancellation)
over it.

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
TCP/RTU gateway alike. The read before that has the same length: a request waits until ``flush_s``
after the last reply to a request of its shape (unit, function, a read's register count, a write's
address and count), so that a copy of that reply made on the way (a gateway or serial device server
that duplicates it) has come, while nothing was asked, before a request it would answer goes out.
A stop (``urgent``) does not wait; the controller reads it back.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from calib.parameters import I4Parameters

from .axes import AxisController, alarm_message, check_targets
from .errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError
from .interfaces import AxisStatus, SoftLimitsM
from .links import Command, decode_status
from .metrics import CountingStats
from .registermap import DEFAULT_MAP, RegisterMap

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

RTU_FRAMED = ("rtu", "rtu-tcp")
_FC_READ, _FC_WRITE = 3, 16

_Client = AsyncModbusTcpClient | AsyncModbusSerialClient


class _Connection:
    """What the trace hooks of one client connection saw (a dropped client's late callbacks touch only it)."""

    def __init__(self) -> None:
        self.pending = False  # a request is out and not yet answered
        self.sent_tid = 0  # transaction id of the last request (Modbus TCP)
        self.last_rx = 0.0  # monotonic time of the last bytes received
        self.drain = False  # bytes came unrequested (or the link follows a fault): wait for quiet before a request
        self.unrequested = 0  # receptions while no request was outstanding
        self.opened = time.monotonic()


class ModbusLink:
    """:class:`drivers.links.AxisLink` over Modbus: checked, retried requests, one in flight, never a stale reply.

    Parameters
    ----------
    transport:
        ``"tcp"`` Modbus TCP, ``"rtu"`` RTU on a serial line, ``"rtu-tcp"`` RTU framing over a TCP socket (a serial
        device server or an RTU gateway).
    host, port:
        TCP endpoint (``tcp``, ``rtu-tcp``).
    serial_port, baudrate:
        Serial device for ``transport="rtu"`` (any pyserial URL works, e.g. ``socket://host:port``).
    regmap:
        The register map; the number of axes is ``len(regmap.axes)``.
    timeout_s, retries, backoff_s, backoff_max_s:
        Reply timeout of one request (s); attempts after the first; exponential back-off between attempts (s),
        bounded by ``backoff_max_s``.
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
    """

    reads_every_axis = False

    def __init__(
        self,
        *,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        serial_port: str | None = None,
        baudrate: int = 115200,
        regmap: RegisterMap = DEFAULT_MAP,
        timeout_s: float = 0.5,
        retries: int = 3,
        backoff_s: float = 0.02,
        backoff_max_s: float = 1.0,
        late_reply_guard_s: float | None = None,
        flush_s: float = 0.01,
        vary_reads: bool = True,
    ) -> None:
        if transport not in ("tcp", "rtu", "rtu-tcp"):
            raise ValueError(f"unknown Modbus transport {transport!r}")
        self.transport = transport
        self.host, self.port = host, int(port)
        self.serial_port, self.baudrate = serial_port, int(baudrate)
        self.map = regmap
        self.n_axes = len(regmap.axes)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.backoff_s, self.backoff_max_s = float(backoff_s), float(backoff_max_s)
        self.late_reply_guard_s = float(2 * self.timeout_s if late_reply_guard_s is None else late_reply_guard_s)
        self.flush_s = float(flush_s)
        self.vary_reads = bool(vary_reads)
        self._quiet_until = 0.0  # RTU framing: no new link before this monotonic time (a late reply may be on the wire)
        self._reopen_settle = False  # RTU framing: the next link follows a fault; let it be quiet first
        self._client: _Client | None = None
        self._link = _Connection()
        self._lock = asyncio.Lock()
        self._read_count: dict[int, int] = {}  # reads per unit (RTU framing: alternate the window length)
        #: when the last reply came to each request shape (unit, function, what the reply shows of the request): a
        #: request of the same shape waits until ``flush_s`` after it (a duplicate of that reply would pass for its)
        self._replied: dict[tuple, float] = {}
        self._windows = [self._read_windows(i) for i in range(self.n_axes)]
        #: counters of this link, also summed process-wide for ``GET /metrics`` (drivers.metrics)
        self.stats = CountingStats(
            "modbus", {"requests": 0, "retries": 0, "timeouts": 0, "reconnects": 0, "stale": 0, "unrequested": 0}
        )

    @property
    def endpoint(self) -> str:
        if self.transport == "rtu":
            return f"{self.serial_port} (RTU, {self.baudrate} Bd)"
        return f"{self.host}:{self.port}" + (" (RTU over TCP)" if self.transport == "rtu-tcp" else "")

    # -- connection ---------------------------------------------------------------------------
    def _new_client(self) -> tuple[_Client, _Connection]:
        link = _Connection()

        def trace_pdu(sending: bool, pdu: Any) -> Any:
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

        client: _Client
        if self.transport == "rtu":
            client = AsyncModbusSerialClient(
                self.serial_port or "",
                framer=FramerType.RTU,
                baudrate=self.baudrate,
                timeout=self.timeout_s,
                retries=0,
                reconnect_delay=0,
                trace_packet=trace_packet,
                trace_pdu=trace_pdu,
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
                trace_packet=trace_packet,
                trace_pdu=trace_pdu,
            )
        return client, link

    async def _open(self) -> _Client:
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
        return client

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

    async def _ready_link(self, urgent: bool) -> _Client:
        """A link fit for the next request. ``urgent`` (a stop): no waiting out the late-reply guard (the
        replies' checks still apply); a link opened that way is replaced before the next non-urgent request."""
        if self._client is not None and not urgent and self._link.opened < self._quiet_until:
            self._drop()  # opened during a guard for a stop: a late reply may still arrive on it
        client = self._client
        if client is None or not client.connected:
            self.stats["reconnects"] += 1
            if not urgent and (quiet := self._quiet_until - time.monotonic()) > 0:
                await asyncio.sleep(quiet)
            client = await self._open()  # a serial port is flushed when it opens
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
        return client

    async def open(self) -> None:
        """Connect, retried ``retries`` times with back-off; :class:`~drivers.errors.DeviceConnectionError`."""
        last: DeviceConnectionError | None = None
        for attempt in range(self.retries + 1):
            try:
                await self._open()
                return
            except DeviceConnectionError as exc:
                last = exc
                await asyncio.sleep(min(self.backoff_s * 2**attempt, self.backoff_max_s))
        assert last is not None
        raise last

    async def close(self) -> None:
        self._drop()

    # -- one checked request ----------------------------------------------------------------------
    def _mismatch(self, rr: Any, kind: str, unit: int, address: int, count_or_values: Any) -> str | None:
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
                shape = _reply_shape(kind, unit, address, count_or_values)
                if not urgent and (wait := self._replied.get(shape, -np.inf) + self.flush_s - time.monotonic()) > 0:
                    # a reply duplicated on its way (a gateway, a serial device server) comes within flush_s of the
                    # original: it must be over before a request it would match goes out (RTU replies name neither
                    # the register nor a transaction; a gateway may give a late serial reply the next request's id)
                    await asyncio.sleep(wait)
                try:
                    client = await self._ready_link(urgent)
                except DeviceConnectionError as exc:
                    last = str(exc)
                    continue
                self.stats["requests"] += 1
                try:
                    if kind == "read":
                        rr = await client.read_holding_registers(address, count=count_or_values, device_id=unit)
                    else:
                        rr = await client.write_registers(address, list(count_or_values), device_id=unit)
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
                self._replied[shape] = time.monotonic()
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
        """Holding registers ``address .. address + count - 1`` of unit ``unit``, by one checked request."""
        regs: list[int] = await self._request("read", unit, address, count)
        return regs

    async def write(self, unit: int, address: int, values: list[int], *, urgent: bool = False) -> None:
        """Write ``values`` from register ``address`` of unit ``unit`` (function 16), by one checked request."""
        await self._request("write", unit, address, values, urgent=urgent)

    # -- the AxisLink ------------------------------------------------------------------------------
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

    async def read_axis(self, axis: int) -> AxisStatus:
        """Axis ``axis`` (0..n-1): status word, encoder and alarm code by one read (``free`` left ``False``)."""
        m = self.map
        unit, base = m.addr(axis, "status")
        base -= m.status
        windows = [(base + lo, n) for lo, n in self._windows[axis][: 2 if self.vary_reads else 1]]
        start, regs = await self._request("read", unit, windows[0][0], windows[0][1], windows=windows)
        lo = start - base
        enc = m.from_regs32(regs[m.actual - lo : m.actual - lo + 2])
        return decode_status(regs[m.status - lo], m.status_bits, m.counts_to_m(enc), regs[m.alarm_code - lo])

    async def read_axes(self, axes: Sequence[int]) -> dict[int, AxisStatus]:
        return {i: await self.read_axis(i) for i in axes}

    async def control(self, axis: int, command: Command | None, *, free: bool, urgent: bool = False) -> None:
        m = self.map
        unit, addr = m.addr(axis, "control")
        value = (m.bit("control", command) if command else 0) | (m.bit("control", "free") if free else 0)
        await self.write(unit, addr, [value], urgent=urgent)

    async def start_move(self, targets_m: np.ndarray, speeds_m_s: np.ndarray) -> None:
        m = self.map
        for i in range(self.n_axes):
            unit, _ = m.addr(i, "target")
            off = m.axes[i].offset
            tregs = m.to_regs32(m.m_to_counts(targets_m[i]))
            sregs = m.to_regs32(m.speed_to_counts(speeds_m_s[i]))
            if m.start_mode == "target_write":
                await self.write(unit, off + m.speed, sregs)
                await self.write(unit, off + m.target, tregs)
            elif m.speed == m.target + 2 and m.control == m.target + 4:
                await self.write(unit, off + m.target, [*tregs, *sregs, m.bit("control", "start")])
            else:
                await self.write(unit, off + m.speed, sregs)
                await self.write(unit, off + m.target, tregs)
                await self.control(i, "start", free=False)  # never free here: a move refuses free drives


def _reply_shape(kind: str, unit: int, address: int, count_or_values: Any) -> tuple:
    """What a reply shows of its request: unit and function, and the register count of a read (its byte count)
    or the address and count of a write (its echo). Two requests of one shape cannot tell their replies apart
    (on RTU framing, and behind a gateway that hands a late serial reply to the next request)."""
    if kind == "read":
        return unit, kind, int(count_or_values)
    return unit, kind, int(address), len(count_or_values)


class ModbusActuators(AxisController):
    """:class:`drivers.interfaces.Actuators` over Modbus: the axis controller over a :class:`ModbusLink`.

    Parameters
    ----------
    transport, host, port, serial_port, baudrate, regmap, timeout_s, retries, backoff_s, backoff_max_s, \
late_reply_guard_s, flush_s, vary_reads:
        The link's (:class:`ModbusLink`); ``backoff_s`` is also the pause before a stop is sent again.
    limits, nominal, workspace_check, speed_m_s, accel_m_s2, poll_s, settle_s, in_position_m, move_timeout_factor, \
move_timeout_margin_s, home_timeout_s, max_speed_m_s, plausibility_margin_m, plausibility_slack_m, stop_deadline_s:
        The axis controller's (:class:`drivers.axes.AxisController`).

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
        self.modbus = ModbusLink(
            transport=transport,
            host=host,
            port=port,
            serial_port=serial_port,
            baudrate=baudrate,
            regmap=regmap,
            timeout_s=timeout_s,
            retries=retries,
            backoff_s=backoff_s,
            backoff_max_s=backoff_max_s,
            late_reply_guard_s=late_reply_guard_s,
            flush_s=flush_s,
            vary_reads=vary_reads,
        )
        super().__init__(
            self.modbus,
            limits=limits,
            nominal=nominal,
            workspace_check=workspace_check,
            speed_m_s=speed_m_s,
            accel_m_s2=accel_m_s2,
            poll_s=poll_s,
            settle_s=settle_s,
            in_position_m=in_position_m,
            move_timeout_factor=move_timeout_factor,
            move_timeout_margin_s=move_timeout_margin_s,
            home_timeout_s=home_timeout_s,
            max_speed_m_s=max_speed_m_s,
            plausibility_margin_m=plausibility_margin_m,
            plausibility_slack_m=plausibility_slack_m,
            stop_deadline_s=stop_deadline_s,
            backoff_s=backoff_s,
        )

    # the link's settings and raw register access, as before the split
    @property
    def transport(self) -> str:
        return self.modbus.transport

    @property
    def host(self) -> str:
        return self.modbus.host

    @property
    def port(self) -> int:
        return self.modbus.port

    @property
    def serial_port(self) -> str | None:
        return self.modbus.serial_port

    @property
    def baudrate(self) -> int:
        return self.modbus.baudrate

    @property
    def map(self) -> RegisterMap:
        return self.modbus.map

    @property
    def timeout_s(self) -> float:
        return self.modbus.timeout_s

    @property
    def retries(self) -> int:
        return self.modbus.retries

    @property
    def late_reply_guard_s(self) -> float:
        return self.modbus.late_reply_guard_s

    @property
    def _client(self) -> _Client | None:
        """The link's current pymodbus client (tests reach its trace hooks)."""
        return self.modbus._client

    async def read(self, unit: int, address: int, count: int) -> list[int]:
        """Holding registers of a unit, by one checked request (:meth:`ModbusLink.read`)."""
        return await self.modbus.read(unit, address, count)

    async def write(self, unit: int, address: int, values: list[int], *, urgent: bool = False) -> None:
        """Write registers of a unit, by one checked request (:meth:`ModbusLink.write`)."""
        await self.modbus.write(unit, address, values, urgent=urgent)


__all__ = [
    "EXCEPTION_TEXT",
    "RETRYABLE_EXCEPTIONS",
    "RTU_FRAMED",
    "ModbusActuators",
    "ModbusLink",
    "alarm_message",
    "check_targets",
]
