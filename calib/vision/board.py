"""ChArUco board: construction from a :class:`~calib.formats.dataset.BoardSpec`, detection and pose.

Uses OpenCV >= 4.7's API: ``cv2.aruco.CharucoDetector``, ``board.matchImagePoints``, ``solvePnP``
(IPPE/iterative) then ``solvePnPRefineLM``. The board frame is OpenCV's: origin at the board's
top-left outer corner, x along the ``squares_x`` side, y along the ``squares_y`` side, z into the
board (away from a camera that sees its face).

A detection can be searched in a region of the image (:meth:`BoardDetector.detect` with ``region``, the region
where the previous frame's board was: :class:`BoardTracker`): the markers are found in that crop, their corners
refined and the ChArUco corners interpolated in the full image, and the result is kept only when nothing the
full-image detection would read lies outside the crop (:meth:`BoardDetector.crop_holds`); otherwise the full image
is searched. An accepted crop gives the full image's corners to the bit.
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
#: the board's motion between consecutive frames that a search region covers after a single detection (px,
#: :class:`BoardTracker`): the rendered paper dataset's line sweeps move it by 12 px a frame, its rotation and
#: translation sweeps by up to 70 px (twice that when two workers share the frames)
MOTION_PX = 64
#: the margin for the board's change of motion between frames (px): the region is grown by the last motion seen
#: plus this (:class:`BoardTracker`)
MOTION_FLOOR_PX = 16
#: a search region covering more than this fraction of the image is not worth a crop: the full image is searched
REGION_MAX_FRACTION = 0.5
#: how far a marker of the board that the crop did not find may lie from where the homography of the markers found
#: puts it (lens distortion), in squares of the board: up to 0.4 on the rendered paper dataset's views when
#: predicting one half of the board from the other
PREDICTION_TOLERANCE_SQUARES = 0.5
#: the largest sub-pixel window of a ChArUco corner (px, half-width; OpenCV's ``getMaximumSubPixWindowSizes``)
CHARUCO_WINDOW_MAX_PX = 10


@dataclass
class BoardDetection:
    """ChArUco corners found in an image: ids (M,) and distorted pixel positions (M, 2).

    Attributes
    ----------
    ids : ndarray of int, shape (M,)
    pixels : ndarray, shape (M, 2)
        Distorted pixels (px).
    n_markers : int
        Markers of the board found (markers of other ids are not counted).
    outline_px : ndarray, shape (4, 2), optional
        The board's four outer corners in the image (px), placed by the homography of the markers found (lens
        distortion ignored): where to search the next frame's board (:class:`BoardTracker`). None when no marker
        of the board is found.
    """

    ids: NDArray[np.int_]
    pixels: Array
    n_markers: int
    outline_px: Array | None = None


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
        dp = _detector_parameters()
        cp = cv2.aruco.CharucoParameters()
        cp.tryRefineMarkers = True
        self.detector = cv2.aruco.CharucoDetector(self.board, cp, dp)
        # the steps of detectBoard, run separately for a search region: markers found in the crop (corners left
        # as the contours give them: whole pixels), then refined, completed and interpolated in the full image
        self._dp = dp
        self._aruco = cv2.aruco.ArucoDetector(self.board.getDictionary(), dp, self.detector.getRefineParameters())
        self._crop_aruco = cv2.aruco.ArucoDetector(self.board.getDictionary(), _detector_parameters())
        self._marker_ids = np.asarray(self.board.getIds(), dtype=int).reshape(-1)
        self._marker_index = {int(k): n for n, k in enumerate(self._marker_ids)}
        self._marker_points = np.asarray(self.board.getObjPoints(), dtype=np.float64)[:, :, :2]  # (n, 4, 2), m
        w, h = spec.squares_x * spec.square_length_m, spec.squares_y * spec.square_length_m
        self._outline_m = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        #: how far (px) beyond a marker or corner OpenCV's detection reads the image: half its largest adaptive
        #: threshold window, the distance to the border under which a candidate is dropped, a sub-pixel window
        self.reach_px = (
            dp.adaptiveThreshWinSizeMax // 2
            + 1
            + dp.minDistanceToBorder
            + max(dp.cornerRefinementWinSize, CHARUCO_WINDOW_MAX_PX)
            + 1
        )
        #: detections searched in a region: ``accepted`` (the crop's result kept), ``fallback`` (the full image
        #: searched after the crop)
        self.region_stats = {"accepted": 0, "fallback": 0}
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

    def detect(self, image: np.ndarray, region: tuple[int, int, int, int] | None = None) -> BoardDetection:
        """Detect ChArUco corners (sub-pixel) in an 8/16-bit mono or colour image.

        Parameters
        ----------
        image : ndarray, shape (H, W) or (H, W, C), uint8 or uint16
            The image as recorded (distorted pixels).
        region : tuple of int, optional
            ``(x0, y0, x1, y1)`` (px, x1 and y1 excluded): search the board there first. The crop's detection is
            kept when it provably equals the full image's (:meth:`crop_holds`), else the full image is searched
            (counted in :attr:`region_stats`). Default: the full image.

        Returns
        -------
        BoardDetection
            Corner ids (M,), their distorted pixel positions (M, 2) (px), the count of the board's markers found and
            the board's outline; empty arrays when no corner is found.
        """
        gray = to_gray8(image)
        if region is not None:
            h, w = gray.shape
            x0, y0 = max(int(region[0]), 0), max(int(region[1]), 0)
            x1, y1 = min(int(region[2]), w), min(int(region[3]), h)
            if (x1 - x0) * (y1 - y0) < w * h and x1 > x0 and y1 > y0:
                found = self._detect_crop(gray, (x0, y0, x1, y1))
                if found is not None:
                    self.region_stats["accepted"] += 1
                    return found
                self.region_stats["fallback"] += 1
        ch_corners, ch_ids, mk_corners, mk_ids = self.detector.detectBoard(gray)
        return self._detection(ch_corners, ch_ids, self._board_markers(mk_corners, mk_ids))

    def _detect_crop(self, gray: np.ndarray, box: tuple[int, int, int, int]) -> BoardDetection | None:
        """detectBoard's steps with the markers found in ``gray[box]``; None unless that provably equals the full
        image's detection."""
        x0, y0, x1, y1 = box
        crop = gray[y0:y1, x0:x1]
        self._crop_aruco.setDetectorParameters(_detector_parameters(crop.shape, gray.shape))
        corners, ids, rejected = self._crop_aruco.detectMarkers(crop)
        if ids is None or len(ids) == 0:
            return None
        found = np.asarray(corners, dtype=np.float32).reshape(-1, 4, 2)
        if np.any(found != np.round(found)):  # not the contours' whole pixels: they would not move exactly
            return None
        # the candidates' whole-pixel corners move exactly into the full image, where OpenCV's own steps follow
        off = np.array([x0, y0], dtype=np.float32)
        refined = self._refine_markers(gray, found + off)
        corners = [refined[k : k + 1] for k in range(len(refined))]
        rejected = [c + off for c in rejected]
        ids = np.asarray(ids, dtype=np.int32).reshape(-1, 1)
        if rejected:
            corners, ids, _rej, _ = self._aruco.refineDetectedMarkers(gray, self.board, corners, ids, rejected)
        ch_corners, ch_ids, mk_corners, mk_ids = self.detector.detectBoard(gray, markerCorners=corners, markerIds=ids)
        markers = self._board_markers(mk_corners, mk_ids)
        det = self._detection(ch_corners, ch_ids, markers)
        return det if self.crop_holds(det, markers, box, gray.shape) else None

    def _refine_markers(self, gray: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """Markers' corners (n, 4, 2) refined as ArucoDetector's CORNER_REFINE_SUBPIX does: each marker's window
        from its module size, computed in float32 as OpenCV does; the corners of equal windows in one call (each
        corner is refined on its own)."""
        dp = self._dp
        c = np.ascontiguousarray(corners, dtype=np.float32)
        side = np.zeros(len(c), dtype=np.float32)
        for k in range(4):  # the sides summed in OpenCV's order
            d = c[:, k] - c[:, (k + 1) % 4]
            side = side + np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
        n_modules = self.board.getDictionary().markerSize + 2 * dp.markerBorderBits
        module = side / np.float32(4 * n_modules)
        win = np.rint(np.float32(dp.relativeCornerRefinmentWinSize) * module).astype(int)
        win = np.minimum(np.maximum(win, 1), dp.cornerRefinementWinSize)
        crit = (
            cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS,
            dp.cornerRefinementMaxIterations,
            dp.cornerRefinementMinAccuracy,
        )
        out = c.copy()
        for w in np.unique(win):
            sel = win == w
            pts = np.ascontiguousarray(c[sel].reshape(-1, 1, 2))
            out[sel] = cv2.cornerSubPix(gray, pts, (int(w), int(w)), (-1, -1), crit).reshape(-1, 4, 2)
        return out

    def _board_markers(self, mk_corners: Any, mk_ids: Any) -> tuple[NDArray[np.int_], Array, Array | None]:
        """The found markers of the board: their indices in the board (n,), corners (n, 4, 2) px and the
        homography board plane (m) to image (px) they give (None without a marker)."""
        if mk_ids is None or len(mk_ids) == 0:
            return np.zeros(0, dtype=int), np.zeros((0, 4, 2)), None
        found = [
            (self._marker_index[k], c)
            for k, c in zip(np.ravel(mk_ids).tolist(), mk_corners, strict=True)
            if k in self._marker_index
        ]
        if not found:
            return np.zeros(0, dtype=int), np.zeros((0, 4, 2)), None
        index = np.array([k for k, _ in found], dtype=int)
        px = np.array([np.asarray(c, dtype=np.float64).reshape(4, 2) for _, c in found])
        H, _ = cv2.findHomography(self._marker_points[index].reshape(-1, 2), px.reshape(-1, 2))
        return index, px, None if H is None else np.asarray(H, dtype=np.float64)

    def _detection(
        self, ch_corners: Any, ch_ids: Any, markers: tuple[NDArray[np.int_], Array, Array | None]
    ) -> BoardDetection:
        index, _px, H = markers
        outline = None if H is None else _apply_homography(H, self._outline_m)
        if ch_ids is None or len(ch_ids) == 0:
            return BoardDetection(np.zeros(0, dtype=int), np.zeros((0, 2)), int(index.size), outline)
        return BoardDetection(
            np.asarray(ch_ids, dtype=int).reshape(-1),
            np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2),
            int(index.size),
            outline,
        )

    def crop_holds(
        self,
        detection: BoardDetection,
        markers: tuple[NDArray[np.int_], Array, Array | None],
        box: tuple[int, int, int, int],
        shape: tuple,
    ) -> bool:
        """Whether a detection made in the crop ``box`` provably equals the full image's.

        OpenCV reads the image up to :attr:`reach_px` beyond a marker or corner (adaptive threshold window, border
        rule, sub-pixel windows). The crop's result is the full image's when, on every side where the crop cuts
        the image: the markers and ChArUco corners found lie at least that far inside it, and so do the board's
        markers not found, placed by the homography of those found, with :data:`PREDICTION_TOLERANCE_SQUARES` of a
        square (at least OpenCV's refinement distance) more for that placement's error. At least two markers of
        the board, each found once. (Outside the board nothing is taken for one of its markers: another object
        printed with the board's markers could be found by the full image only.)

        Parameters
        ----------
        detection : BoardDetection
            The crop's detection (full-image px).
        markers : tuple
            The board's markers it used: indices in the board (n,), corners (n, 4, 2) (full-image px), their
            homography (3, 3) or None.
        box : tuple of int
            ``(x0, y0, x1, y1)`` of the crop (px, x1 and y1 excluded).
        shape : tuple of int
            The full image's ``(H, W)``.

        Returns
        -------
        bool
        """
        index, px, H = markers
        if index.size < 2 or np.unique(index).size != index.size or H is None:
            return False
        x0, y0, x1, y1 = box
        h, w = shape[:2]
        r = float(self.reach_px)
        lo = np.array([x0 + r if x0 > 0 else -np.inf, y0 + r if y0 > 0 else -np.inf])
        hi = np.array([x1 - 1 - r if x1 < w else np.inf, y1 - 1 - r if y1 < h else np.inf])

        def inside(p: Array, extra: float = 0.0) -> bool:
            p = p.reshape(-1, 2)
            return bool(np.all(p >= lo + extra) and np.all(p <= hi - extra))

        if not inside(px) or not inside(detection.pixels):
            return False
        missing = np.setdiff1d(np.arange(self._marker_ids.size), index)
        if missing.size == 0:
            return True
        side_px = float(np.mean(np.linalg.norm(px - np.roll(px, 1, axis=1), axis=2)))
        square_px = side_px * self.spec.square_length_m / self.spec.marker_length_m
        tol = max(PREDICTION_TOLERANCE_SQUARES * square_px, float(self.detector.getRefineParameters().minRepDistance))
        return inside(_apply_homography(H, self._marker_points[missing].reshape(-1, 2)), tol)

    def search_region(
        self, outline_px: Array, shape: tuple, motion_px: float = MOTION_PX
    ) -> tuple[int, int, int, int] | None:
        """Where to search a board last seen with ``outline_px``: its bounding box grown by what :meth:`crop_holds`
        asks around the markers and by ``motion_px``; None when that is most of the image.

        Parameters
        ----------
        outline_px : ndarray, shape (4, 2)
            :attr:`BoardDetection.outline_px` of the earlier detection (px).
        shape : tuple of int
            The image's ``(H, W)``.
        motion_px : float
            The board's largest motion in the image since that detection (px).

        Returns
        -------
        tuple of int or None
            ``(x0, y0, x1, y1)`` (px, x1 and y1 excluded), clipped to the image.
        """
        o = np.asarray(outline_px, dtype=np.float64).reshape(4, 2)
        h, w = shape[:2]
        square_px = float(np.linalg.norm(o[1] - o[0])) / self.spec.squares_x
        grow = self.reach_px + PREDICTION_TOLERANCE_SQUARES * square_px + float(motion_px)
        x0, y0 = np.floor(o.min(axis=0) - grow).astype(int)
        x1, y1 = np.ceil(o.max(axis=0) + grow).astype(int) + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 <= x0 or y1 <= y0 or (x1 - x0) * (y1 - y0) > REGION_MAX_FRACTION * w * h:
            return None
        return int(x0), int(y0), int(x1), int(y1)

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


class BoardTracker:
    """The board of consecutive frames, each searched first where the previous frame's board was.

    Frames in order (extraction hands them out in order, an acquisition records them in order): the board is
    searched around the last detection's outline, grown by the last motion seen (of the outline's bounding box
    between the last two detections) plus :data:`MOTION_FLOOR_PX`, or by ``motion_px`` after a single detection
    (:meth:`BoardDetector.search_region`). The full image is searched when there is no region, the region
    is most of the image (the board jumps between the frames: a pose set) or it does not provably hold the board
    (:meth:`BoardDetector.detect`). The detections are the full image's either way.

    Parameters
    ----------
    detector : BoardDetector
    motion_px : float
        The board's largest motion (px) between a frame and the next when only one detection is known.
    """

    def __init__(self, detector: BoardDetector, motion_px: float = MOTION_PX) -> None:
        self.detector = detector
        self.motion_px = float(motion_px)
        self._last: Array | None = None
        self._before: Array | None = None

    def region(self, shape: tuple) -> tuple[int, int, int, int] | None:
        """Where the next frame's board is searched first (``(x0, y0, x1, y1)`` px), None: the full image.

        Parameters
        ----------
        shape : tuple of int
            The image's ``(H, W)``.

        Returns
        -------
        tuple of int or None
        """
        if self._last is None:
            return None
        if self._before is None:
            return self.detector.search_region(self._last, shape, self.motion_px)
        box = np.r_[self._last.min(axis=0), self._last.max(axis=0)]
        step = box - np.r_[self._before.min(axis=0), self._before.max(axis=0)]
        return self.detector.search_region(self._last, shape, MOTION_FLOOR_PX + float(np.max(np.abs(step))))

    def detect(self, image: np.ndarray) -> BoardDetection:
        """The next frame's detection (as :meth:`BoardDetector.detect` on the full image).

        Parameters
        ----------
        image : ndarray, shape (H, W) or (H, W, C), uint8 or uint16
            The frame as recorded.

        Returns
        -------
        BoardDetection
        """
        det = self.detector.detect(image, self.region(image.shape[:2]))
        self._before = None if det.outline_px is None else self._last
        self._last = det.outline_px
        return det

    def forget(self) -> None:
        """The next frame is searched in the full image (a frame out of sequence)."""
        self._last = self._before = None


def _detector_parameters(
    crop_shape: tuple[int, ...] | None = None, image_shape: tuple[int, ...] | None = None
) -> cv2.aruco.DetectorParameters:
    """The ArUco parameters of the board's detection (sub-pixel corners); for a crop (``crop_shape`` of an
    ``image_shape`` image): corners left as the contours give them, and the perimeter limits, relative to the image's
    size, rescaled to give the full image's limits in px."""
    dp = cv2.aruco.DetectorParameters()
    if crop_shape is None or image_shape is None:
        dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        return dp
    dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    full, crop = max(image_shape[:2]), max(crop_shape[:2])
    # OpenCV takes int(rate * max(cols, rows)) px: the same whole number of px in the crop
    dp.minMarkerPerimeterRate = (int(dp.minMarkerPerimeterRate * full) + 0.5) / crop
    dp.maxMarkerPerimeterRate = (int(dp.maxMarkerPerimeterRate * full) + 0.5) / crop
    return dp


def _apply_homography(H: Array, points: Array) -> Array:
    """``points`` (n, 2) mapped by the homography ``H`` (3, 3), shape (n, 2)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2) @ H[:, :2].T + H[:, 2]
    return p[:, :2] / p[:, 2:3]


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
