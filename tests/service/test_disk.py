"""Disk and retention: the data quota and free-space checks (507 naming the limit, nothing partial kept), DELETE of
datasets and finished runs, and a full disk during a run (the run ends ``failed`` with the reason and resumes when
there is room again).

Real SQLite, real files, the real service over HTTP against the simulated bench. A full disk is produced by the
disk-full failpoint (``service/failpoints.py``, ``I4CAL_DISK_FULL``): while its flag file names a directory, every
``fsync`` of a file under it (frames, ``dataset.json``, observations, results), every upload chunk and every SQLite
write of the service fails with ``ENOSPC`` / ``database or disk is full``, in the server and in its job processes.
It is a stand-in for a real full filesystem, which needs a small filesystem of its own: mounting one needs
privileges (root, or a user namespace where the kernel allows them) that a test run does not have in general.
"""

from __future__ import annotations

import asyncio
import io
import json
import zipfile
from pathlib import Path

import pytest
from sqlalchemy import select

from service.db import Calibration, Event, Run
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state

#: service.failpoints.DISK_FULL_ENV (spelled out: the tests also run against code without the failpoint)
DISK_FULL_ENV = "I4CAL_DISK_FULL"

API = "/api/v1"
ZIP = {"Content-Type": "application/zip", **AUTH}
MIB = 1024 * 1024


def _files(d: Path) -> list[Path]:
    return [f for f in d.rglob("*") if f.is_file()] if d.exists() else []


async def _sweep_zip(c) -> bytes:
    """A recorded dataset (6 frames of the rotation sweep), as the service's own download."""
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
    assert r.status_code == 202, r.text
    rid = r.json()["id"]
    assert (await wait_state(c, rid))["state"] == "done"
    return (await c.get(f"{API}/runs/{rid}/dataset")).content


def _with_junk(z: bytes, junk_bytes: int) -> bytes:
    """The dataset archive with one more member of ``junk_bytes`` zeros (deflated to a few kB)."""
    src = zipfile.ZipFile(io.BytesIO(z))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for info in src.infolist():
            zf.writestr(info, src.read(info))
        zf.writestr("dataset/padding.bin", b"\0" * junk_bytes)
    return buf.getvalue()


async def test_upload_past_the_data_quota_is_507_naming_it_and_keeps_nothing(tmp_path, sim):
    """A small archive that unpacks to more than the quota leaves: 507 naming data_quota_bytes, and nothing of it
    on disk (neither the archive nor the members written before the limit). Within the quota, the same dataset is
    kept."""
    probe = await start_service(make_settings(tmp_path / "probe", sim), sim)
    try:
        z = await _sweep_zip(probe.client)
    finally:
        await probe.client.aclose()
        await probe.stop()
    bomb = _with_junk(z, 24 * MIB)
    assert len(bomb) < 200_000  # deflated: the bytes written are what counts

    settings = make_settings(tmp_path, sim)
    data = settings.data_dir
    svc = await start_service(settings, sim)
    try:
        used = sum(f.stat().st_size for f in _files(data))
    finally:
        await svc.client.aclose()
        await svc.stop()
    svc = await start_service(make_settings(tmp_path, sim, data_quota_bytes=used + 16 * MIB), sim)
    c = svc.client
    try:
        r = await c.post(f"{API}/datasets", content=bomb, headers=ZIP)
        assert r.status_code == 507, r.text
        assert r.json()["detail"]["limit"] == "data_quota_bytes" and "data_quota_bytes" in r.json()["detail"]["msg"]
        assert _files(data / "datasets") == [] and _files(data / "tmp") == []
        assert (await c.get(f"{API}/datasets")).json() == []
        # the dataset without the padding fits, and is kept
        r = await c.post(f"{API}/datasets", content=z, headers=ZIP)
        assert r.status_code == 201, r.text
    finally:
        await c.aclose()
        await svc.stop()


async def test_upload_on_a_full_disk_is_507_and_keeps_nothing(tmp_path, sim, monkeypatch):
    flag = tmp_path / "disk-full"
    monkeypatch.setenv(DISK_FULL_ENV, str(flag))
    svc = await start_service(make_settings(tmp_path, sim), sim)
    c, data = svc.client, svc.settings.data_dir
    try:
        z = await _sweep_zip(c)
        flag.write_text(str((data / "datasets").resolve()))  # the upload's members cannot be written
        r = await c.post(f"{API}/datasets", content=z, headers=ZIP)
        assert r.status_code == 507, r.text
        assert r.json()["detail"]["limit"] == "disk full" and "nothing was kept" in r.text
        assert _files(data / "datasets") == [] and _files(data / "tmp") == []
        flag.unlink()
        assert (await c.post(f"{API}/datasets", content=z, headers=ZIP)).status_code == 201
    finally:
        await c.aclose()
        await svc.stop()


async def test_a_run_that_does_not_fit_is_refused_with_507_before_anything_moves(tmp_path, sim):
    """The free-space check: the plan's frames times the frame's expected size (with the margin) against the free
    space, then against the quota; the run is not created and the axes do not move."""
    huge = 1 << 50  # 1 PiB a frame: no disk has that
    svc = await start_service(make_settings(tmp_path, sim, frame_bytes=huge, data_quota_bytes=0), sim)
    c = svc.client
    try:
        q0 = sim.mechanism.q_true().copy()
        r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
        assert r.status_code == 507, r.text
        assert r.json()["detail"]["limit"] == "min_free_bytes" and "6 frames" in r.json()["detail"]["msg"]
        assert (await c.get(f"{API}/runs")).json() == []
        assert (sim.mechanism.q_true() == q0).all()
    finally:
        await c.aclose()
        await svc.stop()
    # the quota: the data directory already holds more than 1 byte
    svc = await start_service(make_settings(tmp_path, sim, frame_bytes=MIB, data_quota_bytes=1), sim)
    try:
        r = await svc.client.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
        assert r.status_code == 507 and r.json()["detail"]["limit"] == "data_quota_bytes", r.text
    finally:
        await svc.client.aclose()
        await svc.stop()


async def test_delete_runs_and_datasets(tmp_path, sim):
    """DELETE needs a token; removes the run's row, events and files; refuses a run that holds the bench, a run
    whose result is the current calibration, and a dataset a failed run may still read."""
    svc = await start_service(make_settings(tmp_path, sim), sim)
    c, data = svc.client, svc.settings.data_dir
    try:
        z = await _sweep_zip(c)
        done_id = (await c.get(f"{API}/runs")).json()[0]["id"]
        assert (data / "runs" / done_id / "dataset" / "dataset.json").is_file()
        assert (await c.delete(f"{API}/runs/{done_id}")).status_code == 401
        assert (data / "runs" / done_id).is_dir()

        # a run on the bench cannot be deleted
        r = await c.post(f"{API}/runs", json={"plan": "full", "methods": []}, headers=AUTH)
        busy = r.json()["id"]
        r = await c.delete(f"{API}/runs/{busy}", headers=AUTH)
        assert r.status_code == 409 and "holds the bench" in r.text, r.text
        await c.post(f"{API}/runs/{busy}/abort", headers=AUTH)
        assert (await wait_state(c, busy))["state"] == "aborted"

        size = sum(f.stat().st_size for f in _files(data / "runs" / done_id))
        r = await c.delete(f"{API}/runs/{done_id}", headers=AUTH)
        assert r.status_code == 200 and r.json() == {"id": done_id, "freed_bytes": size}, r.text
        assert not (data / "runs" / done_id).exists()
        assert (await c.get(f"{API}/runs/{done_id}")).status_code == 404
        with svc.app.state.manager.db.session() as s:
            assert s.scalars(select(Event).where(Event.run_id == done_id)).all() == []
        assert (await c.delete(f"{API}/runs/{done_id}", headers=AUTH)).status_code == 404

        # the current calibration's run is kept (a calibration row as POST /runs/{id}/apply stores it)
        with svc.app.state.manager.db.session() as s:
            bench = s.get(Run, busy).bench
            s.add(Calibration(bench=bench, run_id=busy, method="legs", software_version="test", payload={}))
        r = await c.delete(f"{API}/runs/{busy}", headers=AUTH)
        assert r.status_code == 409 and "current calibration" in r.text, r.text
        assert (data / "runs" / busy).is_dir()

        # a dataset that a failed run may still read is kept until that run is deleted
        ds = (await c.post(f"{API}/datasets", content=z, headers=ZIP)).json()
        r = await c.post(f"{API}/runs", json={"dataset": ds["id"], "methods": ["combined"]}, headers=AUTH)
        offline = r.json()["id"]
        assert (await wait_state(c, offline))["state"] == "failed"
        assert (await c.delete(f"{API}/datasets/{ds['id']}")).status_code == 401
        r = await c.delete(f"{API}/datasets/{ds['id']}", headers=AUTH)
        assert r.status_code == 409 and offline in r.text, r.text
        assert (await c.delete(f"{API}/runs/{offline}", headers=AUTH)).status_code == 200
        r = await c.delete(f"{API}/datasets/{ds['id']}", headers=AUTH)
        assert r.status_code == 200 and r.json()["freed_bytes"] > 0, r.text
        assert not (data / "datasets" / ds["id"]).exists()
        assert (await c.get(f"{API}/datasets/{ds['id']}")).status_code == 404
    finally:
        await c.aclose()
        await svc.stop()


async def _pause_after(c, rid: str, frames: int) -> None:
    async with asyncio.timeout(60):
        while (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < frames:
            await asyncio.sleep(0.01)
    assert (await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)).status_code == 200


async def test_disk_full_mid_acquisition_fails_the_run_and_resumes(tmp_path, sim, monkeypatch):
    """The disk fills between two frames (files and database alike): the run ends ``failed`` naming the full disk
    (reported at once, recorded in the database as soon as it takes writes again), new runs and resumes get 507
    while it is full; with room again the run resumes from its frames on disk to done, its events numbered without
    a gap."""
    flag = tmp_path / "disk-full"
    monkeypatch.setenv(DISK_FULL_ENV, str(flag))
    svc = await start_service(make_settings(tmp_path, sim), sim)
    c, data, db = svc.client, svc.settings.data_dir, svc.app.state.manager.db
    try:
        r = await c.post(f"{API}/runs", json={"plan": "full", "methods": []}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid, total = r.json()["id"], r.json()["progress"]["total"]
        await _pause_after(c, rid, 3)
        await asyncio.sleep(0.3)  # the pose under way ends and its frame is written
        assert (await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)).status_code == 202
        flag.write_text(str(data.resolve()))  # the disk fills as the next pose is being reached
        run = await wait_state(c, rid, timeout=30)
        assert run["state"] == "failed" and run["error"].startswith("disk full"), run
        assert "during the acquisition" in run["error"] and "resume" in run["error"]
        with db.session() as s:  # the database refuses writes: the end is held
            assert s.get(Run, rid).state == "acquiring"
        listed = (await c.get(f"{API}/runs", params={"state": "failed"})).json()
        assert [r["id"] for r in listed] == [rid] and (await c.get(f"{API}/runs?state=acquiring")).json() == []
        r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
        assert r.status_code == 507 and r.json()["detail"]["limit"] == "disk full", r.text
        r = await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)
        assert r.status_code == 507, r.text
        r = await c.delete(f"{API}/runs/{rid}", headers=AUTH)
        assert r.status_code == 409 and "not recorded yet" in r.text, r.text

        flag.unlink()  # room again
        async with asyncio.timeout(10):
            while True:
                with db.session() as s:
                    row = s.get(Run, rid)
                    if row.state == "failed":
                        break
                await asyncio.sleep(0.1)
        assert row.error == run["error"]
        on_disk = json.loads((data / "runs" / rid / "dataset" / "dataset.json").read_text())["frames"]
        assert 3 <= len(on_disk) < total
        r = await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)
        assert r.status_code == 202, r.text
        run = await wait_state(c, rid)
        assert run["state"] == "done" and run["progress"]["done"] == total, run
        doc = json.loads((data / "runs" / rid / "dataset" / "dataset.json").read_text())
        assert len(doc["frames"]) == total
        evs = await read_events(c, rid)
        assert [e["seq"] for e in evs] == list(range(1, len(evs) + 1))
        states = [e["data"]["state"] for e in evs if e["type"] == "state"]
        assert states[-4:] == ["failed", "queued", "acquiring", "done"], states
    finally:
        await c.aclose()
        await svc.stop()


def _first_frames(z: bytes, n: int) -> bytes:
    """The dataset archive cut to its first ``n`` frames (extraction's cost grows with them)."""
    src = zipfile.ZipFile(io.BytesIO(z))
    doc = json.loads(src.read("dataset/dataset.json"))
    doc["frames"] = doc["frames"][:n]
    keep = {f"dataset/{f['image']}" for f in doc["frames"] if f.get("image")}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("dataset/dataset.json", json.dumps(doc))
        for name in keep:
            zf.writestr(name, src.read(name))
    return buf.getvalue()


async def test_disk_full_during_extraction_fails_the_run_naming_it(tmp_path, sim, monkeypatch, rendered_zip):
    """The extraction's process cannot write observations.json: the run ends ``failed`` naming the full disk (not
    an internal error); with room again it resumes and the extraction writes them (the fit of 12 frames then fails
    for its own reason: the point is the extraction's output)."""
    flag = tmp_path / "disk-full"
    monkeypatch.setenv(DISK_FULL_ENV, str(flag))
    svc = await start_service(make_settings(tmp_path, sim), sim)
    c, data = svc.client, svc.settings.data_dir
    try:
        ds = (await c.post(f"{API}/datasets", content=_first_frames(rendered_zip, 12), headers=ZIP)).json()
        flag.write_text(str((data / "runs").resolve()))  # the runs' files only: the database still writes
        r = await c.post(f"{API}/runs", json={"dataset": ds["id"], "methods": ["combined"]}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        run = await wait_state(c, rid)
        assert run["state"] == "failed" and run["error"].startswith("disk full"), run
        assert "during the extraction" in run["error"] and "observations.json" in run["error"], run["error"]
        assert not (data / "runs" / rid / "observations.json").exists()
        flag.unlink()
        assert (await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)).status_code == 202
        run = await wait_state(c, rid)
        assert (data / "runs" / rid / "observations.json").is_file()
        assert run["state"] in ("done", "failed") and not (run["error"] or "").startswith("disk full"), run
        evs = await read_events(c, rid)
        assert [e["data"]["state"] for e in evs if e["type"] == "state"][-4:-1] == [
            "queued",
            "extracting",
            "calibrating",
        ]
    finally:
        await c.aclose()
        await svc.stop()


@pytest.mark.parametrize("key", ["data_quota_bytes", "min_free_bytes"])
def test_disk_settings_have_defaults_and_refuse_negative_values(key):
    from service.settings import Settings

    s = Settings()
    assert getattr(s, key) > 0
    with pytest.raises(ValueError, match=key):
        Settings(**{key: -1})
