"""The dashboard in a real headless chromium (Debian's, driven by Playwright): start a run on the simulated bench
from the page, watch it finish, read the results tables, apply the calibration.

Needs ``chromium`` (deploy/install-test-system-deps.sh) and the ``playwright`` Python package (its bundled driver
drives /usr/bin/chromium; no browser download)."""

from __future__ import annotations

import pytest

from tests.browser import CHROMIUM, NO_CHROMIUM, enter_token, headless_chromium, page_errors
from tests.service.conftest import TOKEN, make_settings, start_service

pytest.importorskip("playwright.async_api")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)


async def test_dashboard_starts_a_run_and_shows_results(tmp_path):
    from drivers.sim.bench import SimBench

    async with SimBench(port=0, seed=5) as sim:
        cam = tmp_path / "camera.json"
        sim.renderer.settings.camera().save(cam)
        svc = await start_service(make_settings(tmp_path, sim, camera_file=cam, extraction_workers=2), sim)
        try:
            async with headless_chromium() as browser:
                # the wait_for_function strings below are evaluated by the page: its CSP (no 'unsafe-eval') would
                # refuse them; the page under its own CSP is checked by test_browser_security.py
                page = await browser.new_page(bypass_csp=True)
                errors = page_errors(page)
                await page.goto(svc.url + "/")
                assert await page.title() == "i4cal — bench dashboard"
                # without a token the start is refused, and the page says so
                await page.select_option("#plan", "full")
                await page.click("#start")
                await page.wait_for_function("document.querySelector('#message').textContent.includes('401')")
                await enter_token(page, TOKEN)
                # before it runs: what the chosen plan will buy (POST /plans/predict)
                await page.wait_for_function(
                    "document.querySelector('#plan-prediction').textContent.includes('full: predicted std (mm)')",
                    timeout=60_000,
                )
                assert "S-(q04-q03)/2" in await page.inner_text("#plan-prediction-table")
                await page.fill("#note", "from the browser")
                await page.click("#start")
                await page.wait_for_function("document.querySelector('#message').textContent.includes('started')")
                await page.wait_for_selector("#live-panel:not([hidden])")
                # the live view moves: progress and a frame
                await page.wait_for_function("document.querySelector('#progress').value > 0", timeout=60_000)
                await page.wait_for_function("document.querySelector('#frame').naturalWidth > 0", timeout=60_000)
                # per-frame extraction results, then the fits' iterations, in the live view's detail line
                await page.wait_for_function(
                    "/^frame \\d+ \\(/.test(document.querySelector('#detail').textContent)", timeout=240_000
                )
                await page.wait_for_function(
                    "document.querySelector('#live-panel').dataset.state === 'done'", timeout=240_000
                )
                assert "iteration" in await page.inner_text("#detail")
                await page.wait_for_selector("#results-panel:not([hidden])", timeout=30_000)
                t1 = await page.inner_text("#table1")
                for word in ("a priori", "combined", "end-effector", "legs", "S-(q04-q03)/2", "±"):
                    assert word in t1
                # the prediction the service kept with the run, beside the std the fits report (this browser
                # never designed anything: the prediction comes from the run, not from the page's storage)
                await page.wait_for_selector("#design-compare:not([hidden])", timeout=30_000)
                compare = await page.inner_text("#design-compare-table")
                assert "combined" in compare and "×)" in compare, compare
                t2 = await page.inner_text("#table2")
                assert "legs" in t2 and "q04" in t2
                assert await page.locator("#plot svg circle").count() > 0
                rows = await page.locator("#runs tbody tr").count()
                assert rows == 1
                assert "done" in await page.inner_text("#runs tbody tr")
                await page.select_option("#apply-method", "combined")
                await page.click("#apply")
                await page.wait_for_function("document.querySelector('#current').textContent.includes('combined')")
                assert not errors, errors
            cur = (await svc.client.get("/api/v1/calibration/current")).json()
            assert cur["method"] == "combined"
        finally:
            await svc.client.aclose()
            await svc.stop()
