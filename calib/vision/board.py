"""ChArUco board: construction from a :class:`~calib.formats.dataset.BoardSpec`, detection and pose.

Uses OpenCV >= 4.7's API: ``cv2.aruco.CharucoDetector``, ``board.matchImagePoints``, ``solvePnP``
(IPPE/iterative) then ``solvePnPRefineLM``. The board frame is OpenCV's: origin at the board's
top-left outer corner, x along the ``squares_x`` side, y along the ``squares_y`` side, z into the
board (away from a camera that sees its face).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.camera.charuco import board_corners, make_board
from calib.camera.intrinsics import intrinsics_names, projection_columns
from calib.formats.camera import CameraModel
from calib.formats.dataset import BoardSpec
from calib.numerics.robust import chi2_gate

Array = NDArray[np.float64]

#: Below this many ChArUco corners the board is reported missing.
DEFAULT_MIN_CORNERS = 6


@dataclass
class BoardDetection:
    """ChArUco corners found in an image: ids (M,) and distorted pixel positions (M, 2)."""

    ids: NDArray[np.int_]
    pixels: Array
    n_markers: int


@dataclass
class BoardPose:
    """``camera_from_board`` measured in one image.

    Attributes
    ----------
    R : ndarray, shape (3, 3)
    t : ndarray, shape (3,)
        Metres.
    rms_px : float
        RMS reprojection error of the corners used, pixels.
    n_corners : int
        Corners used.
    corners_rejected : int
        Corners detected but left out of the pose: their residual is beyond what the others' scatter allows
        (:func:`reject_corners`: a corner under a rod, a glint).
    cov : ndarray, shape (6, 6)
        Covariance of (rotation vector [rad], t [m]), from the PnP Jacobian scaled by the residual
        variance (floored at 0.05 px so that a perfect fit does not claim infinite precision).
    d_intrinsics : ndarray, shape (6, 8), optional
        First-order change of the pose per unit change of the intrinsics (fx, fy, cx, cy [px], k1,
        k2, p1, p2): rows are a small rotation applied on the left, ``R' = exp([w]) R`` (rad), then
        the change of t (m). It carries the camera calibration's uncertainty to the methods.
    """

    R: Array
    t: Array
    rms_px: float
    n_corners: int
    cov: Array
    d_intrinsics: Array | None = None
    corners_rejected: int = 0

    def to_dict(self) -> dict:
        d = {
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "rms_px": self.rms_px,
            "n_corners": self.n_corners,
            "corners_rejected": self.corners_rejected,
            "cov": self.cov.tolist(),
        }
        if self.d_intrinsics is not None:
            d["d_intrinsics"] = self.d_intrinsics.tolist()
        return d


class BoardDetector:
    """Finds a ChArUco board and measures its pose.

    Parameters
    ----------
    spec : BoardSpec
    min_corners : int
        Fewer corners than this: no pose (the reason says how many were found).
    """

    def __init__(self, spec: BoardSpec, min_corners: int = DEFAULT_MIN_CORNERS) -> None:
        self.spec = spec
        self.board = make_board(spec)
        self.min_corners = int(min_corners)
        dp = cv2.aruco.DetectorParameters()
        dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        cp = cv2.aruco.CharucoParameters()
        cp.tryRefineMarkers = True
        self.detector = cv2.aruco.CharucoDetector(self.board, cp, dp)
        self.ids_all, self.points_nominal = board_corners(spec)
        self.points = self.points_nominal.copy()
        #: (M, 3, 8) change of each corner per unit change of the intrinsics (the refined geometry's
        #: correlation with them in the calibration); zero for a nominal board
        self.points_d_intrinsics = np.zeros((self.points.shape[0], 3, 8))

    def use_refined_points(self, ids: NDArray[np.int_], points: Array, d_intrinsics: Array | None = None) -> None:
        """Use corner coordinates refined by intrinsic calibration (calibrateCameraRO) for poses.

        Corners not in ``ids`` keep their nominal positions.

        Parameters
        ----------
        ids : ndarray of int, shape (K,)
            Ids of the refined corners.
        points : ndarray, shape (K, 3)
            Their refined positions in the board frame (metres).
        d_intrinsics : ndarray, shape (K, 3, n_i), optional
            How the refined corners move with the ``n_i`` intrinsics (metres per unit of each intrinsic:
            px for fx, fy, cx, cy, dimensionless for the distortion coefficients;
            :func:`calib.camera.intrinsics.intrinsics_covariance`); the poses' ``d_intrinsics`` then include it.
            Default: the corners do not move with the intrinsics.
        """
        idx = np.asarray(ids, dtype=int)
        pts = self.points_nominal.copy()
        pts[idx] = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.points = pts
        self.points_d_intrinsics = np.zeros((pts.shape[0], 3, 8))
        if d_intrinsics is not None:
            dI = np.asarray(d_intrinsics, dtype=np.float64)
            ni = dI.shape[-1] if dI.ndim == 3 else 8  # the lens model's parameter count
            self.points_d_intrinsics = np.zeros((pts.shape[0], 3, ni))
            self.points_d_intrinsics[idx] = dI.reshape(-1, 3, ni)

    def detect(self, image: np.ndarray) -> BoardDetection:
        """Detect ChArUco corners (sub-pixel) in an 8/16-bit mono or colour image.

        Parameters
        ----------
        image : ndarray, shape (H, W) or (H, W, C), uint8 or uint16
            The image as recorded (distorted pixels).

        Returns
        -------
        BoardDetection
            Corner ids (M,), their distorted pixel positions (M, 2) (px) and the count of markers found; empty
            arrays when no corner is found.
        """
        gray = to_gray8(image)
        ch_corners, ch_ids, _mk_corners, mk_ids = self.detector.detectBoard(gray)
        n_markers = 0 if mk_ids is None else len(mk_ids)
        if ch_ids is None or len(ch_ids) == 0:
            return BoardDetection(np.zeros(0, dtype=int), np.zeros((0, 2)), n_markers)
        return BoardDetection(
            np.asarray(ch_ids, dtype=int).reshape(-1),
            np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2),
            n_markers,
        )

    def pose(self, detection: BoardDetection, camera: CameraModel) -> BoardPose | str:
        """Pose from a detection, or the reason why there is none (a string).

        Corners the pose cannot explain are removed first (:func:`reject_corners`).

        Parameters
        ----------
        detection : BoardDetection
            Corners found by :meth:`detect` (distorted px).
        camera : CameraModel
            Intrinsics (px) and distortion of the camera that took the image.

        Returns
        -------
        BoardPose or str
            ``camera_from_board`` (rotation (3, 3), translation (3,) in metres), the reprojection RMS (px), the
            pose's covariance and its sensitivity to the intrinsics; or why there is no pose (too few corners,
            no convergence, degenerate configuration, board behind the camera).
        """
        n = detection.ids.size
        if n < self.min_corners:
            return (
                f"board not found: {n} ChArUco corners ({detection.n_markers} markers), "
                f"need at least {self.min_corners}"
            )
        obj = self.points[detection.ids]
        img = detection.pixels
        # planar board: IPPE gives the two-fold ambiguity resolved by reprojection, then LM refinement
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok:
                return "board pose failed: solvePnP did not converge"
        # OpenCV's stubs type every output as any Mat; with float64 inputs these are float64 arrays
        rvec, tvec = cast("tuple[Array, Array]", cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec))
        keep, rvec, tvec = reject_corners(obj, img, camera, rvec, tvec, self.min_corners)
        n_rejected = int(n - keep.sum())
        obj, img, ids, n = obj[keep], img[keep], detection.ids[keep], int(keep.sum())
        proj, jac = cast("tuple[Array, Array]", cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist))
        res = proj.reshape(-1, 2) - img
        rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
        J = jac[:, :6]
        dof = max(2 * n - 6, 1)
        sigma2 = max(float(np.sum(res**2)) / dof, CORNER_FLOOR_PX**2)
        try:
            cov = sigma2 * cast("Array", np.linalg.inv(J.T @ J))  # float64 (numpy's stubs: any floating)
        except np.linalg.LinAlgError:
            return "board pose failed: degenerate corner configuration"
        R, _ = cast("tuple[Array, Any]", cv2.Rodrigues(rvec))
        if float(tvec.reshape(-1)[2]) <= 0:
            return "board pose failed: board behind the camera"
        # intrinsics move the pose directly (projection) and through the refined corners they carry
        cols = projection_columns(intrinsics_names(camera))  # the camera's lens model's intrinsics
        ni = len(cols)
        if max(cols) >= jac.shape[1]:  # a coefficient the camera's dist does not hold (zero): its derivative
            _, jac = cast(
                "tuple[Array, Array]",
                cv2.projectPoints(obj, rvec, tvec, camera.K, np.concatenate([camera.dist, np.zeros(8)])[:8]),
            )
        dX = self.points_d_intrinsics[ids]  # (n, 3, ni)
        if dX.shape[2] != ni:
            dX = np.zeros((n, 3, ni))
        JI = jac[:, cols] + np.einsum("pij,pjk->pik", (jac[:, 3:6].reshape(n, 2, 3) @ R), dX).reshape(2 * n, ni)
        return BoardPose(
            R,
            tvec.reshape(3).astype(np.float64),
            rms,
            int(n),
            cov,
            _pose_sensitivity(jac[:, :6], JI, rvec.reshape(3), R),
            n_rejected,
        )

    def measure(self, image: np.ndarray, camera: CameraModel) -> BoardPose | str:
        """Detect then pose (or the reason).

        Parameters
        ----------
        image : ndarray, shape (H, W) or (H, W, C), uint8 or uint16
            The image as recorded (distorted pixels).
        camera : CameraModel
            The camera that took it.

        Returns
        -------
        BoardPose or str
            As :meth:`pose`.
        """
        return self.pose(self.detect(image), camera)

    def outline_camera(self, R: Array, t: Array, margin_m: float = 0.012) -> Array:
        """The board's outline (4 corners plus a margin) in the camera frame, shape (4, 3).

        Parameters
        ----------
        R : ndarray, shape (3, 3)
            Rotation of ``camera_from_board``.
        t : ndarray, shape (3,)
            Translation of ``camera_from_board`` (metres).
        margin_m : float
            Margin added around the board on every side (metres).

        Returns
        -------
        ndarray, shape (4, 3)
            The outline's corners in the camera frame (metres), in order around the board.
        """
        w, h = self.spec.size_m
        m = margin_m
        c = np.array([[-m, -m, 0.0], [w + m, -m, 0.0], [w + m, h + m, 0.0], [-m, h + m, 0.0]])
        return c @ np.asarray(R).T + np.asarray(t)


#: the corners' residual scatter is taken as at least this (px) when judging one corner (the covariance's floor)
CORNER_FLOOR_PX = 0.05


def reject_corners(
    obj: Array, img: Array, camera: CameraModel, rvec: Array, tvec: Array, min_corners: int
) -> tuple[NDArray[np.bool_], Array, Array]:
    """Corners whose residual the pose cannot explain, removed one at a time (worst first) and the pose refined.

    A ChArUco corner next to an occluding edge (the legs pass in front of the board on an I4) or a glint is
    pulled by a pixel or more while the others scatter by a few hundredths: one such corner moves the pose by
    several times its covariance. Each corner's studentized squared residual ``r^T (I - H_ii)^-1 r``
    (``H_ii``: its 2x2 block of the pose's hat matrix) over the others' robust scale (median over
    ``chi2(2).median``, at least :data:`CORNER_FLOOR_PX`) is gated at chi-square(2)'s 99.9 % quantile; the worst
    beyond the gate goes, while more than ``min_corners`` remain.

    Parameters
    ----------
    obj : ndarray, shape (n, 3)
        The corners in the board frame (metres).
    img : ndarray, shape (n, 2)
        Their detected positions (distorted px).
    camera : CameraModel
        The camera that took the image.
    rvec : ndarray, shape (3, 1)
        Rotation vector of ``camera_from_board`` (radians), the starting pose.
    tvec : ndarray, shape (3, 1)
        Translation of ``camera_from_board`` (metres), the starting pose.
    min_corners : int
        No corner is removed once this many remain.

    Returns
    -------
    keep : ndarray of bool, shape (n,)
    rvec, tvec : ndarray, shape (3, 1)
        The pose refined on the corners kept (radians, metres).
    """
    keep = np.ones(len(obj), dtype=bool)
    gate = float(chi2_gate(2))
    while keep.sum() > min_corners:
        o, m = obj[keep], img[keep]
        proj, jac = cv2.projectPoints(o, rvec, tvec, camera.K, camera.dist)
        r = proj.reshape(-1, 2) - m
        J = jac[:, :6]
        try:
            Hm = J @ np.linalg.solve(J.T @ J, J.T)
        except np.linalg.LinAlgError:
            break
        k = len(o)
        idx = np.arange(k)
        B = np.eye(2) - Hm.reshape(k, 2, k, 2)[idx, :, idx, :]  # (k, 2, 2): each corner's block of I - H
        ok = np.linalg.det(B) > 1e-9  # a corner the pose fits exactly (full leverage) cannot be judged
        d2 = np.zeros(k)
        d2[ok] = np.einsum("ki,ki->k", r[ok], np.linalg.solve(B[ok], r[ok][..., None])[..., 0])
        s2 = max(float(np.median(d2)) / (2.0 * np.log(2.0)), CORNER_FLOOR_PX**2)
        worst = int(np.argmax(d2))
        if d2[worst] <= gate * s2:
            break
        keep[np.nonzero(keep)[0][worst]] = False
        rv, tv = cv2.solvePnPRefineLM(obj[keep], img[keep], camera.K, camera.dist, rvec, tvec)
        rvec, tvec = np.asarray(rv, dtype=np.float64), np.asarray(tv, dtype=np.float64)
    return keep, rvec, tvec


def _pose_sensitivity(Jp: Array, JI: Array, rvec: Array, R: Array) -> Array | None:
    """d(left rotation, t)/d(intrinsics) of a PnP pose, (6, n) (fx, fy, cx, cy, k1, k2, p1, p2 or the camera's
    lens model's parameters).

    The pose minimises the reprojection error: a change dI of the intrinsics moves it by
    ``-(Jp^T Jp)^-1 Jp^T J_I dI`` (Jp (2n, 6): the pixels' derivatives by (rvec, t); J_I (2n, 8): by
    the intrinsics, the corners' own motion with them included).
    """
    try:
        dpose = -np.linalg.solve(Jp.T @ Jp, Jp.T @ JI)  # (6, 8): d rvec, d t
    except np.linalg.LinAlgError:
        return None
    eps = 1e-6
    ni = JI.shape[1]
    out = np.empty((6, ni))
    out[3:] = dpose[3:]
    for j in range(ni):
        R2, _ = cv2.Rodrigues(rvec + eps * dpose[:3, j])
        A = R2 @ R.T  # ~ I + [w]x (cv2.Rodrigues returns 0 for so small an angle: read the skew part)
        out[:3, j] = 0.5 * np.array([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]]) / eps
    return out


def to_gray8(image: np.ndarray) -> np.ndarray:
    """An 8-bit single-channel view of an 8/16-bit mono or colour image.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, C)
        Mono, BGR or BGRA; uint8, uint16 (the high byte is kept) or another type (clipped to 0-255).

    Returns
    -------
    ndarray of uint8, shape (H, W)
    """
    img = image
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        else:
            img = img[:, :, 0]
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img
