"""The crash matrix: the service (a real process) is killed with SIGKILL in every state a run goes through, started
again and the run resumed each time; the run ends done, every frame and event is kept, and nothing moves once the
frames are all on disk.

The kills are exact: ``I4CAL_CRASH_AT`` (:mod:`service.failpoints`) makes the process SIGKILL itself right after a
transition is committed (``state:queued``, ``state:acquiring``, ``state:extracting``, ``state:calibrating``) or right
after the last frame is written (``stage:acquired``: every frame on disk, the run not yet extracting); one more kill is
sent from outside at an arbitrary moment of the acquisition (mid-motion). The simulated bench (real Modbus server on
loopback, image-level twin) lives in the test's process and counts every motion its axes start.
"""

from __future__ import annotations

import asyncio
import time

import httpx
import pytest

from calib.formats.dataset import Dataset
from drivers.sim.bench import SimBench
from tests.service.conftest import AUTH, read_events, wait_state
from tests.service.procs import ServiceProcess, free_port, write_config

API = "/api/v1"
SIZES = {"n_base": 6, "n_fit": 10, "n_lock": 4, "n_validation": 4, "line_samples": 11}
TOTAL = 53  # frames of the 'full' plan at these sizes


@pytest.fixture
async def twin() -> SimBench:
    async with SimBench(port=0, seed=3) as sim:
        yield sim


def count_motions(sim: SimBench, monkeypatch) -> dict[str, int]:
    """Count the motions the simulated axes start (moves and homings), whoever commands them."""
    n = {"moves": 0}
    cls = type(sim.mechanism.axes[0])
    for name in ("start", "home"):
        orig = getattr(cls, name)

        def counted(self, *args, _orig=orig, **kw):
            n["moves"] += 1
            return _orig(self, *args, **kw)

        monkeypatch.setattr(cls, name, counted)
    return n


def moving(sim: SimBench) -> bool:
    sim.mechanism.update()
    return any(ax.moving for ax in sim.mechanism.axes)


async def _post(c: httpx.AsyncClient, path: str, **kw) -> httpx.Response | None:
    """POST that tolerates the server dying before it answers (a crash point inside the request)."""
    try:
        return await c.post(path, headers=AUTH, **kw)
    except httpx.TransportError:
        return None


async def _state(url: str, rid: str) -> dict:
    async with httpx.AsyncClient(base_url=url, timeout=30) as c:
        return (await c.get(f"{API}/runs/{rid}")).json()


async def test_kill_in_every_state_then_resume(tmp_path, twin, monkeypatch):
    cam = tmp_path / "camera.json"
    twin.renderer.settings.camera().save(cam)
    port = free_port()
    cfg = write_config(
        tmp_path / "service.toml",
        twin,
        tmp_path / "data",
        port,
        plan_sizes=SIZES,
        camera_file=cam,
        camera={"timeout_s": 30.0},  # the twin renders in this process: slow when the machine is loaded
    )
    svc = ServiceProcess(cfg, port)
    motions = count_motions(twin, monkeypatch)
    url = svc.url
    try:
        # 1. killed right after the run is queued (inside the POST): after the restart the run is interrupted
        await svc.start(crash_at="state:queued")
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            await _post(c, f"{API}/runs", json={"plan": "full", "methods": ["combined"]})
        assert await svc.wait_exit() == -9
        await svc.start(crash_at="state:acquiring")
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            runs = (await c.get(f"{API}/runs")).json()
            assert len(runs) == 1 and runs[0]["state"] == "interrupted", runs
            rid = runs[0]["id"]
            # 2. killed right after the acquisition starts: nothing has moved yet
            await _post(c, f"{API}/runs/{rid}/resume")
        assert await svc.wait_exit() == -9
        assert motions["moves"] == 0

        # 3. killed from outside while the robot acquires (mid-motion, frames being written)
        await svc.start()
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            assert (await c.get(f"{API}/runs/{rid}")).json()["state"] == "interrupted"
            assert (await _post(c, f"{API}/runs/{rid}/resume")).status_code == 202
            async with asyncio.timeout(120):
                while (run := (await c.get(f"{API}/runs/{rid}")).json())["progress"]["done"] < 8:
                    assert run["state"] in ("queued", "acquiring"), run["error"]
                    await asyncio.sleep(0.01)
        svc.kill()
        ds_dir = tmp_path / "data" / "runs" / rid / "dataset"
        kept = len(Dataset.open(ds_dir).frames)
        assert 8 <= kept < TOTAL
        stop_by = time.monotonic() + 1.0  # the controller's watchdog stops the axes of a dead host: within 1 s
        while moving(twin) and time.monotonic() < stop_by:
            await asyncio.sleep(0.01)
        assert not moving(twin)

        # 4. killed right after the last frame is written, before extraction starts
        await svc.start(crash_at="stage:acquired")
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            assert (await c.get(f"{API}/runs/{rid}")).json()["state"] == "interrupted"
            assert (await _post(c, f"{API}/runs/{rid}/resume")).status_code == 202
        assert await svc.wait_exit() == -9
        ds = Dataset.open(ds_dir)
        assert len(ds.frames) == TOTAL
        moved = motions["moves"]
        assert moved > 0

        # 5.-6. killed as extraction starts, then as the fit starts: every resume from here on must not move
        for crash in ("state:extracting", "state:calibrating"):
            await svc.start(crash_at=crash)
            async with httpx.AsyncClient(base_url=url, timeout=30) as c:
                assert (await c.get(f"{API}/runs/{rid}")).json()["state"] == "interrupted"
                assert (await _post(c, f"{API}/runs/{rid}/resume")).status_code == 202
            assert await svc.wait_exit() == -9
            assert motions["moves"] == moved, f"the robot moved on a resume after {crash}"

        # 7. the last resume ends the run
        await svc.start()
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            assert (await _post(c, f"{API}/runs/{rid}/resume")).status_code == 202
            run = await wait_state(c, rid, timeout=120)
            assert run["state"] == "done", run
            # every stage's timing kept across the kills (each stored as its stage ended), not only the last one's
            assert {"acquisition_s", "extraction_s", "calibration_s", "total_s"} <= set(run["timings"]), run["timings"]
            assert run["timings"]["total_s"] >= sum(run["timings"][k] for k in ("extraction_s", "calibration_s"))
            res = (await c.get(f"{API}/runs/{rid}/result")).json()
            assert res["methods"]["combined"]["converged"]
            evs = await read_events(c, rid)
        assert motions["moves"] == moved
        # every frame kept, once each, in the plan's order
        ds = Dataset.open(ds_dir)
        assert len(ds.frames) == TOTAL
        assert all(ds.load_image(i).size > 0 for i in range(TOTAL))
        # every event kept: numbered without a gap; the states tell the whole story
        assert [e["seq"] for e in evs] == list(range(1, len(evs) + 1))
        states = [e["data"]["state"] for e in evs if e["type"] == "state"]
        assert states == [
            "queued", "interrupted",  # 1: killed in the POST
            "queued", "acquiring", "interrupted",  # 2
            "queued", "acquiring", "interrupted",  # 3: killed mid-acquisition
            "queued", "acquiring", "interrupted",  # 4: killed after the last frame
            "queued", "extracting", "interrupted",  # 5: the frames are complete: no acquisition again
            "queued", "extracting", "calibrating", "interrupted",  # 6
            "queued", "calibrating", "done",  # 7: the observations are on disk: no extraction again
        ]  # fmt: skip
    finally:
        svc.stop()
