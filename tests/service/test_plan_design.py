"""`i4cal plan design` and POST /api/v1/plans/design: a designed plan that validate_plan, `i4cal acquire --plan` and
POST /api/v1/runs (inline plan) accept, on the simulated bench (real Modbus on loopback, real HTTP)."""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.dataset import Dataset
from calib.formats.plan import Plan, SoftLimits, validate_plan
from calib.model.parameters import NOMINAL
from service.cli import main
from service.design import parse_length
from tests.browser import CHROMIUM, NO_CHROMIUM, enter_token, headless_chromium, page_errors
from tests.service.conftest import AUTH, wait_state

API = "/api/v1"
BENCH_SIM = Path(__file__).resolve().parents[2] / "deploy" / "bench-sim.toml"
SMALL = ["--n-fit", "4", "--no-line", "--candidates", "60"]


def test_lengths_in_mm_um_and_metres():
    assert parse_length("0.05mm") == pytest.approx(5e-5)
    assert parse_length("50um") == pytest.approx(5e-5)
    assert parse_length("5e-5") == pytest.approx(5e-5)
    assert parse_length("5e-5m") == pytest.approx(5e-5)
    for bad in ("0.05 furlong", "mm", "-1mm", "2m"):
        with pytest.raises(InputError):
            parse_length(bad)


def test_cli_design_writes_a_plan_that_validates(tmp_path, capsys):
    out = tmp_path / "plan.json"
    assert main(["plan", "design", "--bench", str(BENCH_SIM), "--target-std", "0.5mm", *SMALL, "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "predicted std (mm)" in text and "combined" in text and "motion time" in text
    plan = Plan.load(out)
    validate_plan(plan, NOMINAL, SoftLimits(q_min=[-0.1] * 4, q_max=[0.8] * 4))
    assert plan.count()["poses"] == 4 and "line" not in plan.count()
    design = plan.model_extra["design"]
    assert design["request"]["target_std_m"] == [5e-4] * 4
    assert set(design["prediction"]["std_m"]) == {"combined", "end-effector", "legs"}


def test_cli_design_json_and_a_bad_unit(tmp_path, capsys):
    assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["n_fit"] == 4 and doc["motion"]["total_s"] > 0
    assert main(["plan", "design", "--bench", str(BENCH_SIM), "--target-std", "3 furlongs"]) == 2
    assert "target-std" in capsys.readouterr().err
    # --draws: the best of several draws of the candidates, said in the notes
    assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--draws", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert any("best of 2 draws" in n for n in doc["notes"]), doc["notes"]
    assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--draws", "0"]) == 2
    assert "draws" in capsys.readouterr().err


def test_cli_design_breaks_the_prediction_down_by_source(capsys):
    """--breakdown prints, under the end-effector and legs methods, the std each source of error contributes, whose
    squares add up to the method's (the printed figures, rounded to 0.1 nm); --json always carries them."""
    assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--breakdown"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {ln.split()[0]: ln for ln in lines if ln.startswith("  ") and "|" in ln}
    legs_at = next(i for i, ln in enumerate(lines) if ln.startswith("  legs "))
    parts = [ln for ln in lines[legs_at + 1 :] if ln.startswith("    ") and "|" in ln]
    names = {ln.split()[0] for ln in parts}
    assert {"joint_centres", "joint_depth_systematic", "leg_directions"} <= names, lines

    def values(line: str) -> list[float]:
        return [float(v) for v in line.split(None, 1)[1].split("|")]

    total = np.array(values(rows["legs"]))
    summed = np.sqrt(np.sum([np.square(values(ln)) for ln in parts], axis=0))
    assert summed == pytest.approx(total, abs=2e-4)
    assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL]) == 0
    assert "joint_depth_systematic" not in capsys.readouterr().out
    assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["prediction"]["parts_std_m"]) == {"end-effector", "legs"}


def test_cli_design_lock_frames_buy_the_legs_joints(capsys):
    """--lock-frames sets the frames of each lock phase: twice as many shrink the legs method's joint-centre part (the
    sensor noise, which averages over the frames) but not its systematic depth part (the shading, which does not)."""
    parts = {}
    for frames in (4, 8):
        assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--lock-frames", str(frames), "--json"]) == 0
        doc = json.loads(capsys.readouterr().out)
        assert all(doc["counts"][f"lock-{i}"] == frames for i in range(1, 5)), doc["counts"]
        parts[frames] = doc["prediction"]["parts_std_m"]["legs"]
    for k in ("L", "S-q02/2", "S-(q04-q03)/2"):
        ratio = parts[8]["joint_centres"][k] / parts[4]["joint_centres"][k]
        assert 0.5 < ratio < 0.85, (k, ratio)  # about 1/sqrt(2), the lock poses differing
        sys_ratio = parts[8]["joint_depth_systematic"][k] / parts[4]["joint_depth_systematic"][k]
        assert sys_ratio > 0.8, (k, sys_ratio)
    for bad in ("1", "51"):
        assert main(["plan", "design", "--bench", str(BENCH_SIM), *SMALL, "--lock-frames", bad]) == 2
        assert "--lock-frames" in capsys.readouterr().err


def _paper_plan(path: Path, n_fit: int = 12) -> Plan:
    from calib.formats.plan import make_plan

    plan = make_plan("full", NOMINAL, seed=0, n_fit=n_fit)
    plan = Plan(name="routine", steps=[s for s in plan.steps if s.phase != "line"])
    plan.save(path)
    return plan


def test_cli_design_better_than_a_reference_plan(tmp_path, capsys):
    """``--better-than``: the target is the reference's predicted combined std on every combination; the plan
    designed is the shortest that meets it (its predicted std no larger on any combination)."""
    ref = tmp_path / "routine.json"
    _paper_plan(ref)
    out = tmp_path / "plan.json"
    argv = ["plan", "design", "--bench", str(BENCH_SIM), "--better-than", str(ref), "--no-line", "--candidates", "60"]
    assert main([*argv, "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"target: the predicted combined std of {ref}" in text
    design = Plan.load(out).model_extra["design"]
    assert design["request"]["criterion"] == "target" and design["target_met"] is True
    target = design["request"]["target_std_m"]
    assert len(target) == 4 and len(set(target)) == 4  # one per combination, the reference's
    got = design["prediction"]["std_m"]["combined"]
    for name, t in zip(("L", "H-D", "S-q02/2", "S-(q04-q03)/2"), target, strict=True):
        assert got[name] <= t * (1 + 1e-9), (name, got[name], t)
    assert design["n_fit"] <= 12
    assert main([*argv, "--target-std", "0.05mm"]) == 2
    assert "--better-than" in capsys.readouterr().err


def test_cli_tradeoff_prints_each_count_and_writes_the_recommended_plan(tmp_path, capsys):
    """``--tradeoff``: a designed plan per count side by side; with a target, the fewest poses meeting it, which ``-o``
    writes; no plan to write when none meets it; not with ``--n-fit``."""
    small = ["--no-line", "--candidates", "60", "--lock-frames", "2"]
    argv = ["plan", "design", "--bench", str(BENCH_SIM), "--tradeoff", "12,4", *small, "--json"]
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["n_fit"] for r in doc["tradeoff"]] == [4, 12] and doc["recommended_n_fit"] is None
    assert doc["recommendation"] == "no target or time limit: nothing to recommend"
    assert doc["count_trend"]["n_fit"] == [4, 12] and doc["count_trend"]["n_fit_needed"] is None, doc["count_trend"]
    few, many = (
        [r["predicted_std_m"]["combined"][k] for k in ("L", "H-D", "S-q02/2", "S-(q04-q03)/2")] for r in doc["tradeoff"]
    )
    # a target between the two counts' worst predicted std: 12 poses meet it, 4 do not
    target = float(np.sqrt(max(few) * max(many)))
    out = tmp_path / "plan.json"
    argv = ["plan", "design", "--bench", str(BENCH_SIM), "--tradeoff", "4,12", *small, "--target-std", f"{target:.6g}"]
    assert main([*argv, "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "trade-off" in text and "combined (optimised):" in text and "legs:" in text
    assert "recommended: 12 fit poses" in text and f"wrote {out} (12 fit poses)" in text
    assert "with more fit poses (the trend of the predicted std from 4 to 12): levels off near combined L" in text, text
    plan = Plan.load(out)
    validate_plan(plan, NOMINAL)
    assert plan.count()["poses"] == 12
    # a target no count meets: nothing written, the option named
    assert main([*argv[:-1], "1e-7", "-o", str(tmp_path / "none.json")]) == 2
    assert "--out" in capsys.readouterr().err and not (tmp_path / "none.json").exists()
    assert main(["plan", "design", "--bench", str(BENCH_SIM), "--tradeoff", "4,8", "--n-fit", "4"]) == 2
    assert "--tradeoff" in capsys.readouterr().err
    assert main(["plan", "design", "--bench", str(BENCH_SIM), "--tradeoff", "4,eight"]) == 2
    assert "--tradeoff" in capsys.readouterr().err


async def test_acquire_runs_a_designed_plan(sim, tmp_path):
    text = (
        BENCH_SIM.read_text()
        .replace("modbus+tcp://127.0.0.1:5020", sim.actuators_uri)
        .replace('uri = "sim://127.0.0.1:5022"', f'uri = "{sim.camera_uri}"', 1)
        .replace('uri = "sim://127.0.0.1:5022"', f'uri = "{sim.operator_uri}"', 1)
    )
    bench = tmp_path / "bench.toml"
    bench.write_text(text)
    plan_path = tmp_path / "plan.json"
    rc = await asyncio.to_thread(main, ["plan", "design", "--bench", str(bench), *SMALL, "-o", str(plan_path)])
    assert rc == 0
    # acquire installs signal handlers (main thread only): a real `i4cal acquire` process against this loop's bench
    proc = await asyncio.create_subprocess_exec(
        *[sys.executable, "-m", "service.cli", "acquire", "--bench", str(bench), "--plan", str(plan_path)],
        *["--out", str(tmp_path / "ds"), "--no-progress"],
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    _, err = await asyncio.wait_for(proc.communicate(), 120)
    assert proc.returncode == 0, err.decode()
    plan = Plan.load(plan_path)
    ds = Dataset.open(tmp_path / "ds")
    assert len(ds.frames) == sum(plan.count().values())


async def test_api_designs_a_plan_that_runs_inline(service):
    c = service.client
    body = {"n_fit": 4, "with_line": False, "candidates": 60, "target_std_m": 5e-4}
    r = await c.post(f"{API}/plans/design", json=body)
    assert r.status_code == 401
    r = await c.post(f"{API}/plans/design", json=body, headers=AUTH)
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["n_fit"] == 4 and d["counts"]["poses"] == 4
    assert d["predicted_std_m"]["combined"]["L"] > 0 and d["motion_time_s"] > 0
    # the sources of the end-effector and legs methods' error, their squares adding up to the method's std
    assert set(d["predicted_parts_std_m"]) == {"end-effector", "legs"}
    for m, parts in d["predicted_parts_std_m"].items():
        for k, std in d["predicted_std_m"][m].items():
            assert sum(p[k] ** 2 for p in parts.values()) == pytest.approx(std**2, rel=1e-9), (m, k)
    plan = Plan.from_dict(d["plan"])
    validate_plan(plan, NOMINAL)  # the simulated bench's limits are the defaults
    r = await c.post(f"{API}/runs", json={"plan": d["plan"], "methods": []}, headers=AUTH)
    assert r.status_code == 202, r.text
    run = await wait_state(c, r.json()["id"])
    assert run["state"] == "done", run
    assert run["progress"]["done"] == sum(d["counts"].values())


async def test_api_design_draws_at_most_the_services_candidates(tmp_path, sim):
    """An operator caps the CPU a design request may take (``design_max_candidates``): a request asking for more
    candidates is drawn with the cap and says so; one within it is drawn as asked, without the note."""
    from tests.service.conftest import make_settings, start_service

    svc = await start_service(make_settings(tmp_path, sim, design_max_candidates=40), sim)
    try:
        body = {"n_fit": 4, "with_line": False, "candidates": 500}
        r = await svc.client.post(f"{API}/plans/design", json=body, headers=AUTH)
        assert r.status_code == 200, r.text
        assert "candidates: 40 drawn, the service's limit (asked 500)" in r.json()["notes"]
        assert r.json()["n_fit"] == 4
        r = await svc.client.post(f"{API}/plans/design", json={**body, "candidates": 30}, headers=AUTH)
        assert r.status_code == 200 and not any("service's limit" in n for n in r.json()["notes"])
    finally:
        await svc.client.aclose()
        await svc.stop()


def test_cli_design_for_the_legs_method_too(tmp_path, capsys):
    """``--methods combined,legs --better-than``: each method aims at the reference's own predicted std, and the plan
    meets both (the legs method's std is 5-20x the combined one's: one target for both could not be met)."""
    ref = tmp_path / "routine.json"
    _paper_plan(ref)
    out = tmp_path / "plan.json"
    argv = ["plan", "design", "--bench", str(BENCH_SIM), "--better-than", str(ref), "--methods", "combined,legs"]
    assert main([*argv, "--no-line", "--candidates", "300", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"target: the predicted combined std of {ref}" in text
    assert f"target: the predicted legs std of {ref}" in text
    design = Plan.load(out).model_extra["design"]
    assert design["request"]["methods"] == ["combined", "legs"] and design["target_met"] is True
    targets = {"combined": design["request"]["target_std_m"], **design["request"]["method_targets_m"]}
    for m, target in targets.items():
        got = design["prediction"]["std_m"][m]
        for name, t in zip(("L", "H-D", "S-q02/2", "S-(q04-q03)/2"), target, strict=True):
            assert got[name] <= t * (1 + 1e-9), (m, name, got[name], t)
    assert targets["legs"][0] > 3 * targets["combined"][0]


async def test_api_designs_better_than_a_reference_plan(service, tmp_path):
    c = service.client
    ref = _paper_plan(tmp_path / "routine.json").model_dump(mode="json", exclude_none=True)
    body = {"n_fit": 8, "with_line": False, "candidates": 60, "better_than": ref}
    r = await c.post(f"{API}/plans/design", json=body, headers=AUTH)
    assert r.status_code == 200, r.text
    request = r.json()["plan"]["design"]["request"]
    assert request["criterion"] == "target" and len(request["target_std_m"]) == 4
    r = await c.post(f"{API}/plans/design", json={**body, "methods": ["combined", "legs"]}, headers=AUTH)
    assert r.status_code == 200, r.text
    request = r.json()["plan"]["design"]["request"]
    assert request["methods"] == ["combined", "legs"] and len(request["method_targets_m"]["legs"]) == 4
    r = await c.post(f"{API}/plans/design", json={**body, "target_std_m": 5e-5}, headers=AUTH)
    assert r.status_code == 422 and "better_than" in r.text
    r = await c.post(f"{API}/plans/design", json={**body, "better_than": {"steps": "none"}}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["body", "better_than"], r.text


async def test_api_designs_the_best_of_several_candidate_draws(service):
    """``draws``: the best of several draws of the candidates, the plan saying which draw it is."""
    body = {"n_fit": 4, "with_line": False, "candidates": 40, "draws": 2}
    r = await service.client.post(f"{API}/plans/design", json=body, headers=AUTH)
    assert r.status_code == 200, r.text
    request = r.json()["plan"]["design"]["request"]
    assert request["draws"] == 2 and request["candidate_draw"] in (0, 1), request
    assert any("best of 2 draws of 40 candidate poses" in n for n in r.json()["notes"]), r.json()["notes"]


async def test_api_tradeoff_designs_each_count_and_recommends_one(service):
    c = service.client
    body = {"counts": [12, 4], "with_line": False, "candidates": 60, "lock_frames": 2}
    r = await c.post(f"{API}/plans/tradeoff", json=body)
    assert r.status_code == 401
    r = await c.post(f"{API}/plans/tradeoff", json=body, headers=AUTH)
    assert r.status_code == 200, r.text
    d = r.json()
    assert [row["n_fit"] for row in d["rows"]] == [4, 12] and d["recommended_n_fit"] is None
    few, many = (max(row["predicted_std_m"]["combined"].values()) for row in d["rows"])
    assert many < few and d["rows"][0]["motion_s"] < d["rows"][1]["motion_s"]
    r = await c.post(f"{API}/plans/tradeoff", json={**body, "target_std_m": float(np.sqrt(few * many))}, headers=AUTH)
    assert r.status_code == 200, r.text
    d = r.json()
    assert [row["target_met"] for row in d["rows"]] == [False, True] and d["recommended_n_fit"] == 12
    assert d["recommendation"] == "the fewest fit poses that meet the target"
    # past the largest count, the trend through the two counts: the level each combination settles to, and the count
    # it says meets the target (12 does: at most 12)
    trend = d["count_trend"]
    assert trend["n_fit"] == [4, 12] and trend["n_fit_needed"] is not None and trend["n_fit_needed"] <= 12, trend
    assert all(0 <= v <= many for v in trend["floor_std_m"]["combined"].values()), trend
    plan = Plan.from_dict(d["recommended_plan"])
    validate_plan(plan, NOMINAL)
    assert plan.count()["poses"] == 12
    too_many = {"counts": [4, 8, 12], "draws": 3}  # 9 designs, over the service's 8
    for bad in (
        {"counts": []},
        {"counts": [1]},
        {"counts": [101]},
        {"counts": list(range(2, 11))},
        {"n_fit": 4},
        too_many,
    ):
        r = await c.post(f"{API}/plans/tradeoff", json={**body, **bad}, headers=AUTH)
        assert r.status_code == 422, (bad, r.text)
        assert r.json()["detail"][0]["loc"][:2] in (["body", "counts"], ["body", "n_fit"]), r.text


async def test_api_bounds_its_inputs(service):
    c = service.client
    for bad in (
        {"n_fit": 1000},
        {"candidates": 10**6},
        {"draws": 6},
        {"draws": 0},
        {"target_std_m": -1},
        {"methods": ["generic-end-effector"]},
        {"methods": []},
        {"what": 1},
        {"criterion": "target"},
        {"lock_frames": 1},
        {"lock_frames": 51},
    ):
        r = await c.post(f"{API}/plans/design", json=bad, headers=AUTH)
        assert r.status_code == 422, (bad, r.text)


async def test_dashboard_designs_and_starts_a_plan(service):
    """The dashboard's design panel in headless chromium: design, see the predicted std, start the designed plan."""

    pytest.importorskip("playwright.async_api")
    if CHROMIUM is None:
        pytest.skip(NO_CHROMIUM)
    from tests.service.conftest import TOKEN

    async with headless_chromium() as browser:
        page = await browser.new_page(bypass_csp=True)
        errors = page_errors(page)
        await page.goto(service.url + "/dashboard")
        await enter_token(page, TOKEN)
        await page.fill("#design-nfit", "4")
        await page.fill("#design-lock", "3")
        await page.click("#design")
        await page.wait_for_function(
            "document.querySelector('#design-table').textContent.includes('S-(q04-q03)/2')", timeout=120_000
        )
        table = await page.text_content("#design-table")
        summary = await page.text_content("#design-summary")
        assert "4 fit poses" in summary and "motion" in summary and "lock-1 3" in summary, summary
        assert table.count("\u00b1") == 0 and len(await page.query_selector_all("#design-table tr")) >= 4
        # under the legs method, the sources of its error: the lock phases' shading among them
        assert "of which lock phases: shading (systematic)" in table, table
        assert len(await page.query_selector_all("#design-table tr.part")) >= 4
        assert "designed for combined" in summary and "legs" not in summary, summary
        # designed for the legs method too: the request says so, the summary too
        await page.check("#design-legs")
        await page.click("#design")
        await page.wait_for_function(
            "document.querySelector('#design-summary').textContent.includes('designed for combined and legs')",
            timeout=120_000,
        )
        # the design's notes under its summary: here what a design for the legs method leans on
        notes = await page.text_content("#design-notes")
        assert "designed for the legs method: the poses are those its predicted std is smallest for" in notes, notes
        await page.uncheck("#design-legs")
        await page.click("#design-start")
        await page.wait_for_function(
            "document.querySelector('#message').textContent.includes('started designed run')", timeout=30_000
        )
        run_id = (await service.client.get(f"{API}/runs", headers=AUTH)).json()[0]["id"]
        assert (await page.text_content("#message")).endswith(f"started designed run {run_id[:8]}")
        r = await service.client.get(f"{API}/runs/{run_id}", headers=AUTH)
        assert r.status_code == 200 and r.json()["plan"] == "designed"
        # accuracy against bench time: a row per count, the more poses the smaller the combined std; a target
        # between them recommends the larger, and "use" puts its count in the form
        await page.fill("#tradeoff-counts", "4, 10")
        await page.click("#tradeoff")
        await page.wait_for_function(
            "document.querySelectorAll('#tradeoff-table .use-count').length === 2", timeout=120_000
        )
        rows = await page.eval_on_selector_all(
            "#tradeoff-table tr", "(trs) => trs.slice(1).map((tr) => [...tr.cells].map((c) => c.textContent))"
        )
        assert [row[0] for row in rows] == ["4", "10"], rows
        worst = [max(float(v) for v in row[2:6]) for row in rows]
        assert worst[1] < worst[0], rows
        await page.fill("#design-target", f"{(worst[0] * worst[1]) ** 0.5:.4f}")
        await page.click("#tradeoff")
        await page.wait_for_function(
            "document.querySelector('#tradeoff-table').textContent.includes('(recommended)')", timeout=120_000
        )
        summary = await page.text_content("#tradeoff-summary")
        assert "recommended: 10 fit poses (the fewest fit poses that meet the target)" in summary, summary
        # and past the largest count, where more poses level off (the trend through 4 and 10)
        assert "with more fit poses (trend from 4 to 10): combined levels off near L " in summary, summary
        assert len(await page.query_selector_all("#tradeoff-table tr.recommended")) == 1
        await page.click("#tradeoff-table tr.recommended .use-count")
        assert await page.input_value("#design-nfit") == "10"
        assert not errors, errors


def test_bench_design_compares_plans_of_equal_fit_counts():
    """`i4cal bench design`'s plans: the paper's and a designed one per count, same fit-pose count, no guided line,
    each with its prediction and motion time; a designed plan is not slower to run than the paper's."""
    from i4cal.benchmarks.design import _plans
    from i4cal.cli import main as i4cal_main

    plans = _plans([8], seed=0, speed=0.05, accel=0.5, candidates=200)
    assert set(plans) == {"paper-8", "designed-8"}
    assert plans["designed-8"]["candidates"]["drawn"] == 200 and plans["paper-8"]["candidates"] is None
    assert set(_plans([8], seed=0, speed=0.05, accel=0.5, only=["paper-8"])) == {"paper-8"}
    for p in plans.values():
        assert p["counts"]["poses"] == 8 and "line" not in p["counts"]
        assert set(p["predicted_std_m"]) == {"combined", "end-effector", "legs"}
        assert set(p["predicted_images_std_m"]) == {"combined", "end-effector", "legs"}
    assert plans["designed-8"]["motion_s"] <= plans["paper-8"]["motion_s"] * 1.05
    assert i4cal_main(["bench", "design", "--trials", "0"]) == 2
    # --lock-frames: every plan's lock phases, the paper's and the designed one's
    three = _plans([8], seed=0, speed=0.05, accel=0.5, candidates=60, lock_frames=3)
    for p in three.values():
        assert [p["counts"][f"lock-{i}"] for i in (1, 2, 3, 4)] == [3, 3, 3, 3], p["counts"]
    assert i4cal_main(["bench", "design", "--trials", "1", "--lock-frames", "1"]) == 2


async def test_an_abandoned_tradeoff_is_killed_with_its_process_and_frees_the_pool():
    """A client that goes away (the request cancelled): its trade-off's child process is killed at once, and the
    pool's place and the one-design lock are free (before, in a thread that could not be stopped, abandoned designs
    piled up on the cores and every later request timed out: found by the API fuzz test)."""
    import asyncio
    import os

    from calib.design import DesignRequest
    from drivers.acquisition.config import load_bench
    from service.jobs import HeavyPool, warm_up

    await asyncio.to_thread(warm_up)
    pool = HeavyPool(nice=10)
    lock = asyncio.Lock()
    req = DesignRequest(n_lock=2, n_validation=0, with_line=False, n_candidates=40)
    cfg = load_bench(BENCH_SIM)

    async def handler():
        async with lock:
            return await pool.run("tradeoff", config=cfg, request=req, counts=[4, 5, 6, 7, 8, 9, 10, 11], camera=None)

    task = asyncio.create_task(handler())
    for _ in range(500):
        if pool.running and pool.running[0].process.pid is not None:
            break
        await asyncio.sleep(0.02)
    pid = pool.running[0].process.pid
    os.kill(pid, 0)  # the child computes
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert not lock.locked() and pool.pending == 0 and pool.running == []
    for _ in range(100):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        await asyncio.sleep(0.05)
    else:
        raise AssertionError(f"the abandoned trade-off's process {pid} still runs")


async def test_api_says_how_the_predicted_std_falls_past_the_count_search(service):
    """A target the count search's most poses miss: the response carries the trend of the predicted std over the
    count (``count_trend``: the counts it was fitted at, the level each combination stays above, the count it needs),
    as the plan file does, and the note says it."""
    body = {"with_line": False, "candidates": 60, "lock_frames": 2, "target_std_m": 1e-5}
    r = await service.client.post(f"{API}/plans/design", json=body, headers=AUTH)
    assert r.status_code == 200, r.text
    d = r.json()
    trend = d["count_trend"]
    assert d["target_met"] is False and trend == d["plan"]["design"]["count_trend"], d
    assert len(trend["n_fit"]) == 2 and trend["n_fit"][0] < trend["n_fit"][1], trend
    floor = trend["floor_std_m"]["combined"]
    assert set(floor) == {"L", "H-D", "S-q02/2", "S-(q04-q03)/2"} and all(v >= 0 for v in floor.values()), floor
    assert trend["n_fit_needed"] is None or trend["n_fit_needed"] > d["n_fit"], trend
    assert any("by the trend of the predicted std from" in n for n in d["notes"]), d["notes"]
