"""The data disk: what the service's data take, whether a run or an upload fits, and what a full disk looks like.

Three limits (``service.settings.Settings``): ``data_quota_bytes`` (the bytes under the data directory: database,
runs, datasets, temporary files), ``min_free_bytes`` (free space always left on the data disk) and, per upload,
``max_upload_bytes`` / ``max_unpacked_bytes``. A run on the bench is started (or resumed) only when the frames still
to acquire fit, with ``run_space_margin``: :meth:`DiskGuard.check`, which also writes and flushes a probe file (a
disk that statvfs calls free can still refuse: reserved blocks, quotas). A write that fails for want of space
anywhere in a run is a *disk-full* error (:func:`is_disk_full`): the run ends ``failed`` with the reason and can be
resumed when there is room again.

No HTTP here: :class:`StorageError` becomes a 507 in the routers.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import sqlite3
import stat
from pathlib import Path
from typing import Any

from calib.errors import I4calError
from service import failpoints

#: Bytes per pixel assumed for a frame on disk: a 16-bit image, or an 8-bit one PNG could not compress.
BYTES_PER_PIXEL = 2
#: A frame's size when the camera's image size is not known (2048 x 2048 at 2 bytes a pixel, 4096 x 2048 at 1).
DEFAULT_FRAME_BYTES = 8 * 1024 * 1024
#: What a frame adds besides its image: its line in dataset.json (rewritten whole after each frame), its
#: observations, its share of the result and events.
PER_FRAME_OVERHEAD_BYTES = 16 * 1024
#: Size of the probe file written and flushed before a run starts.
PROBE_BYTES = 64 * 1024

_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
#: the file named in a job process's report of ``OSError: [Errno 28] No space left on device: 'PATH'``
_REPORTED_PATH = re.compile(r"\[Errno \d+\] (?:No space left on device|Disk quota exceeded): '([^']+)'")
_SPACE_TEXTS = ("no space left on device", "database or disk is full", "disk quota exceeded", "[errno 28]")


class StorageError(I4calError):
    """Not enough storage for what was asked (the routers answer 507). ``limit`` names the cause: a setting
    (``data_quota_bytes``, ``min_free_bytes``) or ``disk full``."""

    def __init__(self, message: str, limit: str) -> None:
        super().__init__(message)
        self.limit = limit


def data_usage_bytes(root: Path) -> int:
    """Bytes of the regular files under ``root`` (symbolic links not followed), 0 if it does not exist."""
    total = 0
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            with contextlib.suppress(OSError):
                st = os.lstat(os.path.join(dirpath, name))
                if stat.S_ISREG(st.st_mode):
                    total += st.st_size
    return total


def _chain(exc: BaseException) -> list[BaseException]:
    """``exc`` and what caused it: ``__cause__``, ``__context__``, an acquisition error's ``cause``, a database
    error's ``orig``."""
    seen: list[BaseException] = []
    todo: list[Any] = [exc]
    while todo:
        e = todo.pop()
        if not isinstance(e, BaseException) or any(e is s for s in seen):
            continue
        seen.append(e)
        todo += [e.__cause__, e.__context__, getattr(e, "cause", None), getattr(e, "orig", None)]
    return seen


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) is a write refused for want of space: ``ENOSPC`` or ``EDQUOT`` from a
    file, SQLite's ``database or disk is full``, PostgreSQL's ``disk_full`` (53100), or a job process's report of
    one."""
    for e in _chain(exc):
        if isinstance(e, OSError) and e.errno in _SPACE_ERRNOS:
            return True
        if isinstance(e, sqlite3.OperationalError) and "full" in str(e).lower():
            return True
        if getattr(e, "sqlstate", None) == "53100":
            return True
        if isinstance(e, I4calError) and any(t in str(e).lower() for t in _SPACE_TEXTS):
            return True
    return False


def disk_full_reason(exc: BaseException, data_dir: Path, stage: str) -> str:
    """The error a run ends with when ``exc`` is a disk-full error during ``stage``."""
    what = ""
    for e in _chain(exc):
        if isinstance(e, OSError) and e.errno in _SPACE_ERRNOS and e.filename:
            what = f" writing {_relative(e.filename, data_dir)}"
            break
        if isinstance(e, sqlite3.OperationalError) or getattr(e, "sqlstate", None) == "53100":
            what = " writing the database"
            break
        m = _REPORTED_PATH.search(str(e))  # a job process's report of its OSError
        if m:
            what = f" writing {_relative(m.group(1), data_dir)}"
            break
    return (
        f"disk full: no space left on the data disk ({data_dir}){what} during the {stage}; "
        "free space (DELETE /api/v1/runs/ID, /api/v1/datasets/ID) and resume the run"
    )


def _relative(path: str | os.PathLike[str], data_dir: Path) -> str:
    p = Path(path)
    with contextlib.suppress(ValueError):
        return str(p.resolve().relative_to(data_dir))
    return str(p)


class DiskGuard:
    """The checks before a run or an upload writes: quota, free space, a probe write."""

    def __init__(self, settings: Any, data_dir: Path) -> None:
        self.settings = settings
        self.data_dir = data_dir

    def frame_bytes(self, bench: Any) -> int:
        """Expected bytes of one frame: ``frame_bytes`` if set, else the camera's width x height (bench file, camera
        file) x :data:`BYTES_PER_PIXEL`, else :data:`DEFAULT_FRAME_BYTES`."""
        if self.settings.frame_bytes:
            return int(self.settings.frame_bytes)
        sizes = []
        cam = getattr(getattr(bench, "config", None), "camera", None)
        sizes.append((getattr(cam, "width", None), getattr(cam, "height", None)))
        model = getattr(bench, "camera_model", None)
        sizes.append((getattr(model, "width", None), getattr(model, "height", None)))
        spec = getattr(bench, "camera_spec", None) or {}
        sizes.append((spec.get("width"), spec.get("height")))
        for w, h in sizes:
            if isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0:
                return w * h * BYTES_PER_PIXEL
        return DEFAULT_FRAME_BYTES

    def run_bytes(self, frames: int, frame_bytes: int) -> int:
        """Bytes a run of ``frames`` frames still to acquire is expected to write, with ``run_space_margin``."""
        return int(frames * (frame_bytes + PER_FRAME_OVERHEAD_BYTES) * self.settings.run_space_margin)

    def check(self, need_bytes: int, what: str) -> None:
        """Refuse (:class:`StorageError`) when ``need_bytes`` more would pass ``data_quota_bytes`` or leave less
        than ``min_free_bytes`` free on the data disk, or when the disk refuses a small write and flush now.

        Walks the data directory (call it off the event loop)."""
        quota = self.settings.data_quota_bytes
        if quota:
            used = data_usage_bytes(self.data_dir)
            if used + need_bytes > quota:
                raise StorageError(
                    f"data quota: {what} needs about {need_bytes} bytes and the data directory already holds {used} of "
                    f"its {quota} (data_quota_bytes); delete runs or datasets (DELETE /api/v1/runs/ID, "
                    "/api/v1/datasets/ID) or raise the quota",
                    "data_quota_bytes",
                )
        self.data_dir.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.data_dir).free
        floor = self.settings.min_free_bytes
        if free - need_bytes < floor:
            raise StorageError(
                f"free space: {what} needs about {need_bytes} bytes and the data disk ({self.data_dir}) has {free} "
                f"free, of which {floor} are kept free (min_free_bytes)",
                "min_free_bytes",
            )
        self.probe(what)

    def room(self, what: str) -> tuple[int, str]:
        """The bytes ``what`` (an upload) may still write, and the limit that bounds them (``data_quota_bytes`` or
        ``min_free_bytes``); :class:`StorageError` when there is none, or the disk refuses a write now.

        Walks the data directory (call it off the event loop)."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.data_dir).free - self.settings.min_free_bytes
        room, limit = free, "min_free_bytes"
        quota = self.settings.data_quota_bytes
        if quota:
            left = quota - data_usage_bytes(self.data_dir)
            if left < room:
                room, limit = left, "data_quota_bytes"
        if room <= 0:
            self.check(1, what)  # raises, naming the limit
        self.probe(what)
        return room, limit

    def exceeded(self, what: str, room: int, limit: str) -> StorageError:
        """The error of ``what`` passing the ``room`` :meth:`room` gave."""
        where = "the data directory's quota" if limit == "data_quota_bytes" else "the free space kept on the data disk"
        return StorageError(
            f"{what} would pass {where} ({limit}): it had room for {room} bytes; nothing was kept. Delete runs or "
            "datasets (DELETE /api/v1/runs/ID, /api/v1/datasets/ID)",
            limit,
        )

    def probe(self, what: str) -> None:
        """Write and flush :data:`PROBE_BYTES` in the data directory, then remove them."""
        tmp = self.data_dir / "tmp"
        path = tmp / f".space-probe-{os.getpid()}"
        try:
            tmp.mkdir(parents=True, exist_ok=True)
            failpoints.check_disk(path)
            with open(path, "wb") as fh:
                fh.write(b"\0" * PROBE_BYTES)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            if exc.errno not in _SPACE_ERRNOS:
                raise
            raise StorageError(
                f"disk full: the data disk ({self.data_dir}) refuses to write ({exc.strerror}); {what} cannot start: "
                "free space (DELETE /api/v1/runs/ID, /api/v1/datasets/ID)",
                "disk full",
            ) from None
        finally:
            with contextlib.suppress(OSError):
                path.unlink()
