"""Line fitting for the limbs: (weighted, median-robust) total least squares, 2-point RANSAC then reweighted TLS."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
def _tls(q: Array, w: Array | None = None) -> tuple[float, float, float]:
    """Total least squares line of points ``q`` (N, 2) with optional weights ``w`` (N,): the normal (a, b),
    a^2 + b^2 = 1, and c, as three floats for the inner loops. The normal is the minor axis of the (weighted) scatter
    matrix, in closed form for 2x2."""
    if w is None:
        m = q.sum(0) / q.shape[0]
        d = q - m
        S = d.T @ d
    else:
        m = (w @ q) / w.sum()
        d = q - m
        S = (d * w[:, None]).T @ d
    theta = 0.5 * math.atan2(2.0 * float(S[0, 1]), float(S[0, 0] - S[1, 1]))  # major axis angle
    a, b = -math.sin(theta), math.cos(theta)
    return a, b, -(a * float(m[0]) + b * float(m[1]))


def _median(x: Array) -> float:
    """``np.median`` of a non-empty 1-D array, without its overhead."""
    h = x.size // 2
    if x.size % 2:
        return float(np.partition(x, h)[h])
    p = np.partition(x, (h - 1, h))
    return float((p[h - 1] + p[h]) / 2)


def _tls_q(Q: Array, w: Array | None = None) -> tuple[float, float, float]:
    """:func:`_tls` from homogeneous points Q (N, 3) = [x, y, 1] (centred near 0) and optional weights (N,).

    The weighted moments come from one matrix product; the points being centred, removing the mean from them
    costs no precision.
    """
    M = (Q.T @ Q if w is None else (Q * w[:, None]).T @ Q).tolist()  # the moments as floats: same arithmetic, faster
    s0 = M[2][2]
    mx, my = M[0][2] / s0, M[1][2] / s0
    sxx = M[0][0] - s0 * mx * mx
    syy = M[1][1] - s0 * my * my
    sxy = M[0][1] - s0 * mx * my
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    a, b = -math.sin(theta), math.cos(theta)
    return a, b, -(a * mx + b * my)


#: residuals per block of :func:`_inlier_counts`: its (points, draws) float64 temporaries stay below the allocator's
#: threshold for fresh pages from the system (128 kB), which a temporary of every draw and point of a limb crosses
_BLOCK = 12000


def _inlier_counts(pts: Array, nx: Array, ny: Array, c: Array, inlier_px: float) -> NDArray[np.intp]:
    """For each RANSAC line ``nx x + ny y + c = 0`` (K,), how many points (N, 2) lie within ``inlier_px`` of it.

    The residuals ``x nx + y ny + c`` are the same numbers however the points are blocked.
    """
    counts = np.zeros(c.size, dtype=np.intp)
    step = max(8, _BLOCK // max(c.size, 1))
    for b in range(0, len(pts), step):
        q = pts[b : b + step]
        r = np.multiply.outer(q[:, 0], nx)
        r += np.multiply.outer(q[:, 1], ny)
        r += c
        counts += np.count_nonzero(np.abs(r, out=r) < inlier_px, axis=0)
    return counts


def robust_line(pts: Array, rng: np.random.Generator, iters: int, inlier_px: float) -> tuple[Array, NDArray[np.bool_]]:
    """RANSAC then IRLS (Tukey) total-least-squares line with a final 3-sigma rejection.

    Parameters
    ----------
    pts : ndarray, shape (N, 2)
        Edge points (px).
    rng : numpy.random.Generator
        Draws the RANSAC pairs.
    iters : int
        RANSAC draws.
    inlier_px : float
        RANSAC inlier distance (px).

    Returns
    -------
    line : ndarray, shape (3,)
        ``(a, b, c)`` with ``a x + b y + c = 0`` and unit normal ``(a, b)`` (``c`` in px); NaN when fewer than
        two points agree.
    inliers : ndarray of bool, shape (N,)
    """
    n = len(pts)
    best = None
    best_count = -1
    if n >= 2:
        i = rng.integers(0, n, size=(iters, 2))
        i = i[i[:, 0] != i[:, 1]]
        p = pts[i[:, 0]]
        d = pts[i[:, 1]] - p
        ln = np.hypot(d[:, 0], d[:, 1])
        good = ln > 1e-9
        if not good.all():  # (two points at the same place: no line)
            p, d, ln = p[good], d[good], ln[good]
        nx, ny = -d[:, 1] / ln, d[:, 0] / ln
        c = -(nx * p[:, 0] + ny * p[:, 1])
        if c.size:
            counts = _inlier_counts(pts, nx, ny, c, inlier_px)
            k = int(np.argmax(counts))
            best_count = int(counts[k])
            best = (float(nx[k]), float(ny[k]), float(c[k]))
    if best is None or best_count < 2:
        return np.array([np.nan, np.nan, np.nan]), np.zeros(n, dtype=bool)
    # the fits in coordinates centred on the points (better conditioned, same lines)
    o = pts.sum(0) / n
    Q = np.ones((n, 3))
    Q[:, :2] = pts - o
    a, b, c0 = best
    inl = np.abs(Q @ np.array([a, b, c0 + a * float(o[0]) + b * float(o[1])])) < inlier_px
    a, b, c0 = _tls_q(Q[inl])
    for _ in range(4):
        r = Q @ np.array([a, b, c0])
        cut = 4.685 * max(1.4826 * _median(np.abs(r[inl])), 0.05)
        t = r / cut
        keep = np.abs(t) < 1.0
        if np.count_nonzero(keep) < 2:
            break
        t *= t
        np.subtract(1.0, t, out=t)
        t *= t  # Tukey's biweight (1 - (r / cut)^2)^2, 0 beyond the cut
        t *= keep
        a, b, c0 = _tls_q(Q, t)
    r = np.abs(Q @ np.array([a, b, c0]))
    near = r < 3 * inlier_px
    inl = r < max(3.0 * 1.4826 * _median(r[near]) if near.any() else inlier_px, 0.3)
    if np.count_nonzero(inl) >= 2:
        a, b, c0 = _tls_q(Q[inl])
    return np.array([a, b, c0 - (a * float(o[0]) + b * float(o[1]))]), inl
