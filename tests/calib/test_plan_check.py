"""calib.design.check_plan: what a plan the user already has will buy, counting only what the camera will see."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib.design import MotionSpec, check_plan, plan_motion_time, predict_plan, targets_from_plan, visibility
from calib.design.check import MAX_PREDICTED_FRAMES, MIN_BOARD_CORNERS
from calib.errors import InputError
from calib.formats.plan import Plan, SoftLimits, Step, make_plan, random_poses, validate_plan
from calib.model.kinematics import ikm
from calib.model.parameters import NOMINAL

MOTION = MotionSpec(speed_m_s=0.05, accel_m_s2=0.5, settle_s=0.2)
LIMITS = SoftLimits(q_min=[-0.1] * 4, q_max=[0.8] * 4)


@pytest.fixture(scope="module")
def small_sensor(scene):
    """The twin's camera with a 640 x 480 sensor (same lens, same mounting): a camera that sees less than the one
    the plan was made for."""
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=640, height=480))


def _partly_out_of_view(scene, n: int) -> list[list[float]]:
    """``n`` reachable joint values within the limits where the board's margin leaves the twin's image (seeded)."""
    q = ikm(NOMINAL, random_poses(NOMINAL, 3000, np.random.default_rng(3), limits=LIMITS))
    out = q[~visibility(scene, NOMINAL, q)["board"]]
    assert len(out) >= n, "the workspace has too few poses with the board partly out of view for this test"
    return out[:n].tolist()


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


def test_steps_without_a_board_pose_are_listed_and_not_counted(small_sensor, noise):
    """On a camera that sees less than the plan was made for, the steps with fewer than the extraction's 6 board
    corners in the image give no board pose: the check lists them and predicts without them. Counted (predict_plan
    on the plan as written), they promise a smaller std than the run can give."""
    plan = make_plan("full", NOMINAL)
    check = check_plan(plan, NOMINAL, small_sensor, noise, MOTION, methods=("combined", "end-effector"))
    blind = [u for u in check.unseen if u["board_corners"] < MIN_BOARD_CORNERS and u["phase"] != "line"]
    assert blind and all(not u["board"] for u in blind)
    n_blind = {ph: sum(u["phase"] == ph for u in blind) for ph in ("rotation", "translation", "poses", "validation")}
    assert n_blind["poses"] > 0, check.unseen
    for ph, n in n_blind.items():
        assert check.measured_counts.get(ph, 0) == plan.count()[ph] - n, ph
    assert any(f"fewer than {MIN_BOARD_CORNERS} of the board's corners" in n for n in check.notes), check.notes
    # predicted as the plan without them
    gone = {u["step"] for u in blind}
    seen = Plan(name="seen", steps=[s for i, s in enumerate(plan.steps) if i not in gone])
    ref = predict_plan(seen, NOMINAL, small_sensor, noise, methods=("combined", "end-effector"))
    for m in ("combined", "end-effector"):
        assert check.prediction.std[m] == pytest.approx(ref.std[m], rel=1e-12), m
    # what counting them would have promised: the end-effector method smaller on every combination
    naive = predict_plan(plan, NOMINAL, small_sensor, noise, methods=("end-effector",))
    assert all(naive.std["end-effector"][k] < 0.999 * ref.std["end-effector"][k] for k in ref.std["end-effector"])
    # as a reference to design against (--better-than): the target it gives is the one the camera can reach
    got = targets_from_plan(plan, NOMINAL, small_sensor, noise, method="end-effector")
    assert got == pytest.approx(targets_from_plan(seen, NOMINAL, small_sensor, noise, method="end-effector"))
    # the motion time is the plan's as written: the bench still moves to them
    assert check.motion["total_s"] == pytest.approx(plan_motion_time(plan, MOTION, NOMINAL)["total_s"], rel=1e-12)


def test_a_board_partly_out_of_view_is_counted_and_said(scene, noise):
    """A board whose margin (or a few corners) leaves the image is still measured from the corners in view (the
    extraction finds 13-15 of its 15 there): counted, listed with its corners in view, and said in the notes."""
    full = make_plan("full", NOMINAL)
    extra = _partly_out_of_view(scene, 2)
    at = max(i for i, s in enumerate(full.steps) if s.phase == "poses") + 1
    plan = Plan(name="mine", steps=[*full.steps[:at], *(Step(phase="poses", q=q) for q in extra), *full.steps[at:]])
    validate_plan(plan, NOMINAL, LIMITS)
    check = check_plan(plan, NOMINAL, scene, noise, MOTION, methods=("end-effector",))
    assert [(u["step"], u["board"], u["board_corners"]) for u in check.unseen] == [(at, False, 15), (at + 1, False, 15)]
    assert check.measured_counts["poses"] == 22
    assert any("partly out of view in 2 steps" in n for n in check.notes), check.notes
    ref = predict_plan(plan, NOMINAL, scene, noise, methods=("end-effector",))
    assert check.prediction.std["end-effector"] == pytest.approx(ref.std["end-effector"], rel=1e-12)


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
    """Visibility is computed 256 steps at a time (its arrays grow as steps x 64 x 64): a step after 300
    validation steps is still named by its index in the plan."""
    full = make_plan("full", NOMINAL)
    q = ikm(NOMINAL, random_poses(NOMINAL, 300, np.random.default_rng(2), limits=LIMITS))
    seen = visibility(scene, NOMINAL, q)["board"]
    extra = [Step(phase="validation", q=x) for x in q[seen].tolist()]
    last = Step(phase="validation", q=_partly_out_of_view(scene, 1)[0])
    plan = Plan(name="long", steps=[*full.steps, *extra, last])
    check = check_plan(plan, NOMINAL, scene, noise, MOTION, methods=("combined",))
    assert [u["step"] for u in check.unseen if not u["board"]] == [len(plan.steps) - 1]
