"""``sim_bench = true``: the service's simulated bench runs in its own process (as hardware would), and stops with
the service."""

from __future__ import annotations

from service.auth import hash_token
from service.settings import Settings
from tests.service.conftest import AUTH, SMALL, TOKEN, read_events, start_service, wait_state

API = "/api/v1"


async def test_sim_bench_in_its_own_process(tmp_path):
    import os

    settings = Settings(
        data_dir=tmp_path / "data",
        sim_bench=True,
        sim_fast_renderer=True,
        bench_name="sim-1",
        token_hashes=[hash_token(TOKEN)],
        plan_sizes=SMALL,
    )
    svc = await start_service(settings, None)
    c = svc.client
    manager = svc.app.state.manager
    try:
        sim = manager.bench.sim
        assert sim.process.is_alive() and sim.process.pid != os.getpid()
        dev = (await c.get(f"{API}/devices")).json()
        assert dev["simulated"] and dev["bench"] == "sim-1"
        assert dev["devices"][0]["uri"] == sim.uris["actuators"]
        rid = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()["id"]
        run = await wait_state(c, rid, timeout=60)
        assert run["state"] == "done" and run["progress"]["done"] == run["progress"]["total"] > 0
        assert len((await c.get(f"{API}/runs/{rid}/frames")).json()) == run["progress"]["total"]
        assert any(e["type"] == "progress" for e in await read_events(c, rid))
    finally:
        await c.aclose()
        await svc.stop()
    sim.process.join(10)
    assert not sim.process.is_alive()
