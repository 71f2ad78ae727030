"""Rod (leg) observation: predicted image, limb lines with sub-pixel edges, axis from interpretation planes.

Geometry (the paper's eqs. 6-7). A rod is a cylinder of radius r, axis through P with unit
direction u (camera frame). Its two silhouette (limb) lines are the images of the two planes
through the camera centre tangent to the cylinder; their unit normals h1, h2 ("interpretation
planes") satisfy ``h_j . u = 0`` and ``h_j . X = r`` for every axis point X (signs chosen so that
the axis is on the positive side). Hence ``u = normalize(h1 x h2)`` and the axis point closest to
the camera centre solves ``[h1; h2; u] X = [r, r, 0]``.

Extraction, per rod and per frame (see docs/vision.md):

1. Prediction: the nominal model at the encoder values and a coarse ``camera_from_base`` give the
   rod's axis segment in the camera frame, hence its two limb lines in ideal (undistorted) pixels.
2. Profiles: along the predicted axis, every ``step_px``, a profile perpendicular to it is sampled
   in ideal-pixel coordinates (each sample mapped to the distorted image with the camera model and
   read by bilinear interpolation); samples hidden by the board or outside the image are dropped.
3. Edges: the derivative-of-Gaussian of each profile, its local maxima of |gradient|, parabolic
   interpolation to sub-pixel; per profile the pair of edges of opposite polarity whose spacing
   matches the predicted width and whose centre is nearest the prediction (inside the band).
4. Lines: per limb, RANSAC (2-point) then iteratively reweighted total least squares with a
   3-sigma rejection; quality figures: residual RMS (px), number of edge points, and the angle
   between the two interpretation planes; the two rods of a leg are compared (parallelism).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..camera import CameraModel
from ..kinematics import dkm, joint_points
from ..parameters import I4Parameters
from ..transforms import Rigid

Array = NDArray[np.float64]

_CORR = 1.0
ROD_KEYS = [(leg, rod) for leg in range(4) for rod in range(2)]


def rod_name(leg: int, rod: int) -> str:
    """``leg{1..4}.rod{0,1}`` for 0-based leg index and rod index."""
    return f"leg{leg + 1}.rod{rod}"


# ---------------------------------------------------------------------------------------------
# geometry
def limb_planes(point: ArrayLike, u: ArrayLike, radius: float) -> tuple[Array, Array]:
    """Unit normals of the two tangent planes through the camera centre (eq. 6), each shape (3,).

    Signs: ``h . X = +radius`` for every axis point X. Raises ValueError when the camera centre is
    inside the cylinder.
    """
    P = np.asarray(point, dtype=np.float64).reshape(3)
    uu = np.asarray(u, dtype=np.float64).reshape(3)
    uu = uu / np.linalg.norm(uu)
    p = P - (P @ uu) * uu
    d = float(np.linalg.norm(p))
    if d <= radius:
        raise ValueError(f"camera centre inside the cylinder (distance {d:.4g} m <= radius {radius:.4g} m)")
    e1 = p / d
    e2 = np.cross(uu, e1)
    c = radius / d
    s = np.sqrt(1.0 - c * c)
    return c * e1 + s * e2, c * e1 - s * e2


def axis_from_planes(h1: ArrayLike, h2: ArrayLike, radius: float | None) -> tuple[Array, Array | None]:
    """Axis direction (eq. 7) and, with the radius, the axis point closest to the camera centre.

    Parameters
    ----------
    h1, h2 : array_like, shape (3,)
        Interpretation-plane normals, signed so that the axis is on their positive side.
    radius : float or None
        Rod radius, metres.

    Returns
    -------
    u : ndarray, shape (3,)
        Unit direction (sign: h1 x h2).
    point : ndarray, shape (3,) or None
        Metres, camera frame.
    """
    a = np.asarray(h1, dtype=np.float64).reshape(3)
    b = np.asarray(h2, dtype=np.float64).reshape(3)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    u = np.cross(a, b)
    n = np.linalg.norm(u)
    if n < 1e-12:
        raise ValueError("interpretation planes are parallel: no axis")
    u = u / n
    if radius is None:
        return u, None
    M = np.vstack([a, b, u])
    X = np.linalg.solve(M, np.array([radius, radius, 0.0]))
    return u, X


# ---------------------------------------------------------------------------------------------
@dataclass
class RodPrediction:
    """A rod's predicted axis segment in the camera frame (metres): from ``top`` (actuator) to ``bottom``."""

    leg: int
    rod: int
    top: Array
    bottom: Array

    @property
    def u(self) -> Array:
        d = self.bottom - self.top
        return d / np.linalg.norm(d)


def predict_rods(nominal: I4Parameters, q: ArrayLike, camera_from_base: Rigid, rod_spacing_m: float
                 ) -> list[RodPrediction]:
    """Predicted rod segments (8, in ``ROD_KEYS`` order) from the nominal model and encoder values.

    Raises :class:`~calib.errors.UnreachableError` when the nominal model cannot close at ``q``.
    """
    qv = np.asarray(q, dtype=np.float64).reshape(4)
    pose = dkm(nominal, qv)
    A, B = joint_points(nominal, qv[None], pose[None])
    out = []
    for leg in range(4):
        for rod in range(2):
            off = np.array([(rod - 0.5) * rod_spacing_m, 0.0, 0.0])
            out.append(RodPrediction(leg, rod, camera_from_base.apply(A[0, leg] + off),
                                     camera_from_base.apply(B[0, leg] + off)))
    return out


@dataclass
class RodSettings:
    """Tuning of the rod extraction (pixels are ideal, undistorted pixels)."""

    band_px: float = 18.0          #: search half-band around each predicted limb line
    step_px: float = 3.0           #: spacing of the profiles along the axis
    sigma_px: float = 1.0          #: derivative-of-Gaussian scale on the profiles
    sample_px: float = 0.5         #: sample spacing along each profile
    min_contrast: float = 6.0      #: minimum |gradient| (grey levels per px) of an edge
    width_tolerance: float = 0.35  #: accepted relative deviation of the limb spacing from the prediction
    ransac_iters: int = 150
    inlier_px: float = 1.0         #: RANSAC inlier threshold
    min_points: int = 20           #: per limb, after outlier rejection
    min_length_px: float = 40.0    #: visible length needed
    max_rms_px: float = 0.8        #: residual RMS above this: rod rejected
    min_plane_angle_rad: float = 2e-3
    border_px: float = 3.0         #: samples closer to the image border are dropped
    near_m: float = 0.05           #: the segment is clipped to z >= near_m


@dataclass
class RodMeasurement:
    """One rod measured in one image (or the reason why not: ``reason`` set, ``u`` None)."""

    leg: int
    rod: int
    u: Array | None = None
    point: Array | None = None
    h: tuple[Array, Array] | None = None
    rms_px: tuple[float, float] = (np.nan, np.nan)
    n_points: tuple[int, int] = (0, 0)
    plane_angle_rad: float = np.nan
    reason: str | None = None
    lines_px: list[Array] = field(default_factory=list)  # per limb (a, b, c) in ideal pixels, a^2+b^2=1

    @property
    def ok(self) -> bool:
        return self.u is not None

    def to_dict(self) -> dict | None:
        if self.u is None:
            return None
        d = {"u": self.u.tolist(), "rms_px": [float(x) for x in self.rms_px],
             "n_points": [int(x) for x in self.n_points], "plane_angle_rad": float(self.plane_angle_rad)}
        if self.point is not None:
            d["point"] = self.point.tolist()
        return d


# ---------------------------------------------------------------------------------------------
def _fit_line_tls(pts: Array, w: Array | None = None) -> Array:
    """Total least squares line (a, b, c), a^2 + b^2 = 1, of points (N, 2) with optional weights."""
    if w is None:
        w = np.ones(len(pts))
    c = (w[:, None] * pts).sum(0) / w.sum()
    d = pts - c
    C = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0)
    _, evecs = np.linalg.eigh(C)
    n = evecs[:, 0]
    return np.array([n[0], n[1], -n @ c])


def robust_line(pts: Array, rng: np.random.Generator, iters: int, inlier_px: float) -> tuple[Array, NDArray[np.bool_]]:
    """RANSAC then IRLS (Tukey) total-least-squares line with a final 3-sigma rejection.

    Returns the line (a, b, c) with unit normal and the inlier mask.
    """
    n = len(pts)
    best = None
    best_count = -1
    if n >= 2:
        i = rng.integers(0, n, size=(iters, 2))
        i = i[i[:, 0] != i[:, 1]]
        p, q = pts[i[:, 0]], pts[i[:, 1]]
        d = q - p
        nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
        ln = np.linalg.norm(nrm, axis=1)
        good = ln > 1e-9
        nrm = nrm[good] / ln[good, None]
        c = -np.sum(nrm * p[good], axis=1)
        dist = np.abs(pts @ nrm.T + c)  # (n, m)
        counts = (dist < inlier_px).sum(0)
        if counts.size:
            k = int(np.argmax(counts))
            best_count = int(counts[k])
            best = np.array([nrm[k, 0], nrm[k, 1], c[k]])
    if best is None or best_count < 2:
        return np.array([np.nan, np.nan, np.nan]), np.zeros(n, dtype=bool)
    inl = np.abs(pts @ best[:2] + best[2]) < inlier_px
    line = _fit_line_tls(pts[inl])
    for _ in range(4):
        r = pts @ line[:2] + line[2]
        s = max(1.4826 * float(np.median(np.abs(r[inl]))), 0.05)
        cut = 4.685 * s
        w = np.where(np.abs(r) < cut, (1 - (r / cut) ** 2) ** 2, 0.0)
        if (w > 0).sum() < 2:
            break
        line = _fit_line_tls(pts, w)
    r = pts @ line[:2] + line[2]
    inl = np.abs(r) < max(3.0 * 1.4826 * float(np.median(np.abs(r[np.abs(r) < 3 * inlier_px]))) if
                          np.any(np.abs(r) < 3 * inlier_px) else inlier_px, 0.3)
    if inl.sum() >= 2:
        line = _fit_line_tls(pts[inl])
    return line, inl


def _edges_1d(g: Array, min_contrast: float, side: int = 3) -> tuple[Array, Array, Array]:
    """Sub-pixel edges along axis 1 of the gradient profiles g (P, S), sample spacing 1 px.

    Local maxima of |g| with parabolic interpolation, then a correction for the intensity slopes on
    either side of the edge: for a step of height A between linear ramps of slopes kL and kR seen
    through a Gaussian of variance s^2, the gradient peaks at ``x0 + (kR - kL) s^2 / A``; kL and kR
    are read from g at ``side`` px on each side, s^2 from the peak's curvature and A = g_peak
    sqrt(2 pi) s. Without it, the shading of a rod next to its limb biases the edge by a few
    tenths of a pixel, which the near-parallel limb lines amplify ~40x in the axis direction.

    Returns (profile index, position, signed gradient at the peak).
    """
    a = np.abs(g)
    mid = a[:, 1:-1]
    peak = (mid > a[:, :-2]) & (mid >= a[:, 2:]) & (mid > min_contrast)
    peak[:, : side - 1] = False
    peak[:, mid.shape[1] - side + 1:] = False
    pi, si = np.nonzero(peak)
    si = si + 1
    y0, y1, y2 = a[pi, si - 1], a[pi, si], a[pi, si + 1]
    den = y0 - 2 * y1 + y2
    safe = np.where(np.abs(den) > 1e-12, den, -1e-12)
    off = np.clip(0.5 * (y0 - y2) / safe, -0.5, 0.5)
    gp = g[pi, si]
    s2 = np.clip(-y1 / safe, 0.3, 60.0)
    amp = gp * np.sqrt(2 * np.pi * s2)
    kL = g[pi, si - side]
    kR = g[pi, si + side]
    corr = np.clip((kR - kL) * s2 / amp, -0.5, 0.5) * _CORR
    return pi, si + off - corr, gp


_TRIU: dict[int, tuple[NDArray[np.int_], NDArray[np.int_]]] = {}


def _triu(n: int) -> tuple[NDArray[np.int_], NDArray[np.int_]]:
    if n not in _TRIU:
        _TRIU[n] = np.triu_indices(n, 1)
    return _TRIU[n]


def _gauss_deriv_kernel(sigma: float) -> Array:
    r = max(2, int(np.ceil(3 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = -x * np.exp(-0.5 * (x / sigma) ** 2)
    k /= np.sum(np.abs(x * k))
    return k


def _inside_convex(pts: Array, poly: Array) -> NDArray[np.bool_]:
    """Points (N, 2) inside a convex polygon (M, 2) (either orientation)."""
    d = np.roll(poly, -1, axis=0) - poly
    cr = d[None, :, 0] * (pts[:, None, 1] - poly[None, :, 1]) - d[None, :, 1] * (pts[:, None, 0] - poly[None, :, 0])
    return np.all(cr >= 0, axis=1) | np.all(cr <= 0, axis=1)


def measure_rod(gray: np.ndarray, camera: CameraModel, pred: RodPrediction, radius: float,
                settings: RodSettings | None = None, occluders: list[Array] | None = None,
                rng: np.random.Generator | None = None, ideal_bbox: Array | None = None) -> RodMeasurement:
    """Measure one rod in an image.

    Parameters
    ----------
    gray : ndarray, shape (H, W), float32 or uint8
        The (distorted) image, single channel.
    camera : CameraModel
    pred : RodPrediction
        Predicted axis segment, camera frame.
    radius : float
        Rod radius, metres.
    occluders : list of ndarray, shape (M, 2)
        Convex polygons in ideal pixels that hide the rod (e.g. the board); profiles inside are dropped.
    """
    s = settings or RodSettings()
    rng = rng or np.random.default_rng(0)
    out = RodMeasurement(pred.leg, pred.rod)
    K = camera.K
    top, bot = pred.top.copy(), pred.bottom.copy()
    # clip the segment to z >= near
    if top[2] < s.near_m and bot[2] < s.near_m:
        out.reason = "predicted behind the camera"
        return out
    if top[2] < s.near_m:
        top = top + (bot - top) * (s.near_m - top[2]) / (bot[2] - top[2])
    if bot[2] < s.near_m:
        bot = bot + (top - bot) * (s.near_m - bot[2]) / (top[2] - bot[2])
    # the segment in ideal pixels, clipped to the (undistorted) image region
    try:
        h1p, h2p = limb_planes(top, bot - top, radius)
    except ValueError as exc:
        out.reason = str(exc)
        return out
    a_px = K @ (top / top[2])
    b_px = K @ (bot / bot[2])
    a2, b2 = a_px[:2], b_px[:2]
    # clip the 2-D segment to the ideal-pixel bounding box of the image (Liang-Barsky)
    box = ideal_bbox if ideal_bbox is not None else image_ideal_bbox(camera)
    d2 = b2 - a2
    t0, t1 = 0.0, 1.0
    for p_, q_ in ((-d2[0], a2[0] - box[0]), (d2[0], box[2] - a2[0]), (-d2[1], a2[1] - box[1]),
                   (d2[1], box[3] - a2[1])):
        if abs(p_) < 1e-12:
            if q_ < 0:
                t0, t1 = 1.0, 0.0
            continue
        r_ = q_ / p_
        if p_ < 0:
            t0 = max(t0, r_)
        else:
            t1 = min(t1, r_)
    if t1 <= t0:
        out.reason = "rod predicted outside the image"
        return out
    a2, b2 = a2 + t0 * d2, a2 + t1 * d2
    length = float(np.linalg.norm(b2 - a2))
    if length < 1e-6:
        out.reason = "predicted rod seen end-on"
        return out
    t_dir = (b2 - a2) / length
    n_dir = np.array([-t_dir[1], t_dir[0]])
    # predicted limb offsets along n (ideal px), measured at the segment's middle
    def limb_offset(h: Array, c: Array) -> float:
        lp = np.linalg.inv(K).T @ h  # line in ideal pixels
        lp = lp / np.linalg.norm(lp[:2])
        # signed distance from point c along n to the line: solve lp.(c + x n) = 0
        den = lp[:2] @ n_dir
        return float(-(lp[:2] @ c + lp[2]) / den) if abs(den) > 1e-9 else np.nan
    # limit the length sampled: image bounds are checked per sample below
    ts = np.arange(0.0, length, s.step_px)
    if ts.size > 1500:
        ts = np.linspace(0.0, length, 1500)
    centres = a2[None] + ts[:, None] * t_dir[None]
    # width varies along the rod (perspective): interpolate the limb offsets between the ends
    off1 = np.array([limb_offset(h1p, a2), limb_offset(h1p, b2)])
    off2 = np.array([limb_offset(h2p, a2), limb_offset(h2p, b2)])
    if not np.all(np.isfinite(off1)) or not np.all(np.isfinite(off2)):
        out.reason = "degenerate predicted limb lines"
        return out
    # keep centres inside the image (after distortion) and outside occluders
    xn = camera.from_ideal_pixels(centres)
    dpx = camera.distort_normalized(xn)
    # guard against the distortion polynomial's fold-back far outside the field of view: the
    # samples must lie inside the ideal-pixel bounding box of the image
    inside = ((dpx[:, 0] >= s.border_px) & (dpx[:, 0] <= camera.width - 1 - s.border_px)
              & (dpx[:, 1] >= s.border_px) & (dpx[:, 1] <= camera.height - 1 - s.border_px)
              & (centres[:, 0] >= box[0]) & (centres[:, 0] <= box[2])
              & (centres[:, 1] >= box[1]) & (centres[:, 1] <= box[3]))
    half = 0.5 * float(np.max(np.abs(np.concatenate([off1 - off2]))))
    if occluders:
        for poly in occluders:
            # a profile is hidden when any part of its span is inside the polygon
            for k in (-1.0, 0.0, 1.0):
                inside &= ~_inside_convex(centres + k * (half + 4.0) * n_dir[None], poly)
    if inside.sum() * s.step_px < s.min_length_px:
        vis = inside.sum() * s.step_px
        out.reason = (f"not enough of the rod visible ({vis:.0f} px of {length:.0f} px predicted; "
                      "outside the image or hidden by the board)")
        return out
    ts = ts[inside]
    centres = centres[inside]
    frac = ts / length
    o1 = off1[0] + frac * (off1[1] - off1[0])
    o2 = off2[0] + frac * (off2[1] - off2[0])
    lo = np.minimum(o1, o2).min() - s.band_px
    hi = np.maximum(o1, o2).max() + s.band_px
    ds = s.sample_px
    offs = np.arange(lo, hi + 1e-9, ds)
    grid = centres[:, None, :] + offs[None, :, None] * n_dir[None, None, :]  # (P, S, 2) ideal px
    gpx = camera.distort_normalized(camera.from_ideal_pixels(grid.reshape(-1, 2))).astype(np.float32)
    img = gray if gray.dtype == np.float32 else gray.astype(np.float32)
    prof = cv2.remap(img, gpx[:, 0].reshape(len(ts), -1), gpx[:, 1].reshape(len(ts), -1), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    ker = _gauss_deriv_kernel(s.sigma_px / ds)
    g = cv2.filter2D(prof, cv2.CV_32F, ker[None, ::-1].astype(np.float32), borderType=cv2.BORDER_REPLICATE)
    g = g.astype(np.float64) / ds  # grey levels per pixel
    pi, pos, sg = _edges_1d(g, s.min_contrast, max(2, round(3.0 / ds)))
    off_pos = lo + pos * ds
    # pair selection per profile
    pw = np.abs(o2 - o1)
    pc = 0.5 * (o1 + o2)
    left_is_1 = (o1 < o2)  # the limb with the smaller offset
    pol: list[int] = []
    e1: list[tuple[int, float]] = []
    e2: list[tuple[int, float]] = []
    order = np.argsort(pi, kind="stable")
    pi, off_pos, sg = pi[order], off_pos[order], sg[order]
    bounds = np.searchsorted(pi, np.arange(len(ts) + 1))
    for k in range(len(ts)):
        a, b = bounds[k], bounds[k + 1]
        if b - a < 2:
            continue
        xo, gg = off_pos[a:b], sg[a:b]
        near = np.abs(xo - pc[k]) < pw[k] / 2 + s.band_px
        xo, gg = xo[near], gg[near]
        if xo.size < 2:
            continue
        ii, jj = _triu(xo.size)
        wdt = np.abs(xo[jj] - xo[ii])
        ok = (np.abs(wdt - pw[k]) < s.width_tolerance * pw[k]) & (gg[ii] * gg[jj] < 0)
        if not ok.any():
            continue
        ii, jj = ii[ok], jj[ok]
        cen = 0.5 * (xo[ii] + xo[jj])
        score = (np.minimum(np.abs(gg[ii]), np.abs(gg[jj]))
                 / (1.0 + (np.abs(cen - pc[k]) / 4.0) ** 2 + (np.abs(xo[jj] - xo[ii]) - pw[k]) ** 2 / 4.0))
        m = int(np.argmax(score))
        lo_i = ii[m] if xo[ii[m]] < xo[jj[m]] else jj[m]
        x_lo, x_hi = sorted((xo[ii[m]], xo[jj[m]]))
        pol.append(1 if gg[lo_i] > 0 else -1)
        if left_is_1[k]:
            e1.append((k, x_lo))
            e2.append((k, x_hi))
        else:
            e1.append((k, x_hi))
            e2.append((k, x_lo))
    # one polarity per rod (brighter or darker than its surroundings): the pairs of the other
    # polarity are gaps between two bright things (e.g. the two rods of a leg), dropped
    if pol:
        polarity = np.asarray(pol)
        keep = polarity == (1 if polarity.sum() >= 0 else -1)
        e1 = [e for e, kp in zip(e1, keep, strict=True) if kp]
        e2 = [e for e, kp in zip(e2, keep, strict=True) if kp]
    lines = []
    rms = []
    npts = []
    for e in (e1, e2):
        if len(e) < s.min_points:
            out.reason = (f"too few limb edge points ({len(e)} < {s.min_points}): rod not found in its search band")
            return out
        kk = np.array([x[0] for x in e])
        xo = np.array([x[1] for x in e])
        pts = centres[kk] + xo[:, None] * n_dir[None]
        line, inl = robust_line(pts, rng, s.ransac_iters, s.inlier_px)
        if not np.all(np.isfinite(line)) or inl.sum() < s.min_points:
            out.reason = f"limb line fit failed ({int(inl.sum())} inliers of {len(e)})"
            return out
        r = pts[inl] @ line[:2] + line[2]
        lines.append(line)
        rms.append(float(np.sqrt(np.mean(r ** 2))))
        npts.append(int(inl.sum()))
    out.lines_px = lines
    out.rms_px = (rms[0], rms[1])
    out.n_points = (npts[0], npts[1])
    if max(rms) > s.max_rms_px:
        out.reason = f"limb edges too scattered (residual RMS {max(rms):.2f} px > {s.max_rms_px} px)"
        return out
    # interpretation-plane normals h = K^T l, signed so that the predicted axis is on the positive side
    mid = np.append(0.5 * (a2 + b2), 1.0)
    # use the measured centre line for the sign test
    hs = []
    for line in lines:
        h = K.T @ line
        h = h / np.linalg.norm(h)
        hs.append(h)
    l_c = lines[0] * np.sign(lines[0][:2] @ lines[1][:2])
    # a point between the two measured lines, near the middle of the visible part
    cmid = centres[len(centres) // 2]
    d1 = cmid @ lines[0][:2] + lines[0][2]
    d2 = cmid @ lines[1][:2] + lines[1][2]
    # move cmid along n to the midpoint between the limbs
    n1 = lines[0][:2] @ n_dir
    n2 = lines[1][:2] @ n_dir
    x1 = -d1 / n1 if abs(n1) > 1e-9 else 0.0
    x2 = -d2 / n2 if abs(n2) > 1e-9 else 0.0
    inner = np.append(cmid + 0.5 * (x1 + x2) * n_dir, 1.0)
    del l_c, mid
    m_in = np.linalg.inv(K) @ inner
    hs = [h if h @ m_in > 0 else -h for h in hs]
    ang = float(np.arccos(np.clip(abs(hs[0] @ hs[1]), -1.0, 1.0)))
    out.plane_angle_rad = ang
    if ang < s.min_plane_angle_rad:
        out.reason = f"interpretation planes nearly parallel ({ang * 1e3:.2f} mrad): axis ill-defined"
        return out
    try:
        u, X = axis_from_planes(hs[0], hs[1], radius)
    except ValueError as exc:
        out.reason = str(exc)
        return out
    if u @ pred.u < 0:
        u = -u
    out.h = (hs[0], hs[1])
    out.u = u
    out.point = X
    return out


def image_ideal_bbox(camera: CameraModel, margin_px: float = 2.0) -> Array:
    """Bounding box (xmin, ymin, xmax, ymax) in ideal pixels of the whole image, with a margin."""
    b = camera.to_ideal_pixels(camera.normalized_bounds())
    return np.array([b[:, 0].min() - margin_px, b[:, 1].min() - margin_px, b[:, 0].max() + margin_px,
                     b[:, 1].max() + margin_px])


def measure_rods(gray: np.ndarray, camera: CameraModel, preds: list[RodPrediction], radius: float,
                 settings: RodSettings | None = None, occluders: list[Array] | None = None,
                 seed: int = 0, ideal_bbox: Array | None = None) -> list[RodMeasurement]:
    """Measure every predicted rod of a frame (see :func:`measure_rod`)."""
    img = gray.astype(np.float32) if gray.dtype != np.float32 else gray
    rng = np.random.default_rng(seed)
    box = ideal_bbox if ideal_bbox is not None else image_ideal_bbox(camera)
    return [measure_rod(img, camera, p, radius, settings, occluders, rng, box) for p in preds]


def leg_parallelism(meas: list[RodMeasurement]) -> dict[str, float]:
    """Angle (rad) between the two rods of each leg where both were measured, keyed ``"1".."4"``."""
    out = {}
    by = {(m.leg, m.rod): m for m in meas}
    for leg in range(4):
        a, b = by.get((leg, 0)), by.get((leg, 1))
        if a is not None and b is not None and a.ok and b.ok:
            out[str(leg + 1)] = float(np.arccos(np.clip(abs(a.u @ b.u), -1.0, 1.0)))
    return out
