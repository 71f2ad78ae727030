"""Datasets: upload a recorded dataset (zip or tar archive) to calibrate it offline."""

from __future__ import annotations

import asyncio
import os
import shutil
import tarfile
import tempfile
import zipfile
import zlib
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path, PurePosixPath
from typing import IO, Annotated

from fastapi import APIRouter, HTTPException, Query, Request, status
from pydantic import BaseModel
from sqlalchemy import select

from calib.errors import I4calError
from service import failpoints
from service.api.deps import DatasetId, Manager, SettingsDep, conflict, not_found
from service.api.runs import insufficient_storage
from service.auth import Reader, Writer
from service.db import DatasetRecord
from service.hardening import json_file_problem
from service.jobs import check_frame_numbers
from service.runs import RunConflictError, new_id, now
from service.runs.disk import StorageError, is_disk_full

router = APIRouter(prefix="/datasets", tags=["datasets"])

ARCHIVE_TYPES = (
    "application/zip",
    "application/x-zip-compressed",
    "application/x-tar",
    "application/gzip",
    "application/x-gzip",
    "application/octet-stream",
)


class DatasetOut(BaseModel):
    id: str
    name: str
    created_at: datetime
    frames: int
    size_bytes: int


def dataset_out(d: DatasetRecord) -> DatasetOut:
    return DatasetOut(id=d.id, name=d.name, created_at=d.created_at, frames=d.frames, size_bytes=d.size_bytes)


class ArchiveError(ValueError):
    """The archive is refused (422): the message names the member."""


class ArchiveTooLargeError(ArchiveError):
    """The archive unpacks (or declares it unpacks) to more than ``max_unpacked_bytes`` (422, as before)."""


def _safe_member(name: str) -> PurePosixPath | None:
    """The member's relative path, or None for a directory entry; raises on anything that could escape."""
    if "\\" in name or "\x00" in name or len(name) > 1024:
        raise ArchiveError(f"archive member {name[:80]!r}: bad characters in the name")
    p = PurePosixPath(name)
    if p.is_absolute() or name.startswith("/") or (p.parts and ":" in p.parts[0]):
        raise ArchiveError(f"archive member {name[:80]!r} has an absolute path")
    parts = [x for x in p.parts if x not in ("", ".")]
    if any(x == ".." for x in parts):
        raise ArchiveError(f"archive member {name[:80]!r} escapes the archive ('..')")
    if not parts or name.endswith("/"):
        return None
    return PurePosixPath(*parts)


#: Bytes copied per read while unpacking: at most this much past the last check is ever in memory, none on disk.
CHUNK_BYTES = 1 << 20


class RoomExceededError(Exception):
    """The upload would pass the room the data disk has for it (``data_quota_bytes``, ``min_free_bytes``): 507."""


def _copy_limited(src, dst_path: Path, budget: list[int], member: str, room: list[int] | None = None) -> None:
    """Copy ``src`` to ``dst_path`` in chunks, counting the bytes actually read: a chunk that would take the archive
    past its budget (or past the disk's ``room``) is refused before it is written (declared sizes are not trusted)."""
    try:
        _copy_chunks(src, dst_path, budget, member, room)
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        raise StorageError(
            f"disk full: the data disk refused archive member {member[:80]!r} ({exc.strerror}); nothing was kept",
            "disk full",
        ) from None


def _copy_chunks(src, dst_path: Path, budget: list[int], member: str, room: list[int] | None) -> None:
    with open(dst_path, "wb") as dst:
        while chunk := src.read(CHUNK_BYTES):
            if len(chunk) > budget[0]:
                raise ArchiveTooLargeError(
                    f"archive member {member[:80]!r} unpacks to more than the configured limit (max_unpacked_bytes)"
                )
            if room is not None:
                if len(chunk) > room[0]:
                    raise RoomExceededError(member)
                room[0] -= len(chunk)
            budget[0] -= len(chunk)
            failpoints.check_disk(dst_path)
            dst.write(chunk)


def _too_large(total: int, max_bytes: int, largest: str) -> ArchiveTooLargeError:
    return ArchiveTooLargeError(
        f"archive declares {total} bytes unpacked, more than the configured limit of {max_bytes} "
        f"(max_unpacked_bytes; largest member {largest[:80]!r}); nothing was unpacked"
    )


def unpack_archive(
    archive: Path, dest: Path, *, max_bytes: int, max_members: int, room_bytes: int | None = None
) -> None:
    """Unpack a zip or tar(.gz) into ``dest``: regular files and directories only, no member outside ``dest``,
    at most ``max_members`` members and ``max_bytes`` unpacked.

    Every member's name and type, and the archive's declared unpacked size, are checked before anything is
    written; then the members are copied in chunks of :data:`CHUNK_BYTES`, counting the bytes actually
    decompressed: a chunk that would exceed ``max_bytes`` is refused before it is written, so at most ``max_bytes``
    ever reach the disk, whatever the archive declares.

    ``room_bytes``: what the data disk has room for (quota, free space), counted the same way.

    Raises
    ------
    ArchiveError
        Names the member: unsafe name or type, corrupt data (bad CRC, truncated, unsupported compression,
        encrypted), or too large (:class:`ArchiveTooLargeError`).
    RoomExceededError
        It declares or unpacks to more than ``room_bytes``.
    """
    dest.mkdir(parents=True, exist_ok=False)
    out = _Unpacking(dest.resolve(), [max_bytes], None if room_bytes is None else [room_bytes])
    if zipfile.is_zipfile(archive):
        _unpack_zip(archive, out, max_bytes, max_members)
    else:
        _unpack_tar(archive, out, max_bytes, max_members)


@dataclass
class _Unpacking:
    """Where an archive unpacks (``root``, resolved) and what is left of its byte budget and of the disk's room (one
    element lists, counted down as the chunks are written; ``room`` None: no room limit)."""

    root: Path
    budget: list[int]
    room: list[int] | None

    def target(self, rel: PurePosixPath) -> Path:
        """The file a member's relative path unpacks to (its directory made); raises if it escapes ``root``."""
        t = (self.root / rel).resolve()
        if self.root not in t.parents:
            raise ArchiveError(f"archive member {str(rel)[:80]!r} escapes the data directory")
        t.parent.mkdir(parents=True, exist_ok=True)
        return t

    def copy(self, src: IO[bytes], rel: PurePosixPath, member: str) -> None:
        """Copy one member's stream to its target, within the budget and the room."""
        _copy_limited(src, self.target(rel), self.budget, member, self.room)


def _zip_files(infos: list[zipfile.ZipInfo]) -> list[tuple[zipfile.ZipInfo, PurePosixPath]]:
    """The zip's regular files with their safe relative paths; raises on any other type or unsafe name."""
    files: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
    for info in infos:
        mode = (info.external_attr >> 16) & 0o170000
        if mode and mode not in (0o100000, 0o040000):
            raise ArchiveError(f"archive member {info.filename[:80]!r} is not a regular file")
        rel = _safe_member(info.filename)
        if rel is not None and not info.is_dir():
            files.append((info, rel))
    return files


def _unpack_zip(archive: Path, out: _Unpacking, max_bytes: int, max_members: int) -> None:
    """:func:`unpack_archive` for a zip: every member checked from the central directory, then copied."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise ArchiveError(f"broken zip archive ({exc})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise ArchiveError(f"archive has {len(infos)} members, more than {max_members}")
        files = _zip_files(infos)
        total = sum(info.file_size for info, _ in files)
        if total > max_bytes:
            raise _too_large(total, max_bytes, max(files, key=lambda f: f[0].file_size)[0].filename)
        if out.room is not None and total > out.room[0]:
            raise RoomExceededError(max(files, key=lambda f: f[0].file_size)[0].filename)
        for info, rel in files:
            try:
                with zf.open(info) as src:
                    out.copy(src, rel, info.filename)
            except ArchiveError:
                raise
            except (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, RuntimeError) as exc:
                raise ArchiveError(f"archive member {info.filename[:80]!r} is corrupt or unreadable ({exc})") from None


def _tar_files(
    tf: tarfile.TarFile, out: _Unpacking, max_bytes: int, max_members: int
) -> list[tuple[tarfile.TarInfo, PurePosixPath]]:
    """The tar's regular files with their safe relative paths, from the headers only: names, types, declared sizes
    (stops as soon as a limit is passed)."""
    members: list[tuple[tarfile.TarInfo, PurePosixPath]] = []
    total = 0
    for n, m in enumerate(tf, start=1):
        if n > max_members:
            raise ArchiveError(f"archive has more than {max_members} members")
        rel = _safe_member(m.name)
        if m.isdir() or rel is None:
            continue
        if not m.isfile():
            raise ArchiveError(f"archive member {m.name[:80]!r} is not a regular file (link or device)")
        total += m.size
        if total > max_bytes:
            raise _too_large(total, max_bytes, m.name)
        if out.room is not None and total > out.room[0]:
            raise RoomExceededError(m.name)
        members.append((m, rel))
    return members


def _unpack_tar(archive: Path, out: _Unpacking, max_bytes: int, max_members: int) -> None:
    """:func:`unpack_archive` for a tar(.gz): a first pass over the headers, then the members copied."""
    try:
        tf = tarfile.open(archive, mode="r:*")  # noqa: SIM115 (closed by the with below)
    except (tarfile.TarError, OSError, EOFError, zlib.error) as exc:
        raise ArchiveError(f"not a zip or tar archive ({exc})") from None
    with tf:
        try:
            members = _tar_files(tf, out, max_bytes, max_members)
        except (tarfile.TarError, EOFError, OSError, zlib.error) as exc:
            raise ArchiveError(f"broken archive ({exc})") from None
        for m, rel in members:
            try:
                src = tf.extractfile(m)
                if src is None:
                    continue
                with src:
                    out.copy(src, rel, m.name)
            except ArchiveError:
                raise
            except (tarfile.TarError, EOFError, OSError, zlib.error) as exc:
                raise ArchiveError(f"archive member {m.name[:80]!r} is corrupt or unreadable ({exc})") from None


def _find_root(dest: Path) -> Path:
    if (dest / "dataset.json").is_file():
        return dest
    subs = [p for p in dest.iterdir() if p.is_dir()]
    if len(subs) == 1 and (subs[0] / "dataset.json").is_file():
        return subs[0]
    raise ArchiveError("no dataset.json at the archive's top level (or in its single top directory)")


def _ingest(
    archive: Path, dest: Path, max_bytes: int, max_members: int, room_bytes: int | None = None
) -> tuple[str, int, int]:
    from calib.formats.dataset import Dataset

    unpack_archive(archive, dest, max_bytes=max_bytes, max_members=max_members, room_bytes=room_bytes)
    root = _find_root(dest)
    problem = json_file_problem(root / "dataset.json")  # nested 100000 levels deep: a RecursionError, a 500
    if problem is not None:
        raise ArchiveError(problem)
    try:
        ds = Dataset.open(root)
        check_frame_numbers(root)
    except I4calError as exc:
        raise ArchiveError(f"not a valid dataset v1: {exc}") from None
    for i in range(len(ds.frames)):
        p = ds.image_path(i)
        if p is not None and root.resolve() not in p.resolve().parents:
            raise ArchiveError(f"frame {i}: image path escapes the dataset")
    size = sum(f.stat().st_size for f in dest.rglob("*") if f.is_file())
    return str(root.relative_to(dest.parent.parent)), len(ds.frames), size


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=DatasetOut,
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": "a zip or tar(.gz) archive of a dataset v1 directory (dataset.json + frames)",
            "content": {
                "application/zip": {"schema": {"type": "string", "format": "binary"}},
                "application/gzip": {"schema": {"type": "string", "format": "binary"}},
            },
        }
    },
    responses={
        401: {"description": "no or wrong token"},
        413: {"description": "archive too large"},
        415: {"description": "not an archive type"},
        422: {"description": "not a safe archive of a valid dataset"},
        507: {"description": "no room: data_quota_bytes, min_free_bytes, or the disk is full (nothing kept)"},
    },
)
async def upload_dataset(
    request: Request,
    manager: Manager,
    settings: SettingsDep,
    _: Writer,
    name: Annotated[str, Query(max_length=255, pattern=r"^[\w .,()+-]*$")] = "",
) -> DatasetOut:
    """Upload a recorded dataset as an archive (request body); calibrate it with ``POST /api/v1/runs
    {"dataset": id}``."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in ARCHIVE_TYPES:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE, detail=f"send the archive as one of {', '.join(ARCHIVE_TYPES[:4])}"
        )
    limit = settings.max_upload_bytes
    clen = request.headers.get("content-length")
    if clen is not None and clen.isdigit() and int(clen) > limit:
        raise HTTPException(
            status.HTTP_413_CONTENT_TOO_LARGE if hasattr(status, "HTTP_413_CONTENT_TOO_LARGE") else 413,
            detail=f"archive larger than {limit} bytes",
        )
    room, room_limit = await _upload_room(manager)
    tmpdir = manager.data_dir / "tmp"
    tmpdir.mkdir(parents=True, exist_ok=True)
    fd, tmpname = tempfile.mkstemp(dir=tmpdir, suffix=".upload")
    tmp = Path(tmpname)
    did = new_id()
    dest = manager.data_dir / "datasets" / did
    try:
        got = 0
        with os.fdopen(fd, "wb") as f:
            async for chunk in request.stream():
                got += len(chunk)
                if got > limit:
                    raise HTTPException(413, detail=f"archive larger than {limit} bytes")
                if got > room:
                    raise insufficient_storage(manager.disk.exceeded("the upload", room, room_limit))
                failpoints.check_disk(tmp)
                await asyncio.to_thread(f.write, chunk) if len(chunk) > (1 << 20) else f.write(chunk)
        if got == 0:
            raise HTTPException(422, detail=[{"loc": ["body"], "msg": "empty body", "type": "value_error"}])
        try:
            rel, frames, size = await asyncio.to_thread(
                _ingest, tmp, dest, settings.max_unpacked_bytes, settings.max_archive_members, room - got
            )
        except ArchiveError as exc:
            shutil.rmtree(dest, ignore_errors=True)
            raise HTTPException(422, detail=[{"loc": ["body"], "msg": str(exc), "type": "value_error"}]) from None
        except RoomExceededError:
            raise insufficient_storage(manager.disk.exceeded("the upload", room, room_limit)) from None
        rec = DatasetRecord(id=did, name=name, path=rel, frames=frames, size_bytes=size, created_at=now())
        with manager.db.session() as s:
            s.add(rec)
    except StorageError as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise insufficient_storage(exc) from None
    except Exception as exc:
        shutil.rmtree(dest, ignore_errors=True)
        if not is_disk_full(exc):
            raise
        raise insufficient_storage(
            StorageError(
                f"disk full: the data disk ({manager.data_dir}) refused the upload; nothing was kept", "disk full"
            )
        ) from None
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    finally:
        tmp.unlink(missing_ok=True)
    return dataset_out(rec)


async def _upload_room(manager) -> tuple[int, str]:
    """What an upload may write (the quota and the free space), off the event loop; 507 when nothing."""
    try:
        return await asyncio.to_thread(manager.disk.room, "the upload")
    except StorageError as exc:
        raise insufficient_storage(exc) from None


class DatasetDeleted(BaseModel):
    id: str
    freed_bytes: int


@router.delete(
    "/{dataset_id}",
    response_model=DatasetDeleted,
    responses={
        401: {"description": "no or wrong token"},
        404: {"description": "no such dataset"},
        409: {"description": "a run that may still read it calibrates it, or it is on another service's disk"},
        507: {"description": "the disk is full and the database cannot record the deletion"},
    },
)
async def delete_dataset(dataset_id: DatasetId, manager: Manager, _: Writer) -> DatasetDeleted:
    """Delete an uploaded dataset and its files. Refused (409) while a run that is not done or aborted calibrates
    it; the results of finished runs are kept (their report then has no frames to show)."""
    try:
        found = manager.delete_dataset(dataset_id)
    except RunConflictError as exc:
        raise conflict(str(exc)) from None
    except StorageError as exc:
        raise insufficient_storage(exc) from None
    if found is None:
        raise not_found("dataset")
    path, size = found
    await asyncio.to_thread(manager.delete_tree, path)
    return DatasetDeleted(id=dataset_id, freed_bytes=size)


@router.get("", response_model=list[DatasetOut], responses={401: {"description": "reads closed, no token"}})
async def list_datasets(
    manager: Manager,
    _: Reader,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
) -> list[DatasetOut]:
    with manager.db.session() as s:
        rows = s.scalars(select(DatasetRecord).order_by(DatasetRecord.created_at.desc()).limit(limit).offset(offset))
        return [dataset_out(d) for d in rows]


@router.get("/{dataset_id}", response_model=DatasetOut, responses={404: {"description": "no such dataset"}})
async def read_dataset(dataset_id: DatasetId, manager: Manager, _: Reader) -> DatasetOut:
    with manager.db.session() as s:
        d = s.get(DatasetRecord, dataset_id)
        if d is None:
            raise not_found("dataset")
        return dataset_out(d)
