"""Suspenders over REST on the simulated bench (real HTTP, real Modbus, real SQLite): the light goes off for a few
frames in the middle of a run (``CameraFaults.dark``); the run suspends itself at the pose, says why (a ``suspended``
event, the run's ``progress.suspended``), resumes by itself when the light is back, and ends ``done`` with no dark
frame in its dataset. With the suspenders switched off, the dark frames are recorded (what the acquisition did before
it had suspenders)."""

from __future__ import annotations

import asyncio

import numpy as np

from calib.formats.dataset import Dataset
from drivers.acquisition.suspenders import mean_level
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state

API = "/api/v1"
#: TinyRenderer's frames are a flat grey of 40/255; a dark frame is 5% of that
LIT_LEVEL = 40 / 255


async def _run_with_light_off(tmp_path, sim, suspenders: dict, watch=None) -> tuple[dict, list[dict], list[float]]:
    svc = await start_service(
        make_settings(tmp_path, sim, plan_sizes={"n_fit": 6}, bench_overrides={"suspenders": suspenders}), sim
    )
    c = svc.client
    try:
        # the first grab (before any motion) and two poses lit, then the light off for 4 grabs
        sim.frames.faults.scene_after, sim.frames.faults.dark = 3, 4
        r = await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        if watch is not None:
            await watch(c, rid)
        run = await wait_state(c, rid, timeout=60)
        events = await read_events(c, rid)
        m = svc.app.state.manager
        ds = Dataset.open(m.dataset_path(m.get(rid)))
        levels = [mean_level(ds.load_image(i)) for i in range(len(ds.frames))]
        return run, events, levels
    finally:
        await c.aclose()
        await svc.stop()


async def test_a_run_suspends_while_the_light_is_off_and_resumes_by_itself(tmp_path, sim):
    seen: dict = {}

    async def watch(c, rid) -> None:  # the run's status says why while it holds the robot
        async with asyncio.timeout(30):
            while True:
                run = (await c.get(f"{API}/runs/{rid}")).json()
                if run["progress"]["suspended"] or run["state"] not in ("acquiring", "queued"):
                    seen.update(run)
                    return
                await asyncio.sleep(0.005)

    run, events, levels = await _run_with_light_off(tmp_path, sim, {"poll_s": 0.05, "clear_frames": 2}, watch)
    assert run["state"] == "done", run
    assert "dark" in (seen["progress"]["suspended"] or ""), seen
    suspended = [e["data"] for e in events if e["type"] == "suspended"]
    cleared = [e["data"] for e in events if e["type"] == "suspension_cleared"]
    assert len(suspended) == 1 and suspended[0]["reason"].startswith("brightness: the image is dark")
    assert suspended[0]["frame"] == 2  # held at the third pose: two frames written before
    assert len(cleared) == 1 and "cleared after" in cleared[0]["message"]
    # every frame of the plan recorded, none of them dark: the frame grabbed in the dark was grabbed again
    assert len(levels) == run["progress"]["total"] == 6
    np.testing.assert_allclose(levels, LIT_LEVEL, atol=2 / 255)
    assert sim.frames.faults.dark == 0


async def test_without_suspenders_the_dark_frames_are_recorded(tmp_path, sim):
    run, events, levels = await _run_with_light_off(tmp_path, sim, {"enabled": False})
    assert run["state"] == "done"
    assert not [e for e in events if e["type"] == "suspended"]
    assert sum(level < 0.02 for level in levels) == 4


async def test_a_check_suspends_and_says_why_while_the_light_is_off(tmp_path, sim):
    """A check acquires with the same suspenders: held while dark, its status says why, no dark frame written. (The
    bench's frames are TinyRenderer's, without a board: the fit that follows fails, which this test does not need.)"""
    from tests.service.test_check import _in_force

    svc = await start_service(
        make_settings(tmp_path, sim, bench_overrides={"suspenders": {"poll_s": 0.05, "clear_frames": 3}}), sim
    )
    c = svc.client
    try:
        from service.checks.plan import check_plan_for_bench

        cfg = svc.app.state.manager.bench.config
        doc = await asyncio.to_thread(_in_force, cfg)
        # designed before the request (the service's plan cache): the request then starts at once
        await asyncio.to_thread(check_plan_for_bench, cfg, 60.0, svc.settings.data_dir / "check-plans", 0, None)
        sim.frames.faults.scene_after, sim.frames.faults.dark = 3, 4
        r = await c.post(f"{API}/checks", json={"calibration": doc.model_dump(mode="json")}, headers=AUTH)
        assert r.status_code == 202, r.text
        cid = r.json()["id"]
        why = None
        async with asyncio.timeout(60):
            while (check := (await c.get(f"{API}/checks/{cid}")).json())["state"] == "running":
                why = why or check["suspended"]
                await asyncio.sleep(0.005)
        assert why is not None and why.startswith("brightness: the image is dark"), check
        ds = Dataset.open(svc.settings.data_dir / "checks" / cid / "dataset")
        levels = [mean_level(ds.load_image(i)) for i in range(len(ds.frames))]
        steps = svc.app.state.checks.get(cid).plan["steps"]
        assert len(levels) == len(steps) and sim.frames.faults.dark == 0  # the whole plan, the light back on
        np.testing.assert_allclose(levels, LIT_LEVEL, atol=2 / 255)
    finally:
        await c.aclose()
        await svc.stop()
