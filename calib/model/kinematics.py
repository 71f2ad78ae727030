"""Direct and inverse kinematic models of the I4 mechanism and its Jacobian.

Conventions (base frame R_B, metres; see docs/model.md and the seed's MODEL-NOTES.md):

* ``A1 = (q1, 0, 0)``, ``A2 = (q2 + q02, 0, 0)``, ``A3 = (q3 + q03, 2H, 0)``, ``A4 = (q4 + q04, 2H, 0)``.
* Pose ``(X, Y, Z, T)``: the end-effector point is ``E = (X, H + Y, Z)`` (Y is measured from the
  mid-line y = H), T is a length; the end-effector angle about z_B is ``T / T_per_rad`` radians.
* ``B1 = (X+T-S, H+Y-D, Z)``, ``B2 = (X+T+S, H+Y-D, Z)``, ``B3 = (X-T-S, H+Y+D, Z)``, ``B4 = (X-T+S, H+Y+D, Z)``.
* Legs hang below the actuators (Z < 0) and converge: ``u1x > 0``, ``u3x > 0``.

Every function accepts one pose / joint vector of shape (4,) or many of shape (N, 4) and returns
arrays with the same leading shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.errors import UnreachableError
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import rot_z

Array = NDArray[np.float64]

__all__ = [
    "base_from_ee",
    "dkm",
    "ikm",
    "jacobian",
    "jacobian_ratios",
    "joint_points",
    "leg_directions",
    "pose_from_joints_reduced",
]


def _as_rows(x: ArrayLike, name: str) -> tuple[Array, bool]:
    arr = np.asarray(x, dtype=np.float64)
    single = arr.ndim == 1
    if single:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(f"{name} must have shape (4,) or (N, 4), got {np.shape(x)}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr))[0, 0])
        raise ValueError(f"{name}[{bad}] contains a non-finite value")
    return arr, single


def _unreachable(kind: str, legs: str, idx: NDArray[np.intp], deficit: Array) -> UnreachableError:
    i = int(idx[0])
    d = float(deficit[i])
    more = f" (and {len(idx) - 1} more)" if len(idx) > 1 else ""
    return UnreachableError(
        f"{kind} #{i} is unreachable: legs {legs} are {d * 1e3:.3f} mm too short{more}",
        leg=int(legs[0]),
        index=i,
        deficit_m=d,
    )


def ikm(params: I4Parameters, pose: ArrayLike) -> Array:
    """Inverse kinematic model: joint values for given poses.

    Parameters
    ----------
    params : I4Parameters
    pose : array_like, shape (4,) or (N, 4)
        ``(X, Y, Z, T)`` in metres.

    Returns
    -------
    ndarray, shape (4,) or (N, 4)
        ``(q1, q2, q3, q4)`` in metres.

    Raises
    ------
    UnreachableError
        A leg pair cannot reach the pose; the message names the legs and the deficit.
    """
    P, single = _as_rows(pose, "pose")
    X, Y, Z, T = P.T
    c = params.H - params.D
    L2 = params.L**2
    f1sq = L2 - (Y + c) ** 2 - Z**2
    f3sq = L2 - (Y - c) ** 2 - Z**2
    for fsq, legs, off in ((f1sq, "1 and 2", Y + c), (f3sq, "3 and 4", Y - c)):
        bad = np.flatnonzero(fsq < 0)
        if bad.size:
            deficit = np.sqrt(off**2 + Z**2) - params.L
            raise _unreachable("pose", legs, bad, deficit)
    f1 = np.sqrt(f1sq)
    f3 = np.sqrt(f3sq)
    S = params.S
    q = np.stack(
        [
            X + T - S - f1,
            X + T + S + f1 - params.q02,
            X - T - S - f3 - params.q03,
            X - T + S + f3 - params.q04,
        ],
        axis=1,
    )
    return q[0] if single else q


def pose_from_joints_reduced(combos: ArrayLike, q: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """Y, Z and the leg x-components from the four identifiable combinations.

    Parameters
    ----------
    combos : array_like, shape (4,)
        ``(L, H-D, S-q02/2, S-(q04-q03)/2)`` in metres.
    q : array_like, shape (N, 4)
        Joint values in metres.

    Returns
    -------
    Y, Z, f1, f3 : ndarray, shape (N,)
        Pose components and ``f1 = u1x L``, ``f3 = u3x L``.
    """
    L, c, s1, s3 = np.asarray(combos, dtype=np.float64)
    Q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    a = Q[:, 1] - Q[:, 0] - 2.0 * s1
    b = Q[:, 3] - Q[:, 2] - 2.0 * s3
    Y = (b**2 - a**2) / (16.0 * c)
    zsq = L**2 - c**2 - Y**2 - (a**2 + b**2) / 8.0
    Z = -np.sqrt(np.maximum(zsq, 0.0))
    return Y, Z, a / 2.0, b / 2.0


def dkm(params: I4Parameters, q: ArrayLike) -> Array:
    """Direct kinematic model: poses for given joint values.

    Parameters
    ----------
    params : I4Parameters
    q : array_like, shape (4,) or (N, 4)
        Joint values in metres.

    Returns
    -------
    ndarray, shape (4,) or (N, 4)
        ``(X, Y, Z, T)`` in metres.

    Raises
    ------
    UnreachableError
        The legs cannot close (too short), or a leg pair would cross (the converging
        assembly mode ``u1x > 0``, ``u3x > 0`` is the only one modelled).
    """
    Q, single = _as_rows(q, "q")
    q1, q2, q3, q4 = Q.T
    p = params
    c = p.H - p.D
    a = q2 - q1 - 2.0 * p.S + p.q02
    b = q4 - q3 - 2.0 * p.S + p.q04 - p.q03
    for v, legs in ((a, "1 and 2"), (b, "3 and 4")):
        bad = np.flatnonzero(v <= 0)
        if bad.size:
            i = int(bad[0])
            raise UnreachableError(
                f"joint vector #{i} is unreachable: legs {legs} would cross "
                f"(their lower ends are {-v[i] * 1e3:.3f} mm past each other)",
                leg=int(legs[0]),
                index=i,
                deficit_m=float(-v[i]),
            )
    X = (q1 + q2 + q3 + q4 + p.q02 + p.q03 + p.q04) / 4.0
    T = (q1 + q2 - q3 - q4 + p.q02 - p.q03 - p.q04) / 4.0
    Y = (b**2 - a**2) / (16.0 * c)
    zsq = p.L**2 - c**2 - Y**2 - (a**2 + b**2) / 8.0
    bad = np.flatnonzero(zsq < 0)
    if bad.size:
        i = int(bad[0])
        need12 = np.sqrt((a / 2) ** 2 + (Y + c) ** 2)
        need34 = np.sqrt((b / 2) ** 2 + (Y - c) ** 2)
        legs = "1 and 2" if need12[i] >= need34[i] else "3 and 4"
        deficit = np.maximum(need12, need34) - p.L
        raise _unreachable("joint vector", legs, bad, deficit)
    Z = -np.sqrt(zsq)
    out = np.stack([X, Y, Z, T], axis=1)
    return out[0] if single else out


def leg_directions(params: I4Parameters, pose: ArrayLike) -> Array:
    """Unit leg directions ``u_i`` (from A_i to B_i) in the base frame.

    Parameters
    ----------
    params : I4Parameters
        The geometry (metres).
    pose : array_like, shape (4,) or (N, 4)
        Poses ``(X, Y, Z, T)``, metres.

    Returns
    -------
    ndarray, shape (4, 3) or (N, 4, 3)
        Unit directions (dimensionless).

    Raises
    ------
    UnreachableError
        If a leg pair cannot reach a pose.
    """
    P, single = _as_rows(pose, "pose")
    A, B = joint_points(params, ikm(params, P), P)
    u = (B - A) / params.L
    return u[0] if single else u


def joint_points(params: I4Parameters, q: ArrayLike, pose: ArrayLike) -> tuple[Array, Array]:
    """Joint centres ``A_i`` (on the actuators) and ``B_i`` (on the plate) in the base frame.

    Parameters
    ----------
    params : I4Parameters
        The geometry (metres).
    q, pose : array_like, shape (N, 4)
        Consistent joint values and poses (metres).

    Returns
    -------
    A, B : ndarray, shape (N, 4, 3)
        The joint centres, metres.
    """
    Q, _ = _as_rows(q, "q")
    P, _ = _as_rows(pose, "pose")
    p = params
    n = Q.shape[0]
    A = np.zeros((n, 4, 3))
    A[:, 0, 0] = Q[:, 0]
    A[:, 1, 0] = Q[:, 1] + p.q02
    A[:, 2, 0] = Q[:, 2] + p.q03
    A[:, 3, 0] = Q[:, 3] + p.q04
    A[:, 2:, 1] = 2.0 * p.H
    X, Y, Z, T = P.T
    B = np.empty((n, 4, 3))
    B[:, 0] = np.stack([X + T - p.S, p.H + Y - p.D, Z], axis=1)
    B[:, 1] = np.stack([X + T + p.S, p.H + Y - p.D, Z], axis=1)
    B[:, 2] = np.stack([X - T - p.S, p.H + Y + p.D, Z], axis=1)
    B[:, 3] = np.stack([X - T + p.S, p.H + Y + p.D, Z], axis=1)
    return A, B


def jacobian_ratios(u: ArrayLike) -> Array:
    """The pose-dependent Jacobian entries from leg directions.

    Parameters
    ----------
    u : array_like, shape (..., 4, 3)
        Leg directions in the base frame; sign and norm do not matter.

    Returns
    -------
    ndarray, shape (..., 4, 2)
        ``(u_iy / u_ix, u_iz / u_ix)`` for each leg: columns 2 and 3 of J_X.
    """
    U = np.asarray(u, dtype=np.float64)
    return U[..., 1:] / U[..., :1]


def jacobian(params: I4Parameters, pose: ArrayLike) -> Array:
    """Jacobian of the inverse kinematic model, ``q_dot = J X_dot``.

    Parameters
    ----------
    params : I4Parameters
        The geometry (metres).
    pose : array_like, shape (4,) or (N, 4)
        Poses ``(X, Y, Z, T)``, metres.

    Returns
    -------
    ndarray, shape (4, 4) or (N, 4, 4)
        Rows are legs, columns ``(X, Y, Z, T)``; see MODEL-NOTES.md (row 2, column 4 is +1).
    """
    P, single = _as_rows(pose, "pose")
    u = leg_directions(params, P)
    r = jacobian_ratios(u)
    J = np.empty((P.shape[0], 4, 4))
    J[:, :, 0] = 1.0
    J[:, :, 1:3] = r
    J[:, :, 3] = [1.0, 1.0, -1.0, -1.0]
    return J[0] if single else J


def base_from_ee(params: I4Parameters, pose: ArrayLike) -> tuple[Array, Array]:
    """The end-effector frame in the base frame: rotation ``rot_z(T / T_per_rad)`` (..., 3, 3) and origin
    ``E = (X, H + Y, Z)`` (..., 3), metres, for a pose (4,) or poses (N, 4).

    Parameters
    ----------
    params : I4Parameters
        The geometry (metres; ``T_per_rad`` in metres per radian).
    pose : array_like, shape (4,) or (N, 4)
        Poses ``(X, Y, Z, T)``, metres.

    Returns
    -------
    R : ndarray, shape (3, 3) or (N, 3, 3)
        ``base_from_ee`` rotation (dimensionless).
    t : ndarray, shape (3,) or (N, 3)
        The end-effector origin in the base frame, metres.
    """
    P, single = _as_rows(pose, "pose")
    R = rot_z(P[:, 3] / params.T_per_rad)
    t = np.column_stack([P[:, 0], params.H + P[:, 1], P[:, 2]])
    return (R[0], t[0]) if single else (R, t)
