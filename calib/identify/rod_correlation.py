"""How the rods' direction errors correlate with one another, estimated from a fit's residuals.

Two rods' direction errors are not independent when the two are seen side by side or at nearby places of the image:

* the two rods of a leg in one frame share the frame and the narrow gap between them;
* rods seen at nearby places of the image, in any frame, share the background behind them and the light on them,
  which pull their limb edges the same way. On rendered views the in-image direction errors of two rods of one leg
  in different frames correlate when their midpoints are close (a few tenths within 10 px) and less with distance,
  not at all beyond a few hundred px: an exponential of about 100 px (:data:`KERNEL_LENGTH_PX`).

Counted as independent, such errors average down over the poses far more than they do. The fit cannot tell them from
the geometry it estimates: it absorbs most of a shared error, so the residuals show only its short-range part, and
a correlation (or a noise level) read from the residuals as they are is too small. Here the rods' own scale and the
two correlations are estimated together from quadratic forms of the residuals, each matched to its expectation under
the fit: ``E[r^T Q r] = tr(Q M Sigma M^T) + tr(Q J H^-1 P H^-1 J^T)``, with ``M`` the fit's linearized residual
maker, ``P`` its priors and ``Sigma`` linear in the unknown components (a method of moments that accounts for what
the fit absorbs, as REML does for variance components).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import nnls

Array = NDArray[np.float64]

#: Correlation length (px, between the rods' midpoints in the image) of the shared in-image error
KERNEL_LENGTH_PX = 100.0
#: Fewest same-frame pairs of a leg's rods for their correlation to be estimated
MIN_PAIRS = 10
#: Largest correlation either component may take
MAX_CORRELATION = 0.9


@dataclass(frozen=True)
class RodErrors:
    """The rods' error model estimated from a fit's residuals.

    Attributes
    ----------
    s2 : float
        Scale of each rod's own covariance (``s2 * shape``; dimensionless).
    pair_rho : float
        Correlation of the whitened errors of a leg's two rods in one frame.
    distance_rho : float
        Correlation at zero distance of the in-image errors of rods seen at nearby places
        (``distance_rho * exp(-d / KERNEL_LENGTH_PX)``, other than a leg's same-frame pair).
    dof : float
        The residuals' effective degrees of freedom for the rods' own error (``2M`` less what the fit absorbs).
    """

    s2: float
    pair_rho: float
    distance_rho: float | None
    dof: float
    pair_shape: Array | None = None
    distance_shape: Array | None = None

    def covariance(self, own: Array) -> Array:
        """The rods' error covariance (2M, 2M) in the fit's raw residuals.

        Parameters
        ----------
        own : ndarray, shape (2M, 2M)
            The rods' own error shapes, block diagonal (dimensionless).

        Returns
        -------
        ndarray, shape (2M, 2M)
            The covariance (Jacobian entries squared, dimensionless).
        """
        S = own.copy()
        if self.pair_shape is not None and self.pair_rho > 0:
            S += self.pair_rho * self.pair_shape
        if self.distance_shape is not None and self.distance_rho:
            S += self.distance_rho * self.distance_shape
        return self.s2 * S

    def summary(self) -> dict[str, float | None]:
        return {
            "own_scale": float(np.sqrt(self.s2)),
            "pair_correlation": self.pair_rho,
            "distance_correlation": self.distance_rho,
            "distance_length_px": KERNEL_LENGTH_PX if self.distance_rho is not None else None,
            "dof": self.dof,
        }


def rod_pairs(k: np.ndarray, leg: np.ndarray) -> list[tuple[int, int]]:
    """Index pairs (a, b), a < b, of the two rods of one leg seen in the same frame.

    Parameters
    ----------
    k : ndarray of int, shape (M,)
        Each rod's frame.
    leg : ndarray of int, shape (M,)
        Each rod's leg.

    Returns
    -------
    list of tuple of (int, int)
        The pairs, indices into the M rods.
    """
    first: dict[tuple[int, int], int] = {}
    pairs = []
    for a, key in enumerate(zip(np.asarray(k).tolist(), np.asarray(leg).tolist(), strict=True)):
        b = first.setdefault(key, a)
        if b != a:
            pairs.append((b, a))
    return pairs


def whitening(shape: np.ndarray) -> np.ndarray:
    """Each rod's whitening ``Wh`` of its own error ``shape``: upper triangular, ``Wh^T Wh = shape^-1``.

    Parameters
    ----------
    shape : ndarray, shape (M, 2, 2)
        Each rod's error shape (dimensionless).

    Returns
    -------
    ndarray, shape (M, 2, 2)
        The whitenings.
    """
    return np.linalg.cholesky(np.linalg.inv(shape + 1e-30 * np.eye(2))).transpose(0, 2, 1)


def block_diagonal(blocks: Array) -> Array:
    """The (2M, 2M) block-diagonal matrix of M (2, 2) blocks.

    Parameters
    ----------
    blocks : ndarray, shape (M, 2, 2)
        The blocks.

    Returns
    -------
    ndarray, shape (2M, 2M)
        The block-diagonal matrix.
    """
    m = blocks.shape[0]
    out = np.zeros((2 * m, 2 * m))
    idx = np.arange(m)
    out.reshape(m, 2, m, 2)[idx, :, idx, :] = blocks
    return out


def in_image_sensitivity(u_cam: Array, rays: Array, R_cb: Array, ratio_grad: Array, own_blocks: Array) -> Array:
    """Each rod's in-image error direction in its two Jacobian entries, scaled to unit whitened length.

    The direction is the change of the entries when the rod's direction turns about its viewing ray (its image line
    turns); it is scaled so that ``g_a^T own_a^-1 g_a = 1``: one standard deviation of the rod's own error along it.
    A correlation ``rho`` of these components between rods then keeps every rod's covariance at its own (the
    shared part is ``rho g_a g_a^T`` of it) and the whole covariance positive definite for ``rho < 1``.

    Parameters
    ----------
    u_cam : ndarray, shape (M, 3)
        Rod directions, camera frame (unit).
    rays : ndarray, shape (M, 3)
        Unit viewing rays to the rods' visible middles, camera frame.
    R_cb : ndarray, shape (3, 3)
        Camera-from-base rotation (``u_base = u_cam @ R_cb``).
    ratio_grad : ndarray, shape (M, 2, 3)
        d(entries)/d(u_base) at the rods' directions.
    own_blocks : ndarray, shape (M, 2, 2)
        Shape of each rod's own error in its two entries.

    Returns
    -------
    ndarray, shape (M, 2)
    """
    n_img = np.cross(rays, u_cam)
    n_img /= np.linalg.norm(n_img, axis=1, keepdims=True)
    v = np.einsum("mij,mj->mi", ratio_grad, n_img @ R_cb)
    q = np.einsum("mi,mi->m", v, np.linalg.solve(own_blocks, v[..., None])[..., 0])
    return v / np.sqrt(np.maximum(q, 1e-300))[:, None]


def pair_shape(pairs: list[tuple[int, int]], whitening_inverse: Array, m: int) -> Array:
    """Shape of a correlation between the whitened errors of each same-frame pair of a leg's rods.

    Parameters
    ----------
    pairs : list of tuple of (int, int)
        Same-frame pairs (:func:`rod_pairs`).
    whitening_inverse : ndarray, shape (M, 2, 2)
        Undoes each rod's whitening (its residual ``r = Lc w``).
    m : int
        The rod count M.

    Returns
    -------
    ndarray, shape (2M, 2M)
        The shape (dimensionless), zero outside the pairs' blocks.
    """
    out = np.zeros((2 * m, 2 * m))
    for a, b in pairs:
        blk = whitening_inverse[a] @ whitening_inverse[b].T
        out[2 * a : 2 * a + 2, 2 * b : 2 * b + 2] = blk
        out[2 * b : 2 * b + 2, 2 * a : 2 * a + 2] = blk.T
    return out


def distance_shape(
    rays: Array, focal_px: float, g: Array, pairs: list[tuple[int, int]], length_px: float = KERNEL_LENGTH_PX
) -> Array:
    """Shape ``exp(-d_ab / length) g_a g_b^T`` of the shared in-image error, off the diagonal and off the same-frame
    pairs of a leg's rods (which :func:`pair_shape` covers).

    Parameters
    ----------
    rays : ndarray, shape (M, 3)
        Unit viewing rays to the rods' middles; ``d_ab`` is their angle times ``focal_px`` (px in the image).
    focal_px : float
        The camera's focal length, px.
    g : ndarray, shape (M, 2)
        :func:`in_image_sensitivity`.
    pairs : list of tuple of (int, int)
        Same-frame pairs of a leg's rods (:func:`rod_pairs`), left out.
    length_px : float
        The kernel's correlation length, px.

    Returns
    -------
    ndarray, shape (2M, 2M)
        The shape (dimensionless).
    """
    m = g.shape[0]
    d = focal_px * np.arccos(np.clip(rays @ rays.T, -1.0, 1.0))
    k = np.exp(-d / length_px)
    np.fill_diagonal(k, 0.0)
    for a, b in pairs:
        k[a, b] = k[b, a] = 0.0
    return np.einsum("ab,ai,bj->aibj", k, g, g).reshape(2 * m, 2 * m)


def positive_definite(own: Array, shapes: list[Array], rho: Array) -> Array:
    """``rho`` shrunk (by 0.8 a step) until ``own + sum rho_j S_j`` is positive semi-definite.

    Each correlation alone keeps the covariance positive definite below 1; the two together, the distance kernel
    leaving out a leg's same-frame pairs, may not at strong correlations.

    Parameters
    ----------
    own : ndarray, shape (2M, 2M)
        The rods' own error shapes (dimensionless).
    shapes : list of ndarray, each of shape (2M, 2M)
        The correlation shapes ``S_j`` (dimensionless).
    rho : ndarray, shape (K,)
        The correlations, one per shape.

    Returns
    -------
    ndarray, shape (K,)
        The correlations kept.
    """
    if not shapes or not np.any(rho > 0):
        return rho
    d = np.sqrt(np.clip(np.diag(own), 1e-300, None))
    scaled_own = own / np.outer(d, d)
    scaled = [S / np.outer(d, d) for S in shapes]
    for _ in range(30):
        S = scaled_own + sum(r * Sj for r, Sj in zip(rho, scaled, strict=True))
        if float(np.linalg.eigvalsh(S)[0]) >= -1e-10:
            return rho
        rho = 0.8 * rho
    return np.zeros_like(rho)


def estimate_rod_errors(
    r: Array,
    J: Array,
    Wd: Array,
    P: Array,
    own: Array,
    pair_shape: Array | None = None,
    distance_shape: Array | None = None,
) -> RodErrors:
    """The rods' own scale and their correlations, from the residuals of a fit with priors.

    Parameters
    ----------
    r : ndarray, shape (N,)
        The fit's residuals (unweighted) at its solution.
    J : ndarray, shape (N, p)
        Their Jacobian in the unknowns.
    Wd : ndarray, shape (N, N)
        The fit's data weight (it minimises ``r^T Wd r + v^T P v``).
    P : ndarray, shape (p, p)
        The priors' information (zero rows for unknowns without one).
    own : ndarray, shape (N, N)
        Shape of each rod's own error (block-diagonal).
    pair_shape, distance_shape : ndarray, shape (N, N), optional
        :func:`pair_shape` and :func:`distance_shape`; left out when None.

    Returns
    -------
    RodErrors
    """
    N = r.size
    H = J.T @ Wd @ J + P
    A = np.linalg.solve(H, J.T @ Wd)
    M = np.eye(N) - J @ A
    prior_part = J @ np.linalg.solve(H, P) @ np.linalg.solve(H, J.T)  # the priors' own error, seen in the residuals
    W0 = np.linalg.pinv(own, hermitian=True)
    shapes = [own] + [S for S in (pair_shape, distance_shape) if S is not None]
    Qs = [W0] + [W0 @ S @ W0 for S in shapes[1:]]
    MS = [M @ S @ M.T for S in shapes]
    T = np.array([[float(np.sum(Q * MSj)) for MSj in MS] for Q in Qs])
    b = np.array([float(r @ Q @ r) - float(np.sum(Q * prior_part)) for Q in Qs])
    dof = float(T[0, 0])
    norm = np.sqrt(np.sum(T * T, axis=1))
    norm[norm == 0] = 1.0
    c, _ = nnls(T / norm[:, None], b / norm)
    s2 = float(c[0])
    rho = np.zeros(len(shapes) - 1) if s2 <= 0 else np.minimum(c[1:] / s2, MAX_CORRELATION)
    rho = positive_definite(own, shapes[1:], rho)
    # the own scale again with the correlations held (it is what the first moment pins)
    den = T[0, 0] + float(T[0, 1:] @ rho)
    s2 = max(float(b[0]) / den, 0.0) if den > 0 else 0.0
    it = iter(rho.tolist())
    pair_rho = next(it) if pair_shape is not None else 0.0
    dist_rho = next(it) if distance_shape is not None else None
    return RodErrors(s2, float(pair_rho), dist_rho, dof, pair_shape, distance_shape)


#: the former private name (tests read it)
