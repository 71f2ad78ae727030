"""The intrinsic calibration's bundle: its Jacobian, the per-view weighted refinement and the covariance.

The bundle's unknowns are the intrinsics (``names``: fx, fy, cx, cy [px] and the lens model's distortion
coefficients), every view's ``camera_from_board`` (rotation vector [rad], translation [m]) and, with the
releasing-object method (``fixed_point >= 0``), the board's corner coordinates [m] less OpenCV's gauge (the first
point, the ``fixed_point``-th one and the last one's z are fixed).

Why a weighted refinement after ``cv2.calibrateCameraRO``: OpenCV minimises the plain sum of squared reprojection
errors, the right estimator only when every corner is equally precise. Corner precision varies from view to view
(distance, tilt, blur, the pattern's sampling by the pixel grid): on the image-level twin's camera phases a view's
RMS ranges from 0.02 to 0.2 px (5-95%; 100 phases of 30 views, errors against the rendered truth; a one-off
study, docs/vision.md). Weighting each
view by its own residual variance (iteratively reweighted, :data:`WEIGHTING_ITERATIONS` passes) halves the
intrinsics' error there (fx RMS 1.52 -> 0.70 px, cx 3.6 -> 1.7 px, k2 0.017 -> 0.0094; lens model chosen by BIC)
and its reported standard deviations match it (RMS / mean std 0.85-1.08 over fx, fy, cx, cy, k1, k2), where the
plain fit's ``s^2 (J^T J)^-1`` was 11-12% too small on fx, fy: the noisier views are also the tilted ones that
pin the focal length.

Units: pixels, metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

Array = NDArray[np.float64]

#: OpenCV's distortion coefficients by name: their index in ``dist`` (and, plus 10, in ``cv2.projectPoints``' Jacobian).
DIST_INDEX = {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4, "k4": 5, "k5": 6, "k6": 7}
#: evaluations allowed to each pass of :func:`refine_weighted`: a bundle the views determine converges in 5-10; one
#: they do not (OpenCV's rational model on views that stay short of the image's corners, its k4-k6 all but
#: collinear with k1-k3) crawls along the flat directions for scipy's default 100 per unknown, 23000 evaluations
#: and about ten minutes a pass on a 30-view phase
REFINE_MAX_NFEV = 100
#: reweighting passes of :func:`refine_weighted` (the weights settle in two or three)
WEIGHTING_ITERATIONS = 3
#: fewer degrees of freedom per view than this and the views are not weighted (their variances too uncertain)
MIN_VIEW_DOF = 10.0
#: a view's noise std is kept at or above this fraction of the pooled one: one view cannot take over the fit
MIN_VIEW_SIGMA_FRACTION = 0.1

__all__ = [
    "DIST_INDEX",
    "Bundle",
    "bundle_covariance",
    "estimated_weights_factor",
    "projection_columns",
    "refine_weighted",
    "spd_inverse",
    "view_dof",
    "view_variances",
]


def projection_columns(names: tuple[str, ...] | list[str]) -> list[int]:
    """Columns of ``cv2.projectPoints``' Jacobian (rvec 3, tvec 3, fx, fy, cx, cy, dist...) for ``names``.

    Parameters
    ----------
    names : sequence of str
        Intrinsic parameter names (fx, fy, cx, cy and keys of :data:`DIST_INDEX`).

    Returns
    -------
    list of int
        One column per name.
    """
    base = {"fx": 6, "fy": 7, "cx": 8, "cy": 9}
    return [base[n] if n in base else 10 + DIST_INDEX[n] for n in names]


@dataclass
class Bundle:
    """A calibration bundle's state.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (5,) or (8,)
        OpenCV's distortion vector, long enough for every coefficient of ``names``.
    board_points : ndarray, shape (M, 3)
        Metres.
    rvecs, tvecs : list of ndarray, shape (3,)
        Per view, ``camera_from_board``.
    image_points : list of ndarray, shape (M, 2)
        Per view, the detected pixels in the order of ``board_points``.
    fixed_point : int
        ``iFixedPoint`` of the releasing-object method, or -1 when the board points are not refined.
    names : tuple of str
        The estimated intrinsics.
    """

    K: Array
    dist: Array
    board_points: Array
    rvecs: list[Array]
    tvecs: list[Array]
    image_points: list[Array]
    fixed_point: int
    names: tuple[str, ...]

    @classmethod
    def of(
        cls,
        K: ArrayLike,
        dist: ArrayLike,
        board_points: ArrayLike,
        image_points: list[ArrayLike],
        rvecs: list[ArrayLike],
        tvecs: list[ArrayLike],
        fixed_point: int = -1,
        names: tuple[str, ...] | list[str] = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    ) -> Bundle:
        """Validated copy (float64; ``dist`` padded with zeros to hold every coefficient of ``names``).

        Parameters
        ----------
        K : array_like, shape (3, 3)
            Camera matrix, pixels.
        dist : array_like, shape (n,)
            OpenCV's distortion coefficients.
        board_points : array_like, shape (M, 3)
            Metres.
        image_points : list of array_like, shape (M, 2)
            Per view, the detected pixels in the order of ``board_points``.
        rvecs, tvecs : list of array_like, shape (3,)
            Per view, ``camera_from_board`` (radians, metres).
        fixed_point : int
            ``iFixedPoint`` of the releasing-object method, or -1 when the board points are not refined.
        names : sequence of str
            The estimated intrinsics.

        Returns
        -------
        Bundle

        Raises
        ------
        ValueError
            Image points of another shape than the board's, or as many views as poses.
        """
        d = np.asarray(dist, dtype=np.float64).reshape(-1)
        need = max([c - 9 for c in projection_columns(names)] + [d.size])
        if need > d.size:
            d = np.concatenate([d, np.zeros((8 if need > 5 else 5) - d.size)])
        obj = np.asarray(board_points, dtype=np.float64).reshape(-1, 3)
        imgs = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in image_points]
        for i, p in enumerate(imgs):
            if p.shape[0] != obj.shape[0]:
                raise ValueError(f"image_points[{i}] must have shape ({obj.shape[0]}, 2), got {p.shape}")
        if not (len(imgs) == len(rvecs) == len(tvecs)):
            raise ValueError(f"{len(imgs)} views but {len(rvecs)} rvecs and {len(tvecs)} tvecs")
        return cls(
            np.asarray(K, dtype=np.float64).copy(),
            d,
            obj.copy(),
            [np.asarray(r, dtype=np.float64).reshape(3).copy() for r in rvecs],
            [np.asarray(t, dtype=np.float64).reshape(3).copy() for t in tvecs],
            imgs,
            int(fixed_point),
            tuple(names),
        )

    @property
    def free_board(self) -> NDArray[np.int_]:
        """Flat indices (into ``board_points.ravel()``) of the released board coordinates."""
        m = self.board_points.shape[0]
        if not 0 <= self.fixed_point < m:
            return np.zeros(0, dtype=int)
        free = np.ones((m, 3), dtype=bool)
        free[0] = free[self.fixed_point] = False
        free[m - 1, 2] = False
        return np.flatnonzero(free.ravel())

    @property
    def n_params(self) -> int:
        return len(self.names) + 6 * len(self.image_points) + self.free_board.size

    def vector(self) -> Array:
        """The unknowns as one vector.

        Returns
        -------
        ndarray, shape (n_params,)
            The intrinsics (``names``' order; px, dimensionless), (rvec [rad], tvec [m]) per view, the free board
            coordinates (:attr:`free_board`, metres).
        """
        intr = []
        for c in projection_columns(self.names):
            intr.append(
                {6: self.K[0, 0], 7: self.K[1, 1], 8: self.K[0, 2], 9: self.K[1, 2]}[c] if c < 10 else self.dist[c - 10]
            )
        poses = [np.concatenate([r, t]) for r, t in zip(self.rvecs, self.tvecs, strict=True)]
        return np.concatenate([np.asarray(intr), *poses, self.board_points.ravel()[self.free_board]])

    def with_vector(self, x: ArrayLike) -> Bundle:
        """A copy holding other values of the unknowns.

        Parameters
        ----------
        x : array_like, shape (n_params,)
            :meth:`vector`'s layout.

        Returns
        -------
        Bundle
            Sharing ``image_points`` with this one.
        """
        x = np.asarray(x, dtype=np.float64)
        ni, nv = len(self.names), len(self.image_points)
        K, d = self.K.copy(), self.dist.copy()
        for j, c in enumerate(projection_columns(self.names)):
            if c < 10:
                K[{6: (0, 0), 7: (1, 1), 8: (0, 2), 9: (1, 2)}[c]] = x[j]
            else:
                d[c - 10] = x[j]
        obj = self.board_points.ravel().copy()
        obj[self.free_board] = x[ni + 6 * nv :]
        return Bundle(
            K,
            d,
            obj.reshape(-1, 3),
            [x[ni + 6 * v : ni + 6 * v + 3].copy() for v in range(nv)],
            [x[ni + 6 * v + 3 : ni + 6 * v + 6].copy() for v in range(nv)],
            self.image_points,
            self.fixed_point,
            self.names,
        )

    def residuals(self) -> list[Array]:
        """Projected minus detected pixels.

        Returns
        -------
        list of ndarray, shape (2 M,)
            Per view, ``(du, dv)`` per corner, flattened, pixels.
        """
        return [self._view(v, jacobian=False)[0] for v in range(len(self.image_points))]

    def jacobian(self) -> tuple[list[Array], list[Array]]:
        """The residuals and their Jacobian over :meth:`vector`.

        Returns
        -------
        list of ndarray, shape (2 M,)
            Per view, the residuals (:meth:`residuals`), pixels.
        list of ndarray, shape (2 M, n_params)
            Per view, their Jacobian.
        """
        out = [self._view(v, jacobian=True) for v in range(len(self.image_points))]
        return [r for r, _ in out], [J for _, J in out]

    def _view(self, v: int, jacobian: bool) -> tuple[Array, Array]:
        obj = self.board_points
        proj, jac = cv2.projectPoints(obj, self.rvecs[v], self.tvecs[v], self.K, self.dist)
        r = (proj.reshape(-1, 2) - self.image_points[v]).reshape(-1)
        if not jacobian:
            return r, np.zeros((0, 0))
        m, ni, nv = obj.shape[0], len(self.names), len(self.image_points)
        free = self.free_board
        J = np.zeros((2 * m, self.n_params))
        J[:, :ni] = jac[:, projection_columns(self.names)]
        J[:, ni + 6 * v : ni + 6 + 6 * v] = jac[:, 0:6]
        if free.size:
            R, _ = cv2.Rodrigues(self.rvecs[v])
            dp_dX = jac[:, 3:6].reshape(m, 2, 3) @ R  # d pixel / d board point: d/dt rotated
            blocks = np.zeros((2 * m, 3 * m))
            diagonal = np.arange(m)
            blocks.reshape(m, 2, m, 3)[diagonal, :, diagonal, :] = dp_dX  # point i's 2 x 3 block on the diagonal
            J[:, ni + 6 * nv :] = blocks[:, free]
        return r, J


def view_variances(residuals: list[Array], n_params: int) -> Array:
    """Per view, its corners' noise variance (px^2) from its residuals.

    ``|r_v|^2 / (n_v (N - p) / N)``: each view's share of the bundle's degrees of freedom (N residuals, p unknowns),
    kept at or above ``(MIN_VIEW_SIGMA_FRACTION * s)^2`` of the pooled ``s^2 = |r|^2 / (N - p)``.

    Parameters
    ----------
    residuals : list of ndarray, shape (n_v,)
        Per view, its residuals, pixels.
    n_params : int
        The bundle's unknowns.

    Returns
    -------
    ndarray, shape (V,)
        Per view, px^2.
    """
    n = sum(r.size for r in residuals)
    dof = max(n - n_params, 1)
    pooled = sum(float(r @ r) for r in residuals) / dof
    frac = dof / n
    return np.array(
        [max(float(r @ r) / (r.size * frac), MIN_VIEW_SIGMA_FRACTION**2 * pooled, 1e-12) for r in residuals]
    )


def refine_weighted(
    bundle: Bundle, iterations: int = WEIGHTING_ITERATIONS, max_nfev: int = REFINE_MAX_NFEV
) -> tuple[Bundle, Array, bool]:
    """Iteratively reweighted bundle adjustment: each view weighted by its corners' noise variance.

    Starts from ``bundle`` (OpenCV's unweighted optimum); each pass sets the weights from the current residuals
    (:func:`view_variances`) and minimises the weighted squares with ``scipy.optimize.least_squares``.

    Parameters
    ----------
    bundle : Bundle
        The start.
    iterations : int
        Reweighting passes.
    max_nfev : int
        Evaluations allowed to each pass.

    Returns
    -------
    Bundle
        The refined state.
    ndarray, shape (V,)
        Each view's noise variance (px^2) at the refined state: the weights of :func:`bundle_covariance`.
    bool
        Whether every pass converged within ``max_nfev`` evaluations (False: the views do not determine the bundle
        well; the state is the last pass's, never worse than the start).
    """
    cur = bundle
    converged = True
    for _ in range(iterations):
        var = view_variances(cur.residuals(), cur.n_params)
        w = np.concatenate([np.full(p.size, 1.0 / np.sqrt(s)) for p, s in zip(cur.image_points, var, strict=True)])
        base = cur

        def fun(x: Array, base: Bundle = base, w: Array = w) -> Array:
            return np.concatenate(base.with_vector(x).residuals()) * w

        def jac(x: Array, base: Bundle = base, w: Array = w) -> Array:
            return np.vstack(base.with_vector(x).jacobian()[1]) * w[:, None]

        sol = least_squares(
            fun, cur.vector(), jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=max_nfev
        )
        if not np.all(np.isfinite(sol.x)):
            converged = False
            break
        converged &= bool(sol.status > 0)
        cur = cur.with_vector(sol.x)
    return cur, view_variances(cur.residuals(), cur.n_params), converged


def view_dof(bundle: Bundle) -> float:
    """Degrees of freedom of one view's noise variance (:func:`view_variances`): its mean share of the bundle's.

    Parameters
    ----------
    bundle : Bundle

    Returns
    -------
    float
        ``(N - p) / V``: residual coordinates less unknowns, per view.
    """
    n = sum(p.size for p in bundle.image_points)
    return float(n - bundle.n_params) / len(bundle.image_points)


def estimated_weights_factor(bundle: Bundle) -> float:
    """``nu / (nu - 4)``: the weighted fit's covariance inflated for weights estimated from ``nu`` dof per view.

    ``(sum J_v^T J_v / var_v)^-1`` holds for known variances. Estimated from each view's own residuals
    (:func:`view_variances`), the weights ``1 / var_v`` are high by ``nu / (nu - 2)`` on average (the mean of an
    inverse chi-square) and their noise adds as much again to the estimate's variance: ``nu / (nu - 4)`` to second
    order. Measured against the truth on the image-level twin's camera phases (k1k2 lens, 100 phases each): the
    intrinsics' mean Mahalanobis distance (chi-square(8): 8) goes from 10.3 to 8.4 with 20 views (nu 21.7) and from
    9.7 to 8.0 with 30 views (nu 22.5).

    Parameters
    ----------
    bundle : Bundle

    Returns
    -------
    float
        The factor, above 1.

    Raises
    ------
    ValueError
        :data:`MIN_VIEW_DOF` or fewer degrees of freedom per view.
    """
    nu = view_dof(bundle)
    if nu <= MIN_VIEW_DOF:
        raise ValueError(f"{nu:.1f} degrees of freedom per view: too few to weight views (at least {MIN_VIEW_DOF})")
    return nu / (nu - 4.0)


def spd_inverse(S: Array, rel_floor: float = 1e-15) -> Array:
    """Inverse of a symmetric positive semi-definite information matrix (n, n), positive semi-definite itself.

    The unknowns' scales differ by many orders (fx in px, a rational model's k6 dimensionless), and a model the views
    barely determine makes the information nearly singular: ``np.linalg.inv`` then returned variances below zero
    (a NaN std in the camera file). Here the matrix is scaled to a unit diagonal, decomposed, and its eigenvalues
    floored at ``rel_floor`` of the largest: an undetermined direction gets a huge variance, never a negative one.

    Parameters
    ----------
    S : ndarray, shape (n, n)
        The information matrix (inverse units squared of the unknowns).
    rel_floor : float
        The eigenvalues' floor, relative to the largest (of the unit-diagonal matrix).

    Returns
    -------
    ndarray, shape (n, n)
        The covariance, symmetric positive semi-definite.
    """
    S = 0.5 * (S + S.T)
    d = np.sqrt(np.clip(np.diag(S), 1e-300, None))
    w, V = np.linalg.eigh(S / np.outer(d, d))
    w = np.maximum(w, rel_floor * max(float(w.max()), 1e-300))
    inv = (V / w) @ V.T
    return 0.5 * (inv + inv.T) / np.outer(d, d)


def bundle_covariance(bundle: Bundle, view_var: ArrayLike | None = None, estimated: bool = True) -> tuple[Array, Array]:
    """Covariance of the intrinsics (marginalised, Schur complement) and the board points' regression on them.

    ``view_var`` (V,) px^2: each view's noise variance estimated from its residuals, the weights of the fit:
    ``(sum J_v^T J_v / var_v)^-1``, times :func:`estimated_weights_factor` when the variances were ``estimated`` from
    the views' residuals (:func:`refine_weighted`; False: known variances).
    None: one variance for every corner, the residuals' ``s^2``: ``s^2 (J^T J)^-1`` (the unweighted fit's, OpenCV's).

    Parameters
    ----------
    bundle : Bundle
        At the fit's optimum.
    view_var : array_like, shape (V,), optional
        Per view, its corners' noise variance, px^2.
    estimated : bool
        Whether ``view_var`` was estimated from the views' residuals.

    Returns
    -------
    ndarray, shape (n, n)
        Over ``bundle.names``: pixels for fx, fy, cx, cy; dimensionless for the distortion coefficients.
    ndarray, shape (M, 3, n)
        ``Cov(X, I) Cov(I, I)^-1``: how the refined board points move when the intrinsics do, given the
        calibration's data (Gaussian conditioning); zero for the fixed coordinates.
    """
    rs, Js = bundle.jacobian()
    n, ni = bundle.n_params, len(bundle.names)
    if view_var is None:
        n_res = sum(r.size for r in rs)
        s2 = sum(float(r @ r) for r in rs) / max(n_res - n, 1)
        var = np.full(len(rs), s2)
    else:
        var = np.asarray(view_var, dtype=np.float64).reshape(-1)
        if var.shape != (len(rs),) or not np.all(var > 0):
            raise ValueError(f"view_var must be ({len(rs)},) positive variances, got shape {var.shape}")
    info = np.zeros((n, n))
    for J, s2 in zip(Js, var, strict=True):
        info += J.T @ J / s2
    A, B, C = info[:ni, :ni], info[:ni, ni:], info[ni:, ni:]
    CinvBt = np.linalg.solve(C, B.T)  # (n - ni, ni)
    cov = spd_inverse(A - B @ CinvBt)
    if view_var is not None and estimated:
        cov *= estimated_weights_factor(bundle)
    m = bundle.board_points.shape[0]
    free = bundle.free_board
    reg = np.zeros((m * 3, ni))
    if free.size:  # Cov(others, I) = -C^-1 B^T Cov(I, I): the regression of the others on I is -C^-1 B^T
        reg[free] = -CinvBt[6 * len(rs) :]
    return 0.5 * (cov + cov.T), reg.reshape(m, 3, ni)
