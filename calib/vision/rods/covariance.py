"""The measured axis direction's covariance: each limb line's covariance with its edges' serial correlation, propagated
through the two interpretation planes, with the edge-bias allowance.

The allowance is a slowly varying edge bias (sampling phase, shading, background) with a correlation length along the
limb (``RodSettings.edge_bias_length_px``): over a visible span longer than that length it averages, and both its
angle and offset variances fall as ``length / span`` (:func:`edge_bias_factor`), as those of a fitted line's do under
a bias process of finite correlation length. A constant allowance, independent of the span, would over-cover long
rods and under-cover short ones; with this one the rods' errors over their ``cov_u`` stay about even across spans.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def _line_cov(pts: Array, line: Array, max_lag: int = 12) -> tuple[Array, Array, float]:
    """Centroid, direction and the effective residual variance of a TLS line through points (N, 2).

    Returns (centroid (2,), unit direction (2,), s2 in px^2); the line's normal angle then has
    variance ``s2 / sum(t^2)`` and its offset at the centroid ``s2 / N``. Edge errors of neighbouring
    profiles are correlated (background texture and shading vary slowly along a limb), so ``s2`` is
    the residual variance times the long-run factor ``1 + 2 sum_k w_k rho_k`` (autocorrelation of the
    residuals ordered along the line, Bartlett weights, lags up to ``max_lag``), floored at 1.
    """
    c, t_dir, s2, _t = _line_stats(pts, line, pts @ line[:2] + line[2], max_lag)
    return c, t_dir, s2


def _line_stats(pts: Array, line: Array, r: Array, max_lag: int = 12) -> tuple[Array, Array, float, Array]:
    """:func:`_line_cov` given the points' residuals ``r`` (N,) (``pts @ line[:2] + line[2]``), and the points'
    positions along the line about the centroid (N,) (px), which the covariance and the limb samples read too."""
    n = len(r)
    c = np.add.reduce(pts, axis=0) / n  # pts.mean(0)
    t_dir = np.array([line[1], -line[0]])
    s2 = float(r @ r) / max(n - 2, 1)
    t = (pts - c) @ t_dir
    rr = r[np.argsort(t)]
    rr = rr - np.add.reduce(rr) / n
    v0 = float(rr @ rr)
    factor = 1.0
    if v0 > 0:
        L = min(max_lag, n // 4)
        for k in range(1, L + 1):
            factor += 2.0 * (1.0 - k / (L + 1)) * float(rr[:-k] @ rr[k:]) / v0
    return c, t_dir, s2 * max(factor, 1.0), t


def edge_bias_factor(span_px: Array | float, length_px: float) -> Array:
    """The edge-bias allowance's variance factor for a limb of visible span ``span_px`` (px): ``min(1, length_px /
    span)``, the part of a bias of correlation length ``length_px`` left after a line fit over the span averages it;
    1 (no averaging: a linear trend end to end whatever the span) when ``length_px`` is 0.

    Parameters
    ----------
    span_px : float or ndarray, shape (N,)
        Visible span of each limb (px); spans under 1 px count as 1 px.
    length_px : float
        Correlation length of the edge bias along the limb (px), finite and >= 0.

    Returns
    -------
    ndarray, shape of ``span_px``
        The factor (dimensionless, in (0, 1]).

    Raises
    ------
    ValueError
        ``length_px`` is negative or not finite.
    """
    span = np.maximum(np.asarray(span_px, dtype=np.float64), 1.0)
    if length_px < 0 or not np.isfinite(length_px):
        raise ValueError(f"edge_bias_length_px must be finite and >= 0, got {length_px}")
    return np.ones_like(span) if length_px == 0 else np.minimum(1.0, length_px / span)


def _direction_covariance(
    K: Array,
    fits: list[tuple[Array, Array, float, Array]],
    inner: Array,
    edge_bias_px: float = 0.0,
    edge_bias_length_px: float = 0.0,
) -> Array:
    """Covariance (3, 3) of the axis direction from the two limb fits' line uncertainties.

    Each fit is (centroid, unit direction, sigma^2, points); the line is perturbed by a rotation about
    its centroid (variance sigma^2 / sum t^2) and a shift along its normal (variance sigma^2 / N),
    propagated to ``u = normalize(h1 x h2)`` by central differences. ``edge_bias_px`` adds a slowly
    varying edge bias (sampling phase, shading, background) as a random linear trend along each limb
    whose end-to-end difference has that standard deviation (angle variance ``(b / span)^2``, offset
    variance ``(b / 2)^2``), both times :func:`edge_bias_factor` of the limb's span and ``edge_bias_length_px`` (0: no
    averaging). The depth component of u is
    ~1/(plane angle) times less precise than its image component: the covariance is strongly
    anisotropic, which the combined method's GLS weighting uses.
    """
    ts = [[(pts - c) @ td for c, td, _s2, pts in fits]]
    return _direction_covariance_sets(K, [fits], np.asarray(inner)[None], edge_bias_px, (edge_bias_length_px,), ts)[0][
        0
    ]


def _jacobian_sets() -> tuple[Array, list[tuple[Array, Array, Array]]]:
    """:func:`_direction_jacobian_stack`'s steps (4,) and, per limb, the cosines, sines and shifts (each (9,)) of its
    9 parameter sets (nominal, then +/- each of the 4 parameters)."""
    step = np.array([1e-6, 1e-3, 1e-6, 1e-3])
    P = np.zeros((9, 4))
    for k in range(4):
        P[1 + 2 * k, k] = step[k]
        P[2 + 2 * k, k] = -step[k]
    return step, [(np.cos(P[:, 2 * j]), np.sin(P[:, 2 * j]), P[:, 2 * j + 1].copy()) for j in range(2)]


_JAC_STEP, _JAC_CS_SN = _jacobian_sets()


def _direction_covariances(
    K: Array,
    centroids: Array,
    directions: Array,
    s2: Array,
    n_points: Array,
    t_sumsq: Array,
    t_span: Array,
    inner: Array,
    edge_bias_px: float = 0.0,
    edge_bias_length_px: float = 0.0,
) -> Array:
    """:func:`_direction_covariance` of M rods at once, each limb fit given by its centroid, direction and spread.

    The same model and central-difference scheme (same steps, same sign conventions) as the per-rod function, whose
    fit ``(c, td, s2, pts)`` maps to ``centroids = c``, ``directions = td``, ``n_points = len(pts)``,
    ``t_sumsq = sum(((pts - c) @ td) ** 2)`` and ``t_span = ptp((pts - c) @ td)``; the results agree to rounding.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix, pixels.
    centroids, directions : ndarray, shape (M, 2, 2)
        Per rod and limb: the line's centroid (ideal pixels) and unit direction.
    s2 : ndarray, shape (M, 2)
        Per rod and limb: the effective residual variance of its edge points, px^2.
    n_points : ndarray, shape (M, 2)
        Edge points per limb.
    t_sumsq, t_span : ndarray, shape (M, 2)
        Sum of the squared positions of the edge points along the line about the centroid (px^2), and their span
        (px).
    inner : ndarray, shape (M, 3)
        A direction on the axis' side of both interpretation planes (their sign).
    edge_bias_px : float
        End-to-end standard deviation of the slowly varying edge bias along a limb, pixels.
    edge_bias_length_px : float
        Its correlation length along the limb, pixels (:func:`edge_bias_factor`; 0: no averaging).

    Returns
    -------
    ndarray, shape (M, 3, 3)
        Covariance of each rod's unit axis direction.
    """
    return _direction_covariances_set(
        K, centroids, directions, s2, n_points, t_sumsq, t_span, inner, edge_bias_px, (edge_bias_length_px,)
    )[0]


def _direction_covariances_set(
    K: Array,
    centroids: Array,
    directions: Array,
    s2: Array,
    n_points: Array,
    t_sumsq: Array,
    t_span: Array,
    inner: Array,
    edge_bias_px: float,
    lengths_px: tuple[float, ...],
) -> list[Array]:
    """:func:`_direction_covariances` for each of the allowance's correlation lengths ``lengths_px``, the limb
    planes' derivatives computed once."""
    c = np.asarray(centroids, dtype=np.float64)
    td = np.asarray(directions, dtype=np.float64)
    s2 = np.asarray(s2, dtype=np.float64)
    span = np.maximum(np.asarray(t_span, dtype=np.float64), 1.0)
    J = np.ascontiguousarray(_direction_jacobian_stack(K, c, td, inner).transpose(0, 2, 1))  # (M, 4, 3)
    noise_ang = s2 / np.maximum(np.asarray(t_sumsq, dtype=np.float64), 1e-9)
    noise_sh = s2 / np.asarray(n_points, dtype=np.float64)
    out = []
    for length in lengths_px:
        b2 = edge_bias_px**2 * edge_bias_factor(span, length)
        var_ang = noise_ang + b2 / span**2
        var_sh = noise_sh + 0.25 * b2
        var = np.stack([var_ang[:, 0], var_sh[:, 0], var_ang[:, 1], var_sh[:, 1]], axis=1)  # (M, 4)
        out.append(np.einsum("mki,mk,mkj->mij", J, var, J))
    return out


def _direction_covariance_sets(
    K: Array,
    fits: list[list[tuple[Array, Array, float, Array]]],
    inner: Array,
    edge_bias_px: float,
    lengths_px: tuple[float, ...],
    ts: list[list[Array]],
) -> list[Array]:
    """:func:`_direction_covariance` of M rods at once, for each of the allowance's correlation lengths: each rod's
    slice the numbers the rod alone gets, bit for bit (the function of one rod is this one with M = 1).

    Each rod's variances come from the same scalar arithmetic, and its derivatives and covariance from the same
    products (:func:`_direction_jacobian_stack`), stacked: numpy's stacked matrix products compute each rod's slice
    as the single product does.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix (px).
    fits : list of M lists of 2 (centroid (2,), unit direction (2,), sigma^2 (px^2), points (N, 2))
        Each rod's two limb fits (ideal px).
    inner : ndarray, shape (M, 3)
        Per rod, a direction on the axis' side of both interpretation planes.
    edge_bias_px : float
        End-to-end standard deviation of the edge bias along a limb (px).
    lengths_px : tuple of float
        The allowance's correlation lengths (px; :func:`edge_bias_factor`).
    ts : list of M lists of 2 ndarrays, shape (N,)
        Each fit's ``(pts - c) @ td`` (px).

    Returns
    -------
    list of ndarray, shape (M, 3, 3)
        Per length, each rod's covariance of its unit axis direction.
    """
    m = len(fits)
    var = np.zeros((len(lengths_px), m, 4, 4))
    for r, (rod, rod_ts) in enumerate(zip(fits, ts, strict=True)):
        spans, parts = [], []
        for (_c, _td, s2, pts), t in zip(rod, rod_ts, strict=True):
            spans.append(max(float(t.max() - t.min()), 1.0))
            parts.append((s2 / max(float(t @ t), 1e-9), s2 / len(pts)))
        for k, length in enumerate(lengths_px):
            v = []
            for span, (v_ang, v_sh) in zip(spans, parts, strict=True):
                b2 = edge_bias_px**2 * (1.0 if length == 0 else min(1.0, length / span))
                v += [v_ang + b2 / span**2, v_sh + 0.25 * b2]
            var[k, r] = np.diag(v)
    for length in lengths_px:
        edge_bias_factor(1.0, length)  # (validates the length)
    c = np.array([[f[0] for f in rod] for rod in fits]).reshape(m, 2, 2)
    td = np.array([[f[1] for f in rod] for rod in fits]).reshape(m, 2, 2)
    J = _direction_jacobian_stack(K, c, td, inner)
    Jt = J.transpose(0, 2, 1)
    return [np.matmul(np.matmul(J, var[k]), Jt) for k in range(len(lengths_px))]


def _direction_jacobian_stack(K: Array, c: Array, td: Array, inner: Array) -> Array:
    """d u / d (angle, offset of limb 0, angle, offset of limb 1) of M rods (limb centroids and directions (M, 2, 2),
    ideal px; ``inner`` (M, 3), a direction on the axis' side of both limb planes), (M, 3, 4), by central
    differences: each rod's slice the numbers the rod alone gets (the products stacked)."""
    step, cs_sn = _JAC_STEP, _JAC_CS_SN
    m = len(c)
    hs = []
    lines = np.empty((m, 9, 3))
    for j in range(2):
        cs, sn, sh = cs_sn[j]
        tx, ty = td[:, j, 0, None], td[:, j, 1, None]
        dx = cs * tx - sn * ty  # (M, 9)
        dy = sn * tx + cs * ty
        lines[..., 0] = -dy
        lines[..., 1] = dx
        lines[..., 2] = dy * c[:, j, 0, None] - dx * c[:, j, 1, None] - sh
        h = np.matmul(lines, K)
        h /= np.sqrt(np.add.reduce(h * h, axis=2, keepdims=True))
        hs.append(h * np.where(np.matmul(h, inner[:, :, None])[..., 0] > 0, 1.0, -1.0)[..., None])
    a, b = hs
    u = np.empty((m, 9, 3))
    u[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    u[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    u[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    u /= np.sqrt(np.add.reduce(u * u, axis=2, keepdims=True))
    u *= np.where(np.matmul(u, u[:, 0, :, None])[..., 0] > 0, 1.0, -1.0)[..., None]
    return ((u[:, 1::2] - u[:, 2::2]) / (2.0 * step[:, None])).transpose(0, 2, 1)  # (M, 3, 4)
