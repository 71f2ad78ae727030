"""The dashboard and the API docs under their Content-Security-Policy in a real headless chromium (no CSP bypass):
nothing is refused, the pages work; the dashboard shows a run's UTC creation time in the browser's time zone
(Europe/Paris here), named, not one hour off.

Needs ``chromium`` and the ``playwright`` package (as test_dashboard.py); skipped without them."""

from __future__ import annotations

import asyncio
import re
from datetime import datetime
from zoneinfo import ZoneInfo

import pytest

from tests.browser import CHROMIUM, NO_CHROMIUM, enter_token, headless_chromium, page_errors
from tests.service.conftest import TOKEN

pytest.importorskip("playwright.async_api")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)

API = "/api/v1"
#: collects every CSP violation the page reports (an init script: injected by the browser, not by the page)
WATCH = (
    "window.__csp = []; document.addEventListener('securitypolicyviolation', (e) => window.__csp.push("
    "e.violatedDirective + ' ' + e.blockedURI));"
)


async def _until(page, expr: str, timeout: float = 30.0):
    """Poll ``expr`` (run through the DevTools protocol, which the page's CSP does not govern) until truthy."""
    async with asyncio.timeout(timeout):
        while not (v := await page.evaluate(expr)):
            await asyncio.sleep(0.1)
    return v


async def test_dashboard_and_docs_under_their_csp(service):
    async with headless_chromium() as browser:
        ctx = await browser.new_context(timezone_id="Europe/Paris", locale="en-GB")
        await ctx.add_init_script(WATCH)
        page = await ctx.new_page()
        errors = page_errors(page)
        await page.goto(service.url + "/dashboard")
        await _until(page, "document.querySelector('#methods').dataset.loaded === 'true'")
        await enter_token(page, TOKEN)
        await page.select_option("#plan", "rotation-sweep")
        await page.evaluate("document.querySelectorAll('#methods input').forEach((i) => { i.checked = false; })")
        await page.click("#start")
        await _until(page, "document.querySelector('#message').textContent.includes('started')")
        await _until(page, "document.querySelector('#live-panel').dataset.state === 'done'", 60)
        await _until(page, "document.querySelector('#frame').naturalWidth > 0")  # img-src 'self'
        run = (await service.client.get(f"{API}/runs")).json()[0]
        created = datetime.fromisoformat(run["created_at"]).astimezone(ZoneInfo("Europe/Paris"))
        await page.evaluate("refreshRuns()")
        cell = await page.inner_text("#runs tbody tr td:nth-child(6)")
        # the browser writes the hour without a leading zero ("0:01:52" just after midnight): compare the numbers
        shown = re.search(r"(\d{1,2}):(\d{2}):(\d{2})", cell)
        assert shown is not None and "CET" in cell, (cell, run["created_at"])
        hms = tuple(int(g) for g in shown.groups())
        assert hms == (created.hour, created.minute, created.second), (cell, run["created_at"])
        assert await page.evaluate("window.__csp") == []
        assert not errors, errors

        docs = await ctx.new_page()
        await docs.goto(service.url + f"{API}/docs")
        await docs.wait_for_selector(".swagger-ui .info .title", timeout=30_000)
        await docs.wait_for_selector(".opblock-summary-path", timeout=30_000)  # the spec loaded and rendered
        assert await docs.evaluate("window.__csp") == []
