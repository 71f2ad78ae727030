"""The camera intrinsics' uncertainty, carried to the observations the methods use (first order).

The intrinsics are calibrated once (the ``camera`` phase) and their error is common to every frame:
it does not average out over poses, so a method's standard deviations must include it. The image
extraction keeps what is needed to redo its geometry for other intrinsics:

* per rod, ``limbs_px`` (2, 5, 2): points of each fitted limb line in distorted pixels, from which
  the interpretation planes ``h`` (hence the direction ``u = h1 x h2``) are recomputed;
* per board pose, ``d_intrinsics`` (6, 8): the pose's first-order change per unit change of the
  intrinsics (a left rotation in rad, then t in m);
* the camera's 8x8 covariance of (fx, fy, cx, cy, k1, k2, p1, p2) (``calibration.covariance``; from
  the standard deviations alone when only they are known, fx and fy then fully correlated).

A method evaluates its measured quantities at the intrinsics moved by plus and minus one standard
deviation along each principal direction of that covariance (:func:`principal_steps`) and maps the
change through its estimator's gain.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from ..camera import INTRINSICS_NAMES, CameraModel
from ..observations import Observations, PhaseArrays
from ..transforms import rotvec_to_matrix

Array = NDArray[np.float64]


def intrinsics_prior(obs: Observations, refined: bool = True) -> tuple[CameraModel, Array] | None:
    """The extraction's camera and the covariance (8, 8) of its intrinsics, or None when unknown.

    Order: :data:`calib.camera.INTRINSICS_NAMES` (px for fx, fy, cx, cy; dimensionless after). When
    the rods refined the camera (``calibration.covariance_refined``, the combined fit's posterior),
    that covariance is returned with ``refined`` (methods that do not use the rods); the calibration's
    own with ``refined=False`` (the combined method, which uses the rods again).
    """
    extra = obs.document.model_extra or {}
    cam = (extra.get("extraction") or {}).get("camera") or {}
    calib = cam.get("calibration") or {}
    if not cam.get("K"):
        return None
    camera = CameraModel.from_dict(cam)
    cov = calib.get("covariance_refined") if refined and calib.get("covariance_refined") else calib.get("covariance")
    if cov is not None and list(calib.get("covariance_params") or INTRINSICS_NAMES) == list(INTRINSICS_NAMES):
        C = np.asarray(cov, dtype=np.float64)
        if C.shape == (8, 8) and np.all(np.isfinite(C)):
            return camera, 0.5 * (C + C.T)
    std = calib.get("std") or {}
    if not all(k in std for k in ("fx", "fy", "cx", "cy")):
        return None
    s = np.array([float(std.get(k, 0.0)) for k in INTRINSICS_NAMES])
    C = np.diag(s ** 2)
    C[0, 1] = C[1, 0] = s[0] * s[1]  # one focal scale: the conservative choice without correlations
    return camera, C


def principal_steps(cov: Array, rel_tol: float = 1e-12) -> Array:
    """One standard deviation along each principal direction of ``cov`` (8, 8), shape (n, 8)."""
    w, V = np.linalg.eigh(np.asarray(cov, dtype=np.float64))
    keep = w > rel_tol * max(float(w.max()), 1e-300)
    return (V[:, keep] * np.sqrt(w[keep])).T


def perturbed_camera(camera: CameraModel, step: Array) -> CameraModel:
    """``camera`` with (fx, fy, cx, cy, k1, k2, p1, p2) moved by ``step`` (8,)."""
    K = camera.K.copy()
    K[0, 0] += step[0]
    K[1, 1] += step[1]
    K[0, 2] += step[2]
    K[1, 2] += step[3]
    d = camera.dist.copy()
    d[:4] += step[4:8]
    return CameraModel(K, d, camera.width, camera.height)


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
    m, two, p, _ = L.shape
    xn = camera.undistort_points(L.reshape(-1, 2)).reshape(m, two, p, 2)
    c = xn.mean(axis=2)
    d = xn - c[:, :, None, :]
    S = np.einsum("mlpi,mlpj->mlij", d, d)
    _w, V = np.linalg.eigh(S)
    n = V[..., :, 0]  # normal: the smallest-variance direction
    h = np.concatenate([n, -np.sum(n * c, axis=-1, keepdims=True)], axis=-1)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    return h * np.sign(np.sum(h * reference_h, axis=-1, keepdims=True))


def board_sensitivities(obs: Observations, arrays: PhaseArrays) -> Array | None:
    """``d_intrinsics`` (N, 6, 8) of the board poses of ``arrays`` (zeros where no board), or None if any lacks it."""
    out = np.zeros((len(arrays), 6, 8))
    for k, i in enumerate(arrays.index):
        if not arrays.has_board[k]:
            continue
        board = obs.frames[int(i)].board
        d = getattr(board, "d_intrinsics", None) if board is not None else None
        if d is None:
            return None
        out[k] = np.asarray(d, dtype=np.float64)
    return out


def perturbed_boards(arrays: PhaseArrays, sens: Array, step: Array) -> PhaseArrays:
    """The board poses of ``arrays`` as they would be measured with the intrinsics moved by ``step`` (8,)."""
    d = sens @ step  # (N, 6)
    R = np.einsum("nij,njk->nik", rotvec_to_matrix(d[:, :3]), arrays.board_R)
    return replace(arrays, board_R=R, board_t=arrays.board_t + d[:, 3:])

