"""calib.design.check_plan: what a plan the user already has will buy, counting only what the camera will see."""

from __future__ import annotations

import numpy as np
import pytest

from calib.design import MotionSpec, check_plan, plan_motion_time, predict_plan, targets_from_plan, visibility
from calib.design.check import MAX_PREDICTED_FRAMES
from calib.errors import InputError
from calib.kinematics import ikm
from calib.parameters import NOMINAL
from calib.plan import Plan, SoftLimits, Step, make_plan, random_poses, validate_plan

MOTION = MotionSpec(speed_m_s=0.05, accel_m_s2=0.5, settle_s=0.2)
LIMITS = SoftLimits(q_min=[-0.1] * 4, q_max=[0.8] * 4)


def _board_out_of_view(scene, n: int) -> list[list[float]]:
    """``n`` reachable joint values within the limits where the board is out of view (seeded)."""
    q = ikm(NOMINAL, random_poses(NOMINAL, 3000, np.random.default_rng(3), limits=LIMITS))
    blind = q[~visibility(scene, NOMINAL, q)["board"]]
    assert len(blind) >= n, "the workspace has too few poses with the board out of view for this test"
    return blind[:n].tolist()


def test_a_plan_in_view_is_predicted_as_it_is(scene, noise):
    """The paper's plan, every step in view: the prediction is predict_plan's, the motion time plan_motion_time's."""
    plan = make_plan("full", NOMINAL)
    check = check_plan(plan, NOMINAL, scene, noise, MOTION)
    assert check.unseen == [] and check.measured_counts == check.counts == plan.count()
    ref = predict_plan(plan, NOMINAL, scene, noise)
    for m in ("combined", "end-effector", "legs"):
        assert check.prediction.std[m] == pytest.approx(ref.std[m], rel=1e-12)
    assert check.motion["total_s"] == pytest.approx(plan_motion_time(plan, MOTION, NOMINAL)["total_s"], rel=1e-12)
    # the legs prediction leans on its model of the lock phases' shading there: the check says so
    assert any("shading" in n for n in check.notes), check.notes
    doc = check.summary()
    assert set(doc) == {"plan", "counts", "measured_counts", "prediction", "motion", "unseen", "notes"}


def test_fit_poses_out_of_view_are_listed_and_not_counted(scene, noise):
    """Fit poses whose board the camera will not see give no board pose: the check lists them and predicts without
    them. Counted (predict_plan on the plan as written), they would promise a smaller std than the run can give."""
    full = make_plan("full", NOMINAL)
    blind = _board_out_of_view(scene, 2)
    at = max(i for i, s in enumerate(full.steps) if s.phase == "poses") + 1
    steps = [*full.steps[:at], *(Step(phase="poses", q=q) for q in blind), *full.steps[at:]]
    plan = Plan(name="full-plus-blind", steps=steps)
    validate_plan(plan, NOMINAL, LIMITS)  # within the limits and reachable: only the camera cannot see them
    check = check_plan(plan, NOMINAL, scene, noise, MOTION)
    assert [u["step"] for u in check.unseen] == [at, at + 1], check.unseen
    assert all(u["phase"] == "poses" and u["board"] is False for u in check.unseen)
    assert check.counts["poses"] == 22 and check.measured_counts["poses"] == 20
    assert any("board is out of view in 2 poses steps" in n for n in check.notes), check.notes
    # predicted as the plan without them: the paper's
    ref = predict_plan(full, NOMINAL, scene, noise)
    for m in ("combined", "end-effector"):
        assert check.prediction.std[m] == pytest.approx(ref.std[m], rel=1e-12), m
    # what counting them would have promised: the end-effector method smaller on some combination
    naive = predict_plan(plan, NOMINAL, scene, noise, methods=("end-effector",))
    assert min(naive.std["end-effector"][k] / ref.std["end-effector"][k] for k in ref.std["end-effector"]) < 0.999
    # as a reference to design against (--better-than): the target it gives is the paper's, not stricter
    for m in ("combined", "end-effector"):
        got = targets_from_plan(plan, NOMINAL, scene, noise, method=m)
        assert got == pytest.approx(targets_from_plan(full, NOMINAL, scene, noise, method=m), rel=1e-12), m
    # the motion time is the plan's as written: the bench still moves to them
    assert check.motion["per_phase_s"]["poses"] > plan_motion_time(full, MOTION, NOMINAL)["per_phase_s"]["poses"]


def test_a_plan_that_feeds_no_method_says_why(scene, noise):
    """The lock phases alone feed no method: each is listed with its reason, none raised."""
    check = check_plan(make_plan("lock-actuator", NOMINAL), NOMINAL, scene, noise, MOTION)
    assert check.prediction.std == {}
    assert set(check.prediction.errors) == {"combined", "end-effector", "legs"}
    assert all("fit poses" in why for why in check.prediction.errors.values())


def test_a_plan_too_large_to_predict_is_refused_at_once(scene, noise):
    """The image-level prediction's cost grows faster than the square of the rods (1000 fit poses: 5 min): more fit
    poses than a design takes, or more predicted frames than MAX_PREDICTED_FRAMES, is an error naming the steps."""
    full = make_plan("full", NOMINAL)
    q = ikm(NOMINAL, random_poses(NOMINAL, 201, np.random.default_rng(1), limits=LIMITS))
    many = Plan(name="many", steps=[*full.steps, *(Step(phase="poses", q=x) for x in q.tolist())])
    with pytest.raises(InputError, match="221 fit poses: a prediction takes at most 200") as err:
        check_plan(many, NOMINAL, scene, noise, MOTION)
    assert err.value.field == "steps"
    with pytest.raises(InputError, match="221 fit poses"):  # as a reference to design against, too
        targets_from_plan(many, NOMINAL, scene, noise)
    lock = [s for s in full.steps if s.phase == "lock-1"]
    heavy = Plan(name="heavy", steps=[*full.steps, *lock * (MAX_PREDICTED_FRAMES // len(lock))])
    with pytest.raises(InputError, match=f"at most {MAX_PREDICTED_FRAMES}"):
        check_plan(heavy, NOMINAL, scene, noise, MOTION)


def test_steps_beyond_a_visibility_chunk_are_named_by_their_own_index(scene, noise):
    """Visibility is computed 256 steps at a time (its arrays grow as steps x 64 x 64): a blind step after 300
    validation steps is still named by its index in the plan."""
    full = make_plan("full", NOMINAL)
    q = ikm(NOMINAL, random_poses(NOMINAL, 300, np.random.default_rng(2), limits=LIMITS))
    seen = visibility(scene, NOMINAL, q)["board"]
    extra = [Step(phase="validation", q=x) for x in q[seen].tolist()]
    plan = Plan(name="long", steps=[*full.steps, *extra, Step(phase="validation", q=_board_out_of_view(scene, 1)[0])])
    check = check_plan(plan, NOMINAL, scene, noise, MOTION, methods=("combined",))
    assert [u["step"] for u in check.unseen if not u["board"]] == [len(plan.steps) - 1]
