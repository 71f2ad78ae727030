"""Live progress of extraction and fitting over Server-Sent Events, the live frame, and aborting a computation.

An uploaded rendered dataset (``rendered_zip``: image-level twin, reduced 'full' plan, known intrinsics) is
calibrated offline: the extraction and the fits run in child processes (service.jobs) that report every frame and
every fit iteration; the service batches them (at most one event of a kind per LIVE_INTERVAL_S).
"""

from __future__ import annotations

import asyncio
import itertools
import os
from datetime import datetime

from calib.vision.extract import ROD_PHASES
from service.runs import LIVE_INTERVAL_S
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state

API = "/api/v1"
METHODS = ["combined", "end-effector", "legs"]


async def _upload(c, data: bytes) -> str:
    r = await c.post(f"{API}/datasets", content=data, headers={"Content-Type": "application/zip", **AUTH})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _t(ev: dict) -> float:
    return datetime.fromisoformat(ev["t"]).timestamp()


async def test_offline_run_streams_frames_and_fit_iterations(tmp_path, sim, rendered_zip):
    svc = await start_service(make_settings(tmp_path, sim, extraction_workers=2), sim)
    c = svc.client
    try:
        ds = await _upload(c, rendered_zip)
        r = await c.post(f"{API}/runs", json={"dataset": ds, "methods": METHODS}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        live = None
        async with asyncio.timeout(300):
            while True:
                run = (await c.get(f"{API}/runs/{rid}")).json()
                if run["state"] not in ("queued", "extracting"):
                    break
                if live is None and run["state"] == "extracting" and run["progress"]["last_frame"] is not None:
                    drawn = await c.get(f"{API}/runs/{rid}/frames/latest")
                    raw = await c.get(f"{API}/runs/{rid}/frames/latest", params={"annotate": "false"})
                    if (await c.get(f"{API}/runs/{rid}")).json()["state"] == "extracting":
                        live = (run["progress"]["last_frame"], drawn, raw)
                await asyncio.sleep(0.05)
        run = await wait_state(c, rid, timeout=300)
        assert run["state"] == "done", run
        res = (await c.get(f"{API}/runs/{rid}/result")).json()
        assert all(res["methods"][m]["converged"] for m in METHODS)

        # the live view showed an extracted frame with its detections drawn, not the raw one
        assert live is not None, "never saw the run extracting"
        _, drawn, raw = live
        assert drawn.status_code == raw.status_code == 200 and drawn.content[:4] == b"\x89PNG"
        assert drawn.content != raw.content

        evs = await read_events(c, rid)
        obs_frames = {f["index"] for f in (await c.get(f"{API}/runs/{rid}/frames")).json()}
        frames_evs = [e for e in evs if e["type"] == "frames"]
        items = [it for e in frames_evs for it in e["data"]["items"]]
        assert all(e["data"]["count"] == len(e["data"]["items"]) for e in frames_evs)
        assert sorted(it["frame"] for it in items if it["stage"] == "board") == sorted(obs_frames)
        # a frame measured again (the rods' prediction refitted to the first pass) is reported again: its last
        # report is the one that counts
        rods_items = list({it["frame"]: it for it in items if it["stage"] == "rods"}.values())
        assert sorted(it["frame"] for it in rods_items) == sorted(obs_frames)
        assert sum(it["board"] for it in rods_items) > len(rods_items) // 2
        assert all(it["corners"] >= 6 for it in rods_items if it["board"])
        read = [it for it in rods_items if it["phase"] in ROD_PHASES]  # the others' rods are not read: 0 of 0
        assert read and sum(it["rods"] for it in read) > 4 * len(read)
        assert all(it["rods"] == it["rods_total"] == 0 for it in rods_items if it["phase"] not in ROD_PHASES)
        assert all("detections" not in it for it in items)  # kept in memory for the live frame, not stored
        # what the events said per frame is what the observations say
        listed = {f["index"]: f for f in (await c.get(f"{API}/runs/{rid}/frames")).json()}
        for it in rods_items:
            assert it["rods"] == listed[it["frame"]]["rods"] and it["board"] == listed[it["frame"]]["board"]

        iters = [it for e in evs if e["type"] == "iterations" for it in e["data"]["items"]]
        for m in METHODS:
            mine = [it for it in iters if it["method"] == m]
            assert len(mine) >= 2, m
            assert all(it["cost"] >= 0 for it in mine)
        fits = [(e["data"]["method"], e["data"]["state"]) for e in evs if e["type"] == "fit"]
        assert fits == [(m, s) for m in METHODS for s in ("start", "done")]
        # each method's iterations come between its start and its end
        current = None
        for e in evs:
            if e["type"] == "fit":
                current = e["data"]["method"] if e["data"]["state"] == "start" else None
            elif e["type"] == "iterations":
                assert {it["method"] for it in e["data"]["items"]} == {current}

        # throttled: within each kind, successive batches are LIVE_INTERVAL_S apart (the last one of a stage may
        # be flushed early at the stage's end)
        for kind in ("frames", "iterations"):
            ts = [_t(e) for e in evs if e["type"] == kind]
            gaps = [b - a for a, b in itertools.pairwise(ts)]
            early = sum(g < LIVE_INTERVAL_S - 0.02 for g in gaps)
            assert early <= (1 if kind == "frames" else 2 * len(METHODS)), (kind, gaps)
        ext = [
            e
            for e in evs
            if e["type"] in ("frames", "progress")
            and e["data"].get("stage") != "acquisition"
            and e["data"].get("stage") != "calibration"
        ]
        span = _t(ext[-1]) - _t(ext[0])
        assert len(ext) <= 2 * (span / LIVE_INTERVAL_S + 2), (len(ext), span)
    finally:
        await c.aclose()
        await svc.stop()


async def test_abort_during_extraction_kills_the_process_group(tmp_path, sim, rendered_zip):
    svc = await start_service(make_settings(tmp_path, sim, extraction_workers=2), sim)
    c = svc.client
    manager = svc.app.state.manager
    try:
        ds = await _upload(c, rendered_zip)
        rid = (await c.post(f"{API}/runs", json={"dataset": ds, "methods": ["combined"]}, headers=AUTH)).json()["id"]
        async with asyncio.timeout(120):
            while True:
                run = (await c.get(f"{API}/runs/{rid}")).json()
                a = manager.active.get(rid)
                if run["state"] == "extracting" and run["progress"]["done"] > 0 and a is not None and a.job:
                    break
                assert run["state"] in ("queued", "extracting"), run
                await asyncio.sleep(0.02)
        pid = a.job.process.pid
        os.killpg(pid, 0)  # the extraction's process group exists
        r = await c.post(f"{API}/runs/{rid}/abort", headers=AUTH)
        assert r.status_code == 202
        run = await wait_state(c, rid, timeout=10)
        assert run["state"] == "aborted" and not run["has_result"]
        async with asyncio.timeout(10):
            while True:
                try:
                    os.killpg(pid, 0)
                except ProcessLookupError:
                    break
                await asyncio.sleep(0.05)
        assert not (svc.settings.data_dir / "runs" / rid / "observations.json").exists()
    finally:
        await c.aclose()
        await svc.stop()
