"""Checks over REST on the simulated bench (real HTTP, real Modbus, the image-level twin, real SQLite): a run of the
check plan applied as the bench's calibration; a check holds; a check is refused (409) while a run holds the bench;
the bench's legs then grow by six predicted std of the check's change (``SimBench.set_drift``): the check says
``drifted`` naming L, its update is applied (``POST /api/v1/checks/{id}/apply``) and becomes the current
calibration, and the next check holds. Every check is listed and stored."""

from __future__ import annotations

import asyncio
import math

import pytest

from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig
from drivers.sim.render import RenderSettings
from tests.service.conftest import AUTH, make_settings, start_service, wait_state

API = "/api/v1"
DRIFT_IN_STD = 6.0


async def _finished(client, check_id: str, timeout: float = 120.0) -> dict:
    async with asyncio.timeout(timeout):
        while True:
            c = (await client.get(f"{API}/checks/{check_id}")).json()
            if c["state"] != "running":
                return c
            await asyncio.sleep(0.2)


async def _check(client) -> dict:
    r = await client.post(f"{API}/checks", json={}, headers=AUTH)
    assert r.status_code == 202, r.text
    c = await _finished(client, r.json()["id"])
    assert c["state"] == "done", c
    return c


@pytest.fixture
async def twin_service(tmp_path):
    sim = SimBench(port=0, seed=3, axis_config=AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0))
    await sim.start()
    RenderSettings().camera().save(tmp_path / "camera.json")
    svc = await start_service(make_settings(tmp_path, sim, camera_file=tmp_path / "camera.json"), sim)
    try:
        yield svc
    finally:
        await svc.client.aclose()
        await svc.stop()
        await sim.stop()


async def test_drift_over_rest_is_caught_applied_and_then_holds(twin_service):
    from service.checks.plan import check_plan_for_bench
    from service.checks.run import predicted_check_std

    svc = twin_service
    c = svc.client
    cfg = svc.app.state.manager.bench.config
    cache = svc.settings.data_dir / "check-plans"
    camera = svc.app.state.manager.bench.camera_model
    plan, _, _ = await asyncio.to_thread(check_plan_for_bench, cfg, 60.0, cache, 0, camera)
    # nothing to check before a calibration is applied
    r = await c.post(f"{API}/checks", json={}, headers=AUTH)
    assert r.status_code == 409 and "no calibration" in r.text
    # the calibration in force: a run of the check plan on the bench, applied
    r = await c.post(
        f"{API}/runs",
        json={"plan": plan.model_dump(mode="json", exclude_none=True), "methods": ["combined"]},
        headers=AUTH,
    )
    assert r.status_code == 202, r.text
    rid = r.json()["id"]
    # while the run holds the bench, a check is refused
    r = await c.post(f"{API}/checks", json={}, headers=AUTH)
    assert r.status_code == 409 and "holds the bench" in r.text
    assert (await wait_state(c, rid))["state"] == "done"
    assert (await c.post(f"{API}/runs/{rid}/apply", json={"method": "combined"}, headers=AUTH)).status_code == 201
    in_force = (await c.get(f"{API}/calibration/current")).json()

    first = await _check(c)
    assert first["verdict"] == "holds", first["result"]
    assert first["result"]["plan"]["poses"] == plan.count()["poses"]

    pred = await asyncio.to_thread(predicted_check_std, cfg, plan, camera)
    drift = DRIFT_IN_STD * math.hypot(pred["L"], in_force["combinations_std"]["L"])
    svc.sim.set_drift({"L": drift})
    caught = await _check(c)
    assert caught["verdict"] == "drifted" and "L" in caught["result"]["drifted"], caught["result"]
    got = caught["result"]["drifted"]["L"]
    assert abs(got["change_m"] - drift) < 3 * got["std_m"], (got, drift)
    assert caught["update"] is not None and caught["update"]["format"] == "i4cal.calibration/1"

    r = await c.post(f"{API}/checks/{caught['id']}/apply", headers=AUTH)
    assert r.status_code == 201, r.text
    current = (await c.get(f"{API}/calibration/current")).json()
    assert current["combinations"]["L"] == pytest.approx(caught["update"]["combinations"]["L"], abs=1e-15)
    assert current["covariance"] == caught["update"]["covariance"]
    # applied once only
    assert (await c.post(f"{API}/checks/{caught['id']}/apply", headers=AUTH)).status_code == 409

    after = await _check(c)
    assert after["verdict"] == "holds", after["result"]
    listed = (await c.get(f"{API}/checks")).json()
    assert [x["id"] for x in listed] == [after["id"], caught["id"], first["id"]]
    assert (await c.post(f"{API}/checks/{first['id']}/apply", headers=AUTH)).status_code == 409
    # revisits: every fit pose twice, one of them with a still pair; a count below 2 is refused naming it
    r = await c.post(f"{API}/checks", json={"repeat": 1}, headers=AUTH)
    assert r.status_code == 422 and "repeat" in r.text
    r = await c.post(f"{API}/checks", json={"repeat": 2}, headers=AUTH)
    assert r.status_code == 202, r.text
    rep = (await _finished(c, r.json()["id"]))["result"]["repeatability"]
    n_fit = plan.count()["poses"]
    assert (rep["poses"], rep["visits"]) == (n_fit, 2 * n_fit), rep
    # the simulator renders the same image at the same true pose and its axes reach their targets exactly
    assert rep["measurement_floor_m"] == 0.0 and rep["repeatability_m"] < 1e-9 and rep["outliers"] == []
