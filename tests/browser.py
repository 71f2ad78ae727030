"""A real headless chromium for the browser tests: Debian's (deploy/install-test-system-deps.sh), driven by the
``playwright`` package's bundled driver (no browser download). ``I4CAL_CHROMIUM`` names another executable."""

from __future__ import annotations

import os
import shutil
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

#: the chromium executable, or None (the browser tests are then skipped, saying how to install it)
CHROMIUM = os.environ.get("I4CAL_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
NO_CHROMIUM = "no chromium: run deploy/install-test-system-deps.sh"


@asynccontextmanager
async def headless_chromium() -> AsyncIterator[Any]:
    """A launched headless chromium (a ``playwright.async_api.Browser``), closed on the way out."""
    from playwright.async_api import async_playwright

    async with async_playwright() as p:
        browser = await p.chromium.launch(
            executable_path=CHROMIUM, headless=True, args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"]
        )
        try:
            yield browser
        finally:
            await browser.close()


def page_errors(page: Any) -> list[str]:
    """The uncaught script errors of ``page`` (a playwright ``Page``), collected as they come."""
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    return errors


async def enter_token(page: Any, token: str) -> None:
    """Type the API token into the dashboard's field as a user does (the page reads it on ``change``)."""
    await page.fill("#token", token)
    await page.dispatch_event("#token", "change")
