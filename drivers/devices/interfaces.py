"""The device interfaces the motions, the acquisition and the service depend on, and nothing else.

Small :class:`typing.Protocol` classes with async methods (in the style of ophyd-async): every
backend, real or simulated, implements them and is picked by a URI (see :mod:`drivers.acquisition.config`).
Positions are in metres; counts exist only at the register level inside a backend.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from calib.camera.views import BoardPlacement


@dataclass(frozen=True)
class AxisStatus:
    """One axis as the controller reports it."""

    ready: bool = False
    moving: bool = False
    in_position: bool = False
    alarm: bool = False
    homed: bool = False
    free: bool = False
    alarm_code: int = 0
    position_m: float = float("nan")


@dataclass(frozen=True)
class ActuatorStatus:
    axes: tuple[AxisStatus, ...]

    @property
    def alarms(self) -> dict[int, int]:
        """``{axis (1..n): alarm code}`` of the axes in alarm."""
        return {i + 1: a.alarm_code for i, a in enumerate(self.axes) if a.alarm}

    @property
    def homed(self) -> bool:
        return all(a.homed for a in self.axes)

    @property
    def moving(self) -> bool:
        return any(a.moving for a in self.axes)

    @property
    def in_position(self) -> bool:
        return all(a.in_position and not a.moving for a in self.axes)

    @property
    def positions(self) -> np.ndarray:
        return np.array([a.position_m for a in self.axes])


@dataclass(frozen=True)
class SoftLimitsM:
    """Per-axis soft limits in metres (driver side): one value per axis (four for the I4, the default)."""

    q_min: tuple[float, ...] = (-0.10, -0.10, -0.10, -0.10)
    q_max: tuple[float, ...] = (0.80, 0.80, 0.80, 0.80)


@runtime_checkable
class Actuators(Protocol):
    """Linear axes q1..qn (metres): four for the I4 (the default), as many as the bench file's
    ``[actuators] axes`` otherwise (docs/drivers.md)."""

    limits: SoftLimitsM

    async def connect(self) -> None: ...

    async def close(self) -> None: ...

    async def home(self, timeout_s: float | None = None) -> None:
        """Home every axis and wait until homed."""

    async def move(self, q: Any, timeout_s: float | None = None) -> np.ndarray:
        """Check limits, move every axis to ``q`` (metres), wait until in position; return encoders."""

    async def stop(self) -> None:
        """Stop every axis now (never raises for a device already stopped)."""

    async def read_encoders(self) -> np.ndarray:
        """Actual positions q1..q4 in metres."""

    async def status(self) -> ActuatorStatus: ...

    async def reset_alarms(self) -> None: ...

    async def set_free(self, free: bool) -> None:
        """De-energise (``True``) or re-energise the drives; encoders are still read while free."""


@dataclass
class Frame:
    """One image and what is known about it."""

    image: np.ndarray
    index: int = 0
    timestamp_s: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    async def open(self) -> None: ...

    async def configure(
        self,
        *,
        exposure_us: float | None = None,
        gain_db: float | None = None,
        pixel_format: str | None = None,
        width: int | None = None,
        height: int | None = None,
    ) -> None:
        """Apply what the device supports; settings it lacks are ignored (listed in ``info``)."""

    async def grab(self, timeout_s: float = 2.0) -> Frame:
        """Trigger (software trigger when available) or take the next frame; DeviceTimeoutError after ``timeout_s``."""

    async def close(self) -> None: ...

    @property
    def info(self) -> dict[str, Any]: ...


@runtime_checkable
class Operator(Protocol):
    """Whoever guides the free end-effector along a ruler during a ``line`` step.

    On a real bench: a person, prompted on the console. On the simulated bench: the simulated operator
    who moves the true mechanism along a truly straight segment.
    """

    async def begin_line(
        self, start_pose: list[float], end_pose: list[float], samples: int, rate_hz: float
    ) -> None: ...

    async def end_line(self) -> None: ...


@runtime_checkable
class BoardPresenter(Protocol):
    """Whoever holds the calibration board up for the camera's intrinsics (``i4cal camera calibrate``).

    On a real bench: a person, told where to hold it and pressing Enter
    (:class:`drivers.acquisition.operators.ConsoleOperator`).
    On the simulated bench: the simulated operator, who holds it where asked (:mod:`drivers.sim.hand`).
    """

    async def present_board(self, placement: BoardPlacement) -> None:
        """Hold the board as ``placement`` asks; return once it is held still (the next frame is grabbed then)."""

    async def board_done(self) -> None:
        """The session is over: the board goes back on the end-effector."""
