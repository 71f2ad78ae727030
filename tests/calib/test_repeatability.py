"""Repeatability and the measurement floor (calib.check.repeatability) on seeded synthetic revisits: the floor from the
still pairs, the repeatability from the revisits, the robot's own from their difference, each within its chi-square
bound; a revisit 1 mm off is flagged and no other; a revisit plan visits every fit pose n times from another pose."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.stats import chi2

from calib.check.repeatability import repeat_groups, repeatability
from calib.design.drift_check import with_repeats
from calib.errors import InputError
from calib.formats.plan import Plan, Step

ROBOT_AXIS_M, FLOOR_AXIS_M = 20e-6, 5e-6
POSES, VISITS = 30, 4


def _draw(rng):
    """Frames in the order of a revisit plan: visit 0, then visits 1..n-1, visit 1 with a still pair."""
    centre = rng.uniform(-0.1, 0.1, size=(POSES, 3))
    t, group, still = [], [], []
    for v in range(VISITS):
        for g in range(POSES):
            where = centre[g] + rng.normal(0, ROBOT_AXIS_M, 3)
            t.append(where + rng.normal(0, FLOOR_AXIS_M, 3))
            group.append(g)
            still.append(False)
            if v == 1:
                t.append(where + rng.normal(0, FLOOR_AXIS_M, 3))
                group.append(g)
                still.append(True)
    return np.array(t), np.array(group), np.array(still), np.arange(len(t))


def _bounds(true_3d: float, dof: int) -> tuple[float, float]:
    """99.9% interval of an RMS estimate from ``dof`` chi-square degrees of freedom."""
    return true_3d * np.sqrt(chi2.ppf(5e-4, dof) / dof), true_3d * np.sqrt(chi2.isf(5e-4, dof) / dof)


def test_floor_repeatability_and_the_robots_own_within_their_bounds():
    t, g, s, f = _draw(np.random.default_rng(0))
    r = repeatability(t, g, s, f)
    assert (r.poses, r.visits) == (POSES, POSES * VISITS)
    floor_true = np.sqrt(3) * FLOOR_AXIS_M
    rep_true = np.sqrt(3 * (ROBOT_AXIS_M**2 + FLOOR_AXIS_M**2))
    lo, hi = _bounds(floor_true, 3 * POSES)
    assert lo < r.floor_m < hi
    lo, hi = _bounds(rep_true, 3 * POSES * (VISITS - 1))
    assert lo < r.repeatability_m < hi
    assert r.robot_m == pytest.approx(np.sqrt(r.repeatability_m**2 - r.floor_m**2))
    assert r.robot_m == pytest.approx(np.sqrt(3) * ROBOT_AXIS_M, rel=0.25)


def test_a_revisit_one_millimetre_off_is_the_outlier():
    t, g, s, f = _draw(np.random.default_rng(1))
    k = int(np.flatnonzero((g == 7) & ~s)[2])
    t[k] += [1e-3, 0, 0]
    r = repeatability(t, g, s, f)
    assert [o["frame"] for o in r.outliers] == [k]
    assert r.outliers[0]["deviation_m"] == pytest.approx(1e-3, abs=1e-4)


def test_identical_frames_give_zero_and_no_outliers():
    t = np.repeat(np.random.default_rng(2).uniform(size=(5, 3)), 3, axis=0)
    g = np.repeat(np.arange(5), 3)
    r = repeatability(t, g, np.zeros(15, bool), np.arange(15))
    assert r.repeatability_m < 1e-12 and r.outliers == [] and r.floor_m is None and r.robot_m is None


def test_a_revisit_plan_visits_every_pose_n_times_each_from_another_pose():
    fit = [[0.1 * i, 0.2, 0.3, 0.4] for i in range(5)]
    plan = Plan(name="check", steps=[Step(phase="rotation", q=[0, 0, 0, 0]), *[Step(phase="poses", q=q) for q in fit]])
    rp = with_repeats(plan, 3)
    q = np.array([s.q for s in rp.steps if s.phase in ("poses", "validation")])
    groups = repeat_groups(q, np.array(fit))
    assert np.bincount(groups).tolist() == [4] * 5  # 3 visits, one of them with a still second frame
    moves = [a != b for a, b in itertools.pairwise(groups)]
    assert sum(not m for m in moves) == 5  # the still pairs, and no other frame without a move before it
    with pytest.raises(InputError, match="repeat"):
        with_repeats(plan, 1)
