"""The trend of a plan's predicted std over its fit-pose count (:mod:`calib.design.count_trend`) and what the design
does with it past the count search's ``n_max``: takes the count the trend says meets the target, or says where more
poses level off."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.design import DesignRequest, TradeoffRow, design_plan, predict_plan, tradeoff_trend
from calib.design.count_trend import fit_count_trend
from calib.design.optimize import N_FIT_MOST
from calib.model.parameters import COMBINATION_NAMES, NOMINAL

#: a design small enough for a test: no validation poses, no guided line, two frames per lock phase, 80 candidate
#: poses (so that the most fit poses allowed are the visible ones, fewer than 200)
BASE = DesignRequest(n_lock=2, n_validation=0, with_line=False, n_candidates=80, n_max=16)


def test_trend_recovers_floor_and_slope_of_a_one_over_n_law():
    floor = np.array([4e-5, 1e-5, 2e-5, 0.0]) ** 2
    slope = np.array([3e-7, 2e-8, 1e-7, 5e-8])
    std = {n: {"combined": np.sqrt(floor + slope / n)} for n in (10, 40, 1000)}
    trend = fit_count_trend(10, std[10], 40, std[40])
    np.testing.assert_allclose(trend.floor_var["combined"], floor, atol=1e-20)
    np.testing.assert_allclose(trend.slope["combined"], slope, rtol=1e-9)
    np.testing.assert_allclose(trend.std_at(1000)["combined"], std[1000]["combined"], rtol=1e-9)
    np.testing.assert_allclose(trend.floor_std()["combined"], np.sqrt(floor), atol=1e-15)
    # the fewest poses that put every combination at or under its target: L's 5e-5 needs 3e-7 / (25e-10 - 16e-10)
    assert trend.needed({"combined": np.full(4, 5e-5)}) == 334
    assert trend.needed({"combined": np.full(4, 1.0)}) == 1
    assert trend.needed({"combined": np.array([3.9e-5, 1.0, 1.0, 1.0])}) is None  # under L's floor


def test_trend_of_a_std_that_does_not_fall_or_falls_faster_than_one_over_n():
    trend = fit_count_trend(10, {"legs": np.array([2.0, 1.0])}, 20, {"legs": np.array([2.0, 0.1])})
    # L does not fall: its level is the floor; the second falls 100-fold in variance for 2x the poses: no floor
    np.testing.assert_allclose(trend.floor_var["legs"], [4.0, 0.0])
    np.testing.assert_allclose(trend.slope["legs"], [0.0, 0.01 * 20])
    assert trend.needed({"legs": np.array([2.5, 0.05])}) == 80


def test_tradeoff_trend_through_its_two_largest_counts():
    """A trade-off's rows (any order) give the trend past its largest count through its two largest counts, for the
    optimised methods; the count it says meets the target when one was asked."""
    floor, slope = np.array([4e-5, 1e-5, 2e-5, 2e-5]) ** 2, np.array([3e-7, 2e-8, 1e-7, 1e-7])

    def row(n: int) -> TradeoffRow:
        std = dict(zip(COMBINATION_NAMES, np.sqrt(floor + slope / n).tolist(), strict=True))
        return TradeoffRow(n, 60.0 + n, {"combined": std, "legs": std}, None, None, None)

    rows = [row(30), row(8), row(12)]
    trend = tradeoff_trend(rows, DesignRequest())
    assert trend is not None and trend["n_fit"] == [12, 30] and trend["n_fit_needed"] is None
    assert set(trend["floor_std_m"]) == {"combined"}  # the optimised methods
    np.testing.assert_allclose(list(trend["floor_std_m"]["combined"].values()), np.sqrt(floor), rtol=1e-6)
    asked = tradeoff_trend(rows, DesignRequest(target_std_m=5e-5))
    assert asked is not None and asked["n_fit_needed"] == 334
    assert tradeoff_trend(rows[:1], DesignRequest()) is None
    assert tradeoff_trend(rows, DesignRequest(methods=("end-effector",))) is None  # no prediction of it in the rows


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((20, {"combined": [1.0]}, 10, {"combined": [1.0]}), "n_lo < n_hi"),
        ((10, {"combined": [1.0]}, 20, {"legs": [1.0]}), "different methods"),
        ((10, {"combined": [1.0, 2.0]}, 20, {"combined": [1.0]}), r"combined: std shapes differ, \(2,\) and \(1,\)"),
        ((10, {"combined": [[1.0]]}, 20, {"combined": [[1.0]]}), r"shape \(k,\), got \(1, 1\)"),
    ],
)
def test_trend_rejects_bad_input_naming_it(args, match):
    with pytest.raises(ValueError, match=match):
        fit_count_trend(*args)


def test_design_goes_past_the_count_search_when_the_trend_says_more_poses_meet_the_target(scene, noise):
    """The count search stops at ``n_max``, yet a target that 28 designed poses meet is not reported "not met" with
    16: the trend of the prediction (at 8 and 16 poses, refitted at the counts it gives) picks a larger count, and
    the plan's own prediction meets the target there."""
    target = predict_plan(
        design_plan(NOMINAL, scene, replace(BASE, n_fit=28), noise=noise).plan, NOMINAL, scene, noise, ("combined",)
    ).std["combined"]
    goal = tuple(1.02 * target[c] for c in COMBINATION_NAMES)
    said: list[str] = []
    res = design_plan(NOMINAL, scene, replace(BASE, target_std_m=goal), noise=noise, status=said.append)
    got = res.prediction.std["combined"]
    print(res.n_fit, {c: round(got[c] / goal[i], 3) for i, c in enumerate(COMBINATION_NAMES)}, res.notes)
    assert res.n_fit > BASE.n_max and res.target_met, (res.n_fit, res.notes)
    assert all(got[c] <= goal[i] for i, c in enumerate(COMBINATION_NAMES)), got
    assert any("beyond the 16 the count search tries" in n for n in res.notes), res.notes
    trend = res.count_trend
    assert trend is not None and trend["n_fit_needed"] is not None and trend["n_fit_needed"] <= res.n_fit
    assert res.plan.design is not None and res.plan.design["count_trend"] == trend  # in the plan file too
    # a long design says what it is doing: the candidates, each choice of the count, each count past the search
    assert said[0] == "80 candidate poses: sweeps, visibility, information", said
    assert "choosing the fit poses and their count (choice 1)" in said, said
    assert f"past the count search: {res.n_fit} fit poses" in said, said


def test_design_of_several_draws_says_which_draw_it_is_on(scene):
    said: list[str] = []
    req = DesignRequest(n_fit=4, n_lock=2, n_validation=0, with_line=False, n_candidates=40, draws=2)
    design_plan(NOMINAL, scene, req, status=said.append)
    assert said[0] == "draw 1/2: 40 candidate poses: sweeps, visibility, information", said
    assert "draw 2/2: predicting 4 fit poses" in said, said


def test_design_says_where_more_poses_level_off(scene, noise):
    """A target no count of these poses reaches: the design takes the most fit poses allowed (200 or every visible
    candidate, or what fits in the time allowed), whose prediction still misses it, and says so with the level the
    trend puts the worst combination at."""
    res = design_plan(NOMINAL, scene, replace(BASE, target_std_m=2.5e-5), noise=noise)
    got = res.prediction.std["combined"]
    most = min(N_FIT_MOST, res.candidates["visible"] + res.candidates["reference_visible"])
    assert res.target_met is False and res.n_fit == most and got["L"] > 2.5e-5, (res.n_fit, most, got)
    trend = res.count_trend
    assert trend is not None and trend["n_fit"] == [BASE.n_max, most] and trend["n_fit_needed"] is None
    floor = trend["floor_std_m"]["combined"]
    note = next(n for n in res.notes if "target is not met" in n)
    assert f"{most}, the most the design takes, miss it too" in note, note
    assert f"combined L levels off near {floor['L'] * 1e3:.3f} mm" in note and floor["L"] > 2.5e-5, (note, floor)
    # the note still names the combination furthest over the target, with its predicted std
    worst = max(got, key=lambda k: got[k])
    assert f"worst: combined {worst} {got[worst] * 1e3:.3f} mm predicted for 0.025 mm" in note, note

    # within a time: the most poses that fit in it
    allowed_s = design_plan(NOMINAL, scene, replace(BASE, n_fit=40), noise=noise).motion["total_s"]
    timed = design_plan(NOMINAL, scene, replace(BASE, target_std_m=2.5e-5, max_time_s=allowed_s), noise=noise)
    print(timed.n_fit, timed.motion["total_s"], allowed_s, timed.notes)
    assert BASE.n_max < timed.n_fit < most and timed.motion["total_s"] <= allowed_s and timed.time_met
    assert any(f"the most the design takes within the {allowed_s / 60:.1f} min allowed" in n for n in timed.notes)
