"""The dashboard's Checks panel in a real headless chromium (Debian's, driven by Playwright), with closed reads: the
list of checks with their verdicts, and per combination a plot of its estimated change over time with ± 1 std error
bars and the test's band (± threshold × std).

Three checks are written to the service's database as the service writes them (their documents carry what a check
stores: per combination the change, its std and z, and the threshold; running a check on the bench is the subject of
test_check_api.py): one that holds, one where L drifted, one inconclusive with no estimate. A screenshot is saved
under the test's tmp dir (its path is printed)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from tests.browser import CHROMIUM, NO_CHROMIUM, enter_token, headless_chromium, page_errors
from tests.service.conftest import TOKEN, make_settings, start_service

pytest.importorskip("playwright.async_api")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
COMBOS = ("L", "H-D", "S-q02/2", "S-(q04-q03)/2")
T0 = datetime(2026, 3, 4, 5, 6, 7, tzinfo=UTC)
THRESHOLD = 2.73
STD_M = 4e-5


def _document(verdict: str, change_m: dict[str, float]) -> dict:
    changes = {k: {"change_m": change_m[k], "std_m": STD_M, "z": change_m[k] / STD_M} for k in COMBOS}
    drifted = {k: v for k, v in changes.items() if abs(v["z"]) > THRESHOLD}
    assert (verdict == "drifted") == bool(drifted)
    return {
        "format": "i4cal.check/1",
        "verdict": verdict,
        "drifted": drifted,
        "changes": changes,
        "threshold": THRESHOLD,
        "statistic": max(abs(v["z"]) for v in changes.values()),
        "reasons": [],
    }


def _write_check(svc, cid: str, at: datetime, verdict: str, result: dict) -> None:
    from service.db import Check

    m = svc.app.state.manager
    with m.db.session() as s:
        s.add(
            Check(
                id=cid,
                state="done",
                created_at=at - timedelta(seconds=60),
                finished_at=at,
                verdict=verdict,
                result=result,
                bench=m.bench.name,
                service=m.name,
                in_force={},
                dataset_dir=f"checks/{cid}/dataset",
            )
        )


async def _until(page, expr: str, timeout_s: float = 20.0):
    return await page.wait_for_function(expr, timeout=timeout_s * 1000)


async def test_the_checks_panel_plots_each_combinations_drift_against_its_band(tmp_path, sim):
    svc = await start_service(make_settings(tmp_path, sim, open_reads=False), sim)
    holds_id, drifted_id, unknown_id = "a" * 32, "b" * 32, "c" * 32
    small = {"L": 1e-5, "H-D": -2e-5, "S-q02/2": 3e-5, "S-(q04-q03)/2": -1e-5}
    _write_check(svc, holds_id, T0, "holds", _document("holds", small))
    # L moved by 0.3 mm: z = 7.5, beyond the threshold; the other three within it
    _write_check(svc, drifted_id, T0 + timedelta(hours=6), "drifted", _document("drifted", {**small, "L": 3e-4}))
    inconclusive = {"format": "i4cal.check/1", "verdict": "inconclusive", "drifted": {}, "changes": {},
                    "threshold": THRESHOLD, "reasons": ["the board was seen in 2 frames of 40"]}  # fmt: skip
    _write_check(svc, unknown_id, T0 + timedelta(hours=12), "inconclusive", inconclusive)
    shot = tmp_path / "checks-panel.png"
    try:
        async with headless_chromium() as browser:
            # wait_for_function strings are evaluated by the page: its CSP (no 'unsafe-eval') would refuse them
            page = await browser.new_page(viewport={"width": 1280, "height": 1600}, bypass_csp=True)
            errors = page_errors(page)
            await page.goto(svc.url + "/dashboard")
            # closed reads, no token: the panel says why it is empty
            await _until(page, "document.querySelector('#checks-message').textContent.includes('401')")
            await enter_token(page, TOKEN)
            await _until(page, "document.querySelectorAll('#checks tbody tr').length === 3")
            await _until(page, "document.querySelectorAll('#drift-plots svg.drift-plot').length === 4")

            # the list: newest first, each verdict in its colour, what drifted named with its change in mm
            rows = page.locator("#checks tbody tr")
            assert [await rows.nth(i).get_attribute("data-id") for i in range(3)] == [
                unknown_id,
                drifted_id,
                holds_id,
            ]
            colours = {}
            for cid, verdict in ((holds_id, "holds"), (drifted_id, "drifted"), (unknown_id, "inconclusive")):
                cell = page.locator(f"#checks tbody tr[data-id='{cid}'] td.verdict-{verdict}")
                assert await cell.inner_text() == verdict
                colours[verdict] = await cell.evaluate("(e) => getComputedStyle(e).color")
            assert colours == {
                "holds": "rgb(26, 127, 46)",
                "drifted": "rgb(187, 0, 0)",
                "inconclusive": "rgb(119, 119, 119)",
            }, colours
            drifted_row = await page.inner_text(f"#checks tbody tr[data-id='{drifted_id}']")
            assert "L 0.300 ± 0.040" in drifted_row and "H-D" not in drifted_row, drifted_row
            assert "the board was seen in 2 frames" in await page.inner_text(
                f"#checks tbody tr[data-id='{unknown_id}']"
            )

            # one plot per combination, one point per check that estimated it (not the inconclusive one)
            for k in COMBOS:
                plot = page.locator(f"#drift-plots svg.drift-plot[data-combination='{k}']")
                assert await plot.count() == 1, k
                assert await plot.locator("circle.point").count() == 2, k
                assert await plot.locator("line.errbar").count() == 2, k
                assert await plot.locator("rect.band").count() == 2, k
                labels = await plot.locator("text.axis-label").all_text_contents()
                assert "change (mm)" in labels and any("time" in t for t in labels), labels

            async def geometry(k: str, cid: str) -> dict[str, float]:
                sel = f"#drift-plots svg.drift-plot[data-combination='{k}']"
                return await page.evaluate(
                    "([sel, cid]) => { const s = document.querySelector(sel);"
                    " const c = s.querySelector(`circle.point[data-check='${cid}']`);"
                    " const b = s.querySelector(`rect.band[data-check='${cid}']`);"
                    " const e = s.querySelector(`line.errbar[data-check='${cid}']`);"
                    " const n = (el, a) => parseFloat(el.getAttribute(a));"
                    " return {cx: n(c, 'cx'), cy: n(c, 'cy'), top: n(b, 'y'), bottom: n(b, 'y') + n(b, 'height'),"
                    " e1: n(e, 'y1'), e2: n(e, 'y2'), zero: n(s.querySelector('line'), 'y1')}; }",
                    [sel, cid],
                )

            # L: the drifted check's point lies outside its band (above: a positive change), the holding one inside
            g_drift, g_hold = await geometry("L", drifted_id), await geometry("L", holds_id)
            assert g_drift["cy"] < g_drift["top"], g_drift  # SVG y grows downwards
            assert g_hold["top"] < g_hold["cy"] < g_hold["bottom"], g_hold
            assert g_hold["cx"] < g_drift["cx"]  # at the checks' own times, oldest left
            # the drawn scale is the data's: the band's half-height / the error bar's = threshold; 0.3 mm / 0.04 mm
            band_half = (g_drift["bottom"] - g_drift["top"]) / 2
            bar_half = abs(g_drift["e2"] - g_drift["e1"]) / 2
            assert band_half / bar_half == pytest.approx(THRESHOLD, rel=0.02)
            assert (g_drift["zero"] - g_drift["cy"]) / bar_half == pytest.approx(3e-4 / STD_M, rel=0.02)
            # the other combinations: both points within their bands
            for k in COMBOS[1:]:
                for cid in (holds_id, drifted_id):
                    g = await geometry(k, cid)
                    assert g["top"] < g["cy"] < g["bottom"], (k, cid, g)
            assert await page.get_attribute(
                f"svg.drift-plot[data-combination='L'] circle.point[data-check='{drifted_id}']", "fill"
            ) == "#c00"  # fmt: skip
            await page.locator("#checks-panel").screenshot(path=str(shot))
            assert not errors, errors
        print("screenshot:", shot)
    finally:
        await svc.client.aclose()
        await svc.stop()
