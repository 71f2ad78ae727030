"""The mechanism seam: what plans, methods, validation, twins and drivers need to know about a mechanism.

A :class:`Mechanism` is a small :class:`typing.Protocol`: its joint count, its pose size, the names of its geometric
parameters and their vector <-> object conversion, its inverse and direct kinematic models, the Jacobian of its
inverse model, the end-effector point a camera observes, the combinations of parameters that end-effector data
identify, and, where it has legs, the legs' end points. The I4 (:mod:`calib.mechanisms.i4`, a thin adapter over
:mod:`calib.kinematics` and :mod:`calib.parameters`) is the only full implementation; the linear Delta
(:mod:`calib.mechanisms.linear_delta`) proves the seam in tests (docs/mechanisms.md).

Conventions: metres and radians; one pose of shape ``(pose_dim,)`` or many of shape ``(N, pose_dim)``, one joint
vector of shape ``(n_joints,)`` or many of shape ``(N, n_joints)``; results keep the leading shape. Poses or joint
vectors out of reach raise :class:`calib.errors.UnreachableError` naming the row and the leg.

The registry of mechanisms by name is :mod:`calib.mechanisms` (it imports the implementations; this module imports
none of them).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError, UnreachableError

Array = NDArray[np.float64]

#: Name of a mechanism: lower case, digits and dashes (a CLI and JSON key).
NAME_PATTERN = r"^[a-z][a-z0-9-]{0,31}$"


@runtime_checkable
class Mechanism(Protocol):
    """A parallel mechanism as calibration sees it.

    Attributes
    ----------
    name : str
        Registry key (:data:`NAME_PATTERN`), e.g. ``"i4"``, ``"linear-delta"``.
    n_joints : int
        Number of actuated joints (and of drive axes).
    pose_dim : int
        Size of a pose vector (I4: 4, ``(X, Y, Z, T)``; linear Delta: 3, ``(x, y, z)``).
    parameter_names : tuple of str
        The geometric parameters, in the order of :meth:`to_vector`.
    combination_names : tuple of str
        The identifiable combinations, in the order of :meth:`identifiable_combinations`.
    """

    name: str
    n_joints: int
    pose_dim: int
    parameter_names: tuple[str, ...]
    combination_names: tuple[str, ...]

    def nominal(self) -> Any:
        """The a priori geometry (the mechanism's parameter object)."""
        ...

    def to_vector(self, params: Any) -> Array:
        """Parameters as a vector, shape ``(len(parameter_names),)``, metres and radians."""
        ...

    def from_vector(self, values: ArrayLike, reference: Any | None = None) -> Any:
        """The parameter object from a vector in :attr:`parameter_names` order; constants of the model that are
        not parameters (e.g. the I4's ``T_per_rad``) come from ``reference`` (default: :meth:`nominal`)."""
        ...

    def ikm(self, params: Any, pose: ArrayLike) -> Array:
        """Inverse kinematic model: joint values, shape ``(n_joints,)`` or ``(N, n_joints)``, metres, for poses of
        shape ``(pose_dim,)`` or ``(N, pose_dim)``. Raises :class:`UnreachableError` (names the pose and the leg)."""
        ...

    def dkm(self, params: Any, q: ArrayLike) -> Array:
        """Direct kinematic model: poses, shape ``(pose_dim,)`` or ``(N, pose_dim)``, for joint values of shape
        ``(n_joints,)`` or ``(N, n_joints)`` (metres). Raises :class:`UnreachableError` (names the row)."""
        ...

    def jacobian(self, params: Any, pose: ArrayLike) -> Array:
        """Jacobian of the inverse kinematic model, ``d q / d pose`` (``q_dot = J pose_dot``), shape
        ``(n_joints, pose_dim)`` or ``(N, n_joints, pose_dim)``; dimensionless for length coordinates (m/m),
        m/rad for angular ones."""
        ...

    def ee_point(self, params: Any, pose: ArrayLike) -> Array:
        """The end-effector point a camera observes (a target on the plate) in the base frame, shape ``(3,)`` or
        ``(N, 3)``, metres."""
        ...

    def identifiable_combinations(self, params: Any) -> dict[str, float]:
        """The combinations of parameters that end-effector positions identify (:attr:`combination_names`)."""
        ...

    def leg_rods(self, params: Any, q: ArrayLike, pose: ArrayLike) -> tuple[Array, Array] | None:
        """End points ``(A, B)`` of each leg (on the actuator side, on the plate side), each of shape
        ``(N, n_legs, 3)``, metres, base frame, for consistent joint values and poses (``(N, ...)``); None for a
        mechanism without legs a camera can see."""
        ...


def as_rows(x: ArrayLike, width: int, name: str) -> tuple[Array, bool]:
    """``x`` as an ``(N, width)`` float array and whether it was one row; checks shape and finiteness.

    Raises
    ------
    InputError
        Wrong shape, or a non-finite value (names the row).
    """
    arr = np.asarray(x, dtype=np.float64)
    single = arr.ndim == 1
    if single:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != width:
        raise InputError(f"{name} must have shape ({width},) or (N, {width}), got {np.shape(x)}", field=name)
    if not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr))[0, 0])
        raise InputError(f"{name}[{bad}] contains a non-finite value", field=name, frame=bad)
    return arr, single


def joint_targets(
    mechanism: Mechanism,
    params: Any,
    poses: ArrayLike,
    q_min: ArrayLike,
    q_max: ArrayLike,
) -> Array:
    """Validate a pose plan before anything moves: joint targets of ``poses`` through the nominal ``ikm``, each
    within the per-axis soft limits.

    Parameters
    ----------
    mechanism : Mechanism
    params : object
        The nominal geometry (the mechanism's parameter object).
    poses : array_like, shape (N, pose_dim)
        Metres (radians for angular pose coordinates).
    q_min, q_max : array_like, shape (n_joints,)
        Soft limits, metres.

    Returns
    -------
    ndarray, shape (N, n_joints)
        Joint targets, metres.

    Raises
    ------
    InputError
        A pose the nominal model cannot reach, or whose joint target is outside the soft limits (names the pose as
        ``frame``, the axis and by how much).
    """
    P, _ = as_rows(poses, mechanism.pose_dim, "poses")
    lo = np.asarray(q_min, dtype=np.float64).reshape(-1)
    hi = np.asarray(q_max, dtype=np.float64).reshape(-1)
    if lo.shape != (mechanism.n_joints,) or hi.shape != (mechanism.n_joints,):
        raise InputError(
            f"soft limits need {mechanism.n_joints} values each for {mechanism.name}, got {lo.size} and {hi.size}",
            field="limits",
        )
    q = np.empty((len(P), mechanism.n_joints))
    for i, p in enumerate(P):
        try:
            q[i] = mechanism.ikm(params, p)
        except UnreachableError as exc:
            raise InputError(
                f"pose {np.round(p, 6).tolist()} not reachable by the nominal model: {exc}", frame=i
            ) from None
        out = (q[i] < lo) | (q[i] > hi)
        if out.any():
            ax = int(np.flatnonzero(out)[0])
            bound = lo[ax] if q[i, ax] < lo[ax] else hi[ax]
            raise InputError(
                f"pose {np.round(p, 6).tolist()}: q{ax + 1} = {q[i, ax] * 1e3:.3f} mm is outside the soft limits "
                f"[{lo[ax] * 1e3:.1f}, {hi[ax] * 1e3:.1f}] mm by {abs(q[i, ax] - bound) * 1e3:.3f} mm",
                frame=i,
                field=f"q[{ax}]",
            )
    return q


__all__ = ["NAME_PATTERN", "Mechanism", "as_rows", "joint_targets"]
