"""Resume under faults, against the real service (uvicorn, HTTP) and the simulated bench (real Modbus on loopback):
a refused resume leaves the run as it was; a run failed on a device fault resumes from its last good pose."""

from __future__ import annotations

import asyncio

from calib.formats.dataset import Dataset
from calib.formats.plan import Plan
from drivers.acquisition.acquire import plan_units
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state
from tests.service.held import HELD_GRAB, hold_camera

API = "/api/v1"


async def _until_done_at_least(c, rid: str, n: int) -> None:
    async with asyncio.timeout(30):
        while (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < n:
            await asyncio.sleep(0.02)


async def test_refused_resume_leaves_the_run_as_it_was(tmp_path, sim):
    """A resume answered 409 (the bench is held by another run) leaves the run as it was, never 'queued' forever."""
    settings = make_settings(tmp_path, sim, plan_sizes={"n_fit": 30}, bench_overrides=HELD_GRAB)
    camera = hold_camera(sim)
    camera.hold_at_pose(4)  # the run waits on its fourth pose's frame while the service stops
    svc = await start_service(settings, sim)
    try:
        rid = (await svc.client.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)).json()[
            "id"
        ]
        await camera.wait_held()
        await _until_done_at_least(svc.client, rid, 2)
    finally:
        await svc.client.aclose()
        await svc.stop()  # the service stops mid-run: the run is interrupted
        camera.release.set()
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        assert (await c.get(f"{API}/runs/{rid}")).json()["state"] == "interrupted"
        camera.hold_at_pose(1)  # the other run holds the bench, waiting on its first pose's frame
        other = (await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)).json()["id"]
        await camera.wait_held()
        r = await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)
        assert r.status_code == 409 and "holds the bench" in r.text
        run = (await c.get(f"{API}/runs/{rid}")).json()
        assert run["state"] == "interrupted", run
        states = [e["data"]["state"] for e in await read_events(c, rid) if e["type"] == "state"]
        assert states[-1] == "interrupted" and "queued" not in states[1:]  # no state event from the refused resume
        # a run that is done cannot be resumed either, and stays done
        assert (await c.post(f"{API}/runs/{other}/abort", headers=AUTH)).status_code == 202
        assert (await wait_state(c, other))["state"] == "aborted"
        camera.release.set()
        assert (await c.post(f"{API}/runs/{other}/resume", headers=AUTH)).status_code == 409
        assert (await c.get(f"{API}/runs/{other}")).json()["state"] == "aborted"
        # the bench free again: the resume is accepted and the run completes
        assert (await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)).status_code == 202
        assert (await wait_state(c, rid, timeout=60))["state"] == "done"
        assert len(Dataset.open(tmp_path / "data" / "runs" / rid / "dataset").frames) == 30
    finally:
        camera.release.set()
        await c.aclose()
        await svc.stop()


async def test_failed_run_resumes_from_its_last_good_pose(tmp_path, sim):
    """A run failed on a device fault, which says "resume the run to continue from this pose", resumes at the failed
    pose: every pose recorded once, in the plan's order."""
    # a short grab timeout: the silent camera fails the run after two of them (the grab and its retry)
    settings = make_settings(tmp_path, sim, plan_sizes={"n_fit": 12}, bench_overrides={"camera": {"timeout_s": 1.0}})
    camera = hold_camera(sim)

    def silent_after(frame: int) -> None:  # the camera goes silent after pose 4's frame: the run fails
        if frame == 1 + 4:
            sim.frames.faults.timeouts = 1000

    camera.on_frame = silent_after
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        rid = (await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)).json()["id"]
        run = await wait_state(c, rid, timeout=60)
        assert run["state"] == "failed", run
        assert "resume the run to continue from this pose" in run["error"]
        kept = len(Dataset.open(tmp_path / "data" / "runs" / rid / "dataset").frames)
        assert 3 <= kept < 12
        sim.mechanism.update()
        assert not any(ax.moving for ax in sim.mechanism.axes)
        sim.frames.faults.timeouts = 0  # the cause is cleared
        r = await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)
        assert r.status_code == 202, r.text
        run = await wait_state(c, rid, timeout=60)
        assert run["state"] == "done" and run["error"] is None, run
        ds = Dataset.open(tmp_path / "data" / "runs" / rid / "dataset")
        units = plan_units(Plan.model_validate(ds.document.model_extra["plan"]))  # the plan the run executed
        assert len(ds.frames) == len(units) == 12
        for f, u in zip(ds.frames, units, strict=True):  # once each, in order: the failed pose was redone, not skipped
            assert f.phase == u.phase
            assert max(abs(a - b) for a, b in zip(f.model_extra["q_target"], u.q, strict=True)) < 1e-12
        evs = await read_events(c, rid)
        states = [e["data"]["state"] for e in evs if e["type"] == "state"]
        assert states == ["queued", "acquiring", "failed", "queued", "acquiring", "done"]
        starts = [e["data"]["message"] for e in evs if "starting at" in (e["data"].get("message") or "")]
        assert starts[-1].startswith(f"starting at pose {kept + 1}/12")
        assert [e["seq"] for e in evs] == list(range(1, len(evs) + 1))  # every event kept, none lost
    finally:
        await c.aclose()
        await svc.stop()
