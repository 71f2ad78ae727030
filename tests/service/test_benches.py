"""A lab running several benches: one service per bench, all sharing one database (SQLite file, or PostgreSQL when a
cluster can be started). Runs and calibrations carry their bench; each service controls only its own runs, recovers
only its own after a restart, and gives each bench its own current calibration."""

from __future__ import annotations

import asyncio

import pytest

from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig
from tests.service.conftest import AUTH, empty_database_url, make_settings, start_service, wait_state
from tests.service.held import HELD_GRAB, HeldRenderer

API = "/api/v1"


@pytest.fixture(params=["sqlite", "postgres"])
def shared_db(request, tmp_path) -> str:
    return empty_database_url(request, tmp_path, "lab.db")


async def test_two_benches_share_a_database(tmp_path, sim, shared_db, rendered_zip):
    camera = HeldRenderer()
    other = SimBench(
        port=0,
        renderer=camera,
        seed=2,
        axis_config=AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0),
    )
    await other.start()
    sa = make_settings(tmp_path / "a", sim, database_url=shared_db, bench_name="bench-a", extraction_workers=1)
    sb = make_settings(
        tmp_path / "b",
        other,
        database_url=shared_db,
        bench_name="bench-b",
        extraction_workers=1,
        plan_sizes={"n_fit": 30},
        bench_overrides=HELD_GRAB,
    )
    a = await start_service(sa, sim)
    b = await start_service(sb, other)
    ca, cb = a.client, b.client
    try:
        assert (await ca.get("/healthz")).json()["bench"] == "bench-a"
        # each bench gets a calibration from an offline run (uploaded dataset, real images)
        cur, uploaded = {}, {}
        for svc, c in (("bench-a", ca), ("bench-b", cb)):
            ds = uploaded[svc] = (
                await c.post(
                    f"{API}/datasets", content=rendered_zip, headers={"Content-Type": "application/zip", **AUTH}
                )
            ).json()["id"]
            r = await c.post(f"{API}/runs", json={"dataset": ds, "methods": ["combined"]}, headers=AUTH)
            assert r.status_code == 202, r.text
            run = await wait_state(c, r.json()["id"], timeout=300)
            assert run["state"] == "done" and run["bench"] == run["service"] == svc, run
            r = await c.post(f"{API}/runs/{run['id']}/apply", headers=AUTH)
            assert r.status_code == 201 and r.json()["bench"] == svc
            cur[svc] = r.json()
        # a dataset uploaded to one service is on that service's disk only
        r = await cb.post(f"{API}/runs", json={"dataset": uploaded["bench-a"], "methods": ["combined"]}, headers=AUTH)
        assert r.status_code == 422 and "dataset" in r.text
        # each service's current calibration is its own bench's; any bench's can be asked for
        assert (await ca.get(f"{API}/calibration/current")).json()["id"] == cur["bench-a"]["id"]
        assert (await cb.get(f"{API}/calibration/current")).json()["id"] == cur["bench-b"]["id"]
        got = (await ca.get(f"{API}/calibration/current", params={"bench": "bench-b"})).json()
        assert got["id"] == cur["bench-b"]["id"] and got["bench"] == "bench-b"
        assert (await ca.get(f"{API}/calibration/current", params={"bench": "bench-c"})).status_code == 404
        assert (await ca.get(f"{API}/calibration/current", params={"bench": "../x"})).status_code == 422
        hist = (await cb.get(f"{API}/calibration/history")).json()
        assert {h["bench"] for h in hist} == {"bench-a", "bench-b"}
        assert [
            h["bench"] for h in (await cb.get(f"{API}/calibration/history", params={"bench": "bench-a"})).json()
        ] == ["bench-a"]

        # bench-b acquires; bench-a's service sees the run but cannot control it, and restarting it leaves it alone
        camera.hold_at_pose(4)  # bench-b's fourth pose waits for its frame until bench-a's service has restarted
        rid = (await cb.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)).json()["id"]
        await camera.wait_held()
        async with asyncio.timeout(30):
            while (await cb.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < 2:
                await asyncio.sleep(0.02)
        listed = (await ca.get(f"{API}/runs", params={"bench": "bench-b"})).json()
        assert rid in [x["id"] for x in listed] and all(x["bench"] == "bench-b" for x in listed)
        for action in ("abort", "resume"):
            r = await ca.post(f"{API}/runs/{rid}/{action}", headers=AUTH)
            assert r.status_code == 409 and "bench-b" in r.text, (action, r.text)
        await ca.aclose()
        await a.stop()
        a = await start_service(sa, sim)  # its start-up recovery must not touch bench-b's running run
        ca = a.client
        assert (await ca.get(f"{API}/runs/{rid}")).json()["state"] == "acquiring"
        camera.release.set()
        run = await wait_state(cb, rid, timeout=120)
        assert run["state"] == "done" and run["progress"]["done"] == 30
    finally:
        camera.release.set()
        await ca.aclose()
        await cb.aclose()
        await a.stop()
        await b.stop()
        await other.stop()
