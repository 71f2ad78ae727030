"""``GET /metrics``: the Prometheus text format, parsed with prometheus_client's own parser, on a real service with the
simulated bench (real Modbus server on loopback, real HTTP); the figures agree with the runs the API reports."""

from __future__ import annotations

import pytest
from prometheus_client.parser import text_string_to_metric_families

import drivers.acquisition.metrics
from service.runs import STATES
from tests.service.conftest import AUTH, wait_state

API = "/api/v1"


async def scrape(client) -> dict[tuple[str, tuple], float]:
    r = await client.get("/metrics")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    out = {}
    for fam in text_string_to_metric_families(r.text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


async def test_metrics_runs_durations_frames(service, rendered_zip):
    c = service.client
    m0 = await scrape(c)
    for st in STATES:
        assert m0[("i4cal_runs", (("state", st),))] == 0
    assert m0[("i4cal_run_duration_seconds_count", ())] == 0
    assert m0[("i4cal_frames_extracted_total", ())] == 0
    assert ("process_cpu_seconds_total", ()) in m0
    # a run that only records (acquisition on the bench), an offline run that extracts and fits an uploaded dataset
    r1 = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()
    run1 = await wait_state(c, r1["id"])
    ds = await c.post(f"{API}/datasets", content=rendered_zip, headers={"Content-Type": "application/zip", **AUTH})
    assert ds.status_code == 201, ds.text
    r2 = (await c.post(f"{API}/runs", json={"dataset": ds.json()["id"], "methods": ["combined"]}, headers=AUTH)).json()
    run2 = await wait_state(c, r2["id"])
    assert run1["state"] == "done" and run2["state"] == "done", (run1, run2)
    m = await scrape(c)
    assert m[("i4cal_runs", (("state", "done"),))] == 2
    assert sum(m[("i4cal_runs", (("state", st),))] for st in STATES) == 2
    totals = [run["timings"]["total_s"] for run in (run1, run2)]
    assert m[("i4cal_run_duration_seconds_count", ())] == 2
    assert m[("i4cal_run_duration_seconds_sum", ())] == pytest.approx(sum(totals))
    assert m[("i4cal_run_duration_seconds_bucket", (("le", "+Inf"),))] == 2
    assert m[("i4cal_run_duration_seconds_bucket", (("le", "60.0"),))] == sum(t <= 60 for t in totals)
    assert m[("i4cal_run_stage_duration_seconds_count", (("stage", "acquisition"),))] == 1
    assert m[("i4cal_run_stage_duration_seconds_sum", (("stage", "acquisition"),))] == pytest.approx(
        run1["timings"]["acquisition_s"]
    )
    for stage in ("extraction", "calibration"):
        assert m[("i4cal_run_stage_duration_seconds_count", (("stage", stage),))] == 1
        assert m[("i4cal_run_stage_duration_seconds_sum", (("stage", stage),))] == pytest.approx(
            run2["timings"][f"{stage}_s"]
        )
    assert m[("i4cal_frames_extracted_total", ())] == ds.json()["frames"] > 0
    # a second scrape reads the finished runs from its cache: the same run figures
    m2 = await scrape(c)
    for k, v in m.items():
        if k[0].startswith("i4cal_run"):
            assert m2[k] == v, k


async def test_driver_counters_exported(service):
    c = service.client
    before = await scrape(c)
    for name in ("requests", "retries", "timeouts", "reconnects"):
        assert (f"i4cal_modbus_{name}_total", ()) in before
    drivers.acquisition.metrics.inc("modbus_retries", 2)
    stats = drivers.acquisition.metrics.CountingStats("modbus", {"timeouts": 0})
    stats["timeouts"] += 1
    stats["timeouts"] += 1
    after = await scrape(c)
    assert after[("i4cal_modbus_retries_total", ())] == before[("i4cal_modbus_retries_total", ())] + 2
    assert after[("i4cal_modbus_timeouts_total", ())] == before[("i4cal_modbus_timeouts_total", ())] + 2
    assert stats == {"timeouts": 2}
    with pytest.raises(ValueError, match="only grows"):
        drivers.acquisition.metrics.inc("modbus_retries", -1)


async def test_modbus_requests_of_a_run_are_counted(service):
    c = service.client
    before = (await scrape(c))[("i4cal_modbus_requests_total", ())]
    r = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()
    assert (await wait_state(c, r["id"]))["state"] == "done"
    assert (await scrape(c))[("i4cal_modbus_requests_total", ())] > before
