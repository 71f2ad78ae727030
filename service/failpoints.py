"""Crash points for the crash-matrix tests: the process kills itself with SIGKILL at a named point.

``I4CAL_CRASH_AT`` (read once, at import) lists the points, comma-separated, e.g. ``state:extracting`` (right
after a run's transition to ``extracting`` is committed) or ``stage:acquired`` (right after the last frame of the
acquisition is on disk, before the next state). Unset (always, in production), :func:`hit` does nothing. It exists so
that a test can put a real ``kill -9`` at an exact point of the run lifecycle instead of racing a timer.
"""

from __future__ import annotations

import os
import signal

_POINTS = frozenset(p.strip() for p in os.environ.get("I4CAL_CRASH_AT", "").split(",") if p.strip())


def hit(point: str) -> None:
    """SIGKILL this process if ``point`` is one of ``I4CAL_CRASH_AT``'s points."""
    if point in _POINTS:
        os.kill(os.getpid(), signal.SIGKILL)
