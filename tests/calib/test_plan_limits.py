"""The named plans on a bench whose soft limits are not the simulated bench's: drawn within them, the guided line
shortened to them; on the simulated bench's limits, the same plan as before (its datasets' bytes rely on it)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.plan import MIN_LINE_LENGTH_M, SoftLimits, guided_line, line_poses, make_plan, validate_plan
from calib.model.kinematics import ikm
from calib.model.parameters import NOMINAL

#: the real bench example's limits (deploy/bench-real.example.toml): actuators from 0 to 750 mm
REAL = SoftLimits(q_min=[0.0] * 4, q_max=[0.75] * 4)


def test_the_simulated_benchs_limits_give_the_same_plan():
    assert make_plan("full", NOMINAL, limits=SoftLimits()) == make_plan("full", NOMINAL)


def test_the_named_plans_fit_a_bench_with_other_limits():
    with pytest.raises(InputError, match="outside the soft limits"):  # drawn for the simulated bench's limits
        validate_plan(make_plan("full", NOMINAL), NOMINAL, REAL)
    plan = make_plan("full", NOMINAL, limits=REAL)
    validate_plan(plan, NOMINAL, REAL)
    assert plan.count() == make_plan("full", NOMINAL).count()
    line = next(s.line for s in plan.steps if s.line is not None)
    ends = np.array([line.start_pose, line.end_pose])
    length = np.linalg.norm(ends[1, :3] - ends[0, :3])
    assert MIN_LINE_LENGTH_M <= length < 0.5  # shortened: the paper's 500 mm line leaves these limits
    q = ikm(NOMINAL, line_poses(line))
    assert q.min() >= 0.0 and q.max() <= 0.75
    # the longest that fits, within the 5% steps: 5% longer leaves the limits
    longer = guided_line(NOMINAL, length_m=length / 0.95)[0].line
    assert ikm(NOMINAL, line_poses(longer)).min() < 0.0 or ikm(NOMINAL, line_poses(longer)).max() > 0.75


def test_no_line_fits_is_an_error_naming_the_line():
    with pytest.raises(InputError) as err:
        guided_line(NOMINAL, limits=SoftLimits(q_min=[0.30] * 4, q_max=[0.31] * 4))
    assert err.value.field == "line"
