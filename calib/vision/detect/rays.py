"""Small image and ray geometry shared by the detection steps (canvas sampling, rays, limb planes, line points)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.numerics.transforms import matrix_to_rotvec
from calib.vision.detect.hypotheses import Line2

Array = NDArray[np.float64]


def _sample(img: np.ndarray, pts: Array) -> Array:
    """Bilinear samples of img at canvas points (..., 2)."""
    p = pts.reshape(-1, 2).astype(np.float32)
    n = len(p)
    cols = 1024  # remap's maps must stay below 32767 in both dimensions
    rows = max(1, -(-n // cols))
    m = np.zeros((rows * cols, 2), dtype=np.float32)
    m[:n] = p
    out = cv2.remap(
        img, m[:, 0].reshape(rows, cols), m[:, 1].reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.ravel()[:n].reshape(pts.shape[:-1]).astype(np.float64)


def _to_canvas(p: Array, scale: float, origin: Array) -> Array:
    return (p - origin) * scale


def _ray(K_inv: Array, p: Array) -> Array:
    return K_inv @ np.array([p[0], p[1], 1.0])


def _plane(K: Array, line: Array) -> Array:
    """Unit normal of the interpretation plane of an ideal-pixel line (a, b, c)."""
    h = K.T @ line
    return h / np.linalg.norm(h)


def _line_point(line: Line2, s: float, t: Array) -> Array:
    """The point of ``line`` at abscissa ``s`` along the unit direction ``t`` (ideal px)."""
    nrm = np.array([-t[1], t[0]])
    den = line.n @ nrm
    k = -(line.c + s * (line.n @ t)) / den
    return s * t + k * nrm


def _rotation_angle(Ra: Array, Rb: Array) -> float:
    return float(np.linalg.norm(matrix_to_rotvec(Ra @ Rb.T)))
