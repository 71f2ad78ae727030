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
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {a.shape}")
    return a


def as_mat3(x: ArrayLike, name: str) -> Array:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {a.shape}")
    return a


def rotvec_to_matrix(rv: ArrayLike) -> Array:
    """Rotation matrices from rotation vectors, shape (..., 3) -> (..., 3, 3)."""
    r = np.asarray(rv, dtype=np.float64)
    return Rotation.from_rotvec(r.reshape(-1, 3)).as_matrix().reshape(*r.shape[:-1], 3, 3)


def matrix_to_rotvec(R: ArrayLike) -> Array:
    """Rotation vectors from rotation matrices, shape (..., 3, 3) -> (..., 3)."""
    m = np.asarray(R, dtype=np.float64)
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(*m.shape[:-2], 3)


def rot_z(theta: ArrayLike) -> Array:
    """Rotation about z by ``theta`` radians, shape (...,) -> (..., 3, 3)."""
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
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def unit(v: ArrayLike, axis: int = -1) -> Array:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a, axis=axis, keepdims=True)


def orthonormalize(R: ArrayLike) -> Array:
    """Nearest rotation matrix (SVD)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    M = U @ Vt
    if np.linalg.det(M) < 0:
        U[:, -1] *= -1
        M = U @ Vt
    return M


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
        return cls(rotvec_to_matrix(as_vec3(rotvec, "rotvec")), as_vec3(t, "t"))

    def inverse(self) -> Rigid:
        return Rigid(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Rigid) -> Rigid:
        return Rigid(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, p: ArrayLike) -> Array:
        """Map points of shape (..., 3)."""
        return np.asarray(p, dtype=np.float64) @ self.R.T + self.t

    def to_dict(self) -> dict[str, list]:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Rigid:
        return cls(np.asarray(d["R"], dtype=np.float64), np.asarray(d["t"], dtype=np.float64))
