"""Line fitting for the limbs: (weighted, median-robust) total least squares, 2-point RANSAC then reweighted TLS."""

from __future__ import annotations

import math
from typing import NamedTuple, cast

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
    cc = c[:, None]
    for b in range(0, len(pts), step):
        q = pts[b : b + step]
        r = np.multiply.outer(nx, q[:, 0])  # (K, n): lines along the rows, each row's points contiguous
        r += np.multiply.outer(ny, q[:, 1])
        r += cc
        counts += np.add.reduce(np.abs(r, out=r) < inlier_px, axis=1, dtype=np.intp)
    return counts


#: RANSAC's confidence: the scoring of the drawn candidate lines stops once, with this probability, at least one of
#: the candidates scored came from two inliers, the inlier share being that of the best line so far (the standard
#: termination rule: candidates needed = log(1 - p) / log(1 - w^2)); 1.0 scores every drawn candidate
RANSAC_CONFIDENCE = 0.999
#: candidate lines scored at a time, after the first ``_MIN_SCORED``, before the termination rule is checked again
_SCORE_STEP = 16
#: candidates scored at least (in one block), whatever the best inlier share: on a bowed limb (edges ~1.5 px off a
#: line at its ends) many lines fit nearly as well, the counts are flat near their best and the refinement's result
#: depends on which near-best start it is given; with 48, the 2708 limb fits of an extraction of the rendered
#: dataset (``i4cal simulate --images --seed 0``) are those of the full scoring bit for bit (with 32, one is not)
_MIN_SCORED = 48


class RansacStart(NamedTuple):
    """The best RANSAC candidate line of :func:`ransac_start`."""

    line: tuple[float, float, float] | None
    """``(a, b, c)`` of ``a x + b y + c = 0``, unit normal, ``c`` in px; None when no two distinct points."""
    n_inliers: int
    """Points within the inlier distance of ``line`` (-1 when no line)."""
    scored: int
    """Candidate lines scored before the termination rule stopped the scoring."""
    drawn: int
    """Candidate lines drawn (the pairs of two distinct points among the ``iters`` drawn)."""


def candidates_needed(share: float, confidence: float) -> float:
    """Candidates to score so that, with probability ``confidence``, one came from two inliers.

    Parameters
    ----------
    share : float
        Inlier share w of the points, in [0, 1].
    confidence : float
        Probability p, in [0, 1]; 1.0 needs every candidate (``inf``).

    Returns
    -------
    float
        ``log(1 - p) / log(1 - w^2)``, 0 when w = 1, ``inf`` when w = 0 or p = 1.
    """
    w2 = share * share
    if confidence >= 1.0 or w2 <= 0.0:
        return math.inf
    if w2 >= 1.0:
        return 0.0
    return math.log1p(-confidence) / math.log1p(-w2)


def draw_pairs(n: int, rng: np.random.Generator, iters: int) -> NDArray[np.int64] | None:
    """The point pairs :func:`ransac_start` draws for ``n`` points: ``rng.integers(0, n, size=(iters, 2))``, or
    None (nothing drawn) when n < 2.

    Parameters
    ----------
    n : int
        Number of points.
    rng : numpy.random.Generator
        The generator drawn from.
    iters : int
        Pairs drawn.

    Returns
    -------
    ndarray of int, shape (iters, 2), or None
        Point indices.
    """
    return rng.integers(0, n, size=(iters, 2)) if n >= 2 else None


def _candidates(pts: Array, i: NDArray[np.int64]) -> tuple[Array, Array, Array]:
    """The candidate lines ``nx x + ny y + c = 0`` (each (K,), unit normal, c in px) through the drawn pairs ``i``
    (iters, 2) of points (N, 2) (px), pairs of one point or of two points at the same place dropped."""
    i = i[i[:, 0] != i[:, 1]]
    p = pts[i[:, 0]]
    d = pts[i[:, 1]] - p
    ln = np.hypot(d[:, 0], d[:, 1])
    good = ln > 1e-9
    if not good.all():  # (two points at the same place: no line)
        p, d, ln = p[good], d[good], ln[good]
    nx, ny = -d[:, 1] / ln, d[:, 0] / ln
    return nx, ny, -(nx * p[:, 0] + ny * p[:, 1])


def ransac_start(
    pts: Array, rng: np.random.Generator, iters: int, inlier_px: float, confidence: float = RANSAC_CONFIDENCE
) -> RansacStart:
    """The 2-point RANSAC line with the most inliers, scored in blocks until the termination rule is met.

    All ``iters`` pairs are drawn up front (:func:`draw_pairs`: the generator's consumption does not depend on when
    the scoring stops); the first ``_MIN_SCORED`` candidates are scored, then ``_SCORE_STEP`` at a time until
    :func:`candidates_needed` for the best inlier share so far are scored (the standard RANSAC termination rule),
    ``iters`` at most. Ties go to the first candidate drawn, so with ``confidence=1.0`` the result is that of scoring
    every candidate at once.

    Parameters
    ----------
    pts : ndarray, shape (N, 2)
        Points (px).
    rng : numpy.random.Generator
        Draws the pairs: ``rng.integers(0, N, size=(iters, 2))`` when N >= 2, nothing otherwise.
    iters : int
        Pairs drawn (the most candidates scored).
    inlier_px : float
        Inlier distance (px).
    confidence : float
        RANSAC confidence p (:data:`RANSAC_CONFIDENCE`).

    Returns
    -------
    RansacStart
    """
    n = len(pts)
    i = draw_pairs(n, rng, iters)
    if i is None:
        return RansacStart(None, -1, 0, 0)
    nx, ny, c = _candidates(pts, i)
    best_k, best_count, scored = -1, -1, 0
    while scored < c.size:
        end = min(scored + (_SCORE_STEP if scored else _MIN_SCORED), c.size)
        counts = _inlier_counts(pts, nx[scored:end], ny[scored:end], c[scored:end], inlier_px)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_k, best_count = scored + k, int(counts[k])
        scored = end
        if scored >= max(_MIN_SCORED, candidates_needed(best_count / n, confidence)):
            break
    if best_k < 0:
        return RansacStart(None, -1, 0, 0)
    return RansacStart((float(nx[best_k]), float(ny[best_k]), float(c[best_k])), best_count, scored, int(c.size))


def refine_lines(
    pts: list[Array], starts: list[RansacStart], inlier_px: float
) -> list[tuple[Array, NDArray[np.bool_]]]:
    """:func:`refine_line` of several point sets at once, each from its RANSAC start: the same lines and inliers,
    bit for bit.

    The residuals of all sets come from one stacked product (each set's the matrix-vector product
    :func:`refine_line` computes), the medians, cuts and weights from array operations over all sets; each set's
    moments are its own product, as in :func:`_tls_q`.

    Parameters
    ----------
    pts : list of ndarray, shape (N_l, 2)
        Edge points (px).
    starts : list of RansacStart
        Each set's RANSAC start (:func:`ransac_start`).
    inlier_px : float
        RANSAC inlier distance (px).

    Returns
    -------
    list of (line (3,), inliers (N_l,) bool)
        As :func:`robust_line`'s.
    """
    out: list[tuple[Array, NDArray[np.bool_]]] = [
        (np.array([np.nan, np.nan, np.nan]), np.zeros(len(p), dtype=bool)) for p in pts
    ]
    use = [j for j, st in enumerate(starts) if st.line is not None and st.n_inliers >= 2]
    if not use:
        return out
    fit = _SetFit([pts[j] for j in use])
    abc = fit.padded(np.array([cast("tuple[float, float, float]", starts[j].line) for j in use]))
    # the start in centred coordinates: c0 + a o_x + b o_y
    abc[: fit.sets, 2] = abc[: fit.sets, 2] + abc[: fit.sets, 0] * fit.o[:, 0] + abc[: fit.sets, 1] * fit.o[:, 1]
    inl = (np.abs(fit.residuals(abc)) < inlier_px) & fit.valid
    abc = fit.tls(abc, inl)
    active = fit.valid.any(axis=0)
    for _ in range(4):
        r = fit.residuals(abc)
        cut = 4.685 * np.maximum(1.4826 * _column_medians(np.abs(r), inl), 0.05)
        t = r / cut
        keep = (np.abs(t) < 1.0) & fit.valid
        active &= np.count_nonzero(keep, axis=0) >= 2  # a set whose weights vanish keeps its line from then on
        if not active.any():
            break
        t *= t
        np.subtract(1.0, t, out=t)
        t *= t  # Tukey's biweight (1 - (r / cut)^2)^2, 0 beyond the cut
        t *= keep
        abc = fit.tls(abc, None, t, active)
    r = np.abs(fit.residuals(abc))
    near = (r < 3 * inlier_px) & fit.valid
    cut = np.where(near.any(axis=0), 3.0 * 1.4826 * _column_medians(r, near), inlier_px)
    inl = (r < np.maximum(cut, 0.3)) & fit.valid
    abc = fit.tls(abc, inl, None, np.count_nonzero(inl, axis=0) >= 2)
    for k, j in enumerate(use):
        a, b, c0 = abc[k].tolist()
        line = np.array([a, b, c0 - (a * float(fit.o[k, 0]) + b * float(fit.o[k, 1]))])
        out[j] = (line, inl[: len(pts[j]), k].copy())
    return out


class _SetFit:
    """Point sets (N_l, 2) (px) laid out for :func:`refine_lines`: each centred on its mean, ``o`` (L, 2), as
    :func:`refine_line` centres it (``q`` its homogeneous centred points (N_l, 3)); ``stack`` (L', N, 3) the same
    points padded with zeros to the largest set (L' = max(L, 2) sets), ``valid`` (N, L') which entries are points."""

    def __init__(self, pts: list[Array]) -> None:
        size = [len(p) for p in pts]
        self.sets = len(pts)
        self.o = np.array([p.sum(0) / len(p) for p in pts])
        self.q = []
        self.stack = np.zeros((max(self.sets, 2), max(size), 3))
        for j, p in enumerate(pts):
            q = np.ones((len(p), 3))
            q[:, :2] = p - self.o[j]
            self.q.append(q)
            self.stack[j, : len(p)] = q
        self.valid = np.arange(max(size))[:, None] < np.array(size + [0] * (len(self.stack) - self.sets))

    def padded(self, abc: Array) -> Array:
        """Lines (L, 3) with rows of (0, 1, 0) up to L'."""
        out = np.tile([0.0, 1.0, 0.0], (len(self.stack), 1))
        out[: len(abc)] = abc
        return out

    def residuals(self, abc: Array) -> Array:
        """Each point's residual (N, L') against its set's line ``a x + b y + c = 0`` (abc (L', 3), centred px): each
        set's product ``q @ (a, b, c)``, stacked (padding rows 0 + c)."""
        return np.matmul(self.stack, abc[:, :, None])[..., 0].T

    def tls(
        self,
        abc: Array,
        member: NDArray[np.bool_] | None,
        w: Array | None = None,
        which: NDArray[np.bool_] | None = None,
    ) -> Array:
        """:func:`_tls_q` of each set (those of ``which`` (L',), all by default): of its ``member`` points (N, L'),
        or of all its points with weights ``w`` (N, L'); the other sets keep their line of ``abc`` (L', 3)."""
        out = abc.copy()
        for j, q in enumerate(self.q):
            if which is not None and not which[j]:
                continue
            n = len(q)
            out[j] = _tls_q(q[member[:n, j]]) if member is not None else _tls_q(q, cast("Array", w)[:n, j])
        return out


def _column_medians(v: Array, member: NDArray[np.bool_]) -> Array:
    """The median (``np.median``'s number) of each column of ``v`` (N, L') over its ``member`` entries, shape (L',)
    (a column without members: inf)."""
    m = np.add.reduce(member, axis=0, dtype=np.intp)
    srt = np.sort(np.where(member, v, np.inf).T, axis=1)  # (L', N): each column's values sorted
    h = m // 2
    cols = np.arange(v.shape[1])
    hi = srt[cols, np.minimum(h, v.shape[0] - 1)]
    lo = srt[cols, np.maximum(h - 1, 0)]
    return np.where(m % 2 == 1, hi, (lo + hi) / 2)


def robust_line(
    pts: Array, rng: np.random.Generator, iters: int, inlier_px: float, confidence: float = RANSAC_CONFIDENCE
) -> tuple[Array, NDArray[np.bool_]]:
    """RANSAC (:func:`ransac_start`) then IRLS (Tukey) total-least-squares line with a final 3-sigma rejection.

    Parameters
    ----------
    pts : ndarray, shape (N, 2)
        Edge points (px).
    rng : numpy.random.Generator
        Draws the RANSAC pairs.
    iters : int
        RANSAC draws (the most candidates scored).
    inlier_px : float
        RANSAC inlier distance (px).
    confidence : float
        RANSAC confidence of the adaptive stop (:data:`RANSAC_CONFIDENCE`); 1.0 scores every draw.

    Returns
    -------
    line : ndarray, shape (3,)
        ``(a, b, c)`` with ``a x + b y + c = 0`` and unit normal ``(a, b)`` (``c`` in px); NaN when fewer than
        two points agree.
    inliers : ndarray of bool, shape (N,)
    """
    return refine_line(pts, ransac_start(pts, rng, iters, inlier_px, confidence), inlier_px)


def refine_line(pts: Array, start: RansacStart, inlier_px: float) -> tuple[Array, NDArray[np.bool_]]:
    """:func:`robust_line` from its RANSAC start: IRLS (Tukey) total least squares, then the final 3-sigma cut.

    :func:`refine_lines` gives the same numbers for many sets at once; one set alone is cheaper here (150 against
    250 us: the rods' detection from scratch fits many small sets one by one).

    Parameters
    ----------
    pts : ndarray, shape (N, 2)
        Edge points (px).
    start : RansacStart
        The RANSAC start (:func:`ransac_start`).
    inlier_px : float
        RANSAC inlier distance (px).

    Returns
    -------
    line : ndarray, shape (3,)
        As :func:`robust_line`'s.
    inliers : ndarray of bool, shape (N,)
    """
    n = len(pts)
    best, best_count = start.line, start.n_inliers
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
