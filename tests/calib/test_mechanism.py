"""The mechanism seam: the registry, the I4 adapter (equal to the existing I4 code), the pose-plan check."""

from __future__ import annotations

import numpy as np
import pytest

from calib import kinematics
from calib.errors import InputError, UnreachableError
from calib.mechanism import Mechanism, joint_targets
from calib.mechanisms import get_mechanism, mechanism_names, mechanisms, register_mechanism
from calib.mechanisms.i4 import I4Mechanism
from calib.mechanisms.linear_delta import LinearDelta
from calib.parameters import NOMINAL, PARAMETER_NAMES, identifiable_parameters
from calib.plan import Workspace


def _i4_poses(n: int = 25, seed: int = 3) -> np.ndarray:
    ws = Workspace()
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(*ws.X, n), rng.uniform(*ws.Y, n), rng.uniform(*ws.Z, n), rng.uniform(*ws.T, n)])


def test_registry_has_both_mechanisms_by_name() -> None:
    assert mechanism_names()[:2] == ("i4", "linear-delta")
    assert isinstance(get_mechanism("i4"), I4Mechanism)
    assert isinstance(get_mechanism("linear-delta"), LinearDelta)
    for m in mechanisms():
        assert isinstance(m, Mechanism)  # runtime_checkable protocol: every member present
        assert len(m.parameter_names) == len(m.to_vector(m.nominal()))
        assert tuple(m.identifiable_combinations(m.nominal())) == m.combination_names


def test_registry_refuses_unknown_and_duplicate_names() -> None:
    with pytest.raises(InputError, match="unknown mechanism 'scara'.*i4, linear-delta"):
        get_mechanism("scara")
    with pytest.raises(InputError, match="already registered"):
        register_mechanism(LinearDelta())
    with pytest.raises(InputError, match="does not implement"):
        register_mechanism(type("Half", (), {"name": "half"})())  # type: ignore[arg-type]


def test_i4_adapter_equals_the_existing_i4_functions() -> None:
    m = get_mechanism("i4")
    p = NOMINAL.replace(q03=0.004, S=0.061)
    P = _i4_poses()
    q = kinematics.ikm(p, P)
    np.testing.assert_array_equal(m.ikm(p, P), q)
    np.testing.assert_array_equal(m.dkm(p, q), kinematics.dkm(p, q))
    np.testing.assert_array_equal(m.jacobian(p, P), kinematics.jacobian(p, P))
    A, B = m.leg_rods(p, q, P)
    A0, B0 = kinematics.joint_points(p, q, P)
    np.testing.assert_array_equal(A, A0)
    np.testing.assert_array_equal(B, B0)
    assert m.identifiable_combinations(p) == identifiable_parameters(p)
    assert m.parameter_names == PARAMETER_NAMES
    np.testing.assert_array_equal(m.to_vector(p), p.vector())
    assert m.from_vector(m.to_vector(p), reference=p) == p
    E = m.ee_point(p, P)
    np.testing.assert_array_equal(E, np.column_stack([P[:, 0], p.H + P[:, 1], P[:, 2]]))
    with pytest.raises(UnreachableError):
        m.ikm(p, [1.0, 0.0, -1.2, 0.0])


def test_joint_targets_checks_reach_and_soft_limits_naming_the_pose() -> None:
    m = get_mechanism("linear-delta")
    p = m.nominal()
    poses = np.array([[0.0, 0.0, -0.4], [0.05, 0.0, -0.3]])
    q = joint_targets(m, p, poses, [0.0] * 3, [0.8] * 3)
    np.testing.assert_allclose(q, m.ikm(p, poses))
    with pytest.raises(InputError, match=r"frame 1.*not reachable.*leg") as ei:
        joint_targets(m, p, [[0.0, 0.0, -0.3], [0.5, 0.0, -0.3]], [0.0] * 3, [0.8] * 3)
    assert ei.value.frame == 1
    hi = float(q[1].max()) - 0.01
    assert q[0].max() < hi  # pose 0 passes, pose 1 fails by 10 mm
    with pytest.raises(InputError, match=r"frame 1, field 'q\[\d\]'.*outside the soft limits.*by 10.000 mm"):
        joint_targets(m, p, poses, [0.0] * 3, [hi] * 3)
    with pytest.raises(InputError, match="3 values each"):
        joint_targets(m, p, poses, [0.0] * 4, [0.8] * 4)
