"""The I4 behind the :class:`calib.mechanism.Mechanism` seam: a thin adapter over :mod:`calib.kinematics` and
:mod:`calib.parameters` (the I4 code stays where it is; this module only forwards to it).

Pose ``(X, Y, Z, T)`` (metres; ``T`` a rack length, the end-effector angle is ``T / T_per_rad`` rad), joints
``(q1, q2, q3, q4)`` (metres), seven parameters ``(H, q02, q03, q04, S, D, L)``, four identifiable combinations
``(L, H-D, S-q02/2, S-(q04-q03)/2)`` (docs/model.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from .. import kinematics as k
from ..mechanism import Array, as_rows
from ..parameters import COMBINATION_NAMES, NOMINAL, PARAMETER_NAMES, I4Parameters, identifiable_parameters


class I4Mechanism:
    """The I4 (four linear actuators, four parallelogram legs, a plate translating and turning about z)."""

    name = "i4"
    n_joints = 4
    pose_dim = 4
    parameter_names: tuple[str, ...] = PARAMETER_NAMES
    combination_names: tuple[str, ...] = COMBINATION_NAMES

    def nominal(self) -> I4Parameters:
        """:data:`calib.parameters.NOMINAL`."""
        return NOMINAL

    def to_vector(self, params: I4Parameters) -> Array:
        """The seven parameters, shape (7,), metres."""
        return np.asarray(params.vector(), dtype=np.float64)

    def from_vector(self, values: ArrayLike, reference: I4Parameters | None = None) -> I4Parameters:
        """Seven values (metres) -> :class:`I4Parameters`; ``T_per_rad`` from ``reference`` (default NOMINAL)."""
        ref = reference if reference is not None else NOMINAL
        return I4Parameters.from_vector(np.asarray(values, dtype=np.float64).reshape(-1), T_per_rad=ref.T_per_rad)

    def ikm(self, params: I4Parameters, pose: ArrayLike) -> Array:
        """:func:`calib.kinematics.ikm`."""
        return k.ikm(params, pose)

    def dkm(self, params: I4Parameters, q: ArrayLike) -> Array:
        """:func:`calib.kinematics.dkm`."""
        return k.dkm(params, q)

    def jacobian(self, params: I4Parameters, pose: ArrayLike) -> Array:
        """:func:`calib.kinematics.jacobian`: ``d q / d (X, Y, Z, T)``, shape (4, 4) or (N, 4, 4)."""
        return k.jacobian(params, pose)

    def ee_point(self, params: I4Parameters, pose: ArrayLike) -> Array:
        """The end-effector point ``E = (X, H + Y, Z)`` in the base frame, shape (3,) or (N, 3), metres."""
        P, single = as_rows(pose, 4, "pose")
        E = np.stack([P[:, 0], params.H + P[:, 1], P[:, 2]], axis=1)
        return E[0] if single else E

    def identifiable_combinations(self, params: I4Parameters) -> dict[str, float]:
        """:func:`calib.parameters.identifiable_parameters` (the four combinations)."""
        return identifiable_parameters(params)

    def leg_rods(self, params: I4Parameters, q: ArrayLike, pose: ArrayLike) -> tuple[Array, Array]:
        """:func:`calib.kinematics.joint_points`: ``A, B`` of shape (N, 4, 3), metres."""
        return k.joint_points(params, q, pose)

    def __repr__(self) -> str:
        return "I4Mechanism()"


if TYPE_CHECKING:  # mypy checks that the adapter satisfies the protocol
    from ..mechanism import Mechanism

    _protocol_check: Mechanism = I4Mechanism()
