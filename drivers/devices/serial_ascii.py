"""Actuators over a simple serial ASCII line protocol (pyserial), for controllers that speak one.

Protocol (7-bit ASCII, one request line, exactly one reply line; ``\\n`` or ``\\r\\n`` ends a line)::

    request:  #<seq> <COMMAND> [args...]\\n          seq: 0..9999, chosen by the host, echoed by the controller
    reply:    #<seq> OK [values...]\\r\\n
              #<seq> ERR <code> <text>\\r\\n

    ID?                                   -> OK <model> <protocol version>
    STAT?                                 -> OK st1 pos1 alarm1 st2 pos2 alarm2 st3 pos3 alarm3 st4 pos4 alarm4
                                             st: status word, bits as the Modbus map (0 ready, 1 moving,
                                             2 in position, 3 alarm, 4 homed); pos: counts (1 um); alarm: code
    MOVE t1 t2 t3 t4 v1 v2 v3 v4          -> OK   targets in counts, speeds in counts/s; starts the move
    CTRL <axis 1..4> <bits>               -> OK   control bits as the Modbus map (1 start, 2 stop, 4 home,
                                                  8 alarm reset, 16 free while set)

:class:`SerialAsciiLink` is the :class:`drivers.devices.links.AxisLink` that speaks it; :class:`SerialAsciiActuators` is
the
axis controller (:class:`drivers.devices.axes.AxisController`) over it. A reply whose sequence number is not the
request's
is a stale or stray line and is discarded; every position read must be plausible
(:meth:`drivers.devices.axes.AxisController.check_reading`); a line that does not parse is a framing error; both lead to
a
retry after the buffers are flushed. No reply within the timeout is retried, then raises
:class:`~drivers.errors.DeviceTimeoutError`.

A motion command (``MOVE``, ``CTRL`` with the home bit) is never sent again blind: it goes out once; when no reply
proves it was taken, the link reads ``STAT?`` (the controller answers one line at a time, in order, so a reply to
the later ``STAT?`` proves the command was processed if it arrived) and sends the command again only when every
axis it should have set moving is still idle away from its target (it never arrived); otherwise the move is taken,
or, when even ``STAT?`` gets no answer, :class:`~drivers.devices.links.MotionNotConfirmedError` says it may still
execute.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from drivers.acquisition.metrics import CountingStats
from drivers.devices.axes import AxisController
from drivers.devices.interfaces import AxisStatus
from drivers.devices.links import Command, MotionNotConfirmedError, decode_status
from drivers.devices.registermap import DEFAULT_MAP
from drivers.errors import DeviceConnectionError, DeviceTimeoutError, MissingExtraError, ProtocolError

#: the protocol's axis count (STAT? reports four axes, MOVE takes four targets)
ASCII_AXES = 4


class SerialAsciiLink:
    """:class:`drivers.devices.links.AxisLink` over the ASCII protocol above: one request line, one reply line, retried.

    Parameters
    ----------
    url:
        pyserial port or URL (``/dev/ttyACM0``, ``socket://HOST:PORT``).
    baudrate, timeout_s, retries, backoff_s, backoff_max_s:
        Line speed; reply timeout of one request (s); attempts after the first, with exponential back-off (s)
        bounded by ``backoff_max_s``.
    """

    n_axes = ASCII_AXES
    reads_every_axis = True  # STAT? reports every axis

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = 115200,
        timeout_s: float = 0.5,
        retries: int = 3,
        backoff_s: float = 0.02,
        backoff_max_s: float = 1.0,
    ) -> None:
        self.url = url
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.backoff_s, self.backoff_max_s = float(backoff_s), float(backoff_max_s)
        self._ser: Any = None
        self._seq = 0
        self._lock = asyncio.Lock()
        #: counters (summed with the Modbus driver's under ``modbus_*`` in ``GET /metrics``, as before the split)
        self.stats = CountingStats(
            "modbus",
            {"requests": 0, "retries": 0, "timeouts": 0, "reconnects": 0, "stale": 0, "unrequested": 0, "framing": 0},
        )

    @property
    def endpoint(self) -> str:
        return f"{self.url} (ASCII)"

    def _open_serial(self) -> None:
        try:
            import serial
        except ImportError:
            raise MissingExtraError("pyserial", "serial") from None
        try:
            self._ser = serial.serial_for_url(
                self.url, baudrate=self.baudrate, timeout=self.timeout_s, write_timeout=self.timeout_s
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceConnectionError(f"cannot open serial port {self.url}: {exc}") from None

    def _close_serial(self) -> None:
        if self._ser is not None:
            with contextlib.suppress(Exception):
                self._ser.close()
            self._ser = None

    def _transact(self, command: str, retries: int | None = None) -> list[str]:
        import serial

        retries = self.retries if retries is None else retries
        last = ""
        for attempt in range(retries + 1):
            if attempt:
                self.stats["retries"] += 1
                time.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.backoff_max_s))
            try:
                if self._ser is None:
                    self._open_serial()
                self._seq = (self._seq + 1) % 10000
                tag = f"#{self._seq}"
                self._ser.reset_input_buffer()
                self._ser.write(f"{tag} {command}\n".encode("ascii"))
                self.stats["requests"] += 1
                deadline = time.monotonic() + self.timeout_s
                while True:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        last = f"no reply within {self.timeout_s:.3f} s"
                        break
                    self._ser.timeout = left
                    raw = self._ser.readline()
                    if not raw:
                        continue
                    if not raw.endswith(b"\n"):
                        last = f"no reply within {self.timeout_s:.3f} s (partial line {raw[:40]!r})"
                        break
                    try:
                        line = raw.decode("ascii").strip()
                    except UnicodeDecodeError:
                        self.stats["framing"] += 1
                        last = f"framing error: {raw[:40]!r}"
                        continue
                    seq, _, rest = line.partition(" ")
                    if seq != tag:
                        self.stats["stale"] += 1  # a late reply to an earlier request, or noise
                        last = f"stray line {line[:40]!r}"
                        continue
                    status, *values = rest.split()
                    if status == "OK":
                        return values
                    if status == "ERR":
                        code = int(values[0]) if values and values[0].isdigit() else None
                        raise ProtocolError(
                            f"controller refused {command.split()[0]}: {' '.join(values)}", exception_code=code
                        )
                    self.stats["framing"] += 1
                    last = f"framing error: {line[:40]!r}"
            except (serial.SerialException, OSError) as exc:
                last = f"link error ({exc})"
                self._close_serial()
            except DeviceConnectionError as exc:
                last = str(exc)
        if "link error" in last or "cannot open" in last:
            raise DeviceConnectionError(f"serial controller at {self.url}: {last}, after {retries + 1} attempts")
        raise DeviceTimeoutError(f"serial controller at {self.url}: {last}, after {retries + 1} attempts")

    async def command(self, command: str) -> list[str]:
        """Send one command line, return the reply's values (one request at a time, retried)."""
        async with self._lock:
            return await asyncio.to_thread(self._transact, command)

    async def motion_command(self, command: str, taken: Callable[[dict[int, AxisStatus]], bool | None]) -> None:
        """Send a motion command once; without a reply, learn from ``STAT?`` whether it was taken.

        ``taken(status)`` says from the axes' status whether the command was taken (True), never arrived (False),
        or cannot be told (None). Sent again once, only on False; a second silence, None, or no answer to
        ``STAT?`` raise :class:`~drivers.devices.links.MotionNotConfirmedError` (the command may still execute).
        """
        verb = command.split()[0]
        for attempt in range(2):
            async with self._lock:
                try:
                    await asyncio.to_thread(self._transact, command, 0)
                    return
                except DeviceTimeoutError as exc:
                    self.stats["timeouts"] += 1
                    why = str(exc)
            try:
                status = await self.read_axes(range(ASCII_AXES))
            except DeviceTimeoutError as exc:
                raise MotionNotConfirmedError(
                    f"{verb} got no reply ({why}) and the state could not be read back ({exc}): the controller may "
                    "still execute it; not sent again",
                    axis=1,
                ) from None
            verdict = taken(status)
            if verdict:
                return
            if verdict is None or attempt == 1:
                break
            self.stats["retries"] += 1  # proven not taken: sent again once
        raise MotionNotConfirmedError(
            f"{verb} got no reply ({why}) and the axes' state does not prove it was taken or not: the controller "
            "may still execute it; not sent again",
            axis=1,
        )

    async def open(self) -> None:
        await asyncio.to_thread(self._open_serial)
        await self.command("ID?")

    async def close(self) -> None:
        self._close_serial()

    async def read_axes(self, axes: Sequence[int]) -> dict[int, AxisStatus]:
        """Every axis, by one ``STAT?``."""
        v = await self.command("STAT?")
        if len(v) != 3 * ASCII_AXES:
            raise ProtocolError(f"STAT? gave {len(v)} values, expected {3 * ASCII_AXES}")
        out = {}
        for i in range(ASCII_AXES):
            st, pos, code = int(v[3 * i]), int(v[3 * i + 1]), int(v[3 * i + 2])
            out[i] = decode_status(st, DEFAULT_MAP.status_bits, pos / 1e6, code)
        return out

    async def control(self, axis: int, command: Command | None, *, free: bool, urgent: bool = False) -> None:
        m = DEFAULT_MAP
        value = (m.bit("control", command) if command else 0) | (m.bit("control", "free") if free else 0)
        line = f"CTRL {axis + 1} {value}"
        if command == "home":  # a motion: never sent again blind

            def homing(status: dict[int, AxisStatus]) -> bool:
                return status[axis].moving or status[axis].homed

            await self.motion_command(line, homing)
            return
        await self.command(line)  # stop, alarm reset, free: idempotent, retried

    async def start_move(self, targets_m: np.ndarray, speeds_m_s: np.ndarray) -> None:
        t = [round(x * 1e6) for x in targets_m]
        v = [max(1, round(x * 1e6)) for x in speeds_m_s]
        await self.motion_command("MOVE " + " ".join(map(str, t + v)), _move_taken(np.asarray(targets_m)))


def _move_taken(targets_m: np.ndarray, tol_m: float = 5e-6) -> Callable[[dict[int, AxisStatus]], bool | None]:
    """Whether a ``MOVE`` to ``targets_m`` (m) was taken, from the axes' status: any axis moving or every axis at
    its target -> taken; every axis idle and one away from its target -> never arrived."""

    def taken(status: dict[int, AxisStatus]) -> bool | None:
        if any(st.moving for st in status.values()):
            return True
        away = [i for i, st in status.items() if abs(st.position_m - float(targets_m[i])) > tol_m]
        if not away:
            return True
        return False if all(not status[i].alarm for i in away) else None

    return taken


class SerialAsciiActuators(AxisController):
    """:class:`drivers.devices.interfaces.Actuators` over the ASCII protocol above: the axis controller
    (:class:`drivers.devices.axes.AxisController`, its keywords in ``kw``) over a :class:`SerialAsciiLink`.

    ``backoff_s`` and ``backoff_max_s`` in ``kw`` go to the link too (``backoff_s`` is also the pause before a stop
    is sent again).
    """

    def __init__(
        self, url: str, *, baudrate: int = 115200, timeout_s: float = 0.5, retries: int = 3, **kw: Any
    ) -> None:
        backoff = {k: kw[k] for k in ("backoff_s", "backoff_max_s") if k in kw}
        kw.pop("backoff_max_s", None)
        self.ascii = SerialAsciiLink(url, baudrate=baudrate, timeout_s=timeout_s, retries=retries, **backoff)
        super().__init__(self.ascii, **kw)

    @property
    def url(self) -> str:
        return self.ascii.url

    @property
    def baudrate(self) -> int:
        return self.ascii.baudrate

    @property
    def timeout_s(self) -> float:
        return self.ascii.timeout_s

    @property
    def retries(self) -> int:
        return self.ascii.retries

    async def command(self, command: str) -> list[str]:
        """Send one command line, return the reply's values (:meth:`SerialAsciiLink.command`)."""
        return await self.ascii.command(command)


__all__ = ["ASCII_AXES", "SerialAsciiActuators", "SerialAsciiLink"]
