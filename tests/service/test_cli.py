"""The command line: contracts (--json keys), clear one-line errors, the demo."""

import json
import os
import subprocess
import sys

import pytest

from calib.model.parameters import COMBINATION_NAMES
from service.cli import main
from tests.conftest import NUMERICS_THREAD_VARS


def run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, timeout=300, env=env
    )


@pytest.fixture(scope="module")
def obs_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("cli") / "obs.json"
    assert main(["simulate", "--out", str(p), "--seed", "3"]) == 0
    return p


def test_calibrate_json_contract(obs_file, capsys):
    assert main(["calibrate", str(obs_file), "--method", "all", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["methods"]) == {"combined", "end-effector", "legs"}
    for e in doc["methods"].values():
        assert e["converged"] is True
        assert set(e["parameters"]) == set(COMBINATION_NAMES)
        assert set(e["std"]) == set(COMBINATION_NAMES)
        assert all(v > 0 for v in e["std"].values())
    assert set(doc["methods"]["legs"]["seven"]) == {"H", "q02", "q03", "q04", "S", "D", "L"}
    assert {"a priori", "combined", "end-effector", "legs"} <= set(doc["validation"])
    assert doc["methods"]["combined"]["identifiability"]["finds_paper_four"]
    bound = doc["methods"]["combined"]["bound"]["std"]
    for k in COMBINATION_NAMES:  # the reported std cannot beat the Cramer-Rao bound by much
        assert 0 < bound[k] < 1.2 * doc["methods"]["combined"]["std"][k]
    # every method beats the a priori geometry on the validation poses
    ap = doc["validation"]["a priori"]["gaps_validation"]["rms_mm"]
    for m in ("combined", "end-effector", "legs"):
        assert doc["validation"][m]["gaps_validation"]["rms_mm"] < ap


def test_calibrate_single_method_table(obs_file, capsys):
    assert main(["calibrate", str(obs_file), "--method", "combined"]) == 0
    out = capsys.readouterr().out
    assert "Table I" in out and "Table II" in out and "combined" in out


def test_noise_options(tmp_path):
    p = tmp_path / "o.json"
    assert main(["simulate", "--out", str(p), "--noise", "0"]) == 0
    doc = json.loads(p.read_text())
    assert doc["noise"]["rod_direction_rad"] == 0
    args = ["simulate", "--out", str(p), "--rod-direction-mrad", "2", "--board-translation-mm", "1", "1", "2"]
    assert main(args) == 0
    doc = json.loads(p.read_text())
    assert doc["noise"]["rod_direction_rad"] == pytest.approx(2e-3)
    assert doc["noise"]["board_translation_m"] == pytest.approx([1e-3, 1e-3, 2e-3])


def test_malformed_file_one_line_error(tmp_path, obs_file):
    doc = json.loads(obs_file.read_text())
    doc["frames"][12]["q"] = [0.1, "oops", 0.2, 0.3]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    res = run("calibrate", str(bad))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "bad.json" in lines[0] and "frame 12" in lines[0] and "q.1" in lines[0]
    assert "Traceback" not in res.stderr


def test_missing_file_and_missing_phase_errors(tmp_path, obs_file):
    res = run("calibrate", str(tmp_path / "nope.json"))
    assert res.returncode == 2 and "file not found" in res.stderr and "Traceback" not in res.stderr
    doc = json.loads(obs_file.read_text())
    doc["frames"] = [f for f in doc["frames"] if f["phase"] != "rotation"]
    p = tmp_path / "norot.json"
    p.write_text(json.dumps(doc))
    res = run("calibrate", str(p), "--method", "combined")
    assert res.returncode == 2 and "rotation phase" in res.stderr and "Traceback" not in res.stderr


def test_quick_demo_prints_the_comparison():
    res = run("demo", "--quick")
    assert res.returncode == 0, res.stderr
    for word in ("Table I", "Table II", "combined", "end-effector", "legs", "a priori"):
        assert word in res.stdout


@pytest.mark.slow
def test_full_demo_runs_the_bench_over_modbus_and_extracts_images(tmp_path):
    # as a user runs it: the numerics libraries with their own thread counts, not the suite's one thread (a forked
    # extraction worker that reconfigured OpenCV's threads hung here, and only here)
    env = {k: v for k, v in os.environ.items() if k not in NUMERICS_THREAD_VARS}
    res = run("demo", "--out", str(tmp_path), env=env)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "modbus+tcp://127.0.0.1:" in res.stdout
    assert (tmp_path / "dataset" / "dataset.json").exists()
    doc = json.loads((tmp_path / "observations.json").read_text())
    assert sum(f.get("board") is not None for f in doc["frames"]) > 100
    for word in ("Table I", "Table II", "combined", "end-effector", "legs"):
        assert word in res.stdout
