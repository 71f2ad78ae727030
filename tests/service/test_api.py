"""The service over HTTP against the simulated bench: runs, control, auth, validation, uploads."""

from __future__ import annotations

import asyncio
import io
import tarfile
import time
import zipfile

import httpx
import numpy as np
import pytest

from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state
from tests.service.held import HELD_GRAB, hold_camera

API = "/api/v1"


async def test_health_and_openapi(service):
    c = service.client
    assert (await c.get("/healthz")).json()["status"] == "ok"
    assert (await c.get("/readyz")).json()["status"] == "ready"
    spec = (await c.get(f"{API}/openapi.json")).json()
    assert f"{API}/runs" in spec["paths"] and f"{API}/calibration/current" in spec["paths"]
    # a probe connects to the devices: it needs a token whatever open_reads says
    assert (await c.get(f"{API}/devices", params={"probe": "true"})).status_code == 401
    devs = (await c.get(f"{API}/devices", params={"probe": "true"}, headers=AUTH)).json()
    assert {d["name"]: d["state"] for d in devs["devices"]}["actuators"] == "connected"
    assert devs["held_by"] is None


async def test_no_token_401_and_nothing_moves(service):
    c, mech = service.client, service.sim.mechanism
    q0 = mech.q_true().copy()
    homed0 = [ax.homed for ax in mech.axes] if hasattr(mech.axes[0], "homed") else None
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic abc"}):
        r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=headers)
        assert r.status_code == 401, r.text
        assert r.headers["www-authenticate"] == "Bearer"
    await asyncio.sleep(0.2)
    assert (await c.get(f"{API}/runs")).json() == []
    np.testing.assert_allclose(mech.q_true(), q0, atol=1e-9)
    if homed0 is not None:
        assert [ax.homed for ax in mech.axes] == homed0
    for path in ("runs/0123456789abcdef0123456789abcdef/abort", "datasets"):
        assert (await c.post(f"{API}/{path}")).status_code == 401


async def test_validation_422_names_the_field(service):
    c = service.client
    bad_q = {
        "name": "mine",
        "steps": [{"phase": "poses", "q": [0.3, 0.3, 0.3, 0.3]}, {"phase": "poses", "q": [0.3, 0.3, 0.3, 5.0]}],
    }
    r = await c.post(f"{API}/runs", json={"plan": bad_q, "methods": []}, headers=AUTH)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert d["loc"] == ["body", "plan", "steps", 1, "q[3]"] and "soft limits" in d["msg"]
    r = await c.post(
        f"{API}/runs", json={"plan": {"name": "x", "steps": [{"phase": "nope", "q": [0] * 4}]}}, headers=AUTH
    )
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:4] == ["body", "plan", "steps", 0]
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": ["magic"]}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["body", "methods"]
    r = await c.post(f"{API}/runs", json={"plan": "nope"}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["body", "plan"]
    r = await c.post(f"{API}/runs", json={"dataset": "0" * 32, "methods": ["legs"]}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "dataset"]
    assert (await c.get(f"{API}/runs/../../etc/passwd")).status_code in (404, 422)
    assert (await c.get(f"{API}/runs/not-an-id")).status_code == 422
    assert (await c.get(f"{API}/runs/{'a' * 32}")).status_code == 404
    assert (await c.get(f"{API}/runs")).json() == []


async def test_acquisition_run_409_events_dataset(service):
    c = service.client
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": [], "note": "first"}, headers=AUTH)
    assert r.status_code == 202, r.text
    run = r.json()
    assert run["state"] in ("queued", "acquiring") and run["progress"]["total"] == 6
    r2 = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
    assert r2.status_code == 409, r2.text
    assert run["id"] in r2.json()["detail"]
    done = await wait_state(c, run["id"])
    assert done["state"] == "done", done
    assert done["progress"]["done"] == 6 and done["timings"]["acquisition_s"] > 0
    evs = await read_events(c, run["id"])
    states = [e["data"]["state"] for e in evs if e["type"] == "state"]
    assert states[0] == "queued" and "acquiring" in states and states[-1] == "done"
    poses = [e["data"]["done"] for e in evs if e["type"] == "progress" and e["data"]["stage"] == "acquisition"]
    assert poses[-1] == 6 and poses == sorted(poses)
    assert [e["seq"] for e in evs] == list(range(1, len(evs) + 1))
    assert (await c.get(f"{API}/runs/{run['id']}/result")).status_code == 409
    z = await c.get(f"{API}/runs/{run['id']}/dataset")
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    names = zipfile.ZipFile(io.BytesIO(z.content)).namelist()
    assert "dataset/dataset.json" in names and sum(n.endswith(".png") for n in names) == 6
    img = await c.get(f"{API}/runs/{run['id']}/frames/latest")
    assert img.status_code == 200 and img.content[:4] == b"\x89PNG"
    assert len((await c.get(f"{API}/runs/{run['id']}/frames")).json()) == 6
    # the bench is free again
    r3 = await c.post(f"{API}/runs", json={"plan": "validation", "methods": []}, headers=AUTH)
    assert r3.status_code == 202
    assert (await wait_state(c, r3.json()["id"]))["state"] == "done"
    listed = (await c.get(f"{API}/runs")).json()
    assert [x["id"] for x in listed] == [r3.json()["id"], run["id"]]


async def test_abort_mid_run_stops_actuators(tmp_path, sim):
    svc = await start_service(
        make_settings(
            tmp_path,
            sim,
            plan_sizes={"n_fit": 40},
            bench_overrides={"actuators": {"speed_m_s": 0.3, "accel_m_s2": 2.0}},
        ),
        sim,
    )
    c = svc.client
    try:
        r = await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        async with asyncio.timeout(30):
            while (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < 2:
                await asyncio.sleep(0.02)
        assert (await c.get(f"{API}/devices")).json()["held_by"] == rid
        r = await c.post(f"{API}/runs/{rid}/abort", headers=AUTH)
        assert r.status_code == 202
        run = await wait_state(c, rid, timeout=5)
        assert run["state"] == "aborted" and 2 <= run["progress"]["done"] < 40
        sim.mechanism.update()
        assert not any(ax.moving for ax in sim.mechanism.axes)
        q1 = sim.mechanism.q_true().copy()
        await asyncio.sleep(0.3)
        sim.mechanism.update()
        np.testing.assert_allclose(sim.mechanism.q_true(), q1, atol=1e-9)
        # abort again: accepted, nothing changes; the bench is free
        assert (await c.post(f"{API}/runs/{rid}/abort", headers=AUTH)).status_code == 202
        assert (await c.get(f"{API}/devices")).json()["held_by"] is None
        frames = (await c.get(f"{API}/runs/{rid}/frames")).json()
        assert len(frames) == run["progress"]["done"]
    finally:
        await c.aclose()
        await svc.stop()


async def test_pause_resume(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, plan_sizes={"n_fit": 12}, bench_overrides=HELD_GRAB), sim)
    camera = hold_camera(sim)
    camera.hold_at_pose(3)  # paused while pose 3 waits for its frame: the run pauses after pose 3
    c = svc.client
    try:
        rid = (await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)).json()["id"]
        await camera.wait_held()
        async with asyncio.timeout(30):
            while (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < 1:
                await asyncio.sleep(0.02)
        r = await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)
        assert r.status_code == 200 and r.json()["progress"]["paused"]
        camera.release.set()
        async with asyncio.timeout(30):  # pose 3 ends: its frame is on disk, the run at the pause
            while len((await c.get(f"{API}/runs/{rid}/frames")).json()) < 3:
                await asyncio.sleep(0.02)
        n1 = (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"]
        await asyncio.sleep(0.5)
        run = (await c.get(f"{API}/runs/{rid}")).json()
        assert run["progress"]["done"] == n1 < 12 and run["state"] == "acquiring"
        assert len((await c.get(f"{API}/runs/{rid}/frames")).json()) == 3  # nothing recorded while paused
        assert (await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)).status_code == 202
        assert (await wait_state(c, rid))["state"] == "done"
        assert (await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)).status_code == 409
    finally:
        camera.release.set()
        await c.aclose()
        await svc.stop()


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in members.items():
            zf.writestr(k, v)
    return buf.getvalue()


async def test_uploads_refused_when_oversized_or_malicious(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, max_upload_bytes=200_000, max_unpacked_bytes=1_000_000), sim)
    c = svc.client
    data = tmp_path / "data"
    try:
        z = {"Content-Type": "application/zip", **AUTH}
        r = await c.post(f"{API}/datasets", content=b"x" * 300_000, headers=z)
        assert r.status_code == 413
        r = await c.post(
            f"{API}/datasets", content=_zip({"../../evil.txt": b"pwned", "dataset.json": b"{}"}), headers=z
        )
        assert r.status_code == 422 and "escapes" in r.text
        assert not (tmp_path / "evil.txt").exists() and not (data / "evil.txt").exists()
        r = await c.post(f"{API}/datasets", content=_zip({"/etc/evil": b"x"}), headers=z)
        assert r.status_code == 422 and "absolute" in r.text
        bomb = io.BytesIO()
        with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("dataset.json", b"\0" * 5_000_000)
        r = await c.post(f"{API}/datasets", content=bomb.getvalue(), headers=z)
        assert r.status_code == 422 and "limit" in r.text
        tbuf = io.BytesIO()
        with tarfile.open(fileobj=tbuf, mode="w:gz") as tf:
            ti = tarfile.TarInfo("frames")
            ti.type, ti.linkname = tarfile.SYMTYPE, "/etc"
            tf.addfile(ti)
        r = await c.post(
            f"{API}/datasets", content=tbuf.getvalue(), headers={"Content-Type": "application/gzip", **AUTH}
        )
        assert r.status_code == 422 and "not a regular file" in r.text
        r = await c.post(f"{API}/datasets", content=_zip({"dataset.json": b"{}"}), headers=z)
        assert r.status_code == 422 and "dataset" in r.text
        r = await c.post(f"{API}/datasets", content=b"hello", headers={"Content-Type": "text/plain", **AUTH})
        assert r.status_code == 415
        assert (
            await c.post(f"{API}/datasets", content=_zip({"a": b"b"}), headers={"Content-Type": "application/zip"})
        ).status_code == 401
        assert (await c.get(f"{API}/datasets")).json() == []
        assert list((data / "datasets").iterdir()) == []
        assert list((data / "tmp").iterdir()) == []
    finally:
        await c.aclose()
        await svc.stop()


async def test_upload_dataset_and_offline_run(service):
    """Record a dataset, download it, upload it back and calibrate it offline (the tiny test images have no board:
    the run fails naming why, and nothing moves)."""
    c = service.client
    rid = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()["id"]
    assert (await wait_state(c, rid))["state"] == "done"
    z = (await c.get(f"{API}/runs/{rid}/dataset")).content
    r = await c.post(
        f"{API}/datasets", content=z, params={"name": "sweep 1"}, headers={"Content-Type": "application/zip", **AUTH}
    )
    assert r.status_code == 201, r.text
    ds = r.json()
    assert ds["frames"] == 6 and ds["name"] == "sweep 1"
    assert (await c.get(f"{API}/datasets/{ds['id']}")).json()["id"] == ds["id"]
    q0 = service.sim.mechanism.q_true().copy()
    r = await c.post(f"{API}/runs", json={"dataset": ds["id"], "methods": ["combined"]}, headers=AUTH)
    assert r.status_code == 202, r.text
    run = await wait_state(c, r.json()["id"])
    assert run["state"] == "failed" and run["error"] and run["dataset"] == ds["id"]
    assert run["timings"].get("acquisition_s") is None
    np.testing.assert_allclose(service.sim.mechanism.q_true(), q0, atol=1e-9)


async def test_full_run_real_images_results_apply(tmp_path):
    """A reduced 'full' plan on the image-level twin: acquisition, extraction, the three methods, apply."""
    from drivers.sim.bench import SimBench

    async with SimBench(port=0, seed=3) as sim:
        cam = tmp_path / "camera.json"
        sim.renderer.settings.camera().save(cam)
        svc = await start_service(make_settings(tmp_path, sim, camera_file=cam, extraction_workers=2), sim)
        c = svc.client
        try:
            r = await c.post(
                f"{API}/runs", json={"plan": "full", "methods": ["combined", "end-effector", "legs"]}, headers=AUTH
            )
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            run = await wait_state(c, rid, timeout=300)
            assert run["state"] == "done", run
            assert {"acquisition_s", "extraction_s", "calibration_s"} <= set(run["timings"])
            res = (await c.get(f"{API}/runs/{rid}/result")).json()
            assert res["format"] == "i4cal.result/1"
            for m in ("combined", "end-effector", "legs"):
                e = res["methods"][m]
                assert e["converged"], (m, e.get("error"))
                assert set(e["parameters"]) == {"L", "H-D", "S-q02/2", "S-(q04-q03)/2"}
                assert all(v is not None and v > 0 for v in e["std"].values())
            assert "seven" in res["methods"]["legs"]
            truth = sim.geometry.truth.combinations()
            for m in ("combined", "end-effector"):  # a sanity bound; accuracy is the calib tests' business
                e = res["methods"][m]
                assert all(abs(e["parameters"][k] - truth[k]) < 5 * e["std"][k] for k in truth), (m, e)
            evs = await read_events(c, rid)
            kinds = {e["type"] for e in evs}
            assert {"state", "progress", "extraction", "fit", "prediction"} <= kinds
            # the plan's prediction, kept with the run as it started: POST /plans/predict's for the same plan
            ref = (await c.post(f"{API}/plans/predict", json={"plan": "full"}, headers=AUTH)).json()
            pred = run["prediction"]
            assert pred["error"] is None and pred["motion_time_s"] == pytest.approx(ref["motion_time_s"], rel=1e-9)
            assert "this service's camera (1024 x 768 px)" in pred["noise"]  # its camera file's
            assert set(pred["predicted_std_m"]) == set(ref["predicted_std_m"]), (pred, ref["prediction_errors"])
            for m, std in ref["predicted_std_m"].items():
                assert pred["predicted_std_m"][m] == pytest.approx(std, rel=1e-9), m
            stages = {e["data"].get("stage") for e in evs if e["type"] == "progress"}
            assert stages == {"acquisition", "extraction", "calibration"}
            frames = (await c.get(f"{API}/runs/{rid}/frames")).json()
            assert sum(bool(f["board"]) for f in frames) > len(frames) // 2
            assert sum(f["rods"] or 0 for f in frames) > 4 * len(frames)
            png = await c.get(f"{API}/runs/{rid}/frames/{frames[-1]['index']}")
            assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
            assert (await c.get(f"{API}/calibration/current")).status_code == 404
            assert (await c.post(f"{API}/runs/{rid}/apply", json={"method": "legs"})).status_code == 401
            r = await c.post(f"{API}/runs/{rid}/apply", json={"method": "legs"}, headers=AUTH)
            assert r.status_code == 201, r.text
            r = await c.post(f"{API}/runs/{rid}/apply", headers=AUTH)
            assert r.status_code == 201 and r.json()["method"] == "combined"
            cur = (await c.get(f"{API}/calibration/current")).json()
            assert cur["run_id"] == rid and cur["method"] == "combined" and cur["software_version"]
            assert set(cur["combinations"]) == {"L", "H-D", "S-q02/2", "S-(q04-q03)/2"}
            hist = (await c.get(f"{API}/calibration/history")).json()
            assert [h["method"] for h in hist] == ["combined", "legs"]
            assert set(hist[1]["parameters"]) == {"H", "q02", "q03", "q04", "S", "D", "L"}
        finally:
            await c.aclose()
            await svc.stop()


async def test_killed_service_restarts_interrupted_then_resumes(tmp_path, sim):
    """SIGKILL the service (a real process) mid-run: on restart the run is interrupted with its frames intact, and
    resuming it continues the acquisition to done."""
    from calib.formats.dataset import Dataset
    from tests.service.procs import ServiceProcess, free_port, write_config

    def moving() -> bool:
        sim.mechanism.update()
        return any(ax.moving for ax in sim.mechanism.axes)

    port = free_port()
    cfg = write_config(
        tmp_path / "service.toml",
        sim,
        tmp_path / "data",
        port,
        plan_sizes={"n_fit": 16},
        actuators={"speed_m_s": 1.0, "accel_m_s2": 10.0},  # moves of 0.2-0.6 s: the kill lands in one
    )
    svc = ServiceProcess(cfg, port)
    url = svc.url
    await svc.start()
    try:
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            r = await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            async with asyncio.timeout(30):
                while (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < 4:
                    await asyncio.sleep(0.02)
            async with asyncio.timeout(30):  # killed mid-move
                while not moving():
                    await asyncio.sleep(0.005)
        svc.kill()
        ds_dir = tmp_path / "data" / "runs" / rid / "dataset"
        kept = len(Dataset.open(ds_dir).frames)
        assert 4 <= kept < 16
        stop_by = time.monotonic() + 1.0  # the controller's watchdog stops the axes of a dead host
        while moving() and time.monotonic() < stop_by:
            await asyncio.sleep(0.01)
        assert not moving()
        # the resume at the simulator's speed (the moves after the kill need no slow motion)
        write_config(tmp_path / "service.toml", sim, tmp_path / "data", port, plan_sizes={"n_fit": 16})
        await svc.start()
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            run = (await c.get(f"{API}/runs/{rid}")).json()
            assert run["state"] == "interrupted" and "resume" in run["error"]
            assert len((await c.get(f"{API}/runs/{rid}/frames")).json()) == kept
            ds = Dataset.open(ds_dir)
            for i in range(kept):
                assert ds.load_image(i).size > 0
            r = await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)
            assert r.status_code == 202, r.text
            run = await wait_state(c, rid, timeout=60)
            assert run["state"] == "done", run
            ds = Dataset.open(ds_dir)
            assert len(ds.frames) == 16
            evs = await read_events(c, rid)
            states = [e["data"]["state"] for e in evs if e["type"] == "state"]
            assert states[-3:] == ["queued", "acquiring", "done"] and "interrupted" in states
            starts = [
                e["data"]["message"]
                for e in evs
                if e["type"] == "progress" and "starting at" in (e["data"]["message"] or "")
            ]
            assert starts[-1].startswith(f"starting at pose {kept + 1}/16")
    finally:
        svc.stop()
