"""A run's methods fitted at once (``fit_workers``): the same result document as one after the other.

An uploaded rendered dataset (``rendered_zip``) is calibrated by the service with two fit processes; its result is
compared with the methods fitted one after the other (:func:`service.jobs.fit_job`, what ``fit_workers = 1`` runs)
on the run's own observations.
"""

from __future__ import annotations

from service.jobs import fit_job
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state

API = "/api/v1"
METHODS = ["combined", "end-effector", "legs"]


def _strip(doc):
    """The document without the fits' wall-clock durations."""
    if isinstance(doc, dict):
        return {k: _strip(v) for k, v in doc.items() if k != "time_s"}
    if isinstance(doc, list):
        return [_strip(v) for v in doc]
    return doc


async def test_methods_fitted_at_once_give_the_sequential_result(tmp_path, sim, rendered_zip):
    settings = make_settings(tmp_path, sim, fit_workers=2)
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        r = await c.post(f"{API}/datasets", content=rendered_zip, headers={"Content-Type": "application/zip", **AUTH})
        r = await c.post(f"{API}/runs", json={"dataset": r.json()["id"], "methods": METHODS}, headers=AUTH)
        rid = r.json()["id"]
        run = await wait_state(c, rid, timeout=600)
        assert run["state"] == "done", run
        res = (await c.get(f"{API}/runs/{rid}/result")).json()
        evs = await read_events(c, rid)
    finally:
        await c.aclose()
        await svc.stop()
    obs = next((tmp_path / "data").rglob("observations.json"))
    sequential = fit_job(emit=lambda kind, data: None, observations=str(obs), methods=METHODS)
    assert _strip(res) == _strip(sequential)
    fits = [(e["data"]["method"], e["data"]["state"], e["data"]["index"]) for e in evs if e["type"] == "fit"]
    assert sorted(fits) == sorted((m, s, k) for k, m in enumerate(METHODS) for s in ("start", "done"))
    starts = [f[0] for f in fits if f[1] == "start"]
    # two at once, never more: at some point two fits had started (been given a place) and not ended (one after the
    # other: never two)
    running, most = 0, 0
    for _method, state, _k in fits:
        running += 1 if state == "start" else -1
        most = max(most, running)
    assert most == 2, fits
    assert sorted(starts[:2]) == sorted(METHODS[:2])  # in the order given, as places free up
    progress = [e["data"]["done"] for e in evs if e["type"] == "progress" and e["data"].get("stage") == "calibration"]
    assert progress == [1, 2, 3]
