"""Failpoints for the tests: crash points and a full data disk. Inert unless their environment variable is set.

Crash points. ``I4CAL_CRASH_AT`` (read once, at import) lists the points, comma-separated, e.g.
``state:extracting`` (right after a run's transition to ``extracting`` is committed) or ``stage:acquired`` (right
after the last frame of the acquisition is on disk, before the next state). Unset (always, in production),
:func:`hit` does nothing. It exists so that a test can put a real ``kill -9`` at an exact point of the run lifecycle
instead of racing a timer.

A full disk. ``I4CAL_DISK_FULL`` names a *flag file*; while that file exists and holds a directory, every write the
service and its job processes make under that directory fails with ``ENOSPC``, as on a full disk: the files'
``fsync`` (every crash-safe writer of the project flushes through it: frames, ``dataset.json``, observations,
results), the uploads' chunks (:func:`check_disk`) and the SQLite database's writes (``database or disk is full``,
:func:`service.db.session.Database`). Deleting the flag file is the space coming back. A file rather than a
variable, so that a test can fill and free the disk of a running service and of its job processes (a forkserver's
children do not see the server's later environment). A real full disk needs a small filesystem of its own, which
needs privileges a test run does not have (mount, or a user namespace where the kernel allows them).
"""

from __future__ import annotations

import errno
import os
import signal
from pathlib import Path

_POINTS = frozenset(p.strip() for p in os.environ.get("I4CAL_CRASH_AT", "").split(",") if p.strip())

#: The environment variable naming the disk-full flag file.
DISK_FULL_ENV = "I4CAL_DISK_FULL"


def hit(point: str) -> None:
    """SIGKILL this process if ``point`` is one of ``I4CAL_CRASH_AT``'s points."""
    if point in _POINTS:
        os.kill(os.getpid(), signal.SIGKILL)


def full_directory() -> Path | None:
    """The directory the disk-full failpoint makes full now (None: unset, or the flag file is absent)."""
    flag = os.environ.get(DISK_FULL_ENV)
    if not flag:
        return None
    try:
        text = Path(flag).read_text(encoding="utf-8").strip()
    except OSError:
        return None
    return Path(text).resolve() if text else None


def is_full(path: str | os.PathLike[str]) -> bool:
    """Whether the disk-full failpoint refuses writes to ``path`` now."""
    d = full_directory()
    if d is None:
        return False
    p = Path(path).resolve()
    return p == d or d in p.parents


def check_disk(path: str | os.PathLike[str]) -> None:
    """Raise ``OSError(ENOSPC)`` if the disk-full failpoint covers ``path`` (a no-op unless armed)."""
    if is_full(path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


_real_fsync = os.fsync
_installed = False


def _fsync(fd) -> None:
    n = fd if isinstance(fd, int) else fd.fileno()
    try:
        path = os.readlink(f"/proc/self/fd/{n}")
    except OSError:
        path = ""
    if path:
        check_disk(path)
    _real_fsync(fd)


def install(env: str | None = None) -> None:
    """Arm the disk-full failpoint's ``fsync`` seam in this process if ``I4CAL_DISK_FULL`` is set (``env``: its value
    in the server, for a job process whose environment is the forkserver's). Idempotent; nothing without it."""
    global _installed
    if env:
        os.environ[DISK_FULL_ENV] = env
    if _installed or not os.environ.get(DISK_FULL_ENV):
        return
    os.fsync = _fsync
    _installed = True
