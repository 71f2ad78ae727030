"""Camera model (pinhole + OpenCV distortion) and intrinsic calibration with ``cv2.calibrateCameraRO``.

Conventions: pixel coordinates ``(u, v)`` with the origin at the centre of the top-left pixel
(OpenCV's); normalized coordinates ``(x, y) = (X/Z, Y/Z)`` of a point ``(X, Y, Z)`` in the camera
frame (metres; z along the optical axis). "Ideal pixels" are undistorted pixel coordinates
``K (x, y, 1)``.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .bundle import DIST_INDEX, MIN_VIEW_DOF, REFINE_MAX_NFEV, Bundle, bundle_covariance, refine_weighted, view_dof
from .bundle import projection_columns as projection_columns
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
        # OpenCV's stubs do not allow None for R and P, which the function takes (no rectification, normalized out)
        out = cv2.undistortPointsIter(  # type: ignore[call-overload]
            px.reshape(-1, 1, 2), self.K, self.dist, None, None, _UNDISTORT_CRITERIA
        )
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
    #: the lens model chosen and its evidence (``calibration.lens_model`` of the camera file)
    lens_model: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        out = {
            "rms_px": self.rms_px,
            "per_view_rms_px": {str(k): v for k, v in self.per_view_rms_px.items()},
            "std": self.std,
            "rejected": {str(k): v for k, v in self.rejected.items()},
            "n_views": len(self.per_view_rms_px),
        }
        if self.lens_model is not None:
            out["lens_model"] = self.lens_model
        return out


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


#: Intrinsic parameters whose joint covariance :func:`intrinsics_covariance` gives by default, in this order (the
#: ``k1k2`` lens model's; a camera calibrated with another model lists its own, :func:`intrinsics_names`).
INTRINSICS_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")

#: Candidate lens models: the distortion coefficients each estimates (the others are zero). ``-radial``: no
#: tangential terms (p1 = p2 = 0). ``rational`` is OpenCV's ``CALIB_RATIONAL_MODEL`` (k1..k6).
LENS_MODELS: dict[str, tuple[str, ...]] = {
    "k1k2": ("k1", "k2", "p1", "p2"),
    "k1k2k3": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "k1k2-radial": ("k1", "k2"),
    "k1k2k3-radial": ("k1", "k2", "k3"),
    "rational-radial": ("k1", "k2", "k3", "k4", "k5", "k6"),
}
#: What ``lens_model`` accepts (``auto``: chosen from the board views, :func:`calibrate_intrinsics`).
LENS_MODEL_CHOICES = ("auto", *LENS_MODELS)
#: Board views that reach less than this fraction of the image's corner radius leave the distortion beyond them
#: extrapolated: said in the calibration's ``lens_model.warnings``.
MIN_FIELD_COVERAGE = 0.85
#: ``auto`` keeps the tangential terms unless the data bound their effect at the image's corner below this (px)
TANGENTIAL_BOUND_PX = 0.1


def lens_model_params(model: str) -> tuple[str, ...]:
    """The intrinsic parameters a lens model estimates: ``(fx, fy, cx, cy, *distortion)``.

    Raises
    ------
    InputError
        An unknown model name.
    """
    if model not in LENS_MODELS:
        raise InputError(
            f"unknown lens model {model!r}; lens models are {', '.join(LENS_MODEL_CHOICES)}", field="lens_model"
        )
    return ("fx", "fy", "cx", "cy", *LENS_MODELS[model])


def _lens_flags(model: str) -> int:
    d = set(LENS_MODELS[model])
    flags = 0
    if "k3" not in d:
        flags |= cv2.CALIB_FIX_K3
    if "k4" in d:
        flags |= cv2.CALIB_RATIONAL_MODEL
    if "p1" not in d:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def intrinsics_names(camera: CameraModel) -> tuple[str, ...]:
    """The parameters of a camera's calibration covariance (``calibration.covariance_params``), in its order.

    :data:`INTRINSICS_NAMES` (fx, fy, cx, cy, k1, k2, p1, p2) when the camera does not say (cameras calibrated
    before lens models were chosen); the chosen lens model's (:func:`lens_model_params`) otherwise.
    """
    names = ((camera.extra or {}).get("calibration") or {}).get("covariance_params")
    if not names or not all(n in ("fx", "fy", "cx", "cy") or n in DIST_INDEX for n in names):
        return INTRINSICS_NAMES
    return tuple(str(n) for n in names)


def intrinsics_vector(camera: CameraModel, names: tuple[str, ...] | list[str] = INTRINSICS_NAMES) -> Array:
    """The camera's intrinsics ``names`` as a vector (px for fx, fy, cx, cy; zero for a coefficient ``dist`` lacks)."""
    d = np.concatenate([camera.dist, np.zeros(8)])
    where = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    return np.array([camera.K[where[n]] if n in where else d[DIST_INDEX[n]] for n in names])


def moved_camera(
    camera: CameraModel, step: ArrayLike, names: tuple[str, ...] | list[str] = INTRINSICS_NAMES
) -> CameraModel:
    """``camera`` with the intrinsics ``names`` moved by ``step`` (same length; px for fx, fy, cx, cy).

    The distortion vector is lengthened (zeros) when a coefficient beyond it moves (k3: 5, k4..k6: 8).
    """
    st = np.asarray(step, dtype=np.float64).reshape(-1)
    K = camera.K.copy()
    d = camera.dist.copy()
    need = max([DIST_INDEX[n] + 1 for n in names if n in DIST_INDEX] + [d.size])
    if need > d.size:
        d = np.concatenate([d, np.zeros((8 if need > 5 else 5) - d.size)])
    where = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    for n, s in zip(names, st, strict=True):
        if n in where:
            K[where[n]] += s
        else:
            d[DIST_INDEX[n]] += s
    return CameraModel(K, d, camera.width, camera.height, camera.extra)


def _corner_radius_norm(K: Array, dist: Array, size: tuple[int, int], pixels: Array) -> tuple[float, float]:
    """Largest undistorted radius (normalized) of ``pixels`` (N, 2) and of the image's corners."""
    cam = CameraModel(K, dist, int(size[0]), int(size[1]))
    w, h = size[0] - 1.0, size[1] - 1.0
    corners = cam.undistort_points(np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]))
    pts = cam.undistort_points(pixels)
    return float(np.max(np.linalg.norm(pts, axis=1))), float(np.max(np.linalg.norm(corners, axis=1)))


def _radial_monotonic(K: Array, dist: Array, size: tuple[int, int]) -> bool:
    """Whether the radial distortion r -> r radial(r) rises (no fold, no pole) out to 1.1 x the image's corner radius
    (the candidate's own undistorted corner radius, from the pinhole alone when its undistortion fails)."""
    d = np.concatenate([dist, np.zeros(8)])[:8]
    k1, k2, _, _, k3, k4, k5, k6 = d
    w, h = size[0] - 1.0, size[1] - 1.0
    corner = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    rc = float(np.max(np.linalg.norm((corner - K[:2, 2]) / np.diag(K)[:2], axis=1)))
    r = np.linspace(0.0, 2.0 * rc, 400)  # the undistorted radius reaches beyond the distorted one for barrel lenses
    r2 = r * r
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    if np.any(den <= 1e-3):
        return False
    rd = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / den
    reach = np.nonzero(rd >= 1.1 * rc)[0]  # up to where the distorted radius covers the image
    stop = int(reach[0]) + 1 if reach.size else r.size
    return bool(np.all(np.diff(rd[:stop]) > 0)) and bool(reach.size)


def radial_residual_profile(
    K: Array,
    dist: Array,
    board_points: Array,
    image_points: list[Array],
    rvecs: list[Array],
    tvecs: list[Array],
    size: tuple[int, int],
    n_bins: int = 6,
) -> dict[str, Any]:
    """The calibration's reprojection residuals along the radius, binned by distance from the principal point.

    A lens model that cannot follow the lens leaves a residual that depends on the radius (the same in every
    view); noise does not. Per bin (equal widths up to the image's corner radius, px): the mean radial residual
    (observed minus predicted, px, outward positive), its standard error, and the systematic part
    ``sign(mean) sqrt(max(mean^2 - se^2, 0))`` (the unbiased estimate of the squared mean; zero when the mean
    is within its noise). ``chi2`` = sum (mean / se)^2 over the bins, about ``n_bins`` when nothing is left.

    Returns
    -------
    dict
        ``radius_px`` (bin centres), ``mean_px``, ``se_px``, ``systematic_px``, ``count`` (per bin), ``chi2``,
        ``dof``, ``max_systematic_px``.
    """
    c = np.array([K[0, 2], K[1, 2]])
    r_all, e_all = [], []
    for v, img in enumerate(image_points):
        proj, _ = cv2.projectPoints(
            board_points, np.asarray(rvecs[v], dtype=np.float64).reshape(3), np.asarray(tvecs[v]).reshape(3), K, dist
        )
        proj = proj.reshape(-1, 2)
        d = proj - c
        r = np.linalg.norm(d, axis=1)
        u = d / np.maximum(r, 1e-9)[:, None]
        r_all.append(r)
        e_all.append(np.sum((np.asarray(img, dtype=np.float64).reshape(-1, 2) - proj) * u, axis=1))
    r = np.concatenate(r_all) if r_all else np.zeros(0)
    e = np.concatenate(e_all) if e_all else np.zeros(0)
    rmax = float(np.hypot(max(c[0], size[0] - 1 - c[0]), max(c[1], size[1] - 1 - c[1])))
    edges = np.linspace(0.0, rmax, n_bins + 1)
    centre, mean, se, sysv, count = [], [], [], [], []
    for a, b in itertools.pairwise(edges):
        sel = (r >= a) & (r < b)
        n = int(sel.sum())
        centre.append(0.5 * (a + b))
        count.append(n)
        if n < 3:
            mean.append(0.0)
            se.append(float("inf") if n == 0 else float(np.abs(e[sel]).max()))
            sysv.append(0.0)
            continue
        m = float(np.mean(e[sel]))
        s = float(np.std(e[sel], ddof=1) / np.sqrt(n))
        mean.append(m)
        se.append(s)
        sysv.append(float(np.sign(m) * np.sqrt(max(m * m - s * s, 0.0))))
    ok = [i for i in range(n_bins) if count[i] >= 3 and se[i] > 0]
    chi = float(sum((mean[i] / se[i]) ** 2 for i in ok))
    return {
        "radius_px": centre,
        "mean_px": mean,
        "se_px": [s if np.isfinite(s) else None for s in se],
        "systematic_px": sysv,
        "count": count,
        "chi2": chi,
        "dof": len(ok),
        "max_systematic_px": float(max([abs(s) for s in sysv] + [0.0])),
    }


def calibrate_intrinsics(
    views: Mapping[int, tuple[ArrayLike, ArrayLike, object]],
    image_size: tuple[int, int],
    board_ids: ArrayLike,
    board_points: ArrayLike,
    *,
    min_views: int = 5,
    outlier_factor: float = 3.0,
    outlier_floor_px: float = 1.0,
    fix_k3: bool = True,
    refine_object: bool = True,
    lens_model: str | None = None,
    weight_views: bool = True,
) -> IntrinsicsResult:
    """Intrinsic calibration from ChArUco views, refining the board's geometry (``calibrateCameraRO``).

    ``calibrateCameraRO`` (Strobl & Hirzinger's "releasing object" method) needs the same object
    points in every view: only views where every corner of the board was detected are used, the
    others are rejected with the reason. Views whose RMS reprojection error exceeds
    ``max(outlier_factor * median, outlier_floor_px)`` are rejected and the calibration is redone.

    Lens model (``lens_model``): one of :data:`LENS_MODELS` (k1k2 = k1, k2, p1, p2; k1k2k3; OpenCV's rational
    k1..k6; each also without tangential terms, ``-radial``), or ``"auto"``: every candidate is fitted to the
    same views (the outliers rejected first with k1k2k3) and the one with the lowest Bayesian information
    criterion ``BIC = n ln(RSS / n) + k ln(n)`` is kept (n: residual coordinates, k: every unknown of the
    bundle -- intrinsics, 6 per view, the released board points; only the distortion count differs between
    candidates). Why BIC rather than cross-validation over views: the candidates are nested and fitted to the
    same corners whose noise is close to independent Gaussian, for which BIC approximates the models' posterior
    odds and is consistent (it picks the true model as views are added, where AIC keeps overfitting by a
    fixed margin); held-out views would need one calibration per candidate and fold (some 30 instead of 6,
    seconds against the extraction's few-second budget) and score mostly the held-out poses' own noise.

    Two exceptions, because neither criterion sees beyond the board views while the rods that refine the camera
    afterwards reach the image's corners: a ``-radial`` model is allowed only when the matching full fit bounds
    the tangential terms' effect at the corner (``(|p| + 2 std) 3 r_c^2 f``) below :data:`TANGENTIAL_BOUND_PX`;
    and when the views reach less than :data:`MIN_FIELD_COVERAGE` of the corner radius, a chosen ``k1k2``
    becomes ``k1k2k3`` (over a smaller radius k1, k2 absorb a sixth-order term, which shows only beyond it:
    on the image twin's 30-view camera phase, whose full-board views reach ~60-70% of the corner radius, k3's
    std is 0.01-0.035, so k3 = -0.012 is invisible to BIC, yet left out it biased the rods' refinement; kept as a
    parameter with its wide uncertainty, the rods pin it). ``lens_model.lowest_bic`` keeps BIC's own choice,
    ``lens_model.warnings`` says why it was overruled or that the views do not cover the field.

    The evidence per candidate (RMS, RSS, BIC, parameter count) is in the camera's ``calibration.lens_model``,
    with the field coverage and the chosen model's radial residual profile (:func:`radial_residual_profile`),
    the model error the methods carry into their standard deviations (``std_breakdown.lens_model``).
    ``None``: ``k1k2`` (``fix_k3``) or ``k1k2k3`` (the behaviour before lens models were chosen).

    Parameters
    ----------
    views : dict[int, (ids, image_points, unused)]
        Per view key: detected corner ids (M,), their pixels (M, 2), and a free slot (ignored).
    image_size : (width, height)
    board_ids : array_like, shape (M,)
        All corner ids of the board.
    board_points : array_like, shape (M, 3)
        Nominal corner coordinates in the board frame, metres.
    lens_model : str, optional
        ``"auto"`` or a key of :data:`LENS_MODELS`.
    weight_views : bool
        After OpenCV's fit (plain least squares, which the lens model's choice and the outlier test use), weight
        each view by its corners' noise variance, estimated from its residuals, and refine the whole bundle
        (:func:`calib.bundle.refine_weighted`); the covariance is then the weighted fit's. False: OpenCV's estimate
        and ``s^2 (J^T J)^-1``. The per-view noise is in ``calibration.view_sigma_px``.

    Raises
    ------
    InputError
        Fewer than ``min_views`` usable views; an unknown lens model.
    """
    model = lens_model or ("k1k2" if fix_k3 else "k1k2k3")
    if model != "auto":
        lens_model_params(model)  # raises for an unknown name
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

    def run(keys: list[int], flags: int) -> tuple:
        objp = [obj.astype(np.float32).reshape(-1, 1, 3) for _ in keys]
        imgp = [keep[k].astype(np.float32).reshape(-1, 1, 2) for k in keys]
        with opencv_single_thread():  # bit-reproducible: OpenCV's threads change the result in the last digits
            # OpenCV's stubs do not allow None for the initial camera matrix and distortion, which the function
            # takes (no initial guess)
            return cv2.calibrateCameraROExtended(  # type: ignore[call-overload]
                objp,
                imgp,
                (w, h),
                fixed,
                None,
                None,
                flags=flags,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12),
            )

    first = "k1k2k3" if model == "auto" else model
    for _ in range(5):
        if len(keep) < min_views:
            raise InputError(
                f"intrinsic calibration needs at least {min_views} full-board views, got {len(keep)}"
                + (f" ({len(rejected)} rejected)" if rejected else ""),
                field="camera",
            )
        keys = list(keep)
        ret = run(keys, _lens_flags(first))
        per_view = np.asarray(ret[9]).reshape(-1)
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
    keys = list(keep)
    m_pts = obj.shape[0]
    n_res = 2 * m_pts * len(keys)
    n_board = (3 * m_pts - 7) if fixed >= 0 else 0  # released points less OpenCV's gauge (two points and a z)
    candidates = list(LENS_MODELS) if model == "auto" else [model]
    fits: dict[str, tuple] = {first: ret} if first in candidates else {}
    evidence: list[dict[str, Any]] = []  # one JSON object per candidate model (mixed value types)
    for name in candidates:
        r = fits.get(name) or run(keys, _lens_flags(name))
        fits[name] = r
        Kc, dc = r[1], np.asarray(r[2], dtype=np.float64).reshape(-1)
        oc = np.asarray(r[5], dtype=np.float64).reshape(-1, 3) if r[5] is not None and np.size(r[5]) else obj
        rss = 0.0
        for k, rv, tv in zip(keys, r[3], r[4], strict=True):
            proj, _ = cv2.projectPoints(oc, np.asarray(rv).reshape(3), np.asarray(tv).reshape(3), Kc, dc)
            rss += float(np.sum((proj.reshape(-1, 2) - keep[k]) ** 2))
        n_int = len(lens_model_params(name))
        k_all = n_int + 6 * len(keys) + n_board
        bic = n_res * np.log(max(rss, 1e-300) / n_res) + k_all * np.log(n_res)
        evidence.append(
            {
                "model": name,
                "n_params": n_int,
                "rms_px": float(r[0]),
                "rss_px2": rss,
                "bic": float(bic) if np.isfinite(bic) else None,
                "finite": bool(np.all(np.isfinite(dc)) and np.all(np.isfinite(Kc))),
            }
        )
    for e in evidence:  # a model whose radial map folds or has a pole inside the image is no lens
        r = fits[e["model"]]
        e["monotonic"] = _radial_monotonic(r[1], np.asarray(r[2], dtype=np.float64).reshape(-1), (int(w), int(h)))
    usable = [e for e in evidence if e["finite"] and e["bic"] is not None and (model != "auto" or e["monotonic"])]
    if model == "auto":
        # tangential terms are dropped only when their effect at the image's corner is bounded below
        # TANGENTIAL_BOUND_PX by the matching full fit (|p| + 2 std): a lens's decentring hardly shows over
        # the board views, and the rods that refine the camera afterwards reach the corners
        k0, d0 = fits["k1k2"][1], np.asarray(fits["k1k2"][2]).reshape(-1)
        _, rc = _corner_radius_norm(k0, d0, (int(w), int(h)), np.zeros((1, 2)))
        for e in usable:
            if e["model"].endswith("-radial"):
                full = fits[e["model"].removesuffix("-radial")]
                dfull = np.asarray(full[2]).reshape(-1)
                sfull = np.asarray(full[6]).reshape(-1)
                bound = float(np.max(np.abs(dfull[2:4]) + 2 * sfull[6:8])) * 3 * rc**2 * float(full[1][0, 0])
                e["tangential_bound_px"] = bound
                e["allowed"] = bound < TANGENTIAL_BOUND_PX
        # OpenCV's rational model adds a denominator whose k4-k6 all but repeat k1-k3 over the views' radius: fitted
        # to views that stay short of the image's corners, it lowers the corners' RSS by bending where no corner is,
        # and its extrapolation there is undetermined (on the image twin's 30-view phases it won BIC on a plain
        # lens, its k1-k6 std 0.6-5, and the rods moved it by 5 std; the combined errors were 0.5-0.9 mm)
        kr0, cr0 = _corner_radius_norm(k0, d0, (int(w), int(h)), np.vstack(list(keep.values())))
        if cr0 > 0 and kr0 / cr0 < MIN_FIELD_COVERAGE:
            for e in usable:
                if e["model"].startswith("rational"):
                    e["allowed"] = False
                    e["not_allowed_because"] = (
                        f"the board views reach {100 * kr0 / cr0:.0f}% of the image's corner radius, less than "
                        f"{100 * MIN_FIELD_COVERAGE:.0f}%: a rational model's extra terms are not determined there"
                    )
        allowed = [e for e in usable if e.get("allowed", True)]
        chosen = min(allowed, key=lambda e: e["bic"])["model"] if allowed else "k1k2"
    else:
        chosen = candidates[0]
    promoted = None
    if model == "auto" and chosen.startswith("k1k2") and not chosen.startswith("k1k2k3"):
        # views that do not reach the image's corners cannot tell whether the lens has a sixth-order term
        # (k1, k2 absorb it over their radius): it stays a parameter with its (wide) uncertainty, which the rods,
        # seen up to the corners, then pin (the combined method's nuisance unknowns)
        kr, cr = _corner_radius_norm(
            fits[chosen][1], np.asarray(fits[chosen][2]).reshape(-1), (int(w), int(h)), np.vstack(list(keep.values()))
        )
        if cr > 0 and kr / cr < MIN_FIELD_COVERAGE:
            promoted, chosen = chosen, chosen.replace("k1k2", "k1k2k3", 1)
    best_bic = min((e["bic"] for e in usable), default=0.0)
    for e in evidence:
        e["delta_bic"] = None if e["bic"] is None else float(e["bic"] - best_bic)
    _rms, K, dist, rvecs, tvecs, new_obj, _std_int, _std_ext, _std_obj, _per_view = fits[chosen]
    new_obj = np.asarray(new_obj, dtype=np.float64).reshape(-1, 3) if new_obj is not None and np.size(new_obj) else obj
    pnames = lens_model_params(chosen)
    bundle = Bundle.of(K, dist, new_obj, [keep[k] for k in keys], rvecs, tvecs, fixed, pnames)
    view_sigma = None
    refined_converged = True
    if weight_views and view_dof(bundle) > MIN_VIEW_DOF:
        # each view weighted by its own corner noise (calib.bundle: the plain fit's premise fails)
        bundle, view_var, refined_converged = refine_weighted(bundle)
        view_sigma = np.sqrt(view_var)
    cov, d_board = bundle_covariance(bundle, None if view_sigma is None else view_sigma**2)
    K, new_obj, rvecs, tvecs = bundle.K, bundle.board_points, bundle.rvecs, bundle.tvecs
    dist = bundle.dist[: max(np.asarray(dist).size, 5)]
    res_v = bundle.residuals()
    per_view = np.array([float(np.sqrt(np.mean(r**2))) for r in res_v])
    rms = float(np.sqrt(np.mean(np.concatenate(res_v) ** 2)))
    profile = radial_residual_profile(K, dist, new_obj, [keep[k] for k in keys], rvecs, tvecs, (int(w), int(h)))
    reach, corner = _corner_radius_norm(K, dist, (int(w), int(h)), np.vstack([keep[k] for k in keys]))
    coverage = reach / corner if corner > 0 else 1.0
    warnings = []
    if promoted is not None:
        warnings.append(
            f"lens model {chosen} instead of {promoted} (lowest BIC): the board views reach {100 * coverage:.0f}% "
            "of the image's corner radius, too little to exclude a sixth-order term; it is kept with its "
            "calibration uncertainty for the rods to pin"
        )
    elif coverage < MIN_FIELD_COVERAGE:
        warnings.append(
            f"the board views reach {100 * coverage:.0f}% of the image's corner radius: the distortion beyond "
            "is extrapolated (higher-order terms there are not determined; present the board near the corners)"
        )
    if not refined_converged:
        warnings.append(
            f"lens model {chosen}: the views-weighted refinement did not converge within {REFINE_MAX_NFEV} evaluations "
            "a pass: the board views do not determine this model well (its coefficients trade off along flat "
            "directions); views near the image's corners, or a model with fewer terms, would"
        )
    lens_info = {
        "chosen": chosen,
        "requested": model,
        "lowest_bic": promoted or chosen,
        "criterion": "BIC = n ln(RSS/n) + k ln(n) over the board views' corners" if model == "auto" else "given",
        "candidates": evidence,
        "n_residuals": n_res,
        "field_coverage": float(coverage),
        "residual_profile": profile,
        "warnings": warnings,
    }
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
    std = {n: 0.0 for n in names}  # the fixed coefficients: 0, as OpenCV reports them
    std.update({n: float(np.sqrt(cov[i, i])) for i, n in enumerate(pnames)})
    cam = CameraModel(
        K,
        dist,
        int(w),
        int(h),
        {
            "calibration": {
                "rms_px": float(rms),
                "n_views": len(keys),
                "std": std,
                "covariance_params": list(pnames),
                "covariance": cov.tolist(),
                "method": "cv2.calibrateCameraRO"
                + (", views weighted by their noise" if view_sigma is not None else ""),
                "view_sigma_px": None if view_sigma is None else [float(x) for x in view_sigma],
                "lens_model": lens_info,
                "board_points": {
                    "ids": sort_ids.tolist(),
                    "points_m": new_obj.tolist(),
                    "d_intrinsics": d_board.tolist(),
                },
            }
        },
    )
    res = IntrinsicsResult(
        cam,
        float(rms),
        {k: float(e) for k, e in zip(keys, per_view, strict=True)},
        std,
        rejected,
        new_obj,
        sort_ids,
        {k: (np.asarray(r).reshape(3), np.asarray(t).reshape(3)) for k, r, t in zip(keys, rvecs, tvecs, strict=True)},
    )
    res.lens_model = lens_info
    return res


def intrinsics_covariance(
    K: ArrayLike,
    dist: ArrayLike,
    board_points: ArrayLike,
    image_points: list[ArrayLike],
    rvecs: list[ArrayLike],
    tvecs: list[ArrayLike],
    fixed_point: int = -1,
    names: tuple[str, ...] | list[str] = INTRINSICS_NAMES,
) -> Array:
    """Joint covariance (n, n) of the intrinsics ``names`` (default fx, fy, cx, cy [px], k1, k2, p1, p2).

    Gauss-Newton covariance ``s^2 (J^T J)^-1`` of the full bundle (intrinsics, every view's pose and,
    with the releasing-object method, the board's points), marginalised to the intrinsics (Schur
    complement), ``s^2`` the residual variance per coordinate. The board points' gauge is OpenCV's
    (``calibrateCameraRO``): the first point, the ``fixed_point``-th one and the last one's z are fixed.
    The distortion coefficients not in ``names`` are taken as fixed (the lens model's). OpenCV returns only the
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
    names : sequence of str
        The estimated intrinsics (:func:`lens_model_params`), in the covariance's order; ``dist`` must be long
        enough to hold each (5 with k3, 8 with k4..k6).

    Returns
    -------
    ndarray, shape (n, n)
        Pixels for fx, fy, cx, cy; dimensionless for the distortion coefficients.
    """
    return bundle_covariance(Bundle.of(K, dist, board_points, image_points, rvecs, tvecs, fixed_point, names))[0]
