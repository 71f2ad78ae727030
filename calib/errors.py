"""The project's exception hierarchy.

Every error raised on purpose by i4cal derives from :class:`I4calError`, so a
script can catch one type. The few subclasses name what went wrong: bad input
data, an unreachable pose, a pose set that does not excite a parameter, a fit
that did not converge. Drivers add their device errors under the same root.
"""

from __future__ import annotations


class I4calError(Exception):
    """Root of every error raised on purpose by i4cal."""


class InputError(I4calError, ValueError):
    """Bad input data: names the file, frame and field when they are known."""

    def __init__(
        self, message: str, *, file: str | None = None, frame: int | None = None, field: str | None = None
    ) -> None:
        self.file = file
        self.frame = frame
        self.field = field
        self.reason = message
        where = []
        if file is not None:
            where.append(str(file))
        if frame is not None:
            where.append(f"frame {frame}")
        if field is not None:
            where.append(f"field '{field}'")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class UnreachableError(I4calError, ValueError):
    """A pose or joint vector outside the mechanism's reach (names the leg and by how much)."""

    def __init__(
        self, message: str, *, leg: int | None = None, index: int | None = None, deficit_m: float | None = None
    ) -> None:
        self.leg = leg
        self.index = index
        self.deficit_m = deficit_m
        super().__init__(message)


class IdentifiabilityError(I4calError):
    """The pose set does not excite a parameter, or the data needed for a step are missing."""

    def __init__(self, message: str, *, parameter: str | None = None) -> None:
        self.parameter = parameter
        super().__init__(message)


class ConvergenceError(I4calError):
    """An iterative fit did not converge."""
