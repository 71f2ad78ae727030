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

A reply whose sequence number is not the request's is a stale or stray line and is discarded; every
position read must be plausible (:meth:`drivers.modbus.ModbusActuators.check_reading`); a line
that does not parse is a framing error; both lead to a retry after the buffers are flushed. No reply
within the timeout is retried, then raises :class:`~drivers.errors.DeviceTimeoutError`.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

import numpy as np

from .errors import DeviceConnectionError, DeviceTimeoutError, MissingExtraError, ProtocolError
from .interfaces import ActuatorStatus, AxisStatus
from .modbus import ModbusActuators
from .registermap import DEFAULT_MAP


class SerialAsciiActuators(ModbusActuators):
    """:class:`drivers.interfaces.Actuators` over the ASCII protocol above (move/wait/stop logic shared with
    the Modbus driver)."""

    def __init__(
        self, url: str, *, baudrate: int = 115200, timeout_s: float = 0.5, retries: int = 3, **kw: Any
    ) -> None:
        super().__init__(transport="tcp", timeout_s=timeout_s, retries=retries, **kw)
        self.url = url
        self.baudrate = int(baudrate)
        self._ser = None
        self._seq = 0
        self.stats.update(stale=0, framing=0)

    @property
    def endpoint(self) -> str:
        return f"{self.url} (ASCII)"

    # -- link ----------------------------------------------------------------------------------------
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

    def _transact(self, command: str) -> list[str]:
        import serial

        last = ""
        for attempt in range(self.retries + 1):
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
            raise DeviceConnectionError(f"serial controller at {self.url}: {last}, after {self.retries + 1} attempts")
        raise DeviceTimeoutError(f"serial controller at {self.url}: {last}, after {self.retries + 1} attempts")

    async def command(self, command: str) -> list[str]:
        async with self._lock:
            return await asyncio.to_thread(self._transact, command)

    async def connect(self) -> None:
        await asyncio.to_thread(self._open_serial)
        await self.command("ID?")
        await self.status()

    async def close(self) -> None:
        self._close_serial()

    # -- hooks used by the shared move/home/wait logic ---------------------------------------------------
    async def status(self) -> ActuatorStatus:
        t_request = time.monotonic()
        v = await self.command("STAT?")
        if len(v) != 12:
            raise ProtocolError(f"STAT? gave {len(v)} values, expected 12")
        b = DEFAULT_MAP.status_bits
        axes = []
        for i in range(4):
            st, pos, code = int(v[3 * i]), int(v[3 * i + 1]), int(v[3 * i + 2])
            self.check_reading(i, pos / 1e6, t_request)  # plausible, else ProtocolError (nothing moves on it)
            axes.append(
                AxisStatus(
                    ready=bool(st >> b.ready & 1),
                    moving=bool(st >> b.moving & 1),
                    in_position=bool(st >> b.in_position & 1),
                    alarm=bool(st >> b.alarm & 1),
                    homed=bool(st >> b.homed & 1),
                    free=bool(self._free_bits[i]),
                    alarm_code=code,
                    position_m=pos / 1e6,
                )
            )
        return ActuatorStatus(tuple(axes))

    async def read_axis(self, axis: int) -> AxisStatus:
        return (await self.status()).axes[axis]

    async def _control(self, axis: int, bit: str | None, *, urgent: bool = False) -> None:
        m = DEFAULT_MAP
        value = (m.bit("control", bit) if bit else 0) | (m.bit("control", "free") if self._free_bits[axis] else 0)
        await self.command(f"CTRL {axis + 1} {value}")

    async def _start_move(self, target: np.ndarray, speeds: np.ndarray) -> None:
        t = [round(x * 1e6) for x in target]
        v = [max(1, round(x * 1e6)) for x in speeds]
        await self.command("MOVE " + " ".join(map(str, t + v)))
