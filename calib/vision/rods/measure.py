"""Rod measurement: profiles across the predicted limbs, sub-pixel edges, occlusion by the board and by other rods, the
limb lines, every rod of a frame, and the two rods of a leg compared.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.formats.camera import CameraModel
from calib.numerics.transforms import cross
from calib.vision.rods.covariance import _direction_covariance_sets, _line_stats
from calib.vision.rods.cylinder import _CORR, axis_point_seen_along, limb_planes, norm3
from calib.vision.rods.linefit import ransac_start, refine_lines
from calib.vision.rods.types import ROD_OCCLUDER_CLEARANCE_PX, RodMeasurement, RodPrediction, RodSettings

Array = NDArray[np.float64]


def _edges_1d(
    g: NDArray[np.floating], min_contrast: float, side: int = 3, valid: NDArray[np.bool_] | None = None, radius: int = 0
) -> tuple[NDArray[np.intp], Array, Array]:
    """Sub-pixel edges along axis 1 of the gradient profiles g (P, S), in samples.

    Local maxima of |g|, located by a parabola through the logarithms of the three samples about the maximum
    (exact for the Gaussian that a blurred step's gradient is; a parabola through the values themselves is
    off by up to 0.07 samples, depending on where the edge falls between samples), then a correction for the
    intensity slopes on either side of the edge: for a step of height A between linear ramps of slopes kL
    and kR seen through a Gaussian of variance s^2, the gradient peaks at ``x0 + (kR - kL) s^2 / A``; kL and
    kR are read from g at ``side`` samples on each side of the located peak (interpolated: at the nearest
    samples, the Gaussian's tails differ by an amount that changes with the edge's place between samples, and
    so would the edge, by up to 0.08 samples), s^2 from the peak's curvature and A = g_peak sqrt(2 pi) s.
    Without it, the shading of a rod next to its limb biases the edge by a few tenths of a pixel, which the
    near-parallel limb lines amplify ~40x in the axis direction.

    ``valid`` (P, S): the samples inside the image (beyond it a profile reads the border's replicated pixels, which
    pull the last edges of a limb leaving the image by up to several pixels): a peak whose derivative kernel
    (``radius`` samples either side) reaches an invalid sample is dropped, one whose slope samples do is kept without
    the slope correction, so that the limbs keep their far ends (the edges there carry the most weight on the
    axis direction).

    Returns (profile index, position in samples, signed gradient at the peak), float64 (g may be float32).
    """
    pk = _peaks(g, min_contrast, side, valid, radius)
    return _kept(pk, *_subpixel(pk.si, pk.win, side))


@dataclass
class _Peaks:
    """The local maxima of |g| in gradient profiles (:func:`_peaks`): profile index (N,) and sample (N,) of each,
    the profile's samples about it (N, 2 side + 3) (from ``side + 1`` before to ``side + 1`` after), which of them
    to drop (N,) and which to keep without the slope correction (N,), both None when all samples are valid."""

    pi: NDArray[np.intp]
    si: NDArray[np.intp]
    win: NDArray[np.floating]
    drop: NDArray[np.bool_] | None
    flat: NDArray[np.bool_] | None


def _peaks(
    g: NDArray[np.floating], min_contrast: float, side: int, valid: NDArray[np.bool_] | None, radius: int
) -> _Peaks:
    """The first stage of :func:`_edges_1d`: its peaks found, the samples its interpolation reads gathered."""
    a = np.abs(g)
    mid = a[:, 1:-1]
    peak = mid > min_contrast
    peak &= mid > a[:, :-2]
    peak &= mid >= a[:, 2:]
    # the slope samples (side + 1 about the peak, for the interpolation) must lie within the profile
    peak[:, :side] = False
    peak[:, mid.shape[1] - side :] = False
    n = g.shape[1]
    pi, si = np.divmod(np.flatnonzero(peak), mid.shape[1])  # row-major, as np.nonzero
    si += 1
    at = pi * n + si  # in the flattened profiles
    win = np.ravel(g).take(at[:, None] + np.arange(-side - 1, side + 2))
    drop = flat = None
    if valid is not None and not valid.all():  # (all valid: nothing dropped, every correction kept)
        # samples beyond the image (the border's replicated pixels): a peak whose derivative kernel reaches them is
        # dropped; one whose slope samples do is kept without the slope correction
        drop = np.zeros(pi.size, dtype=bool)
        flat = np.zeros(pi.size, dtype=bool)
        row_ok: NDArray[np.bool_] = np.all(valid, axis=1)
        sel = np.flatnonzero(~row_ok[pi])  # the peaks of profiles with invalid samples
        reach = max(radius, side) + 1
        col = si[sel, None] + np.arange(-reach, reach + 1)
        bad = ~np.ravel(valid).take(pi[sel, None] * n + np.clip(col, 0, n - 1)) & (col >= 0) & (col < n)
        drop[sel] = bad[:, reach - radius - 1 : reach + radius + 2].any(axis=1)
        flat[sel] = bad[:, reach - side - 1 : reach + side + 2].any(axis=1)
    return _Peaks(pi, si, win, drop, flat)


def _subpixel(si: NDArray[np.intp], win: NDArray[np.floating], side: int) -> tuple[Array, Array, Array]:
    """The second stage of :func:`_edges_1d`, on the peaks of any number of profiles: each peak's position (samples,
    without the slope correction), the slope correction (samples) and the signed gradient, float64, from its samples
    ``win`` (N, 2 side + 3)."""
    f64 = np.float64
    c = side + 1  # the peak's column in win
    gp = win[:, c].astype(f64)
    y0, y1, y2 = np.abs(win[:, c - 1]).astype(f64), np.abs(gp), np.abs(win[:, c + 1]).astype(f64)
    tiny = 1e-6 * y1
    l0, l1, l2 = np.log(np.maximum(y0, tiny)), np.log(y1), np.log(np.maximum(y2, tiny))
    den = l0 - 2 * l1 + l2  # -1 / s^2 for a Gaussian
    safe = np.where(den < -1e-12, den, -1e-12)
    off = np.clip(0.5 * (l0 - l2) / safe, -0.5, 0.5)
    s2 = np.clip(-1.0 / safe, 0.3, 60.0)
    amp = np.sign(gp) * np.exp(l1 - 0.5 * off * off * safe) * np.sqrt(2 * np.pi * s2)  # the step's height
    rows = np.arange(len(si))
    base = si - c  # the sample at win's column 0

    def at(x: Array) -> Array:
        # linear interpolation of g at x (samples); x lies within the window (the peaks keep side + 1 samples from
        # either end of their profile)
        i0 = np.floor(x).astype(np.intp)
        fr = np.clip(x - i0, 0.0, 1.0)
        j = i0 - base
        return (1.0 - fr) * win[rows, j].astype(f64) + fr * win[rows, j + 1].astype(f64)

    x0 = si + off
    kL, kR = at(x0 - side), at(x0 + side)
    corr = np.clip((kR - kL) * s2 / amp, -0.5, 0.5) * _CORR
    return x0, corr, gp


def _kept(pk: _Peaks, x0: Array, corr: Array, gp: Array) -> tuple[NDArray[np.intp], Array, Array]:
    """:func:`_edges_1d`'s result from its peaks and their :func:`_subpixel` positions: the peaks reading invalid
    samples dropped, or kept without the slope correction."""
    if pk.drop is None or pk.flat is None:
        return pk.pi, x0 - corr, gp
    keep = ~pk.drop
    return pk.pi[keep], (x0 - np.where(pk.flat, 0.0, corr))[keep], gp[keep]


@functools.lru_cache(maxsize=8)
def _gauss_deriv_kernel(sigma: float) -> Array:
    """The derivative-of-Gaussian kernel of scale ``sigma`` (samples), shape (2 r + 1,), normalised by ``sum |x k|``
    (read-only: computed once per scale)."""
    r = max(2, int(np.ceil(3 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = -x * np.exp(-0.5 * (x / sigma) ** 2)
    k /= np.sum(np.abs(x * k))
    k.setflags(write=False)
    return k


def _inside_convex(pts: Array, poly: Array) -> NDArray[np.bool_]:
    """Points (N, 2) inside a convex polygon (M, 2) (either orientation)."""
    d = np.roll(poly, -1, axis=0) - poly
    cr = d[None, :, 0] * (pts[:, None, 1] - poly[None, :, 1]) - d[None, :, 1] * (pts[:, None, 0] - poly[None, :, 0])
    return np.all(cr >= 0, axis=1) | np.all(cr <= 0, axis=1)


def _hidden(centres: Array, shift: Array, ks: tuple[float, ...], poly: Array) -> NDArray[np.bool_]:
    """Whether any of the points ``centres + k * shift`` (k in ks) is inside the convex polygon ``poly``.

    Same test as :func:`_inside_convex` on each shifted set, with the edge cross products computed once
    (they are affine in the shift). ``shift``: shape (2,), or (N, 2) one per centre.
    """
    d = np.roll(poly, -1, axis=0) - poly
    base = d[None, :, 0] * (centres[:, None, 1] - poly[None, :, 1]) - d[None, :, 1] * (
        centres[:, None, 0] - poly[None, :, 0]
    )
    sh = np.atleast_2d(shift)
    dv = d[None, :, 0] * sh[:, 1:2] - d[None, :, 1] * sh[:, 0:1]
    out = np.zeros(len(centres), dtype=bool)
    for k in ks:
        cr = base + k * dv
        out |= np.all(cr >= 0, axis=1) | np.all(cr <= 0, axis=1)
    return out


class _IdealToImage:
    """Ideal (undistorted) pixels -> distorted image pixels of one camera, the constants computed once.

    The model is :meth:`calib.formats.camera.CameraModel.distort_normalized` (OpenCV's: radial, rational,
    tangential, thin prism). :meth:`grid` evaluates it in float32 on a profile grid (error ~1e-4 px,
    below the 1/32 px resolution of ``cv2.remap``'s bilinear weights).
    """

    def __init__(self, camera: CameraModel) -> None:
        self.camera = camera
        self.Kinv = np.linalg.inv(camera.K)
        self.A = self.Kinv[:2, :2]
        self.b = self.Kinv[:2, 2]
        d = np.zeros(14)
        d[: camera.dist.size] = camera.dist
        self.d = d
        self.rational = bool(np.any(d[5:8] != 0))
        self.prism = bool(np.any(d[8:12] != 0))

    def points(self, uv: Array) -> Array:
        """Ideal pixels (N, 2) -> distorted pixels (N, 2), float64 (the camera's own arithmetic)."""
        xn = uv @ self.A.T + self.b
        if self.rational or self.prism:
            return self.camera.distort_normalized(xn)
        return self._distort64(xn)

    def points_of(self, uvs: list[Array]) -> Array:
        """:meth:`points` of several arrays of ideal pixels (each (N_i, 2)), concatenated: the same numbers (each
        array's normalized coordinates from its own matrix product, the distortion applied to all at once)."""
        if self.rational or self.prism:
            return np.concatenate([self.points(uv) for uv in uvs])
        return self._distort64(np.concatenate([uv @ self.A.T + self.b for uv in uvs]))

    def _distort64(self, xn: Array) -> Array:
        """Normalized coordinates (N, 2) -> distorted pixels (N, 2), float64 (radial k1 k2 k3 and tangential)."""
        k1, k2, p1, p2, k3 = self.d[:5]
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        K = self.camera.K
        out = np.empty_like(xn)
        out[:, 0] = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        out[:, 1] = K[1, 1] * yd + K[1, 2]
        return out

    def grid(self, centres: Array, n_dir: Array, offs: Array) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Distorted pixels (x, y maps, each (P, S), float32) of the ideal points ``centres[p] + offs[s] n_dir``."""
        f32 = np.float32
        xc = centres @ self.A.T + self.b
        nn = self.A @ n_dir
        o = offs.astype(f32)
        x = xc[:, 0:1].astype(f32) + o[None] * f32(nn[0])
        y = xc[:, 1:2].astype(f32) + o[None] * f32(nn[1])
        return self._distort_f32(x, y)

    def _distort_f32(
        self, x: NDArray[np.float32], y: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Normalized coordinates (float32 arrays) -> distorted pixels (x, y maps), float32."""
        f32 = np.float32
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (f32(v) for v in self.d[:12])
        xy = x * y
        x2 = x * x
        y2 = y * y
        r2 = x2 + y2
        tmp = np.empty_like(xy)  # the terms below computed in place: the same operations on the same numbers
        rad = k3 * r2
        rad += k2
        rad *= r2
        rad += k1
        rad *= r2
        rad += f32(1)
        if self.rational:
            # a rational model's denominator can vanish far outside the image (its pole; the calibration admits no
            # model with one inside it): grid points of a profile's band that reach it map to inf, beyond the image
            with np.errstate(divide="ignore", invalid="ignore"):
                rad /= f32(1) + r2 * (k4 + r2 * (k5 + r2 * k6))
        xd = x * rad
        xd += np.multiply(xy, f32(2) * p1, out=tmp)  # 2 p1 xy
        x2 *= f32(2)
        x2 += r2
        x2 *= p2
        xd += x2  # p2 (r2 + 2 x^2)
        yd = y * rad
        y2 *= f32(2)
        y2 += r2
        y2 *= p1
        yd += y2  # p1 (r2 + 2 y^2)
        yd += np.multiply(xy, f32(2) * p2, out=tmp)  # 2 p2 xy
        if self.prism:
            r4 = r2 * r2
            xd += s1 * r2 + s2 * r4
            yd += s3 * r2 + s4 * r4
        K = self.camera.K
        mx = xd * f32(K[0, 0])
        if K[0, 1] != 0:
            mx += f32(K[0, 1]) * yd
        mx += f32(K[0, 2])
        yd *= f32(K[1, 1])
        yd += f32(K[1, 2])
        return mx, yd


@dataclass
class _Neighbours:
    """Other rods' predicted axis segments in ideal pixels, ends ``a``, ``b`` (K, 2), and half-widths ``hw`` (K,)
    (px): what a rod's limb points must keep clear of."""

    a: Array
    b: Array
    hw: Array

    @classmethod
    def of(cls, neighbours: list[tuple[Array, Array, float]]) -> _Neighbours:
        """From (a, b, half-width) tuples (:func:`_silhouette`)."""
        return cls(
            np.array([nb[0] for nb in neighbours]).reshape(-1, 2),
            np.array([nb[1] for nb in neighbours]).reshape(-1, 2),
            np.array([nb[2] for nb in neighbours], dtype=np.float64),
        )

    def subset(self, keep: NDArray[np.bool_]) -> _Neighbours:
        """The neighbours where ``keep`` (K,)."""
        return _Neighbours(self.a[keep], self.b[keep], self.hw[keep])


def _near_segments(
    centres: Array,
    t_dir: Array,
    n_dir: Array,
    o_lo: float,
    o_hi: float,
    neighbours: _Neighbours,
    margin_px: float,
) -> _Neighbours:
    """The neighbours that may come closer than half-width + margin to the band.

    The band is the points ``centres[p] + o n_dir`` with o in [o_lo, o_hi]; a neighbour segment separated
    from it by more than that along t_dir or n_dir (a lower bound of the distance) cannot.
    """
    t = centres @ t_dir
    o = centres @ n_dir
    t_lo, t_hi = float(t.min()), float(t.max())
    o_lo, o_hi = float(o.min()) + o_lo, float(o.max()) + o_hi
    ends = np.stack([neighbours.a, neighbours.b], axis=1)  # (K, 2, 2)
    # each end's a @ t_dir and a @ n_dir, (K, 2): the two products and their sum
    te = ends[..., 0] * t_dir[0] + ends[..., 1] * t_dir[1]
    oe = ends[..., 0] * n_dir[0] + ends[..., 1] * n_dir[1]
    gap = np.maximum.reduce([te.min(1) - t_hi, t_lo - te.max(1), oe.min(1) - o_hi, o_lo - oe.max(1)])
    return neighbours.subset(gap <= neighbours.hw + margin_px)


@dataclass
class _Segment:
    """A predicted rod's visible axis segment in ideal pixels and its predicted limb offsets."""

    a: Array  #: start (ideal px), shape (2,)
    t_dir: Array  #: unit direction along the axis, shape (2,)
    n_dir: Array  #: unit normal, shape (2,)
    length: float  #: px
    off1: Array  #: limb 1 offset along n at the start and the end (px), shape (2,)
    off2: Array  #: limb 2 offset along n at the start and the end (px), shape (2,)
    #: its profiles' positions and centres (:func:`_visible_centres`) or why too few are, and their edge pairs
    #: (:func:`_limb_pairs`), when measured already with the rest of the frame's rods (:func:`_profile_frame`)
    vis: tuple[Array, Array] | str | None = None
    pairs: _LimbPairs | None = None

    def limb_offsets(self, frac: Array) -> tuple[Array, Array]:
        o1 = self.off1[0] + frac * (self.off1[1] - self.off1[0])
        o2 = self.off2[0] + frac * (self.off2[1] - self.off2[0])
        return o1, o2


def _predicted_segment(
    camera: CameraModel, pred: RodPrediction, radius: float, near_m: float, box: Array
) -> _Segment | str:
    """The predicted rod in ideal pixels, clipped to z >= near and to the image; a reason if none."""
    K = camera.K
    top, bot = pred.top.copy(), pred.bottom.copy()
    if top[2] < near_m and bot[2] < near_m:
        return "predicted behind the camera"
    if top[2] < near_m:
        top = top + (bot - top) * (near_m - top[2]) / (bot[2] - top[2])
    if bot[2] < near_m:
        bot = bot + (top - bot) * (near_m - bot[2]) / (top[2] - bot[2])
    try:
        h1p, h2p = limb_planes(top, bot - top, radius)
    except ValueError as exc:
        return str(exc)
    a2 = (K @ (top / top[2]))[:2]
    b2 = (K @ (bot / bot[2]))[:2]
    d2 = b2 - a2
    t0, t1 = 0.0, 1.0  # Liang-Barsky clip to the ideal-pixel bounding box of the image
    for p_, q_ in (
        (-d2[0], a2[0] - box[0]),
        (d2[0], box[2] - a2[0]),
        (-d2[1], a2[1] - box[1]),
        (d2[1], box[3] - a2[1]),
    ):
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
        return "rod predicted outside the image"
    a2, b2 = a2 + t0 * d2, a2 + t1 * d2
    length = norm3(b2 - a2)
    if length < 1e-6:
        return "predicted rod seen end-on"
    t_dir = (b2 - a2) / length
    n_dir = np.array([-t_dir[1], t_dir[0]])
    Kit = _inv_t(K)

    def limb_offset(h: Array, c: Array) -> float:
        lp = Kit @ h  # the limb line in ideal pixels
        lp = lp / norm3(lp[:2])
        den = lp[:2] @ n_dir
        return float(-(lp[:2] @ c + lp[2]) / den) if abs(den) > 1e-9 else np.nan

    off1 = np.array([limb_offset(h1p, a2), limb_offset(h1p, b2)])
    off2 = np.array([limb_offset(h2p, a2), limb_offset(h2p, b2)])
    if not (np.all(np.isfinite(off1)) and np.all(np.isfinite(off2))):
        return "degenerate predicted limb lines"
    return _Segment(a2, t_dir, n_dir, length, off1, off2)


def _inv_t(K: Array) -> Array:
    """``np.linalg.inv(K).T`` of a camera matrix (3, 3), computed once per matrix (in the same memory layout, which
    the products with it follow to the last bit)."""
    return _inv_t_of(K.tobytes()).copy(order="K")


@functools.lru_cache(maxsize=16)
def _inv_t_of(k: bytes) -> Array:
    return cast("Array", np.linalg.inv(np.frombuffer(k, dtype=np.float64).reshape(3, 3)).T)


def _pair_edges(
    pi: NDArray[np.int_], xo: Array, gs: Array, pc: Array, pw: Array, band_px: float, width_tol: float
) -> tuple[NDArray[np.int_], Array, Array, NDArray[np.int_]]:
    """Per profile, the pair of opposite-polarity edges that best matches the predicted rod (vectorised).

    Parameters
    ----------
    pi : ndarray of int, shape (E,)
        Profile index of each edge, sorted ascending.
    xo, gs : ndarray, shape (E,)
        Edge offset along the profile normal (px) and signed gradient.
    pc, pw : ndarray, shape (P,)
        Predicted rod centre offset and width (px) per profile.

    Returns
    -------
    k : ndarray of int, shape (M,)
        Profiles with a pair.
    x_lo, x_hi : ndarray, shape (M,)
        The pair's lower and upper offsets (px).
    polarity : ndarray of int, shape (M,)
        +1 when the edge at ``x_lo`` rises (a rod brighter than its surroundings), -1 otherwise.
    """
    near = np.abs(xo - pc[pi]) < pw[pi] / 2 + band_px
    pi, xo, gs = pi[near], xo[near], gs[near]
    if pi.size < 2:
        e = np.zeros(0, dtype=np.int_)
        return e, np.zeros(0), np.zeros(0), e
    counts = np.bincount(pi)
    cand_i: list[NDArray[np.int_]] = []
    cand_j: list[NDArray[np.int_]] = []
    for d in range(1, int(counts.max())):
        i = np.arange(pi.size - d)
        same = pi[i] == pi[i + d]
        cand_i.append(i[same])
        cand_j.append(i[same] + d)
    if not cand_i:
        e = np.zeros(0, dtype=np.int_)
        return e, np.zeros(0), np.zeros(0), e
    ii = np.concatenate(cand_i)
    jj = np.concatenate(cand_j)
    k = pi[ii]
    wdt = np.abs(xo[jj] - xo[ii])
    ok = (np.abs(wdt - pw[k]) < width_tol * pw[k]) & (gs[ii] * gs[jj] < 0)
    ii, jj, k, wdt = ii[ok], jj[ok], k[ok], wdt[ok]
    if ii.size == 0:
        e = np.zeros(0, dtype=np.int_)
        return e, np.zeros(0), np.zeros(0), e
    cen = 0.5 * (xo[ii] + xo[jj])
    # the width is predicted far better than the position (a placement error shifts the rod more
    # than it scales it): a pair of the wrong width (a limb and the edge of a specular streak, say)
    # is penalised hard even when its edges are stronger than the true limb's
    sw = 0.5 + 0.04 * pw[k]
    score = (
        np.minimum(np.abs(gs[ii]), np.abs(gs[jj]))
        * np.exp(-0.5 * ((wdt - pw[k]) / sw) ** 2)
        / (1.0 + (np.abs(cen - pc[k]) / 4.0) ** 2)
    )
    # best pair per profile: sort by (profile, -score) and take the first of each profile
    order = np.lexsort((-score, k))
    ko = k[order]
    first = np.ones(order.size, dtype=bool)
    first[1:] = ko[1:] != ko[:-1]
    best = order[first]
    i_b, j_b = ii[best], jj[best]
    lo_is_i = xo[i_b] < xo[j_b]
    x_lo = np.where(lo_is_i, xo[i_b], xo[j_b])
    x_hi = np.where(lo_is_i, xo[j_b], xo[i_b])
    g_lo = np.where(lo_is_i, gs[i_b], gs[j_b])
    return k[best], x_lo, x_hi, np.where(g_lo > 0, 1, -1)


def measure_rod(
    gray: np.ndarray,
    camera: CameraModel,
    pred: RodPrediction,
    radius: float,
    settings: RodSettings | None = None,
    occluders: list[Array] | None = None,
    rng: np.random.Generator | None = None,
    ideal_bbox: Array | None = None,
    neighbours: list[tuple[Array, Array, float]] | _Neighbours | None = None,
    segment: _Segment | str | None = None,
    projector: _IdealToImage | None = None,
    polarity: int | None = None,
) -> RodMeasurement:
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
    settings : RodSettings, optional
        Default: ``RodSettings()``.
    occluders : list of ndarray, shape (M, 2)
        Convex polygons in ideal pixels that hide the rod (e.g. the board); profiles inside are dropped.
    rng : numpy.random.Generator, optional
        Random sampling of the robust line fits; default seeded with 0.
    ideal_bbox : ndarray, shape (4,), optional
        :func:`image_ideal_bbox` of the camera (computed when not given).
    neighbours : list of (a, b, half_width_px)
        The other rods' predicted axis segments in ideal pixels (a, b shape (2,)) and half-widths:
        a limb point closer to one of them than its half-width plus ``settings.neighbour_px`` is
        dropped (its edge is merged with or hidden by the other rod's). Or the same as a :class:`_Neighbours`.
    segment : _Segment or str, optional
        The rod's predicted visible segment in ideal pixels, or the reason it has none, when already computed
        for the frame (:func:`measure_rods`); computed from ``pred`` when not given.
    projector : _IdealToImage, optional
        Ideal to image pixels of ``camera``, when already built for the frame; built when not given.
    polarity : {1, -1}, optional
        Keep only the edge pairs of this polarity (+1: a rod brighter than its surroundings); by default
        ``settings.polarity``, or when that is 0 the polarity of most of the rod's pairs.

    Returns
    -------
    RodMeasurement
        With ``u``, ``point``, quality figures and ``cov_u`` (3x3 covariance of u from the limb
        edges' residual scatter), or ``reason`` when the rod was not measured.
    """
    s = settings or RodSettings()
    rng = rng or np.random.default_rng(0)
    box = ideal_bbox if ideal_bbox is not None else image_ideal_bbox(camera)
    proj = projector if projector is not None else _IdealToImage(camera)
    job = _rod_job(gray, camera, pred, radius, s, occluders, box, neighbours, segment, proj, polarity)
    if isinstance(job, RodMeasurement):
        return job
    fits = _fit_limb_points(job.pts, s, rng)
    if isinstance(fits, str):
        job.out.reason = fits
        return job.out
    job.out.reason = _limb_quality(job.out, fits, s)
    if job.out.reason is not None:
        return job.out
    job.fits = fits
    _axes_from_limbs([job], camera, radius, s, proj)
    return job.out


@dataclass
class _RodJob:
    """One rod between the stages of its measurement (:func:`_rod_job`, the limb fits, :func:`_axes_from_limbs`):
    its measurement so far, prediction, visible profile centres (P, 2) and segment normal (2,) (ideal px), its two
    limbs' edge points (N_i, 2) (ideal px, neighbours' limb points dropped), and its limb fits once fitted."""

    out: RodMeasurement
    pred: RodPrediction
    centres: Array
    n_dir: Array
    pts: tuple[Array, Array]
    fits: _LimbFits | None = None


def _rod_job(
    gray: np.ndarray,
    camera: CameraModel,
    pred: RodPrediction,
    radius: float,
    s: RodSettings,
    occluders: list[Array] | None,
    box: Array,
    neighbours: _Neighbours | list[tuple[Array, Array, float]] | None,
    segment: _Segment | str | None,
    proj: _IdealToImage,
    polarity: int | None,
) -> _RodJob | RodMeasurement:
    """The stages of :func:`measure_rod` before the limb fits (its arguments): the rod's edge pairs, polarity and
    limb points; or the measurement with the reason why the rod has none."""
    out = RodMeasurement(pred.leg, pred.rod)
    seg = segment if segment is not None else _predicted_segment(camera, pred, radius, s.near_m, box)
    if isinstance(seg, str):
        out.reason = seg
        return out
    vis = seg.vis if seg.vis is not None else _visible_centres(camera, seg, s, box, proj, occluders)
    if isinstance(vis, str):
        out.reason = vis
        return out
    pairs = seg.pairs if seg.pairs is not None else _limb_pairs(gray, camera, seg, s, proj, *vis)
    if isinstance(neighbours, list):
        neighbours = _Neighbours.of(neighbours)
    if neighbours is not None and len(neighbours.hw):
        neighbours = _near_segments(
            vis[1],
            seg.t_dir,
            seg.n_dir,
            float(min(pairs.o1.min(), pairs.o2.min())),
            float(max(pairs.o1.max(), pairs.o2.max())),
            neighbours,
            s.neighbour_px,
        )
    # one polarity per rod (brighter or darker than its surroundings): pairs of the other polarity
    # are gaps between two bright things (e.g. the two rods of a leg), dropped
    out.pairs_by_polarity = (int(np.count_nonzero(pairs.pol > 0)), int(np.count_nonzero(pairs.pol < 0)))
    if polarity is None and s.polarity:
        polarity = 1 if s.polarity > 0 else -1
    out.polarity = polarity if polarity is not None else (1 if pairs.pol.sum() >= 0 else -1)
    pts = _limb_points(pairs, out.polarity, vis[1], seg.n_dir, s, neighbours)
    return _RodJob(out, pred, vis[1], seg.n_dir, pts)


@dataclass
class _LimbPairs:
    """The edge pairs found across a rod's profiles: profile index (N,), the pair's lower and higher edge (N,)
    and its polarity (N,) (+1: brighter inside), and the predicted limb offsets o1, o2 (P,) of every profile
    (ideal px along the segment's normal)."""

    k: NDArray[np.intp]
    x_lo: Array
    x_hi: Array
    pol: NDArray[np.intp]
    o1: Array
    o2: Array


@dataclass
class _LimbFits:
    """The two limb lines of a rod (ideal px, ``a x + b y + c = 0``), their fits' (centre, direction, variance,
    inlier points) for the covariance, residual RMS (px) and inlier counts."""

    lines: list[Array]
    fits: list[tuple[Array, Array, float, Array]]
    rms: list[float]
    npts: list[int]
    #: per limb, its inlier points' positions along the line about their centroid (px), when known
    ts: list[Array] = field(default_factory=list)


def _visible_centres(
    camera: CameraModel,
    seg: _Segment,
    s: RodSettings,
    box: Array,
    proj: _IdealToImage,
    occluders: list[Array] | None,
) -> tuple[Array, Array] | str:
    """The profiles' positions along the segment (P,) and centres (P, 2) (ideal px) inside the image and outside the
    occluders, or why too few are."""
    ts, centres = _profile_positions(seg, s)
    inside = _visible(camera, centres, (_clearance(seg) * seg.n_dir)[None], s, box, proj, occluders)
    return _visible_or_why(seg, s, ts, centres, inside)


def _profile_positions(seg: _Segment, s: RodSettings) -> tuple[Array, Array]:
    """The profiles' positions along the segment (P,) and their centres (P, 2) (ideal px), visible or not."""
    ts = np.arange(0.0, seg.length, s.step_px)
    if ts.size > 1500:
        ts = np.linspace(0.0, seg.length, 1500)
    return ts, seg.a[None] + ts[:, None] * seg.t_dir[None]


def _clearance(seg: _Segment) -> float:
    """How far (px) from a profile's centre an occluder hides it: the rod's half width plus the clearance."""
    return 0.5 * float(np.max(np.abs(seg.off1 - seg.off2))) + ROD_OCCLUDER_CLEARANCE_PX


def _visible(
    camera: CameraModel,
    centres: Array,
    shift: Array,
    s: RodSettings,
    box: Array,
    proj: _IdealToImage,
    occluders: list[Array] | None,
) -> NDArray[np.bool_]:
    """Which profile centres (N, 2) (ideal px) are inside the image and whose span (``centre +- shift``, shift (1, 2)
    or (N, 2), ideal px) is outside the occluders, shape (N,)."""
    # keep centres inside the image (after distortion; the ideal-pixel box guards against the
    # distortion polynomial's fold-back far outside the field of view) and outside occluders
    dpx = proj.points(centres)
    inside = (
        (dpx[:, 0] >= s.border_px)
        & (dpx[:, 0] <= camera.width - 1 - s.border_px)
        & (dpx[:, 1] >= s.border_px)
        & (dpx[:, 1] <= camera.height - 1 - s.border_px)
        & (centres[:, 0] >= box[0])
        & (centres[:, 0] <= box[2])
        & (centres[:, 1] >= box[1])
        & (centres[:, 1] <= box[3])
    )
    for poly in occluders or []:
        # a profile is hidden when any part of its span is inside the polygon
        inside &= ~_hidden(centres, shift, (-1.0, 0.0, 1.0), poly)
    return inside


def _visible_or_why(
    seg: _Segment, s: RodSettings, ts: Array, centres: Array, inside: NDArray[np.bool_]
) -> tuple[Array, Array] | str:
    """The visible profiles' positions (P,) and centres (P, 2), or why too few are."""
    n_in = int(np.count_nonzero(inside))
    if n_in * s.step_px < s.min_length_px:
        return (
            f"not enough of the rod visible ({n_in * s.step_px:.0f} px of {seg.length:.0f} px predicted; "
            "outside the image or hidden by the board)"
        )
    return ts[inside], centres[inside]


def _limb_pairs(
    gray: np.ndarray,
    camera: CameraModel,
    seg: _Segment,
    s: RodSettings,
    proj: _IdealToImage,
    ts: Array,
    centres: Array,
) -> _LimbPairs:
    """Profiles across the predicted limbs at ``centres`` (P, 2), their sub-pixel edges and the best edge pair of
    each profile."""
    pr = _gradient_profiles(gray, camera, seg, s, proj, ts, centres)
    pi, pos, sg = _edges_1d(pr.g, s.min_contrast, pr.side, pr.inside, pr.radius)  # pi ascending (row-major scan)
    k, x_lo, x_hi, pol = _pair_edges(
        pi, pr.lo + pos * s.sample_px, sg, 0.5 * (pr.o1 + pr.o2), np.abs(pr.o2 - pr.o1), s.band_px, s.width_tolerance
    )
    return _LimbPairs(k, x_lo, x_hi, pol, pr.o1, pr.o2)


@dataclass
class _Profiles:
    """A rod's gradient profiles across its predicted limbs (:func:`_gradient_profiles`): the gradient (P, S) (grey
    levels per px, float32), which samples are inside the image (P, S; None: all of them), the first sample's offset
    (ideal px along the segment's normal), the predicted limb offsets o1, o2 (P,) (ideal px), and the edge search's
    slope and kernel half-widths (samples)."""

    g: NDArray[np.float32]
    inside: NDArray[np.bool_] | None
    lo: float
    o1: Array
    o2: Array
    side: int
    radius: int


def _gradient_profiles(
    gray: np.ndarray, camera: CameraModel, seg: _Segment, s: RodSettings, proj: _IdealToImage, ts: Array, centres: Array
) -> _Profiles:
    """The profiles across the predicted limbs at the positions ``ts`` (P,) along the segment (centres (P, 2), ideal
    px), differentiated."""
    n_dir = seg.n_dir
    o1, o2 = seg.limb_offsets(ts / seg.length)
    lo = np.minimum(o1, o2).min() - s.band_px
    hi = np.maximum(o1, o2).max() + s.band_px
    ds = s.sample_px
    offs = np.arange(lo, hi + 1e-9, ds)
    mx, my = proj.grid(centres, n_dir, offs)  # (P, S) distorted px of centres[p] + offs[s] n_dir
    img = gray if gray.dtype == np.float32 else gray.astype(np.float32)
    prof = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ker = _gauss_deriv_kernel(s.sigma_px / ds)
    # ddepth CV_32F: the filtered profiles are float32 (OpenCV's stubs type the result as any Mat)
    g = cast(
        "NDArray[np.float32]",
        cv2.filter2D(prof, cv2.CV_32F, ker[None, ::-1].astype(np.float32), borderType=cv2.BORDER_REPLICATE),
    )
    g *= np.float32(1.0 / ds)  # grey levels per pixel
    inside_img = None  # every sample inside the image
    if not (mx.min() >= 0 and mx.max() <= camera.width - 1 and my.min() >= 0 and my.max() <= camera.height - 1):
        inside_img = (mx >= 0) & (mx <= camera.width - 1) & (my >= 0) & (my <= camera.height - 1)
    return _Profiles(g, inside_img, float(lo), o1, o2, max(2, round(3.0 / ds)), len(ker) // 2)


def _profile_frame(
    gray: np.ndarray,
    camera: CameraModel,
    segs: list[_Segment | str],
    s: RodSettings,
    box: Array,
    proj: _IdealToImage,
    occluders: list[Array] | None,
) -> None:
    """:func:`_visible_centres` and :func:`_limb_pairs` of every rod of a frame set on its segment (``vis``,
    ``pairs``), the same numbers computed for all rods at once where that pays (:func:`_frame_pairs`)."""
    rods = [g for g in segs if not isinstance(g, str)]
    if not rods:
        return
    pos = [_profile_positions(g, s) for g in rods]
    centres = np.concatenate([c for _, c in pos])
    counts = np.array([len(t) for t, _ in pos])
    shift = np.repeat(np.array([_clearance(g) * g.n_dir for g in rods]), counts, axis=0)
    inside = np.split(_visible(camera, centres, shift, s, box, proj, occluders), np.cumsum(counts)[:-1])
    seen: list[tuple[_Segment, Array, Array]] = []
    for g, (ts, c), ins in zip(rods, pos, inside, strict=True):
        g.vis = _visible_or_why(g, s, ts, c, ins)
        if not isinstance(g.vis, str):
            seen.append((g, *g.vis))
    if seen:
        for g, pairs in zip((x[0] for x in seen), _frame_pairs(gray, camera, seen, s, proj), strict=True):
            g.pairs = pairs


def _frame_pairs(
    gray: np.ndarray,
    camera: CameraModel,
    seen: list[tuple[_Segment, Array, Array]],
    s: RodSettings,
    proj: _IdealToImage,
) -> list[_LimbPairs]:
    """:func:`_limb_pairs` of several rods (segment, visible profiles' positions (P,) and centres (P, 2)) at once,
    the same numbers: each rod's profiles sampled, filtered and searched for peaks on their own (small arrays, in
    cache), the peaks' sub-pixel positions and the edge pairs of all rods together."""
    prs, pks = [], []
    for g, ts, c in seen:
        pr = _gradient_profiles(gray, camera, g, s, proj, ts, c)
        prs.append(pr)
        pks.append(_peaks(pr.g, s.min_contrast, pr.side, pr.inside, pr.radius))
    counts = np.array([len(pr.o1) for pr in prs])
    rows = np.concatenate([[0], np.cumsum(counts)])
    pi = np.concatenate([pk.pi + rows[r] for r, pk in enumerate(pks)])
    si = np.concatenate([pk.si for pk in pks])
    x0, corr, sg = _subpixel(si, np.concatenate([pk.win for pk in pks]), prs[0].side)
    if any(pk.drop is not None for pk in pks):  # (see _kept)
        drop = np.concatenate([np.zeros(len(pk.si), dtype=bool) if pk.drop is None else pk.drop for pk in pks])
        flat = np.concatenate([np.zeros(len(pk.si), dtype=bool) if pk.flat is None else pk.flat for pk in pks])
        keep = ~drop
        pi, x0, corr, sg = pi[keep], x0[keep], np.where(flat, 0.0, corr)[keep], sg[keep]
    pos = x0 - corr
    lo = np.repeat(np.array([pr.lo for pr in prs]), counts)
    pc = np.concatenate([0.5 * (pr.o1 + pr.o2) for pr in prs])
    pw = np.concatenate([np.abs(pr.o2 - pr.o1) for pr in prs])
    k, x_lo, x_hi, pol = _pair_edges(pi, lo[pi] + pos * s.sample_px, sg, pc, pw, s.band_px, s.width_tolerance)
    cut = np.searchsorted(k, rows)
    return [
        _LimbPairs(
            k[cut[r] : cut[r + 1]] - rows[r],
            x_lo[cut[r] : cut[r + 1]],
            x_hi[cut[r] : cut[r + 1]],
            pol[cut[r] : cut[r + 1]],
            pr.o1,
            pr.o2,
        )
        for r, pr in enumerate(prs)
    ]


def _limb_points(
    pairs: _LimbPairs,
    polarity: int,
    centres: Array,
    n_dir: Array,
    s: RodSettings,
    neighbours: _Neighbours | list[tuple[Array, Array, float]] | None,
) -> tuple[Array, Array]:
    """The two limbs' edge points (N_i, 2) (ideal px) of the pairs of this polarity, points near a neighbour
    dropped."""
    k, x_lo, x_hi, pol, o1, o2 = pairs.k, pairs.x_lo, pairs.x_hi, pairs.pol, pairs.o1, pairs.o2
    if k.size:
        keep = pol == polarity
        k, x_lo, x_hi = k[keep], x_lo[keep], x_hi[keep]
    one_low = o1[k] < o2[k]
    edges = (np.where(one_low, x_lo, x_hi), np.where(one_low, x_hi, x_lo))
    pred_off = (o1[k], o2[k])
    ck = centres[k]
    pts = [ck + x_e[:, None] * n_dir[None] for x_e in edges]
    if isinstance(neighbours, list):
        neighbours = _Neighbours.of(neighbours)
    if neighbours is None or not len(neighbours.hw):
        return pts[0], pts[1]
    # drop limb points whose edge may merge with another rod's silhouette (both limbs' predicted points at once)
    limb_pred = np.concatenate([ck + x_p[:, None] * n_dir[None] for x_p in pred_off])
    clear = _clear_of(limb_pred, neighbours, s.neighbour_px)
    return pts[0][clear[: len(ck)]], pts[1][clear[len(ck) :]]


def _clear_of(pts: Array, neighbours: _Neighbours, margin_px: float) -> NDArray[np.bool_]:
    """Which points (N, 2) (ideal px) are farther than each neighbour's half-width plus ``margin_px`` from its
    segment (each point's distance to the segment's nearest point), all neighbours at once, shape (N,)."""
    a = neighbours.a
    d = neighbours.b - a
    L2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]  # d @ d
    rel = pts[None] - a[:, None]  # (K, N, 2)
    t = np.matmul(rel, d[:, :, None])[..., 0] / np.where(L2 > 0, L2, 1.0)[:, None]
    t = np.where((L2 > 0)[:, None], np.clip(t, 0.0, 1.0), 0.0)
    dist = np.linalg.norm(pts[None] - (a[:, None] + t[..., None] * d[:, None]), axis=2)
    return np.all(dist > (neighbours.hw + margin_px)[:, None], axis=0)


def _too_few(n: int, s: RodSettings) -> str:
    """Why a limb of ``n`` edge points is not fitted."""
    return (
        f"too few limb edge points ({n} < {s.min_points}): rod not found in its search band, or too close to "
        "another rod"
    )


def _fit_limb_points(pts2: tuple[Array, Array], s: RodSettings, rng: np.random.Generator) -> _LimbFits | str:
    """The two limb lines fitted (RANSAC, then refined: :func:`refine_lines`) to the limbs' edge points (N_i, 2)
    (ideal px), in turn; or why not (the second limb not fitted when the first is not)."""
    found = []
    for pts in pts2:
        if len(pts) < s.min_points:
            return _too_few(len(pts), s)
        start = ransac_start(pts, rng, s.ransac_iters, s.inlier_px)
        line, inl = refine_lines([pts], [start], s.inlier_px)[0]
        reason = _limb_fit_failed(pts, line, inl, s)
        if reason is not None:
            return reason
        found.append((pts[inl], line))
    return _limb_fits([found])[0]


def _fit_limbs_frame(pts: list[tuple[Array, Array]], s: RodSettings, rng: np.random.Generator) -> list[_LimbFits | str]:
    """The two limb lines of each rod of a frame (each rod's two limbs' edge points (N_i, 2), ideal px; ``rng`` the
    frame's generator), or why not: :func:`_fit_limb_points` of the rods in turn, with the same draws from ``rng``,
    each limb's RANSAC start then refined with the others' (:func:`refine_lines`).

    The starts are drawn in measurement order as if every first limb's fit succeeded; a rod whose first limb then
    fails has drawn for its second limb, which the rod-by-rod fits do not: the generator is then put back and the
    rods fitted in turn (rare: a first limb with enough points whose fit keeps too few of them).
    """
    state = rng.bit_generator.state
    sets: list[Array] = []
    starts = []
    for p2 in pts:
        for limb in p2 if len(p2[0]) >= s.min_points else ():
            if len(limb) >= s.min_points:
                sets.append(limb)
                starts.append(ransac_start(limb, rng, s.ransac_iters, s.inlier_px))
    refined = iter(refine_lines(sets, starts, s.inlier_px))
    out: list[list[tuple[Array, Array]] | str] = []
    for p2 in pts:
        res: list[tuple[Array, Array]] | str = []
        for j, limb in enumerate(p2):
            if len(limb) < s.min_points:
                res = _too_few(len(limb), s)
                break
            line, inl = next(refined)
            reason = _limb_fit_failed(limb, line, inl, s)
            if reason is not None:
                if j == 0 and len(p2[1]) >= s.min_points:  # its second limb drew: fitted rod by rod
                    rng.bit_generator.state = state
                    return [_fit_limb_points(x, s, rng) for x in pts]
                res = reason
                break
            cast("list", res).append((limb[inl], line))
        out.append(res)
    fitted = iter(_limb_fits([x for x in out if not isinstance(x, str)]))
    return [x if isinstance(x, str) else next(fitted) for x in out]


def _limb_fit_failed(pts: Array, line: Array, inl: NDArray[np.bool_], s: RodSettings) -> str | None:
    """Why the limb line ``line`` (3,) fitted to ``pts`` (N, 2) with inliers ``inl`` (N,) is not kept, or None."""
    n_in = int(np.count_nonzero(inl))
    if not np.all(np.isfinite(line)) or n_in < s.min_points:
        return f"limb line fit failed ({n_in} inliers of {len(pts)})"
    return None


def _limb_fits(rods: list[list[tuple[Array, Array]]]) -> list[_LimbFits]:
    """Each rod's two limb lines (their inlier points (N, 2), ideal px, and line (3,)) with their statistics
    (:func:`_line_stats`, residual RMS)."""
    out = []
    for rod in rods:
        fits = _LimbFits([], [], [], [])
        for p_in, line in rod:
            r = p_in @ line[:2] + line[2]
            c, td, s2, t = _line_stats(p_in, line, r)  # (_line_cov)
            fits.lines.append(line)
            fits.fits.append((c, td, s2, p_in))
            fits.ts.append(t)
            fits.rms.append(float(np.sqrt(np.add.reduce(r * r) / len(p_in))))  # RMS of r (np.mean's numbers)
            fits.npts.append(len(p_in))
        out.append(fits)
    return out


def _limb_quality(out: RodMeasurement, fits: _LimbFits, s: RodSettings) -> str | None:
    """The limb lines and their quality figures set on ``out``; why the rod is rejected (its limb edges scattered
    beyond ``s.max_rms_px``), else None."""
    out.lines_px = fits.lines
    out.rms_px = (fits.rms[0], fits.rms[1])
    out.n_points = (fits.npts[0], fits.npts[1])
    if max(fits.rms) > s.max_rms_px:
        return f"limb edges too scattered (residual RMS {max(fits.rms):.2f} px > {s.max_rms_px} px)"
    return None


def _axes_from_limbs(
    jobs: list[_RodJob], camera: CameraModel, radius: float, s: RodSettings, proj: _IdealToImage, edges: bool = True
) -> None:
    """The axes of M rods with limb fits, from their two limb lines (interpretation planes), set on each job's
    measurement with their covariances and limb samples, and (``edges``) their raw edges (``edges_px``,
    ``middle_px``); or why not (the measurement then keeps only the planes' angle). Each rod's products are those of
    one rod alone, stacked: the same numbers bit for bit whatever M.

    Parameters
    ----------
    jobs : list of _RodJob
        M rods whose limb fits passed :func:`_limb_quality` (``fits`` set).
    camera : CameraModel
        The camera (its K, px).
    radius : float
        Rod radius (m).
    s : RodSettings
        The settings (minimum plane angle, edge-bias allowance).
    proj : _IdealToImage
        Ideal to image pixels of ``camera``.
    edges : bool
        Set ``edges_px`` and ``middle_px`` from the jobs' edge points (a re-expression keeps the measured ones).
    """
    if not jobs:
        return
    fits = [cast("_LimbFits", j.fits) for j in jobs]
    inner, hs, ang = _planes_stack(camera, proj, fits, jobs)
    axes = []
    for r, j in enumerate(jobs):
        j.out.plane_angle_rad = float(ang[r])
        if ang[r] < s.min_plane_angle_rad:
            j.out.reason = f"interpretation planes nearly parallel ({ang[r] * 1e3:.2f} mrad): axis ill-defined"
        else:
            axes.append(r)
    if not axes:
        return
    sel = np.array(axes)
    u, X, parallel = _axes_stack(hs[sel], radius, np.array([jobs[r].pred.u for r in axes]))
    X = axis_point_seen_along(X, u, inner[sel])
    done = [r for r, bad in zip(axes, parallel, strict=True) if not bad]
    for r, bad in zip(axes, parallel, strict=True):
        if bad:
            jobs[r].out.reason = "interpretation planes are parallel: no axis"
    if not done:
        return
    keep = np.array([k for k, bad in enumerate(parallel) if not bad])
    done_fits = [fits[r] for r in done]
    # the allowance whole (cov_u) and averaged along the limb (cov_u_own), the planes' derivatives computed once
    cov, cov_own = _direction_covariance_sets(
        camera.K,
        [f.fits for f in done_fits],
        inner[sel[keep]],
        s.edge_bias_px,
        (0.0, s.edge_bias_length_px),
        [f.ts for f in done_fits],
    )
    samples = _limb_samples_stack(done_fits, proj)
    raw = _edges_stack([jobs[r] for r in done], proj) if edges else None
    for k, r in enumerate(done):
        out = jobs[r].out
        out.h = (hs[r, 0], hs[r, 1])
        out.u = u[keep[k]]
        out.point = X[keep[k]]
        out.cov_u, out.cov_u_own = cov[k], cov_own[k]
        out.limbs_px = samples[k]
        if raw is not None:  # the raw measurement, for another camera (calib.vision.rods.reexpress)
            out.edges_px, out.middle_px = raw[k]


def _planes_stack(
    camera: CameraModel, proj: _IdealToImage, fits: list[_LimbFits], jobs: list[_RodJob]
) -> tuple[Array, Array, Array]:
    """The interpretation planes of M rods' limb lines (h = K^T l, signed so that a point between the two limbs, near
    the middle of the visible part, is on their positive side): that direction between them (M, 3), their unit
    normals (M, 2, 3) and the angle between them (M,) (rad)."""
    K = camera.K
    lines = np.array([f.lines for f in fits]).reshape(len(fits), 2, 3)
    n_dir = np.array([j.n_dir for j in jobs])
    cmid = np.array([j.centres[len(j.centres) // 2] for j in jobs])
    ab = lines[:, :, :2]
    den = np.matmul(ab[:, :, None, :], n_dir[:, None, :, None])[:, :, 0, 0]  # line[:2] @ n_dir, (M, 2)
    num = np.matmul(ab[:, :, None, :], cmid[:, None, :, None])[:, :, 0, 0] + lines[:, :, 2]
    big = np.abs(den) > 1e-9
    xs = np.where(big, -num / np.where(big, den, 1.0), 0.0)
    mid = np.ones((len(fits), 3))
    mid[:, :2] = cmid + (0.5 * (xs[:, 0] + xs[:, 1]))[:, None] * n_dir
    inner = np.matmul(proj.Kinv, mid[:, :, None])[:, :, 0]
    h = np.matmul(K.T, lines[..., None])[..., 0]  # (M, 2, 3)
    h = h / np.sqrt(np.matmul(h[..., None, :], h[..., None])[..., 0])  # np.linalg.norm's numbers
    side = np.matmul(h, inner[:, :, None])[..., 0]  # (M, 2)
    h = np.where((side > 0)[..., None], h, -h)
    cos = np.matmul(h[:, 0, None, :], h[:, 1, :, None])[:, 0, 0]
    return inner, h, np.arccos(np.clip(np.abs(cos), -1.0, 1.0))


def _axes_stack(hs: Array, radius: float, pred_u: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
    """:func:`axis_from_planes` of M rods' plane normals (M, 2, 3) with the radius (m), each direction signed along
    its prediction's ``pred_u`` (M, 3): unit directions (M, 3), axis points (M, 3) (m) and which rods' planes are
    parallel (M,) (their direction and point then meaningless); the same numbers bit for bit."""

    def unit(v: Array) -> tuple[Array, Array]:
        n = np.sqrt(np.matmul(v[:, None, :], v[:, :, None])[:, 0])  # norm3's numbers, (M, 1)
        return v / n, n[:, 0]

    a, _ = unit(hs[:, 0])
    b, _ = unit(hs[:, 1])
    u, n = unit(cross(a, b))
    parallel = n < 1e-12
    mats = np.stack([a, b, u], axis=1)
    mats[parallel] = np.eye(3)
    X = np.linalg.solve(mats, np.broadcast_to(np.array([radius, radius, 0.0])[:, None], (len(hs), 3, 1)))[..., 0]
    flip = np.matmul(u[:, None, :], pred_u[:, :, None])[:, 0, 0] < 0
    return np.where(flip[:, None], -u, u), X, parallel


def _limb_samples_stack(fits: list[_LimbFits], proj: _IdealToImage) -> Array:
    """:func:`_limb_samples` of M rods (M, 2, 5, 2) (distorted px), the same numbers: the bins' sums of all limbs in
    one reduction (each bin's points added in order, as the per-limb sums add them)."""
    limbs = [(fit, f.ts[i] if f.ts else None) for f in fits for i, fit in enumerate(f.fits)]
    if any(len(fit[3]) < 5 for fit, _ in limbs):  # (never with RodSettings.min_points >= 5)
        bins = [b for f in fits for b in _limb_bins(f.fits, f.ts or None)]
        return proj.points_of(bins).reshape(len(fits), 2, 5, 2)
    srt: list[Array] = []
    starts: list[int] = []
    sizes: list[int] = []
    off = 0
    for (c, td, _s2, pts), t in limbs:
        srt.append(pts[np.argsort((pts - c) @ td if t is None else t, kind="stable")])
        q, extra = divmod(len(pts), 5)  # np.array_split's bins: the first ``extra`` one longer
        size = [q + 1] * extra + [q] * (5 - extra)
        starts += [off + sum(size[:k]) for k in range(5)]
        sizes += size
        off += len(pts)
    # the bins side by side, one per column (zeros below a bin's points): summed row by row, as each bin alone is
    n_bin = np.array(sizes)
    rows = np.arange(int(n_bin.max()))[:, None]
    pts = np.concatenate([*srt, np.zeros((1, 2))])
    idx = np.where(rows < n_bin, np.array(starts) + rows, len(pts) - 1)
    sums = np.add.reduce(pts[idx].reshape(len(rows), -1), axis=0).reshape(-1, 2)
    means = sums / n_bin.astype(np.float64)[:, None]
    return proj.points_of(list(means.reshape(-1, 5, 2))).reshape(len(fits), 2, 5, 2)


def _edges_stack(jobs: list[_RodJob], proj: _IdealToImage) -> list[tuple[tuple[Array, Array], Array]]:
    """Each rod's two limbs' inlier edge points and the middle of its visible part, distorted px (the raw
    measurement, :attr:`RodMeasurement.edges_px` and ``middle_px``), the same numbers as :meth:`_IdealToImage.points`
    of each."""
    parts: list[Array] = []
    for j in jobs:
        f = cast("_LimbFits", j.fits)
        parts += [f.fits[0][3], f.fits[1][3], j.centres[len(j.centres) // 2][None]]
    cut = np.cumsum([len(p) for p in parts])[:-1]
    px = np.split(proj.points_of(parts), cut)
    return [((px[3 * r], px[3 * r + 1]), px[3 * r + 2][0]) for r in range(len(jobs))]


def _limb_samples(
    camera: CameraModel,
    fits: list[tuple[Array, Array, float, Array]],
    projector: _IdealToImage | None = None,
    ts: list[Array] | None = None,
) -> Array:
    """Five points per limb, distorted pixels (2, 5, 2): the means of its edge points in five bins of equal count
    along it, taken in ideal pixels (where the limb is straight, so that a mean lies on it) and then to the image.

    They follow the edge points, not the line this camera fitted: a method that redoes the limb's plane through
    other intrinsics (:func:`calib.identify.intrinsics.limb_planes_for`) then gets the line those intrinsics would
    have fitted to the edge points, to first order. Points of the fitted line carried the extraction camera's
    distortion: undistorted by other intrinsics they bend by the two distortions' difference over the whole limb,
    which tilts a rod's recomputed direction in depth the same way on every rod in that part of the image.
    """
    proj = projector if projector is not None else _IdealToImage(camera)
    bins = _limb_bins(fits, ts)
    return proj.points_of(bins).reshape(len(fits), 5, 2) if bins else np.empty((0, 5, 2))


def _limb_bins(fits: list[tuple[Array, Array, float, Array]], ts: list[Array] | None) -> list[Array]:
    """:func:`_limb_samples` in ideal pixels: per limb, the means of its edge points in five bins (5, 2)."""
    bins = []
    for i, (c, td, _s2, pts) in enumerate(fits):
        if len(pts) >= 5:
            # (ts: each fit's (pts - c) @ td when known)
            order = np.argsort((pts - c) @ td if ts is None else ts[i], kind="stable")
            srt = pts[order]
            q, extra = divmod(len(pts), 5)  # np.array_split's bins: the first ``extra`` one longer
            ends = np.cumsum([0] + [q + 1] * extra + [q] * (5 - extra))
            means = np.array([np.add.reduce(srt[a:b], axis=0) / (b - a) for a, b in itertools.pairwise(ends)])
        else:  # fewer points than bins (never with RodSettings.min_points >= 5): points of the fitted line
            means = c[None] + _quantiles5(np.sort((pts - c) @ td))[:, None] * td[None]
        bins.append(means)
    return bins


def _quantiles5(x: Array) -> Array:
    """``np.quantile(x, [0, 1/4, 1/2, 3/4, 1])`` (linear) of a sorted non-empty 1-D array, without its overhead."""
    v = np.array([0.0, 0.25, 0.5, 0.75, 1.0]) * (x.size - 1)
    i0 = np.floor(v).astype(int)
    i1 = np.minimum(i0 + 1, x.size - 1)
    gam = v - i0
    a, b = x[i0], x[i1]
    diff = b - a
    return np.where(gam >= 0.5, b - diff * (1 - gam), a + diff * gam)


def image_ideal_bbox(camera: CameraModel, margin_px: float = 2.0) -> Array:
    """Bounding box (xmin, ymin, xmax, ymax) in ideal pixels of the whole image, with a margin.

    Parameters
    ----------
    camera : CameraModel
        The camera whose image is bounded.
    margin_px : float
        Margin added on every side (ideal px).

    Returns
    -------
    ndarray, shape (4,)
        ``(xmin, ymin, xmax, ymax)`` (ideal px).
    """
    b = camera.to_ideal_pixels(camera.normalized_bounds())
    return np.array(
        [b[:, 0].min() - margin_px, b[:, 1].min() - margin_px, b[:, 0].max() + margin_px, b[:, 1].max() + margin_px]
    )


def measure_rods(
    gray: np.ndarray,
    camera: CameraModel,
    preds: list[RodPrediction],
    radius: float,
    settings: RodSettings | None = None,
    occluders: list[Array] | None = None,
    seed: int = 0,
    ideal_bbox: Array | None = None,
) -> list[RodMeasurement]:
    """Measure every predicted rod of a frame (see :func:`measure_rod`).

    Each rod's limb points near another rod's predicted silhouette are dropped. The rods are measured with
    one polarity, that of most of the frame's edge pairs (:func:`_frame_polarity`). When the two rods of a
    leg latch onto the same physical rod (a prediction off by about the rods' image spacing; their
    measured axes then nearly coincide), or one of them onto the gap between them (measured with the other
    polarity), the rod measured nearer its prediction (resp. with the frame's polarity) is kept and the
    other is measured again, predicted from it shifted by the rods' spacing. A rod left with the other
    polarity than the frame's is dropped (reason given): a rod against a background of the other
    brightness than the rest of the frame's is lost, never a gap measured as a rod.

    Parameters
    ----------
    gray : ndarray, shape (H, W), float32 or uint8
        The (distorted) image, single channel.
    camera : CameraModel
        The camera that took it.
    preds : list of RodPrediction
        Predicted axis segments (camera frame, metres), one per rod.
    radius : float
        Rod radius (metres).
    settings : RodSettings, optional
        Default: ``RodSettings()``.
    occluders : list of ndarray, shape (M, 2), optional
        Convex polygons in ideal pixels that hide the rods (e.g. the board); profiles inside are dropped.
    seed : int
        Seed of the robust line fits' random sampling.
    ideal_bbox : ndarray, shape (4,), optional
        :func:`image_ideal_bbox` of the camera (ideal px; computed when not given).

    Returns
    -------
    list of RodMeasurement
        One per prediction, in the order of ``preds``.
    """
    s = settings or RodSettings()
    img = gray.astype(np.float32) if gray.dtype != np.float32 else gray
    box = ideal_bbox if ideal_bbox is not None else image_ideal_bbox(camera)
    segs = [_predicted_segment(camera, p, radius, s.near_m, box) for p in preds]
    proj = _IdealToImage(camera)
    _profile_frame(img, camera, segs, s, box, proj, occluders)
    fr = _FrameRods(
        img,
        camera,
        list(preds),
        radius,
        s,
        occluders,
        np.random.default_rng(seed),
        box,
        proj,
        segs,
        [None if isinstance(g, str) else _silhouette(g) for g in segs],
    )
    out = _measure_frame(fr)
    index = {(p.leg, p.rod): i for i, p in enumerate(preds)}
    # one polarity per frame (the rods share their material; see _frame_polarity): a rod measured with the
    # other one is measured again with the frame's
    frame_pol = _frame_polarity(out, s.polarity)
    _remeasure_with_polarity(fr, out, frame_pol)
    for leg in range(4):
        i0, i1 = index.get((leg, 0)), index.get((leg, 1))
        if i0 is not None and i1 is not None and out[i0].ok and out[i1].ok:
            _separate_leg(fr, out, i0, i1, frame_pol)
    # still of the other polarity, its leg's other rod not measured: most likely the gap, the other rod's limb
    # hidden by this rod's prediction. Both rods measured again, predicted on either side of the gap.
    for leg in range(4):
        i0, i1 = index.get((leg, 0)), index.get((leg, 1))
        if frame_pol != 0 and i0 is not None and i1 is not None:
            _straddle_gap(fr, out, leg, i0, i1, frame_pol)
    # still of the other polarity: a wrong rod costs a calibration more than a missing one
    return _drop_other_polarity(out, frame_pol)


def _measure_frame(fr: _FrameRods) -> list[RodMeasurement]:
    """Every rod of the frame measured on its prediction (:meth:`_FrameRods.measure` in turn, the same numbers and
    the same draws from the frame's generator), each stage run for all rods at once: the edge points of each rod,
    the limb fits in measurement order, then the axes of all rods fitted (:func:`_axes_from_limbs`)."""
    s = fr.settings
    jobs = [fr.job(i, p, fr.segs[i]) for i, p in enumerate(fr.preds)]
    live = [j for j in jobs if isinstance(j, _RodJob)]
    ready = []
    for j, fits in zip(live, _fit_limbs_frame([j.pts for j in live], s, fr.rng), strict=True):
        if isinstance(fits, str):
            j.out.reason = fits
            continue
        j.out.reason = _limb_quality(j.out, fits, s)
        if j.out.reason is None:
            j.fits = fits
            ready.append(j)
    _axes_from_limbs(ready, fr.camera, fr.radius, s, fr.proj)
    return [j.out if isinstance(j, _RodJob) else j for j in jobs]


def _remeasure_with_polarity(fr: _FrameRods, out: list[RodMeasurement], frame_pol: int) -> None:
    """Each rod measured with the other polarity than the frame's, which has pairs of the frame's: measured again
    with the frame's, kept when found (``out`` updated)."""
    for i, m in enumerate(out):
        if frame_pol and m.polarity == -frame_pol and m.pairs_by_polarity[0 if frame_pol > 0 else 1] > 0:
            again = fr.measure(i, fr.preds[i], fr.segs[i], frame_pol)
            if again.ok:
                out[i] = again


def _drop_other_polarity(out: list[RodMeasurement], frame_pol: int) -> list[RodMeasurement]:
    """The rods still measured with the other polarity than the frame's replaced by the reason."""
    for i, m in enumerate(out):
        if m.ok and frame_pol and m.polarity == -frame_pol:
            out[i] = RodMeasurement(
                m.leg,
                m.rod,
                reason=(
                    f"{'darker' if frame_pol > 0 else 'brighter'} than its surroundings, unlike most rods of the "
                    "frame: probably the gap between its leg's two rods"
                ),
            )
    return out


@dataclass
class _FrameRods:
    """What the rods of one frame are measured with (:func:`measure_rods`): the image (float32), the camera, the
    predictions, the rod radius (m), the settings, the occluders (ideal px), the frame's random generator (shared
    by its rods, in measurement order), the image's ideal-pixel box, the projector, and each rod's predicted
    segment and silhouette (updated when a rod is predicted again)."""

    img: np.ndarray
    camera: CameraModel
    preds: list[RodPrediction]
    radius: float
    settings: RodSettings
    occluders: list[Array] | None
    rng: np.random.Generator
    box: Array
    proj: _IdealToImage
    segs: list[_Segment | str]
    sil: list[tuple[Array, Array, float] | None]
    #: the rows of ``sil`` that are silhouettes and their arrays, once built (None: to build)
    nb: tuple[NDArray[np.intp], _Neighbours] | None = None

    def measure(
        self, i: int, pred: RodPrediction, seg: _Segment | str | None = None, polarity: int | None = None
    ) -> RodMeasurement:
        """Rod ``i`` measured on ``pred``, the other rods' silhouettes its neighbours."""
        return measure_rod(
            self.img,
            self.camera,
            pred,
            self.radius,
            self.settings,
            self.occluders,
            self.rng,
            self.box,
            neighbours=self._neighbours(i),
            segment=seg,
            projector=self.proj,
            polarity=polarity,
        )

    def job(self, i: int, pred: RodPrediction, seg: _Segment | str | None = None) -> _RodJob | RodMeasurement:
        """:meth:`measure`'s stages before the limb fits (:func:`_rod_job`)."""
        s = self.settings
        return _rod_job(
            self.img,
            self.camera,
            pred,
            self.radius,
            s,
            self.occluders,
            self.box,
            self._neighbours(i),
            seg,
            self.proj,
            None,
        )

    def _neighbours(self, i: int) -> _Neighbours:
        """The other rods' silhouettes (:func:`_silhouette`)."""
        if self.nb is None:  # (built once for the silhouettes, again when one changes)
            rows = [j for j, x in enumerate(self.sil) if x is not None]
            self.nb = (np.array(rows, dtype=np.intp), _Neighbours.of([x for x in self.sil if x is not None]))
        rows_arr, nb = self.nb
        return nb.subset(rows_arr != i)


def _separate_leg(fr: _FrameRods, out: list[RodMeasurement], i0: int, i1: int, frame_pol: int) -> None:
    """A leg whose two measured rods are of different polarities (one on the gap between them) or the same rod
    twice: the rod kept (the frame's polarity, resp. nearer its prediction) and the other measured again, predicted
    from the kept one shifted by the rods' predicted spacing (``out`` updated)."""
    preds = fr.preds
    spacing = float(np.linalg.norm(preds[i1].top - preds[i0].top))
    if out[i0].polarity != out[i1].polarity:
        # the two rods of a leg see the same background: one of them was measured on the gap between them
        ref = frame_pol or (1 if sum(out[i0].pairs_by_polarity) >= sum(out[i1].pairs_by_polarity) else -1)
        keep, redo = (i0, i1) if out[i0].polarity == ref else (i1, i0)
        why = "measured on the gap between its leg's two rods (the other polarity)"
    elif _line_distance(out[i0], out[i1]) <= 0.5 * spacing:
        # the same rod twice: keep the one nearer its prediction
        d0, d1 = (_line_distance_to_point(out[i], preds[i].top) for i in (i0, i1))
        keep, redo = (i0, i1) if d0 <= d1 else (i1, i0)
        why = "both rods of the leg matched the same rod image"
    else:
        return
    # measured again, predicted from the rod kept shifted by the rods' predicted spacing
    shift = preds[redo].top - preds[keep].top
    m = out[keep]
    top = _foot(m, preds[keep].top) + shift
    bottom = _foot(m, preds[keep].bottom) + shift
    again = fr.measure(redo, RodPrediction(preds[redo].leg, preds[redo].rod, top, bottom), polarity=m.polarity)
    if again.ok and _line_distance(out[keep], again) > 0.5 * spacing:
        out[redo] = again
    else:
        out[redo] = RodMeasurement(
            preds[redo].leg, preds[redo].rod, reason=f"{why} and the other was not found beside it"
        )


def _straddle_gap(fr: _FrameRods, out: list[RodMeasurement], leg: int, i0: int, i1: int, frame_pol: int) -> None:
    """One rod of the leg measured with the other polarity than the frame's and the other rod not measured: both
    measured again, predicted on either side of that gap (``out`` updated; ``fr``'s segments too)."""
    preds = fr.preds
    gap = [i for i in (i0, i1) if out[i].ok and out[i].polarity == -frame_pol]
    if len(gap) != 1 or out[i0 if gap[0] == i1 else i1].ok:
        return
    g_m = out[gap[0]]
    spacing = float(np.linalg.norm(preds[i1].top - preds[i0].top))
    mid_top, mid_bottom = 0.5 * (preds[i0].top + preds[i1].top), 0.5 * (preds[i0].bottom + preds[i1].bottom)
    moved = {
        i: RodPrediction(
            leg,
            preds[i].rod,
            _foot(g_m, mid_top) + preds[i].top - mid_top,
            _foot(g_m, mid_bottom) + preds[i].bottom - mid_bottom,
        )
        for i in (i0, i1)
    }
    s = fr.settings
    for i, p in moved.items():
        seg = _predicted_segment(fr.camera, p, fr.radius, s.near_m, fr.box)
        fr.segs[i] = seg
        fr.sil[i] = None if isinstance(seg, str) else _silhouette(seg)
        fr.nb = None
    for i, p in moved.items():
        again = fr.measure(i, p, fr.segs[i], frame_pol)
        if again.ok and _line_distance(g_m, again) > 0.25 * spacing:
            out[i] = again


def _silhouette(seg: _Segment) -> tuple[Array, Array, float]:
    """A predicted rod's axis segment ends and half-width in ideal pixels (the neighbours of :func:`measure_rod`)."""
    return seg.a, seg.a + seg.length * seg.t_dir, 0.5 * float(np.max(np.abs(seg.off1 - seg.off2)))


def _frame_polarity(out: list[RodMeasurement], fixed: int = 0) -> int:
    """The rods' polarity in a frame: +1 brighter than their surroundings, -1 darker, 0 undecided.

    ``fixed`` (:attr:`RodSettings.polarity`) when not 0; otherwise the polarity most of the frame's rods were
    measured with (each rod with edge pairs one vote), a tie decided by the pairs' count. A rod whose
    prediction falls between the two rods of its leg finds two kinds of pairs: its own limbs, and the gap
    between the two rods (about a rod wide, of the other polarity). Measured on the gap, a rod comes out
    parallel to the true ones in the image but tens of mrad off in depth (its limbs are the rods' inner
    limbs), in every frame of the pose. The rods share their material: most of a frame's rods have the
    rods' polarity.
    """
    if fixed:
        return 1 if fixed > 0 else -1
    votes = sum(m.polarity for m in out if sum(m.pairs_by_polarity) > 0)
    if votes == 0:
        votes = sum(m.pairs_by_polarity[0] - m.pairs_by_polarity[1] for m in out)
    return 0 if votes == 0 else (1 if votes > 0 else -1)


def _foot(m: RodMeasurement, x: Array) -> Array:
    """The point of a measured axis nearest x (camera frame, metres)."""
    assert m.point is not None and m.u is not None  # a measured rod (ok) of measure_rod, whose radius sets the point
    return m.point + ((x - m.point) @ m.u) * m.u


def _line_distance_to_point(m: RodMeasurement, x: Array) -> float:
    return float(np.linalg.norm(x - _foot(m, x)))


def _line_distance(a: RodMeasurement, b: RodMeasurement) -> float:
    """Distance (metres) between two measured axes, taken at a's point (the rods are near parallel)."""
    assert a.point is not None  # a measured rod (ok) of measure_rod, whose radius sets the point
    return _line_distance_to_point(b, a.point)


def leg_parallelism(meas: list[RodMeasurement]) -> dict[str, float]:
    """Angle (rad) between the two rods of each leg where both were measured, keyed ``"1".."4"``.

    Parameters
    ----------
    meas : list of RodMeasurement
        A frame's rod measurements.

    Returns
    -------
    dict of str to float
        Leg number (``"1"`` to ``"4"``) -> angle between its rods' axes (radians, in [0, pi/2]).
    """
    out = {}
    by = {(m.leg, m.rod): m for m in meas}
    for leg in range(4):
        a, b = by.get((leg, 0)), by.get((leg, 1))
        if a is not None and b is not None and a.ok and b.ok:
            assert a.u is not None and b.u is not None  # ok: u is set
            out[str(leg + 1)] = float(np.arccos(np.clip(abs(a.u @ b.u), -1.0, 1.0)))
    return out
