"""What the axis controller needs of a motion controller's protocol: the :class:`AxisLink`, and nothing more.

A link speaks one protocol to the motion controller (Modbus: :class:`drivers.devices.modbus.ModbusLink`; the serial
ASCII
protocol: :class:`drivers.devices.serial_ascii.SerialAsciiLink`). It reads the axes (status bits, encoder position in
metres,
alarm code), writes the targets and speeds of every axis at once, and writes one axis' control word (start, stop,
home, alarm reset, free). It owns its transport's reliability (retries, reply matching, stale-reply guards) and its
request counters. The motion logic over any link (soft limits, move timeouts, waiting, plausible readings, confirmed
stop, cancellation) is :class:`drivers.devices.axes.AxisController`'s.

Positions are metres and speeds metres per second here; counts exist only inside a link.
"""

from __future__ import annotations

from collections.abc import MutableMapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np

from drivers.devices.interfaces import AxisStatus
from drivers.devices.registermap import StatusBits
from drivers.errors import DeviceTimeoutError

#: A control command for one axis (the bits of the control word: :class:`drivers.devices.registermap.ControlBits`).
Command = Literal["start", "stop", "home", "reset"]


class AxisLink(Protocol):
    """The link from the axis controller to a motion controller of ``n_axes`` axes (numbered 0..n-1 here).

    Errors are :class:`~drivers.errors.DeviceError` subclasses: :class:`~drivers.errors.DeviceConnectionError`
    (no link), :class:`~drivers.errors.DeviceTimeoutError` (no reply after the link's retries),
    :class:`~drivers.errors.ProtocolError` (the controller refused, or a reply makes no sense).
    """

    @property
    def n_axes(self) -> int:
        """Number of axes."""

    @property
    def reads_every_axis(self) -> bool:
        """``True`` when one read reports every axis (then :meth:`read_axes` always returns them all)."""

    @property
    def endpoint(self) -> str:
        """Where the controller is, for messages (e.g. ``127.0.0.1:502 (RTU over TCP)``)."""

    @property
    def stats(self) -> MutableMapping[str, Any]:
        """The link's counters (requests, retries, timeouts, ...)."""

    async def open(self) -> None:
        """Connect (retried as the link's settings say)."""

    async def close(self) -> None:
        """Disconnect; never raises."""

    async def read_axes(self, axes: Sequence[int]) -> dict[int, AxisStatus]:
        """Read axes ``axes`` (0-based) by requests sent after this call.

        Returns ``{axis: status}`` for at least ``axes`` (every axis when :attr:`reads_every_axis`); ``free`` is
        left ``False`` (the controller knows whether it set the drives free), ``position_m`` is the encoder (m).
        """

    async def start_move(self, targets_m: np.ndarray, speeds_m_s: np.ndarray) -> None:
        """Write every axis' target (m) and speed (m/s), shape ``(n_axes,)`` each, and start the move."""

    async def control(self, axis: int, command: Command | None, *, free: bool, urgent: bool = False) -> None:
        """Write axis ``axis``'s control word: ``command``'s bit (``None``: none), with the free bit when ``free``.

        ``urgent`` (a stop): send it now, without waiting out a guard of the link (its replies are still checked).
        """


# Optional, read with ``getattr`` by the axis controller: ``motion_in_doubt`` (bool), ``True`` while a motion command
# that got no reply may still be executed by the controller (its connection was lost before its fate was read back):
# the controller stops every axis, confirmed, before it reports or moves again, and then clears it. And
# ``poll_interval_s`` (float): the axis controller polls a move no faster (a link whose guards limit how often an axis
# can be read: :attr:`drivers.devices.modbus.ModbusLink.poll_interval_s`).


@dataclass(frozen=True)
class SafetySettings:
    """The motion-safety settings of a link and its axis controller (bench file ``[actuators]``, same names).

    duplicate_window_s:
        A reply may be duplicated on its way (a serial device server, a gateway) up to this long (s) after it came:
        no request whose reply would look the same (unit, function, register count; a write's address and count)
        goes out meanwhile. Reads pick another window of the axis' registers instead of waiting.
    motion_confirm_s:
        After a motion command (a start, a target that starts the move, homing) got no reply: how long (s) the link
        keeps reading the drive's state back on the SAME connection to learn whether the command was taken.
        ``None``: ``4 x timeout_s``. Past it the move fails (the command may still execute; the axes are stopped).
    watchdog_s:
        The drives' communication watchdog (s; 0: none): the reply timeout is capped at
        ``0.8 x watchdog_s - backoff_s`` so that a retry reaches the drive before its watchdog stops the move.
    stop_persist_s:
        A run that fails keeps stopping the axes this long (s) until the stop is confirmed, while the controller is
        connected but silent (a stalled PLC, an overloaded gateway); then it says that it could not.
    max_accel_m_s2:
        Fastest an axis accelerates (m/s^2), for the plausibility of readings during a commanded move. ``None``: not
        bounded (the commanded speed still is).
    """

    duplicate_window_s: float = 0.06
    motion_confirm_s: float | None = None
    watchdog_s: float = 0.5
    stop_persist_s: float = 30.0
    max_accel_m_s2: float | None = None

    def __post_init__(self) -> None:
        for name in ("duplicate_window_s", "watchdog_s", "stop_persist_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("motion_confirm_s", "max_accel_m_s2"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")


class MotionNotConfirmedError(DeviceTimeoutError):
    """A motion command got no reply and whether the drive took it could not be proven: it may still execute.

    It was not sent again. ``axis``: 1..n.
    """

    def __init__(self, message: str, *, axis: int) -> None:
        self.axis = axis
        super().__init__(message)


def decode_status(word: int, bits: StatusBits, position_m: float, alarm_code: int) -> AxisStatus:
    """An axis' status from its status word (bit numbers ``bits``), its position (m) and its alarm code."""
    return AxisStatus(
        ready=bool(word >> bits.ready & 1),
        moving=bool(word >> bits.moving & 1),
        in_position=bool(word >> bits.in_position & 1),
        alarm=bool(word >> bits.alarm & 1),
        homed=bool(word >> bits.homed & 1),
        alarm_code=alarm_code,
        position_m=position_m,
    )


__all__ = ["AxisLink", "Command", "MotionNotConfirmedError", "SafetySettings", "decode_status"]
