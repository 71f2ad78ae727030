import numpy as np

from calib.observations import Observations
from calib.validation import displacement_gaps, straightness
from drivers.sim.twin import GeometricTwin, NoiseSpec


def test_true_geometry_has_no_gap_without_noise(noise_free_obs):
    obs, twin = noise_free_obs
    g = displacement_gaps(obs, twin.geometry.truth)
    assert g["n_pairs"] == 19
    assert g["rms_mm"] < 1e-9
    assert straightness(obs, twin.geometry.truth)["rms_mm"] < 1e-9
    # the a priori parameters do not fit the true mechanism
    assert displacement_gaps(obs, obs.nominal)["rms_mm"] > 0.5


def test_line_is_500_mm(noise_free_obs):
    s = straightness(*[noise_free_obs[0], noise_free_obs[1].geometry.truth])
    assert abs(s["length_mm"] - 500.0) < 1e-6


def test_gap_noise_floor_matches_board_noise(paper_plan):
    """With the true parameters the gap RMS comes from board noise only: about sqrt(2) x the
    translation noise projected on the displacement (within a factor 2)."""
    twin = GeometricTwin(noise=NoiseSpec(0, 0, 0, (1e-4, 1e-4, 1e-4), 0))
    obs = Observations.from_dict(twin.observations(plan=paper_plan, seed=3))
    g = displacement_gaps(obs, twin.geometry.truth)
    expected = np.sqrt(2) * 0.1
    assert expected / 2 < g["rms_mm"] < expected * 2
