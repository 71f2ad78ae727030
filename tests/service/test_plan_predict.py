"""What a plan will buy before motion: `i4cal plan predict`, POST /api/v1/plans/predict, and a run's prediction kept
with the run (GET /api/v1/runs/{id}) beside what the fits then report; on the simulated bench (real Modbus on
loopback, real HTTP)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np

from calib.design import visibility
from calib.formats.plan import Plan, SoftLimits, Step, make_plan, random_poses
from calib.model.kinematics import ikm
from calib.model.parameters import NOMINAL
from service.cli import main
from service.design import twin_scene
from tests.service.conftest import AUTH, wait_state

API = "/api/v1"
BENCH_SIM = Path(__file__).resolve().parents[2] / "deploy" / "bench-sim.toml"


def _plan_with_partly_seen_fit_poses(n: int) -> Plan:
    """The paper's plan with ``n`` more fit poses (within the limits, reachable) whose board's margin leaves the
    image (its corners stay in view: tests/calib/test_plan_check.py has boards the camera cannot measure)."""
    scene = twin_scene()
    q = ikm(NOMINAL, random_poses(NOMINAL, 3000, np.random.default_rng(3), limits=SoftLimits()))
    blind = q[~visibility(scene, NOMINAL, q)["board"]][:n]
    assert len(blind) == n
    full = make_plan("full", NOMINAL)
    return Plan(name="mine", steps=[*full.steps, *(Step(phase="poses", q=x) for x in blind.tolist())])


def test_cli_predicts_a_plan_name_and_a_plan_file(tmp_path, capsys):
    assert main(["plan", "predict", "full", "--bench", str(BENCH_SIM)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("plan full: rotation 10, translation 10, poses 20"), out
    assert "predicted std (mm)" in out and "motion time" in out
    rows = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith("  ") and "|" in ln}
    assert {"combined", "end-effector", "legs"} <= set(rows), out
    # a file with fit poses the camera will not see in full: listed by step, and said in the notes
    path = tmp_path / "mine.json"
    plan = _plan_with_partly_seen_fit_poses(2)
    plan.save(path)
    assert main(["plan", "predict", str(path), "--bench", str(BENCH_SIM), "--methods", "combined", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    n = len(plan.steps)
    assert [u["step"] for u in doc["unseen"]] == [n - 2, n - 1] and not doc["unseen"][0]["board"]
    assert doc["unseen"][0]["board_corners"] == 15 and doc["measured_counts"]["poses"] == 22  # measured, counted
    assert any("partly out of view in 2 steps" in n for n in doc["notes"]), doc["notes"]
    assert set(doc["prediction"]["std_m"]) == {"combined"} and doc["motion"]["total_s"] > 0
    assert main(["plan", "predict", str(path), "--bench", str(BENCH_SIM)]) == 0
    out = capsys.readouterr().out
    assert f"  step {n - 1} (poses): board partly out of view (15 corners in the image)" in out, out
    # user mistakes: one line naming the option or the file, exit status 2
    assert main(["plan", "predict", "full", "--bench", str(BENCH_SIM), "--methods", "combined,magic"]) == 2
    assert "--methods" in capsys.readouterr().err
    assert main(["plan", "predict", str(tmp_path / "none.json"), "--bench", str(BENCH_SIM)]) == 2
    assert "none.json" in capsys.readouterr().err


async def test_api_predicts_the_plan_a_run_would_execute(service):
    c = service.client
    r = await c.post(f"{API}/plans/predict", json={"plan": "full", "methods": ["combined", "legs"]}, headers=AUTH)
    assert r.status_code == 200, r.text
    d = r.json()
    assert set(d["predicted_std_m"]) <= {"combined", "legs"} and d["predicted_std_m"]["combined"]["L"] > 0
    assert d["motion_time_s"] > 0 and d["plan"] == "full" and d["unseen"] == []
    # requests at the same time (a page asking again as its token is entered) wait their turn, none refused
    both = await asyncio.gather(
        *(c.post(f"{API}/plans/predict", json={"plan": p}, headers=AUTH) for p in ("full", "pose-set"))
    )
    assert [x.status_code for x in both] == [200, 200] and both[1].json()["plan"] == "pose-set"
    # an inline plan with a fit pose whose board is partly out of view: listed with its corners in view
    plan = _plan_with_partly_seen_fit_poses(1)
    r = await c.post(
        f"{API}/plans/predict", json={"plan": plan.model_dump(mode="json", exclude_none=True)}, headers=AUTH
    )
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["unseen"] == [
        {"step": len(plan.steps) - 1, "phase": "poses", "board": False, "board_corners": 15, "rods_hidden": []}
    ]
    assert d["measured_counts"] == d["counts"]
    # an invalid plan: 422 naming the field
    bad = plan.model_dump(mode="json", exclude_none=True)
    bad["steps"][3]["q"] = [9.0, 0.0, 0.0, 0.0]
    r = await c.post(f"{API}/plans/predict", json={"plan": bad}, headers=AUTH)
    assert r.status_code == 422 and "steps" in r.text, r.text


async def test_a_prediction_never_holds_up_or_fails_a_run(service, monkeypatch):
    """A run that only records (no method) has no prediction; a prediction that fails is stored as its error and
    the run goes on (the full prediction of a run is checked against POST /plans/predict in
    tests/service/test_api.py's full run on images)."""
    c = service.client
    r = await c.post(f"{API}/runs", json={"plan": "full", "methods": []}, headers=AUTH)
    run = await wait_state(c, r.json()["id"])
    assert run["state"] == "done" and run["prediction"] is None, run

    async def broken(*args, **kwargs):
        raise RuntimeError("no scene for this bench")

    # the prediction is computed in a child process (service.jobs.HeavyPool.run_now): it fails as the server sees it
    monkeypatch.setattr(service.app.state.manager.heavy, "run_now", broken)
    r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
    run = await wait_state(c, r.json()["id"])
    assert run["state"] == "done", run["error"]
    assert run["prediction"]["error"] == "RuntimeError: no scene for this bench", run["prediction"]
    events = (await c.get(f"{API}/runs/{run['id']}/events", params={"follow": "false"})).text
    assert "event: prediction" in events


def test_cli_predicts_the_paper_plan_on_the_real_bench_example(capsys):
    """A named plan is drawn within the bench's own soft limits (the real example's 0-750 mm; the line shortened to
    them): before, the 'full' plan for the simulated bench's limits was refused there, naming a fit pose."""
    real = BENCH_SIM.with_name("bench-real.example.toml")
    assert main(["plan", "predict", "full", "--bench", str(real)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("plan full: rotation 10, translation 10, poses 20") and "line" in out, out


def _camera_file(path: Path, width: int, height: int) -> Path:
    """The simulated bench's lens on a ``width`` x ``height`` sensor, as a camera file (i4cal.camera/1)."""
    import dataclasses

    dataclasses.replace(twin_scene().camera, width=width, height=height).save(path)
    return path


def test_cli_predicts_and_designs_for_the_benchs_own_camera(tmp_path, capsys):
    """--camera FILE: the bench's own camera in place of the simulated bench's. On a 640 x 480 sensor the paper's
    plan loses board poses (listed, not counted) and its predicted std grows; on a 900 x 680 one a design for that
    camera keeps every sweep and fit pose's board wholly in view, where the same design for the simulated bench's
    camera does not."""
    small = _camera_file(tmp_path / "small.json", 640, 480)
    base = ["plan", "predict", "full", "--bench", str(BENCH_SIM), "--methods", "end-effector", "--json"]
    assert main(base) == 0
    ref = json.loads(capsys.readouterr().out)
    assert main([*base, "--camera", str(small)]) == 0
    doc = json.loads(capsys.readouterr().out)
    blind = [u for u in doc["unseen"] if u["board_corners"] < 6 and u["phase"] == "poses"]
    assert blind and doc["measured_counts"]["poses"] == doc["counts"]["poses"] - len(blind)
    got, was = doc["prediction"]["std_m"]["end-effector"], ref["prediction"]["std_m"]["end-effector"]
    assert all(got[k] > was[k] for k in got), (got, was)
    cam = _camera_file(tmp_path / "cam.json", 900, 680)
    design = ["plan", "design", "--bench", str(BENCH_SIM), "--n-fit", "4", "--no-line", "--candidates", "60"]
    partly = {}
    for name, extra in (("twin", []), ("own", ["--camera", str(cam)])):
        plan = tmp_path / f"{name}.json"
        assert main([*design, *extra, "-o", str(plan)]) == 0
        capsys.readouterr()
        assert main(["plan", "predict", str(plan), "--bench", str(BENCH_SIM), "--camera", str(cam), "--json"]) == 0
        unseen = json.loads(capsys.readouterr().out)["unseen"]
        partly[name] = [u for u in unseen if u["phase"] in ("rotation", "translation", "poses") and not u["board"]]
    assert partly["twin"] and not partly["own"], partly


async def test_the_services_camera_file_is_the_predictions_camera(tmp_path, sim):
    """A service with a camera file predicts with that camera: POST /plans/predict and a run's prediction."""
    from tests.service.conftest import make_settings, start_service

    cam = _camera_file(tmp_path / "cam.json", 640, 480)
    svc = await start_service(make_settings(tmp_path, sim, camera_file=cam), sim)
    try:
        d = (await svc.client.post(f"{API}/plans/predict", json={"plan": "full"}, headers=AUTH)).json()
        assert any(u["board_corners"] < 6 for u in d["unseen"]), d["unseen"]
        assert d["measured_counts"] != d["counts"]
    finally:
        await svc.client.aclose()
        await svc.stop()


def test_cli_predicts_for_the_camera_file_the_bench_file_names(tmp_path, capsys):
    """Without --camera, `plan predict` uses the bench file's own camera file ([camera] intrinsics), as `acquire`
    records it: the same prediction as --camera FILE, not the simulated bench's camera."""
    small = _camera_file(tmp_path / "small.json", 640, 480)
    bench = tmp_path / "bench.toml"
    text = BENCH_SIM.read_text(encoding="utf-8")
    assert "\n[camera]\n" in text
    bench.write_text(text.replace("\n[camera]\n", '\n[camera]\nintrinsics = "small.json"\n', 1), encoding="utf-8")
    base = ["plan", "predict", "full", "--methods", "end-effector", "--json"]
    assert main([*base, "--bench", str(bench)]) == 0
    named = json.loads(capsys.readouterr().out)["prediction"]["std_m"]
    assert main([*base, "--bench", str(BENCH_SIM), "--camera", str(small)]) == 0
    given = json.loads(capsys.readouterr().out)["prediction"]["std_m"]
    assert main([*base, "--bench", str(BENCH_SIM)]) == 0
    sim = json.loads(capsys.readouterr().out)["prediction"]["std_m"]
    assert named == given and named != sim


def test_cli_predicts_before_the_camera_step_with_a_warning(tmp_path, capsys):
    """A bench file naming a camera file not written yet (the real-bench example before `i4cal camera calibrate`):
    the prediction uses the simulated bench's camera and says so."""
    bench = tmp_path / "bench.toml"
    text = BENCH_SIM.read_text(encoding="utf-8")
    bench.write_text(text.replace("\n[camera]\n", '\n[camera]\nintrinsics = "later.json"\n', 1), encoding="utf-8")
    assert main(["plan", "predict", "full", "--bench", str(bench), "--methods", "end-effector", "--json"]) == 0
    out = capsys.readouterr()
    assert "later.json does not exist yet" in out.err
    assert main(["plan", "predict", "full", "--bench", str(BENCH_SIM), "--methods", "end-effector", "--json"]) == 0
    assert json.loads(out.out)["prediction"] == json.loads(capsys.readouterr().out)["prediction"]
