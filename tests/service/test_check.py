"""``i4cal check`` on the simulated bench, with the commands a user types: a bench that did not move holds; a bench
whose legs grew (``sim-bench --drift L=+X``, X six predicted std of the check's change) is found drifted on L with
its change within 3 std of X, the update is written (an i4cal.calibration/1 document) and the next check against it
holds. A check plan without the combined method's phases, or a calibration without covariance, is refused before
any motion.

The calibration in force is the simulator's true geometry with the full plan's predicted combined covariance (what
a full calibration of this bench knows; a full run would cost this test a minute): the check's statistics treat it
as an estimate, which only makes a false alarm rarer. The camera file is the simulated lens (what `i4cal camera
calibrate` measures, docs/camera.md)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from calib.identify.export import COMPLETION_RULES, CalibrationDocument, Completion, load_calibration
from calib.model.parameters import COMBINATION_NAMES
from drivers.acquisition.config import load_bench
from drivers.sim.render import RenderSettings
from drivers.sim.twin import BenchGeometry
from tests.drivers.test_processes import _free_base

I4CAL = [sys.executable, "-m", "i4cal"]
#: the drift injected, in predicted std of the check's change (the check and the calibration in force together)
DRIFT_IN_STD = 6.0


def _bench_file(path: Path, port: int) -> Path:
    path.write_text(
        f"""name = "simulated I4 bench"
[actuators]
uri = "modbus+tcp://127.0.0.1:{port}"
speed_m_s = 10.0
accel_m_s2 = 1000.0
timeout_s = 0.5
poll_s = 0.001
home_timeout_s = 10.0
[actuators.limits]
q_min = [-0.10, -0.10, -0.10, -0.10]
q_max = [0.80, 0.80, 0.80, 0.80]
[camera]
uri = "sim://127.0.0.1:{port + 2}"
timeout_s = 10.0
intrinsics = "camera.json"
[operator]
uri = "sim://127.0.0.1:{port + 2}"
[acquisition]
line_rate_hz = 50.0
""",
        encoding="utf-8",
    )
    return path


def _in_force(cfg) -> CalibrationDocument:
    """The true geometry, with the full plan's predicted combined covariance."""
    from calib.formats.plan import make_plan
    from service.design import check_for_bench

    full = make_plan("full", cfg.nominal_parameters(), seed=0, limits=cfg.calib_limits())
    pred = check_for_bench(cfg, full, None, ("combined",)).prediction
    truth, nominal = BenchGeometry().truth, cfg.nominal_parameters()
    return CalibrationDocument(
        bench="simulated I4 bench",
        method="combined",
        method_choice="the simulator's truth with the full plan's predicted covariance (test)",
        software_version="test",
        seven=truth.seven(),
        seven_std=dict.fromkeys(truth.seven()),
        identified=["q02", "q04", "D", "L"],
        fixed_at_nominal=["H", "S", "q03"],
        completion=Completion(rule="combinations+nominal", text=COMPLETION_RULES["combinations+nominal"]),
        T_per_rad=truth.T_per_rad,
        combinations=truth.combinations(),
        combinations_std=dict(pred.std["combined"]),
        covariance=pred.covariance["combined"],
        nominal=nominal.as_dict(),
        nominal_combinations=nominal.combinations(),
    )


class _SimBench:
    def __init__(self, *extra: str) -> None:
        self.port = _free_base()
        self.proc = subprocess.Popen(
            [*I4CAL, "sim-bench", "--port", str(self.port), *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        seen = [self.proc.stdout.readline() for _ in range(3)]
        assert any(line.startswith("actuators = ") for line in seen), seen

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The camera file, the calibration in force, the designed check plan (cached), and the drift X (m)."""
    from service.checks.plan import check_plan_for_bench
    from service.checks.run import predicted_check_std

    d = tmp_path_factory.mktemp("check")
    RenderSettings().camera().save(d / "camera.json")
    cfg = load_bench(_bench_file(d / "probe.toml", 5020))
    doc = _in_force(cfg)
    (d / "in_force.json").write_text(doc.model_dump_json(indent=1), encoding="utf-8")
    plan, _, _ = check_plan_for_bench(cfg, 60.0, d / "cache")
    pred = predicted_check_std(cfg, plan)
    std_change = math.hypot(pred["L"], doc.combinations_std["L"])
    return d, DRIFT_IN_STD * std_change, std_change


@pytest.fixture(scope="module")
def still_bench(setup):
    b = _SimBench()
    yield _bench_file(setup[0] / "still.toml", b.port)
    b.stop()


@pytest.fixture(scope="module")
def drifted_bench(setup):
    b = _SimBench("--drift", f"L=+{setup[1] * 1e3:.4f}mm")
    yield _bench_file(setup[0] / "drifted.toml", b.port)
    b.stop()


def _check(d: Path, bench: Path, calibration: Path, *extra: str) -> tuple[int, dict]:
    out = subprocess.run(
        [
            *I4CAL,
            "check",
            "--bench",
            str(bench),
            "--calibration",
            str(calibration),
            "--plan-cache",
            str(d / "cache"),
            "--json",
            "--no-progress",
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode in (0, 1, 3), out.stderr[-3000:]
    return out.returncode, json.loads(out.stdout)


def test_a_bench_that_did_not_move_holds(setup, still_bench):
    d = setup[0]
    rc, doc = _check(d, still_bench, d / "in_force.json")
    assert (rc, doc["verdict"], doc["drifted"]) == (0, "holds", {}), doc
    assert doc["plan"]["source"].startswith("cached: ")  # designed once by the fixture, not per check
    assert set(doc["plan"]) >= {"rotation", "translation", "poses"}
    assert set(doc["predicted_std_m"]) == set(COMBINATION_NAMES)
    assert not doc["update"]["accepted"]


def test_a_drift_is_caught_the_update_written_and_the_next_check_holds(setup, drifted_bench):
    d, drift_m, std_change = setup
    rc, doc = _check(d, drifted_bench, d / "in_force.json", "--update-out", str(d / "updated.json"))
    assert (rc, doc["verdict"]) == (1, "drifted"), doc
    assert "L" in doc["drifted"], doc["drifted"]
    got = doc["drifted"]["L"]
    assert got["std_m"] == pytest.approx(std_change, rel=0.5)  # the check's own std near its prediction
    assert abs(got["change_m"] - drift_m) < 3 * got["std_m"], (got, drift_m)
    assert doc["update"]["accepted"], doc["update"]
    updated = load_calibration(json.loads((d / "updated.json").read_text()), "updated.json")
    true_l = BenchGeometry().truth.L + drift_m
    assert abs(updated.combinations["L"] - true_l) < 3 * updated.combinations_std["L"]
    assert updated.completion.rule == "combinations+in-force"
    rc, again = _check(d, drifted_bench, d / "updated.json")
    assert (rc, again["verdict"]) == (0, "holds"), again


def test_a_plan_without_the_fit_phases_or_a_calibration_without_covariance_is_refused(setup):
    d = setup[0]
    bench = _bench_file(d / "nowhere.toml", 9)  # nothing listens: a refusal must come before any connection
    out = subprocess.run(
        [*I4CAL, "check", "--bench", str(bench), "--calibration", str(d / "in_force.json"), "--plan", "pose-set"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and "--plan" in out.stderr and "rotation" in out.stderr, out.stderr
    bare = json.loads((d / "in_force.json").read_text())
    bare["covariance"] = None
    (d / "bare.json").write_text(json.dumps(bare), encoding="utf-8")
    out = subprocess.run(
        [*I4CAL, "check", "--bench", str(bench), "--calibration", str(d / "bare.json")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and "covariance" in out.stderr and "bare.json" in out.stderr, out.stderr
