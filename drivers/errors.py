"""Device errors: one root (:class:`DeviceError`, itself an :class:`calib.errors.I4calError`).

``DeviceConnectionError``: the device cannot be reached or the link dropped.
``DeviceTimeoutError``: a reply, a move or a frame did not arrive in time.
``LimitError``: a target outside the soft limits or the workspace; refused before anything moves.
``AlarmError``: the device reports an alarm; carries the axis and the alarm code.
``StopNotConfirmedError``: a stop could not be confirmed by reading the axes back: motion may NOT have stopped.
``FrameError``: a frame arrived corrupt or incomplete.
``MissingExtraError``: an optional vendor library is not installed; names the extra.
"""

from __future__ import annotations

from calib.errors import I4calError


class DeviceError(I4calError):
    """Root of every device (actuator, camera) error."""


class DeviceConnectionError(DeviceError, ConnectionError):
    """The device cannot be reached, or the link dropped."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A reply, a move or a frame did not arrive in time."""


class LimitError(DeviceError, ValueError):
    """A target outside the soft limits or the reachable workspace (nothing moved)."""

    def __init__(self, message: str, *, axis: int | None = None) -> None:
        self.axis = axis
        super().__init__(message)


class AlarmError(DeviceError):
    """The device reports an alarm (``code`` as the device gives it; ``axis`` 1..4 when known)."""

    def __init__(self, message: str, *, code: int | None = None, axis: int | None = None) -> None:
        self.code = code
        self.axis = axis
        super().__init__(message)


class StopNotConfirmedError(DeviceError):
    """A stop was requested but not confirmed by read-back before its deadline: motion may NOT have stopped.

    ``axes``: the axes (1..4) not confirmed stopped.
    """

    def __init__(self, message: str, *, axes: tuple[int, ...] = ()) -> None:
        self.axes = tuple(axes)
        super().__init__(message)


class ProtocolError(DeviceError):
    """A reply that does not match the request (wrong length, exception code, bad framing)."""

    def __init__(self, message: str, *, exception_code: int | None = None) -> None:
        self.exception_code = exception_code
        super().__init__(message)


class FrameError(DeviceError):
    """A camera frame arrived corrupt or incomplete."""


class MissingExtraError(DeviceError, ImportError):
    """An optional vendor library is missing."""

    def __init__(self, library: str, extra: str) -> None:
        self.library = library
        self.extra = extra
        super().__init__(f"{library} is not installed: pip install 'i4cal[{extra}]'")


class AbortedError(DeviceError):
    """An operation was aborted on request (the actuators were stopped)."""
