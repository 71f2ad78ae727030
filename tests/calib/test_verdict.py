"""The verdict rule (calib.identify.verdict): which method's result to load, why, and the next command."""

from __future__ import annotations

import pytest

from calib.identify.verdict import COMBINATIONS, UNCERTAINTY, verdict

ORDER = ("combined", "legs", "end-effector")


def _method(std_mm: float, converged: bool = True, error: str | None = None) -> dict:
    if not converged:
        return {"converged": False, "error": error, "parameters": None, "std": None}
    std = {k: std_mm * 1e-3 for k in COMBINATIONS}
    return {"converged": True, "parameters": {k: 1.0 for k in COMBINATIONS}, "std": std, "combinations_std": std}


def _gaps(rms: float, n: int = 9) -> dict:
    return {"gaps_validation": {"rms_mm": rms, "n_pairs": n}, "gaps_poses": {"rms_mm": rms * 1.2, "n_pairs": 19}}


def test_the_smallest_gap_wins_and_the_next_command_names_the_result():
    doc = {
        "methods": {"combined": _method(0.4), "end-effector": _method(3.0), "legs": _method(1.5)},
        "validation": {"a priori": _gaps(1.4), "combined": _gaps(0.6), "end-effector": _gaps(0.25), "legs": _gaps(0.9)},
    }
    v = verdict(doc, "result.json", ORDER)
    assert v.method == "end-effector"
    assert v.gap_mm == 0.25 and v.a_priori_gap_mm == 1.4
    assert v.next_command == "i4cal export result.json -o calibration.json --method end-effector"
    assert UNCERTAINTY in v.reason and "0.250 mm" in v.reason and "1.400 mm" in v.reason
    # no truth: the floor is the best fit-pose gap, and says so
    assert v.floor_mm == pytest.approx(0.25 * 1.2) and v.floor_source == "best fit-pose gap"
    assert len(v.lines()) == 2


def test_gaps_within_their_sampling_spread_are_a_tie_broken_by_the_std():
    # 9 gaps: an RMS is known to about 1/sqrt(18) = 24% of itself; 0.26 vs 0.25 is a tie, the smaller std wins
    doc = {
        "methods": {"combined": _method(0.4), "end-effector": _method(3.0)},
        "validation": {"a priori": _gaps(1.4), "combined": _gaps(0.26), "end-effector": _gaps(0.25)},
    }
    v = verdict(doc, order=ORDER)
    assert v.method == "combined" and "smallest std" in v.reason


def test_a_failed_fit_is_never_chosen_and_its_reason_is_kept_once():
    doc = {
        "methods": {"legs": _method(0, converged=False, error="the legs method needs the lock-1 phase")},
        "validation": {"a priori": _gaps(1.4)},
    }
    v = verdict(doc, order=ORDER)
    assert v.method is None and v.next_command is None
    assert v.failed == {"legs": "the legs method needs the lock-1 phase"}
    # the reason is said once, under the table, not again in the verdict
    assert "lock-1" not in v.reason and "legs" in v.reason and v.lines()[0].startswith("verdict: nothing to load")


def test_no_method_better_than_the_a_priori_loads_nothing():
    doc = {"methods": {"combined": _method(0.4)}, "validation": {"a priori": _gaps(0.3), "combined": _gaps(0.5)}}
    v = verdict(doc, order=ORDER)
    assert v.method is None and "a priori" in v.reason


def test_on_a_real_twin_calibration_the_floor_is_the_true_geometry():
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate, to_jsonable
    from drivers.sim.twin import GeometricTwin

    doc = to_jsonable(calibrate(Observations.from_dict(GeometricTwin().observations(seed=0))))
    v = verdict(doc, "r.json")
    assert v.method in doc["methods"] and doc["methods"][v.method]["converged"]
    assert v.floor_source == "true geometry"
    assert v.floor_mm == pytest.approx(doc["validation"]["truth"]["gaps_validation"]["rms_mm"])
    assert v.gap_mm < v.a_priori_gap_mm
