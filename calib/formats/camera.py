"""The camera model and its file (``i4cal.camera/1``): a pinhole camera with OpenCV's distortion model.

Conventions: pixel coordinates ``(u, v)`` with the origin at the centre of the top-left pixel
(OpenCV's); normalized coordinates ``(x, y) = (X/Z, Y/Z)`` of a point ``(X, Y, Z)`` in the camera
frame (metres; z along the optical axis). "Ideal pixels" are undistorted pixel coordinates
``K (x, y, 1)``. The intrinsic calibration that fills it is :mod:`calib.vision.camera.intrinsics`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.errors import InputError

Array = NDArray[np.float64]

CAMERA_FORMAT = "i4cal.camera/1"
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)


def _points2(x: ArrayLike, name: str) -> Array:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {a.shape}")
    return a


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera with OpenCV's distortion model.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix, pixels.
    dist : ndarray, shape (n,)
        OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, ...]])``; n in {4, 5, 8, 12, 14}.
    width, height : int
        Image size, pixels.
    """

    K: Array
    dist: Array
    width: int
    height: int
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must have shape (3, 3), got {K.shape}")
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if d.size not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"dist must have 4, 5, 8, 12 or 14 coefficients, got shape {d.shape}")
        if d.size == 0:
            d = np.zeros(5)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)

    # -- accessors ------------------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (int(self.width), int(self.height))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def focal_px(self) -> float:
        """Mean focal length, pixels."""
        return 0.5 * (self.fx + self.fy)

    # -- projection ----------------------------------------------------------------------------
    def project(self, points_cam: ArrayLike) -> Array:
        """Project camera-frame points to pixels, with distortion.

        Parameters
        ----------
        points_cam : array_like, shape (N, 3)
            Points in the camera frame, metres (z > 0 in front of the camera).

        Returns
        -------
        ndarray, shape (N, 2)
            Distorted pixel coordinates.
        """
        p = np.asarray(points_cam, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points_cam must have shape (N, 3), got {p.shape}")
        if p.shape[0] == 0:
            return np.zeros((0, 2))
        return self.distort_normalized(p[:, :2] / p[:, 2:3])

    def distort_normalized(self, xn: ArrayLike) -> Array:
        """Normalized coordinates to distorted pixels (OpenCV's model, vectorised).

        Parameters
        ----------
        xn : array_like, shape (N, 2)
            Normalized coordinates ``(X/Z, Y/Z)``, dimensionless.

        Returns
        -------
        ndarray, shape (N, 2)
            Distorted pixel coordinates.
        """
        xy = _points2(xn, "xn")
        d = np.zeros(14)
        d[: self.dist.size] = self.dist
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
        K = self.K
        return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])

    def undistort_points(self, pixels: ArrayLike) -> Array:
        """Distorted pixels to normalized coordinates (``cv2.undistortPointsIter``, iterated to convergence).

        Parameters
        ----------
        pixels : array_like, shape (N, 2)
            Distorted pixel coordinates.

        Returns
        -------
        ndarray, shape (N, 2)
            Normalized coordinates ``(X/Z, Y/Z)``, dimensionless.
        """
        px = _points2(pixels, "pixels")
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        # OpenCV's stubs do not allow None for R and P, which the function takes (no rectification, normalized out)
        out = cv2.undistortPointsIter(  # type: ignore[call-overload]
            px.reshape(-1, 1, 2), self.K, self.dist, None, None, _UNDISTORT_CRITERIA
        )
        return out.reshape(-1, 2).astype(np.float64)

    def to_ideal_pixels(self, xn: ArrayLike) -> Array:
        """Normalized coordinates to undistorted ("ideal") pixels ``K (x, y, 1)``.

        Parameters
        ----------
        xn : array_like, shape (N, 2)
            Normalized coordinates, dimensionless.

        Returns
        -------
        ndarray, shape (N, 2)
            Ideal pixels.
        """
        xy = _points2(xn, "xn")
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def from_ideal_pixels(self, uv: ArrayLike) -> Array:
        """Undistorted ("ideal") pixels to normalized coordinates ``K^-1 (u, v, 1)``.

        Parameters
        ----------
        uv : array_like, shape (N, 2)
            Ideal pixels.

        Returns
        -------
        ndarray, shape (N, 2)
            Normalized coordinates, dimensionless.
        """
        p = _points2(uv, "uv")
        Kinv = np.linalg.inv(self.K)
        return p @ Kinv[:2, :2].T + Kinv[:2, 2]

    def normalized_bounds(self, margin_px: float = 0.0) -> Array:
        """Normalized coordinates of points along the image border (a closed polygon).

        Parameters
        ----------
        margin_px : float
            Distance of the polygon inside the image's border, pixels.

        Returns
        -------
        ndarray, shape (132, 2)
            33 points per side (top, right, bottom, left), normalized coordinates.
        """
        w, h = self.width - 1.0, self.height - 1.0
        n = 33
        t = np.linspace(0.0, 1.0, n)
        m = margin_px
        top = np.column_stack([m + t * (w - 2 * m), np.full(n, m)])
        right = np.column_stack([np.full(n, w - m), m + t * (h - 2 * m)])
        bottom = np.column_stack([w - m - t * (w - 2 * m), np.full(n, h - m)])
        left = np.column_stack([np.full(n, m), h - m - t * (h - 2 * m)])
        return self.undistort_points(np.vstack([top, right, bottom, left]))

    # -- persistence ----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The camera as an ``i4cal.camera/1`` JSON object.

        Returns
        -------
        dict
            ``format``, ``width``, ``height`` (px), ``K`` (3 x 3, px), ``dist`` and the ``extra`` fields.
        """
        return {
            "format": CAMERA_FORMAT,
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            **self.extra,
        }

    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> CameraModel:
        """A camera from its ``i4cal.camera/1`` JSON object.

        Parameters
        ----------
        data : dict
            The object (:meth:`to_dict`'s layout; fields other than the camera's own kept in ``extra``).
        source : str, optional
            Where it was read, named in errors.

        Returns
        -------
        CameraModel

        Raises
        ------
        InputError
            Not an object, a missing field or an invalid value, naming ``source`` and the field.
        """
        if not isinstance(data, dict):
            raise InputError("camera must be a JSON object", file=source)
        try:
            extra = {k: v for k, v in data.items() if k not in ("format", "width", "height", "K", "dist")}
            return cls(
                np.asarray(data["K"], dtype=np.float64),
                np.asarray(data.get("dist") or [], dtype=np.float64),
                int(data["width"]),
                int(data["height"]),
                extra,
            )
        except KeyError as exc:
            raise InputError("missing field", file=source, field=str(exc.args[0])) from None
        except (TypeError, ValueError) as exc:
            raise InputError(str(exc), file=source) from None

    def save(self, path: str | Path) -> None:
        """Write the camera as ``i4cal.camera/1`` JSON (atomically).

        Parameters
        ----------
        path : str or Path
            The file to write.
        """
        from calib.numerics.jsonio import write_json_atomic

        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> CameraModel:
        """Read an ``i4cal.camera/1`` JSON file.

        Parameters
        ----------
        path : str or Path

        Returns
        -------
        CameraModel

        Raises
        ------
        InputError
            An unreadable file or an invalid camera, naming the file.
        """
        from calib.numerics.jsonio import read_json

        return cls.from_dict(read_json(path), source=str(path))
