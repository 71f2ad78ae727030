"""Simulated drift: ``SimBench(drift_m=...)`` and ``i4cal sim-bench --drift`` move the simulated robot's true
geometry by the given lengths (the frames show the moved robot; ``--truth-out`` writes the moved truth), and a
malformed ``--drift`` is a usage error naming the option."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import numpy as np
import pytest

from calib.model.kinematics import dkm
from drivers.sim.bench import SimBench, drifted
from drivers.sim.twin import BenchGeometry
from tests.drivers.test_processes import _free_base

I4CAL = [sys.executable, "-m", "i4cal"]


def test_drift_moves_the_true_geometry_and_what_the_robot_does():
    base = BenchGeometry()
    bench = SimBench(port=0, drift_m={"L": 3e-4, "q03": -5e-4}, renderer=object())
    truth = bench.geometry.truth
    assert pytest.approx(base.truth.L + 3e-4, abs=1e-15) == truth.L
    assert truth.q03 == pytest.approx(base.truth.q03 - 5e-4, abs=1e-15)
    assert (truth.H, truth.q02, truth.q04, truth.S, truth.D) == (
        base.truth.H,
        base.truth.q02,
        base.truth.q04,
        base.truth.S,
        base.truth.D,
    )
    # the mechanism's true pose at a joint vector is the drifted robot's, not the nominal one
    q = bench.mechanism.q_true()
    assert np.allclose(bench.mechanism.pose_true(q), dkm(truth, q), atol=1e-12)
    assert not np.allclose(bench.mechanism.pose_true(q), dkm(base.truth, q), atol=1e-6)


def test_drift_of_an_unknown_parameter_is_refused():
    with pytest.raises(ValueError, match="T_per_rad"):
        drifted(BenchGeometry(), {"T_per_rad": 1e-3})


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("L=0.3", "give a unit"),
        ("X=0.3mm", "'X' is not a parameter"),
        ("L=0.3mm,L=1mm", "L is given twice"),
        ("L=0.3in", "unknown unit 'in'"),
        ("L=+0.3mm,", "is not NAME=CHANGE"),
    ],
)
def test_a_malformed_drift_is_a_usage_error_naming_the_option(text, says, capsys):
    from service.cli import build_parser

    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["sim-bench", "--drift", text])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--drift" in err and says in err, err


def test_sim_bench_drift_writes_the_moved_truth(tmp_path):
    port = _free_base()
    truth_file = tmp_path / "truth.json"
    proc = subprocess.Popen(
        [*I4CAL, "sim-bench", "--port", str(port), "--drift", "L=+0.3mm,q03=-500um", "--truth-out", str(truth_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        seen = [proc.stdout.readline() for _ in range(3)]
        assert any(line.startswith("actuators = ") for line in seen), seen
        truth = json.loads(truth_file.read_text())
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
    base = BenchGeometry().truth
    assert truth["L"] == pytest.approx(base.L + 3e-4, abs=1e-12)
    assert truth["q03"] == pytest.approx(base.q03 - 5e-4, abs=1e-12)
    assert truth["H"] == base.H
