"""First-frame rod detection: no prior pose, only the image, the encoder values and the nominal model.

Without a coarse camera placement (``camera_from_base``) no rod can be predicted, so
:func:`calib.vision.rods.measure_rod` has no search band. This module finds the rods from scratch,
associates them to the legs, and gives back what :func:`calib.vision.rods.predict_rods` gives (one
axis segment per rod, camera frame) plus a coarse ``camera_from_base`` (see docs/vision.md):

1. **Segments**: the image is resampled to ideal (undistorted) pixels on a canvas of the original
   area (straight rods stay straight), then ``cv2.createLineSegmentDetector``. Each segment gets its
   polarity (which side is brighter) and contrast from samples on either side.
2. **Lines**: collinear segments of the same polarity are merged (union-find on angle, distance and
   gap, so a limb cut by the board or by another rod is one line), re-measured with sub-pixel edges
   on profiles across them (LSD's lines sit ~2 px inside a shaded rod's limbs) and merged again.
3. **Rods**: pairs of lines that are nearly parallel, overlap, face each other (a bright rod: each
   limb's bright side towards the other; ``polarity``), are as far apart as a rod of the known
   radius between ``depth_range_m``, and whose inside is brighter (darker) than their outside along
   the overlap. Each gives its two limb planes h1, h2 (camera frame, paper eq. 6).
4. **Legs**: pairs of rod candidates that are nearly parallel in the image, of similar width, whose
   separation over width matches ``rod_spacing / (2 rod_radius)`` (foreshortened). The two rods are
   parallel in space, so the leg's 3-D direction is the intersection of their axis planes
   (``h1 - h2`` bisects the limb planes and contains the axis).
5. **Association and placement**: the nominal model at the encoder values gives the legs'
   directions in the base frame. Assignments of leg candidates to legs 1..4 (at least ``min_legs``)
   whose pairwise angles match are enumerated with the directions' signs; the rotation is a weighted
   Kabsch fit, the rod order in each leg follows from the side of x_B, the translation is linear
   (every limb plane satisfies ``h . X = r`` on the axis), then Levenberg-Marquardt on the limb
   lines' end points (ideal px) refines ``camera_from_base``. The best hypothesis (most legs, then
   lowest RMS) wins unless a *rival* that labels the rods differently fits about as well: then the
   frame is ambiguous and its rods are reported missing (only the leg concerned when the rival just
   swaps the two rods of one leg).

The I4 is symmetric under a half-turn about the vertical through the end-effector when ``Y = 0``
(legs 1<->4, 2<->3; the nominal model is centimetres off, so in practice up to ``|Y|`` ~ 0.1 m):
rods alone cannot tell those labellings apart. A ``prior`` (a coarse ``camera_from_base``: the
bench's camera mounting, or the placement other frames agreed on, :func:`resolve_frames`) drops
the hypotheses rotated more than ``prior_tol_rad`` from it.

The priors handed to ``measure_rod`` are the detected rods themselves (their limb planes and the
radius), along the detected leg direction, over the nominal model's extent: the nominal model's
rods are 1-2 cm (10-25 px) off even at the fitted placement, the detected lines are not.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..camera import CameraModel
from ..errors import I4calError
from ..kinematics import dkm, joint_points
from ..parameters import I4Parameters
from ..transforms import Rigid, matrix_to_rotvec, rotvec_to_matrix
from .rods import (
    ROD_KEYS,
    RodMeasurement,
    RodPrediction,
    RodSettings,
    image_ideal_bbox,
    measure_rods,
    predict_rods,
    robust_line,
    rod_name,
)

Array = NDArray[np.float64]


@dataclass
class DetectSettings:
    """Tuning of :func:`detect_rods` (pixels are ideal, undistorted pixels of the camera model)."""

    min_segment_px: float = 15.0  #: LSD segments shorter than this are dropped
    min_contrast: float = 12.0  #: grey levels between the two sides of a segment
    merge_angle_rad: float = 0.025  #: collinear merge: angle between segments
    merge_dist_px: float = 2.0  #: collinear merge: end point distance to the other line
    merge_gap_px: float = 450.0  #: collinear merge: largest gap along the line
    refine_step_px: float = 6.0  #: edge refinement: profile spacing along a line
    refine_band_px: float = 4.0  #: edge refinement: half-length of each profile
    limb_angle_rad: float = 0.08  #: angle between the two limbs of a rod (perspective)
    depth_range_m: tuple[float, float] = (0.15, 3.0)  #: rods nearer / farther are not searched
    min_rod_px: float = 60.0  #: overlap of the two limbs of a rod candidate
    polarity: Literal["bright", "dark", "auto"] = "auto"  #: rods brighter/darker than their background
    leg_angle_rad: float = 0.1  #: angle between the two rods of a leg in the image
    leg_width_ratio: float = 1.6  #: largest width ratio of the two rods of a leg
    spacing_ratio_range: tuple[float, float] = (0.15, 1.3)  #: image separation / nominal (spacing / width)
    min_legs: int = 3  #: legs needed to solve the placement
    centre_plane_sigma_rad: float = 1.5e-3  #: error of a rod's axis plane (sets a leg direction's error)
    model_direction_rad: float = 0.03  #: nominal-model error of a leg direction
    pair_angle_tol_rad: float = 0.1  #: pairwise leg-angle mismatch (plus 3 sigma of both directions)
    kabsch_tol: float = 3.0  #: weighted RMS direction misfit (sigmas) of an assignment's rotation
    max_hypotheses: int = 6  #: per leg count, refined by Levenberg-Marquardt (best first)
    max_rms_px: float = 12.0  #: placement fit RMS above this: hypothesis rejected
    ambiguity_ratio: float = 1.5  #: a rival within ratio x RMS + ambiguity_px is a tie
    ambiguity_px: float = 1.0
    prior_tol_rad: float = 0.5  #: hypotheses rotated farther from the prior are dropped
    depth_tolerance: float = 0.12  #: a prior's depth / model's off the frame's median by more: moved


@dataclass
class Line2:
    """A merged straight edge in ideal pixels: ``n . x + c = 0``, ``n`` towards the brighter side."""

    n: Array
    c: float
    t: Array  # unit direction, n rotated by -90 deg
    s0: float  # extent along t (s = t . x)
    s1: float
    contrast: float  # grey levels across it

    def point(self, s: float) -> Array:
        return -self.c * self.n + s * self.t


@dataclass
class RodCandidate:
    """Two limb lines facing each other: a rod seen in the image."""

    limbs: tuple[Line2, Line2]
    s0: float  # overlap extent along ``t``
    s1: float
    t: Array
    width_px: tuple[float, float]  # at s0 and s1
    centre: tuple[Array, Array]  # centre-line points at s0 and s1 (ideal px)
    bright: bool
    h: tuple[Array, Array]  # limb planes (camera), unit normals, the axis on their positive side
    m: Array  # the axis plane: through the camera centre and the axis (bisects h)

    @property
    def length(self) -> float:
        return self.s1 - self.s0


@dataclass
class LegCandidate:
    """Two rod candidates side by side at the rod spacing: a leg seen in the image."""

    rods: tuple[int, int]  # indices into the rod candidates
    d: Array  # 3-D direction (camera), sign arbitrary
    sigma: float  # its expected error, rad (centre-plane error / angle between the planes)


@dataclass
class Hypothesis:
    """An association of leg candidates to legs with its fitted placement."""

    legs: dict[int, tuple[int, int]]  # leg (0-based) -> (rod candidate of rod0, of rod1)
    camera_from_base: Rigid
    rms_px: float
    kabsch_misfit: float

    def labels(self) -> dict[int, tuple[int, int]]:
        """Rod candidate -> (leg, rod)."""
        return {c: (leg, r) for leg, pair in self.legs.items() for r, c in enumerate(pair)}


@dataclass
class RodDetection:
    """What :func:`detect_rods` found in one frame.

    Attributes
    ----------
    predictions : list of RodPrediction or None, length 8 (``ROD_KEYS`` order)
        Priors for :func:`calib.vision.rods.measure_rod`; None where the rod was not associated.
    reasons : dict
        ``rod_name -> reason`` for every None prediction.
    camera_from_base : Rigid or None
        The coarse placement fitted to this frame's rods (None when not solved).
    rms_px : float
        Residual RMS of the limb end points to the predicted limb lines (ideal px).
    ambiguous : bool
        Another labelling of the legs fits as well: every rod is None (see ``reason``).
    hypotheses : list of Hypothesis
        Every accepted hypothesis, best first (diagnostics).
    directions : list of ndarray (3,) or None, length 8
        Each associated rod's detected direction in the camera frame, oriented from the actuator to
        the plate: its leg's direction from the two rods' axis planes, weighted with the nominal
        model's at the fitted placement where those planes nearly coincide.
    rods : list of RodCandidate
    leg_candidates : list of LegCandidate
    counts : dict
        Numbers of segments, lines, rod and leg candidates.
    reason : str or None
        Why nothing was associated (no legs, no fit, ambiguous).
    """

    predictions: list[RodPrediction | None]
    reasons: dict[str, str]
    camera_from_base: Rigid | None = None
    rms_px: float = float("nan")
    ambiguous: bool = False
    hypotheses: list[Hypothesis] = field(default_factory=list)
    directions: list[Array | None] = field(default_factory=lambda: [None] * 8)
    rods: list[RodCandidate] = field(default_factory=list)
    leg_candidates: list[LegCandidate] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.camera_from_base is not None


# ---------------------------------------------------------------------------------------------
# 1. undistorted canvas and segments
@functools.lru_cache(maxsize=4)
def _canvas_maps(
    K: tuple, dist: tuple, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, float, Array, np.ndarray]:
    cam = CameraModel(np.asarray(K).reshape(3, 3), np.asarray(dist), width, height)
    box = image_ideal_bbox(cam, 0.0)
    area = (box[2] - box[0]) * (box[3] - box[1])
    scale = float(min(1.0, np.sqrt(width * height / area)))
    cw = int(np.ceil((box[2] - box[0]) * scale))
    ch = int(np.ceil((box[3] - box[1]) * scale))
    u, v = np.meshgrid(np.arange(cw, dtype=np.float64), np.arange(ch, dtype=np.float64))
    ideal = np.column_stack([u.ravel() / scale + box[0], v.ravel() / scale + box[1]])
    d = cam.distort_normalized(cam.from_ideal_pixels(ideal))
    mx = d[:, 0].reshape(ch, cw).astype(np.float32)
    my = d[:, 1].reshape(ch, cw).astype(np.float32)
    valid = (mx >= 1) & (mx <= width - 2) & (my >= 1) & (my <= height - 2)
    valid = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return mx, my, scale, box[:2].copy(), valid


def undistorted_canvas(gray: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, float, Array, np.ndarray]:
    """The image resampled to ideal pixels, scaled to the original area.

    Returns
    -------
    canvas : ndarray, shape (h, w), float32
    scale : float
        Canvas pixels per ideal pixel.
    origin : ndarray, shape (2,)
        Ideal pixel of canvas (0, 0): ``ideal = canvas / scale + origin``.
    valid : ndarray of bool, shape (h, w)
        Canvas pixels that see the image.
    """
    mx, my, scale, origin, valid = _canvas_maps(
        tuple(camera.K.ravel()), tuple(camera.dist), camera.width, camera.height
    )
    img = gray.astype(np.float32) if gray.dtype != np.float32 else gray
    canvas = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return canvas, scale, origin, valid


def _sample(img: np.ndarray, pts: Array) -> Array:
    """Bilinear samples of img at canvas points (..., 2)."""
    p = pts.reshape(-1, 2).astype(np.float32)
    n = len(p)
    cols = 1024  # remap's maps must stay below 32767 in both dimensions
    rows = max(1, -(-n // cols))
    m = np.zeros((rows * cols, 2), dtype=np.float32)
    m[:n] = p
    out = cv2.remap(
        img, m[:, 0].reshape(rows, cols), m[:, 1].reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.ravel()[:n].reshape(pts.shape[:-1]).astype(np.float64)


def detect_segments(
    canvas: np.ndarray, valid: np.ndarray, scale: float, origin: Array, settings: DetectSettings
) -> tuple[Array, Array, Array]:
    """LSD segments in ideal pixels with their polarity.

    Returns
    -------
    seg : ndarray, shape (N, 2, 2)
        End points, ideal px, ordered so that the brighter side is on the left of p0 -> p1
        (normal ``n = (-t_y, t_x)`` points to the brighter side).
    contrast : ndarray, shape (N,)
        Mean grey-level difference across the segment.
    length : ndarray, shape (N,)
        Ideal px.
    """
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    lines = lsd.detect(np.clip(canvas, 0, 255).astype(np.uint8))[0]
    if lines is None:
        return np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0)
    L = lines.reshape(-1, 2, 2).astype(np.float64)
    d = L[:, 1] - L[:, 0]
    ln = np.linalg.norm(d, axis=1)
    keep = ln / scale >= settings.min_segment_px
    L, d, ln = L[keep], d[keep], ln[keep]
    if len(L) == 0:
        return np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0)
    # clip each segment to its longest part that sees the image (the canvas' corners do not)
    h, w = valid.shape
    f = np.linspace(0.0, 1.0, 33)
    p = np.rint(L[:, None, 0] + f[None, :, None] * d[:, None]).astype(int)
    inside = (p[..., 0] >= 0) & (p[..., 0] < w) & (p[..., 1] >= 0) & (p[..., 1] < h)
    vis = np.zeros(inside.shape, dtype=bool)
    vis[inside] = valid[p[..., 1][inside], p[..., 0][inside]]
    ok = np.ones(len(L), dtype=bool)
    for k in np.flatnonzero(~vis.all(axis=1)):
        runs = np.diff(np.concatenate([[0], vis[k].astype(np.int8), [0]]))
        starts, ends = np.flatnonzero(runs == 1), np.flatnonzero(runs == -1)
        if starts.size == 0:
            ok[k] = False
            continue
        j = int(np.argmax(ends - starts))
        a, b = f[starts[j]], f[ends[j] - 1]
        L[k] = [L[k, 0] + a * d[k], L[k, 0] + b * d[k]]
    d = L[:, 1] - L[:, 0]
    ln = np.linalg.norm(d, axis=1)
    ok &= ln / scale >= settings.min_segment_px
    ln = np.maximum(ln, 1e-9)
    t = d / ln[:, None]
    n = np.column_stack([-t[:, 1], t[:, 0]])
    # polarity and contrast: samples 2.5 canvas px either side at 9 places along the segment
    f = np.linspace(0.1, 0.9, 9)
    mid = L[:, 0, None, :] + f[None, :, None] * d[:, None, :]
    off = 2.5 * n[:, None, :]
    diff = (_sample(canvas, mid + off) - _sample(canvas, mid - off)).mean(axis=1)
    flip = diff < 0
    L[flip] = L[flip][:, ::-1]
    con = np.abs(diff)
    ok &= con >= settings.min_contrast
    seg = L[ok] / scale + origin
    return seg, con[ok], ln[ok] / scale


# ---------------------------------------------------------------------------------------------
# 2. collinear merge
def _fit_line(points: Array, weights: Array) -> tuple[Array, float]:
    c = (weights[:, None] * points).sum(0) / weights.sum()
    d = points - c
    C = (weights[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0)
    _, v = np.linalg.eigh(C)
    n = v[:, 0]
    return n, float(-n @ c)


def merge_segments(seg: Array, contrast: Array, length: Array, settings: DetectSettings) -> list[Line2]:
    """Merge collinear segments of the same polarity into lines (ideal px)."""
    N = len(seg)
    if N == 0:
        return []
    d = seg[:, 1] - seg[:, 0]
    t = d / np.linalg.norm(d, axis=1)[:, None]
    n = np.column_stack([-t[:, 1], t[:, 0]])
    c = -np.einsum("ij,ij->i", n, seg[:, 0])
    # pairwise tests (N is a few hundred)
    cosang = t @ t.T
    same = cosang > np.cos(settings.merge_angle_rad)
    # distance of j's end points to line i, both ways
    dist0 = np.abs(n @ seg[:, 0].T + c[:, None])
    dist1 = np.abs(n @ seg[:, 1].T + c[:, None])
    dmax = np.maximum(dist0, dist1)
    close = (dmax < settings.merge_dist_px) & (settings.merge_dist_px > dmax.T)
    # gap along the direction
    s0 = np.einsum("ij,kj->ik", t, seg[:, 0])  # s0[i, k] = t_i . p0_k
    s1 = np.einsum("ij,kj->ik", t, seg[:, 1])
    lo = np.minimum(s0, s1)
    hi = np.maximum(s0, s1)
    own_lo, own_hi = np.diag(lo), np.diag(hi)
    gap = np.maximum(lo - own_hi[:, None], own_lo[:, None] - hi)
    link = same & close & (gap < settings.merge_gap_px)
    parent = list(range(N))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j in zip(*np.nonzero(np.triu(link, 1)), strict=True):
        ri, rj = find(int(i)), find(int(j))
        if ri != rj:
            parent[rj] = ri
    groups: dict[int, list[int]] = {}
    for i in range(N):
        groups.setdefault(find(i), []).append(i)
    out: list[Line2] = []
    for idx in groups.values():
        pts = []
        wts = []
        for i in idx:
            k = max(2, int(length[i] // 4))
            f = np.linspace(0.0, 1.0, k)
            pts.append(seg[i, 0] + f[:, None] * d[i])
            wts.append(np.full(k, length[i] / k))
        P = np.vstack(pts)
        Wt = np.concatenate(wts)
        nn, cc = _fit_line(P, Wt)
        # orient n towards the brighter side (the segments' common n)
        nmean = (n[idx] * length[idx, None]).sum(0)
        if nn @ nmean < 0:
            nn, cc = -nn, -cc
        tt = np.array([nn[1], -nn[0]])
        s = P @ tt
        out.append(
            Line2(nn, cc, tt, float(s.min()), float(s.max()), float(np.average(contrast[idx], weights=length[idx])))
        )
    return out


def refine_lines(
    lines: list[Line2],
    canvas: np.ndarray,
    scale: float,
    origin: Array,
    settings: DetectSettings,
    rng: np.random.Generator,
) -> list[Line2]:
    """Sub-pixel edge positions along each line, robust refit.

    LSD's line is the axis of its gradient-support rectangle: on a shaded rod it sits ~2 px inside the
    limb. Each line is re-measured on profiles across it (every ``refine_step_px``, +/- ``refine_band_px``):
    the |gradient| peak of the line's polarity nearest to it, interpolated by a parabola, then a
    RANSAC + IRLS line fit (:func:`calib.vision.rods.robust_line`). Lines with too few edge points are
    dropped; the extent becomes that of the inliers.
    """
    if not lines:
        return []
    step, band, ds = settings.refine_step_px, settings.refine_band_px, 0.5
    offs = np.arange(-band, band + 1e-9, ds)
    per, base, nrm = [], [], []
    for ln in lines:
        k = int(min(max(2, (ln.s1 - ln.s0) // step + 1), 200))
        s = np.linspace(ln.s0, ln.s1, k)
        per.append(k)
        base.append(ln.point(0.0)[None] + s[:, None] * ln.t[None])
        nrm.append(np.repeat(ln.n[None], k, axis=0))
    B = np.vstack(base)
    Nn = np.vstack(nrm)
    grid = B[:, None, :] + offs[None, :, None] * Nn[:, None, :]
    prof = _sample(canvas, _to_canvas(grid, scale, origin))
    g = np.gradient(prof, ds, axis=1)
    g = cv2.GaussianBlur(g.astype(np.float32), (5, 1), 0.8 / ds).astype(np.float64)
    # positive gradient (brighter along n) nearest the line
    w = np.where(g > 0, g, 0.0) * np.exp(-0.5 * (offs / (0.6 * band)) ** 2)[None]
    j = np.clip(np.argmax(w, axis=1), 1, len(offs) - 2)
    r = np.arange(len(j))
    y0, y1, y2 = g[r, j - 1], g[r, j], g[r, j + 1]
    den = y0 - 2 * y1 + y2
    dx = np.where(den < -1e-9, 0.5 * (y0 - y2) / np.where(den < -1e-9, den, -1.0), 0.0)
    pos = offs[j] + np.clip(dx, -0.5, 0.5) * ds
    # a blurred step of height C peaks at about C / (sqrt(2 pi) sigma) grey levels per px
    good = (g[r, j] > 0.15 * settings.min_contrast) & (np.abs(offs[j]) < band - ds)
    pts = B + pos[:, None] * Nn
    out: list[Line2] = []
    start = 0
    for ln, k in zip(lines, per, strict=True):
        P = pts[start : start + k][good[start : start + k]]
        start += k
        if len(P) < max(4, 0.3 * k):
            continue
        line, inl = robust_line(P, rng, 60, 0.7)
        if not np.all(np.isfinite(line)) or inl.sum() < max(4, 0.3 * k):
            continue
        n = line[:2]
        c = float(line[2])
        if n @ ln.n < 0:
            n, c = -n, -c
        t = np.array([n[1], -n[0]])
        sp = P[inl] @ t
        out.append(Line2(n, c, t, float(sp.min()), float(sp.max()), ln.contrast))
    return out


def merge_lines(lines: list[Line2], settings: DetectSettings) -> list[Line2]:
    """Join refined lines that are pieces of one edge (e.g. a limb cut by the board or by a rod).

    Same tests as :func:`merge_segments` on the lines' end points; the joined line is fitted to the
    pieces' end points weighted by their lengths.
    """
    if len(lines) < 2:
        return lines
    seg = np.array([[ln.point(ln.s0), ln.point(ln.s1)] for ln in lines])
    con = np.array([ln.contrast for ln in lines])
    length = np.array([ln.s1 - ln.s0 for ln in lines])
    merged = merge_segments(seg, con, length, settings)
    return merged if len(merged) < len(lines) else lines


# ---------------------------------------------------------------------------------------------
# 3. rods
def _to_canvas(p: Array, scale: float, origin: Array) -> Array:
    return (p - origin) * scale


def _ray(K_inv: Array, p: Array) -> Array:
    return K_inv @ np.array([p[0], p[1], 1.0])


def _plane(K: Array, line: Array) -> Array:
    """Unit normal of the interpretation plane of an ideal-pixel line (a, b, c)."""
    h = K.T @ line
    return h / np.linalg.norm(h)


def _inside_fraction(
    canvas: np.ndarray, scale: float, origin: Array, pa: list[Array], pb: list[Array], bright: bool, need: float
) -> float:
    """Fraction of 9 profiles across the span between two lines where the inside is brighter (darker)
    than both outsides by ``need`` grey levels: its darkest (brightest) of 5 samples against the
    brighter (darker) of the samples 3 px beyond each line (near enough to stay in a narrow gap
    between the two rods of a leg). ``pa``, ``pb``: each line's points at the span's ends (ideal px).
    """
    fr = np.linspace(0.05, 0.95, 9)
    A = pa[0][None] + fr[:, None] * (pa[1] - pa[0])[None]
    B = pb[0][None] + fr[:, None] * (pb[1] - pb[0])[None]
    across = B - A
    u = across / np.linalg.norm(across, axis=1)[:, None]
    inner = A[:, None] + np.linspace(0.2, 0.8, 5)[None, :, None] * across[:, None]
    Ii = _sample(canvas, _to_canvas(inner, scale, origin))
    Ia = _sample(canvas, _to_canvas(A - 3.0 * u, scale, origin))
    Ib = _sample(canvas, _to_canvas(B + 3.0 * u, scale, origin))
    if bright:
        margin = Ii.min(axis=1) - np.maximum(Ia, Ib)
    else:
        margin = np.minimum(Ia, Ib) - Ii.max(axis=1)
    return float(np.mean(margin > need))


def find_rods(
    lines: list[Line2],
    canvas: np.ndarray,
    scale: float,
    origin: Array,
    camera: CameraModel,
    radius: float,
    settings: DetectSettings,
) -> list[RodCandidate]:
    """Pairs of lines that bound a rod (see the module docstring, step 3)."""
    f = camera.focal_px
    wmin = 2 * radius * f / settings.depth_range_m[1]
    wmax = 2 * radius * f / settings.depth_range_m[0]
    cands: list[tuple[float, int, int, RodCandidate]] = []
    K = camera.K
    K_inv = np.linalg.inv(K)
    if len(lines) < 2:
        return []
    T = np.array([ln.t for ln in lines])
    par = np.abs(T @ T.T) >= np.cos(settings.limb_angle_rad)
    for i, j in zip(*np.nonzero(np.triu(par, 1)), strict=True):
        i, j = int(i), int(j)
        a, b = lines[i], lines[j]
        # common direction (a's), extents of both on it
        t = a.t
        ea = sorted((a.point(a.s0) @ t, a.point(a.s1) @ t))
        eb = sorted((b.point(b.s0) @ t, b.point(b.s1) @ t))
        s0, s1 = max(ea[0], eb[0]), min(ea[1], eb[1])
        if s1 - s0 < settings.min_rod_px:
            continue
        pa = [_line_point(a, s0, t), _line_point(a, s1, t)]
        pb = [_line_point(b, s0, t), _line_point(b, s1, t)]
        wd = (float(np.linalg.norm(pb[0] - pa[0])), float(np.linalg.norm(pb[1] - pa[1])))
        if min(wd) < wmin or max(wd) > wmax:
            continue
        # facing: a's bright side towards b and b's towards a (bright rod), or both away (dark rod)
        mid_a, mid_b = 0.5 * (pa[0] + pa[1]), 0.5 * (pb[0] + pb[1])
        fa = a.n @ (mid_b - mid_a) > 0
        fb = b.n @ (mid_a - mid_b) > 0
        if fa != fb:
            continue
        bright = bool(fa)
        if (settings.polarity == "bright" and not bright) or (settings.polarity == "dark" and bright):
            continue
        inside = _inside_fraction(canvas, scale, origin, pa, pb, bright, 0.3 * min(a.contrast, b.contrast))
        if inside < 0.7:
            continue
        # limb lines as (a, b, c) with the axis on the positive side of their planes
        centre = (0.5 * (pa[0] + pb[0]), 0.5 * (pa[1] + pb[1]))
        cm = 0.5 * (centre[0] + centre[1])
        hs = []
        for ln in (a, b):
            h = _plane(K, np.array([ln.n[0], ln.n[1], ln.c]))
            if h @ _ray(K_inv, cm) < 0:
                h = -h
            hs.append(h)
        # the plane through the camera centre and the axis bisects the two limb planes
        m = hs[0] - hs[1]
        m = m / np.linalg.norm(m)
        rc = RodCandidate((a, b), s0, s1, t, wd, centre, bright, (hs[0], hs[1]), m)
        score = (s1 - s0) * inside * np.sqrt(np.mean(wd))
        cands.append((score, i, j, rc))
    # each line bounds at most one rod of each polarity (the inner limb of a bright rod also bounds
    # the dark gap between the two rods of its leg): best score first
    cands.sort(key=lambda x: -x[0])
    used: set[tuple[int, bool]] = set()
    out = []
    for _, i, j, rc in cands:
        if (i, rc.bright) in used or (j, rc.bright) in used:
            continue
        used.update(((i, rc.bright), (j, rc.bright)))
        out.append(rc)
    return out


# ---------------------------------------------------------------------------------------------
# 4. legs
def find_legs(rods: list[RodCandidate], radius: float, spacing: float, settings: DetectSettings) -> list[LegCandidate]:
    """Pairs of parallel rod candidates at the rod spacing (see the module docstring, step 4)."""
    out = []
    nominal_ratio = spacing / (2 * radius)
    lo, hi = settings.spacing_ratio_range
    for i, j in itertools.combinations(range(len(rods)), 2):
        a, b = rods[i], rods[j]
        if a.bright != b.bright or abs(a.t @ b.t) < np.cos(settings.leg_angle_rad):
            continue
        t = a.t
        ea = sorted((a.centre[0] @ t, a.centre[1] @ t))
        eb = sorted((b.centre[0] @ t, b.centre[1] @ t))
        s0, s1 = max(ea[0], eb[0]), min(ea[1], eb[1])
        if s1 - s0 < 0.3 * min(a.length, b.length):
            continue
        sm = 0.5 * (s0 + s1)
        nrm = np.array([-t[1], t[0]])

        def at(rc: RodCandidate, s: float, nrm=nrm, t=t) -> tuple[float, float]:
            c0, c1 = rc.centre
            s_0, s_1 = c0 @ t, c1 @ t
            f = (s - s_0) / (s_1 - s_0) if abs(s_1 - s_0) > 1e-9 else 0.5
            p = c0 + f * (c1 - c0)
            w = rc.width_px[0] + f * (rc.width_px[1] - rc.width_px[0])
            return float(p @ nrm), float(w)

        ka, wa = at(a, sm)
        kb, wb = at(b, sm)
        if max(wa, wb) > settings.leg_width_ratio * min(wa, wb) or min(wa, wb) <= 0:
            continue
        ratio = abs(ka - kb) / (0.5 * (wa + wb))
        if not lo * nominal_ratio <= ratio <= hi * nominal_ratio:
            continue
        d = np.cross(a.m, b.m)
        sn = float(np.linalg.norm(d))
        if sn < 1e-4:
            continue
        out.append(LegCandidate((i, j), d / sn, settings.centre_plane_sigma_rad / sn))
    return out


# ---------------------------------------------------------------------------------------------
# 5. association and placement
def _kabsch(U: Array, D: Array, w: Array) -> tuple[Array, float]:
    """Rotation R minimising sum w_k |R U_k - D_k|^2 (rows unit vectors) and the weighted RMS misfit.

    With ``w_k = 1 / sigma_k^2`` the misfit is in sigmas.
    """
    H = (U * w[:, None]).T @ D
    Us, _, Vt = np.linalg.svd(H)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ Us.T))])
    R = Vt.T @ S @ Us.T
    r = np.linalg.norm(U @ R.T - D, axis=1)
    return R, float(np.sqrt(np.mean(w * r**2)))


def _assignments(
    model_ang: Array, cand_ang: Array, n_cand: int, min_legs: int, tol: Array
) -> list[tuple[int | None, ...]]:
    """Injective partial maps leg -> candidate whose pairwise angles agree within tol."""
    out: list[tuple[int | None, ...]] = []

    def rec(leg: int, cur: list[int | None]) -> None:
        if leg == 4:
            if sum(c is not None for c in cur) >= min_legs:
                out.append(tuple(cur))
            return
        if sum(c is None for c in cur) < 4 - min_legs:
            rec(leg + 1, [*cur, None])
        for k in range(n_cand):
            if k in cur:
                continue
            if all(c is None or abs(cand_ang[k, c] - model_ang[leg, lg]) < tol[k, c] for lg, c in enumerate(cur)):
                rec(leg + 1, [*cur, k])

    rec(0, [])
    return out


def _rod_model(nominal: I4Parameters, q: Array, spacing: float) -> tuple[Array, Array]:
    """Rod top points (4, 2, 3) and leg directions (4, 3), base frame."""
    pose = dkm(nominal, q)
    A, B = joint_points(nominal, q[None], pose[None])
    u = B[0] - A[0]
    u = u / np.linalg.norm(u, axis=1)[:, None]
    off = np.array([-0.5, 0.5])[:, None] * spacing * np.array([1.0, 0.0, 0.0])
    return A[0][:, None, :] + off[None], u


class _Fitter:
    """Limb end-point residuals (ideal px) of assigned rods for a placement (vectorised over rods)."""

    def __init__(self, rods: list[RodCandidate], tops: Array, u: Array, radius: float, K: Array) -> None:
        self.rods = rods
        self.tops = tops
        self.u = u
        self.r = radius
        self.K = K
        self.KiT = np.linalg.inv(K).T
        self.Ki = np.linalg.inv(K)
        # per rod candidate: limb end points (2 limbs, 2 ends, homogeneous) and limb planes
        self.ends = (
            np.array(
                [
                    [[np.append(_line_point(limb, s_, rc.t), 1.0) for s_ in (rc.s0, rc.s1)] for limb in rc.limbs]
                    for rc in rods
                ]
            )
            if rods
            else np.zeros((0, 2, 2, 3))
        )
        self.h = np.array([np.vstack(rc.h) for rc in rods]) if rods else np.zeros((0, 2, 3))

    def setup(self, legs: dict[int, tuple[int, int]]) -> tuple[Array, Array, Array]:
        """Model tops (M, 3), leg directions (M, 3) and candidate indices (M,) of the assigned rods."""
        idx, tops, us = [], [], []
        for leg, pair in legs.items():
            for rod, ci in enumerate(pair):
                idx.append(ci)
                tops.append(self.tops[leg, rod])
                us.append(self.u[leg])
        return np.asarray(tops), np.asarray(us), np.asarray(idx, dtype=int)

    def predicted_planes(self, X: Array, tops: Array, us: Array) -> tuple[Array, Array]:
        """Predicted limb planes (P, M, 2, 3) and the camera-centre distance to each axis (P, M).

        ``X`` (P, 6): rotation vectors and translations of P placements.
        """
        R = rotvec_to_matrix(X[:, :3])  # (P, 3, 3)
        P = np.einsum("pij,mj->pmi", R, tops) + X[:, None, 3:]  # (P, M, 3)
        U = np.einsum("pij,mj->pmi", R, us)
        p = P - np.sum(P * U, axis=-1)[..., None] * U
        d = np.linalg.norm(p, axis=-1)
        e1 = p / d[..., None]
        e2 = np.cross(U, e1)
        c = np.clip(self.r / d, 0.0, 0.999)[..., None]
        sn = np.sqrt(1.0 - c * c)
        return np.stack([c * e1 + sn * e2, c * e1 - sn * e2], axis=-2), d

    def residuals(self, X: Array, tops: Array, us: Array, idx: Array) -> Array:
        """Signed distances (ideal px) of the measured limb end points to the predicted limb lines.

        ``X`` (P, 6) -> (P, M * 4); each measured limb is matched to the predicted limb whose
        interpretation plane it is closest to.
        """
        h, _ = self.predicted_planes(X, tops, us)
        lines = h @ self.KiT.T  # (P, M, 2, 3): l = K^-T h
        lines = lines / np.linalg.norm(lines[..., :2], axis=-1)[..., None]
        hd = self.h[idx][None]  # measured planes (1, M, 2, 3)
        straight = np.sum(hd * h, axis=(-2, -1))
        crossed = np.sum(hd * h[..., ::-1, :], axis=(-2, -1))
        lines = np.where((crossed > straight)[..., None, None], lines[..., ::-1, :], lines)
        ends = self.ends[idx]  # (M, 2 limbs, 2 ends, 3)
        return np.einsum("pmkj,mkej->pmke", lines, ends).reshape(len(X), -1)


def _levenberg_marquardt(
    f: Callable[[Array], Array], x0: Array, steps: Array, iters: int = 40, tol: float = 1e-6
) -> tuple[Array, Array]:
    """Minimise |f(x)|^2, f batched ((P, n) -> (P, m)): each forward-difference Jacobian is one call.

    Returns the solution (n,) and its residuals (m,); stops when a step is below ``tol`` in every
    coordinate or none decreases the cost.
    """
    x = x0.astype(np.float64).copy()
    r = f(x[None])[0]
    cost = float(r @ r)
    lam = 1e-3
    eye = np.diag(steps)
    for _ in range(iters):
        F = f(np.vstack([x[None], x[None] + eye]))
        r = F[0]
        J = (F[1:] - r[None]) / steps[:, None]  # (n, m)
        A = J @ J.T
        g = J @ r
        improved = False
        for _ in range(8):
            try:
                dx = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            rn = f((x + dx)[None])[0]
            cn = float(rn @ rn)
            if np.isfinite(cn) and cn < cost:
                x, r, cost = x + dx, rn, cn
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or np.all(np.abs(dx) < tol):
            break
    return x, r


def _line_point(line: Line2, s: float, t: Array) -> Array:
    """The point of ``line`` at abscissa ``s`` along the unit direction ``t`` (ideal px)."""
    nrm = np.array([-t[1], t[0]])
    den = line.n @ nrm
    k = -(line.c + s * (line.n @ t)) / den
    return s * t + k * nrm


def _rotation_angle(Ra: Array, Rb: Array) -> float:
    return float(np.linalg.norm(matrix_to_rotvec(Ra @ Rb.T)))


def _differences(best: Hypothesis, other: Hypothesis) -> tuple[bool, set[int]]:
    """How ``other`` labels the rods differently from ``best``.

    Returns
    -------
    legs_swapped : bool
        Some rod candidate belongs to another leg, or some leg to another rod pair.
    orders : set of int
        Legs (0-based) whose two rods are the same pair in the other order.
    """
    la, lb = best.labels(), other.labels()
    swapped = any(c in lb and lb[c][0] != v[0] for c, v in la.items())
    orders = set()
    for leg in set(best.legs) & set(other.legs):
        if set(best.legs[leg]) != set(other.legs[leg]):
            swapped = True
        elif best.legs[leg] != other.legs[leg]:
            orders.add(leg)
    return swapped, orders


def associate(
    rods: list[RodCandidate],
    legs_c: list[LegCandidate],
    nominal: I4Parameters,
    q: Array,
    radius: float,
    spacing: float,
    K: Array,
    settings: DetectSettings,
    prior: Rigid | None = None,
) -> tuple[list[Hypothesis], list[Hypothesis]]:
    """Accepted hypotheses (legs -> rod candidates, placement), best first, and the best's rivals.

    A rival labels the rods differently and explains them about as well (see :func:`_rivals`).
    """
    tops, u = _rod_model(nominal, q, spacing)
    if len(legs_c) < settings.min_legs:
        return [], []
    D = np.array([lc.d for lc in legs_c])
    cand_ang = np.arccos(np.clip(np.abs(D @ D.T), 0.0, 1.0))
    model_ang = np.arccos(np.clip(np.abs(u @ u.T), 0.0, 1.0))
    sig = np.array([np.hypot(lc.sigma, settings.model_direction_rad) for lc in legs_c])
    tol = settings.pair_angle_tol_rad + 3.0 * (sig[:, None] + sig[None, :])
    seeds = []
    for mp in _assignments(model_ang, cand_ang, len(legs_c), settings.min_legs, tol):
        legs = [lg for lg in range(4) if mp[lg] is not None]
        cand = [mp[lg] for lg in legs]
        # no two candidates may share a rod; one polarity for all rods
        used = [r for k in cand for r in legs_c[k].rods]
        if len(set(used)) != len(used) or len({rods[r].bright for r in used}) > 1:
            continue
        for signs in itertools.product((1.0, -1.0), repeat=len(legs)):
            R, res = _kabsch(u[legs], D[cand] * np.asarray(signs)[:, None], 1.0 / sig[cand] ** 2)
            if res > settings.kabsch_tol:
                continue
            if prior is not None and _rotation_angle(R, prior.R) > settings.prior_tol_rad:
                continue
            seeds.append((res, mp, R))
    fitter = _Fitter(rods, tops, u, radius, K)
    # every seed (and rod-order variant) gets its linear translation and a quick residual; the best
    # few of each leg count are refined
    quick: list[tuple[int, float, float, dict[int, tuple[int, int]], Array]] = []
    seen: set[tuple] = set()
    for res, mp, R in sorted(seeds, key=lambda x: x[0]):
        for lv in _rod_orders(mp, legs_c, rods, R[:, 0], fitter.Ki):
            key = (tuple(sorted(lv.items())), tuple(np.round(matrix_to_rotvec(R), 1)))
            if key in seen:
                continue
            seen.add(key)
            x0 = _initial(fitter, lv, R, radius)
            r0 = fitter.residuals(x0[None], *fitter.setup(lv))[0]
            quick.append((len(lv), float(np.sqrt(np.mean(r0**2))), res, lv, x0))
    hyps: list[Hypothesis] = []
    for n in sorted({qk[0] for qk in quick}, reverse=True):
        group = sorted((qk for qk in quick if qk[0] == n), key=lambda qk: qk[1])
        for _, _, res, lv, x0 in group[: settings.max_hypotheses]:
            h = _solve_placement(fitter, lv, x0, radius)
            if h is None or h.rms_px > settings.max_rms_px:
                continue
            if prior is not None and _rotation_angle(h.camera_from_base.R, prior.R) > settings.prior_tol_rad:
                continue
            h.kabsch_misfit = res
            hyps.append(h)
    hyps.sort(key=lambda h: (-len(h.legs), h.rms_px))
    uniq: list[Hypothesis] = []  # the same labels and about the same placement: one hypothesis
    for h in hyps:
        if any(h.legs == g.legs and _rotation_angle(h.camera_from_base.R, g.camera_from_base.R) < 0.05 for g in uniq):
            continue
        uniq.append(h)
    if not uniq:
        return [], []
    return uniq, _rivals(uniq, fitter, radius, settings)


def _rivals(hyps: list[Hypothesis], fitter: _Fitter, radius: float, settings: DetectSettings) -> list[Hypothesis]:
    """Hypotheses that label the rods differently and fit about as well as the best.

    "About as well": RMS <= ``ambiguity_ratio`` x the best's + ``ambiguity_px``. A rival with one
    leg fewer is compared with the best refitted on the legs they share (fewer legs fit better).
    """
    best = hyps[0]
    x_best = np.concatenate([matrix_to_rotvec(best.camera_from_base.R), best.camera_from_base.t])
    out = []
    for h in hyps[1:]:
        swapped, orders = _differences(best, h)
        if (not swapped and not orders) or len(h.legs) < len(best.legs) - 1:
            continue
        ref = best.rms_px
        shared = set(h.labels())
        common = {lg: pair for lg, pair in best.legs.items() if set(pair) <= shared}
        if 2 <= len(common) < len(best.legs):
            sub = _solve_placement(fitter, common, x_best, radius)
            if sub is not None:
                ref = sub.rms_px
        if h.rms_px <= settings.ambiguity_ratio * ref + settings.ambiguity_px:
            out.append(h)
    return out


def _rod_orders(
    mp: tuple[int | None, ...], legs_c: list[LegCandidate], rods: list[RodCandidate], xb: Array, K_inv: Array
) -> list[dict[int, tuple[int, int]]]:
    """Leg -> (rod0, rod1) candidates, rod0 on the -x_B side (both orders when it cannot be told).

    Rod j is on the +x_B side of rod i when the ray to j's image and x_B (camera frame) lie on the
    same side of i's axis plane: directions only, no depth needed.
    """
    legs: dict[int, tuple[int, int]] = {}
    unsure = []
    for lg in range(4):
        k = mp[lg]
        if k is None:
            continue
        i, j = legs_c[k].rods
        ray_j = K_inv @ np.append(0.5 * (rods[j].centre[0] + rods[j].centre[1]), 1.0)
        side_x = float(rods[i].m @ xb)
        side_j = float(rods[i].m @ (ray_j / np.linalg.norm(ray_j)))
        legs[lg] = (i, j) if side_x * side_j > 0 else (j, i)
        if abs(side_x) < 0.1:
            unsure.append(lg)
    variants = [legs]
    for lg in unsure:
        variants += [{**v, lg: v[lg][::-1]} for v in variants]
    return variants


def _initial(fitter: _Fitter, legs: dict[int, tuple[int, int]], R: Array, radius: float) -> Array:
    """Rotation vector and the linear translation: h . (R top + t) = r for every limb plane h."""
    tops, _, idx = fitter.setup(legs)
    H = fitter.h[idx].reshape(-1, 3)
    b = radius - np.einsum("mkj,mj->mk", fitter.h[idx], tops @ R.T).ravel()
    t, *_ = np.linalg.lstsq(H, b, rcond=None)
    return np.concatenate([matrix_to_rotvec(R), t])


def _solve_placement(fitter: _Fitter, legs: dict[int, tuple[int, int]], x0: Array, radius: float) -> Hypothesis | None:
    """Refine a placement on the assigned rods' limb lines; None when it puts a rod behind the camera."""
    tops, us, idx = fitter.setup(legs)
    x, r = _levenberg_marquardt(lambda X: fitter.residuals(X, tops, us, idx), x0, np.full(6, 1e-6))
    if not np.all(np.isfinite(r)):
        return None
    C = Rigid(rotvec_to_matrix(x[:3]), x[3:])
    _, d = fitter.predicted_planes(x[None], tops, us)
    if np.any(d <= radius):
        return None
    # the axis point seen at the middle of each rod's image must be in front of the camera
    P = tops @ C.R.T + C.t
    U = us @ C.R.T
    for k, ci in enumerate(idx):
        rc = fitter.rods[ci]
        ray = fitter.Ki @ np.append(0.5 * (rc.centre[0] + rc.centre[1]), 1.0)
        # closest points of the axis P + a U and of the ray b ray
        A2 = np.array([[U[k] @ U[k], -U[k] @ ray], [U[k] @ ray, -ray @ ray]])
        try:
            _, lam = np.linalg.solve(A2, np.array([-(P[k] @ U[k]), -(P[k] @ ray)]))
        except np.linalg.LinAlgError:
            return None
        if lam <= 0:
            return None
    return Hypothesis(legs, C, float(np.sqrt(np.mean(r**2))), 0.0)


# ---------------------------------------------------------------------------------------------
def detect_rods(
    image: np.ndarray,
    camera: CameraModel,
    nominal: I4Parameters,
    q: ArrayLike,
    rod_radius_m: float,
    rod_spacing_m: float | None,
    settings: DetectSettings | None = None,
    prior: Rigid | None = None,
) -> RodDetection:
    """Find the eight rods in one frame with no prior pose and associate them to the legs.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The (distorted) image, 8-bit or float, single channel (BGR is converted).
    camera : CameraModel
        Intrinsics (the detection works in its ideal pixels).
    nominal : I4Parameters
        The nominal geometry.
    q : array_like, shape (4,)
        Encoder values, metres.
    rod_radius_m, rod_spacing_m : float
        Rod radius and distance between the two rods of a leg (along x_B), metres.
    settings : DetectSettings, optional
    prior : Rigid, optional
        A coarse ``camera_from_base`` (bench mounting, other frames): hypotheses rotated more than
        ``settings.prior_tol_rad`` from it are dropped. Needed for near-symmetric poses.

    Returns
    -------
    RodDetection
        Priors for the rods of the associated legs (``predict_rods`` structure, None elsewhere),
        the fitted ``camera_from_base``, and the reasons for what was not found.
    """
    s = settings or DetectSettings()
    qv = np.asarray(q, dtype=np.float64).reshape(4)
    if not rod_spacing_m or rod_spacing_m <= 0:
        return _nothing("no rod detection: the rod spacing is not known (dataset legs.rod_spacing_m)")
    try:
        dkm(nominal, qv)
    except I4calError as exc:
        return _nothing(f"no rod detection: {exc}")
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    canvas, scale, origin, valid = undistorted_canvas(gray, camera)
    seg, con, ln = detect_segments(canvas, valid, scale, origin, s)
    # only lines long enough to bound a rod are refined and paired
    lines = [li for li in merge_segments(seg, con, ln, s) if li.s1 - li.s0 >= s.min_rod_px]
    lines = merge_lines(refine_lines(lines, canvas, scale, origin, s, np.random.default_rng(0)), s)
    rods = find_rods(lines, canvas, scale, origin, camera, rod_radius_m, s)
    legs_c = find_legs(rods, rod_radius_m, rod_spacing_m, s)
    counts = {"segments": len(seg), "lines": len(lines), "rod_candidates": len(rods), "leg_candidates": len(legs_c)}
    return _decide(rods, legs_c, counts, camera, nominal, qv, rod_radius_m, rod_spacing_m, s, prior)


def _nothing(reason: str, **kw) -> RodDetection:
    return RodDetection([None] * 8, {rod_name(lg, r): reason for lg, r in ROD_KEYS}, reason=reason, **kw)


def _decide(
    rods: list[RodCandidate],
    legs_c: list[LegCandidate],
    counts: dict[str, int],
    camera: CameraModel,
    nominal: I4Parameters,
    q: Array,
    radius: float,
    spacing: float,
    s: DetectSettings,
    prior: Rigid | None,
) -> RodDetection:
    kw = {"rods": rods, "leg_candidates": legs_c, "counts": counts}
    if len(legs_c) < s.min_legs:
        return _nothing(
            f"rods not detected: {len(legs_c)} rod pairs found ({len(rods)} rods), need {s.min_legs} legs", **kw
        )
    hyps, rivals = associate(rods, legs_c, nominal, q, radius, spacing, camera.K, s, prior)
    if not hyps:
        why = "within the placement prior and " if prior is not None else ""
        return _nothing(
            f"rods not associated: no assignment of the {len(legs_c)} rod pairs to the legs fits "
            f"{why}the nominal model within {s.max_rms_px:.0f} px",
            **kw,
        )
    best = hyps[0]
    unsure: dict[int, str] = {}
    for rival in rivals:
        swapped, orders = _differences(best, rival)
        if swapped:
            lab = rival.labels()
            mine = "-".join(str(lg + 1) for lg in sorted(best.legs))
            other = "-".join(
                str(lab[best.legs[lg][0]][0] + 1) if best.legs[lg][0] in lab else "?" for lg in sorted(best.legs)
            )
            reason = (
                f"ambiguous leg association: legs {mine} fit as well as {other} ({best.rms_px:.1f} px vs "
                f"{rival.rms_px:.1f} px); a near-symmetric pose needs a placement prior"
            )
            return RodDetection(
                [None] * 8,
                {rod_name(lg, r): reason for lg, r in ROD_KEYS},
                None,
                best.rms_px,
                True,
                hyps,
                reason=reason,
                **kw,
            )
        for lg in orders:
            unsure[lg] = (
                f"leg {lg + 1}: which of its two rods is which is ambiguous (both orders fit, "
                f"{best.rms_px:.1f} px vs {rival.rms_px:.1f} px)"
            )
    reasons: dict[str, str] = {}
    for leg, rod in ROD_KEYS:
        if leg not in best.legs or leg in unsure:
            reasons[rod_name(leg, rod)] = unsure.get(leg) or (
                f"leg {leg + 1} not detected: no rod pair in the image matches it (hidden or out of view)"
            )
    model = predict_rods(nominal, q, best.camera_from_base, spacing)
    dirs: list[Array | None] = [None] * 8
    for k, p in enumerate(model):
        if rod_name(p.leg, p.rod) not in reasons:
            lc = next(lc for lc in legs_c if set(lc.rods) == set(best.legs[p.leg]))
            dirs[k] = _leg_direction(lc, p.u, s.model_direction_rad)
    preds = _priors(rods, best, model, dirs, radius, np.ones(8))
    # a width read off a candidate with one wrong limb puts its prior at a wrong depth: each rod's
    # depth over the model's (the fitted placement's depth error is common to the frame) must agree
    # with the frame's median; the outliers are moved to the median ratio
    ratio = np.array(
        [
            _depth_ratio(p, m, rods[best.legs[m.leg][m.rod]], camera.K) if p is not None else np.nan
            for p, m in zip(preds, model, strict=True)
        ]
    )
    if np.sum(np.isfinite(ratio)) >= 4:
        med = float(np.nanmedian(ratio))
        off = np.isfinite(ratio) & (np.abs(ratio / med - 1.0) > s.depth_tolerance)
        if off.any():
            preds = _priors(rods, best, model, dirs, radius, np.where(off, med / ratio, 1.0))
    return RodDetection(preds, reasons, best.camera_from_base, best.rms_px, False, hyps, dirs, **kw)


def _priors(
    rods: list[RodCandidate],
    best: Hypothesis,
    model: list[RodPrediction],
    dirs: list[Array | None],
    radius: float,
    depth_scale: Array,
) -> list[RodPrediction | None]:
    """The associated rods' priors (None where ``dirs`` is None), in ``ROD_KEYS`` order."""
    preds: list[RodPrediction | None] = []
    for k, p in enumerate(model):
        d = dirs[k]
        if d is None:
            preds.append(None)
            continue
        rc = rods[best.legs[p.leg][p.rod]]
        p0 = preds[k - 1] if p.rod == 1 else None
        if p0 is not None:
            # rod 1 beside rod 0's prior: the leg's two priors stay one rod spacing apart
            m0 = model[k - 1]
            p = RodPrediction(p.leg, 1, p0.top + (p.top - m0.top), p0.bottom + (p.bottom - m0.bottom))
        preds.append(_prior_from_candidate(rc, d, p, radius, float(depth_scale[k])))
    return preds


def _depth_ratio(prior: RodPrediction, model: RodPrediction, rc: RodCandidate, K: Array) -> float:
    """Depth of the prior's axis over the model's, where the ray through the rod's image middle meets them."""
    ray = np.linalg.solve(K, np.append(0.5 * (rc.centre[0] + rc.centre[1]), 1.0))
    ray = ray / np.linalg.norm(ray)

    def along(a: Array, u: Array) -> float:
        A2 = np.array([[u @ u, -u @ ray], [u @ ray, -1.0]])
        try:
            return float(np.linalg.solve(A2, np.array([-(a @ u), -(a @ ray)]))[1])
        except np.linalg.LinAlgError:
            return float("nan")

    zp, zm = along(prior.top, prior.u), along(model.top, model.u)
    return zp / zm if zm > 0 and zp > 0 else float("nan")


def _leg_direction(lc: LegCandidate, u_model: Array, sigma_model: float) -> Array:
    """A leg's direction (camera frame, oriented like ``u_model``): the image's, weighted with the model's.

    The image gives it as the intersection of the two rods' axis planes, ill-conditioned when they
    are nearly the same plane (the leg seen edge-on, ``lc.sigma`` large) and wrong when a limb of
    either rod is; the nominal model at the fitted placement gives ``u_model`` to ``sigma_model``.
    Inverse-variance mean of the two; the model's alone when they disagree by more than 3 sigma.
    """
    d = lc.d if lc.d @ u_model >= 0 else -lc.d
    if np.arccos(np.clip(d @ u_model, -1.0, 1.0)) > 3.0 * np.hypot(lc.sigma, sigma_model):
        return u_model
    v = d / lc.sigma**2 + u_model / sigma_model**2
    return v / np.linalg.norm(v)


def _prior_from_candidate(
    rc: RodCandidate, d: Array, model: RodPrediction, radius: float, depth_scale: float = 1.0
) -> RodPrediction:
    """The rod's prior for measure_rod: its detected axis, over the model's extent.

    The axis lies in the candidate's axis plane (through the camera centre, bisecting its limb
    planes), along the leg's detected direction ``d`` projected into that plane (the two rods of a
    leg stay parallel), at the depth where both limb planes are tangent to a cylinder of the rod's
    radius (times ``depth_scale``, which moves the axis along the rays: same image, other width):
    its image is the detected rod to a pixel or so. The nominal model, centimetres off, only gives
    the extent: the end points are the points of the axis nearest to ``model``'s (oriented actuator
    to plate like ``d``). Falls back to ``model`` when the planes are degenerate.
    """
    u = d - (d @ rc.m) * rc.m
    n = float(np.linalg.norm(u))
    if n < 1e-9:
        return model
    u = u / n
    try:
        X = depth_scale * np.linalg.solve(np.vstack([rc.h[0], rc.h[1], u]), np.array([radius, radius, 0.0]))
    except np.linalg.LinAlgError:
        return model
    top = X + ((model.top - X) @ u) * u
    bottom = X + ((model.bottom - X) @ u) * u
    return RodPrediction(model.leg, model.rod, top, bottom)


def resolve(
    detection: RodDetection,
    camera: CameraModel,
    nominal: I4Parameters,
    q: ArrayLike,
    rod_radius_m: float,
    rod_spacing_m: float,
    prior: Rigid,
    settings: DetectSettings | None = None,
) -> RodDetection:
    """Associate a detection's rod candidates again, keeping only placements near ``prior``.

    For a frame that was ambiguous alone, once other frames (or the bench's mounting) fix the
    placement; the image is not read again.
    """
    s = settings or DetectSettings()
    return _decide(
        detection.rods,
        detection.leg_candidates,
        detection.counts,
        camera,
        nominal,
        np.asarray(q, dtype=np.float64).reshape(4),
        rod_radius_m,
        rod_spacing_m,
        s,
        prior,
    )


def consensus_placement(placements: Sequence[Rigid], tol_rad: float = 0.1) -> Rigid | None:
    """The placement most frames agree on: the largest group within ``tol_rad`` of one of them.

    Its rotation is the chordal mean of the group's, its translation the median. None when there
    are no placements or when another, disjoint group is as large (frames disagree).
    """
    if not placements:
        return None
    Rs = [p.R for p in placements]
    groups = [[j for j in range(len(Rs)) if _rotation_angle(Rs[i], Rs[j]) <= tol_rad] for i in range(len(Rs))]
    best = max(groups, key=len)
    if any(len(g) == len(best) and not set(g) & set(best) for g in groups):
        return None
    U, _, Vt = np.linalg.svd(np.mean([Rs[j] for j in best], axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return Rigid(R, np.median([placements[j].t for j in best], axis=0))


def resolve_frames(
    detections: Mapping[int, RodDetection],
    camera: CameraModel,
    nominal: I4Parameters,
    q: Mapping[int, ArrayLike],
    rod_radius_m: float,
    rod_spacing_m: float,
    prior: Rigid | None = None,
    settings: DetectSettings | None = None,
) -> tuple[dict[int, RodDetection], Rigid | None, str]:
    """Frames of one camera: frames that were ambiguous alone are associated again near the placement
    that the unambiguous frames agree on (or near ``prior`` when given).

    Parameters
    ----------
    detections : mapping frame -> RodDetection
        From :func:`detect_rods` (with ``prior`` when there is one).
    q : mapping frame -> array_like, shape (4,)
        Encoder values.

    Returns
    -------
    detections : dict frame -> RodDetection
    placement : Rigid or None
        The consensus ``camera_from_base`` (coarse) of the associated frames.
    source : str
        ``"prior"``, ``"consensus of N frames"`` (the frames associated alone) or ``"none"``.
    """
    s = settings or DetectSettings()
    solved = [d.camera_from_base for d in detections.values() if d.camera_from_base is not None]
    anchor = prior if prior is not None else consensus_placement(solved, s.prior_tol_rad / 2)
    n = len(solved)
    source = "prior" if prior is not None else (f"consensus of {n} frame{'s' if n != 1 else ''}" if anchor else "none")
    out = dict(detections)
    if anchor is not None and prior is None:  # (with a prior the detections already used it)
        for i, d in detections.items():
            if d.ambiguous:
                out[i] = resolve(d, camera, nominal, q[i], rod_radius_m, rod_spacing_m, anchor, s)
    placed = consensus_placement(
        [d.camera_from_base for d in out.values() if d.camera_from_base is not None], s.prior_tol_rad / 2
    )
    return out, placed, source


def measure_detected(
    gray: np.ndarray,
    camera: CameraModel,
    detection: RodDetection,
    radius: float,
    settings: RodSettings | None = None,
    occluders: list[Array] | None = None,
    seed: int = 0,
    ideal_bbox: Array | None = None,
) -> list[RodMeasurement]:
    """Measure the rods a detection found (:func:`calib.vision.rods.measure_rods`), the others missing.

    Returns eight measurements in ``ROD_KEYS`` order.
    """
    found = [p for p in detection.predictions if p is not None]
    meas = (
        {(m.leg, m.rod): m for m in measure_rods(gray, camera, found, radius, settings, occluders, seed, ideal_bbox)}
        if found
        else {}
    )
    out = []
    for leg, rod in ROD_KEYS:
        m = meas.get((leg, rod))
        if m is None:
            m = RodMeasurement(leg, rod, reason=detection.reasons.get(rod_name(leg, rod), "not detected"))
        out.append(m)
    return out
