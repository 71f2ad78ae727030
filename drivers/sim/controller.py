"""A simulated multi-axis controller (four axes for the I4) that is a real Modbus server (pymodbus 3.16 SimDevice
actions): one axis per register-map axis, each driving the mechanism's axis of the same index.

It serves a :class:`drivers.devices.registermap.RegisterMap` (the default map unless told otherwise) over
TCP on loopback (``ModbusTcpServer``) or with RTU framing over a socket (``ModbusSerialServer`` with
``port="socket://127.0.0.1:P"``) or a pty. Every request runs the device action first: it brings the
shared :class:`~drivers.sim.mechanism.Mechanism` up to date, refreshes the read-only registers
(status, actual position, alarm code) and applies the control bits of a write.

As strict as a real drive: a write of one register (FC6) is answered with the exact echo of the
request (pymodbus builds that reply by reading the register back after the write, and the control
register clears itself, so it would echo 0); a request for a unit id the controller does not serve is
answered with exception 0x0B (gateway target failed to respond) and an unsupported function with 0x01,
without a traceback; the communication watchdog (``watchdog_s``, 0 = off) that stops a move when no
request came for ``watchdog_s`` puts the stopped axes in alarm :data:`ALARM_WATCHDOG`, so that nobody
reads "in position, no alarm" at a position that is not the target.

Fault injection (:class:`Faults`, for tests): exception replies, dropped replies, a cut connection,
and, through :mod:`drivers.sim.faultproxy` (TCP proxies in front of the
server), delayed, dropped, duplicated replies and a gateway sharing one serial line. Delays are not
injected by sleeping inside an action: the server keeps one pending PDU per connection and a reply
delayed there can leave with the next request's transaction id.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.devices.registermap import ALARM_WATCHDOG, DEFAULT_MAP, RegisterMap
from drivers.sim.mechanism import Mechanism

log = logging.getLogger(__name__)

__all__ = ["ALARM_WATCHDOG", "AsciiServer", "Faults", "FreezeFront", "Request", "SimController", "StrictContext"]


class StrictContext:
    """The server's datastore as a real drive answers: FC6 echoed exactly, unknown units refused with 0x0B
    (gateway target failed to respond; pymodbus' own path for them logs an error with a frame dump, or a
    traceback for SimDevice servers), unsupported functions with 0x01. Wraps pymodbus' ``SimCore``."""

    def __init__(self, core) -> None:
        self.core = core
        self._echo: tuple[int, int, list[int]] | None = None

    def device_ids(self) -> list[int]:
        return self.core.device_ids()

    def _unknown(self, device_id: int) -> bool:
        if device_id in self.core.devices:
            return False
        log.debug("request for unit %d, which this controller does not serve: exception 0x0B", device_id)
        return True

    async def async_setValues(self, device_id: int, func_code: int, address: int, values):
        self._echo = None
        if self._unknown(device_id):
            return ExcCodes.GATEWAY_NO_RESPONSE
        request = [int(v) for v in (values if isinstance(values, list) else [values])]  # before the action edits it
        try:
            rc = await self.core.async_setValues(device_id, func_code, address, values)
        except AttributeError:  # "Datastore, not supported function code"
            return ExcCodes.ILLEGAL_FUNCTION
        if func_code == 6 and rc is None:
            # pymodbus answers FC6 with the register read back after the write; a drive echoes the request
            self._echo = (device_id, address, request)
        return rc

    async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1):
        if self._unknown(device_id):
            return ExcCodes.GATEWAY_NO_RESPONSE
        echo, self._echo = self._echo, None
        if func_code == 6 and echo is not None and echo[:2] == (device_id, address):
            return echo[2]
        try:
            return await self.core.async_getValues(device_id, func_code, address, count)
        except AttributeError:
            return ExcCodes.ILLEGAL_FUNCTION


@dataclass
class Faults:
    """Counters of faults still to inject (each use decrements); set them from a test."""

    exception_code: int = 0  # reply with this Modbus exception code ...
    exception_count: int = 0  # ... to this many requests
    drop_replies: int = 0  # swallow this many replies
    duplicate_replies: int = 0  # send this many replies twice


def apply_control(ax, bits: int, target_m: float, speed_m_s: float, now: float, cb) -> None:
    """Apply control bits (free, stop, reset, home, start; in that order) to one simulated axis."""
    free = bool(bits & (1 << cb.free))
    if free != ax.free:
        ax.set_free(free, now)
    if bits & (1 << cb.stop):
        ax.stop(now)
    if bits & (1 << cb.reset):
        ax.reset(now)
    if bits & (1 << cb.home):
        ax.home(now)
    if bits & (1 << cb.start):
        ax.start(target_m, speed_m_s, now)


def status_word(ax, sb) -> int:
    st = 0
    if not ax.free and not ax.alarm_code:
        st |= 1 << sb.ready
    if ax.moving:
        st |= 1 << sb.moving
    if ax.in_position():
        st |= 1 << sb.in_position
    if ax.alarm_code:
        st |= 1 << sb.alarm
    if ax.homed:
        st |= 1 << sb.homed
    return st


class SimController:
    """Modbus front end of a :class:`Mechanism` for one register map."""

    def __init__(self, mechanism: Mechanism, regmap: RegisterMap = DEFAULT_MAP, watchdog_s: float = 0.5) -> None:
        if watchdog_s < 0:
            raise ValueError(f"watchdog_s must be >= 0 (0 = off), got {watchdog_s}")
        if len(regmap.axes) != len(mechanism.axes):
            raise ValueError(
                f"the register map has {len(regmap.axes)} axes but the simulated mechanism {len(mechanism.axes)}"
            )
        self.mechanism = mechanism
        self.watchdog_s = float(watchdog_s)
        self.frozen = False  # a FreezeFront has stopped the controller (its watchdog does not run either)
        self._watchdog_task: asyncio.Task | None = None
        self.map = regmap
        self.faults = Faults()
        self.requests = 0
        self.writes = 0  # write requests that reached an axis (FC6/FC16)
        self._servers: list = []
        # unit -> list of (axis index, offset)
        self._units: dict[int, list[tuple[int, int]]] = {}
        for i, a in enumerate(regmap.axes):
            self._units.setdefault(a.unit, []).append((i, a.offset))

    # -- devices --------------------------------------------------------------------------------
    def devices(self) -> list[SimDevice]:
        m = self.map
        rw = {m.target, m.target + 1, m.speed, m.speed + 1, m.control}
        ro = {m.status, m.actual, m.actual + 1, m.alarm_code}
        out = []
        for unit, axes in self._units.items():
            flags: dict[int, bool] = {}
            for _, off in axes:
                flags.update({off + r: False for r in rw})
                flags.update({off + r: True for r in ro})
            blocks: list[SimData] = []
            addrs = sorted(flags)
            start = prev = addrs[0]
            for a in [*addrs[1:], None]:
                if a is not None and a == prev + 1 and flags[a] == flags[start]:
                    prev = a
                    continue
                blocks.append(
                    SimData(start, count=prev - start + 1, values=0, datatype=DataType.REGISTERS, readonly=flags[start])
                )
                if a is not None:
                    start = prev = a
            out.append(SimDevice(unit, simdata=blocks, action=self._action_for(unit)))
        return out

    def _action_for(self, unit: int):
        axes = self._units[unit]

        async def action(
            fc: int, start_address: int, address: int, count: int, registers: list[int], set_values
        ) -> ExcCodes | None:
            return self._action(axes, fc, start_address, address, count, registers, set_values)

        return action

    def _action(self, axes, fc, start_address, address, count, registers, set_values) -> ExcCodes | None:
        self.requests += 1
        if set_values is not None:
            self.writes += 1
        self.mechanism.last_contact = self.mechanism.clock()
        f = self.faults
        if f.exception_count > 0:
            f.exception_count -= 1
            return ExcCodes(f.exception_code or ExcCodes.DEVICE_BUSY)
        m = self.map
        mech = self.mechanism
        now = mech.update()
        values = None
        if set_values is not None and fc in (6, 16, 23):
            values = list(set_values) if isinstance(set_values, list) else [set_values]

        def reg(abs_addr: int) -> int:
            if values is not None and address <= abs_addr < address + len(values):
                return int(values[abs_addr - address])
            return int(registers[abs_addr - start_address])

        with mech.lock:
            for axis, off in axes:
                ax = mech.axes[axis]
                if values is not None:
                    ctrl_addr = off + m.control
                    target_m = m.counts_to_m(m.from_regs32([reg(off + m.target), reg(off + m.target + 1)]))
                    speed = m.counts_to_speed(m.from_regs32([reg(off + m.speed), reg(off + m.speed + 1)]))
                    if address <= ctrl_addr < address + len(values):
                        bits = int(values[ctrl_addr - address])
                        cb = m.control_bits
                        apply_control(ax, bits, target_m, speed, now, cb)
                        keep = bits & (1 << cb.free)
                        set_values[ctrl_addr - address] = keep
                    elif m.start_mode == "target_write" and address <= off + m.target < address + len(values):
                        ax.start(target_m, speed, now)
                ax.update(now)
                self._refresh(registers, start_address, off, ax)
        return None

    def _refresh(self, registers, start_address, off, ax) -> None:
        m = self.map
        st = status_word(ax, m.status_bits)
        axis = self.mechanism.axes.index(ax)
        enc = m.to_regs32(m.m_to_counts(self.mechanism.encoder_m(axis)))
        registers[off + m.status - start_address] = st
        registers[off + m.actual - start_address] = enc[0]
        registers[off + m.actual + 1 - start_address] = enc[1]
        registers[off + m.alarm_code - start_address] = ax.alarm_code & 0xFFFF

    # -- fault helpers ---------------------------------------------------------------------------
    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending and self.faults.drop_replies > 0:
            self.faults.drop_replies -= 1
            return b""
        if sending and self.faults.duplicate_replies > 0:
            self.faults.duplicate_replies -= 1
            return data + data
        return data

    def cut_connections(self) -> int:
        """Abort every open client connection (the server keeps listening); returns how many."""
        n = 0
        for srv in self._servers:
            for conn in list(getattr(srv, "active_connections", {}).values()):
                with contextlib.suppress(Exception):
                    conn.transport.abort()
                    n += 1
        return n

    async def _watchdog(self) -> None:
        """Communication watchdog: a move with no request from the master for ``watchdog_s`` is stopped, and
        the axes it stopped go into alarm :data:`ALARM_WATCHDOG` (cleared by an alarm reset)."""
        mech = self.mechanism
        while True:
            await asyncio.sleep(min(0.05, self.watchdog_s / 4))
            if self.frozen:
                continue
            now = mech.update()
            if now - mech.last_contact > self.watchdog_s:
                with mech.lock:
                    for i, ax in enumerate(mech.axes):
                        if ax.moving:
                            log.warning(
                                "watchdog: no request for %.2f s during a move; axis %d stopped in alarm 0x%02X",
                                self.watchdog_s,
                                i + 1,
                                ALARM_WATCHDOG,
                            )
                            target = ax.target
                            ax.stop(now)
                            ax.target = target  # not where it was sent: never "in position" there
                            ax.alarm_code = ALARM_WATCHDOG

    def _start_watchdog(self) -> None:
        if self.watchdog_s and self._watchdog_task is None:
            self._watchdog_task = asyncio.create_task(self._watchdog())

    # -- servers --------------------------------------------------------------------------------
    async def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Start a Modbus TCP server; returns the bound (host, port) (``port=0``: a free one)."""
        if port == 0:
            port = _free_port(host)
        srv = ModbusTcpServer(self.devices(), address=(host, port), trace_packet=self._trace_packet)
        # StrictContext wraps the server's context and answers its calls (duck-typed, not a pymodbus subclass)
        srv.context = StrictContext(srv.context)  # type: ignore[assignment]
        await srv.serve_forever(background=True)
        self._servers.append(srv)
        self._start_watchdog()
        return host, port

    async def serve_rtu(self, port: str | None = None, baudrate: int = 115200) -> str:
        """Start a Modbus RTU server; ``port`` is a serial device (e.g. a pty) or ``None`` for RTU over a
        loopback socket. Returns the pyserial URL/device a client opens."""
        if port is None:
            tcp_port = _free_port("127.0.0.1")
            port = f"socket://127.0.0.1:{tcp_port}"
        srv = ModbusSerialServer(
            self.devices(), framer=FramerType.RTU, port=port, baudrate=baudrate, trace_packet=self._trace_packet
        )
        # StrictContext wraps the server's context and answers its calls (duck-typed, not a pymodbus subclass)
        srv.context = StrictContext(srv.context)  # type: ignore[assignment]
        await srv.serve_forever(background=True)
        self._servers.append(srv)
        self._start_watchdog()
        return port

    async def shutdown(self) -> None:
        if self._watchdog_task is not None:
            self._watchdog_task.cancel()
            with contextlib.suppress(BaseException):
                await self._watchdog_task
            self._watchdog_task = None
        for srv in self._servers:
            with contextlib.suppress(Exception):
                await srv.shutdown()
        self._servers.clear()


def _free_port(host: str = "127.0.0.1") -> int:
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class AsciiServer:
    """The simulated controller's serial ASCII front end (protocol in :mod:`drivers.devices.serial_ascii`), on a
    loopback TCP socket (a client opens it as the pyserial URL ``socket://127.0.0.1:P``)."""

    def __init__(self, mechanism: Mechanism) -> None:
        self.mechanism = mechanism
        #: faults: the next N replies lost (the command executed), the next N request lines lost before the
        #: controller (never executed), the next N replies preceded by line noise
        self.drop_replies = 0
        self.drop_requests = 0
        self.garble_replies = 0
        #: a verb (``MOVE``) after whose execution the controller answers nothing more (a controller that stalls)
        self.mute_after: str | None = None
        #: commands executed, by verb (``MOVE``, ``CTRL``, ``STAT?``, ...)
        self.executed: collections.Counter[str] = collections.Counter()
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._handle, host, port)
        return self._server.sockets[0].getsockname()[:2]

    def reply(self, line: str) -> str:
        from drivers.devices.registermap import ControlBits, StatusBits

        seq, _, rest = line.strip().partition(" ")
        if not seq.startswith("#"):
            return "#? ERR 1 framing: expected #SEQ CMD"
        cmd, *args = rest.split()
        mech = self.mechanism
        now = mech.update()
        mech.last_contact = now
        try:
            with mech.lock:
                if cmd == "ID?":
                    out = "OK I4ASCII 1"
                elif cmd == "STAT?":
                    vals = []
                    for i, ax in enumerate(mech.axes):
                        ax.update(now)
                        vals += [status_word(ax, StatusBits()), round(mech.encoder_m(i) * 1e6), ax.alarm_code]
                    out = "OK " + " ".join(map(str, vals))
                elif cmd == "MOVE" and len(args) == 8:
                    for i, ax in enumerate(mech.axes):
                        ax.start(int(args[i]) / 1e6, int(args[4 + i]) / 1e6, now)
                    out = "OK"
                elif cmd == "CTRL" and len(args) == 2 and args[0] in "1234":
                    ax = mech.axes[int(args[0]) - 1]
                    bits = int(args[1])
                    apply_control(ax, bits, ax.target, 0.0, now, ControlBits())
                    out = "OK"
                else:
                    out = f"ERR 2 unknown command or arguments: {rest[:40]}"
        except ValueError:
            out = "ERR 3 bad number"
        return f"{seq} {out}"

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            while line := await reader.readline():
                if self.drop_requests > 0:
                    self.drop_requests -= 1
                    continue
                text = line.decode(errors="replace")
                verb = text.split()[1] if len(text.split()) > 1 else "?"
                self.executed[verb] += 1
                out = self.reply(text)
                if self.mute_after is not None and verb == self.mute_after:
                    self.drop_replies = 10**9
                if self.drop_replies > 0:
                    self.drop_replies -= 1
                    continue
                if self.garble_replies > 0:
                    self.garble_replies -= 1
                    writer.write(b"\x15\xfe garbage\n")
                writer.write(out.encode() + b"\r\n")
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            self._writers.discard(writer)
            with contextlib.suppress(Exception):
                writer.close()

    async def close(self) -> None:
        for w in list(self._writers):
            with contextlib.suppress(Exception):
                w.transport.abort()
        if self._server is not None:
            self._server.close()


@dataclass(frozen=True)
class Request:
    """A Modbus request as the controller receives it: unit, function code, first register, and the values of a
    write (``values``) or the register count of a read (``count``)."""

    unit: int
    function: int
    address: int
    count: int
    values: tuple[int, ...] = ()

    @property
    def is_write(self) -> bool:
        return self.function in (6, 16)

    def writes(self, register: int) -> bool:
        """Whether this request writes ``register`` (absolute address)."""
        return self.is_write and self.address <= register < self.address + len(self.values)


def _split_request(buf: bytes, framing: str) -> tuple[bytes, Request | None, bytes] | None:
    """One whole request at the head of ``buf`` -> (its bytes, what it asks, the rest); None: more bytes needed."""
    if framing == "tcp":
        if len(buf) < 8:
            return None
        length = int.from_bytes(buf[4:6], "big")
        if len(buf) < 6 + length:
            return None
        frame, rest = buf[: 6 + length], buf[6 + length :]
        return frame, _parse_pdu(frame[6], frame[7:]), rest
    if len(buf) < 2:
        return None
    fc = buf[1]
    n = (9 + buf[6] if len(buf) >= 7 else None) if fc == 16 else 8
    if n is None or len(buf) < n:
        return None
    return buf[:n], _parse_pdu(buf[0], buf[2 : n - 2], fc), buf[n:]


def _parse_pdu(unit: int, body: bytes, fc: int | None = None) -> Request | None:
    """``body``: the PDU after the function code (RTU: ``fc`` given) or including it (TCP)."""
    if fc is None:
        fc, body = body[0], body[1:]
    if len(body) < 4:
        return None
    address, count = int.from_bytes(body[0:2], "big"), int.from_bytes(body[2:4], "big")
    if fc == 6:
        return Request(unit, fc, address, 1, (count,))
    if fc == 16:
        regs = body[5 : 5 + 2 * count]
        return Request(
            unit, fc, address, count, tuple(int.from_bytes(regs[k : k + 2], "big") for k in range(0, len(regs), 2))
        )
    return Request(unit, fc, address, count)


class _FrontConnection:
    def __init__(self, number: int) -> None:
        self.number = number
        self.frames: asyncio.Queue[tuple[bytes, Request | None, bool] | None] = asyncio.Queue()
        self.turn = asyncio.Event()  # released after a freeze
        self.replied = asyncio.Event()
        self.last: Request | None = None  # the request whose reply is awaited
        self.held = 0  # requests that waited out a freeze
        self.lose_reply = False  # the reply to the request on its way is lost


class FreezeFront:
    """The simulated controller frozen like a stalled PLC or a SIGSTOPped process, while the kernel keeps accepting.

    A front door (loopback TCP, the controller's framing: ``"tcp"`` Modbus TCP, ``"rtu"`` RTU over TCP) in front of
    one of the controller's servers (``upstream``). Normally it passes each request on and its reply back, one at
    a time per connection. While frozen it serves nothing: connections are still accepted and requests buffered
    (as the kernel does for a stopped process), the controller's watchdog is stopped too (its process is); then
    it executes every buffered request, connection after connection (``order``: ``"newest"`` first, the worst
    case for a master that sent a stop on a new connection after a command on an old one, or ``"oldest"``), each
    connection's in the order sent, and serves on. :meth:`freeze` freezes now; :meth:`freeze_on` freezes when a
    request matching a predicate arrives (``when="before"``: it is buffered) or once it has been answered
    (``"after"``). ``executed_late``: the requests executed after a freeze ended, in order. :meth:`lose_on` loses
    one request, or its reply.
    """

    def __init__(
        self, controller: SimController, upstream: tuple[str, int], *, framing: str = "tcp", order: str = "newest"
    ) -> None:
        if framing not in ("tcp", "rtu") or order not in ("newest", "oldest"):
            raise ValueError(
                f"framing must be 'tcp' or 'rtu' and order 'newest' or 'oldest', got {framing!r}, {order!r}"
            )
        self.controller, self.upstream, self.framing, self.order = controller, upstream, framing, order
        self.frozen = False
        self.freezes = 0
        self.executed_late: list[Request | None] = []
        self._trigger: tuple[Callable[[Request], bool], float, str] | None = None
        self._lose: tuple[Callable[[Request], bool], str] | None = None
        self.lost: list[tuple[str, Request]] = []  # requests lost, or whose reply was
        self._waiting: list[_FrontConnection] = []
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._count = 0
        self._thawed = asyncio.Event()
        self._thawed.set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._handle, host, port)
        return self._server.sockets[0].getsockname()[:2]

    def freeze(self, seconds: float) -> None:
        """Stop serving now for ``seconds``; then execute what was buffered, and serve on."""
        if self.frozen:
            return
        self.frozen = True
        self.freezes += 1
        self._thawed.clear()
        self.controller.frozen = True
        log.warning("controller frozen for %.2f s (requests buffered)", seconds)
        self._spawn(self._thaw_after(seconds))

    def freeze_on(self, match: Callable[[Request], bool], seconds: float, *, when: str = "before") -> None:
        """Freeze for ``seconds`` at the first request that ``match`` accepts: before it is executed, or after."""
        if when not in ("before", "after"):
            raise ValueError(f"when must be 'before' or 'after', got {when!r}")
        self._trigger = (match, float(seconds), when)

    def lose_on(self, match: Callable[[Request], bool], *, what: str = "request") -> None:
        """Lose the next request that ``match`` accepts (``what="request"``: it never reaches the controller, as a
        frame lost on a serial line) or its reply (``"reply"``: executed, the answer lost)."""
        if what not in ("request", "reply"):
            raise ValueError(f"what must be 'request' or 'reply', got {what!r}")
        self._lose = (match, what)

    def _spawn(self, coro) -> None:
        t = asyncio.create_task(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)

    async def _thaw_after(self, seconds: float) -> None:
        await asyncio.sleep(seconds)
        self.frozen = False
        ctl = self.controller
        ctl.frozen = False
        ctl.mechanism.last_contact = ctl.mechanism.clock()  # its watchdog did not run meanwhile
        while self._waiting:  # connection after connection; what arrives meanwhile on a waiting one waits too
            conn = self._waiting.pop() if self.order == "newest" else self._waiting.pop(0)
            conn.turn.set()
            while conn.held:  # its buffered requests are executed, in order
                await asyncio.sleep(0.002)
        self._thawed.set()
        log.warning("controller thawed: %d buffered requests executed late", len(self.executed_late))

    def _hold(self, conn: _FrontConnection) -> bool:
        """Whether a request arriving now on ``conn`` waits: frozen, or thawing and ``conn`` not yet served."""
        if not (self.frozen or (not self._thawed.is_set() and not conn.turn.is_set())):
            return False
        conn.held += 1
        if conn not in self._waiting:
            conn.turn.clear()
            self._waiting.append(conn)
        return True

    def _check_trigger(self, req: Request | None, when: str) -> None:
        if self._trigger is None or req is None:
            return
        match, seconds, at = self._trigger
        if at == when and match(req):
            self._trigger = None
            self.freeze(seconds)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._count += 1
        conn = _FrontConnection(self._count)
        self._writers.add(writer)
        try:
            ur, uw = await asyncio.open_connection(*self.upstream)
        except OSError:
            writer.close()
            return
        self._writers.add(uw)
        forward = asyncio.create_task(self._forward(conn, uw))
        back = asyncio.create_task(self._back(conn, ur, writer))
        buf = b""
        with contextlib.suppress(ConnectionError, OSError):
            while data := await reader.read(65536):
                buf += data
                while (got := _split_request(buf, self.framing)) is not None:
                    frame, req, buf = got
                    await conn.frames.put((frame, req, self._hold(conn)))
        await conn.frames.put(None)  # the client has gone: what it sent is still executed (a FIN, not a reset)
        await forward
        back.cancel()
        with contextlib.suppress(BaseException):
            await back
        for w in (uw, writer):
            w.close()
            self._writers.discard(w)

    async def _forward(self, conn: _FrontConnection, uw: asyncio.StreamWriter) -> None:
        while (item := await conn.frames.get()) is not None:
            frame, req, late = item
            self._check_trigger(req, "before")
            if not late and self.frozen:  # the trigger froze it just now
                late = self._hold(conn)
            if late:  # buffered: executed once the freeze is over, this connection's turn come
                await conn.turn.wait()
            conn.last, conn.replied, conn.lose_reply = req, asyncio.Event(), False
            if self._lose is not None and req is not None and not late and self._lose[0](req):
                what = self._lose[1]
                self._lose = None
                self.lost.append((what, req))
                if what == "request":
                    continue
                conn.lose_reply = True
            with contextlib.suppress(ConnectionError, OSError):
                uw.write(frame)
                await uw.drain()
            if late:
                self.executed_late.append(req)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(conn.replied.wait(), 0.5)
            if late:
                conn.held -= 1

    async def _back(self, conn: _FrontConnection, ur: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError, OSError):
            while data := await ur.read(65536):
                if conn.lose_reply:
                    conn.lose_reply = False
                elif not writer.is_closing():
                    writer.write(data)
                conn.replied.set()
                self._check_trigger(conn.last, "after")

    async def close(self) -> None:
        for w in list(self._writers):
            with contextlib.suppress(Exception):
                w.transport.abort()
        for t in list(self._tasks):
            t.cancel()
        if self._server is not None:
            self._server.close()
