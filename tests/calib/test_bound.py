"""The Cramer-Rao bound against a brute-force Monte-Carlo of an efficient (maximum-likelihood) estimator."""

import numpy as np
import pytest

from calib.formats.observations import Observations
from calib.identify import calibrate_combined
from calib.identify.baseframe import base_frame_from_observations
from calib.identify.bound import MeasurementNoise, crlb_combined
from calib.model.parameters import COMBINATION_NAMES
from drivers.sim.twin import GeometricTwin, NoiseSpec
from tests.calib._ml_estimator import ml_combined

K = 0.1  # small noise: the ML estimator is efficient there
TWIN_NOISE = NoiseSpec(5e-4 * K, 0.0, 3e-4 * K, (1e-4 * K, 1e-4 * K, 3e-4 * K), 0.0)
NOISE = MeasurementNoise(5e-4 * K, 3e-4 * K, (1e-4 * K, 1e-4 * K, 3e-4 * K))
N_TRIALS = 150  # the sample std's relative standard error is 1/sqrt(2N) = 5.8%


@pytest.fixture(scope="module")
def trials(paper_plan):
    twin = GeometricTwin(noise=TWIN_NOISE)
    t4 = twin.geometry.truth.combinations()
    truth = np.array([t4[k] for k in COMBINATION_NAMES])
    ml, comb = [], []
    for seed in range(N_TRIALS):
        obs = Observations.from_dict(twin.observations(plan=paper_plan, seed=1000 + seed))
        bf = base_frame_from_observations(obs)  # estimated once per data set, for both estimators
        start = calibrate_combined(obs, base_frame=bf, weighting="gls")
        comb.append(start.vector() - truth)
        ml.append(ml_combined(obs, NOISE, start=start, base_frame=bf) - truth)
    bound = crlb_combined(twin.geometry.truth, paper_plan, NOISE, twin.geometry.camera_from_base.R)
    return np.asarray(ml), np.asarray(comb), np.array([bound["std"][k] for k in COMBINATION_NAMES])


def test_bound_matches_efficient_estimator_within_15_percent(trials):
    ml, _, bound = trials
    ratio = ml.std(axis=0, ddof=1) / bound
    assert np.all(np.abs(ratio - 1) < 0.15), np.round(ratio, 3)


def test_combined_method_is_near_efficient(trials):
    """Issue target: RMS error within 1.5x the bound (efficiency >= 0.67 in std ratio terms)."""
    _, comb, bound = trials
    ratio = np.sqrt(np.mean(comb**2, axis=0)) / bound
    assert np.all(ratio < 1.5), np.round(ratio, 3)


def test_bound_scales_with_noise_and_pose_count(paper_plan):
    from calib.formats.plan import make_plan
    from calib.model.parameters import NOMINAL

    b1 = crlb_combined(NOMINAL, paper_plan, NOISE)["std"]
    b2 = crlb_combined(NOMINAL, paper_plan, MeasurementNoise(1e-3 * K, 6e-4 * K, (2e-4 * K, 2e-4 * K, 6e-4 * K)))["std"]
    for k in COMBINATION_NAMES:
        assert b2[k] == pytest.approx(2 * b1[k], rel=1e-6)  # the bound is linear in the noise
    more = make_plan("full", NOMINAL, seed=0, n_fit=80)
    b3 = crlb_combined(NOMINAL, more, NOISE)["std"]
    assert all(b3[k] < b1[k] for k in COMBINATION_NAMES)
