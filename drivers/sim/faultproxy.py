"""Real TCP fault proxies in front of the simulated controller: the link faults a Modbus master meets.

* :class:`FaultProxy`: one upstream connection per client connection (a Modbus TCP device, or a serial device
  server with one port per client). Replies (server -> client chunks) can be delayed, dropped or duplicated
  (the copy a little later), and connections cut.
* :class:`SerialGateway`: several TCP clients share ONE serial line (one upstream connection to the controller's
  RTU server), as a serial device server or a Modbus TCP/RTU gateway does: requests are put on the line one at
  a time (the next after the reply, or after the gateway's own ``line_timeout_s``), and bytes from the line go
  to the client whose request is on the line (the last one that sent one), else (``route="open"``, a serial
  device server) to the newest open connection: a late or duplicated reply is handed to whoever asks next,
  which is the hazard a master must survive. ``client_framing="rtu"``: clients speak RTU over TCP
  (transparent); ``"tcp"``: clients speak Modbus TCP and the gateway converts, giving a reply the
  transaction id of the request it waits for. With a ``line_timeout_s`` shorter than the injected delays this is
  the Modbus TCP/RTU gateway of the field whose serial response timeout is shorter than the drives' late replies:
  a reply that comes after the gateway gave up is handed to the next request on the line, with that request's
  transaction id (tests/drivers/test_link_faults.py, transport ``gateway``).

Duplicates: ``LinkFaults.duplicate_after_s`` sets how late a copy follows its original (the fault matrix: up to
50 ms, as RTU links and serial device servers that repeat a frame do).

The same :class:`LinkFaults` drive both; randomness is seeded. The faults apply to replies only (a request
always reaches the controller), so what the master reads can be compared with the simulated mechanism.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import struct
from collections import Counter
from dataclasses import dataclass

from pymodbus.framer import FramerRTU


@dataclass
class LinkFaults:
    """Faults applied to each reply. ``*_count``: the next N replies; ``*_prob``: each reply with this
    probability (seeded). Delays are drawn uniformly in ``delay_s``; a duplicate follows its original after
    ``duplicate_after_s``. ``cut_prob``: after a reply, every client connection is cut."""

    delay_s: tuple[float, float] = (0.25, 0.45)
    delay_count: int = 0
    delay_prob: float = 0.0
    drop_count: int = 0
    drop_prob: float = 0.0
    duplicate_count: int = 0
    duplicate_prob: float = 0.0
    duplicate_after_s: tuple[float, float] = (0.001, 0.02)
    cut_prob: float = 0.0


class _Faulty:
    def __init__(self, seed: int) -> None:
        self.faults = LinkFaults()
        self.rng = random.Random(seed)
        self.stats: Counter[str] = Counter()

    def plan(self, data: bytes) -> tuple[list[tuple[float, bytes]], bool]:
        """Deliveries ``[(delay s, bytes)]`` of one reply, and whether to cut the connections after it."""
        f, r = self.faults, self.rng
        self.stats["replies"] += 1
        if f.drop_count > 0 or (f.drop_prob and r.random() < f.drop_prob):
            f.drop_count = max(0, f.drop_count - 1)
            self.stats["dropped"] += 1
            return [], False
        delay = 0.0
        if f.delay_count > 0 or (f.delay_prob and r.random() < f.delay_prob):
            f.delay_count = max(0, f.delay_count - 1)
            delay = r.uniform(*f.delay_s)
            self.stats["delayed"] += 1
        out = [(delay, data)]
        if f.duplicate_count > 0 or (f.duplicate_prob and r.random() < f.duplicate_prob):
            f.duplicate_count = max(0, f.duplicate_count - 1)
            out.append((delay + r.uniform(*f.duplicate_after_s), data))
            self.stats["duplicated"] += 1
        cut = bool(f.cut_prob and r.random() < f.cut_prob)
        return out, cut


class FaultProxy(_Faulty):
    """A TCP proxy on loopback in front of ``target``: each client connection gets its own upstream one;
    replies are delayed, dropped, duplicated as :attr:`faults` says; :meth:`cut` aborts every connection."""

    def __init__(self, target: tuple[str, int], *, seed: int = 0) -> None:
        super().__init__(seed)
        self.target = target
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._timers: set[asyncio.TimerHandle] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._handle, host, port)
        return self._server.sockets[0].getsockname()[:2]

    def _later(self, delay: float, dst: asyncio.StreamWriter, data: bytes) -> None:
        def send() -> None:
            if not dst.is_closing():
                dst.write(data)

        if delay <= 0:
            send()
            return
        handle = asyncio.get_running_loop().call_later(delay, send)
        self._timers.add(handle)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            ur, uw = await asyncio.open_connection(*self.target)
        except OSError:
            writer.close()
            return
        self._writers |= {writer, uw}

        async def up() -> None:
            with contextlib.suppress(ConnectionError, OSError):
                while data := await reader.read(65536):
                    uw.write(data)
                    await uw.drain()
            uw.close()

        async def down() -> None:
            with contextlib.suppress(ConnectionError, OSError):
                while data := await ur.read(65536):
                    deliveries, cut = self.plan(data)
                    for delay, chunk in deliveries:
                        self._later(delay, writer, chunk)
                    if cut:
                        self.cut()
                        break
            writer.close()

        try:
            await asyncio.gather(up(), down())
        finally:
            self._writers -= {writer, uw}

    def cut(self) -> None:
        self.stats["cuts"] += 1
        for w in list(self._writers):
            with contextlib.suppress(Exception):
                w.transport.abort()
        self._writers.clear()

    async def close(self) -> None:
        for h in self._timers:
            h.cancel()
        self.cut()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)


class _Client:
    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.tid = 0  # Modbus TCP: transaction id of the client's request on the line

    @property
    def open(self) -> bool:
        return not self.writer.is_closing()


async def cancel_and_wait(tasks: list[asyncio.Task], rounds: int = 20, wait_s: float = 0.5) -> None:
    """Cancel ``tasks`` and wait until they have ended, cancelling again those that swallowed it.

    Python 3.11's ``asyncio.wait_for`` drops a cancellation that arrives as the awaited future completes
    (CPython gh-86296): a task looping around ``wait_for`` (the gateway's line master) then goes on, and awaiting it
    after one ``cancel()`` hung a test for 15 minutes. The next cancellation reaches it at its next await. Gives up
    after ``rounds`` attempts (a task that never ends is left behind, not waited for forever).
    """
    pending = {t for t in tasks if not t.done()}
    for _ in range(rounds):
        if not pending:
            return
        for t in pending:
            t.cancel()
        _, pending = await asyncio.wait(pending, timeout=wait_s)


class SerialGateway(_Faulty):
    """Several TCP clients sharing ONE serial line to the controller's RTU server ``line`` (host, port).

    ``line_timeout_s``: how long the gateway waits for a reply before it puts the next request on the line.
    ``route``: where bytes from the line go when the client whose request is on the line has gone:
    ``"open"`` to the newest open connection (a serial device server: the hazard of a master that reconnects),
    ``"requester"`` nowhere (a Modbus gateway).
    """

    def __init__(
        self,
        line: tuple[str, int],
        *,
        client_framing: str = "rtu",
        line_timeout_s: float = 0.1,
        route: str = "open",
        seed: int = 0,
    ) -> None:
        if client_framing not in ("rtu", "tcp"):
            raise ValueError(f"client_framing must be 'rtu' or 'tcp', got {client_framing!r}")
        if route not in ("open", "requester"):
            raise ValueError(f"route must be 'open' or 'requester', got {route!r}")
        self.route = route
        super().__init__(seed)
        self.line = line
        self.client_framing = client_framing
        self.line_timeout_s = float(line_timeout_s)
        self._server: asyncio.base_events.Server | None = None
        self._clients: list[_Client] = []
        self._queue: asyncio.Queue[tuple[_Client, bytes]] = asyncio.Queue()
        self._current: _Client | None = None  # whose request is (or was last) on the line
        self._answered = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        self._timers: set[asyncio.TimerHandle] = set()
        self._line_writer: asyncio.StreamWriter | None = None

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        lr, lw = await asyncio.open_connection(*self.line)
        self._line_writer = lw
        self._tasks = [asyncio.create_task(self._line_reader(lr)), asyncio.create_task(self._line_master())]
        self._server = await asyncio.start_server(self._handle, host, port)
        return self._server.sockets[0].getsockname()[:2]

    # -- clients -> line ---------------------------------------------------------------------------------
    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = _Client(writer)
        self._clients.append(client)
        buf = b""
        try:
            while data := await reader.read(65536):
                buf += data
                while frame := self._split(buf):
                    req, buf = frame
                    await self._queue.put((client, req))
        except (ConnectionError, OSError):
            pass
        finally:
            with contextlib.suppress(ValueError):
                self._clients.remove(client)
            writer.close()

    def _split(self, buf: bytes) -> tuple[bytes, bytes] | None:
        """One whole request from the client's stream -> (RTU frame for the line, rest); None: need more."""
        if self.client_framing == "tcp":
            if len(buf) < 7:
                return None
            tid, _, length = struct.unpack(">HHH", buf[:6])
            if len(buf) < 6 + length:
                return None
            adu, rest = buf[6 : 6 + length], buf[6 + length :]  # unit + PDU
            frame = adu + FramerRTU.compute_CRC(adu).to_bytes(2, "big")
            return struct.pack(">H", tid) + frame, rest  # the tid rides along to the line master
        # RTU over TCP: a client sends whole frames (read/write requests); take the chunk as it came
        return (buf, b"") if buf else None

    async def _line_master(self) -> None:
        while True:
            client, req = await self._queue.get()
            if not client.open:
                continue
            if self.client_framing == "tcp":
                client.tid, req = struct.unpack(">H", req[:2])[0], req[2:]
            self._current = client
            self._answered.clear()
            assert self._line_writer is not None  # opened before this task is started
            self._line_writer.write(req)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._answered.wait(), self.line_timeout_s)

    # -- line -> clients ---------------------------------------------------------------------------------
    def _target(self) -> _Client | None:
        if self._current is not None and self._current.open:
            return self._current
        if self.route == "requester":
            return None  # a Modbus gateway drops a reply whose requester has gone
        return next((c for c in reversed(self._clients) if c.open), None)  # a serial server's open connection

    def _arrive(self, data: bytes) -> None:
        """Bytes appear on the line (now): the request on the line is answered; the bytes go to its client."""
        self._answered.set()
        client = self._target()
        if client is None:
            self.stats["lost"] += 1
            return
        if self.client_framing == "tcp":
            if len(data) < 4 or not FramerRTU.check_CRC(data[:-2], int.from_bytes(data[-2:], "big")):
                self.stats["garbled"] += 1
                return
            adu = data[:-2]
            data = struct.pack(">HHH", client.tid, 0, len(adu)) + adu
        client.writer.write(data)

    async def _line_reader(self, reader: asyncio.StreamReader) -> None:
        loop = asyncio.get_running_loop()
        with contextlib.suppress(ConnectionError, OSError):
            while data := await reader.read(65536):
                deliveries, cut = self.plan(data)
                for delay, chunk in deliveries:
                    if delay <= 0:
                        self._arrive(chunk)
                    else:
                        self._timers.add(loop.call_later(delay, self._arrive, chunk))
                if cut:
                    self.cut()

    def cut(self) -> None:
        """Abort every client connection (the serial line stays)."""
        self.stats["cuts"] += 1
        for c in list(self._clients):
            with contextlib.suppress(Exception):
                c.writer.transport.abort()

    async def close(self) -> None:
        for h in self._timers:
            h.cancel()
        self.cut()
        await cancel_and_wait(self._tasks)
        if self._line_writer is not None:
            self._line_writer.close()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
