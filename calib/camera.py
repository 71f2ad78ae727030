"""Camera model (pinhole + OpenCV distortion) and intrinsic calibration with ``cv2.calibrateCameraRO``.

Conventions: pixel coordinates ``(u, v)`` with the origin at the centre of the top-left pixel
(OpenCV's); normalized coordinates ``(x, y) = (X/Z, Y/Z)`` of a point ``(X, Y, Z)`` in the camera
frame (metres; z along the optical axis). "Ideal pixels" are undistorted pixel coordinates
``K (x, y, 1)``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

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
        """Project camera-frame points (metres), shape (N, 3) -> pixels (N, 2), with distortion."""
        p = np.asarray(points_cam, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points_cam must have shape (N, 3), got {p.shape}")
        if p.shape[0] == 0:
            return np.zeros((0, 2))
        return self.distort_normalized(p[:, :2] / p[:, 2:3])

    def distort_normalized(self, xn: ArrayLike) -> Array:
        """Normalized coordinates (N, 2) -> distorted pixels (N, 2) (OpenCV's model, vectorised)."""
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
        """Distorted pixels (N, 2) -> normalized coordinates (N, 2) (iterative inverse, converged)."""
        px = _points2(pixels, "pixels")
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        out = cv2.undistortPointsIter(px.reshape(-1, 1, 2), self.K, self.dist, None, None, _UNDISTORT_CRITERIA)
        return out.reshape(-1, 2).astype(np.float64)

    def to_ideal_pixels(self, xn: ArrayLike) -> Array:
        """Normalized coordinates (N, 2) -> undistorted ("ideal") pixels (N, 2)."""
        xy = _points2(xn, "xn")
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def from_ideal_pixels(self, uv: ArrayLike) -> Array:
        """Undistorted ("ideal") pixels (N, 2) -> normalized coordinates (N, 2)."""
        p = _points2(uv, "uv")
        Kinv = np.linalg.inv(self.K)
        return p @ Kinv[:2, :2].T + Kinv[:2, 2]

    def normalized_bounds(self, margin_px: float = 0.0) -> Array:
        """Normalized coordinates of points along the image border, shape (M, 2) (a closed polygon)."""
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
        from .jsonio import write_json_atomic

        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> CameraModel:
        from .jsonio import read_json

        return cls.from_dict(read_json(path), source=str(path))


# ---------------------------------------------------------------------------------------------
@dataclass
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    camera : CameraModel
    rms_px : float
        RMS reprojection error over the kept views, pixels.
    per_view_rms_px : dict[int, float]
        Per kept view (keyed by the caller's view key), pixels.
    std : dict[str, float]
        Standard deviations of fx, fy, cx, cy (pixels) and the distortion coefficients.
    rejected : dict[int, str]
        Views not used, with the reason.
    board_points : ndarray, shape (M, 3)
        The board's corner coordinates (metres) as refined by ``calibrateCameraRO``.
    board_ids : ndarray, shape (M,)
        ChArUco corner ids of ``board_points``.
    view_poses : dict[int, tuple[ndarray, ndarray]]
        Per kept view, ``camera_from_board`` as (rvec (3,), tvec (3,)).
    """

    camera: CameraModel
    rms_px: float
    per_view_rms_px: dict[int, float]
    std: dict[str, float]
    rejected: dict[int, str]
    board_points: Array
    board_ids: NDArray[np.int_]
    view_poses: dict[int, tuple[Array, Array]]

    def summary(self) -> dict[str, Any]:
        return {
            "rms_px": self.rms_px,
            "per_view_rms_px": {str(k): v for k, v in self.per_view_rms_px.items()},
            "std": self.std,
            "rejected": {str(k): v for k, v in self.rejected.items()},
            "n_views": len(self.per_view_rms_px),
        }


@contextlib.contextmanager
def opencv_single_thread() -> Iterator[None]:
    """Run OpenCV single-threaded inside the block (the process-wide thread count is restored after).

    ``cv2.calibrateCameraRO`` gives results that differ in the last digits from one process to the next
    when OpenCV runs several threads (measured: fx by ~2e-7 px, enough for a whole extraction to differ
    after the rods' refinement and its second pass); single-threaded it is bit-reproducible.
    """
    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(n)


def calibrate_intrinsics(
    views: dict[int, tuple[ArrayLike, ArrayLike, ArrayLike]],
    image_size: tuple[int, int],
    board_ids: ArrayLike,
    board_points: ArrayLike,
    *,
    min_views: int = 5,
    outlier_factor: float = 3.0,
    outlier_floor_px: float = 1.0,
    fix_k3: bool = True,
    refine_object: bool = True,
) -> IntrinsicsResult:
    """Intrinsic calibration from ChArUco views, refining the board's geometry (``calibrateCameraRO``).

    ``calibrateCameraRO`` (Strobl & Hirzinger's "releasing object" method) needs the same object
    points in every view: only views where every corner of the board was detected are used, the
    others are rejected with the reason. Views whose RMS reprojection error exceeds
    ``max(outlier_factor * median, outlier_floor_px)`` are rejected and the calibration is redone.

    Parameters
    ----------
    views : dict[int, (ids, image_points, unused)]
        Per view key: detected corner ids (M,), their pixels (M, 2), and a free slot (ignored).
    image_size : (width, height)
    board_ids : array_like, shape (M,)
        All corner ids of the board.
    board_points : array_like, shape (M, 3)
        Nominal corner coordinates in the board frame, metres.

    Raises
    ------
    InputError
        Fewer than ``min_views`` usable views.
    """
    ids_all = np.asarray(board_ids, dtype=int).reshape(-1)
    obj_nom = np.asarray(board_points, dtype=np.float64).reshape(-1, 3)
    if obj_nom.shape[0] != ids_all.size:
        raise ValueError(f"board_points must have shape ({ids_all.size}, 3), got {obj_nom.shape}")
    rejected: dict[int, str] = {}
    keep: dict[int, Array] = {}
    for key, (ids, img, _unused) in views.items():
        ids = np.asarray(ids, dtype=int).reshape(-1)
        img = np.asarray(img, dtype=np.float64).reshape(-1, 2)
        if ids.size != ids_all.size or set(ids.tolist()) != set(ids_all.tolist()):
            rejected[key] = (
                f"partial board ({ids.size} of {ids_all.size} corners); calibrateCameraRO needs "
                "every corner in every view"
            )
            continue
        order = np.argsort(ids)
        keep[key] = img[order]
    sort_ids = np.sort(ids_all)
    obj = obj_nom[np.argsort(ids_all)]
    w, h = image_size
    ncols = int(np.sum(np.isclose(obj[:, 1], obj[0, 1])))
    fixed = ncols - 1 if refine_object and ncols > 1 else -1
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    for _ in range(5):
        if len(keep) < min_views:
            raise InputError(
                f"intrinsic calibration needs at least {min_views} full-board views, got {len(keep)}"
                + (f" ({len(rejected)} rejected)" if rejected else ""),
                field="camera",
            )
        keys = list(keep)
        objp = [obj.astype(np.float32).reshape(-1, 1, 3) for _ in keys]
        imgp = [keep[k].astype(np.float32).reshape(-1, 1, 2) for k in keys]
        with opencv_single_thread():  # bit-reproducible: OpenCV's threads change the result in the last digits
            ret = cv2.calibrateCameraROExtended(
                objp,
                imgp,
                (w, h),
                fixed,
                None,
                None,
                flags=flags,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12),
            )
        rms, K, dist, rvecs, tvecs, new_obj, std_int, _std_ext, _std_obj, per_view = ret
        per_view = np.asarray(per_view).reshape(-1)
        med = float(np.median(per_view))
        limit = max(outlier_factor * med, outlier_floor_px)
        bad = [k for k, e in zip(keys, per_view, strict=True) if e > limit]
        if not bad:
            break
        worst = keys[int(np.argmax(per_view))]
        rejected[worst] = (
            f"outlier view: reprojection RMS {float(per_view.max()):.2f} px > limit {limit:.2f} px "
            f"(median {med:.2f} px)"
        )
        del keep[worst]
    std_int = np.asarray(std_int).reshape(-1)
    new_obj = np.asarray(new_obj, dtype=np.float64).reshape(-1, 3) if new_obj is not None and np.size(new_obj) else obj
    cov, d_board = _bundle_covariance(
        K, np.asarray(dist).reshape(-1), new_obj, [keep[k] for k in keys], rvecs, tvecs, fixed_point=fixed
    )
    names = [
        "fx",
        "fy",
        "cx",
        "cy",
        "k1",
        "k2",
        "p1",
        "p2",
        "k3",
        "k4",
        "k5",
        "k6",
        "s1",
        "s2",
        "s3",
        "s4",
        "tau_x",
        "tau_y",
    ]
    std = {n: float(s) for n, s in zip(names, std_int, strict=False)}
    cam = CameraModel(
        K,
        np.asarray(dist).reshape(-1),
        int(w),
        int(h),
        {
            "calibration": {
                "rms_px": float(rms),
                "n_views": len(keys),
                "std": std,
                "covariance_params": list(INTRINSICS_NAMES),
                "covariance": cov.tolist(),
                "method": "cv2.calibrateCameraRO",
                "board_points": {
                    "ids": sort_ids.tolist(),
                    "points_m": new_obj.tolist(),
                    "d_intrinsics": d_board.tolist(),
                },
            }
        },
    )
    return IntrinsicsResult(
        cam,
        float(rms),
        {k: float(e) for k, e in zip(keys, per_view, strict=True)},
        std,
        rejected,
        new_obj,
        sort_ids,
        {k: (np.asarray(r).reshape(3), np.asarray(t).reshape(3)) for k, r, t in zip(keys, rvecs, tvecs, strict=True)},
    )


#: Intrinsic parameters whose joint covariance :func:`intrinsics_covariance` gives, in this order.
INTRINSICS_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")


def intrinsics_covariance(
    K: ArrayLike,
    dist: ArrayLike,
    board_points: ArrayLike,
    image_points: list[ArrayLike],
    rvecs: list[ArrayLike],
    tvecs: list[ArrayLike],
    fixed_point: int = -1,
) -> Array:
    """Joint covariance (8, 8) of (fx, fy, cx, cy [px], k1, k2, p1, p2) after a calibration.

    Gauss-Newton covariance ``s^2 (J^T J)^-1`` of the full bundle (intrinsics, every view's pose and,
    with the releasing-object method, the board's points), marginalised to the intrinsics (Schur
    complement), ``s^2`` the residual variance per coordinate. The board points' gauge is OpenCV's
    (``calibrateCameraRO``): the first point, the ``fixed_point``-th one and the last one's z are fixed.
    k3 and higher coefficients are taken as fixed (``CALIB_FIX_K3``). OpenCV returns only the
    standard deviations; the correlations (fx with fy, the principal point with the tangential
    coefficients, ...) matter when the uncertainty is propagated to a calibration.

    Parameters
    ----------
    K : array_like, shape (3, 3)
    dist : array_like, shape (n,)
    board_points : array_like, shape (M, 3)
        Board points (metres) as the calibration used them (refined when ``fixed_point >= 0``).
    image_points : list of array_like, shape (M, 2)
        Per view, the detected pixels in the order of ``board_points``.
    rvecs, tvecs : list of array_like, shape (3,)
        Per view, ``camera_from_board``.
    fixed_point : int
        ``iFixedPoint`` of the releasing-object method, or -1 when the board points were not refined.

    Returns
    -------
    ndarray, shape (8, 8)
        Pixels for fx, fy, cx, cy; dimensionless for the distortion coefficients.
    """
    return _bundle_covariance(K, dist, board_points, image_points, rvecs, tvecs, fixed_point)[0]


def _bundle_covariance(
    K: ArrayLike,
    dist: ArrayLike,
    board_points: ArrayLike,
    image_points: list[ArrayLike],
    rvecs: list[ArrayLike],
    tvecs: list[ArrayLike],
    fixed_point: int = -1,
) -> tuple[Array, Array]:
    """:func:`intrinsics_covariance` and the board points' regression on the intrinsics, (M, 3, 8).

    The regression ``Cov(X, I) Cov(I, I)^-1`` is how the refined board points move when the
    intrinsics do, given the calibration's data (Gaussian conditioning): when other measurements
    (the rods) correct the intrinsics, the board geometry estimated jointly with them follows.
    Zero for the fixed coordinates and without the releasing-object method.
    """
    K = np.asarray(K, dtype=np.float64)
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    obj = np.asarray(board_points, dtype=np.float64).reshape(-1, 3)
    m = obj.shape[0]
    nv = len(image_points)
    ro = 0 <= fixed_point < m
    free_obj = np.ones((m, 3), dtype=bool) if ro else np.zeros((m, 3), dtype=bool)
    if ro:
        free_obj[0] = free_obj[fixed_point] = False
        free_obj[m - 1, 2] = False
    obj_cols = np.flatnonzero(free_obj.ravel())
    n_obj = obj_cols.size
    n = 8 + 6 * nv + n_obj
    JtJ = np.zeros((n, n))
    sse = 0.0
    for v in range(nv):
        proj, jac = cv2.projectPoints(
            obj,
            np.asarray(rvecs[v], dtype=np.float64).reshape(3),
            np.asarray(tvecs[v], dtype=np.float64).reshape(3),
            K,
            d,
        )
        res = proj.reshape(-1, 2) - np.asarray(image_points[v], dtype=np.float64).reshape(-1, 2)
        sse += float(np.sum(res**2))
        # projectPoints' Jacobian columns: rvec (3), tvec (3), f (2), c (2), dist (n)
        J = np.zeros((2 * m, n))
        J[:, 0:4] = jac[:, 6:10]
        J[:, 4:8] = jac[:, 10:14]
        J[:, 8 + 6 * v : 14 + 6 * v] = jac[:, 0:6]
        if n_obj:
            R, _ = cv2.Rodrigues(np.asarray(rvecs[v], dtype=np.float64).reshape(3))
            dp_dX = jac[:, 3:6].reshape(m, 2, 3) @ R  # d pixel / d board point: d/dt rotated
            blocks = np.zeros((2 * m, 3 * m))
            for i in range(m):
                blocks[2 * i : 2 * i + 2, 3 * i : 3 * i + 3] = dp_dX[i]
            J[:, 8 + 6 * nv :] = blocks[:, obj_cols]
        JtJ += J.T @ J
    dof = max(2 * m * nv - n, 1)
    s2 = sse / dof
    A, B, C = JtJ[:8, :8], JtJ[:8, 8:], JtJ[8:, 8:]
    CinvBt = np.linalg.solve(C, B.T)  # (n - 8, 8)
    schur = A - B @ CinvBt
    cov = s2 * np.linalg.inv(schur)
    # Cov(others, I) = -C^-1 B^T Cov(I, I): the regression of the others on I is -C^-1 B^T
    reg = np.zeros((m * 3, 8))
    if n_obj:
        reg[obj_cols] = -CinvBt[6 * nv :]
    return 0.5 * (cov + cov.T), reg.reshape(m, 3, 8)
