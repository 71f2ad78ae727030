"""Scheduled checks (service setting ``check_schedule``) on the simulated bench (real HTTP, real Modbus, the
image-level twin, real SQLite), with a check due every second: none starts while no calibration is applied (said
so); none starts while a run holds the bench (deferred, said so, the run left to move alone); once the bench is free
the check runs, is stored with its trigger and action, and its ``notify`` reaches a real HTTP receiver on loopback.

The calibration in force is the simulator's truth with a full calibration's predicted covariance (as in
tests/service/test_check.py: a full run would cost a minute), stored as the bench's current calibration on the run
that held the bench (a calibration names its run)."""

from __future__ import annotations

import asyncio
import json
import threading
from datetime import UTC, datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig
from drivers.sim.render import RenderSettings
from tests.service.conftest import AUTH, make_settings, start_service, wait_state
from tests.service.test_check import _in_force

API = "/api/v1"


class _Receiver:
    """A webhook receiver on loopback: the JSON bodies POSTed to it."""

    def __init__(self) -> None:
        self.bodies: list[dict] = []
        received = self.bodies

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                n = int(self.headers.get("Content-Length") or 0)
                received.append(json.loads(self.rfile.read(n)))
                self.send_response(204)
                self.end_headers()

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver():
    r = _Receiver()
    yield r
    r.close()


async def _events(c, kind: str, n: int = 1, timeout: float = 60.0) -> list[dict]:
    async with asyncio.timeout(timeout):
        while True:
            ev = [e for e in (await c.get(f"{API}/checks/schedule")).json()["events"] if e["type"] == kind]
            if len(ev) >= n:
                return ev
            await asyncio.sleep(0.05)


async def test_a_scheduled_check_waits_for_the_run_then_runs_and_notifies(tmp_path, receiver):
    from service.db import Calibration
    from service.runs import calibrations

    sim = SimBench(port=0, seed=3, axis_config=AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0))
    await sim.start()
    RenderSettings().camera().save(tmp_path / "camera.json")
    schedule = {"every_hours": 1 / 3600, "action": "notify", "notify_url": receiver.url, "poll_s": 0.1}
    settings = make_settings(
        tmp_path,
        sim,
        camera_file=tmp_path / "camera.json",
        check_schedule=schedule,
        bench_overrides={"actuators": {"speed_m_s": 0.5, "accel_m_s2": 10.0}},  # the full plan holds the bench a while
    )
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        skipped = await _events(c, "skipped")
        assert "no calibration applied" in skipped[0]["message"]
        r = await c.post(f"{API}/runs", json={"plan": "full", "methods": []}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        m = svc.app.state.manager
        cfg = m.bench.config
        doc = await asyncio.to_thread(_in_force, cfg)
        calibrations.store(
            m.db,
            Calibration(
                bench=m.bench.name,
                run_id=rid,
                method="combined",
                software_version="test",
                applied_at=datetime.now(UTC),
                payload={"document": doc.model_dump(mode="json")},
            ),
        )
        deferred = await _events(c, "deferred", timeout=30)
        assert f"run {rid} holds the bench" in deferred[0]["message"]
        assert (await c.get(f"{API}/checks")).json() == []  # nothing started while the run holds the bench
        assert (await c.get(f"{API}/checks/schedule")).json()["deferred"] == f"run {rid}"
        assert (await c.post(f"{API}/runs/{rid}/abort", headers=AUTH)).status_code == 202
        assert (await wait_state(c, rid))["state"] == "aborted"
        started = await _events(c, "started", timeout=60)
        cid = started[0]["check"]
        await _events(c, "notified", timeout=180)
        check = (await c.get(f"{API}/checks/{cid}")).json()
        assert check["state"] == "done" and check["verdict"] == "holds", check
        sched = check["result"]["schedule"]
        assert sched["trigger"] == "every" and sched["action"] == "notify"
        assert sched["notified"] == {"url": receiver.url, "status": 204}
        assert receiver.bodies[0]["check"] == cid and receiver.bodies[0]["verdict"] == "holds"
    finally:
        await c.aclose()
        await svc.stop()
        await sim.stop()


def test_a_schedule_without_a_trigger_or_a_webhook_is_refused(tmp_path):
    from calib.errors import InputError
    from service.settings import load_settings

    with pytest.raises(InputError, match="every_hours or idle_minutes") as e:
        load_settings(None, data_dir=tmp_path, check_schedule={"action": "record"})
    assert e.value.field == "check_schedule"
    with pytest.raises(InputError, match="notify_url"):
        load_settings(None, data_dir=tmp_path, check_schedule={"every_hours": 1, "action": "notify"})
