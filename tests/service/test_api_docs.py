"""The interactive API docs (``/api/v1/docs``) work offline: their Swagger UI assets are served by the service
(service/static/docs, from swagger-ui-dist), and a headless chromium that may reach nothing but the service renders
the API's operations."""

from __future__ import annotations

import re
from urllib.parse import urlparse

import pytest

from tests.browser import CHROMIUM, NO_CHROMIUM, headless_chromium, page_errors


async def test_docs_page_names_only_local_assets(service):
    c = service.client
    html = (await c.get("/api/v1/docs")).text
    urls = re.findall(r"""(?:src|href)=['"]([^'"]+)['"]""", html) + re.findall(r"""url: ['"]([^'"]+)['"]""", html)
    assert {"/static/docs/swagger-ui-bundle.js", "/static/docs/swagger-ui.css", "/api/v1/openapi.json"} <= set(urls)
    assert all(u.startswith("/") and not u.startswith("//") for u in urls), urls
    assert "cdn" not in html and "https://" not in html
    js = await c.get("/static/docs/swagger-ui-bundle.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"] and len(js.content) > 500_000
    css = await c.get("/static/docs/swagger-ui.css")
    assert css.status_code == 200 and css.headers["content-type"].startswith("text/css")


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
async def test_docs_render_with_the_network_cut_off(service):
    pytest.importorskip("playwright.async_api")
    host = urlparse(service.url).netloc
    blocked: list[str] = []

    async def only_the_service(route):
        if urlparse(route.request.url).netloc == host:
            await route.continue_()
        else:
            blocked.append(route.request.url)
            await route.abort()

    async with headless_chromium() as browser:
        page = await browser.new_page()
        errors = page_errors(page)
        await page.route("**/*", only_the_service)
        await page.goto(service.url + "/api/v1/docs")
        await page.wait_for_selector(".swagger-ui .info .title", timeout=30_000)
        assert "i4cal service" in await page.inner_text(".swagger-ui .info .title")
        await page.wait_for_selector(".opblock-summary-path[data-path='/api/v1/runs']", timeout=30_000)
        assert await page.locator(".opblock").count() > 10
        assert not blocked, blocked
        assert not errors, errors
