"""Rod geometry (the paper's eqs. 6-7): the limb planes of a cylinder seen from the camera centre, the axis from two
planes, the rods' names.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.numerics.transforms import cross

Array = NDArray[np.float64]


_CORR = 1.0
ROD_KEYS = [(leg, rod) for leg in range(4) for rod in range(2)]


def rod_name(leg: int, rod: int) -> str:
    """``leg{1..4}.rod{0,1}`` for 0-based leg index and rod index.

    Parameters
    ----------
    leg : int
        Leg index, 0 to 3.
    rod : int
        Rod index within the leg, 0 or 1.

    Returns
    -------
    str
        For example ``"leg1.rod0"``.
    """
    return f"leg{leg + 1}.rod{rod}"


# ---------------------------------------------------------------------------------------------
# geometry
def norm3(v: Array) -> float:
    """Euclidean norm of a 1-D float64 vector: ``np.linalg.norm(v)``'s number (the square root of ``v.dot(v)``),
    without its overhead.

    Parameters
    ----------
    v : ndarray, shape (N,)
        The vector (any unit).

    Returns
    -------
    float
        Its norm (the vector's unit).
    """
    return math.sqrt(v.dot(v))


def limb_planes(point: ArrayLike, u: ArrayLike, radius: float) -> tuple[Array, Array]:
    """Unit normals of the two tangent planes through the camera centre (eq. 6), each shape (3,).

    Signs: ``h . X = +radius`` for every axis point X.

    Parameters
    ----------
    point : array_like, shape (3,)
        A point of the rod's axis in the camera frame (metres).
    u : array_like, shape (3,)
        The axis direction (any length; normalised here).
    radius : float
        Rod radius (metres).

    Returns
    -------
    h1, h2 : ndarray, shape (3,)
        Unit normals (dimensionless) of the two planes.

    Raises
    ------
    ValueError
        The camera centre is inside the cylinder.
    """
    P = np.asarray(point, dtype=np.float64).reshape(3)
    uu = np.asarray(u, dtype=np.float64).reshape(3)
    uu = uu / norm3(uu)
    p = P - (P @ uu) * uu
    d = norm3(p)
    if d <= radius:
        raise ValueError(f"camera centre inside the cylinder (distance {d:.4g} m <= radius {radius:.4g} m)")
    e1 = p / d
    e2 = cross(uu, e1)
    c = radius / d
    s = np.sqrt(1.0 - c * c)
    return c * e1 + s * e2, c * e1 - s * e2


def axis_from_planes(h1: ArrayLike, h2: ArrayLike, radius: float | None) -> tuple[Array, Array | None]:
    """Axis direction (eq. 7) and, with the radius, the axis point closest to the camera centre.

    Parameters
    ----------
    h1, h2 : array_like, shape (3,)
        Interpretation-plane normals, signed so that the axis is on their positive side.
    radius : float or None
        Rod radius, metres.

    Returns
    -------
    u : ndarray, shape (3,)
        Unit direction (sign: h1 x h2).
    point : ndarray, shape (3,) or None
        Metres, camera frame.
    """
    a = np.asarray(h1, dtype=np.float64).reshape(3)
    b = np.asarray(h2, dtype=np.float64).reshape(3)
    a = a / norm3(a)
    b = b / norm3(b)
    u = cross(a, b)
    n = norm3(u)
    if n < 1e-12:
        raise ValueError("interpretation planes are parallel: no axis")
    u = u / n
    if radius is None:
        return u, None
    M = np.vstack([a, b, u])
    X = np.linalg.solve(M, np.array([radius, radius, 0.0]))
    return u, X


def axis_point_seen_along(point: ArrayLike, u: ArrayLike, ray: ArrayLike) -> Array:
    """The point of each axis (``point + t u``) nearest the ray from the camera centre along ``ray``.

    What a rod's measurement reports as its point: the axis point seen at the middle of its visible limbs (``ray``
    through their centre line there), not the point nearest the camera centre, which for a rod seen obliquely lies
    far outside the image. An axis along the ray keeps ``point``.

    Parameters
    ----------
    point, u, ray : array_like, shape (..., 3)
        An axis point (m, camera frame), the axis's unit direction, and the ray's direction (any length).

    Returns
    -------
    ndarray, shape (..., 3)
        Metres, camera frame.
    """
    X = np.asarray(point, dtype=np.float64)
    uu = np.asarray(u, dtype=np.float64)
    r = np.asarray(ray, dtype=np.float64)
    r = r / np.linalg.norm(r, axis=-1, keepdims=True)
    w = uu - np.sum(uu * r, axis=-1, keepdims=True) * r
    ww = np.sum(w * w, axis=-1, keepdims=True)
    t = np.where(ww > 1e-12, np.sum(X * w, axis=-1, keepdims=True) / np.maximum(ww, 1e-12), 0.0)
    return X - t * uu
