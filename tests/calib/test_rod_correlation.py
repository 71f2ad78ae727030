"""The rods' shared errors: estimated from a fit's residuals with what the fit absorbs accounted for.

Rods seen at nearby places of the image share part of their direction error (background and light; on the
image-level twin the in-image errors of a leg's rods in different poses correlate at ~0.3 within 10 px, ~0.08 at
100-150 px). The fit absorbs most of such an error, so the residuals hide it and a std that counts the rods as
independent is too small. Two levels:

* the estimator alone, on a linear model with priors whose unknowns absorb the shared error's long-range part (as the
  combined fit's geometry, base frame and intrinsics do): the spread of the estimates over many draws is what the
  sandwich with the estimated components says, and what the independent model says is too small;
* the combined method on the geometric twin, its rods' in-image errors drawn with a shared part that decays with the
  distance between the rods in the image (the twin has no images: this stands in for the extraction's errors).
"""

import numpy as np
import pytest
from scipy.stats import chi2

from calib.formats.observations import Observations
from calib.identify import calibrate_combined
from calib.identify import rod_correlation as rc
from calib.model.parameters import COMBINATION_NAMES
from tests.calib.test_combined_rod_pairs import twin_with_exact_rods

FOCAL_PX = 774.0


def _linear_problem(rng: np.random.Generator, m: int = 150):
    """A fit of 4 unknowns plus 3 with a unit prior, over m rods' two entries each, rods at random image places:
    the rods' own error shape (2m, 2m), the shared error's distance shape, the Jacobian (2m, 7) and the priors."""
    mid = rng.uniform([0.0, 0.0], [1000.0, 800.0], size=(m, 2))
    rays = np.c_[(mid - [500.0, 400.0]) / FOCAL_PX, np.ones(m)]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    A = rng.standard_normal((m, 2, 2))
    own_blocks = np.einsum("mij,mkj->mik", A, A) + 0.2 * np.eye(2)
    u = rng.standard_normal((m, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    g = rc.in_image_sensitivity(u, rays, np.eye(3), rng.standard_normal((m, 2, 3)), own_blocks)
    # the unknowns: 4 free ones with entries that vary from rod to rod, and 3 nuisances with a prior (a constant and
    # two image gradients of the in-image direction: what a camera's intrinsics do to every rod at once)
    J = np.zeros((2 * m, 7))
    # the free unknowns move nearby rods alike (the pose, hence a rod's sensitivity, varies smoothly over the image)
    xy = (mid - mid.mean(0)) / 500.0
    k = rng.uniform(2.0, 6.0, size=(4, 2))
    phase = rng.uniform(0.0, 2 * np.pi, size=4)
    for j in range(4):
        f = np.cos(xy @ k[j] + phase[j])
        J[:, j] = (g * f[:, None] + 0.3 * rng.standard_normal((m, 2))).ravel()
    for j, f in enumerate((np.ones(m), xy[:, 0], xy[:, 1])):
        J[:, 4 + j] = (g * f[:, None]).ravel()
    P = np.zeros((7, 7))
    P[4:, 4:] = np.eye(3)
    return rc.block_diagonal(own_blocks), rc.distance_shape(rays, FOCAL_PX, g, []), J, P


def test_estimated_shared_error_gives_the_spread_that_independent_rods_miss():
    rng = np.random.default_rng(7)
    own, dist, J, P = _linear_problem(rng)
    m = own.shape[0] // 2
    s2_true, rho_true = 0.3, 0.4
    cov_e = s2_true * (own + rho_true * dist)
    L = np.linalg.cholesky(cov_e)
    W = np.linalg.inv(own)  # the fit's weights: each rod's own shape
    H = J.T @ W @ J + P
    B = np.linalg.solve(H, J.T @ W)
    n_rep = 300
    est, sd_new, sd_old, rhos = [], [], [], []
    for _ in range(n_rep):
        zeta = rng.standard_normal(3)  # the nuisances' priors are themselves off by N(0, 1)
        e = L @ rng.standard_normal(2 * m)
        theta_hat = -B @ e + np.linalg.solve(H, P[:, 4:] @ zeta)
        r = e + J @ theta_hat  # residuals at the solution (the true unknowns are zero)
        est.append(theta_hat[:4])
        errs = rc.estimate_rod_errors(r, J, W, P, own, distance_shape=dist)
        rhos.append(errs.distance_rho)
        Sig = errs.covariance(own)
        Hinv = np.linalg.inv(H)
        cov = B @ Sig @ B.T + Hinv @ P @ Hinv
        sd_new.append(np.sqrt(np.diag(cov)[:4]))
        # the independent model: the residuals' chi-square over its degrees of freedom, no shared part
        s2_old = float(r @ W @ r) / (2 * m - 4)
        cov_old = s2_old * B @ own @ B.T + Hinv @ P @ Hinv
        sd_old.append(np.sqrt(np.diag(cov_old)[:4]))
    spread = np.std(np.array(est), axis=0)
    ratio_new = np.mean(sd_new, axis=0) / spread
    ratio_old = np.mean(sd_old, axis=0) / spread
    # a standard deviation from n_rep draws is known to about 1/sqrt(2 n_rep) (4%): 4 of those either side
    tol = 4.0 / np.sqrt(2 * n_rep)
    assert np.all(np.abs(ratio_new - 1.0) < tol), f"std / spread with the shared error estimated: {ratio_new.round(3)}"
    # counted independent, the std of the unknowns that nearby rods move alike is too small
    assert np.min(ratio_old) < 1.0 - tol, f"std / spread counting the rods independent: {ratio_old.round(3)}"
    # the correlation itself is recovered (its estimate from one fit is noisy: compare the mean)
    se = np.std(rhos) / np.sqrt(n_rep)
    assert abs(np.mean(rhos) - rho_true) < 4 * se + 0.02, f"mean estimated correlation {np.mean(rhos):.3f}"


def test_no_shared_error_is_estimated_near_zero():
    rng = np.random.default_rng(8)
    own, dist, J, P = _linear_problem(rng)
    m = own.shape[0] // 2
    L = np.linalg.cholesky(0.3 * own)
    W = np.linalg.inv(own)
    H = J.T @ W @ J + P
    B = np.linalg.solve(H, J.T @ W)
    s2s, rhos = [], []
    for _ in range(200):
        e = L @ rng.standard_normal(2 * m)
        r = e + J @ (-B @ e + np.linalg.solve(H, P[:, 4:] @ rng.standard_normal(3)))
        errs = rc.estimate_rod_errors(r, J, W, P, own, distance_shape=dist)
        s2s.append(errs.s2)
        rhos.append(errs.distance_rho)
    # the own scale is unbiased (its moment accounts for the 4 free unknowns and the priors' share)
    assert abs(np.mean(s2s) / 0.3 - 1.0) < 4 * np.std(s2s) / 0.3 / np.sqrt(200) + 0.01
    # clipped at zero, the correlation's estimate is small: half the draws at zero, the rest the estimate's noise
    assert np.median(rhos) < 0.02 and np.mean(rhos) < 0.1, f"median {np.median(rhos):.3f}, mean {np.mean(rhos):.3f}"


def _twin_observations(plan, seed: int, rho: float) -> tuple[Observations, np.ndarray]:
    """The twin's rods with per-rod anisotropic noise whose in-image part is shared with the rods nearby in the image
    (correlation ``rho * exp(-d / 100 px)``, any frame, any leg), and a camera of focal ``FOCAL_PX``."""
    twin = twin_with_exact_rods()
    doc = twin.observations(plan=plan, seed=seed)
    rods = [rod for f in doc["frames"] for rs in (f.get("legs") or {}).values() for rod in rs if rod is not None]
    p = np.array([rod["point"] for rod in rods])
    rays = p / np.linalg.norm(p, axis=1, keepdims=True)
    d = FOCAL_PX * np.arccos(np.clip(rays @ rays.T, -1.0, 1.0))
    C = (1.0 - rho) * np.eye(len(rods)) + rho * np.exp(-d / rc.KERNEL_LENGTH_PX)
    rng = np.random.default_rng(seed)
    z_img = np.linalg.cholesky(C) @ rng.standard_normal(len(rods))
    s_img, s_depth = 2e-5, 5e-4
    for rod, zi in zip(rods, z_img, strict=True):
        u, pt = np.asarray(rod["u"]), np.asarray(rod["point"])
        n = np.cross(pt, u)
        n /= np.linalg.norm(n)
        e = np.cross(n, u)
        um = u + s_depth * rng.standard_normal() * e + s_img * zi * n
        rod["u"] = (um / np.linalg.norm(um)).tolist()
        rod["cov_u"] = (s_depth**2 * np.outer(e, e) + s_img**2 * np.outer(n, n)).tolist()
    K = [[FOCAL_PX, 0.0, 512.0], [0.0, FOCAL_PX, 384.0], [0.0, 0.0, 1.0]]
    doc["extraction"] = {"camera": {"format": "i4cal-camera/1", "width": 1024, "height": 768, "K": K, "dist": []}}
    t4 = twin.geometry.truth.combinations()
    return Observations.from_dict(doc), np.array([t4[k] for k in COMBINATION_NAMES])


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_combined_std_is_honest_when_rods_nearby_in_the_image_share_their_error(paper_plan, rho):
    n_rep = 40
    d2, rhos = [], []
    for seed in range(n_rep):
        obs, truth = _twin_observations(paper_plan, seed, rho)
        res = calibrate_combined(obs)
        e = np.array([res.combinations[k] for k in COMBINATION_NAMES]) - truth
        d2.append(float(e @ np.linalg.solve(res.covariance, e)))
        rhos.append(res.diagnostics["rod_errors"]["distance_correlation"])
    # the mean of n_rep chi-square(4) draws: its 99.9% interval
    lo, hi = chi2.ppf([0.0005, 0.9995], 4 * n_rep) / n_rep
    assert lo < np.mean(d2) < hi, f"mean squared Mahalanobis error {np.mean(d2):.2f}, expected {lo:.2f}-{hi:.2f}"
    se = np.std(rhos) / np.sqrt(n_rep)
    assert abs(np.mean(rhos) - rho) < 4 * se + 0.05, f"mean estimated correlation {np.mean(rhos):.3f}, drawn {rho}"


def test_the_estimated_covariance_is_positive_semi_definite_at_strong_correlations():
    """A leg's same-frame pair and the distance kernel (which leaves those pairs out) can together make an indefinite
    covariance at strong correlations (here 0.9 and 0.9: smallest eigenvalue of the correlation matrix -0.61): the
    estimate shrinks them until it is not, and leaves alone a combination that is."""
    rng = np.random.default_rng(11)
    own, dist, _J, _P = _linear_problem(rng)
    m = own.shape[0] // 2
    pairs = [(a, a + 1) for a in range(0, m - 1, 2)]
    whitening_inverse = np.linalg.cholesky(own.reshape(m, 2, m, 2)[np.arange(m), :, np.arange(m), :])
    pair = rc.pair_shape(pairs, whitening_inverse, m)

    def smallest(rp, rd):
        S = own + rp * pair + rd * dist
        d = np.sqrt(np.diag(S))
        return np.linalg.eigvalsh(S / np.outer(d, d))[0]

    assert smallest(0.9, 0.9) < -0.1  # the case guarded against
    rp, rd = rc.positive_definite(own, [pair, dist], np.array([0.9, 0.9]))
    assert smallest(rp, rd) > -1e-9 and rp > 0.3 and rd > 0.3
    assert smallest(0.0, 0.9) > 0
    np.testing.assert_array_equal(rc.positive_definite(own, [pair, dist], np.array([0.0, 0.9])), [0.0, 0.9])
