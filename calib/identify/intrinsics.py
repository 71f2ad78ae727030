"""The camera intrinsics' uncertainty, carried to the observations the methods use (first order).

The intrinsics are calibrated once (the ``camera`` phase) and their error is common to every frame:
it does not average out over poses, so a method's standard deviations must include it. The image
extraction keeps what is needed to redo its geometry for other intrinsics:

* per rod, ``limbs_px`` (2, 5, 2): points of each fitted limb line in distorted pixels, from which
  the interpretation planes ``h`` (hence the direction ``u = h1 x h2``) are recomputed;
* per board pose, ``d_intrinsics`` (6, n): the pose's first-order change per unit change of the
  intrinsics (a left rotation in rad, then t in m);
* the camera's n x n covariance of its lens model's intrinsics, (fx, fy, cx, cy, k1, k2, p1, p2) for the
  default ``k1k2`` model (``calibration.covariance`` over ``calibration.covariance_params``; from
  the standard deviations alone when only they are known, fx and fy then fully correlated).

A method evaluates its measured quantities at the intrinsics moved by plus and minus one standard
deviation along each principal direction of that covariance (:func:`principal_steps`) and maps the
change through its estimator's gain.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from calib.camera.intrinsics import INTRINSICS_NAMES, intrinsics_names, moved_camera
from calib.formats.camera import CameraModel
from calib.formats.observations import Observations, PhaseArrays
from calib.numerics.transforms import rotvec_to_matrix

Array = NDArray[np.float64]


def intrinsics_prior(obs: Observations, refined: bool = True) -> tuple[CameraModel, Array] | None:
    """The extraction's camera and the covariance (n, n) of its intrinsics, or None when unknown.

    Order: the camera's ``calibration.covariance_params`` (:func:`calib.camera.intrinsics.intrinsics_names`: the
    chosen lens
    model's parameters, :data:`calib.camera.intrinsics.INTRINSICS_NAMES` for a calibration that names no lens
    model; px for fx,
    fy, cx, cy; dimensionless after). When the rods refined the camera (``calibration.covariance_refined``, the
    combined fit's posterior), that covariance is returned with ``refined`` (methods that do not use the rods); the
    calibration's own with ``refined=False`` (the combined method, which uses the rods again).

    Parameters
    ----------
    obs : Observations
        The observations whose extraction recorded the camera.
    refined : bool
        Return the rods' refined covariance when there is one.

    Returns
    -------
    tuple of (CameraModel, ndarray of shape (n, n)) or None
        The camera and its intrinsics' covariance (px^2 for fx, fy, cx, cy; dimensionless for the distortion).
    """
    extra = obs.document.model_extra or {}
    cam = (extra.get("extraction") or {}).get("camera") or {}
    calib = cam.get("calibration") or {}
    if not cam.get("K"):
        return None
    camera = CameraModel.from_dict(cam)
    names = intrinsics_names(camera)
    n = len(names)
    cov = calib.get("covariance_refined") if refined and calib.get("covariance_refined") else calib.get("covariance")
    if cov is not None and list(calib.get("covariance_params") or INTRINSICS_NAMES) == list(names):
        C = np.asarray(cov, dtype=np.float64)
        if C.shape == (n, n) and np.all(np.isfinite(C)):
            return camera, 0.5 * (C + C.T)
    std = calib.get("std") or {}
    if not all(k in std for k in ("fx", "fy", "cx", "cy")):
        return None
    s = np.array([float(std.get(k, 0.0)) for k in names])
    C = np.diag(s**2)
    C[0, 1] = C[1, 0] = s[0] * s[1]  # one focal scale: the conservative choice without correlations
    return camera, C


def calibration_offset(obs: Observations) -> Array | None:
    """The calibration's intrinsics minus the extraction camera's, shape (n,), when the rods refined that camera.

    A camera refined by the rods (:func:`calib.vision.refine.refine_camera_by_rods`) records the shift it was moved by
    (``calibration.refined_by_rods.shift``); the calibration's own estimate is the camera minus that shift, and
    it, with the calibration's covariance, is the prior of a fit that uses the rods again. None when the camera
    was not refined.

    Parameters
    ----------
    obs : Observations
        The observations whose extraction recorded the camera.

    Returns
    -------
    ndarray, shape (n,), or None
        Minus the recorded shift, in ``covariance_params`` order (px for fx, fy, cx, cy; dimensionless after).
    """
    extra = obs.document.model_extra or {}
    calib = (((extra.get("extraction") or {}).get("camera") or {}).get("calibration")) or {}
    shift = (calib.get("refined_by_rods") or {}).get("shift")
    names = calib.get("covariance_params") or INTRINSICS_NAMES
    if not shift or not all(k in shift for k in names):
        return None
    return -np.array([float(shift[k]) for k in names])


def principal_steps(cov: Array, rel_tol: float = 1e-12) -> Array:
    """One standard deviation along each principal direction of ``cov`` (p, p), shape (n, p).

    Parameters
    ----------
    cov : ndarray, shape (p, p)
        A covariance (units of the parameters squared).
    rel_tol : float
        Eigenvalues below ``rel_tol`` times the largest are dropped (dimensionless).

    Returns
    -------
    ndarray, shape (n, p)
        One row per kept direction, in the parameters' units; n <= p.
    """
    w, V = np.linalg.eigh(np.asarray(cov, dtype=np.float64))
    keep = w > rel_tol * max(float(w.max()), 1e-300)
    return (V[:, keep] * np.sqrt(w[keep])).T


def perturbed_camera(camera: CameraModel, step: Array) -> CameraModel:
    """``camera`` with its intrinsics moved by ``step``.

    The intrinsics are :func:`calib.camera.intrinsics.intrinsics_names` (fx, fy, cx, cy, k1, k2, p1, p2 unless
    its calibration
    chose another lens model); a step of another length than the camera's list (a camera that lists no parameters)
    moves the first ``len(step)`` of :data:`calib.camera.intrinsics.INTRINSICS_NAMES`.

    Parameters
    ----------
    camera : CameraModel
        The camera.
    step : ndarray, shape (n,)
        The change of each intrinsic (px for fx, fy, cx, cy; dimensionless after).

    Returns
    -------
    CameraModel
        The moved camera, with ``camera``'s extra.
    """
    st = np.asarray(step, dtype=np.float64).reshape(-1)
    names = intrinsics_names(camera)
    if st.size != len(names):  # a camera that lists no parameters: the first len(step) of the eight
        names = INTRINSICS_NAMES[: st.size]
    out = moved_camera(camera, st, names)
    return CameraModel(out.K, out.dist, out.width, out.height, camera.extra)


def limb_planes_for(camera: CameraModel, limbs_px: Array, reference_h: Array) -> Array:
    """Interpretation planes of rods seen through ``camera``, from their limb samples.

    Parameters
    ----------
    camera : CameraModel
    limbs_px : ndarray, shape (M, 2, P, 2)
        Per rod and limb, points of the limb in distorted pixels.
    reference_h : ndarray, shape (M, 2, 3)
        The planes as measured: each result is signed like its reference.

    Returns
    -------
    ndarray, shape (M, 2, 3)
        Unit normals of the planes through the camera centre and each limb (normalized coordinates
        line through the undistorted points, total least squares).
    """
    L = np.asarray(limbs_px, dtype=np.float64)
    xn = camera.undistort_points(L.reshape(-1, 2)).reshape(L.shape)
    return planes_through(xn, reference_h)


def planes_through(xn: Array, reference_h: Array) -> Array:
    """Unit normals of the planes through the camera centre and each limb's points (total least squares line).

    Parameters
    ----------
    xn : ndarray, shape (M, 2, P, 2)
        Per rod and limb, the limb's points in normalized coordinates (dimensionless).
    reference_h : ndarray, shape (M, 2, 3)
        The planes as measured: each result is signed like its reference.

    Returns
    -------
    ndarray, shape (M, 2, 3)
        Unit plane normals.
    """
    c = xn.mean(axis=2)
    d = xn - c[:, :, None, :]
    # normal: the smallest-variance direction of the 2x2 scatter [[a, b], [b, e]] (closed form): the
    # line's direction is the largest eigenvector (b, lam - a) ~ (lam - e, b), rotated by 90 degrees
    a = np.einsum("mlp,mlp->ml", d[..., 0], d[..., 0])
    b = np.einsum("mlp,mlp->ml", d[..., 0], d[..., 1])
    e = np.einsum("mlp,mlp->ml", d[..., 1], d[..., 1])
    lam = 0.5 * (a + e) + np.hypot(0.5 * (a - e), b)
    t1 = np.stack([b, lam - a], axis=-1)
    t2 = np.stack([lam - e, b], axis=-1)
    t = np.where((np.abs(lam - a) > np.abs(lam - e))[..., None], t1, t2)
    n = np.stack([-t[..., 1], t[..., 0]], axis=-1)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    h = np.concatenate([n, -np.sum(n * c, axis=-1, keepdims=True)], axis=-1)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    return h * np.sign(np.sum(h * reference_h, axis=-1, keepdims=True))


def planes_through_jacobian(xn: Array, dxn: Array, reference_h: Array) -> tuple[Array, Array]:
    """:func:`planes_through` and its derivatives along given moves of the points (first order, exact).

    The line's normal is the scatter's smallest-variance eigenvector; it turns towards the line's direction by
    ``t^T dS n / (lambda_min - lambda_max)`` (eigenvector perturbation); the plane's normal then follows the line's
    normal and centroid through its normalisation.

    Parameters
    ----------
    xn : ndarray, shape (M, 2, P, 2)
        Per rod and limb, the limb's points in normalized coordinates (dimensionless).
    dxn : ndarray, shape (n, M, 2, P, 2)
        ``n`` moves of those points (per unit of each of ``n`` unknowns).
    reference_h : ndarray, shape (M, 2, 3)
        The planes as measured: each result is signed like its reference.

    Returns
    -------
    h : ndarray, shape (M, 2, 3)
        Unit plane normals, as :func:`planes_through` gives them.
    dh : ndarray, shape (n, M, 2, 3)
        Their derivatives per unit of each unknown.
    """
    h = planes_through(xn, reference_h)
    c = xn.mean(axis=2)
    d = xn - c[:, :, None, :]
    a = np.einsum("mlp,mlp->ml", d[..., 0], d[..., 0])
    b = np.einsum("mlp,mlp->ml", d[..., 0], d[..., 1])
    e = np.einsum("mlp,mlp->ml", d[..., 1], d[..., 1])
    root = np.hypot(0.5 * (a - e), b)
    gap = -2.0 * root  # lambda_min - lambda_max
    # the line's unit normal and direction, recovered from h (same sign as h: h = s [n, -n.c] / |.|)
    nn = h[..., :2] / np.linalg.norm(h[..., :2], axis=-1, keepdims=True)
    tt = np.stack([-nn[..., 1], nn[..., 0]], axis=-1)
    dc = dxn.mean(axis=3)  # (n, M, 2, 2)
    td = np.einsum("mlpi,mli->mlp", d, tt)
    nd = np.einsum("mlpi,mli->mlp", d, nn)
    tdx = np.einsum("kmlpi,mli->kmlp", dxn, tt)
    ndx = np.einsum("kmlpi,mli->kmlp", dxn, nn)
    tSn = np.einsum("kmlp,mlp->kml", tdx, nd) + np.einsum("mlp,kmlp->kml", td, ndx)
    dn = tt[None] * (tSn / gap[None])[..., None]  # (n, M, 2, 2)
    scale = np.linalg.norm(np.concatenate([nn, -np.sum(nn * c, axis=-1, keepdims=True)], axis=-1), axis=-1)
    dhp = np.concatenate(
        [dn, -(np.sum(dn * c[None], axis=-1, keepdims=True) + np.sum(nn[None] * dc, axis=-1, keepdims=True))], axis=-1
    )
    dh = (dhp - h[None] * np.sum(h[None] * dhp, axis=-1, keepdims=True)) / scale[None, ..., None]
    return h, dh


def board_sensitivities(obs: Observations, arrays: PhaseArrays, n: int | None = None) -> Array | None:
    """``d_intrinsics`` of the board poses of ``arrays`` (zeros where no board), or None if any lacks it.

    Parameters
    ----------
    obs : Observations
        The observations holding the boards.
    arrays : PhaseArrays
        The phase's arrays (which frames, which have a board).
    n : int, optional
        The intrinsics count each must have (default: the first board's, i.e. the camera's lens model's; 8 when no
        board has one).

    Returns
    -------
    ndarray, shape (N, 6, n), or None
        Per pose, d (left rotation, rad; t, m) / d intrinsic; None when a board lacks it or has another count.
    """
    if n is None:
        first = next(
            (
                b.d_intrinsics
                for i in arrays.index
                if (b := obs.frames[int(i)].board) is not None and b.d_intrinsics is not None
            ),
            None,
        )
        n = np.asarray(first).shape[-1] if first is not None else 8
    out = np.zeros((len(arrays), 6, n))
    for k, i in enumerate(arrays.index):
        if not arrays.has_board[k]:
            continue
        board = obs.frames[int(i)].board
        d = board.d_intrinsics if board is not None else None
        if d is None:
            return None
        a = np.asarray(d, dtype=np.float64)
        if a.shape != (6, n):
            return None
        out[k] = a
    return out


def perturbed_boards(arrays: PhaseArrays, sens: Array, step: Array) -> PhaseArrays:
    """The board poses of ``arrays`` as they would be measured with the intrinsics moved by ``step`` (n,).

    Parameters
    ----------
    arrays : PhaseArrays
        The phase's arrays with the measured board poses.
    sens : ndarray, shape (N, 6, n)
        The boards' sensitivities (:func:`board_sensitivities`), rad and m per unit of each intrinsic.
    step : ndarray, shape (n,)
        The change of the intrinsics (px for fx, fy, cx, cy; dimensionless after).

    Returns
    -------
    PhaseArrays
        ``arrays`` with ``board_R`` (N, 3, 3) and ``board_t`` (N, 3), m, moved to first order.
    """
    d = sens @ step  # (N, 6)
    R = np.einsum("nij,njk->nik", rotvec_to_matrix(d[:, :3]), arrays.board_R)
    return replace(arrays, board_R=R, board_t=arrays.board_t + d[:, 3:])


class LinearizedLimbs:
    """Limb samples' normalized coordinates for the intrinsics moved by the nuisance z, fast.

    The first-order guess ``xn0 + sum_j z_j dxn_j`` (``dxn_j`` the central difference over one
    standard deviation along principal direction j, ``steps`` (n, p) over the camera's p intrinsics,
    :func:`principal_steps`),
    then two Newton steps on the exact distortion model: equal to the iterative undistortion within
    1e-9 up to 5 standard deviations (tests/calib/test_intrinsics_propagation.py), points that do
    not converge are undistorted exactly.

    Parameters
    ----------
    camera : CameraModel
    steps : ndarray, shape (n, p)
    limbs_px : ndarray, shape (M, 2, P, 2)
        Per rod and limb, points of the limb in distorted pixels.
    """

    def __init__(self, camera: CameraModel, steps: Array, limbs_px: Array) -> None:
        L = np.asarray(limbs_px, dtype=np.float64)
        self.camera, self.steps, self.px = camera, np.asarray(steps, dtype=np.float64), L
        self.shape = L.shape
        flat = L.reshape(-1, 2)
        self.xn0 = camera.undistort_points(flat).reshape(L.shape)
        d = [
            (perturbed_camera(camera, st).undistort_points(flat) - perturbed_camera(camera, -st).undistort_points(flat))
            / 2.0
            for st in self.steps
        ]
        self.dxn = np.asarray(d).reshape((len(d), *L.shape)) if d else np.zeros((0, *L.shape))

    def subset(self, keep: Array) -> LinearizedLimbs:
        """The same for the rods ``keep`` (boolean mask or indices over M).

        Parameters
        ----------
        keep : ndarray
            Boolean mask (M,) or indices of the rods kept.

        Returns
        -------
        LinearizedLimbs
            The linearisation restricted to those rods.
        """
        out = object.__new__(LinearizedLimbs)
        out.camera, out.steps = self.camera, self.steps
        out.px, out.xn0, out.dxn = self.px[keep], self.xn0[keep], self.dxn[:, keep]
        out.shape = out.px.shape
        return out

    def points(self, z: Array) -> Array:
        """Normalized coordinates (M, 2, P, 2) of the limb samples for the nuisance ``z`` (n,).

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance, in standard deviations along each principal direction (dimensionless).

        Returns
        -------
        ndarray, shape (M, 2, P, 2)
            Normalized coordinates (dimensionless).
        """
        zz = np.asarray(z, dtype=np.float64)
        x = self.xn0 + np.tensordot(zz, self.dxn, axes=(0, 0))
        if not np.any(zz):
            return x
        # the first-order guess, then Newton steps on the exact distortion (quadratic convergence)
        cam = perturbed_camera(self.camera, self.steps.T @ zz)
        K, d = cam.K, np.zeros(8)
        d[: min(8, cam.dist.size)] = cam.dist[:8]
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        xd = (self.px[..., 0] - K[0, 2] - K[0, 1] / K[1, 1] * (self.px[..., 1] - K[1, 2])) / K[0, 0]
        yd = (self.px[..., 1] - K[1, 2]) / K[1, 1]
        xx, yy = x[..., 0], x[..., 1]
        for _ in range(2):
            r2 = xx * xx + yy * yy
            num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
            radial = num / den  # OpenCV's rational model (k4 = k5 = k6 = 0: the polynomial one)
            dr = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * den - num * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / den**2
            fx = xx * radial + 2 * p1 * xx * yy + p2 * (r2 + 2 * xx * xx) - xd
            fy = yy * radial + p1 * (r2 + 2 * yy * yy) + 2 * p2 * xx * yy - yd
            a = radial + 2 * xx * xx * dr + 2 * p1 * yy + 6 * p2 * xx
            b = 2 * xx * yy * dr + 2 * p1 * xx + 2 * p2 * yy
            c = radial + 2 * yy * yy * dr + 6 * p1 * yy + 2 * p2 * xx
            det = a * c - b * b
            xx, yy = xx - (c * fx - b * fy) / det, yy - (a * fy - b * fx) / det
        out = np.stack([xx, yy], axis=-1)
        # far from the first-order guess (a large z) Newton may not have converged: those points exactly
        flat_px = self.px.reshape(-1, 2)
        bad = ~np.all(np.abs(cam.distort_normalized(out.reshape(-1, 2)) - flat_px) < 1e-8, axis=1)
        if np.any(bad):
            flat = out.reshape(-1, 2)
            flat[bad] = cam.undistort_points(flat_px[bad])
            out = flat.reshape(out.shape)
        return out

    def points_jacobian(self, z: Array, xn: Array) -> Array:
        """Derivatives (n, M, 2, P, 2) of :meth:`points` with the nuisance ``z``, at its points ``xn``.

        The undistorted points solve ``distort(xn; intrinsics) = px``: by the implicit function theorem they move
        by ``-(d distort / d xn)^-1 (d distort / d intrinsics)`` along each intrinsic (closed form for fx, fy, cx,
        cy, k1..k6, p1, p2: OpenCV's rational model), mapped through ``steps``.

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance, in standard deviations along each principal direction (dimensionless).
        xn : ndarray, shape (M, 2, P, 2)
            ``points(z)``: the limb samples' normalized coordinates there.

        Returns
        -------
        ndarray, shape (n, M, 2, P, 2)
            Normalized coordinates per standard deviation along each principal direction.
        """
        zz = np.asarray(z, dtype=np.float64)
        cam = perturbed_camera(self.camera, self.steps.T @ zz)
        names = intrinsics_names(self.camera)
        if self.steps.shape[1] != len(names):  # as perturbed_camera moves them
            names = INTRINSICS_NAMES[: self.steps.shape[1]]
        K, d = cam.K, np.zeros(8)
        d[: min(8, cam.dist.size)] = cam.dist[:8]
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        x, y = xn[..., 0], xn[..., 1]
        r2 = x * x + y * y
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = num / den
        dr = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * den - num * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / den**2
        # the distortion's Jacobian in the normalized coordinates (symmetric) and its inverse
        a = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        c = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
        det = a * c - b * b
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        fx, skew, fy = K[0, 0], K[0, 1], K[1, 1]
        one, zero = np.ones_like(x), np.zeros_like(x)
        # per intrinsic, the change of the distorted normalized point (xd, yd) at fixed xn that the moved pixel
        # mapping asks for: minus d(distort)/d(theta) in normalized units
        partial = {
            "fx": (xd / fx, zero),
            "fy": (-skew * yd / (fx * fy), yd / fy),
            "cx": (one / fx, zero),
            "cy": (-skew * one / (fx * fy), one / fy),
            "k1": (x * r2 / den, y * r2 / den),
            "k2": (x * r2**2 / den, y * r2**2 / den),
            "k3": (x * r2**3 / den, y * r2**3 / den),
            "k4": (-x * radial * r2 / den, -y * radial * r2 / den),
            "k5": (-x * radial * r2**2 / den, -y * radial * r2**2 / den),
            "k6": (-x * radial * r2**3 / den, -y * radial * r2**3 / den),
            "p1": (2 * x * y, r2 + 2 * y * y),
            "p2": (r2 + 2 * x * x, 2 * x * y),
        }
        gx = np.stack([partial[n][0] for n in names])  # (p, M, 2, P)
        gy = np.stack([partial[n][1] for n in names])
        dx = -(c * gx - b * gy) / det  # (p, ...): -J^-1 g
        dy = -(a * gy - b * gx) / det
        dth = np.stack([dx, dy], axis=-1)  # (p, M, 2, P, 2)
        return np.tensordot(self.steps, dth, axes=(1, 0))

    def planes(self, z: Array, reference_h: Array) -> Array:
        """Interpretation planes (M, 2, 3) for ``z``, signed like ``reference_h``.

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance, in standard deviations along each principal direction (dimensionless).
        reference_h : ndarray, shape (M, 2, 3)
            The planes as measured (signs; returned as is when there is no rod).

        Returns
        -------
        ndarray, shape (M, 2, 3)
            Unit plane normals.
        """
        if self.shape[0] == 0:
            return np.asarray(reference_h, dtype=np.float64)
        return planes_through(self.points(z), reference_h)


def outward_shift_normalized(camera: CameraModel, limbs_px: Array, step_px: float = 0.5) -> Array:
    """Per limb sample, its move in normalized coordinates when the limb's edge moves 1 px outward in the (distorted)
    image, where the extraction measured it.

    Outward: along the normal of the limb's line through its samples, away from the rod's other limb. An edge bias
    that is the same number of image pixels everywhere (what an edge detector's response to a rod's profile gives) is
    not the same in normalized coordinates: the undistortion magnifies it with the radius (central difference of the
    camera's own undistortion over +/- ``step_px``).

    Parameters
    ----------
    camera : CameraModel
        The camera the limbs were seen through.
    limbs_px : ndarray, shape (M, 2, P, 2)
        Per rod, its two limbs' samples in distorted pixels.
    step_px : float
        Half the central difference's step, px.

    Returns
    -------
    ndarray, shape (M, 2, P, 2)
        Move of each sample per pixel of outward edge shift, normalized coordinates per px.
    """
    L = np.asarray(limbs_px, dtype=np.float64)
    c = L.mean(axis=2)  # (M, 2, 2)
    d = L - c[:, :, None, :]
    a = np.einsum("mlp,mlp->ml", d[..., 0], d[..., 0])
    b = np.einsum("mlp,mlp->ml", d[..., 0], d[..., 1])
    e = np.einsum("mlp,mlp->ml", d[..., 1], d[..., 1])
    # the line's direction angle: the fit planes_through does, written apart (sharing it moves results by rounding)
    ang = 0.5 * np.arctan2(2 * b, a - e)
    n = np.stack([-np.sin(ang), np.cos(ang)], axis=-1)  # (M, 2, 2) unit normals
    other = c[:, ::-1] - c  # towards the rod's other limb
    n *= np.where(np.sum(n * other, axis=-1, keepdims=True) > 0, -1.0, 1.0)
    step = step_px * n[:, :, None, :]
    flat = lambda x: x.reshape(-1, 2)  # noqa: E731
    plus = camera.undistort_points(flat(L + step)).reshape(L.shape)
    minus = camera.undistort_points(flat(L - step)).reshape(L.shape)
    return (plus - minus) / (2.0 * step_px)


def lens_model_error(camera: CameraModel) -> tuple[Array, Array] | None:
    """The radial model error the camera's calibration measured, or None (none measured, or all zero).

    ``calibration.lens_model.residual_profile`` (:func:`calib.camera.intrinsics.radial_residual_profile`): bin
    radii (px from
    the principal point) and the systematic radial residual there (px, outward), the part of the board views'
    residuals the chosen lens model could not follow beyond their noise.

    Parameters
    ----------
    camera : CameraModel
        The camera whose ``extra`` holds its calibration.

    Returns
    -------
    tuple of (ndarray, ndarray), each of shape (B,), or None
        The bin radii (px) and the systematic radial residual there (px, outward).
    """
    prof = (((camera.extra or {}).get("calibration") or {}).get("lens_model") or {}).get("residual_profile") or {}
    r, e = prof.get("radius_px"), prof.get("systematic_px")
    if not r or not e or len(r) != len(e):
        return None
    ra, ea = np.asarray(r, dtype=np.float64), np.asarray(e, dtype=np.float64)
    if not np.all(np.isfinite(ea)) or not np.any(ea):
        return None
    return ra, ea


def correct_model_error(camera: CameraModel, pixels: Array, profile: tuple[Array, Array]) -> Array:
    """Distorted pixels moved by minus the radial model error at their radius: where they would be seen were the lens
    exactly the model.

    Parameters
    ----------
    camera : CameraModel
        The camera (its principal point is the radii's centre).
    pixels : ndarray, shape (..., 2)
        Distorted pixel coordinates, px.
    profile : tuple of (ndarray, ndarray), each of shape (B,)
        Bin radii and systematic radial residual, px (:func:`lens_model_error`), linearly interpolated.

    Returns
    -------
    ndarray, shape (..., 2)
        The corrected pixels, px.
    """
    px = np.asarray(pixels, dtype=np.float64)
    c = camera.K[:2, 2]
    d = px - c
    r = np.linalg.norm(d, axis=-1, keepdims=True)
    de = np.interp(r[..., 0], profile[0], profile[1])[..., None]
    return px - de * d / np.maximum(r, 1e-9)
