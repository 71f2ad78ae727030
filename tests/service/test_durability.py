"""Durability: SQLite commits with ``synchronous=FULL`` (WAL), and every rename-based writer flushes the
directory after its rename. A power cut cannot be made here: the directory flush is observed by recording which
files and directories ``os.fsync`` is called on, and in which order with the renames (the real calls still run)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from calib.numerics.jsonio import write_json_atomic
from service.db import Database


def test_sqlite_commits_are_synchronous_full(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'd.db'}")
    try:
        db.upgrade()
        with db.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA synchronous").scalar() == 2  # FULL (NORMAL is 1)
    finally:
        db.dispose()


@pytest.fixture
def io_log(monkeypatch):
    """The sequence of ``("replace", dst)`` and ``("fsync", path)`` calls (the real ones are made)."""
    log: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        log.append(("fsync", os.path.realpath(os.readlink(f"/proc/self/fd/{fd}"))))
        return real_fsync(fd)

    def replace(src, dst, *a, **kw):
        out = real_replace(src, dst, *a, **kw)
        log.append(("replace", os.path.realpath(dst)))
        return out

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return log


def _dir_synced_after_rename(log: list[tuple[str, str]], path: str) -> bool:
    i = log.index(("replace", os.path.realpath(path)))
    return ("fsync", os.path.realpath(os.path.dirname(path))) in log[i + 1 :]


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name the file descriptors")
def test_write_json_atomic_syncs_the_directory_after_the_rename(tmp_path, io_log):
    p = tmp_path / "result.json"
    write_json_atomic(p, {"a": 1})
    assert ("fsync", str(tmp_path / ".result.json.tmp")) in io_log  # the data, before the rename
    assert _dir_synced_after_rename(io_log, str(p))


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name the file descriptors")
def test_dataset_writer_syncs_the_directories_of_its_renames(tmp_path, io_log):
    from calib.formats.dataset import BoardSpec, CameraSpec, DatasetWriter, LegsSpec
    from drivers.sim.twin import BenchGeometry

    w = DatasetWriter(
        tmp_path / "ds",
        camera=CameraSpec(width=8, height=8),
        board=BoardSpec(),
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=BenchGeometry().nominal.as_dict(),
    )
    w.add_frame("poses", [0.3, 0.3, 0.3, 0.3], np.zeros((8, 8), np.uint8))
    assert _dir_synced_after_rename(io_log, str(tmp_path / "ds" / "frames" / "000000.png"))
    assert _dir_synced_after_rename(io_log, str(tmp_path / "ds" / "dataset.json"))
