"""On ``i4cal demo``'s own dataset (the paper's full plan with its line and lock phases, the simulated bench of
``deploy/bench-sim.toml``), what every method reports agrees with what ``i4cal plan predict`` predicts for that plan
and bench, and covers its errors against the simulator's truth.

The demo runs as a user runs it (the simulated bench over Modbus on loopback, its camera phase, the extraction, the
three methods) once for the module: about 30 s on an idle machine (2 cores). Before the demo calibrated its camera
from board views, it handed the extraction the renderer's true intrinsics: no covariance, and the board's nominal
corners, which the simulated board misses by 0.2 mm RMS; the end-effector method then reported 5.6-6.1x the
predicted std on this plan.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calib.formats.observations import Observations
from calib.formats.plan import Plan
from calib.identify.pipeline import calibrate, to_jsonable
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, SEVEN_TO_FOUR

ROOT = Path(__file__).resolve().parents[2]
METHODS = ("combined", "end-effector", "legs")


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> dict:
    """The demo's dataset, observations, calibration (JSON document) and ``plan predict``'s prediction for its plan."""
    import argparse

    from drivers.acquisition.config import load_bench
    from service.cli._output import make_console
    from service.cli.demo import _full
    from service.design import check_for_bench

    out = tmp_path_factory.mktemp("demo")
    _full(argparse.Namespace(out=str(out), seed=1, small=False), make_console(), out)
    obs_doc = json.loads((out / "observations.json").read_text())
    plan = Plan.model_validate(json.loads((out / "dataset" / "dataset.json").read_text())["plan"])
    check = check_for_bench(load_bench(ROOT / "deploy" / "bench-sim.toml"), plan, methods=METHODS)
    return {
        "dir": out,
        "obs": obs_doc,
        "result": to_jsonable(calibrate(Observations.from_dict(obs_doc))),
        "predicted": check.prediction.std,
    }


@pytest.mark.parametrize("method", METHODS)
def test_reported_std_is_within_30_percent_of_plan_predict(demo, method):
    # on this dataset: combined 0.86-1.26, end-effector 0.71-0.74 (the prediction at the demo's true geometry is
    # 0.93x the nominal's; the method measured its corners at 0.82x the prediction's noise), legs 0.97-1.26
    reported = demo["result"]["methods"][method]["combinations_std"]
    predicted = demo["predicted"][method]
    ratio = np.array([reported[k] / predicted[k] for k in COMBINATION_NAMES])
    assert np.all(np.abs(ratio - 1.0) <= 0.3), f"{method}: reported / predicted std = {np.round(ratio, 2)}"


@pytest.mark.parametrize("method", METHODS)
def test_errors_lie_within_three_reported_std(demo, method):
    res = demo["result"]
    std = res["methods"][method]["combinations_std"]
    z = np.array([res["truth_errors"][method][k] / std[k] for k in COMBINATION_NAMES])
    assert np.all(np.abs(z) < 3.0), f"{method}: error / std = {np.round(z, 2)}"


def test_demo_camera_is_calibrated_from_board_views(demo):
    """The camera the demo's extraction used: calibrated (its covariance, the board's corners refined), written
    beside the observations for ``i4cal extract --camera``; the methods carry its uncertainty."""
    calib = json.loads((demo["dir"] / "camera.json").read_text())["calibration"]
    assert len(calib["board_points"]["ids"]) == 15 and np.asarray(calib["covariance"]).shape[0] >= 8
    # the extraction's camera is that calibration (refined by the rods, as ``i4cal extract`` does)
    used = demo["obs"]["extraction"]["camera"]["calibration"]
    assert used["board_points"]["ids"] == calib["board_points"]["ids"] and used["covariance"] == calib["covariance"]
    assert "intrinsics" in demo["result"]["methods"]["end-effector"]["std_breakdown"]


def test_legs_seven_cover_their_errors_or_are_reported_not_identified(demo):
    """Along the three directions the four combinations do not see, the legs' image data were 9-11 std off here:
    those directions are reported as not identified and the result there is the a priori geometry with its
    tolerance; every one of the seven then lies within 3 reported std of the truth."""
    legs = demo["result"]["methods"]["legs"]
    truth = demo["obs"]["truth"]["parameters"]
    z = np.array([(legs["seven"][k] - truth[k]) / legs["seven_std"][k] for k in PARAMETER_NAMES])
    assert np.all(np.abs(z) < 3.0), dict(zip(PARAMETER_NAMES, np.round(z, 1), strict=True))
    dirs = legs["diagnostics"]["identifiability"]["not_identified"]
    N = np.array([[d["direction"][k] for k in PARAMETER_NAMES] for d in dirs]).T
    assert N.shape == (7, 3) and np.allclose(SEVEN_TO_FOUR @ N, 0.0, atol=1e-12)
    assert any("do not identify the seven" in w for w in legs["warnings"])
