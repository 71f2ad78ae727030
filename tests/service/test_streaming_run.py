"""A service run measures each frame while the bench moves (streaming): the run's events say how far extraction is
during the acquisition, and the extraction at the end takes what was measured.

The simulated bench runs here on loopback with its image-level twin (rendered 1024x768 frames) and the service gets
the twin camera's intrinsics as a camera file, as a bench with a calibrated camera has; a small 'full' plan.
"""

from __future__ import annotations

from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state

API = "/api/v1"
TINY = {"n_base": 3, "n_fit": 4, "n_lock": 1, "n_validation": 1, "line_samples": 3}


async def test_a_run_reports_extraction_progress_during_acquisition(tmp_path):
    b = SimBench(port=0, seed=1, rtu=False, axis_config=AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0))
    await b.start()
    cam_file = tmp_path / "camera.json"
    b.renderer.camera.save(cam_file)
    svc = await start_service(
        make_settings(tmp_path, b, camera_file=cam_file, plan_sizes=TINY, extraction_workers=1), b
    )
    c = svc.client
    try:
        r = await c.post(f"{API}/runs", json={"plan": "full", "methods": ["combined"]}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        run = await wait_state(c, rid, timeout=600)
        assert run["state"] == "done", run
        events = await read_events(c, rid)
    finally:
        await c.aclose()
        await svc.stop()
        await b.stop()
    seq_of = lambda pred: [e["seq"] for e in events if pred(e)]  # noqa: E731
    # the acquisition's frames, and the streamed measurements of frames, interleaved: extraction progressed while
    # the bench moved
    streamed = [e for e in events if e["type"] == "streamed"]
    items = [it for e in streamed for it in e["data"]["items"]]
    acq_last = max(seq_of(lambda e: e["type"] == "progress" and e["data"].get("stage") == "acquisition"))
    assert streamed and streamed[0]["seq"] < acq_last, [e["type"] for e in events]
    assert any(it["board"] for it in items)
    assert [it["measured"] for it in items if "failed" not in it] == list(range(1, len(items) + 1))
    # the stream's end is told once, before the extraction starts, with the count of frames measured
    ends = [e for e in events if e["type"] == "streaming"]
    assert len(ends) == 1 and ends[0]["data"]["state"] == "done", ends
    assert ends[0]["data"]["measured"] == len(items) and ends[0]["data"]["submitted"] == len(items)
    extracting = min(seq_of(lambda e: e["type"] == "state" and e["data"]["state"] == "extracting"))
    assert ends[0]["seq"] < extracting
    # the extraction took the boards measured during the acquisition
    taken = next(e for e in events if e["type"] == "extraction")["data"]["streamed"]
    assert taken["boards"] == sum(1 for it in items if it["phase"] != "camera") and taken["failed"] == 0
