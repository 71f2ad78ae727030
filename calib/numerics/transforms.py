"""Small rigid-transform helpers (rotation matrices, rotation vectors, rigid transforms).

Frames are named ``a_from_b``: a point ``p_b`` in frame b maps to ``p_a = R p_b + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

Array = NDArray[np.float64]


def as_vec3(x: ArrayLike, name: str) -> Array:
    """A 3-vector as float64, checked.

    Parameters
    ----------
    x : array_like, shape (3,)
        The vector (any unit; kept).
    name : str
        Its name in the error message.

    Returns
    -------
    ndarray, shape (3,)
        ``x`` as float64.

    Raises
    ------
    ValueError
        If ``x`` is not of shape (3,).
    """
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {a.shape}")
    return a


def as_mat3(x: ArrayLike, name: str) -> Array:
    """A 3x3 matrix as float64, checked.

    Parameters
    ----------
    x : array_like, shape (3, 3)
        The matrix (dimensionless for a rotation).
    name : str
        Its name in the error message.

    Returns
    -------
    ndarray, shape (3, 3)
        ``x`` as float64.

    Raises
    ------
    ValueError
        If ``x`` is not of shape (3, 3).
    """
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {a.shape}")
    return a


def rotvec_to_matrix(rv: ArrayLike) -> Array:
    """Rotation matrices from rotation vectors, shape (..., 3) -> (..., 3, 3).

    Parameters
    ----------
    rv : array_like, shape (..., 3)
        Rotation vectors (axis times angle), radians.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        The rotation matrices (dimensionless).
    """
    r = np.asarray(rv, dtype=np.float64)
    return Rotation.from_rotvec(r.reshape(-1, 3)).as_matrix().reshape(*r.shape[:-1], 3, 3)


#: Largest ``|R R^T - I|`` entry of a matrix :func:`matrix_to_rotvec` takes as a rotation without projecting it.
ROTATION_TOLERANCE = 1e-10


def matrix_to_rotvec(R: ArrayLike) -> Array:
    """Rotation vectors from rotation matrices, shape (..., 3, 3) -> (..., 3).

    A matrix that is not a rotation to :data:`ROTATION_TOLERANCE` is first replaced by the nearest rotation
    (SciPy's projection). SciPy tests every matrix for that itself, at several times the cost of the conversion;
    the test is made here once, vectorised, and the conversion then skips it (``assume_valid``: the same
    algorithm, bit for bit the same rotation vectors): fits evaluate this thousands of times per calibration.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Rotation matrices (dimensionless).

    Returns
    -------
    ndarray, shape (..., 3)
        Rotation vectors (axis times angle), radians, angle in [0, pi].
    """
    m = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    off = m @ np.swapaxes(m, -1, -2)
    off -= _EYE3
    valid = bool(np.abs(off).max(initial=0.0) <= ROTATION_TOLERANCE) and bool(np.all(np.linalg.det(m) > 0))
    rv = Rotation.from_matrix(m, assume_valid=valid).as_rotvec()
    return rv.reshape(*np.shape(R)[:-2], 3)


_EYE3 = np.eye(3)


def so3_left_jacobian(rv: ArrayLike) -> Array:
    """Left Jacobian of SO(3), shape (..., 3) -> (..., 3, 3): ``exp(rv + d) = exp(J_l(rv) d) exp(rv)`` to first order.

    ``J_l(phi) = I + (1 - cos a) / a^2 [phi]x + (a - sin a) / a^3 [phi]x^2`` with ``a = |phi|`` (series below 1e-4 rad).

    Parameters
    ----------
    rv : array_like, shape (..., 3)
        Rotation vectors ``phi``, radians.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``J_l(phi)`` (dimensionless).
    """
    phi = np.asarray(rv, dtype=np.float64)
    a2 = np.sum(phi * phi, axis=-1)[..., None, None]
    a = np.sqrt(a2)
    small = a < 1e-4
    safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a2 / 120.0, (safe - np.sin(safe)) / safe**3)
    K = skew(phi)
    return np.eye(3) + c1 * K + c2 * (K @ K)


def so3_left_jacobian_inverse(rv: ArrayLike) -> Array:
    """Inverse of :func:`so3_left_jacobian`, shape (..., 3) -> (..., 3, 3): ``d log(exp(d) exp(phi)) / d d``.

    ``J_l^-1(phi) = I - [phi]x / 2 + (1 / a^2 - (1 + cos a) / (2 a sin a)) [phi]x^2`` (series below 1e-4 rad;
    valid for ``a < pi``).

    Parameters
    ----------
    rv : array_like, shape (..., 3)
        Rotation vectors ``phi``, radians, ``|phi| < pi``.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``J_l(phi)^-1`` (dimensionless).
    """
    phi = np.asarray(rv, dtype=np.float64)
    a2 = np.sum(phi * phi, axis=-1)[..., None, None]
    a = np.sqrt(a2)
    small = a < 1e-4
    safe = np.where(small, 1.0, a)
    c2 = np.where(small, 1.0 / 12.0 + a2 / 720.0, 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    K = skew(phi)
    return np.eye(3) - 0.5 * K + c2 * (K @ K)


def rot_z(theta: ArrayLike) -> Array:
    """Rotation about z by ``theta`` radians, shape (...,) -> (..., 3, 3).

    Parameters
    ----------
    theta : array_like, shape (...,)
        Angles, radians.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        The rotation matrices.
    """
    th = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(th), np.sin(th)
    R = np.zeros((*th.shape, 3, 3))
    R[..., 0, 0] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 1, 1] = c
    R[..., 2, 2] = 1.0
    return R


def skew(v: ArrayLike) -> Array:
    """Cross-product matrices ``[v]x`` (``[v]x w = v x w``), shape (..., 3) -> (..., 3, 3).

    Parameters
    ----------
    v : array_like, shape (..., 3)
        Vectors (any unit).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        The skew-symmetric matrices, in the unit of ``v``.

    Raises
    ------
    ValueError
        If the last axis of ``v`` is not 3.
    """
    v = np.asarray(v, dtype=np.float64)
    if v.shape[-1:] != (3,):
        raise ValueError(f"v must have shape (..., 3), got {v.shape}")
    K = np.zeros((*v.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def cross(a: ArrayLike, b: ArrayLike) -> Array:
    """Cross product over the last axis, shapes (..., 3) broadcast -> (..., 3): ``np.cross``'s numbers.

    The same products and differences as ``np.cross`` (bit for bit), without its axis bookkeeping: ~10x faster on
    single 3-vectors, which the per-rod and per-candidate geometry computes by the thousand.

    Parameters
    ----------
    a, b : array_like, shape (..., 3)
        The factors (any unit), broadcast against each other.

    Returns
    -------
    ndarray, shape (..., 3)
        ``a x b``, in the product of their units.

    Raises
    ------
    ValueError
        If either last axis is not 3.
    """
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    if x.shape[-1:] != (3,) or y.shape[-1:] != (3,):
        raise ValueError(f"cross needs (..., 3) arrays, got {x.shape} and {y.shape}")
    if x.ndim == 1 and y.ndim == 1:
        x0, x1, x2 = x
        y0, y1, y2 = y
        return np.array([x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0])
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    y0, y1, y2 = y[..., 0], y[..., 1], y[..., 2]
    return np.stack([x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0], axis=-1)


def unit(v: ArrayLike, axis: int = -1) -> Array:
    """Vectors scaled to unit norm along ``axis``.

    Parameters
    ----------
    v : array_like, shape (..., K)
        Non-zero vectors (any unit).
    axis : int, optional
        The axis holding the components (last by default).

    Returns
    -------
    ndarray, same shape as ``v``
        The unit vectors (dimensionless).
    """
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a, axis=axis, keepdims=True)


def orthonormalize(R: ArrayLike) -> Array:
    """Nearest rotation matrix (SVD).

    Parameters
    ----------
    R : array_like, shape (3, 3)
        An almost-rotation (dimensionless).

    Returns
    -------
    ndarray, shape (3, 3)
        The proper rotation nearest to ``R`` in the Frobenius norm.
    """
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    M = U @ Vt
    if np.linalg.det(M) < 0:
        U[:, -1] *= -1
        M = U @ Vt
    return M


def kabsch(to_vectors: ArrayLike, from_vectors: ArrayLike, weights: ArrayLike | None = None) -> Array:
    """Rotation ``R`` minimising ``sum_k w_k |R from_k - to_k|^2`` (Wahba's problem), via SciPy.

    Parameters
    ----------
    to_vectors, from_vectors : array_like, shape (N, 3)
        Corresponding vectors (directions, or points already centred on their centroids).
    weights : array_like, shape (N,), optional
        Non-negative weights (e.g. ``1 / sigma_k^2``); equal by default.

    Returns
    -------
    ndarray, shape (3, 3)
        The proper rotation matrix ``to_from_from``.
    """
    a = np.asarray(to_vectors, dtype=np.float64)
    b = np.asarray(from_vectors, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        raise ValueError(f"kabsch needs two (N, 3) arrays of the same shape, got {a.shape} and {b.shape}")
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    if len(a) == 1:  # one pair: SciPy's minimal rotation (the fit is not unique anyway)
        return Rotation.align_vectors(a, b)[0].as_matrix()
    return Rotation.align_vectors(a, b, weights=w)[0].as_matrix()


def kabsch_points(to_points: ArrayLike, from_points: ArrayLike) -> Array:
    """Rotation ``R`` of the rigid map ``to = R from + t`` fitting two (N, 3) point sets in least squares.

    Parameters
    ----------
    to_points, from_points : array_like, shape (N, 3)
        Corresponding points (metres, or any common unit).

    Returns
    -------
    ndarray, shape (3, 3)
        The rotation ``to_from_from``; ``t`` is ``mean(to) - R mean(from)``.
    """
    P = np.asarray(from_points, dtype=np.float64)
    Q = np.asarray(to_points, dtype=np.float64)
    return kabsch(Q - Q.mean(axis=0), P - P.mean(axis=0))


def tangent_basis(u: ArrayLike) -> Array:
    """Orthonormal basis of the plane normal to the direction ``u``.

    Parameters
    ----------
    u : array_like, shape (3,) or (..., 3)
        Direction(s), normalised here.

    Returns
    -------
    ndarray, shape (3, 2) or (..., 3, 2)
        Columns ``e1, e2`` with ``e1 x e2 = u / |u|``: tangent coordinates of a small direction change are
        ``T.T @ du``.
    """
    n = unit(np.asarray(u, dtype=np.float64))
    # a helper axis far from n: the coordinate axis of n's smallest component
    helper = np.zeros_like(n)
    np.put_along_axis(helper, np.argmin(np.abs(n), axis=-1)[..., None], 1.0, axis=-1)
    e1 = unit(cross(helper, n))
    e2 = cross(n, e1)
    return np.stack([e1, e2], axis=-1)


@dataclass(frozen=True)
class Rigid:
    """A rigid transform ``a_from_b``: ``p_a = R p_b + t`` (metres)."""

    R: Array
    t: Array

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", as_mat3(self.R, "R"))
        object.__setattr__(self, "t", as_vec3(self.t, "t"))

    @classmethod
    def identity(cls) -> Rigid:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_rotvec(cls, rotvec: ArrayLike, t: ArrayLike) -> Rigid:
        """The transform of a rotation vector and a translation.

        Parameters
        ----------
        rotvec : array_like, shape (3,)
            Rotation vector, radians.
        t : array_like, shape (3,)
            Translation, metres.

        Returns
        -------
        Rigid
            ``p_a = exp([rotvec]x) p_b + t``.
        """
        return cls(rotvec_to_matrix(as_vec3(rotvec, "rotvec")), as_vec3(t, "t"))

    def inverse(self) -> Rigid:
        return Rigid(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Rigid) -> Rigid:
        return Rigid(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, p: ArrayLike) -> Array:
        """Map points of shape (..., 3).

        Parameters
        ----------
        p : array_like, shape (..., 3)
            Points in frame b, metres.

        Returns
        -------
        ndarray, shape (..., 3)
            The same points in frame a, metres.
        """
        return np.asarray(p, dtype=np.float64) @ self.R.T + self.t

    def to_dict(self) -> dict[str, list]:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Rigid:
        """The transform of :meth:`to_dict`'s mapping.

        Parameters
        ----------
        d : dict
            ``{"R": 3x3 nested list (dimensionless), "t": 3-list (metres)}``.

        Returns
        -------
        Rigid
            The transform.
        """
        return cls(np.asarray(d["R"], dtype=np.float64), np.asarray(d["t"], dtype=np.float64))
