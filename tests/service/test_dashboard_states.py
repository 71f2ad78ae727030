"""The dashboard's states and times from the run's own data, in a real headless chromium, with closed reads
(``open_reads`` false: every GET needs the token, which the page sends on its fetches, its live events, its frame
images and its downloads).

Three runs: a finished run and a run whose only fit failed, written to the service's database as the service writes
them (their results are real calibrations of the geometric twin's observations; the acquisition that would have
produced them is the subject of test_dashboard.py), and a run acquiring on the simulated bench, paused. A screenshot
of each is saved under the test's tmp dir (their paths are printed).
"""

from __future__ import annotations

import asyncio
import uuid
from datetime import UTC, datetime, timedelta

import pytest

from tests.browser import CHROMIUM, NO_CHROMIUM, enter_token, headless_chromium, page_errors
from tests.service.conftest import AUTH, TOKEN, make_settings, start_service

pytest.importorskip("playwright.async_api")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
API = "/api/v1"
#: the events of the finished runs happened long before the page loads: the log must show these times
EVENT_T = datetime(2021, 3, 4, 5, 6, 7, tzinfo=UTC)


def _results() -> tuple[dict, dict]:
    """A calibration with the three methods (the full plan), and one whose only fit (legs) fails (no lock phases)."""
    from calib.formats.observations import Observations
    from calib.formats.plan import make_plan
    from calib.identify.pipeline import calibrate, to_jsonable
    from drivers.sim.twin import GeometricTwin

    twin = GeometricTwin()
    good = to_jsonable(calibrate(Observations.from_dict(twin.observations(seed=0))))
    poses = twin.observations(plan=make_plan("pose-set", twin.geometry.nominal, seed=0), seed=0)
    failed = to_jsonable(calibrate(Observations.from_dict(poses), ["legs"], strict=False))
    assert not failed["methods"]["legs"]["converged"] and failed["methods"]["legs"]["error"]
    return good, failed


def _write_run(svc, result: dict, methods: list[str], note: str) -> str:
    from service.db.models import Event, Run

    m = svc.app.state.manager
    rid = uuid.uuid4().hex
    t0 = EVENT_T - timedelta(minutes=2)
    with m.db.session() as s:
        s.add(
            Run(
                id=rid,
                state="done",
                created_at=t0,
                started_at=t0,
                finished_at=EVENT_T,
                bench=m.bench.name,
                service=m.name,
                note=note,
                plan_name="full",
                methods=methods,
                dataset_dir=f"runs/{rid}/dataset",
                done=121,
                total=121,
                timings={"acquisition_s": 71.4, "extraction_s": 20.2, "calibration_s": 3.1, "total_s": 95.0},
                result=result,
                prediction={"predicted_std_m": {}, "motion_time_s": 3.1},
            )
        )
        s.flush()
        s.add(Event(run_id=rid, seq=1, t=t0, type="state", data={"state": "acquiring"}))
        s.add(Event(run_id=rid, seq=2, t=EVENT_T, type="state", data={"state": "done"}))
    return rid


async def _until(page, expr: str, timeout_s: float = 30.0):
    return await page.wait_for_function(expr, timeout=timeout_s * 1000)


async def test_finished_failed_fit_and_running_runs(tmp_path, sim):
    from tests.service.held import hold_camera

    good, failed = _results()
    svc = await start_service(make_settings(tmp_path, sim, open_reads=False), sim)
    shots = tmp_path / "screenshots"
    shots.mkdir()
    c = svc.client
    camera = hold_camera(sim)
    try:
        done_id = _write_run(svc, good, ["combined", "end-effector", "legs"], "finished")
        failed_id = _write_run(svc, failed, ["legs"], "only fit failed")
        async with headless_chromium() as browser:
            ctx = await browser.new_context(
                viewport={"width": 1280, "height": 1600}, accept_downloads=True, bypass_csp=True
            )
            page = await ctx.new_page()
            errors = page_errors(page)
            await page.goto(svc.url + "/dashboard")
            # closed reads, no token yet: the page says why it shows nothing
            await _until(page, "document.querySelector('#message').textContent.includes('401')")
            await enter_token(page, TOKEN)
            await page.evaluate("refreshRuns(); refreshDevices();")
            await _until(page, "document.querySelectorAll('#runs tbody tr').length === 2")
            # the devices before any run: not "unknown"
            await _until(page, "document.querySelector('#devices').textContent.length > 0")
            devices = await page.inner_text("#devices")
            assert "unknown" not in devices and "not contacted yet" in devices, devices
            # the forms' fields do not break (a label's text and its input stay on one line)
            broken = await page.evaluate(
                "[...document.querySelectorAll('#design-form label, #start-form label')].filter((l) => {"
                " const i = l.querySelector('input, select'); if (!i) return false;"
                " return l.getClientRects().length > 1"
                " || l.getBoundingClientRect().height > 1.5 * Math.max(i.getBoundingClientRect().height,"
                " parseFloat(getComputedStyle(l).lineHeight)); })"
                ".map((l) => l.textContent.trim())"
            )
            assert broken == [], broken

            # -- the run whose only fit failed ---------------------------------------------------------------
            await page.click(f"#runs tbody tr[data-id='{failed_id}']")
            await _until(page, "document.querySelector('#results-panel').hidden === false")
            await _until(page, "document.querySelector('#verdict').hidden === false")
            badge = await page.inner_text("#run-state")
            assert badge == "done · no fit converged", badge
            assert "done-nofit" in await page.get_attribute("#run-state", "class")
            row_badge = await page.inner_text(f"#runs tbody tr[data-id='{failed_id}'] .state")
            assert row_badge == "done · no fit converged"
            reason = failed["methods"]["legs"]["error"]
            results = await page.inner_text("#results-panel")
            assert results.count(reason) == 1, results  # once, not in four cells
            assert (await page.inner_text("#verdict")).startswith("verdict: nothing to load")
            for b in ("#pause", "#resume", "#abort"):
                assert await page.is_disabled(b), b
            # the log at the events' own times, not the page's
            await _until(page, "document.querySelectorAll('#log li').length === 2")
            expected = await page.evaluate(f"new Date('{EVENT_T.isoformat()}').toLocaleTimeString()")
            last = await page.inner_text("#log li:last-child")
            assert last == f"{expected} state: done", (last, expected)
            # no frame on disk: no broken image, a caption saying so
            await asyncio.sleep(0.6)
            assert await page.evaluate("document.querySelector('#frame').hidden")
            assert await page.inner_text("#frame-caption") == "no frame yet"
            await page.screenshot(path=str(shots / "failed-fit.png"), full_page=True)

            # -- the finished run ----------------------------------------------------------------------------
            await page.click(f"#runs tbody tr[data-id='{done_id}']")
            await _until(page, f"document.querySelector('#results-panel').dataset.run === '{done_id}'")
            await _until(page, "document.querySelector('#verdict').textContent.startsWith('verdict: load')")
            from calib.identify.verdict import verdict

            v = verdict(good, done_id)
            assert await page.inner_text("#run-state") == "done"
            verdict_text = await page.inner_text("#verdict")
            assert f"load {v.method}" in verdict_text and "± 1 std" in verdict_text, verdict_text
            assert f"i4cal export {done_id} -o calibration.json --method {v.method}" in verdict_text
            timings = await page.inner_text("#timings")
            assert "acquisition 71 s" in timings and "predicted motion 3.1 s" in timings, timings
            for b in ("#pause", "#resume", "#abort"):
                assert await page.is_disabled(b), b
            plot = await page.inner_text("#plot")
            assert "gap, vision − model (mm)" in plot and "validation pose pair" in plot, plot
            assert "Table I — the four combinations (mm, ± 1 std)" in await page.inner_text("#results-panel")
            await page.screenshot(path=str(shots / "finished.png"), full_page=True)
            await page.click("#apply")
            await _until(page, "document.querySelector('#current').textContent.includes('± 1 std')")
            assert "(mm, ± 1 std)" in await page.inner_text("#current")

            # -- a running run, paused: live events, frame and download through the token -----------------
            camera.hold_at_pose(3)
            r = await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            await camera.wait_held()
            async with asyncio.timeout(30):
                while (await c.get(f"{API}/runs/{rid}", headers=AUTH)).json()["progress"]["done"] < 1:
                    await asyncio.sleep(0.02)
            assert (await c.post(f"{API}/runs/{rid}/pause", headers=AUTH)).status_code == 200
            camera.release.set()
            await page.evaluate("refreshRuns()")
            await page.click(f"#runs tbody tr[data-id='{rid}']")
            await _until(page, "document.querySelector('#run-state').textContent === 'acquiring (paused)'")
            await _until(page, "document.querySelector('#frame').naturalWidth > 0")
            await _until(
                page,
                "[...document.querySelectorAll('#log li')].some((li) => li.textContent.includes('state: acquiring'))",
            )
            assert await page.is_disabled("#pause") and await page.is_enabled("#resume")
            assert await page.is_enabled("#abort")
            assert await page.inner_text("#live-error") == ""
            await page.screenshot(path=str(shots / "running.png"), full_page=True)
            async with page.expect_download() as dl:
                await page.click("#download")
            d = await dl.value
            assert d.suggested_filename == f"i4cal-{rid[:8]}-dataset.zip"
            assert (await d.path()).stat().st_size > 100
            # the live view follows the run to its end: abort from the page
            await page.click("#abort")
            await _until(page, "document.querySelector('#live-panel').dataset.state === 'aborted'")
            await _until(page, "document.querySelector('#abort').disabled")
            assert not errors, errors
        print("screenshots:", *sorted(str(p) for p in shots.iterdir()))
    finally:
        camera.release.set()
        await c.aclose()
        await svc.stop()


async def test_a_refused_token_is_said_in_the_live_view(tmp_path, sim):
    """Closed reads and a wrong token: the live view says why it shows nothing (not a silent empty panel)."""
    svc = await start_service(make_settings(tmp_path, sim, open_reads=False), sim)
    try:
        r = await svc.client.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
        rid = r.json()["id"]
        async with headless_chromium() as browser:
            page = await browser.new_page(bypass_csp=True)  # wait_for_function strings (CSP: no eval)
            await page.goto(svc.url + "/dashboard")
            await page.evaluate(f"document.querySelector('#token').value = {TOKEN!r}; select({rid!r});")
            await _until(page, "document.querySelector('#live-panel').hidden === false")
            await page.evaluate("document.querySelector('#token').value = 'wrong'; select(selected);")
            await _until(page, "document.querySelector('#live-error').textContent.includes('401')")
            assert "token" in await page.inner_text("#live-error")
    finally:
        await svc.client.aclose()
        await svc.stop()


async def test_a_late_answer_for_a_run_left_is_not_shown_over_the_one_selected(tmp_path, sim):
    """The user selects a run, then another before the first one's details arrive (a slow network, a busy service):
    when they do, the page keeps showing the run selected last (its state badge, its results), not the one left."""
    good, failed = _results()
    svc = await start_service(make_settings(tmp_path, sim, open_reads=False), sim)
    try:
        done_id = _write_run(svc, good, ["combined", "end-effector", "legs"], "finished")
        failed_id = _write_run(svc, failed, ["legs"], "only fit failed")
        async with headless_chromium() as browser:
            page = await browser.new_page(bypass_csp=True)
            errors = page_errors(page)
            answered = asyncio.Event()

            async def slow(route):  # the finished run's details answer 1.5 s late
                await asyncio.sleep(1.5)
                await route.continue_()
                answered.set()

            await page.route(f"**{API}/runs/{done_id}", slow)
            await page.goto(svc.url + "/dashboard")
            # (not awaited: the page goes on while the answer is on its way)
            await page.evaluate(f"document.querySelector('#token').value = {TOKEN!r}; select({done_id!r}); 0")
            await page.evaluate(f"select({failed_id!r}); 0")
            await _until(page, "document.querySelector('#verdict').hidden === false")
            await _until(page, "document.querySelector('#run-state').textContent === 'done · no fit converged'")
            # every text the state badge takes from now on (a flash of the other run's state counts)
            await page.evaluate(
                "window.badges = []; new MutationObserver(() => badges.push("
                "document.querySelector('#run-state').textContent)).observe("
                "document.querySelector('#run-state'), {childList: true, characterData: true, subtree: true});"
            )
            await asyncio.wait_for(answered.wait(), 10)
            await asyncio.sleep(1.0)  # the late answer handled by the page, and what it would have started
            badges = await page.evaluate("badges")
            assert set(badges) <= {"done · no fit converged"}, badges
            assert await page.inner_text("#run-state") == "done · no fit converged"
            assert await page.evaluate("selected") == failed_id
            assert await page.get_attribute("#results-panel", "data-run") == failed_id
            assert (await page.inner_text("#verdict")).startswith("verdict: nothing to load")
            assert not errors, errors
    finally:
        await svc.client.aclose()
        await svc.stop()
