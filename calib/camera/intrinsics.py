"""Intrinsic calibration with ``cv2.calibrateCameraRO`` of the camera model :class:`calib.formats.camera.CameraModel`.

Conventions: pixel coordinates ``(u, v)`` with the origin at the centre of the top-left pixel
(OpenCV's); normalized coordinates ``(x, y) = (X/Z, Y/Z)`` of a point ``(X, Y, Z)`` in the camera
frame (metres; z along the optical axis). "Ideal pixels" are undistorted pixel coordinates
``K (x, y, 1)``.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from calib.camera.bundle import (
    DIST_INDEX,
    MIN_VIEW_DOF,
    REFINE_MAX_NFEV,
    Bundle,
    bundle_covariance,
    refine_weighted,
    view_dof,
)
from calib.camera.bundle import projection_columns as projection_columns
from calib.errors import InputError
from calib.formats.camera import CameraModel

Array = NDArray[np.float64]


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
        """The calibration's figures as a JSON object.

        Returns
        -------
        dict
            ``rms_px``, ``per_view_rms_px`` and ``rejected`` (keyed by the view key as a string), ``std``,
            ``n_views`` and, when chosen, ``lens_model``.
        """
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
    when OpenCV runs several threads (fx by ~2e-7 px, enough for a whole extraction to differ
    after the rods' refinement and its second pass); single-threaded it is bit-reproducible.

    Returns
    -------
    context manager
        Yields nothing.
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

    Parameters
    ----------
    model : str
        A key of :data:`LENS_MODELS`.

    Returns
    -------
    tuple of str
        The names, in the order of the calibration's covariance.

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

    Parameters
    ----------
    camera : CameraModel

    Returns
    -------
    tuple of str
    """
    names = ((camera.extra or {}).get("calibration") or {}).get("covariance_params")
    if not names or not all(n in ("fx", "fy", "cx", "cy") or n in DIST_INDEX for n in names):
        return INTRINSICS_NAMES
    return tuple(str(n) for n in names)


def intrinsics_vector(camera: CameraModel, names: tuple[str, ...] | list[str] = INTRINSICS_NAMES) -> Array:
    """The camera's intrinsics ``names`` as a vector.

    Parameters
    ----------
    camera : CameraModel
    names : sequence of str
        Intrinsic parameter names (fx, fy, cx, cy and distortion coefficients,
        :data:`calib.camera.bundle.DIST_INDEX`).

    Returns
    -------
    ndarray, shape (len(names),)
        Pixels for fx, fy, cx, cy; dimensionless for the coefficients (zero for one ``dist`` lacks).
    """
    d = np.concatenate([camera.dist, np.zeros(8)])
    where = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    return np.array([camera.K[where[n]] if n in where else d[DIST_INDEX[n]] for n in names])


def moved_camera(
    camera: CameraModel, step: ArrayLike, names: tuple[str, ...] | list[str] = INTRINSICS_NAMES
) -> CameraModel:
    """``camera`` with the intrinsics ``names`` moved by ``step`` (same length; px for fx, fy, cx, cy).

    The distortion vector is lengthened (zeros) when a coefficient beyond it moves (k3: 5, k4..k6: 8).

    Parameters
    ----------
    camera : CameraModel
    step : array_like, shape (len(names),)
        Pixels for fx, fy, cx, cy; dimensionless for the coefficients.
    names : sequence of str
        The intrinsics moved, in ``step``'s order.

    Returns
    -------
    CameraModel
        A new camera (``extra`` shared with ``camera``).
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

    Parameters
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix, pixels.
    dist : ndarray, shape (n,)
        OpenCV's distortion coefficients.
    board_points : ndarray, shape (M, 3)
        The board's corners in the board frame, metres.
    image_points : list of ndarray, shape (M, 2)
        Per view, the detected pixels of ``board_points``.
    rvecs, tvecs : list of ndarray, shape (3,)
        Per view, ``camera_from_board`` (radians, metres).
    size : tuple of int
        ``(width, height)``, pixels.
    n_bins : int
        Radial bins.

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


@dataclass(frozen=True)
class IntrinsicsSettings:
    """Settings of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    min_views : int
        Fewer full-board views than this (after the outliers' rejection) and the calibration fails.
    outlier_factor : float
        A view whose RMS reprojection error exceeds ``max(outlier_factor * median, outlier_floor_px)`` is an outlier.
    outlier_floor_px : float
        The outlier limit's floor, pixels.
    fix_k3 : bool
        The lens model when ``lens_model`` is None: ``k1k2`` (True) or ``k1k2k3`` (False).
    refine_object : bool
        Release the board's corners (``calibrateCameraRO``'s ``iFixedPoint``): their coordinates are refined.
    lens_model : str or None
        ``"auto"`` (chosen from the views, :func:`choose_lens_model`) or a key of :data:`LENS_MODELS`.
    weight_views : bool
        Refine the chosen model's bundle with each view weighted by its own noise (:func:`refine_intrinsics`).
    max_outlier_passes : int
        At most this many outlier views are rejected, one per pass (the worst first).
    shared_start : bool
        With ``auto``, fit the candidates of :data:`SHARED_START_MODELS` from the outlier test's ``k1k2k3`` fit
        (:func:`fit_lens_candidates`' ``start``) rather than each from OpenCV's own guess: the same minima, in less
        CPU. False: every candidate from OpenCV's own guess.
    """

    min_views: int = 5
    outlier_factor: float = 3.0
    outlier_floor_px: float = 1.0
    fix_k3: bool = True
    refine_object: bool = True
    lens_model: str | None = None
    weight_views: bool = True
    max_outlier_passes: int = 5
    shared_start: bool = True

    @property
    def requested_model(self) -> str:
        """The lens model asked for: ``lens_model``, else ``k1k2`` or ``k1k2k3`` by ``fix_k3``."""
        return self.lens_model or ("k1k2" if self.fix_k3 else "k1k2k3")


@dataclass
class BoardViews:
    """The full-board views of a calibration, in the board's id order (:func:`select_board_views`).

    Attributes
    ----------
    ids : ndarray of int, shape (M,)
        The board's corner ids, sorted.
    points : ndarray, shape (M, 3)
        The nominal corner coordinates of ``ids`` in the board frame, metres.
    image_points : dict[int, ndarray, shape (M, 2)]
        Per kept view (the caller's key), the detected pixels of ``ids``.
    rejected : dict[int, str]
        Views not used, with the reason.
    fixed_point : int
        ``iFixedPoint`` of ``calibrateCameraRO`` (the last corner of the first row), -1: the board is not refined.
    image_size : tuple of int
        ``(width, height)``, pixels.
    """

    ids: NDArray[np.int_]
    points: Array
    image_points: dict[int, Array]
    rejected: dict[int, str]
    fixed_point: int
    image_size: tuple[int, int]

    @property
    def keys(self) -> list[int]:
        """The kept views' keys, in the order of every fit's per-view outputs."""
        return list(self.image_points)

    def stacked_pixels(self) -> Array:
        """Every kept view's pixels.

        Returns
        -------
        ndarray, shape (V M, 2)
            Pixels, view after view.
        """
        return np.vstack(list(self.image_points.values()))

    def n_residuals(self) -> int:
        """Residual coordinates of a fit to the kept views.

        Returns
        -------
        int
            2 M V.
        """
        return 2 * self.points.shape[0] * len(self.image_points)

    def n_board_unknowns(self) -> int:
        """The released board coordinates a fit estimates.

        Returns
        -------
        int
            3 M less OpenCV's gauge of 7 (the first point, the fixed one, the last one's z); 0 when not released.
        """
        return (3 * self.points.shape[0] - 7) if self.fixed_point >= 0 else 0

    def n_unknowns(self, model: str, n_views: int) -> int:
        """Every unknown of a bundle fit of ``model`` to ``n_views`` of these views: the intrinsics, 6 per view and
        the released board points.

        Parameters
        ----------
        model : str
            A key of :data:`LENS_MODELS`.
        n_views : int
            Views fitted.

        Returns
        -------
        int
        """
        return len(lens_model_params(model)) + 6 * n_views + self.n_board_unknowns()


@dataclass(frozen=True)
class LensFit:
    """One ``cv2.calibrateCameraROExtended`` fit of a lens model to a set of views (:func:`fit_lens_model`).

    Attributes
    ----------
    model : str
        The lens model (:data:`LENS_MODELS`).
    keys : tuple of int
        The views fitted, in the order of ``rvecs``, ``tvecs``, ``per_view_rms_px``.
    rms_px : float
        OpenCV's RMS reprojection error, pixels.
    K : ndarray, shape (3, 3)
        Camera matrix, pixels.
    dist : ndarray, shape (n,)
        OpenCV's distortion coefficients (n = 5, or more with the rational model).
    rvecs, tvecs : tuple of ndarray, shape (3, 1)
        Per view, ``camera_from_board`` (radians, metres).
    board_points : ndarray, shape (M, 3)
        The board's corners as the fit refined them (the nominal ones when not released), metres.
    std_intrinsics : ndarray
        OpenCV's standard deviations of (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, ...).
    per_view_rms_px : ndarray, shape (V,)
        Per view, its RMS reprojection error, pixels.
    """

    model: str
    keys: tuple[int, ...]
    rms_px: float
    K: Array
    dist: Array
    rvecs: tuple[Array, ...]
    tvecs: tuple[Array, ...]
    board_points: Array
    std_intrinsics: Array
    per_view_rms_px: Array

    def finite(self) -> bool:
        """Whether K and the distortion coefficients are finite.

        Returns
        -------
        bool
        """
        return bool(np.all(np.isfinite(self.dist)) and np.all(np.isfinite(self.K)))


@dataclass
class LensChoice:
    """The lens model :func:`choose_lens_model` keeps, and its evidence.

    Attributes
    ----------
    chosen : str
        The model kept.
    lowest_bic : str
        The model BIC chose (``chosen`` unless promoted to a ``k3`` model).
    promoted : bool
        Whether ``chosen`` replaces ``lowest_bic`` because the views do not cover the field.
    evidence : list of dict
        Per candidate: ``model``, ``n_params``, ``rms_px``, ``rss_px2``, ``bic``, ``finite``, ``monotonic``, with
        ``auto`` the ``tangential_bound_px`` and ``allowed`` of a ``-radial`` model, ``not_allowed_because``, and
        ``delta_bic`` (against the lowest usable BIC).
    """

    chosen: str
    lowest_bic: str
    promoted: bool
    evidence: list[dict[str, Any]]


@dataclass
class RefinedIntrinsics:
    """The chosen model's bundle after the views-weighted refinement, with its covariance (:func:`refine_intrinsics`).

    Attributes
    ----------
    bundle : calib.camera.bundle.Bundle
        The refined state (intrinsics, per-view poses, board points).
    names : tuple of str
        The estimated intrinsics, the covariance's order (:func:`lens_model_params`).
    covariance : ndarray, shape (n, n)
        Of ``names``: px^2 for fx, fy, cx, cy; dimensionless for the distortion coefficients.
    d_board : ndarray, shape (M, 3, n)
        How the refined board points move with the intrinsics (metres per unit of each).
    view_sigma_px : ndarray, shape (V,) or None
        Per view, its corners' noise std (pixels); None when the views were not weighted.
    converged : bool
        Whether every weighted pass converged.
    dist_size : int
        Length of the camera's distortion vector (at least 5).
    """

    bundle: Bundle
    names: tuple[str, ...]
    covariance: Array
    d_board: Array
    view_sigma_px: Array | None
    converged: bool
    dist_size: int

    @property
    def dist(self) -> Array:
        """The camera's distortion coefficients, shape (``dist_size``,)."""
        return self.bundle.dist[: self.dist_size]


#: every intrinsic parameter OpenCV reports a std for, in its order (``calibration.std`` of a camera file)
_STD_NAMES = (
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
)
#: ``calibrateCameraROExtended``'s iteration limit (:func:`fit_lens_model`)
RO_MAX_ITERATIONS = 200
#: ``calibrateCameraROExtended``'s stopping rule: iterations, relative step
_RO_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, RO_MAX_ITERATIONS, 1e-12)
#: the lens models :func:`fit_lens_candidates` fits from a shared start: those without OpenCV's rational denominator.
#: From a start, the rational models' k4-k6 (all but collinear with k1-k3) make the solver that takes a start crawl
#: (on some view sets twice the CPU of OpenCV's own guess in its Schur-complement solver) and stop at other minima,
#: lower or higher; the others reach their minimum from it in a third to two thirds of the CPU.
SHARED_START_MODELS = tuple(m for m in LENS_MODELS if "k4" not in LENS_MODELS[m])
#: a candidate fitted from a shared start is kept only when its RMS exceeds no nested model's by more than this
#: fraction (a model with more terms cannot fit worse at its minimum; more means it stopped at another one)
NESTED_RMS_TOLERANCE = 1e-9


def select_board_views(
    views: Mapping[int, tuple[ArrayLike, ArrayLike, object]],
    board_ids: ArrayLike,
    board_points: ArrayLike,
    image_size: tuple[int, int],
    refine_object: bool = True,
) -> BoardViews:
    """The views where every corner of the board was detected, in the board's id order.

    ``calibrateCameraRO`` needs the same object points in every view: the other views are rejected with the reason.

    Parameters
    ----------
    views : mapping of int to (ids, image_points, unused)
        Per view key: detected corner ids (N,), their pixels (N, 2), and a free slot (ignored).
    board_ids : array_like of int, shape (M,)
        All corner ids of the board.
    board_points : array_like, shape (M, 3)
        Nominal corner coordinates in the board frame, metres.
    image_size : tuple of int
        ``(width, height)``, pixels.
    refine_object : bool
        Release the board's corners (the releasing-object method's ``iFixedPoint``: the first row's last corner).

    Returns
    -------
    BoardViews
        The kept views and the rejected ones.

    Raises
    ------
    ValueError
        ``board_points`` not of shape (M, 3).
    """
    ids_all = np.asarray(board_ids, dtype=int).reshape(-1)
    obj_nom = np.asarray(board_points, dtype=np.float64).reshape(-1, 3)
    if obj_nom.shape[0] != ids_all.size:
        raise ValueError(f"board_points must have shape ({ids_all.size}, 3), got {obj_nom.shape}")
    rejected: dict[int, str] = {}
    keep: dict[int, Array] = {}
    wanted = set(ids_all.tolist())
    for key, (ids, img, _unused) in views.items():
        ids = np.asarray(ids, dtype=int).reshape(-1)
        img = np.asarray(img, dtype=np.float64).reshape(-1, 2)
        if ids.size != ids_all.size or set(ids.tolist()) != wanted:
            rejected[key] = (
                f"partial board ({ids.size} of {ids_all.size} corners); calibrateCameraRO needs "
                "every corner in every view"
            )
            continue
        keep[key] = img[np.argsort(ids)]
    obj = obj_nom[np.argsort(ids_all)]
    ncols = int(np.sum(np.isclose(obj[:, 1], obj[0, 1])))
    fixed = ncols - 1 if refine_object and ncols > 1 else -1
    return BoardViews(np.sort(ids_all), obj, keep, rejected, fixed, (int(image_size[0]), int(image_size[1])))


def start_distortion(start: LensFit, model: str) -> Array:
    """``start``'s distortion coefficients as a start for ``model``: those ``model`` estimates, the others zero.

    Parameters
    ----------
    start : LensFit
        The fit started from.
    model : str
        A key of :data:`LENS_MODELS`.

    Returns
    -------
    ndarray, shape (5,) or (8,)
        OpenCV's distortion vector (8 long for the rational models); dimensionless.
    """
    d = np.zeros(8 if "k4" in LENS_MODELS[model] else 5)
    for name in LENS_MODELS[model]:
        i = DIST_INDEX[name]
        if i < start.dist.size:
            d[i] = start.dist[i]
    return d


def fit_lens_model(
    board: BoardViews,
    model: str,
    keys: list[int] | None = None,
    start: LensFit | None = None,
    max_iterations: int = RO_MAX_ITERATIONS,
) -> LensFit:
    """Fit one lens model to the views with ``cv2.calibrateCameraROExtended``.

    Without ``start``, from OpenCV's own initial guess. With ``start`` (``cv2.CALIB_USE_INTRINSIC_GUESS``), from its
    camera matrix and the distortion coefficients ``model`` shares with it (:func:`start_distortion`); the views'
    poses OpenCV computes from that camera, the released board starts nominal (OpenCV takes no start for either).
    OpenCV 4.14's Schur-complement solver refuses a guess with the released board (an assertion), so such a fit runs
    in its other solver (``cv2.CALIB_DISABLE_SCHUR_COMPLEMENT``), its steps solved by LU (``cv2.CALIB_USE_LU``;
    by SVD, OpenCV's default there, each iteration costs 3-5 times more).

    Single-threaded (:func:`opencv_single_thread`): bit-reproducible.

    Parameters
    ----------
    board : BoardViews
        The full-board views.
    model : str
        A key of :data:`LENS_MODELS`.
    keys : list of int, optional
        The views to fit (default: every kept view of ``board``).
    start : LensFit, optional
        A fit to start from (K in pixels, its principal point inside the image), of any lens model.
    max_iterations : int
        Levenberg-Marquardt iterations allowed (the fit also stops when a step moves the unknowns by less than
        1e-12 of themselves).

    Returns
    -------
    LensFit
    """
    keys = board.keys if keys is None else list(keys)
    objp = [board.points.astype(np.float32).reshape(-1, 1, 3) for _ in keys]
    imgp = [board.image_points[k].astype(np.float32).reshape(-1, 1, 2) for k in keys]
    flags = _lens_flags(model)
    # OpenCV's stubs do not allow None for the initial camera matrix and distortion, which the function takes (no
    # initial guess)
    K0: Any = None
    d0: Any = None
    if start is not None:
        K0, d0 = start.K.copy(), start_distortion(start, model)
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
        if board.fixed_point >= 0:
            flags |= cv2.CALIB_DISABLE_SCHUR_COMPLEMENT | cv2.CALIB_USE_LU
    criteria = (_RO_CRITERIA[0], int(max_iterations), _RO_CRITERIA[2])
    with opencv_single_thread():  # bit-reproducible: OpenCV's threads change the result in the last digits
        r: Any = cv2.calibrateCameraROExtended(
            objp, imgp, board.image_size, board.fixed_point, K0, d0, flags=flags, criteria=criteria
        )
    new_obj = r[5]
    refined = new_obj is not None and np.size(new_obj)
    return LensFit(
        model,
        tuple(keys),
        float(r[0]),
        np.asarray(r[1], dtype=np.float64),
        np.asarray(r[2], dtype=np.float64).reshape(-1),
        tuple(r[3]),
        tuple(r[4]),
        np.asarray(new_obj, dtype=np.float64).reshape(-1, 3) if refined else board.points,
        np.asarray(r[6], dtype=np.float64).reshape(-1),
        np.asarray(r[9], dtype=np.float64).reshape(-1),
    )


def reject_outlier_views(board: BoardViews, model: str, settings: IntrinsicsSettings) -> tuple[BoardViews, LensFit]:
    """Fit ``model`` and reject the worst view while any view's RMS exceeds the outlier limit.

    The limit is ``max(outlier_factor * median, outlier_floor_px)`` of the views' RMS reprojection errors; one view
    is rejected per pass (the worst), at most ``settings.max_outlier_passes`` passes; the fit returned is always the
    one of the views kept.

    Parameters
    ----------
    board : BoardViews
        The full-board views (not modified).
    model : str
        The lens model the test fits (a key of :data:`LENS_MODELS`).
    settings : IntrinsicsSettings

    Returns
    -------
    BoardViews
        The views kept, the rejected ones with the reason.
    LensFit
        ``model`` fitted to the views kept.

    Raises
    ------
    InputError
        Fewer than ``settings.min_views`` views left.
    """
    keep = dict(board.image_points)
    rejected = dict(board.rejected)
    for _ in range(settings.max_outlier_passes):
        _require_views(len(keep), len(rejected), settings.min_views)
        fit = fit_lens_model(board, model, list(keep))
        per_view = fit.per_view_rms_px
        med = float(np.median(per_view))
        limit = max(settings.outlier_factor * med, settings.outlier_floor_px)
        if not np.any(per_view > limit):
            break
        worst = fit.keys[int(np.argmax(per_view))]
        rejected[worst] = (
            f"outlier view: reprojection RMS {float(per_view.max()):.2f} px > limit {limit:.2f} px "
            f"(median {med:.2f} px)"
        )
        del keep[worst]
    else:  # the last pass rejected a view: the views left are fitted once more
        _require_views(len(keep), len(rejected), settings.min_views)
        fit = fit_lens_model(board, model, list(keep))
    return BoardViews(board.ids, board.points, keep, rejected, board.fixed_point, board.image_size), fit


def _require_views(n_kept: int, n_rejected: int, min_views: int) -> None:
    if n_kept < min_views:
        raise InputError(
            f"intrinsic calibration needs at least {min_views} full-board views, got {n_kept}"
            + (f" ({n_rejected} rejected)" if n_rejected else ""),
            field="camera",
        )


def fit_lens_candidates(
    board: BoardViews, candidates: list[str], fitted: Mapping[str, LensFit], start: LensFit | None = None
) -> dict[str, LensFit]:
    """Every candidate lens model fitted to the same views (those already ``fitted`` reused).

    Each from OpenCV's own guess, or with ``start`` those of :data:`SHARED_START_MODELS` from that fit
    (:func:`fit_lens_model`), the models with fewer terms first. A fit from ``start`` that did not reach the minimum
    OpenCV's own guess leads to (:func:`at_the_start_s_minimum`), or a start OpenCV refuses, is fitted again from that
    guess.

    Parameters
    ----------
    board : BoardViews
        The views kept.
    candidates : list of str
        Keys of :data:`LENS_MODELS`.
    fitted : mapping of str to LensFit
        Fits to ``board``'s views already made (the outlier test's).
    start : LensFit, optional
        The shared start: a fit to ``board``'s views (the outlier test's).

    Returns
    -------
    dict of str to LensFit
        Per candidate, in ``candidates``' order.
    """
    fits = dict(fitted)
    for name in sorted(candidates, key=lambda n: len(LENS_MODELS[n])):  # a nested model before those containing it
        if name in fits:
            continue
        fit = _fit_from(start, board, name) if start is not None and name in SHARED_START_MODELS else None
        if fit is None or not at_the_start_s_minimum(fit, start, fits, board):
            fit = fit_lens_model(board, name)
        fits[name] = fit
    return {name: fits[name] for name in candidates}


def _fit_from(start: LensFit, board: BoardViews, model: str) -> LensFit | None:
    """``model`` fitted from ``start``, None when OpenCV refuses the start (a principal point outside the image)."""
    try:
        return fit_lens_model(board, model, start=start)
    except cv2.error:
        return None


def at_the_start_s_minimum(
    fit: LensFit, start: LensFit | None, others: Mapping[str, LensFit], board: BoardViews
) -> bool:
    """Whether a fit from ``start`` reached the minimum its model has near ``start``'s (not another one).

    It must be finite, fit no worse than any of ``others`` whose terms its model contains (by more than
    :data:`NESTED_RMS_TOLERANCE`), and its residual sum of squares must not exceed ``start``'s by more than dropping
    ``start``'s terms its model lacks can explain: ``s^2 (2 W + 10)``, ``W = sum (c / std_c)^2`` over the dropped
    coefficients (the Wald statistic from OpenCV's standard deviations; the quadratic prediction of the rise is
    ``s^2 W``, within 25% of the fitted rise on rendered and synthetic views), ``s^2`` ``start``'s residual
    variance; no rise at all when it drops none.

    Parameters
    ----------
    fit : LensFit
        The fit from ``start``.
    start : LensFit or None
        The fit it started from, to the same views (None: only the first two tests).
    others : mapping of str to LensFit
        Other candidates fitted to the same views.
    board : BoardViews
        The views fitted.

    Returns
    -------
    bool
    """
    terms = set(LENS_MODELS[fit.model])
    nested = [o.rms_px for o in others.values() if set(LENS_MODELS[o.model]) <= terms]
    if not fit.finite() or any(fit.rms_px > r * (1.0 + NESTED_RMS_TOLERANCE) for r in nested):
        return False
    if start is None:
        return True
    n_points = board.n_residuals() // 2
    rss, rss0 = fit.rms_px**2 * n_points, start.rms_px**2 * n_points
    dropped = [DIST_INDEX[t] for t in LENS_MODELS[start.model] if t not in terms]
    if not dropped:
        return rss <= rss0 * (1.0 + NESTED_RMS_TOLERANCE) ** 2
    s2 = rss0 / max(board.n_residuals() - board.n_unknowns(start.model, len(start.keys)), 1)
    std = start.std_intrinsics[[4 + i for i in dropped]]
    wald = float(np.sum((start.dist[dropped] / np.where(std > 0, std, np.inf)) ** 2))
    return rss <= rss0 + s2 * (2.0 * wald + 10.0)


def lens_model_evidence(fit: LensFit, board: BoardViews) -> dict[str, Any]:
    """A fit's evidence: its residual sum of squares and Bayesian information criterion over the views' corners.

    ``BIC = n ln(RSS / n) + k ln(n)``, n the residual coordinates, k every unknown of the bundle (the intrinsics,
    6 per view, the released board points).

    Parameters
    ----------
    fit : LensFit
    board : BoardViews
        The views fitted.

    Returns
    -------
    dict
        ``model``, ``n_params`` (intrinsics), ``rms_px``, ``rss_px2`` (px^2), ``bic`` (None when not finite),
        ``finite`` (K and dist), ``monotonic`` (:func:`_radial_monotonic`).
    """
    rss = 0.0
    for k, rv, tv in zip(fit.keys, fit.rvecs, fit.tvecs, strict=True):
        proj, _ = cv2.projectPoints(
            fit.board_points, np.asarray(rv).reshape(3), np.asarray(tv).reshape(3), fit.K, fit.dist
        )
        rss += float(np.sum((proj.reshape(-1, 2) - board.image_points[k]) ** 2))
    n_res = board.n_residuals()
    n_int = len(lens_model_params(fit.model))
    k_all = board.n_unknowns(fit.model, len(fit.keys))
    bic = n_res * np.log(max(rss, 1e-300) / n_res) + k_all * np.log(n_res)
    return {
        "model": fit.model,
        "n_params": n_int,
        "rms_px": fit.rms_px,
        "rss_px2": rss,
        "bic": float(bic) if np.isfinite(bic) else None,
        "finite": fit.finite(),
        "monotonic": _radial_monotonic(fit.K, fit.dist, board.image_size),
    }


def _judge_tangential(usable: list[dict[str, Any]], fits: Mapping[str, LensFit], corner_radius: float) -> None:
    """Mark each usable ``-radial`` model allowed only when the matching full fit bounds the tangential terms' effect
    at the image's corner (``(|p| + 2 std) 3 r_c^2 f``, px) below :data:`TANGENTIAL_BOUND_PX`."""
    for e in usable:
        if e["model"].endswith("-radial"):
            full = fits[e["model"].removesuffix("-radial")]
            bound = (
                float(np.max(np.abs(full.dist[2:4]) + 2 * full.std_intrinsics[6:8]))
                * 3
                * corner_radius**2
                * float(full.K[0, 0])
            )
            e["tangential_bound_px"] = bound
            e["allowed"] = bound < TANGENTIAL_BOUND_PX


def _judge_rational(usable: list[dict[str, Any]], coverage: float) -> None:
    """Mark the rational models not allowed when the views reach less than :data:`MIN_FIELD_COVERAGE`.

    OpenCV's rational model adds a denominator whose k4-k6 all but repeat k1-k3 over the views' radius: fitted to
    views that stay short of the image's corners, it lowers the corners' RSS by bending where no corner is, and its
    extrapolation there is undetermined.
    """
    if coverage >= MIN_FIELD_COVERAGE:
        return
    for e in usable:
        if e["model"].startswith("rational"):
            e["allowed"] = False
            e["not_allowed_because"] = (
                f"the board views reach {100 * coverage:.0f}% of the image's corner radius, less than "
                f"{100 * MIN_FIELD_COVERAGE:.0f}%: a rational model's extra terms are not determined there"
            )


def _field_coverage(fit: LensFit, board: BoardViews) -> tuple[float, float]:
    """The views' largest undistorted radius and the image corners', normalized, under ``fit``'s camera."""
    return _corner_radius_norm(fit.K, fit.dist, board.image_size, board.stacked_pixels())


def choose_lens_model(requested: str, fits: Mapping[str, LensFit], board: BoardViews) -> LensChoice:
    """The lens model kept among the fitted candidates, with every candidate's evidence.

    ``requested`` a model: that one. ``"auto"``: the lowest BIC (:func:`lens_model_evidence`) among the models whose
    fit is finite and whose radial map rises over the image (no fold, no pole), with two exceptions because neither
    criterion sees beyond the board views while the rods that refine the camera afterwards reach the image's
    corners: a ``-radial`` model only when the matching full fit bounds the tangential terms' effect at the corner
    below :data:`TANGENTIAL_BOUND_PX`, no rational model when the views reach less than :data:`MIN_FIELD_COVERAGE`
    of the corner radius; and a chosen ``k1k2`` becomes ``k1k2k3`` then (promoted: over a smaller radius k1, k2
    absorb a sixth-order term that shows only beyond it; kept as a parameter with its wide uncertainty, the rods
    pin it).

    Parameters
    ----------
    requested : str
        ``"auto"`` or a key of :data:`LENS_MODELS`.
    fits : mapping of str to LensFit
        The candidates fitted to ``board``'s views (with ``auto``, every model of :data:`LENS_MODELS`).
    board : BoardViews

    Returns
    -------
    LensChoice
    """
    evidence = [lens_model_evidence(f, board) for f in fits.values()]
    auto = requested == "auto"
    usable = [e for e in evidence if e["finite"] and e["bic"] is not None and (not auto or e["monotonic"])]
    if auto:
        reach0, corner0 = _field_coverage(fits["k1k2"], board)
        _judge_tangential(usable, fits, corner0)
        if corner0 > 0:
            _judge_rational(usable, reach0 / corner0)
        allowed = [e for e in usable if e.get("allowed", True)]
        chosen = min(allowed, key=lambda e: e["bic"])["model"] if allowed else "k1k2"
    else:
        chosen = next(iter(fits))
    lowest = chosen
    if auto and chosen.startswith("k1k2") and not chosen.startswith("k1k2k3"):
        # views that do not reach the image's corners cannot tell whether the lens has a sixth-order term
        reach, corner = _field_coverage(fits[chosen], board)
        if corner > 0 and reach / corner < MIN_FIELD_COVERAGE:
            chosen = chosen.replace("k1k2", "k1k2k3", 1)
    best_bic = min((e["bic"] for e in usable), default=0.0)
    for e in evidence:
        e["delta_bic"] = None if e["bic"] is None else float(e["bic"] - best_bic)
    return LensChoice(chosen, lowest, lowest != chosen, evidence)


def refine_intrinsics(fit: LensFit, board: BoardViews, weight_views: bool = True) -> RefinedIntrinsics:
    """The chosen fit's bundle refined with each view weighted by its noise, and the intrinsics' covariance.

    OpenCV minimises the plain sum of squares; with ``weight_views`` (and enough degrees of freedom per view,
    :data:`calib.camera.bundle.MIN_VIEW_DOF`) each view is weighted by its corners' noise variance estimated from
    its
    residuals (:func:`calib.camera.bundle.refine_weighted`) and the covariance is the weighted fit's; otherwise
    OpenCV's
    estimate and ``s^2 (J^T J)^-1``.

    Parameters
    ----------
    fit : LensFit
        The chosen model's fit.
    board : BoardViews
        The views fitted.
    weight_views : bool

    Returns
    -------
    RefinedIntrinsics
    """
    names = lens_model_params(fit.model)
    bundle = Bundle.of(
        fit.K,
        fit.dist,
        fit.board_points,
        [board.image_points[k] for k in fit.keys],
        list(fit.rvecs),
        list(fit.tvecs),
        board.fixed_point,
        names,
    )
    view_sigma = None
    converged = True
    if weight_views and view_dof(bundle) > MIN_VIEW_DOF:
        bundle, view_var, converged = refine_weighted(bundle)
        view_sigma = np.sqrt(view_var)
    cov, d_board = bundle_covariance(bundle, None if view_sigma is None else view_sigma**2)
    return RefinedIntrinsics(bundle, names, cov, d_board, view_sigma, converged, max(fit.dist.size, 5))


def _lens_warnings(choice: LensChoice, coverage: float, converged: bool) -> list[str]:
    """What the calibration's ``lens_model.warnings`` say: a promoted model, a field the views do not cover, a
    weighted refinement that did not converge."""
    warnings = []
    if choice.promoted:
        warnings.append(
            f"lens model {choice.chosen} instead of {choice.lowest_bic} (lowest BIC): the board views reach "
            f"{100 * coverage:.0f}% of the image's corner radius, too little to exclude a sixth-order term; it is "
            "kept with its calibration uncertainty for the rods to pin"
        )
    elif coverage < MIN_FIELD_COVERAGE:
        warnings.append(
            f"the board views reach {100 * coverage:.0f}% of the image's corner radius: the distortion beyond "
            "is extrapolated (higher-order terms there are not determined; present the board near the corners)"
        )
    if not converged:
        warnings.append(
            f"lens model {choice.chosen}: the views-weighted refinement did not converge within {REFINE_MAX_NFEV} "
            "evaluations a pass: the board views do not determine this model well (its coefficients trade off along "
            "flat directions); views near the image's corners, or a model with fewer terms, would"
        )
    return warnings


def intrinsics_result(
    board: BoardViews, choice: LensChoice, refined: RefinedIntrinsics, requested: str
) -> IntrinsicsResult:
    """The calibration's outcome: the camera with its ``calibration`` record, the views' RMS, poses and board.

    Parameters
    ----------
    board : BoardViews
        The views kept and rejected.
    choice : LensChoice
        The lens model kept and the candidates' evidence.
    refined : RefinedIntrinsics
        The chosen model's refined bundle and covariance.
    requested : str
        The lens model asked for (``auto`` or a model).

    Returns
    -------
    IntrinsicsResult
    """
    b = refined.bundle
    K, dist, new_obj, keys = b.K, refined.dist, b.board_points, board.keys
    w, h = board.image_size
    res_v = b.residuals()
    per_view = np.array([float(np.sqrt(np.mean(r**2))) for r in res_v])
    rms = float(np.sqrt(np.mean(np.concatenate(res_v) ** 2)))
    images = [board.image_points[k] for k in keys]
    profile = radial_residual_profile(K, dist, new_obj, images, b.rvecs, b.tvecs, (w, h))
    reach, corner = _corner_radius_norm(K, dist, (w, h), np.vstack(images))
    coverage = reach / corner if corner > 0 else 1.0
    lens_info = {
        "chosen": choice.chosen,
        "requested": requested,
        "lowest_bic": choice.lowest_bic,
        "criterion": "BIC = n ln(RSS/n) + k ln(n) over the board views' corners" if requested == "auto" else "given",
        "candidates": choice.evidence,
        "n_residuals": board.n_residuals(),
        "field_coverage": float(coverage),
        "residual_profile": profile,
        "warnings": _lens_warnings(choice, coverage, refined.converged),
    }
    cov = refined.covariance
    std = {n: 0.0 for n in _STD_NAMES}  # the fixed coefficients: 0, as OpenCV reports them
    std.update({n: float(np.sqrt(cov[i, i])) for i, n in enumerate(refined.names)})
    sigma = refined.view_sigma_px
    calibration = {
        "rms_px": float(rms),
        "n_views": len(keys),
        "std": std,
        "covariance_params": list(refined.names),
        "covariance": cov.tolist(),
        "method": "cv2.calibrateCameraRO" + (", views weighted by their noise" if sigma is not None else ""),
        "view_sigma_px": None if sigma is None else [float(x) for x in sigma],
        "lens_model": lens_info,
        "board_points": {
            "ids": board.ids.tolist(),
            "points_m": new_obj.tolist(),
            "d_intrinsics": refined.d_board.tolist(),
        },
    }
    cam = CameraModel(K, dist, w, h, {"calibration": calibration})
    res = IntrinsicsResult(
        cam,
        float(rms),
        {k: float(e) for k, e in zip(keys, per_view, strict=True)},
        std,
        board.rejected,
        new_obj,
        board.ids,
        {
            k: (np.asarray(r).reshape(3), np.asarray(t).reshape(3))
            for k, r, t in zip(keys, b.rvecs, b.tvecs, strict=True)
        },
    )
    res.lens_model = lens_info
    return res


def calibrate_intrinsics(
    views: Mapping[int, tuple[ArrayLike, ArrayLike, object]],
    image_size: tuple[int, int],
    board_ids: ArrayLike,
    board_points: ArrayLike,
    settings: IntrinsicsSettings | None = None,
    **overrides: Any,
) -> IntrinsicsResult:
    """Intrinsic calibration from ChArUco views, refining the board's geometry (``calibrateCameraRO``).

    The stages, each a function of its own:

    1. :func:`select_board_views`: the views where every corner was detected (``calibrateCameraRO``, Strobl &
       Hirzinger's "releasing object" method, needs the same object points in every view).
    2. :func:`reject_outlier_views`: views whose RMS reprojection error exceeds
       ``max(outlier_factor * median, outlier_floor_px)`` rejected, the worst first (fitted with ``k1k2k3`` when
       the model is ``auto``).
    3. :func:`fit_lens_candidates`: each candidate lens model fitted to the same views (one with a given model,
       every one of :data:`LENS_MODELS` with ``auto``; with ``shared_start``, those of :data:`SHARED_START_MODELS`
       from the outlier test's fit).
    4. :func:`choose_lens_model`: with ``auto``, the lowest Bayesian information criterion
       ``BIC = n ln(RSS / n) + k ln(n)`` (n: residual coordinates, k: every unknown of the bundle -- intrinsics,
       6 per view, the released board points; only the distortion count differs between candidates), with the
       exceptions it lists.
    5. :func:`refine_intrinsics`: the views-weighted refinement of the chosen model's bundle and its covariance.
    6. :func:`intrinsics_result`: the camera with its ``calibration`` record.

    Why BIC rather than cross-validation over views: the candidates are nested and fitted to the same corners whose
    noise is close to independent Gaussian, for which BIC approximates the models' posterior odds and is consistent
    (it picks the true model as views are added, where AIC keeps overfitting by a fixed margin); held-out views
    would need one calibration per candidate and fold (some 30 instead of 6) and score mostly the held-out poses'
    own noise.

    The evidence per candidate (RMS, RSS, BIC, parameter count) is in the camera's ``calibration.lens_model``, with
    the field coverage and the chosen model's radial residual profile (:func:`radial_residual_profile`), the model
    error the methods carry into their standard deviations (``std_breakdown.lens_model``); ``lowest_bic`` keeps
    BIC's own choice, ``warnings`` say why it was overruled or that the views do not cover the field. The per-view
    noise of the weighted fit is in ``calibration.view_sigma_px``.

    Parameters
    ----------
    views : mapping of int to (ids, image_points, unused)
        Per view key: detected corner ids (N,), their pixels (N, 2), and a free slot (ignored).
    image_size : tuple of int
        ``(width, height)``, pixels.
    board_ids : array_like of int, shape (M,)
        All corner ids of the board.
    board_points : array_like, shape (M, 3)
        Nominal corner coordinates in the board frame, metres.
    settings : IntrinsicsSettings, optional
        Default: ``IntrinsicsSettings()``.
    **overrides
        Fields of :class:`IntrinsicsSettings` by name (``lens_model="auto"``, ``weight_views=False``, ...), replacing
        those of ``settings``.

    Returns
    -------
    IntrinsicsResult
        The camera (K in pixels, its ``calibration`` record), RMS (px), per-view RMS, stds, rejected views, the
        refined board (metres) and the views' poses.

    Raises
    ------
    InputError
        Fewer than ``min_views`` usable views; an unknown lens model.
    TypeError
        An override that is no field of :class:`IntrinsicsSettings`.
    """
    opts = replace(settings or IntrinsicsSettings(), **overrides)
    model = opts.requested_model
    if model != "auto":
        lens_model_params(model)  # raises for an unknown name
    # one BLAS thread: the bundle's matrices are small, more threads only spin (and change the last digits with the
    # machine's core count)
    with threadpool_limits(limits=1):
        return _calibrate(views, image_size, board_ids, board_points, opts, model)


def _calibrate(
    views: Mapping[int, tuple[ArrayLike, ArrayLike, object]],
    image_size: tuple[int, int],
    board_ids: ArrayLike,
    board_points: ArrayLike,
    opts: IntrinsicsSettings,
    model: str,
) -> IntrinsicsResult:
    """:func:`calibrate_intrinsics`' stages, in order."""
    board = select_board_views(views, board_ids, board_points, image_size, opts.refine_object)
    first = "k1k2k3" if model == "auto" else model
    board, first_fit = reject_outlier_views(board, first, opts)
    candidates = list(LENS_MODELS) if model == "auto" else [model]
    fits = fit_lens_candidates(board, candidates, {first: first_fit}, first_fit if opts.shared_start else None)
    choice = choose_lens_model(model, fits, board)
    refined = refine_intrinsics(fits[choice.chosen], board, opts.weight_views)
    return intrinsics_result(board, choice, refined, model)


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
