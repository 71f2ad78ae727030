"""Actuators over Modbus (pymodbus 3.16 async client; TCP, RTU on a serial line, RTU over TCP).

Every reply is checked (exception code, register count, unit id, echoed address); a request that
gets no reply in time is retried on a *fresh* connection (the old one is closed), so a late reply
can never be taken for the answer to another request; reconnection uses a bounded exponential
back-off. One request is in flight at a time. On a serial line (RTU) a fresh connection is the same
wire, and an RTU reply carries neither a transaction id nor the register address: after a timeout the
port stays closed for ``late_reply_guard_s`` and is flushed when it reopens, so a reply up to
``timeout_s + late_reply_guard_s`` late is discarded rather than taken for the next request's answer.

A move follows one shape: check the targets (per-axis soft limits, then the nominal kinematic
model), compute a timeout from the distances and speeds, write target + speed + start, poll until
every axis is in position, and stop every axis on any error, timeout or cancellation.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
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
)
from .interfaces import ActuatorStatus, AxisStatus, SoftLimitsM
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


def check_targets(q: Any, limits: SoftLimitsM, nominal: I4Parameters | None) -> np.ndarray:
    """Refuse targets outside the per-axis soft limits, or that the kinematic model cannot reach."""
    qv = np.asarray(q, dtype=np.float64).reshape(-1)
    if qv.shape != (4,) or not np.all(np.isfinite(qv)):
        raise LimitError(f"a target needs four finite values in metres, got {q!r}")
    for i in range(4):
        lo, hi = limits.q_min[i], limits.q_max[i]
        if not lo <= qv[i] <= hi:
            bound = lo if qv[i] < lo else hi
            raise LimitError(
                f"q{i + 1} = {qv[i] * 1e3:.3f} mm is outside the soft limits [{lo * 1e3:.1f}, "
                f"{hi * 1e3:.1f}] mm by {abs(qv[i] - bound) * 1e3:.3f} mm; nothing moved",
                axis=i + 1,
            )
    if nominal is not None:
        try:
            dkm(nominal, qv)
        except UnreachableError as exc:
            raise LimitError(
                f"target {np.round(qv * 1e3, 3).tolist()} mm is outside the workspace of the "
                f"kinematic model ({exc}); nothing moved"
            ) from None
    return qv


class ModbusActuators:
    """:class:`drivers.interfaces.Actuators` over Modbus.

    Parameters
    ----------
    host, port:
        TCP endpoint (``transport="tcp"`` Modbus TCP, ``"rtu-tcp"`` RTU framing over a TCP socket).
    serial_port, baudrate:
        Serial device for ``transport="rtu"`` (any pyserial URL works, e.g. ``socket://host:port``).
    speed_m_s, accel_m_s2:
        Move speed of the axis that travels furthest (the others are scaled to arrive together) and the
        drive's acceleration, used only for the move timeout.
    late_reply_guard_s:
        RTU only: after a request timed out, the serial port stays closed this long (s) before it is
        reopened and flushed, so that the late reply is discarded. ``None``: ``timeout_s``.
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
    ) -> None:
        if transport not in ("tcp", "rtu", "rtu-tcp"):
            raise ValueError(f"unknown Modbus transport {transport!r}")
        self.transport = transport
        self.host, self.port = host, int(port)
        self.serial_port, self.baudrate = serial_port, int(baudrate)
        self.map = regmap
        self.limits = limits or SoftLimitsM()
        self.nominal = nominal
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
        self.late_reply_guard_s = float(self.timeout_s if late_reply_guard_s is None else late_reply_guard_s)
        self._quiet_until = 0.0  # RTU: no new link before this monotonic time (a late reply may be on the wire)
        self._client: AsyncModbusTcpClient | AsyncModbusSerialClient | None = None
        self._lock = asyncio.Lock()
        self._free_bits = [0, 0, 0, 0]
        self.stats = {"requests": 0, "retries": 0, "reconnects": 0}

    @property
    def endpoint(self) -> str:
        if self.transport == "rtu":
            return f"{self.serial_port} (RTU, {self.baudrate} Bd)"
        return f"{self.host}:{self.port}" + (" (RTU over TCP)" if self.transport == "rtu-tcp" else "")

    # -- connection ---------------------------------------------------------------------------
    def _new_client(self):
        if self.transport == "rtu":
            return AsyncModbusSerialClient(
                self.serial_port,
                framer=FramerType.RTU,
                baudrate=self.baudrate,
                timeout=self.timeout_s,
                retries=0,
                reconnect_delay=0,
            )
        framer = FramerType.SOCKET if self.transport == "tcp" else FramerType.RTU
        return AsyncModbusTcpClient(
            self.host, port=self.port, framer=framer, timeout=self.timeout_s, retries=0, reconnect_delay=0
        )

    async def _open(self) -> None:
        self._drop()
        client = self._new_client()
        try:
            ok = await asyncio.wait_for(client.connect(), timeout=max(self.timeout_s, 0.5) * 2)
        except (TimeoutError, OSError, ModbusException):
            ok = False
        if not ok:
            with contextlib.suppress(Exception):
                client.close()
            raise DeviceConnectionError(f"cannot connect to the Modbus controller at {self.endpoint}")
        self._client = client

    def _drop(self) -> None:
        if self._client is not None:
            with contextlib.suppress(Exception):
                self._client.close()
            self._client = None

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
        await self.status()  # every axis answers

    async def close(self) -> None:
        self._drop()

    async def __aenter__(self) -> ModbusActuators:
        await self.connect()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    # -- one checked request ----------------------------------------------------------------------
    async def _request(self, kind: str, unit: int, address: int, count_or_values: Any) -> list[int]:
        async with self._lock:
            last: str = ""
            for attempt in range(self.retries + 1):
                if attempt:
                    self.stats["retries"] += 1
                    await asyncio.sleep(min(self.backoff_s * 2 ** (attempt - 1), self.backoff_max_s))
                try:
                    if self._client is None or not self._client.connected:
                        self.stats["reconnects"] += 1
                        if (quiet := self._quiet_until - time.monotonic()) > 0:
                            await asyncio.sleep(quiet)
                        await self._open()  # a serial port is flushed when it opens
                    self.stats["requests"] += 1
                    if kind == "read":
                        rr = await self._client.read_holding_registers(address, count=count_or_values, device_id=unit)
                    else:
                        rr = await self._client.write_registers(address, list(count_or_values), device_id=unit)
                except DeviceConnectionError as exc:
                    last = str(exc)
                    continue
                except ConnectionException as exc:
                    last = f"connection lost ({exc})"
                    self._drop()
                    continue
                except (ModbusIOException, TimeoutError) as exc:
                    # no reply in time: never reuse this link, a late reply could pair with the next request
                    last = f"no reply within {self.timeout_s:.3f} s ({type(exc).__name__})"
                    self._drop()
                    if self.transport == "rtu":  # same wire: let the late reply land on a closed port
                        self._quiet_until = time.monotonic() + self.late_reply_guard_s
                    continue
                except ModbusException as exc:
                    last = f"Modbus error ({exc})"
                    self._drop()
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
                if getattr(rr, "dev_id", unit) not in (unit, 0):
                    last = f"reply from unit {rr.dev_id} to a request for unit {unit}"
                    self._drop()
                    continue
                if kind == "read":
                    regs = list(rr.registers)
                    if len(regs) != count_or_values:
                        last = f"reply with {len(regs)} registers to a request for {count_or_values}"
                        self._drop()
                        continue
                    return regs
                n = len(count_or_values)
                if getattr(rr, "address", address) != address or getattr(rr, "count", n) != n:
                    last = f"write echo (address {rr.address}, count {rr.count}) does not match the request"
                    self._drop()
                    continue
                return []
            if "connect" in last or "connection" in last:
                raise DeviceConnectionError(
                    f"Modbus controller at {self.endpoint}: {last}, after {self.retries + 1} attempts"
                )
            raise DeviceTimeoutError(
                f"Modbus controller at {self.endpoint}, unit {unit}: {last}, after {self.retries + 1} attempts"
            )

    async def read(self, unit: int, address: int, count: int) -> list[int]:
        return await self._request("read", unit, address, count)

    async def write(self, unit: int, address: int, values: list[int]) -> None:
        await self._request("write", unit, address, values)

    # -- status ------------------------------------------------------------------------------------
    async def read_axis(self, axis: int) -> AxisStatus:
        m = self.map
        lo, n = m.readback_window()
        unit, base = m.addr(axis, "status")
        base = base - m.status + lo
        regs = await self.read(unit, base, n)
        st = regs[m.status - lo]
        enc = m.from_regs32(regs[m.actual - lo : m.actual - lo + 2])
        code = regs[m.alarm_code - lo]
        b = m.status_bits
        return AxisStatus(
            ready=bool(st >> b.ready & 1),
            moving=bool(st >> b.moving & 1),
            in_position=bool(st >> b.in_position & 1),
            alarm=bool(st >> b.alarm & 1),
            homed=bool(st >> b.homed & 1),
            free=bool(self._free_bits[axis]),
            alarm_code=code,
            position_m=m.counts_to_m(enc),
        )

    async def status(self) -> ActuatorStatus:
        return ActuatorStatus(tuple([await self.read_axis(i) for i in range(4)]))

    async def read_encoders(self) -> np.ndarray:
        return (await self.status()).positions

    def _raise_alarms(self, st: ActuatorStatus) -> None:
        alarms = st.alarms
        if alarms:
            axis, code = next(iter(alarms.items()))
            more = "" if len(alarms) == 1 else f" (and axes {sorted(set(alarms) - {axis})})"
            raise AlarmError(alarm_message(axis, code) + more, code=code, axis=axis)

    # -- control -------------------------------------------------------------------------------------
    async def _control(self, axis: int, bit: str | None) -> None:
        m = self.map
        unit, addr = m.addr(axis, "control")
        value = (m.bit("control", bit) if bit else 0) | (m.bit("control", "free") if self._free_bits[axis] else 0)
        await self.write(unit, addr, [value])

    async def stop(self) -> None:
        """Stop every axis; tries all of them even when one fails, then raises the first failure."""
        first: Exception | None = None
        for i in range(4):
            try:
                await self._control(i, "stop")
            except DeviceError as exc:
                first = first or exc
        if first is not None:
            raise first

    async def _stop_quietly(self) -> None:
        try:
            await asyncio.shield(self.stop())
        except Exception as exc:  # the original error matters more
            log.error("stop after a failed move also failed: %s", exc)

    async def reset_alarms(self) -> None:
        for i in range(4):
            await self._control(i, "reset")

    async def set_free(self, free: bool) -> None:
        for i in range(4):
            self._free_bits[i] = int(bool(free))
            await self._control(i, None)

    async def home(self, timeout_s: float | None = None) -> None:
        st = await self.status()
        self._raise_alarms(st)
        try:
            for i in range(4):
                await self._control(i, "home")
            await self._wait(lambda s: s.homed and not s.moving, timeout_s or self.home_timeout_s, "homing")
        except BaseException:
            await self._stop_quietly()
            raise

    def move_timeout(self, distance_m: np.ndarray, speeds_m_s: np.ndarray) -> float:
        t = [d / v + v / self.accel_m_s2 for d, v in zip(distance_m, speeds_m_s, strict=True) if d > 0]
        return max(t, default=0.0) * self.move_timeout_factor + self.move_timeout_margin_s

    async def move(self, q: Any, timeout_s: float | None = None, speed_m_s: float | None = None) -> np.ndarray:
        target = check_targets(q, self.limits, self.nominal)
        st = await self.status()
        self._raise_alarms(st)
        if any(a.free for a in st.axes):
            raise DeviceError("drives are free (de-energised); re-energise them before a move")
        dist = np.abs(target - st.positions)
        v = float(speed_m_s or self.speed_m_s)
        dmax = float(dist.max())
        speeds = np.full(4, v) if dmax == 0 else np.maximum(v * dist / dmax, v * 1e-3)
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
        except BaseException:
            await self._stop_quietly()
            raise

    async def _start_move(self, target: np.ndarray, speeds: np.ndarray) -> None:
        m = self.map
        for i in range(4):
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
