"""`POST /api/v1/camera/calibrations`: the guided board session of `i4cal camera calibrate` run by the service on its
simulated bench (the simulated operator holds the board where asked; real HTTP, real Modbus, the image-level
renderer), holding the bench meanwhile; the camera file it serves is the simulated lens within 3 std. A bench whose
operator needs a terminal is refused with what to run instead."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig
from drivers.sim.render import RenderSettings
from tests.service.conftest import AUTH, make_settings, start_service

API = "/api/v1/camera/calibrations"


@pytest.fixture
async def rendered_sim():
    b = SimBench(port=0, seed=2, axis_config=AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0))
    await b.start()
    try:
        yield b
    finally:
        await b.stop()


async def test_the_service_calibrates_the_camera_of_its_bench(tmp_path, rendered_sim):
    svc = await start_service(make_settings(tmp_path, rendered_sim), rendered_sim)
    c = svc.client
    try:
        assert (await c.post(API, json={"views": 15})).status_code == 401
        r = await c.post(API, json={"views": 15, "lens_model": "fisheye"}, headers=AUTH)
        assert r.status_code == 422 and "unknown lens model" in r.text
        r = await c.post(API, json={"views": 15}, headers=AUTH)
        assert r.status_code == 202, r.text
        job = r.json()
        assert job["state"] == "running"
        busy = await c.post("/api/v1/runs", json={"plan": "full"}, headers=AUTH)  # the session holds the bench
        assert busy.status_code == 409 and "camera calibration" in busy.text
        assert (await c.post(API, json={}, headers=AUTH)).status_code == 409
        for _ in range(1200):
            job = (await c.get(f"{API}/{job['id']}")).json()
            if job["state"] != "running":
                break
            await asyncio.sleep(0.1)
        assert job["state"] == "done", (job["error"], job["messages"][-5:])
        assert job["missing"] == [] and job["kept"] >= 15 and any("still missing" in m for m in job["messages"])
        res = job["result"]
        for name, k in (("fx", 0), ("fy", 1)):
            assert abs(res["K"][k][k] - RenderSettings().fx) < 3 * res["std"][name], (name, res)
        f = await c.get(job["camera_file"])
        assert f.status_code == 200 and f.json()["format"] == "i4cal.camera/1"
        assert f.json()["K"] == res["K"] and f.json()["acquired"]["coverage"]["missing"] == []
        assert (await c.get(f"{API}/{'0' * 32}")).status_code == 404
    finally:
        await c.aclose()
        await svc.stop()


async def test_a_console_operator_is_refused_with_what_to_run(tmp_path, rendered_sim):
    settings = make_settings(tmp_path, rendered_sim, bench_overrides={"operator": {"uri": "console"}})
    svc = await start_service(settings, rendered_sim)
    try:
        r = await svc.client.post(API, json={}, headers=AUTH)
        assert r.status_code == 409 and "i4cal camera calibrate --bench" in r.json()["detail"]
    finally:
        await svc.client.aclose()
        await svc.stop()


async def test_the_service_bench_takes_the_bench_files_camera_for_its_predictions(tmp_path):
    """A bench file naming a camera file ([camera] intrinsics): the service's predictions and designs use that camera
    (without a camera_file setting), as every acquisition records it."""
    from calib.formats.camera import CameraModel
    from service.runs.bench import Bench
    from service.settings import Settings

    cal = {"rms_px": 0.1, "covariance_params": ["fx"], "covariance": [[1.0]]}
    K = [[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]]
    CameraModel(np.asarray(K), np.zeros(5), 32, 24, {"calibration": cal}).save(tmp_path / "camera.json")
    (tmp_path / "bench.toml").write_text(
        '[actuators]\nuri = "modbus+tcp://127.0.0.1:1"\n'
        '[camera]\nuri = "sim://127.0.0.1:2"\nintrinsics = "camera.json"\n'
    )
    bench = await Bench.from_settings(Settings(data_dir=tmp_path / "data", bench_file=tmp_path / "bench.toml"))
    assert bench is not None and bench.camera_model is not None
    assert bench.camera_model.size == (32, 24) and bench.camera_model.extra["calibration"] == cal
