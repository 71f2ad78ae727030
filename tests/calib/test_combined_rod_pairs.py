"""The combined method's std when the two rods of a leg share part of their error.

A leg's two rods are seen in the same frame, side by side, with a narrow gap between them: on the image-level twin
their depth errors correlate (0.16-0.22 in the whitened depth error of the rendered lens-sweep trials, measured
against the truth). Counted as independent, the pair's errors average down more than they do and the std comes out
low. The method now measures the correlation from its own residuals and puts it into the covariance.

The geometric twin's rods are re-drawn here with the anisotropic noise the image extraction reports (precise across
the image line, tens of times less in depth) and a shared part between the two rods of a leg in a frame (the twin
has no images: this stands in for the extraction's errors), with that covariance as their ``cov_u``.
"""

import numpy as np
import pytest
from scipy.stats import chi2

from calib.formats.observations import Observations
from calib.identify import calibrate_combined
from calib.model.parameters import COMBINATION_NAMES
from drivers.sim.twin import GeometricTwin, NoiseSpec

S_IMG = 2e-5  # rad, across the rod's image line
S_DEPTH = 5e-4  # rad, in its interpretation plane
N_REP = 40


def twin_with_exact_rods() -> GeometricTwin:
    """The geometric twin with exact rods (a test draws their errors) and its default board and encoder noise."""
    return GeometricTwin(
        noise=NoiseSpec(
            rod_direction_rad=0.0,
            rod_point_m=0.0,
            board_rotation_rad=1e-3,
            board_translation_m=(1e-4, 1e-4, 3e-4),
            encoder_m=1e-6,
        )
    )


def _observations(plan, seed: int, rho: float) -> tuple[Observations, np.ndarray]:
    twin = twin_with_exact_rods()
    doc = twin.observations(plan=plan, seed=seed)
    rng = np.random.default_rng(seed)
    for f in doc["frames"]:
        for rods in (f.get("legs") or {}).values():
            shared = rng.standard_normal(2)  # the pair's common part, in each rod's own (depth, across) axes
            for rod in rods:
                if rod is None:
                    continue
                u, p = np.asarray(rod["u"]), np.asarray(rod["point"])
                n = np.cross(p, u)
                n /= np.linalg.norm(n)
                e = np.cross(n, u)
                z = np.sqrt(1.0 - rho) * rng.standard_normal(2) + np.sqrt(rho) * shared
                um = u + S_DEPTH * z[0] * e + S_IMG * z[1] * n
                rod["u"] = (um / np.linalg.norm(um)).tolist()
                rod["cov_u"] = (S_DEPTH**2 * np.outer(e, e) + S_IMG**2 * np.outer(n, n)).tolist()
    t4 = twin.geometry.truth.combinations()
    return Observations.from_dict(doc), np.array([t4[k] for k in COMBINATION_NAMES])


@pytest.mark.parametrize("rho", [0.0, 0.8])
def test_std_is_honest_when_a_legs_two_rods_share_their_error(paper_plan, rho):
    d2, rhos = [], []
    for seed in range(N_REP):
        obs, truth = _observations(paper_plan, seed, rho)
        res = calibrate_combined(obs)
        e = np.array([res.combinations[k] for k in COMBINATION_NAMES]) - truth
        d2.append(float(e @ np.linalg.solve(res.covariance, e)))
        rhos.append(res.diagnostics["rod_pair_correlation"])
    # the mean of N_REP chi-square(4) draws: its 99.9% interval (counted as independent, rho = 0.8 gave about 7)
    lo, hi = chi2.ppf([0.0005, 0.9995], 4 * N_REP) / N_REP
    assert lo < np.mean(d2) < hi, f"mean squared Mahalanobis error {np.mean(d2):.2f}, expected {lo:.2f}-{hi:.2f}"
    # the measured correlation: the residuals lose a little of it to the fit (4 unknowns and the nuisances)
    assert abs(np.mean(rhos) - rho) < 0.1, f"measured pair correlation {np.mean(rhos):.3f}, drawn {rho}"
