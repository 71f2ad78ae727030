"""The accuracy / bench-time trade-off (calib.design.tradeoff): one design per fit-pose count, each the design that
``design_plan`` gives for that count, the target's ratio and the recommended count consistent with the predictions."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from calib.design import (
    DesignRequest,
    Scene,
    design_plan,
    design_tradeoff,
    parse_counts,
    recommendation_reason,
    recommended_count,
)
from calib.errors import InputError
from calib.formats.plan import validate_plan
from calib.model.parameters import COMBINATION_NAMES, NOMINAL
from tests.calib.test_design import twin_scene

SMALL = {"n_lock": 2, "n_validation": 0, "with_line": False, "n_candidates": 100}


@pytest.fixture(scope="module")
def scene() -> Scene:
    return twin_scene()


def _combined(row) -> np.ndarray:
    return np.array([row.std_m["combined"][c] for c in COMBINATION_NAMES])


def test_each_count_is_the_design_of_that_count(scene):
    """Rows in increasing count, each the plan and prediction ``design_plan`` gives for that count; more poses
    predict a smaller combined std on every combination, and take longer."""
    req = DesignRequest(**SMALL)
    done = []
    rows, results = design_tradeoff(NOMINAL, scene, req, "24,6,12", progress=lambda d, t: done.append((d, t)))
    assert [r.n_fit for r in rows] == [6, 12, 24]
    assert done == [(1, 3), (2, 3), (3, 3)]
    for row, res in zip(rows, results, strict=True):
        alone = design_plan(NOMINAL, scene, replace(req, n_fit=row.n_fit))
        assert res.plan.count()["poses"] == row.n_fit
        np.testing.assert_allclose(_combined(row), [alone.prediction.std["combined"][c] for c in COMBINATION_NAMES])
        assert row.motion_s == pytest.approx(alone.motion["total_s"])
        assert set(row.std_m) == {"combined", "end-effector", "legs"}
        validate_plan(res.plan, NOMINAL)
        # no target and no time limit were asked
        assert row.worst_ratio is None and row.target_met is None and row.time_met is None
    assert np.all(_combined(rows[-1]) < _combined(rows[0])), (_combined(rows[0]), _combined(rows[-1]))
    assert rows[0].motion_s < rows[-1].motion_s
    assert recommended_count(rows) is None


def test_target_and_time_pick_the_fewest_poses_that_meet_both(scene):
    """With a target the rows carry the worst predicted std over it (optimised methods) and whether it is met; with a
    time limit too, the recommended count is the fewest that meets both."""
    # a target between what 6 and 20 poses are predicted to give
    probe, _ = design_tradeoff(NOMINAL, scene, DesignRequest(**SMALL), [6, 20])
    target = float(np.sqrt(np.max(_combined(probe[0])) * np.max(_combined(probe[1]))))
    req = DesignRequest(**SMALL, target_std_m=target, criterion="target")
    rows, _ = design_tradeoff(NOMINAL, scene, req, [6, 10, 14, 20])
    for r in rows:
        assert r.worst_ratio == pytest.approx(np.max(_combined(r)) / target)
        assert r.target_met == (r.worst_ratio <= 1.0 + 1e-9)
    assert rows[0].target_met is False and rows[-1].target_met is True
    first = min(r.n_fit for r in rows if r.target_met)
    assert recommended_count(rows) == first
    # a time limit: the same designs (the count is given), each within it or not; the fewest poses meeting both
    assert all(a.motion_s < b.motion_s for a, b in itertools.pairwise(rows))
    t_first = next(r.motion_s for r in rows if r.n_fit == first)
    for limit, want in ((t_first * (1 + 1e-6), first), (t_first * (1 - 1e-6), None)):
        timed, _ = design_tradeoff(NOMINAL, scene, replace(req, max_time_s=limit), [r.n_fit for r in rows])
        np.testing.assert_allclose([r.motion_s for r in timed], [r.motion_s for r in rows])
        assert [r.time_met for r in timed] == [r.motion_s <= limit for r in rows]
        assert recommended_count(timed) == want, (limit, want)
        assert recommendation_reason(timed) == "the fewest fit poses that meet the target within the time"


def test_a_time_limit_alone_recommends_the_most_poses_that_fit(scene):
    """Without a target the most accurate plan the time allows: the largest count whose plan fits in the time."""
    rows, _ = design_tradeoff(NOMINAL, scene, DesignRequest(**SMALL), [6, 12, 24])
    assert all(a.motion_s < b.motion_s for a, b in itertools.pairwise(rows))
    limit = 0.5 * (rows[1].motion_s + rows[2].motion_s)  # 6 and 12 poses fit, 24 do not
    timed, _ = design_tradeoff(NOMINAL, scene, DesignRequest(**SMALL, max_time_s=limit), [6, 12, 24])
    assert [r.time_met for r in timed] == [True, True, False] and all(r.target_met is None for r in timed)
    assert recommended_count(timed) == 12
    assert recommendation_reason(timed) == "the most fit poses that fit in the time"
    short, _ = design_tradeoff(NOMINAL, scene, DesignRequest(**SMALL, max_time_s=0.5 * rows[0].motion_s), [6, 12])
    assert recommended_count(short) is None


@pytest.mark.parametrize(
    ("counts", "says"),
    [
        ("8,x", "comma-separated"),
        ("", "at least one"),
        ([1, 8], "2..200"),
        (list(range(2, 12)), "at most 8"),
    ],
)
def test_bad_counts_are_refused_naming_the_field(counts, says):
    with pytest.raises(InputError, match=says) as exc:
        parse_counts(counts, field="--tradeoff")
    assert exc.value.field == "--tradeoff"


def test_counts_are_sorted_and_unique():
    assert parse_counts("30, 8,12,8") == [8, 12, 30]


def test_designs_of_one_candidate_draw_share_the_sweeps_and_candidates(scene):
    """``cache``: designs that differ in their count compute the sweeps and the candidates' information once per
    candidate draw, and are the designs computed without it."""
    cache: dict = {}
    req = DesignRequest(**SMALL, draws=2)
    shared = [design_plan(NOMINAL, scene, replace(req, n_fit=n), cache=cache) for n in (6, 10)]
    assert len(cache) == 2  # one pool per candidate draw
    for res, n in zip(shared, (6, 10), strict=True):
        alone = design_plan(NOMINAL, scene, replace(req, n_fit=n))
        assert res.plan.steps == alone.plan.steps
        assert res.prediction.std == alone.prediction.std


def test_an_absurdly_small_target_gives_an_infinite_ratio_without_warnings(scene):
    """A target of 5e-324 m (the API accepts any positive one): every count misses it, no overflow warning (the API
    fuzz found one)."""
    import warnings

    req = DesignRequest(**SMALL, target_std_m=5e-324, criterion="target")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        rows, _ = design_tradeoff(NOMINAL, scene, req, [4, 6])
    assert all(r.target_met is False and r.worst_ratio == np.inf for r in rows)
    assert recommended_count(rows) is None


def test_each_optimised_method_is_judged_on_its_own_target(scene):
    """Designed for the combined and legs methods with a target of their own each (``method_targets_m``, what
    ``--better-than`` gives): a row's worst ratio is the larger of the two methods' own, and the printed line names
    both targets."""
    from service.design import tradeoff_lines, twin_image_noise

    noise = twin_image_noise()
    tc, tl = (0.08e-3,) * 4, (0.6e-3, 0.3e-3, 0.7e-3, 0.6e-3)
    req = DesignRequest(
        **{**SMALL, "n_lock": 3},
        methods=("combined", "legs"),
        target_std_m=tc,
        method_targets_m=(("legs", tl),),
        criterion="target",
    )
    rows, _ = design_tradeoff(NOMINAL, scene, req, [6, 12], noise=noise)
    for r in rows:
        legs = np.array([r.std_m["legs"][c] for c in COMBINATION_NAMES])
        want = max(np.max(_combined(r) / np.asarray(tc)), np.max(legs / np.asarray(tl)))
        assert r.worst_ratio == pytest.approx(want)
    text = "\n".join(tradeoff_lines(rows, req))
    assert "target combined L 0.080" in text and "target legs L 0.600" in text, text
