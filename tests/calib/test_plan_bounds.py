"""Plan size bounds and finite numbers: refused with an InputError naming the step and
the field, before any kinematics; the vectorised validation reports the same first error as a step-by-step check."""

from __future__ import annotations

import time

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.plan import (
    MAX_LINE_SAMPLES,
    MAX_PLAN_FRAMES,
    MAX_PLAN_STEPS,
    Plan,
    SoftLimits,
    make_plan,
    validate_plan,
)
from calib.formats.plan import _check_step as check_step
from drivers.sim.twin import BenchGeometry

NOMINAL = BenchGeometry().nominal


def _doc() -> dict:
    return make_plan("full", NOMINAL, n_base=4, n_fit=6, n_lock=3, n_validation=3, line_samples=11).model_dump(
        exclude_none=True
    )


def test_nan_in_q_is_an_input_error_naming_step_and_axis():
    doc = _doc()
    doc["steps"][2]["q"][1] = float("nan")
    with pytest.raises(InputError) as err:
        Plan.from_dict(doc)
    assert (err.value.frame, err.value.field) == (2, "q[1]")
    # a plan built in code (no validation of its fields) is caught by validate_plan, not by dkm's ValueError
    plan = Plan.from_dict(_doc())
    plan.steps[3].q[2] = float("inf")
    with pytest.raises(InputError) as err:
        validate_plan(plan, NOMINAL)
    assert (err.value.frame, err.value.field) == (3, "q[2]") and "finite" in err.value.reason


def test_non_finite_line_and_rate_refused():
    doc = _doc()
    i = next(k for k, s in enumerate(doc["steps"]) if "line" in s)
    doc["steps"][i]["line"]["end_pose"][0] = float("-inf")
    with pytest.raises(InputError) as err:
        Plan.from_dict(doc)
    assert (err.value.frame, err.value.field) == (i, "line.end_pose[0]")
    doc = _doc()
    doc["steps"][i]["line"]["rate_hz"] = float("inf")
    with pytest.raises(InputError) as err:
        Plan.from_dict(doc)
    assert (err.value.frame, err.value.field) == (i, "line.rate_hz")


def test_size_bounds_are_checked_before_any_work():
    doc = _doc()
    i = next(k for k, s in enumerate(doc["steps"]) if "line" in s)
    doc["steps"][i]["line"]["samples"] = 1_000_000
    t0 = time.perf_counter()
    with pytest.raises(InputError) as err:
        validate_plan(Plan.from_dict(doc), NOMINAL)
    assert time.perf_counter() - t0 < 0.5
    assert (err.value.frame, err.value.field) == (i, "line.samples") and str(MAX_LINE_SAMPLES) in err.value.reason
    with pytest.raises(InputError) as err:
        Plan.from_dict({"name": "x", "steps": [doc["steps"][0]] * (MAX_PLAN_STEPS + 1)})
    assert err.value.field == "steps" and err.value.frame is None
    line = {**doc["steps"][i], "line": {**doc["steps"][i]["line"], "samples": MAX_LINE_SAMPLES}}
    n = MAX_PLAN_FRAMES // MAX_LINE_SAMPLES
    assert Plan.from_dict({"name": "x", "steps": [line] * n}).count() == {"line": MAX_PLAN_FRAMES}
    with pytest.raises(InputError) as err:
        Plan.from_dict({"name": "x", "steps": [line] * n + [doc["steps"][0]]})
    assert (err.value.frame, err.value.field) == (n, "steps") and str(MAX_PLAN_FRAMES) in err.value.reason
    # a plan built in code is held to the same bounds by validate_plan
    plan = Plan.from_dict({"name": "x", "steps": [line] * n})
    plan.steps.append(plan.steps[0])
    with pytest.raises(InputError, match=str(MAX_PLAN_FRAMES)):
        validate_plan(plan, NOMINAL)


def test_vectorised_validation_names_the_first_bad_step_as_step_by_step_does():
    """Seeded random damage to a valid plan: the batch check finds the same first error as checking each step in
    turn (limits, reach, finiteness)."""
    rng = np.random.default_rng(12)
    limits = SoftLimits()
    lo, hi = np.asarray(limits.q_min), np.asarray(limits.q_max)
    base = _doc()
    validate_plan(Plan.from_dict(base), NOMINAL)
    errors = 0
    for _ in range(200):
        plan = Plan.from_dict(base)
        for _ in range(int(rng.integers(1, 4))):
            step = plan.steps[int(rng.integers(len(plan.steps)))]
            if step.q is not None:
                step.q[int(rng.integers(4))] += float(rng.normal(0, 0.3))
        expected = None
        for k, step in enumerate(plan.steps):
            try:
                check_step(k, step, NOMINAL, lo, hi)
            except InputError as exc:
                expected = str(exc)
                break
        try:
            validate_plan(plan, NOMINAL, limits)
            got = None
        except InputError as exc:
            got = str(exc)
        assert got == expected
        errors += got is not None
    assert 50 < errors < 200  # both outcomes exercised
