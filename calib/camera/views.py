"""Board views for an intrinsic calibration, taken one at a time: each view checked as it comes, what is still
missing said in words, and where to hold the board next.

The I4 turns its board only about the vertical, which cannot fix the focal length (a board seen turning about one
axis leaves the focal length and the distance traded against each other); the intrinsics come from a hand-held
board shown over the whole image, tilted both ways about both image axes, near and far (docs/camera.md). What the
views must cover (:class:`ViewGoals`):

* **image corners**: in each quadrant, a board corner at least ``corner_reach`` of the way from the image centre to
  the image's corner (the lens model's choice needs views near the corners:
  :data:`calib.camera.intrinsics.MIN_FIELD_COVERAGE`);
* **tilts**: the board turned by ``tilt_deg`` or more about the image's horizontal axis (top edge away from the
  camera, and towards it) and about its vertical axis (right edge away, and towards);
* **distances**: a near view (the board spanning ``near_fill`` of the image width or more) and a far one
  (``far_fill`` or less);
* **count**: ``views`` full-board views kept.

A view is kept when every corner of the board was found (``cv2.calibrateCameraRO`` needs the same points in every
view), when it is not a repeat of a kept one, and, from the fifth on, when its corners fit a quick calibration of the
kept views as well as the others do (the outlier test of :func:`calib.camera.intrinsics.calibrate_intrinsics`:
RMS above
``max(3 x median, 1 px)`` is a moved or bent board). Tilts and distances are measured from each view's pose with the
current estimate of the camera (``cv2.initCameraMatrix2D`` until five views are kept, then the quick calibration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.camera.intrinsics import opencv_single_thread
from calib.formats.dataset import BoardSpec

Array = NDArray[np.float64]

#: Image corners by name, as (sign of x, sign of y) from the image centre (y down).
CORNERS: dict[str, tuple[int, int]] = {"top-left": (-1, -1), "top-right": (1, -1), "bottom-left": (-1, 1),
                                       "bottom-right": (1, 1)}  # fmt: skip
#: Tilt directions by name: (axis, sign); axis 0 about the image's horizontal axis, 1 about its vertical axis.
TILTS: dict[str, tuple[int, int]] = {
    "top edge away from the camera": (0, 1),
    "top edge towards the camera": (0, -1),
    "right edge away from the camera": (1, 1),
    "right edge towards the camera": (1, -1),
}
GOAL_KEYS = ("views", "corner_reach", "tilt_deg", "near_fill", "far_fill")
QUICK_MIN_VIEWS = 5  # kept views from which a quick calibration checks each new one


@dataclass(frozen=True)
class ViewGoals:
    """What the board views must cover before the intrinsics are calibrated (see the module's docstring)."""

    views: int = 15
    #: a whole board held in view (its inner corners a square and a margin in from its edge) reaches some 75-80% of
    #: the way to the image's corner; the lens model's choice asks 85%
    #: (calib.camera.intrinsics.MIN_FIELD_COVERAGE) and keeps
    #: k3, with its uncertainty, when the views stay short of it (the rods, seen up to the corners, pin it)
    corner_reach: float = 0.75
    tilt_deg: float = 20.0
    near_fill: float = 0.55
    far_fill: float = 0.35
    outlier_factor: float = 3.0
    outlier_floor_px: float = 1.0
    #: a view whose centre is within this fraction of the image width of a kept view's, whose tilts are within
    #: ``repeat_tilt_deg`` and whose fill is within 10% of it adds nothing: it is a repeat
    repeat_centre: float = 0.04
    repeat_tilt_deg: float = 5.0


@dataclass(frozen=True)
class BoardPlacement:
    """Where to hold the board for the next view: what an operator is asked.

    Attributes
    ----------
    index : int
        The view asked for, from 1.
    centre : (float, float)
        Where the board's centre should appear: fractions of the image width and height from the top-left.
    fill : float
        How much of the image width the board should span, 0-1.
    tilt_deg : (float, float)
        The board's turn about the image's horizontal axis (positive: top edge away from the camera) and about its
        vertical axis (positive: right edge away from the camera), degrees.
    text : str
        The request in words.
    """

    index: int
    centre: tuple[float, float]
    fill: float
    tilt_deg: tuple[float, float]
    text: str

    def to_dict(self) -> dict[str, Any]:
        """The placement as a JSON object.

        Returns
        -------
        dict
            ``index``, ``centre`` (fractions of the image), ``fill`` (0-1), ``tilt_deg`` (degrees), ``text``.
        """
        return {
            "index": self.index,
            "centre": list(self.centre),
            "fill": self.fill,
            "tilt_deg": list(self.tilt_deg),
            "text": self.text,
        }


@dataclass
class ViewFeatures:
    """What one view shows: where the board is in the image, how far and how tilted.

    Attributes
    ----------
    centre : (float, float)
        The board corners' mean, fractions of the image width and height.
    fill : float
        The board's span as a fraction of the image width (from the area its corners enclose).
    reach : dict[str, float]
        Per image corner (:data:`CORNERS`): how far towards it the board's corners go, 0 (centre) to 1 (the corner).
    tilt_deg : (float, float)
        Turn about the image's horizontal axis (+: top edge away) and vertical axis (+: right edge away), degrees.
    distance_m : float
        Distance of the board's centre from the camera, metres (with the current camera estimate).
    """

    centre: tuple[float, float]
    fill: float
    reach: dict[str, float]
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    distance_m: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """The features as a JSON object, rounded for display.

        Returns
        -------
        dict
            ``centre`` and ``fill`` (fractions of the image), ``reach`` (0-1 per corner), ``tilt_deg`` (degrees),
            ``distance_m`` (metres).
        """
        return {
            "centre": [round(v, 4) for v in self.centre],
            "fill": round(self.fill, 4),
            "reach": {k: round(v, 4) for k, v in self.reach.items()},
            "tilt_deg": [round(v, 2) for v in self.tilt_deg],
            "distance_m": round(self.distance_m, 4),
        }


@dataclass
class ViewVerdict:
    """The check of one grabbed view: kept or not, why, and what it added."""

    key: int
    kept: bool
    reason: str
    features: ViewFeatures | None = None
    rms_px: float | None = None
    added: list[str] = field(default_factory=list)


def _location(x: float, y: float) -> str:
    h = "left" if x < 0.4 else ("right" if x > 0.6 else "")
    v = "top" if y < 0.4 else ("bottom" if y > 0.6 else "")
    return f"{v}-{h}" if v and h else (v or h or "centre")


def _tilt_words(tilt: tuple[float, float]) -> str:
    parts = []
    words = (("top edge away from", "top edge towards"), ("right edge away from", "right edge towards"))
    for axis, (pos, neg) in enumerate(words):
        a = tilt[axis]
        if abs(a) >= 1.0:
            parts.append(f"turned about {abs(a):.0f} deg with its {pos if a > 0 else neg} the camera")
    return " and ".join(parts) if parts else "facing the camera squarely"


class ViewGuide:
    """Checks board views as they are grabbed and says what is still missing.

    Parameters
    ----------
    board : BoardSpec
        The ChArUco board held up (the same board as on the end-effector: its refined corners are reused).
    image_size : (int, int)
        ``(width, height)``, pixels.
    goals : ViewGoals
    """

    def __init__(self, board: BoardSpec, image_size: tuple[int, int], goals: ViewGoals | None = None) -> None:
        from calib.camera.charuco import board_corners

        self.board = board
        self.width, self.height = int(image_size[0]), int(image_size[1])
        self.goals = goals or ViewGoals()
        self.ids_all, self.points = board_corners(board)
        self.kept: dict[int, Array] = {}  # key -> pixels (M, 2) in id order
        self.features: dict[int, ViewFeatures] = {}
        self.rejected: dict[int, str] = {}
        self.K = self._default_K()
        self.dist = np.zeros(5)
        self.quick_rms_px: dict[int, float] = {}
        self._asked = 0

    # -- the camera estimate ------------------------------------------------------------------------------------
    def _default_K(self) -> Array:
        f = float(max(self.width, self.height))
        return np.array([[f, 0, (self.width - 1) / 2], [0, f, (self.height - 1) / 2], [0, 0, 1.0]])

    def _objp(self, n: int) -> list[np.ndarray]:
        return [self.points.astype(np.float32).reshape(-1, 1, 3) for _ in range(n)]

    def _estimate(self, views: dict[int, Array]) -> tuple[Array, Array, dict[int, float]]:
        """Camera matrix, distortion and per-view RMS (px) from ``views``: a quick calibration from
        :data:`QUICK_MIN_VIEWS` views on (k1, k2, p1, p2), before that ``cv2.initCameraMatrix2D``."""
        keys = list(views)
        imgp = [views[k].astype(np.float32).reshape(-1, 1, 2) for k in keys]
        size = (self.width, self.height)
        if len(keys) < QUICK_MIN_VIEWS:
            K = self._default_K()
            if len(keys) >= 2:
                with opencv_single_thread():
                    Ki = cv2.initCameraMatrix2D(self._objp(len(keys)), imgp, size, 1.0)
                f = float(Ki[0, 0])
                if np.all(np.isfinite(Ki)) and 0.3 * self.width < f < 20 * self.width:
                    K = np.array([[f, 0, K[0, 2]], [0, f, K[1, 2]], [0, 0, 1.0]])
            return K, np.zeros(5), {}
        with opencv_single_thread():
            fit = cv2.calibrateCamera(self._objp(len(keys)), imgp, size, None, None, flags=cv2.CALIB_FIX_K3)
        Kq = np.asarray(fit[1], dtype=np.float64)
        dq = np.asarray(fit[2], dtype=np.float64).reshape(-1)
        per = {}
        for k, ip, rv, tv in zip(keys, imgp, fit[3], fit[4], strict=True):
            proj, _ = cv2.projectPoints(self.points, rv, tv, Kq, dq)
            per[k] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - ip.reshape(-1, 2)) ** 2, axis=1))))
        return Kq, dq, per

    # -- one view -----------------------------------------------------------------------------------------------
    def _features(self, px: Array) -> ViewFeatures:
        w, h = self.width, self.height
        c = np.array([(w - 1) / 2, (h - 1) / 2])
        d = px - c
        reach = {}
        for name, (sx, sy) in CORNERS.items():
            inq = (np.sign(d[:, 0]) == sx) & (np.sign(d[:, 1]) == sy)
            corner = np.array([sx * (w - 1) / 2, sy * (h - 1) / 2])
            reach[name] = float(np.max(np.linalg.norm(d[inq], axis=1)) / np.linalg.norm(corner)) if inq.any() else 0.0
        hull = cv2.convexHull(px.astype(np.float32))
        sx_, sy_ = self.board.squares_x, self.board.squares_y
        area = float(cv2.contourArea(hull)) * (sx_ * sy_) / max((sx_ - 2) * (sy_ - 2), 1)
        W, H = self.board.size_m
        fill = math.sqrt(max(area, 0.0) * W / H) / w
        mean = px.mean(axis=0)
        feat = ViewFeatures((float(mean[0] / w), float(mean[1] / h)), fill, reach)
        ok, rvec, tvec = cv2.solvePnP(self.points, px, self.K, self.dist, flags=cv2.SOLVEPNP_IPPE)
        if ok:
            R, _ = cv2.Rodrigues(rvec)
            n = R[:, 2] * (1.0 if R[2, 2] >= 0 else -1.0)  # the board's normal, away from the camera
            feat.tilt_deg = (math.degrees(math.atan2(n[1], n[2])), math.degrees(math.atan2(-n[0], n[2])))
            centre = R @ np.array([W / 2, H / 2, 0.0]) + np.asarray(tvec).reshape(3)
            feat.distance_m = float(np.linalg.norm(centre))
        return feat

    def _repeat_of(self, f: ViewFeatures) -> int | None:
        g = self.goals
        for k, o in self.features.items():
            if (
                math.hypot(f.centre[0] - o.centre[0], (f.centre[1] - o.centre[1]) * self.height / self.width)
                < g.repeat_centre
                and max(abs(a - b) for a, b in zip(f.tilt_deg, o.tilt_deg, strict=True)) < g.repeat_tilt_deg
                and abs(f.fill - o.fill) < 0.1 * o.fill
            ):
                return k
        return None

    def add(self, key: int, ids: ArrayLike, pixels: ArrayLike) -> ViewVerdict:
        """Check a grabbed view and keep it or say why not.

        Parameters
        ----------
        key : int
            The view's key (a frame index).
        ids : array_like of int, shape (N,)
            The detected ChArUco corner ids.
        pixels : array_like, shape (N, 2)
            Their pixels.

        Returns
        -------
        ViewVerdict
            Kept or not, why, the view's features and RMS against the quick calibration (px), what it added.
        """
        ids = np.asarray(ids, dtype=int).reshape(-1)
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        m = self.ids_all.size
        if ids.size == 0:
            return self._reject(key, "no board found: hold the whole board in view, facing the camera, well lit")
        if ids.size != m or set(ids.tolist()) != set(self.ids_all.tolist()):
            return self._reject(
                key,
                f"part of the board: {ids.size} of its {m} corners found; keep the whole board (and a margin around "
                "it) inside the image, not hidden by a hand",
            )
        px = px[np.argsort(ids)]
        feat = self._features(px)
        rep = self._repeat_of(feat)
        if rep is not None:
            return self._reject(key, f"a repeat of view {rep}: move or turn the board to add something new", feat)
        before = self.missing_items()
        trial = {**self.kept, key: px}
        K, dist, per = self._estimate(trial)
        rms = per.get(key)
        if per:
            others = [v for k, v in per.items() if k != key]
            limit = max(self.goals.outlier_factor * float(np.median(others)), self.goals.outlier_floor_px)
            if rms is not None and rms > limit:
                return self._reject(
                    key,
                    f"its corners fit the other views' calibration at {rms:.2f} px RMS (limit {limit:.2f} px): the "
                    "board moved during the exposure, or it is bent; hold it still and take it again",
                    feat,
                    rms,
                )
        self.kept[key] = px
        self.features[key] = feat
        self.K, self.dist, self.quick_rms_px = K, dist, per
        for k, v in self.kept.items():  # every view measured again with the better camera
            self.features[k] = self._features(v)
        still = {kind for kind, _text in self.missing_items()}
        added = [text.split(" (")[0] for kind, text in before if kind not in still and kind != "count"]
        return ViewVerdict(key, True, "kept", self.features[key], rms, added)

    def _reject(self, key: int, reason: str, feat: ViewFeatures | None = None, rms: float | None = None) -> ViewVerdict:
        self.rejected[key] = reason
        return ViewVerdict(key, False, reason, feat, rms)

    # -- coverage -----------------------------------------------------------------------------------------------
    def missing_items(self) -> list[tuple[str, str]]:
        """What the kept views still lack, in the order they are asked for.

        Returns
        -------
        list of (str, str)
            ``(kind, words)`` with kind ``corner:NAME``, ``tilt:NAME``, ``near``, ``far`` or ``count``.
        """
        g = self.goals
        feats = list(self.features.values())
        out: list[tuple[str, str]] = []
        for name in CORNERS:
            best = max((f.reach[name] for f in feats), default=0.0)
            if best < g.corner_reach:
                out.append(
                    (
                        f"corner:{name}",
                        f"the image's {name} corner (board corners reach {100 * best:.0f}% of the way there; "
                        f"{100 * g.corner_reach:.0f}% needed)",
                    )
                )
        for name, (axis, sign) in TILTS.items():
            best = max((sign * f.tilt_deg[axis] for f in feats), default=0.0)
            if best < g.tilt_deg:
                out.append(
                    (
                        f"tilt:{name}",
                        f"the board turned with its {name} by {g.tilt_deg:.0f} deg or more (most so far "
                        f"{max(best, 0.0):.0f} deg)",
                    )
                )
        largest = max((f.fill for f in feats), default=0.0)
        if largest < g.near_fill:
            out.append(
                (
                    "near",
                    f"a near view: the board spanning {100 * g.near_fill:.0f}% of the image width or more "
                    f"(largest so far {100 * largest:.0f}%)",
                )
            )
        smallest = min((f.fill for f in feats), default=1.0)
        if smallest > g.far_fill:
            out.append(
                (
                    "far",
                    f"a far view: the board spanning {100 * g.far_fill:.0f}% of the image width or less"
                    + (f" (smallest so far {100 * smallest:.0f}%)" if feats else ""),
                )
            )
        if len(self.kept) < g.views:
            n = g.views - len(self.kept)
            out.append(("count", f"{n} more view{'s' if n > 1 else ''} ({len(self.kept)} of {g.views} kept)"))
        return out

    def missing(self) -> list[str]:
        """What is still missing, in words.

        Returns
        -------
        list of str
            Empty when the views cover everything.
        """
        return [text for _kind, text in self.missing_items()]

    @property
    def complete(self) -> bool:
        return not self.missing_items()

    @staticmethod
    def first_placement() -> BoardPlacement:
        """The first view, asked before the image size is known: the board in the middle, facing the camera.

        Returns
        -------
        BoardPlacement
        """
        return BoardPlacement(
            0,
            (0.5, 0.5),
            0.45,
            (0.0, 0.0),
            "view 1: hold the board so that it spans about 45% of the image width, its centre in the middle of the "
            "image, facing the camera squarely; keep every corner of the board in view and hold it still",
        )

    def next_placement(self) -> BoardPlacement:
        """Where to hold the board next: for the first thing missing, else a placement that varies the views.

        Returns
        -------
        BoardPlacement
        """
        self._asked += 1
        items = self.missing_items()
        kind = items[0][0] if items else "count"
        aspect = (self.board.size_m[1] / self.board.size_m[0]) * self.width / self.height
        tilt = (0.0, 0.0)
        if kind.startswith("corner:"):
            sx, sy = CORNERS[kind.split(":", 1)[1]]
            fill = 0.3
            centre = (0.5 + sx * (0.5 - 0.03 - fill / 2), 0.5 + sy * (0.5 - 0.03 - fill * aspect / 2))
            what = f"its outer corner close to the image's {kind.split(':', 1)[1]} corner (a finger's width from it)"
        elif kind.startswith("tilt:"):
            axis, sign = TILTS[kind.split(":", 1)[1]]
            fill, centre = 0.42, (0.5, 0.5)
            tilt = (30.0 * sign, 0.0) if axis == 0 else (0.0, 30.0 * sign)
            what = "its centre in the middle of the image"
        elif kind == "near":
            fill, centre, what = 0.62, (0.5, 0.5), "its centre in the middle of the image"
        elif kind == "far":
            fill, centre, what = 0.3, (0.5, 0.5), "its centre in the middle of the image"
        else:  # vary: positions around the image, alternating tilts
            k = self._asked
            cells = [(0.3, 0.3), (0.7, 0.7), (0.7, 0.3), (0.3, 0.7), (0.5, 0.5), (0.5, 0.3), (0.5, 0.7), (0.3, 0.5),
                     (0.7, 0.5)]  # fmt: skip
            tilts = [(25.0, 0.0), (0.0, -25.0), (-25.0, 0.0), (0.0, 25.0), (18.0, 18.0), (-18.0, -18.0)]
            centre, tilt, fill = cells[k % len(cells)], tilts[k % len(tilts)], (0.38, 0.45, 0.5)[k % 3]
            where = _location(*centre)
            what = (
                "its centre in the middle of the image"
                if where == "centre"
                else f"its centre at the {where} of the image"
            )
        text = (
            f"view {len(self.kept) + 1}: hold the board so that it spans about {100 * fill:.0f}% of the image width, "
            f"{what}, {_tilt_words(tilt)}; keep every corner of the board in view and hold it still"
        )
        return BoardPlacement(self._asked, (float(centre[0]), float(centre[1])), float(fill), tilt, text)

    def views(self) -> dict[int, tuple[NDArray[np.int_], Array, None]]:
        """The kept views as :func:`calib.camera.intrinsics.calibrate_intrinsics` takes them.

        Returns
        -------
        dict of int to (ndarray, ndarray, None)
            Per key: the board's corner ids (M,), sorted, and their pixels (M, 2).
        """
        return {k: (self.ids_all.copy(), v, None) for k, v in self.kept.items()}

    def coverage(self) -> dict[str, Any]:
        """The views' coverage (the camera file's ``acquired.coverage``).

        Returns
        -------
        dict
            ``goals``, ``corner_reach`` (0-1 per image corner), ``tilt_deg`` (the largest turn per direction,
            degrees), ``fill`` (smallest and largest, fractions of the image width), ``kept``, ``rejected``,
            ``missing`` (words) and ``views`` (each kept view's features).
        """
        feats = list(self.features.values())
        return {
            "goals": {k: getattr(self.goals, k) for k in GOAL_KEYS},
            "corner_reach": {n: max((f.reach[n] for f in feats), default=0.0) for n in CORNERS},
            "tilt_deg": {n: max((s * f.tilt_deg[a] for f in feats), default=0.0) for n, (a, s) in TILTS.items()},
            "fill": [min((f.fill for f in feats), default=0.0), max((f.fill for f in feats), default=0.0)],
            "kept": len(self.kept),
            "rejected": {str(k): v for k, v in self.rejected.items()},
            "missing": self.missing(),
            "views": {str(k): f.to_dict() for k, f in self.features.items()},
        }
