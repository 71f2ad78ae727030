"""Actuators over Modbus (pymodbus 3.16 async client; TCP, RTU on a serial line, RTU over TCP).

:class:`ModbusLink` is the :class:`drivers.devices.links.AxisLink` that speaks Modbus (register map
:class:`drivers.devices.registermap.RegisterMap`); :class:`ModbusActuators` is the axis controller
(:class:`drivers.devices.axes.AxisController`: limits, move timeouts, plausible readings, confirmed stop, cancellation)
over it.

Stale replies. A reply is taken as the answer to a request only when it matches it: function code, unit id,
register count or echoed address/count, and on Modbus TCP the transaction id (which a TCP/RTU gateway gives a late
serial reply of another request, so it proves little). What a reply shows of its request is its *shape* (unit,
function, a read's register count, a write's address and count). A request that got no reply in time (or was
cancelled, lost its link, got a stale reply) leaves its reply possibly on the way, on every transport: no request of
its shape goes out for ``late_reply_guard_s``, and its link is not reused (a fresh one is opened). A reply may also
be duplicated on its way: no request of an axis read's or state read's shape goes out within
``duplicate_window_s`` after its reply (others: ``flush_s``). Axis reads choose among every window of the axis'
registers that covers the read-back (six lengths in the default map) the one whose shape is free soonest, so that
the guards rarely wait. Bytes that arrive while no request is outstanding are counted (``stats["unrequested"]``)
and discarded; on RTU framing the next request waits for ``flush_s`` of quiet.

Motion commands (a start, a target that starts the move, homing) are sent once. When no reply proves one taken,
the link stays on its connection (a controller serves a connection in order; pymodbus never closes it on its own):
it reads the axis' target, speed, control and status registers back there, within ``motion_confirm_s``, and sends
the command again, on that connection, only when that state proves it was not taken. Otherwise
:class:`drivers.devices.links.MotionNotConfirmedError`; the stop that follows goes out on the same connection, after the
command. A connection lost with a command's fate open sets ``motion_in_doubt``: the axis controller stops every
axis, confirmed, before it reports or moves again.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from calib.model.parameters import I4Parameters
from drivers.acquisition.metrics import CountingStats
from drivers.devices.axes import AxisController, AxisSettings, alarm_message, check_targets
from drivers.devices.interfaces import AxisStatus, SoftLimitsM
from drivers.devices.links import Command, MotionNotConfirmedError, SafetySettings, decode_status
from drivers.devices.registermap import DEFAULT_MAP, RegisterMap
from drivers.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError

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


class _NoAnswerError(Exception):
    """One attempt got no usable answer (internal): ``why`` for the error message."""

    def __init__(self, why: str, *, lost: bool = False) -> None:
        self.why, self.lost = why, lost
        super().__init__(why)


class _MotionUnansweredError(DeviceTimeoutError):
    """A motion command went out and no reply proved it taken (internal; ``lost``: its connection is gone)."""

    def __init__(self, message: str, *, lost: bool) -> None:
        self.lost = lost
        super().__init__(message)


@dataclass(frozen=True)
class ModbusLinkSettings:
    """How a :class:`ModbusLink` reaches the controller and retries (each field documented there): the transport
    (``"tcp"``, ``"rtu"``, ``"rtu-tcp"``) and its endpoint, the register map, the reply timeout, retries and back-off
    (s), the late-reply guard and the RTU flush (s), varied read windows."""

    transport: str = "tcp"
    host: str = "127.0.0.1"
    port: int = 502
    serial_port: str | None = None
    baudrate: int = 115200
    regmap: RegisterMap = DEFAULT_MAP
    timeout_s: float = 0.5
    retries: int = 3
    backoff_s: float = 0.02
    backoff_max_s: float = 1.0
    late_reply_guard_s: float | None = None
    flush_s: float = 0.01
    vary_reads: bool = True


class ModbusLink:
    """:class:`drivers.devices.links.AxisLink` over Modbus: checked, retried requests, one in flight, never a stale
    reply.

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
        Reply timeout of one request (s; capped by ``safety.watchdog_s``); attempts after the first; exponential
        back-off between attempts (s), bounded by ``backoff_max_s``.
    late_reply_guard_s:
        Every transport: after a request got no reply (timed out, cancelled, its link lost, a stale reply in its
        place), no request whose reply would look the same (its shape) goes out for this long (s), so that its late
        reply, wherever it lands, answers nothing. ``None``: ``2 * timeout_s`` (a reply up to three timeouts late).
    flush_s:
        RTU framing only: a link reopened after a fault, or that received unrequested bytes, must have been
        quiet this long (s) before the next request goes out; what arrived meanwhile is discarded.
    vary_reads:
        Read an axis through any window of its registers that covers the read-back (the status, position and alarm
        registers, widened by adjacent registers of the same axis) so that a request never has the shape of one
        whose reply may still come. ``False`` for a drive that refuses to read the others (then reads of one unit
        wait out the guards).
    safety:
        :class:`drivers.devices.links.SafetySettings` (duplicate window, motion confirmation, watchdog).
    """

    reads_every_axis = False

    def __init__(self, settings: ModbusLinkSettings | None = None, safety: SafetySettings | None = None) -> None:
        st = settings or ModbusLinkSettings()
        transport, regmap, timeout_s = st.transport, st.regmap, st.timeout_s
        if transport not in ("tcp", "rtu", "rtu-tcp"):
            raise ValueError(f"unknown Modbus transport {transport!r}")
        self.transport = transport
        self.host, self.port = st.host, int(st.port)
        self.serial_port, self.baudrate = st.serial_port, int(st.baudrate)
        self.map = regmap
        self.n_axes = len(regmap.axes)
        self.safety = safety or SafetySettings()
        self.timeout_s = float(timeout_s)
        self.retries = int(st.retries)
        self.backoff_s, self.backoff_max_s = float(st.backoff_s), float(st.backoff_max_s)
        guard = st.late_reply_guard_s
        self.late_reply_guard_s = float(2 * self.timeout_s if guard is None else guard)
        self.flush_s = float(st.flush_s)
        self.vary_reads = bool(st.vary_reads)
        wd = self.safety.watchdog_s
        #: the reply timeout in use: ``timeout_s``, capped so that a retry goes out before the drives' watchdog trips
        self.reply_timeout_s = min(self.timeout_s, max(0.8 * wd - self.backoff_s, 0.05)) if wd else self.timeout_s
        mc = self.safety.motion_confirm_s
        self.motion_confirm_s = float(4 * self.reply_timeout_s if mc is None else mc)
        self._reopen_settle = False  # RTU framing: the next link follows a fault; let it be quiet first
        self._client: _Client | None = None
        self._link = _Connection()
        self._lock = asyncio.Lock()
        #: request shape -> monotonic time before which a reply of that shape may still arrive (late or duplicated):
        #: no request of that shape goes out before (reads take another window)
        self._late: dict[tuple, float] = {}
        #: request shape -> when its last reply came (a duplicate of it may follow within a duplicate window)
        self._answered: dict[tuple, float] = {}
        #: the connection a motion command that got no reply went out on: every request stays on it (a controller
        #: serves one connection in order) until one is answered, which proves that the command was processed
        self._pin: _Connection | None = None
        #: a motion command got no reply and its connection was lost before its fate was known: it may still run
        self.motion_in_doubt = False
        self._windows = [self._read_windows(i, self._poll_registers()) for i in range(self.n_axes)]
        self._state_windows = [self._read_windows(i, self._state_registers()) for i in range(self.n_axes)]
        #: counters of this link, also summed process-wide for ``GET /metrics`` (drivers.acquisition.metrics)
        self.stats = CountingStats(
            "modbus",
            {
                "requests": 0,
                "retries": 0,
                "timeouts": 0,
                "reconnects": 0,
                "stale": 0,
                "unrequested": 0,
                "motion_unanswered": 0,
                "motion_resent": 0,
            },
        )

    @property
    def poll_interval_s(self) -> float:
        """The shortest interval (s) between two polls of every axis that the duplicate-window guard sustains with
        room to spare: a unit's reads take its read windows (one shape each) for ``duplicate_window_s`` each, so a
        poll of its axes every ``duplicate_window_s x axes / (windows - 3 x axes)`` leaves a free window for each of
        the three readings that follow a move at once (the frame's reading before and after its grab, the next
        move's check). Polled faster, a move's last polls take every window and those readings wait for one to
        free (up to the whole window); with too few windows for that (``vary_reads = false``, many axes on a unit)
        the polls are spread over the windows there are. The axis controller polls no faster
        (:meth:`drivers.devices.axes.AxisController._wait`)."""
        m = self.map
        per_unit: dict[int, int] = {}
        for i in range(self.n_axes):
            unit = m.addr(i, "status")[0]
            per_unit[unit] = per_unit.get(unit, 0) + 1
        windows = min(len(w) for w in self._windows) if self.vary_reads else 1
        axes = max(per_unit.values(), default=1)
        spare = windows - 3 * axes
        return self.safety.duplicate_window_s * axes / (spare if spare > 0 else windows)

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

        common: dict[str, Any] = dict(
            timeout=self.reply_timeout_s, retries=0, reconnect_delay=0, trace_packet=trace_packet, trace_pdu=trace_pdu
        )
        client: _Client
        if self.transport == "rtu":
            client = AsyncModbusSerialClient(
                self.serial_port or "", framer=FramerType.RTU, baudrate=self.baudrate, **common
            )
        else:
            framer = FramerType.SOCKET if self.transport == "tcp" else FramerType.RTU
            client = AsyncModbusTcpClient(self.host, port=self.port, framer=framer, **common)
        # never closed by pymodbus after unanswered requests: the driver decides (a pinned connection must stay)
        client.set_max_no_responses(1 << 30)
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

    def _fault(self) -> None:
        """Never reuse this link (a late reply may come on it); RTU framing: the next one waits for quiet first.
        A pinned link is kept (every request stays on it until one is answered)."""
        if self._pin is not None and self._pin is self._link:
            return
        self._drop()
        if self.transport in RTU_FRAMED:
            self._reopen_settle = True

    def _pin_lost(self) -> None:
        """The connection of a motion command that got no reply is gone before its fate was read back."""
        log.error(
            "Modbus controller at %s: the connection of an unanswered motion command was lost; the command may "
            "still be executed: the axes are stopped before anything else",
            self.endpoint,
        )
        self._pin = None
        self.motion_in_doubt = True
        self._fault()

    def _pinned_client(self) -> _Client | None:
        if self._pin is None:
            return None
        if self._pin is self._link and self._client is not None and self._client.connected:
            return self._client
        self._pin_lost()
        return None

    async def _ready_link(self, urgent: bool) -> _Client:
        """A link fit for the next request: the pinned one when a motion command's fate is open, else the current
        one, or a new one. RTU framing: a link that follows a fault, or got unrequested bytes, waits for quiet
        (``flush_s``) unless ``urgent`` (a stop)."""
        pinned = self._pinned_client()
        if pinned is not None:
            return pinned
        client = self._client
        if client is None or not client.connected:
            self.stats["reconnects"] += 1
            client = await self._open()  # a serial port is flushed when it opens
            if self._reopen_settle:
                self._link.last_rx = max(self._link.last_rx, time.monotonic())
                self._link.drain = True
                self._reopen_settle = False
        link = self._link
        if link.drain and self.transport in RTU_FRAMED and not urgent:
            # drain: whatever arrives unrequested (a buffered late reply, a duplicate) must be over first;
            # the request's send then discards it
            deadline = time.monotonic() + max(self.reply_timeout_s, self.flush_s) * 2
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
        self._pin = None
        self._drop()

    # -- shapes: no request whose reply may still come is asked again -------------------------------
    def _busy_for(self, shape: tuple, seconds: float) -> None:
        self._late[shape] = max(self._late.get(shape, 0.0), time.monotonic() + seconds)

    def _free_at(self, shape: tuple, window_s: float) -> float:
        """When no reply of this shape can come any more: a late one (guard) or a copy of the last (window)."""
        return max(self._late.get(shape, 0.0), self._answered.get(shape, -np.inf) + window_s)

    async def _choose(
        self,
        kind: str,
        unit: int,
        address: int,
        count_or_values: Any,
        windows: Sequence[tuple[int, int]] | None,
        window_s: float,
    ) -> tuple[int, Any, tuple]:
        """The request to send: of the ``windows`` (reads), the one whose shape is free soonest; then wait until
        no reply of that shape can still come (a late reply to an unanswered request, a duplicate of an answer)."""
        options = list(windows) if windows else [(address, count_or_values)]
        shapes = [_reply_shape(kind, unit, a, c) for a, c in options]
        free = [self._free_at(sh, window_s) for sh in shapes]
        k = min(range(len(options)), key=free.__getitem__)
        if (wait := free[k] - time.monotonic()) > 0:
            await asyncio.sleep(wait)
        return options[k][0], options[k][1], shapes[k]

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

    async def _exchange(self, client: _Client, kind: str, unit: int, address: int, cv: Any, shape: tuple) -> Any:
        """Send one request on ``client`` and return its checked reply; :class:`_NoAnswerError` when none came that is
        provably its answer (its shape stays busy for ``late_reply_guard_s``: the reply may still come)."""
        guard = self.late_reply_guard_s
        self.stats["requests"] += 1
        try:
            if kind == "read":
                rr = await client.read_holding_registers(address, count=cv, device_id=unit)
            else:
                rr = await client.write_registers(address, list(cv), device_id=unit)
        except asyncio.CancelledError:
            self._busy_for(shape, guard)  # the reply may still be on its way
            raise
        except ConnectionException as exc:
            self._busy_for(shape, guard)
            raise _NoAnswerError(f"connection lost ({exc})", lost=True) from None
        except (ModbusIOException, TimeoutError) as exc:
            self._busy_for(shape, guard)
            self.stats["timeouts"] += 1
            raise _NoAnswerError(f"no reply within {self.reply_timeout_s:.3f} s ({type(exc).__name__})") from None
        except ModbusException as exc:
            self._busy_for(shape, guard)
            raise _NoAnswerError(f"Modbus error ({exc})") from None
        task = asyncio.current_task()
        if task is not None and task.cancelling():
            # Python 3.11's wait_for (inside pymodbus) returns a reply that lands together with a
            # cancellation and drops the cancellation (CPython gh-86296): honour it here
            self._answered[shape] = time.monotonic()
            raise asyncio.CancelledError
        if problem := self._mismatch(rr, kind, unit, address, cv):
            # a late, duplicated or foreign reply: refuse it; its own reply may still come
            self.stats["stale"] += 1
            self._busy_for(shape, guard)
            log.warning("Modbus controller at %s, unit %d: stale or foreign reply: %s", self.endpoint, unit, problem)
            raise _NoAnswerError(f"stale or foreign reply: {problem}")
        self._answered[shape] = time.monotonic()  # a copy of this reply may follow
        if self._pin is self._link:
            self._pin = None  # answered on the pinned connection: everything sent before it was processed
        return rr

    async def _request(
        self,
        kind: str,
        unit: int,
        address: int,
        count_or_values: Any,
        *,
        urgent: bool = False,
        windows: Sequence[tuple[int, int]] | None = None,
        motion: bool = False,
        attempts: int | None = None,
        on: _Connection | None = None,
        window_s: float | None = None,
    ) -> Any:
        """One checked request, retried (``motion``: sent once; see :meth:`_motion_write`). ``windows``: a read of any
        of these (start, count), chosen so that no reply that may still come has its shape; the result is then
        ``(start, registers)``. ``urgent`` (a stop): no waiting for a shape or for quiet. ``on``: only on this
        connection, the pinned one (a timeout when it is gone). ``window_s``: how long after a reply of the same
        shape a copy of it may still come (default ``flush_s``; the axis reads and state reads use
        ``duplicate_window_s``)."""
        async with self._lock:
            last: str = ""
            n_attempts = 1 if motion else (self.retries + 1 if attempts is None else attempts)
            for attempt in range(n_attempts):
                if attempt:
                    self.stats["retries"] += 1
                    await asyncio.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.backoff_max_s))
                if urgent:
                    shape = _reply_shape(kind, unit, address, count_or_values)
                else:
                    dup_s = self.flush_s if window_s is None else window_s
                    address, count_or_values, shape = await self._choose(
                        kind, unit, address, count_or_values, windows, dup_s
                    )
                if on is not None and (self._pin is not on or self._pinned_client() is None):
                    last = "the connection of the command was lost"
                    break
                try:
                    client = await self._ready_link(urgent)
                except DeviceConnectionError as exc:
                    last = str(exc)
                    continue
                try:
                    rr = await self._exchange(client, kind, unit, address, count_or_values, shape)
                except asyncio.CancelledError:
                    if motion:  # its fate is open: stay on its connection (the stop goes after it, in order)
                        self._pin = self._link
                    self._fault()
                    raise
                except _NoAnswerError as exc:
                    last = exc.why
                    self._unanswered(exc, unit, motion)
                    continue
                if rr.isError():
                    last = self._exception_reply(rr, unit, address, motion)
                    continue
                if windows:
                    return address, list(rr.registers)
                return list(rr.registers) if kind == "read" else []
            if "connect" in last or "connection" in last:
                raise DeviceConnectionError(
                    f"Modbus controller at {self.endpoint}: {last}, after {n_attempts} attempts"
                )
            raise DeviceTimeoutError(
                f"Modbus controller at {self.endpoint}, unit {unit}: {last}, after {n_attempts} attempts"
            )

    def _unanswered(self, exc: _NoAnswerError, unit: int, motion: bool) -> None:
        """A request got no answer (:meth:`_exchange`): the link marked faulty, the pinned connection dropped when it
        was lost; a motion command raises :class:`_MotionUnansweredError` (never re-sent here), the others return to
        be retried."""
        if motion:
            self.stats["motion_unanswered"] += 1
            if exc.lost:
                self.motion_in_doubt = True
            else:
                self._pin = self._link  # its fate is read back on this connection, and the stop goes here
            self._fault()
            raise _MotionUnansweredError(
                f"Modbus controller at {self.endpoint}, unit {unit}: {exc.why}", lost=exc.lost
            ) from None
        if exc.lost and self._pin is self._link:
            self._pin_lost()
        self._fault()

    @staticmethod
    def _exception_reply(rr: Any, unit: int, address: int, motion: bool) -> str:
        """A Modbus exception reply: its message when it may be retried (busy codes, never a motion command), else
        :class:`~drivers.errors.ProtocolError`."""
        code = int(getattr(rr, "exception_code", 0) or 0)
        msg = f"unit {unit} register {address}: exception code {code} ({EXCEPTION_TEXT.get(code, 'unknown')})"
        if code in RETRYABLE_EXCEPTIONS and not motion:
            return msg
        raise ProtocolError(msg, exception_code=code)

    async def read(self, unit: int, address: int, count: int) -> list[int]:
        """Holding registers ``address .. address + count - 1`` of unit ``unit``, by one checked request."""
        regs: list[int] = await self._request("read", unit, address, count)
        return regs

    async def write(self, unit: int, address: int, values: list[int], *, urgent: bool = False) -> None:
        """Write ``values`` from register ``address`` of unit ``unit`` (function 16), by one checked request."""
        await self._request("write", unit, address, values, urgent=urgent)

    # -- motion commands: never re-sent blind -------------------------------------------------------
    async def _motion_write(
        self, axis: int, unit: int, address: int, values: list[int], taken: _TakenTest, label: str
    ) -> None:
        """Send a motion command (a start, a target that starts, homing) once. When no reply proves it was taken,
        read the axis' state back on the SAME connection (a controller serves a connection in order: an answer
        there proves the command was processed) and send it again only when that state proves it was not taken,
        on that connection still. Otherwise :class:`~drivers.devices.links.MotionNotConfirmedError` (the link stays on
        that connection: the stop that follows goes out after the command)."""
        what = f"axis {axis + 1}: {label} (unit {unit}, register {address})"
        for _attempt in range(self.retries + 1):
            try:
                await self._request("write", unit, address, values, motion=True)
                return
            except _MotionUnansweredError as exc:
                if exc.lost or self._pin is None:  # its connection is gone: nothing can prove its fate
                    raise MotionNotConfirmedError(
                        f"{what} got no reply ({exc}) and its connection is lost: the controller may still execute "
                        "it; not sent again",
                        axis=axis + 1,
                    ) from exc
                conn = self._link
            state = await self._read_state(axis, conn, what)
            verdict = taken(state)
            if verdict:
                log.warning("%s: no reply, but the drive's state read back shows it taken (%s)", what, state)
                return
            if self._link is not conn:
                raise MotionNotConfirmedError(
                    f"{what}: not taken, and its connection changed: not sent again", axis=axis + 1
                )
            self.stats["motion_resent"] += 1
            # answered on its connection after the command: the command's own reply, if any, came before; its shape
            # is free again on this connection
            self._late.pop(_reply_shape("write", unit, address, values), None)
            log.warning("%s: not taken (state read back on its connection: %s); sent again on it", what, state)
        raise MotionNotConfirmedError(
            f"{what}: not taken after {self.retries + 1} attempts, each read back on its connection", axis=axis + 1
        )

    async def _read_state(self, axis: int, conn: _Connection, what: str) -> AxisState:
        """The axis' command and status registers read on connection ``conn``, within ``motion_confirm_s``."""
        m = self.map
        unit, base = m.addr(axis, "target")
        base -= m.target
        windows = [(base + lo, n) for lo, n in self._state_windows[axis]]
        t_end = time.monotonic() + self.motion_confirm_s
        last = ""
        while time.monotonic() < t_end and self._pin is conn:
            try:
                start, regs = await self._request(
                    "read",
                    unit,
                    windows[0][0],
                    windows[0][1],
                    windows=windows,
                    attempts=1,
                    on=conn,
                    window_s=self.safety.duplicate_window_s,
                )
            except (DeviceTimeoutError, DeviceConnectionError) as exc:
                last = str(exc)
                continue
            return AxisState.decode(m, regs, start - base)
        raise MotionNotConfirmedError(
            f"{what} got no reply, and the drive's state could not be read back on its connection within "
            f"{self.motion_confirm_s:.2f} s ({last or 'connection lost'}): the controller may still execute it; "
            "not sent again",
            axis=axis + 1,
        )

    # -- the AxisLink ------------------------------------------------------------------------------
    def _poll_registers(self) -> set[int]:
        m = self.map
        return {m.status, m.actual, m.actual + 1, m.alarm_code}

    def _state_registers(self) -> set[int]:
        m = self.map
        return {m.target, m.target + 1, m.speed, m.speed + 1, m.control, m.status}

    def _read_windows(self, axis: int, needed: set[int]) -> list[tuple[int, int]]:
        """Every contiguous relative window (start, count) of the axis' own registers that covers ``needed``,
        shortest first: reads of a unit pick among them so that no reply that may still come has their shape."""
        m = self.map
        own = {m.target, m.target + 1, m.speed, m.speed + 1, m.control, m.status, m.actual, m.actual + 1}
        own.add(m.alarm_code)
        lo, hi = min(needed), max(needed) + 1
        if not set(range(lo, hi)) <= own:
            return [(lo, hi - lo)]  # a gap: one window (the drive is asked only what the map names)
        a = lo
        while a - 1 in own:
            a -= 1
        b = hi
        while b in own:
            b += 1
        out = [(s, e - s) for s in range(a, lo + 1) for e in range(hi, b + 1)]
        out.sort(key=lambda w: (w[1], -w[0]))
        by_length: dict[int, tuple[int, int]] = {}
        for w in out:
            by_length.setdefault(w[1], w)  # one window per length (its shape)
        return list(by_length.values())

    async def read_axis(self, axis: int) -> AxisStatus:
        """Axis ``axis`` (0..n-1): status word, encoder and alarm code by one read (``free`` left ``False``)."""
        m = self.map
        unit, base = m.addr(axis, "status")
        base -= m.status
        windows = [(base + lo, n) for lo, n in self._windows[axis][: None if self.vary_reads else 1]]
        start, regs = await self._request(
            "read", unit, windows[0][0], windows[0][1], windows=windows, window_s=self.safety.duplicate_window_s
        )
        lo = start - base
        enc = m.from_regs32(regs[m.actual - lo : m.actual - lo + 2])
        return decode_status(regs[m.status - lo], m.status_bits, m.counts_to_m(enc), regs[m.alarm_code - lo])

    async def read_axes(self, axes: Sequence[int]) -> dict[int, AxisStatus]:
        return {i: await self.read_axis(i) for i in axes}

    async def control(self, axis: int, command: Command | None, *, free: bool, urgent: bool = False) -> None:
        m = self.map
        unit, addr = m.addr(axis, "control")
        value = (m.bit("control", command) if command else 0) | (m.bit("control", "free") if free else 0)
        if command == "home":
            homing = _Taken(m, home=True)
            await self._motion_write(axis, unit, addr, [value], homing, "the homing command")
            return
        await self.write(unit, addr, [value], urgent=urgent)

    async def start_move(self, targets_m: np.ndarray, speeds_m_s: np.ndarray) -> None:
        m = self.map
        for i in range(self.n_axes):
            unit, _ = m.addr(i, "target")
            off = m.axes[i].offset
            tregs = m.to_regs32(m.m_to_counts(targets_m[i]))
            sregs = m.to_regs32(m.speed_to_counts(speeds_m_s[i]))
            taken = _Taken(m, target=tregs, speed=sregs)
            label = f"the start of the move to {targets_m[i] * 1e3:.3f} mm"
            if m.start_mode == "target_write":
                await self.write(unit, off + m.speed, sregs)
                await self._motion_write(i, unit, off + m.target, tregs, taken, label)
            elif m.speed == m.target + 2 and m.control == m.target + 4:
                values = [*tregs, *sregs, m.bit("control", "start")]
                await self._motion_write(i, unit, off + m.target, values, taken, label)
            else:
                await self.write(unit, off + m.speed, sregs)
                await self.write(unit, off + m.target, tregs)
                # never free here: a move refuses free drives
                start = [m.bit("control", "start")]
                await self._motion_write(i, unit, off + m.control, start, _Taken(m, start=True), label)


@dataclass(frozen=True)
class AxisState:
    """An axis' command and status registers as read back after a motion command got no reply."""

    target: list[int]
    speed: list[int]
    control: int
    status: int

    @classmethod
    def decode(cls, m: RegisterMap, regs: list[int], lo: int) -> AxisState:
        def at(rel: int, n: int = 1) -> list[int]:
            return [int(r) for r in regs[rel - lo : rel - lo + n]]

        return cls(at(m.target, 2), at(m.speed, 2), at(m.control)[0], at(m.status)[0])


@dataclass(frozen=True)
class _Taken:
    """Whether an axis' state read back shows a motion command taken: the target and speed it wrote (a write
    that starts the move), or the start bit's effect (moving, in position, alarm: the drive acted), or homing's."""

    m: RegisterMap
    target: list[int] | None = None
    speed: list[int] | None = None
    start: bool = False
    home: bool = False

    def __call__(self, s: AxisState) -> bool:
        bit = partial(_bit, self.m, s.status)
        if self.target is not None:
            return s.target == list(self.target) and s.speed == list(self.speed or s.speed)
        if self.home:
            return bit("moving") or bit("homed") or bit("alarm")
        # a start taken shows: the drive moving, in alarm, or the start bit still set (a drive that clears it when
        # done); an axis that already arrived reads none of them and gets the start again, which moves it nowhere
        return bool(s.control & self.m.bit("control", "start")) or bit("moving") or bit("alarm")


def _bit(m: RegisterMap, word: int, name: str) -> bool:
    return bool(word & m.bit("status", name))


_TakenTest = Callable[[AxisState], bool]


def _reply_shape(kind: str, unit: int, address: int, count_or_values: Any) -> tuple:
    """What a reply shows of its request: unit and function, and the register count of a read (its byte count)
    or the address and count of a write (its echo). Two requests of one shape cannot tell their replies apart
    (on RTU framing, and behind a gateway that hands a late serial reply to the next request)."""
    if kind == "read":
        return unit, kind, int(count_or_values)
    return unit, kind, int(address), len(count_or_values)


class ModbusActuators(AxisController):
    """:class:`drivers.devices.interfaces.Actuators` over Modbus: the axis controller over a :class:`ModbusLink`.

    Parameters
    ----------
    link:
        The link's settings (:class:`ModbusLinkSettings`); its ``backoff_s`` is also the pause before a stop is sent
        again.
    axes:
        The axis controller's motion settings (:class:`drivers.devices.axes.AxisSettings`).
    limits, nominal, workspace_check:
        The axis controller's soft limits and kinematic check (:class:`drivers.devices.axes.AxisController`).
    safety:
        :class:`drivers.devices.links.SafetySettings`, both's (duplicate window, motion confirmation, the drives'
        watchdog,
        how long a failed run keeps stopping).

    The number of axes is the register map's (``len(link.regmap.axes)``, four by default); ``limits`` must have as
    many values (default: -0.10 to 0.80 m on every axis).
    """

    def __init__(
        self,
        link: ModbusLinkSettings | None = None,
        axes: AxisSettings | None = None,
        *,
        limits: SoftLimitsM | None = None,
        nominal: I4Parameters | None = None,
        workspace_check: Callable[[np.ndarray], Any] | None = None,
        safety: SafetySettings | None = None,
    ) -> None:
        safety = safety or SafetySettings()
        link = link or ModbusLinkSettings()
        self.modbus = ModbusLink(link, safety)
        super().__init__(
            self.modbus,
            limits=limits,
            nominal=nominal,
            workspace_check=workspace_check,
            backoff_s=link.backoff_s,
            safety=safety,
            **dataclasses.asdict(axes or AxisSettings()),
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
    "ModbusLinkSettings",
    "alarm_message",
    "check_targets",
]
