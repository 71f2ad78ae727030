"""The method registry: a toy method ("a-priori", tests/_toy_method.py: the nominal parameters with their tolerance,
no fit) registered in one module is seen by the pipeline, the command line, the REST service (GET /api/v1/methods,
run requests, the fit process), the report and the dashboard; the built-in three keep their names and order."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.observations import Observations
from calib.identify import registry
from calib.identify.pipeline import calibrate
from calib.identify.registry import MethodContext, MethodSpec, get_method, method_names, register_method
from tests.browser import CHROMIUM, NO_CHROMIUM, headless_chromium, page_errors
from tests.service.conftest import AUTH, service, sim, wait_state  # noqa: F401  (fixtures; rendered_zip: tests/conftest.py)

ROOT = Path(__file__).resolve().parents[1]
API = "/api/v1"
TOY = "tests._toy_method"


@pytest.fixture
def toy():
    """Register the toy method for one test (import its module), then remove it."""
    sys.modules.pop(TOY, None)
    mod = importlib.import_module(TOY)
    try:
        yield mod
    finally:
        registry.unregister_method("a-priori")
        sys.modules.pop(TOY, None)


@pytest.fixture(scope="module")
def obs_path(tmp_path_factory) -> Path:
    from drivers.sim.twin import GeometricTwin

    p = tmp_path_factory.mktemp("toy") / "obs.json"
    p.write_text(json.dumps(GeometricTwin().observations(seed=3)), encoding="utf-8")
    return p


def test_builtin_methods_in_order_with_their_properties():
    assert method_names()[:3] == ("combined", "end-effector", "legs")
    assert registry.apply_order()[:3] == ("combined", "legs", "end-effector")
    comb = get_method("combined")
    assert comb.bound and comb.identifiability is not None and "rotation" in comb.required_phases
    assert not get_method("legs").bound and "lock-4" in get_method("legs").required_phases
    with pytest.raises(InputError, match="unknown method 'nope'; methods are combined, end-effector, legs"):
        get_method("nope")


def test_register_refuses_bad_names_and_duplicates():
    def fit(obs, ctx):  # pragma: no cover - never called
        raise AssertionError

    for bad in ("All", "all", "with space", "", "x" * 40):
        with pytest.raises(InputError, match="method name"):
            MethodSpec(name=bad, label="x", colour="#000000", description="x", fit=fit)
    with pytest.raises(InputError, match="colour"):
        MethodSpec(name="x", label="x", colour="red", description="x", fit=fit)
    with pytest.raises(InputError, match="already registered"):
        register_method(MethodSpec(name="legs", label="x", colour="#000000", description="x", fit=fit))
    with pytest.raises(InputError, match="built-in"):
        registry.unregister_method("legs")


def test_toy_method_in_the_pipeline(toy, obs_path):
    obs = Observations.load(obs_path)
    assert method_names()[-1] == "a-priori" and registry.plugin_modules() == (TOY,)
    doc = calibrate(obs)
    assert list(doc["methods"]) == ["combined", "end-effector", "legs", "a-priori"]
    e = doc["methods"]["a-priori"]
    assert e["converged"] and e["identifiability"] is None and "bound" not in e
    assert e["parameters"] == pytest.approx(obs.nominal.combinations(), abs=0)
    # std from the tolerance: L is one parameter (5 mm), H-D two (5 sqrt 2), S-(q04-q03)/2 = S + ... (5 sqrt 1.5)
    t = toy.TOLERANCE_M
    assert e["std"]["L"] == pytest.approx(t) and e["std"]["H-D"] == pytest.approx(t * np.sqrt(2))
    assert e["std"]["S-(q04-q03)/2"] == pytest.approx(t * np.sqrt(1.5))
    # the nominal parameters validate as the a priori row does
    assert doc["validation"]["a-priori"]["gaps_poses"]["rms_mm"] == pytest.approx(
        doc["validation"]["a priori"]["gaps_poses"]["rms_mm"]
    )
    truth = obs.document.model_extra["truth"]["combinations"]
    assert doc["truth_errors"]["a-priori"]["L"] == pytest.approx(obs.nominal.L - truth["L"])


def test_toy_method_from_the_command_line(toy, obs_path, tmp_path, capsys):
    from service.cli import main

    assert main(["calibrate", str(obs_path), "--method", "a-priori", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert list(doc["methods"]) == ["a-priori"] and doc["methods"]["a-priori"]["converged"]
    # another process (python -m i4cal) knows it through I4CAL_METHODS, and --help lists it
    env = {**os.environ, registry.ENV_VAR: TOY, "PYTHONPATH": str(ROOT)}
    out = tmp_path / "r.json"
    r = subprocess.run(
        [sys.executable, "-m", "i4cal", "calibrate", str(obs_path), "-m", "a-priori", "-o", str(out)],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert "A priori" not in r.stderr and json.loads(out.read_text())["methods"]["a-priori"]["converged"]
    r = subprocess.run([sys.executable, "-m", "i4cal", "calibrate", "--help"], capture_output=True, text=True, env=env)
    assert "a-priori" in r.stdout
    # without it the name is refused naming the choices, in one line, exit 2
    env.pop(registry.ENV_VAR)
    r = subprocess.run(
        [sys.executable, "-m", "i4cal", "calibrate", str(obs_path), "-m", "a-priori"],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 2 and "invalid choice: 'a-priori'" in r.stderr


def test_toy_method_in_the_report(toy, obs_path, tmp_path):
    from service.cli import main

    out = tmp_path / "report.html"
    assert main(["report", str(obs_path), "-o", str(out), "--methods", "a-priori", "legs", "--quiet"]) == 0
    html = out.read_text(encoding="utf-8")
    assert "A priori (toy, no fit): the nominal parameters with their manufacturing tolerance" in html
    assert "legs only: joint centres from the lock-actuator phases" in html


async def test_toy_method_in_the_api_and_the_fit_process(toy, service, obs_path, tmp_path, rendered_zip):  # noqa: F811
    c = service.client
    ms = (await c.get(f"{API}/methods")).json()
    assert [m["name"] for m in ms] == ["combined", "end-effector", "legs", "a-priori"]
    toy_out = ms[-1]
    assert toy_out["label"] == "A priori (toy, no fit)" and toy_out["colour"] == "#8c564b"
    assert toy_out["required_phases"] == ["poses"] and toy_out["bound"] is False
    assert ms[0]["bound"] is True and ms[0]["required_phases"] == ["rotation", "translation", "poses"]
    spec = (await c.get(f"{API}/openapi.json")).json()
    enum = spec["components"]["schemas"]["RunCreate"]["properties"]["methods"]["items"]["enum"]
    assert enum == ["combined", "end-effector", "legs", "a-priori"]
    # a run request naming it is accepted; an unknown name is refused naming the field and the methods
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": ["nope"]}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["body", "methods"]
    assert "methods are combined, end-effector, legs, a-priori" in r.json()["detail"][0]["msg"]
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": ["a-priori"]}, headers=AUTH)
    assert r.status_code == 202, r.text
    assert r.json()["methods"] == ["a-priori"]
    # an offline run with it on an uploaded rendered dataset: its result, then applied as the bench's calibration
    ds = await c.post(f"{API}/datasets", content=rendered_zip, headers={"Content-Type": "application/zip", **AUTH})
    assert ds.status_code == 201, ds.text
    r = await c.post(f"{API}/runs", json={"dataset": ds.json()["id"], "methods": ["a-priori"]}, headers=AUTH)
    run = await wait_state(c, r.json()["id"])
    assert run["state"] == "done", run
    res = (await c.get(f"{API}/runs/{run['id']}/result")).json()
    assert list(res["methods"]) == ["a-priori"]
    assert res["methods"]["a-priori"]["parameters"] == pytest.approx(res["nominal_combinations"])
    cal = await c.post(f"{API}/runs/{run['id']}/apply", json={"method": "a-priori"}, headers=AUTH)
    assert cal.status_code == 201, cal.text
    assert (await c.get(f"{API}/calibration/current")).json()["method"] == "a-priori"
    report = await c.get(f"{API}/runs/{run['id']}/report", params={"methods": "a-priori"})
    assert report.status_code == 200 and "A priori (toy, no fit)" in report.text
    # the service's fit process (a forkserver child: a fresh interpreter) fits with it
    from service.jobs import Job

    events: list[tuple[str, dict]] = []
    doc = Job("fit", {"observations": str(obs_path), "methods": ["a-priori"]}, lambda k, d: events.append((k, d))).run()
    assert list(doc["methods"]) == ["a-priori"] and doc["methods"]["a-priori"]["converged"]
    assert ("fit", {"method": "a-priori", "state": "done"}) in [
        (k, {"method": d["method"], "state": d["state"]}) for k, d in events if k == "fit"
    ]


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
async def test_toy_method_in_the_dashboard(toy, service):  # noqa: F811
    pytest.importorskip("playwright.async_api")
    async with headless_chromium() as browser:
        page = await browser.new_page()
        errors = page_errors(page)
        await page.goto(service.url + "/dashboard")
        await page.wait_for_selector("#methods[data-loaded='true']")
        boxes = page.locator("#methods input[type=checkbox]")
        assert await boxes.evaluate_all("els => els.map(e => e.value)") == [
            "combined",
            "end-effector",
            "legs",
            "a-priori",
        ]
        assert "A priori (toy, no fit)" in await page.inner_text("#methods")
        assert not errors, errors


def test_method_context_is_what_the_pipeline_hands_over(toy, obs_path):
    seen: list[MethodContext] = []

    def fit(obs, ctx):
        seen.append(ctx)
        return toy.fit_a_priori(obs, ctx)

    register_method(MethodSpec(name="spy", label="spy", colour="#000000", description="x", fit=fit))
    try:
        calibrate(Observations.load(obs_path), ["spy"], on_iteration=lambda info: None)
    finally:
        registry.unregister_method("spy")
    assert seen and seen[0].base_frame is not None and seen[0].on_iteration is not None
