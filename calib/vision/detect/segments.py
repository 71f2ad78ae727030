"""Detection steps 1-2: the undistorted canvas, line segments (LSD) and their collinear merge, sub-pixel re-
measurement.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.formats.camera import CameraModel
from calib.vision.detect.hypotheses import DetectSettings, Line2
from calib.vision.detect.rays import _sample, _to_canvas
from calib.vision.rods import image_ideal_bbox, robust_line

Array = NDArray[np.float64]


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

    Parameters
    ----------
    gray : ndarray, shape (H, W)
        The (distorted) image, single channel.
    camera : CameraModel
        Its intrinsics (px) and distortion.

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


def detect_segments(
    canvas: np.ndarray, valid: np.ndarray, scale: float, origin: Array, settings: DetectSettings
) -> tuple[Array, Array, Array]:
    """LSD segments in ideal pixels with their polarity.

    Parameters
    ----------
    canvas : ndarray, shape (h, w), float32
        The undistorted image (:func:`undistorted_canvas`).
    valid : ndarray of bool, shape (h, w)
        Canvas pixels that see the image; segments outside are dropped.
    scale : float
        Canvas pixels per ideal pixel.
    origin : ndarray, shape (2,)
        Ideal pixel of canvas (0, 0) (px).
    settings : DetectSettings
        Thresholds of the detection.

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
    """Merge collinear segments of the same polarity into lines (ideal px).

    Parameters
    ----------
    seg : ndarray, shape (N, 2, 2)
        Segment end points (ideal px), brighter side on the left (:func:`detect_segments`).
    contrast : ndarray, shape (N,)
        Grey-level difference across each segment.
    length : ndarray, shape (N,)
        Segment lengths (ideal px).
    settings : DetectSettings
        Angle, offset and gap tolerances of a merge.

    Returns
    -------
    list of Line2
        The merged lines (ideal px).
    """
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

    Parameters
    ----------
    lines : list of Line2
        Merged LSD lines (ideal px).
    canvas : ndarray, shape (h, w), float32
        The undistorted image (:func:`undistorted_canvas`).
    scale : float
        Canvas pixels per ideal pixel.
    origin : ndarray, shape (2,)
        Ideal pixel of canvas (0, 0) (px).
    settings : DetectSettings
        Profile step and band, minimum edge count, RANSAC settings.
    rng : numpy.random.Generator
        Random sampling of the RANSAC fits.

    Returns
    -------
    list of Line2
        The refined lines (ideal px), those with too few edge points dropped.
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

    Parameters
    ----------
    lines : list of Line2
        Refined lines (ideal px).
    settings : DetectSettings
        Angle, offset and gap tolerances of a merge.

    Returns
    -------
    list of Line2
        The joined lines (ideal px).
    """
    if len(lines) < 2:
        return lines
    seg = np.array([[ln.point(ln.s0), ln.point(ln.s1)] for ln in lines])
    con = np.array([ln.contrast for ln in lines])
    length = np.array([ln.s1 - ln.s0 for ln in lines])
    merged = merge_segments(seg, con, length, settings)
    return merged if len(merged) < len(lines) else lines
