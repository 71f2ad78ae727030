"""The calibration report: built from a small rendered dataset (image-level twin, reduced plan), self-contained,
opened in a real headless chromium; the command line (dataset, observations, run, server) and the API route."""

from __future__ import annotations

import asyncio
import base64
import io
import json
import re
import subprocess
import sys
import zipfile
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.formats.plan import make_plan
from calib.model.parameters import COMBINATION_NAMES
from drivers.sim.rendered_dataset import simulate_dataset
from drivers.sim.twin import BenchGeometry
from service.cli import main
from service.report import ReportInputs, build_report, inputs_from_path
from service.report.analysis import dataset_sha256
from tests.browser import CHROMIUM, NO_CHROMIUM, headless_chromium, page_errors
from tests.service.conftest import AUTH, wait_state

API = "/api/v1"
METHODS = ["combined", "end-effector", "legs"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A 'full' plan cut down to 27 poses plus 6 camera views, rendered by the image-level twin."""
    g = BenchGeometry()
    plan = make_plan("full", g.nominal, seed=2, n_base=5, n_fit=8, n_lock=3, n_validation=4, line_samples=5)
    return simulate_dataset(tmp_path_factory.mktemp("report") / "ds", seed=2, plan=plan, n_camera_views=6)


@pytest.fixture(scope="module")
def built(dataset, tmp_path_factory) -> tuple[ReportInputs, str, Path]:
    inputs = inputs_from_path(dataset, METHODS, workers=2)
    html = build_report(inputs)
    out = tmp_path_factory.mktemp("out") / "report.html"
    out.write_text(html, encoding="utf-8")
    return inputs, html, out


class _Refs(HTMLParser):
    """Every src/href attribute and every tag of a document."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: list[tuple[str, str, str]] = []
        self.tags: set[str] = set()

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        for k, v in attrs:
            if k in ("src", "href", "srcset", "action", "poster", "data"):
                self.refs.append((tag, k, v or ""))


def _plot_images(html: str) -> list[np.ndarray]:
    out = []
    for b64 in re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html):
        img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None
        out.append(img)
    return out


def _coloured_pixels(img: np.ndarray) -> int:
    """Pixels of a saturated colour (plotted data; axes, text and grid are grey)."""
    i = img.astype(int)
    return int(np.sum(np.max(i, axis=2) - np.min(i, axis=2) > 60))


def test_report_holds_the_result_and_is_self_contained(built, dataset):
    inputs, html, _ = built
    res = inputs.result.to_dict()
    for m in METHODS:
        e = res["methods"][m]
        assert e["converged"], (m, e.get("error"))
        for k in COMBINATION_NAMES:
            assert f"{e['parameters'][k] * 1e3:.4f}" in html, (m, k)  # identified, mm
            assert f"{e['std'][k] * 1e3:.4f}" in html, (m, k)  # u, mm
            assert f"{2 * e['std'][k] * 1e3:.4f}" in html, (m, k)  # U (k = 2), mm
        for k, v in (e.get("seven") or {}).items():
            assert f"{v * 1e3:.4f}" in html, (m, k)
    for k, v in res["methods"]["combined"]["bound"]["std"].items():
        assert f"{v * 1e3:.4f}" in html, k  # Cramer-Rao bound
    budget = html[html.index('<section id="budget">') :]
    budget = budget[: budget.index("</section>")]
    for m in METHODS:  # uncertainty budget: every contribution
        for src, contrib in res["methods"][m]["std_breakdown"].items():
            for k, v in contrib.items():
                assert f"{v * 1e3:.4f}" in budget, (m, src, k)
    assert "limb-edge bias common to every rod" in budget and "camera intrinsics" in budget
    for k, v in res["truth_errors"]["combined"].items():
        if k in COMBINATION_NAMES:
            assert f"{v * 1e3:+.4f}" in html, k  # simulated: errors vs the truth
    for name, v in res["validation"].items():
        assert f"{v['gaps_validation']['rms_mm']:.4f}" in html, name  # Table II
        assert f"{v['straightness']['rms_mm']:.4f}" in html, name  # Table III
    digest, n_files, missing = dataset_sha256(dataset)
    assert digest in html and n_files == 1 + len(list((dataset / "frames").glob("*.png"))) and not missing
    from service import __version__

    assert f"i4cal {__version__}" in html
    cam = inputs.observations["extraction"]["summary"]["camera"]
    assert f"{cam['rms_px']:.3f} px" in html and "Rejected calibration views" in html
    # self-contained: every reference is a data: URI or an in-page anchor; nothing else points outside
    p = _Refs()
    p.feed(html)
    assert not p.tags & {"script", "link", "iframe", "object", "embed"}
    srcs = [v for t, k, v in p.refs if k == "src"]
    assert len(srcs) >= 8 and all(v.startswith("data:image/") for v in srcs)
    assert all(v.startswith("#") for t, k, v in p.refs if k == "href")
    text = re.sub(r"data:image/[a-z]+;base64,[A-Za-z0-9+/=]+", "", html)
    assert "http" not in text and 'src="/' not in text and "url(" not in text
    # the plots are real plots: not blank, data drawn in colour
    plots = _plot_images(html)
    assert len(plots) == 5
    for img in plots:
        assert img.shape[1] >= 400 and img.std() > 20 and _coloured_pixels(img) > 300


def test_report_opens_in_a_real_browser(built):
    pytest.importorskip("playwright.async_api")
    if CHROMIUM is None:
        pytest.skip(NO_CHROMIUM)
    path = built[2]

    async def check() -> None:
        async with headless_chromium() as browser:
            page = await browser.new_page(viewport={"width": 1280, "height": 900})
            requests: list[str] = []
            page.on("request", lambda r: requests.append(r.url))
            errors = page_errors(page)
            await page.goto(path.as_uri())
            await page.wait_for_load_state("load")
            assert "calibration report" in (await page.title())
            imgs = page.locator("img")
            n = await imgs.count()
            assert n == 8  # 5 plots, 3 frames
            for i in range(n):
                img = imgs.nth(i)
                await img.scroll_into_view_if_needed()
                assert await img.evaluate("i => i.decode().then(() => i.complete && i.naturalWidth)") >= 400
                assert await img.is_visible()
            tables = page.locator("table")
            assert await tables.count() >= 10
            for i in range(await tables.count()):
                assert await tables.nth(i).is_visible()
            t1 = await page.locator("table", has_text="Table I - identifiable parameters").inner_text()
            for word in ("a priori", "combined", "end-effector", "legs", "truth", "S-(q04-q03)/2", "±"):
                assert word in t1
            # what the browser shows of the first plot is a readable picture, not an empty box
            shot = await page.locator("figure img").first.screenshot()
            img = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
            assert img.shape[1] >= 400 and img.std() > 20 and _coloured_pixels(img) > 300
            assert not errors, errors
            assert all(u.startswith(("file:", "data:")) for u in requests), requests

    asyncio.run(check())


def test_cli_report_from_observations_with_frames(built, dataset, tmp_path):
    inputs = built[0]
    obs = tmp_path / "obs.json"
    obs.write_text(json.dumps(inputs.observations), encoding="utf-8")
    out = tmp_path / "r.html"
    assert (
        main(["report", str(obs), "--dataset", str(dataset), "-o", str(out), "--methods", "combined", "--quiet"]) == 0
    )
    text = out.read_text(encoding="utf-8")
    comb = inputs.result.to_dict()["methods"]["combined"]
    for k in COMBINATION_NAMES:  # the same observations calibrate to the same values
        assert f"{comb['parameters'][k] * 1e3:.4f}" in text
    assert "Method: legs" not in text and "Method: combined" in text
    assert len(_plot_images(text)) == 5 and text.count("data:image/jpeg") == 3


def _run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=120)


def test_cli_errors_are_one_line(tmp_path):
    res = _run_cli("report", str(tmp_path / "nope"), "-o", str(tmp_path / "r.html"))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "nope" in res.stderr
    cfg = tmp_path / "service.toml"
    cfg.write_text(f'data_dir = "{tmp_path / "data"}"\n', encoding="utf-8")
    res = _run_cli("report", "0123abcd", "--config", str(cfg), "-o", str(tmp_path / "r.html"))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "no run 0123abcd" in res.stderr
    assert not (tmp_path / "r.html").exists()


async def test_api_report_route_and_cli_run_modes(service, dataset, tmp_path, monkeypatch):
    c = service.client
    assert (await c.get(f"{API}/runs/{'a' * 32}/report")).status_code == 404
    # a run without a result: 409
    rid0 = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()["id"]
    assert (await wait_state(c, rid0))["state"] == "done"
    r = await c.get(f"{API}/runs/{rid0}/report")
    assert r.status_code == 409 and "no result" in r.json()["detail"]
    # upload the rendered dataset, calibrate it offline, read its report
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for f in sorted(dataset.rglob("*")):
            if f.is_file():
                zf.write(f, f"dataset/{f.relative_to(dataset).as_posix()}")
    r = await c.post(f"{API}/datasets", content=buf.getvalue(), headers={"Content-Type": "application/zip", **AUTH})
    assert r.status_code == 201, r.text
    r = await c.post(f"{API}/runs", json={"dataset": r.json()["id"], "methods": ["combined", "legs"]}, headers=AUTH)
    rid = r.json()["id"]
    run = await wait_state(c, rid, timeout=240)
    assert run["state"] == "done", run
    result = (await c.get(f"{API}/runs/{rid}/result")).json()
    r = await c.get(f"{API}/runs/{rid}/report")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    html = r.text
    assert rid in html and "Kinematic calibration report" in html
    for m in ("combined", "legs"):
        for k in COMBINATION_NAMES:
            assert f"{result['methods'][m]['parameters'][k] * 1e3:.4f}" in html
    assert html.count("data:image/jpeg") == 3  # the run's frames with detections
    assert dataset_sha256(dataset)[0] in html  # the uploaded copy hashes as the original
    only = (await c.get(f"{API}/runs/{rid}/report", params={"methods": "legs"})).text
    assert "Method: legs" in only and "Method: combined" not in only
    # the command line: the run from the data directory (id prefix), and from the running service
    monkeypatch.setenv("I4CAL_DATA_DIR", str(service.settings.data_dir))
    out = tmp_path / "run.html"
    assert await asyncio.to_thread(main, ["report", rid[:10], "-o", str(out), "--quiet"]) == 0
    assert f"{result['methods']['combined']['parameters']['L'] * 1e3:.4f}" in out.read_text(encoding="utf-8")
    out2 = tmp_path / "server.html"
    assert await asyncio.to_thread(main, ["report", rid[:8], "--server", service.url, "-o", str(out2), "--quiet"]) == 0
    assert f"run {rid}" in out2.read_text(encoding="utf-8")
    assert await asyncio.to_thread(main, ["report", rid0, "--server", service.url, "-o", str(out2), "--quiet"]) == 2


def test_report_sets_the_runs_prediction_beside_the_reported_std(built):
    """A run's prediction before motion (Run.prediction) stands beside each method's reported std, with their
    ratio; a report not made from a run says why there is none."""
    import dataclasses

    inputs, html, _ = built

    def predicted(doc: str) -> str:
        sec = doc[doc.index('<section id="predicted">') :]
        return sec[: sec.index("</section>")]

    assert "Not available: the report was not made from a run on the bench" in predicted(html)
    std = inputs.result.to_dict()["methods"]["combined"]["std"]
    pred = {"combined": {k: 2 * v for k, v in std.items()}, "legs": {k: 1.0 for k in COMBINATION_NAMES}}
    doc = build_report(
        dataclasses.replace(inputs, prediction={"predicted_std_m": pred, "motion_time_s": 300.0}, methods=["combined"]),
        max_frames=0,
    )
    sec = predicted(doc)
    for k in COMBINATION_NAMES:
        assert f"{2 * std[k] * 1e3:.4f} / {std[k] * 1e3:.4f} (0.50x)" in sec, (k, sec)
    assert "Predicted motion time: 5.0 min" in sec and "legs" not in sec  # only the methods shown
    doc = build_report(dataclasses.replace(inputs, prediction={"error": "RuntimeError: boom"}), max_frames=0)
    assert "Not available: RuntimeError: boom" in predicted(doc)


def test_conditions_show_the_combined_fits_noise_scale_and_the_rods_shared_errors():
    """An image run's combined fit weighs the rods by their own covariances (GLS): its noise figure is a scale on
    them, not an angle (it was shown as degrees: 0.56 read as 32 deg); the rods' shared errors are shown too."""
    from service.report.analysis import conditions

    diag = {
        "weighting": "gls",
        "direction_noise_scale": 0.56,
        "rod_errors": {
            "own_scale": 0.58,
            "pair_correlation": 0.13,
            "distance_correlation": 0.29,
            "distance_length_px": 100.0,
            "dof": 300.2,
        },
    }
    rows = dict(conditions({"methods": {"combined": {"diagnostics": diag}}}, None, None))
    assert rows["rod direction noise (combined fit)"] == "0.56 x the rods' cov_u"
    shared = rows["rods' shared errors (combined fit, correlation)"]
    assert shared == "own scale 0.58; a leg's two rods 0.13; rods nearby in the image 0.29 x exp(-d / 100 px)"
    # the geometric twin's fit (no camera): no distance term, and its noise is an angle
    diag = {"weighting": "frobenius", "direction_noise_scale": 1e-3, "rod_errors": {**diag["rod_errors"]}}
    diag["rod_errors"]["distance_correlation"] = None
    rows = dict(conditions({"methods": {"combined": {"diagnostics": diag}}}, None, None))
    assert rows["rod direction noise (combined fit)"] == "0.0573 deg"
    assert rows["rods' shared errors (combined fit, correlation)"] == "own scale 0.58; a leg's two rods 0.13"
