"""``GET /api/v1/runs/{id}/export`` and ``GET /api/v1/calibration/current`` serve the calibration document
(i4cal.calibration/1) of a finished offline run (the shared rendered dataset, uploaded and calibrated by the
service); ``i4cal export RUN`` takes the same run from the data directory and from the running service, and its
``--check`` passes over the run's own plan."""

from __future__ import annotations

import asyncio
import io
import json
import zipfile
from datetime import datetime

import yaml

from calib.identify.export import REPRODUCE_TOL_M, CalibrationDocument, load_calibration
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES
from service.cli import main
from service.report.analysis import dataset_sha256
from tests.service.conftest import AUTH, wait_state

API = "/api/v1"


def _reproduces(doc: CalibrationDocument, entry: dict) -> None:
    got = doc.to_parameters().combinations()
    assert max(abs(got[k] - entry["combinations"][k]) for k in COMBINATION_NAMES) <= REPRODUCE_TOL_M
    assert doc.combinations == entry["combinations"] and doc.covariance == entry["covariance"]


async def test_export_route_current_calibration_and_cli_run_modes(service, rendered_zip, tmp_path, monkeypatch, capsys):
    c = service.client
    assert (await c.get(f"{API}/runs/{'a' * 32}/export")).status_code == 404
    ds = await c.post(f"{API}/datasets", content=rendered_zip, headers={"Content-Type": "application/zip", **AUTH})
    assert ds.status_code == 201, ds.text
    r = await c.post(f"{API}/runs", json={"dataset": ds.json()["id"], "methods": ["combined", "legs"]}, headers=AUTH)
    rid = r.json()["id"]
    run = await wait_state(c, rid, timeout=300)
    assert run["state"] == "done", run
    result = (await c.get(f"{API}/runs/{rid}/result")).json()
    assert all(result["methods"][m]["converged"] for m in ("combined", "legs"))
    with zipfile.ZipFile(io.BytesIO(rendered_zip)) as zf:
        zf.extractall(tmp_path / "unzipped")
    ds_hash = dataset_sha256(tmp_path / "unzipped" / "dataset")[0]

    # the run's export: the recommended method, its provenance, its numbers
    r = await c.get(f"{API}/runs/{rid}/export")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/json")
    doc = load_calibration(r.json())
    assert doc.method == "combined" and doc.method_choice.startswith("recommended: load combined")
    assert doc.run == rid and doc.bench == run["bench"] and doc.dataset_hash == ds_hash
    assert datetime.fromisoformat(doc.date) == datetime.fromisoformat(run["finished_at"])
    _reproduces(doc, result["methods"]["combined"])
    assert doc.fixed_at_nominal == ["H", "S", "q03"]
    legs = load_calibration((await c.get(f"{API}/runs/{rid}/export", params={"method": "legs"})).json())
    _reproduces(legs, result["methods"]["legs"])
    assert legs.seven == result["methods"]["legs"]["seven"]
    r = await c.get(f"{API}/runs/{rid}/export", params={"method": "legs", "format": "yaml"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/yaml")
    as_yaml = yaml.safe_load(r.text)
    assert as_yaml["seven"] == legs.seven and as_yaml["covariance"] == legs.covariance
    # mistakes: a method the run did not fit, an unknown one, a format, a run without a result
    r = await c.get(f"{API}/runs/{rid}/export", params={"method": "end-effector"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "method"]
    assert (await c.get(f"{API}/runs/{rid}/export", params={"method": "nope"})).status_code == 422
    assert (await c.get(f"{API}/runs/{rid}/export", params={"format": "xml"})).status_code == 422
    rid0 = (await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)).json()["id"]
    assert (await wait_state(c, rid0))["state"] == "done"
    r = await c.get(f"{API}/runs/{rid0}/export")
    assert r.status_code == 409 and "no result" in r.json()["detail"]

    # the current calibration: the document, with the record's keys kept as they were
    assert (await c.get(f"{API}/calibration/current")).status_code == 404
    assert (await c.post(f"{API}/runs/{rid}/apply", json={"method": "legs"}, headers=AUTH)).status_code == 201
    cur = (await c.get(f"{API}/calibration/current")).json()
    assert cur["run_id"] == rid and cur["method"] == "legs" and cur["software_version"] and isinstance(cur["id"], int)
    assert set(cur["parameters"]) == set(PARAMETER_NAMES) and cur["parameters"] == legs.seven
    assert set(cur["combinations"]) == set(COMBINATION_NAMES) and cur["applied_at"]
    cur_doc = load_calibration(cur)
    assert cur_doc.seven == legs.seven and cur_doc.covariance == legs.covariance
    assert cur_doc.dataset_hash == ds_hash and cur_doc.run == rid and cur_doc.method_choice.startswith("applied")
    assert (await c.post(f"{API}/runs/{rid}/apply", headers=AUTH)).json()["method"] == "combined"
    cur = (await c.get(f"{API}/calibration/current")).json()
    assert cur["parameters"] is None  # the record's key keeps its meaning: the seven where the method identifies them
    assert cur["seven"] == doc.seven and cur["fixed_at_nominal"] == ["H", "S", "q03"]
    r = await c.get(f"{API}/calibration/current", params={"format": "yaml"})
    assert r.headers["content-type"].startswith("application/yaml") and yaml.safe_load(r.text)["seven"] == doc.seven
    hist = (await c.get(f"{API}/calibration/history")).json()
    assert [h["method"] for h in hist] == ["combined", "legs"]  # the history as it was

    # the command line: the run from the data directory (an id prefix), and from the running service
    monkeypatch.setenv("I4CAL_DATA_DIR", str(service.settings.data_dir))
    out = tmp_path / "run.json"
    assert await asyncio.to_thread(main, ["export", rid[:10], "-o", str(out), "--method", "legs"]) == 0
    from_dir = json.loads(out.read_text(encoding="utf-8"))
    served_legs = (await c.get(f"{API}/runs/{rid}/export", params={"method": "legs"})).json()
    assert _same(from_dir, served_legs) and from_dir["dataset_hash"] == ds_hash  # the same document, key for key
    capsys.readouterr()
    assert await asyncio.to_thread(main, ["export", "--check", str(out), "--json"]) == 0  # the run it names
    rep = json.loads(capsys.readouterr().out)
    assert rep["plan"].startswith("the run's plan") and rep["result"] == f"run {rid}", rep
    assert rep["n_poses"] == len(_dataset(tmp_path)["frames"])  # the uploaded dataset's frames, as executed
    out2 = tmp_path / "server.yaml"
    assert await asyncio.to_thread(main, ["export", rid[:8], "--server", service.url, "-o", str(out2)]) == 0
    served = yaml.safe_load(out2.read_text(encoding="utf-8"))
    assert served["method"] == "combined" and _same(served, doc.model_dump(mode="json"))
    assert await asyncio.to_thread(main, ["export", "--check", str(out2), "--server", service.url]) == 0
    assert await asyncio.to_thread(main, ["export", rid0, "--server", service.url, "-o", str(tmp_path / "x")]) == 2
    assert "no result" in capsys.readouterr().err

    # a current calibration whose run's result is no longer stored: the document from the record alone
    from service.db import Run

    with service.app.state.manager.db.session() as s:
        s.get(Run, rid).result = None
    cur = (await c.get(f"{API}/calibration/current")).json()
    gone = load_calibration(cur)
    assert gone.seven == doc.seven and gone.combinations == doc.combinations and gone.covariance is None
    assert gone.fixed_at_nominal == ["H", "S", "q03"] and cur["id"] and cur["run_id"] == rid


def _same(a: dict, b: dict) -> bool:
    """Two documents equal but for when they were written."""
    return {k: v for k, v in a.items() if k != "exported_at"} == {k: v for k, v in b.items() if k != "exported_at"}


def _dataset(tmp_path) -> dict:
    return json.loads((tmp_path / "unzipped" / "dataset" / "dataset.json").read_text(encoding="utf-8"))
