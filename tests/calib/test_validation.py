import copy

import numpy as np
import pytest

from calib.formats.observations import Observations
from calib.formats.plan import Plan
from calib.identify.baseframe import fit_translation_direction, translation_scale_std
from calib.identify.validation import displacement_gaps, straightness, validate, vision_scale
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


def _scaled_board(obs_dict: dict, k: float) -> Observations:
    """The same observations with every board position scaled by ``k`` about the camera centre: what a board
    printed ``1/k`` of its nominal size gives (a camera calibration that fixes the board's scale by two of its
    points cannot tell)."""
    doc = copy.deepcopy(obs_dict)
    for f in doc["frames"]:
        if f.get("board"):
            f["board"]["t"] = [k * v for v in f["board"]["t"]]
    return Observations.from_dict(doc)


def test_vision_scale_is_taken_out_of_the_gaps(paper_plan):
    """Vision measuring every displacement 0.3% long (a board printed 0.3% small) is not a gap of the true
    geometry: the translation phase measures that scale against the encoders and the gaps are divided by it."""
    twin = GeometricTwin(noise=NoiseSpec.zero())
    obs = _scaled_board(twin.observations(plan=paper_plan, seed=0), 1.003)
    plain = displacement_gaps(obs, twin.geometry.truth)
    assert plain["rms_mm"] > 0.2  # 0.3% of the fit poses' displacements (about 200 mm and more)
    sc = vision_scale(obs)
    assert sc["source"] == "translation phase" and sc["n_poses"] >= 3
    assert abs(sc["scale"] - 1.003) < 1e-9 and sc["std"] < 1e-9
    v = validate(obs, twin.geometry.truth)
    assert v["vision_scale"] == sc
    assert v["gaps_poses"]["rms_mm"] < 1e-6
    assert v["gaps_poses"]["vision_scale"] == sc["scale"]
    # a wrong geometry is still seen: the a priori gap stays (the scale is not fitted to the poses)
    assert validate(obs, obs.nominal)["gaps_poses"]["rms_mm"] > 0.5
    assert "warning" not in sc
    # a board configured 1% off is divided out too, and said
    far = vision_scale(_scaled_board(twin.observations(plan=paper_plan, seed=0), 1.01))
    assert "+1.00%" in far["warning"] and "square length" in far["warning"]


def test_vision_scale_std_matches_its_spread(paper_plan):
    """The translation scale's reported std against its spread over 400 seeded noisy twins (board noise only):
    within 20% (the spread's own relative std is 1/sqrt(2 x 400) = 3.5%, so 20% is beyond 5 of it), and the mean
    within 4 standard errors of 1."""
    twin = GeometricTwin(noise=NoiseSpec(0, 0, 3e-4, (1e-4, 1e-4, 3e-4), 1e-6))
    plan = Plan.model_validate(
        {"name": "translation", "steps": [s.model_dump() for s in paper_plan.steps if s.phase == "translation"]}
    )
    scales, stds = [], []
    for seed in range(400):
        obs = Observations.from_dict(twin.observations(plan=plan, seed=seed))
        d = obs.arrays("translation")
        s = d.q.mean(axis=1)
        x, _, res, scale = fit_translation_direction(d.board_t, s)
        scales.append(scale)
        stds.append(translation_scale_std(res, s, x))
    spread = float(np.std(scales, ddof=1))
    assert 0.8 < float(np.mean(stds)) / spread < 1.2, (np.mean(stds), spread)
    assert abs(float(np.mean(scales)) - 1.0) < 4 * spread / np.sqrt(len(scales))


def test_gaps_reject_a_bad_scale(noise_free_obs):
    obs, twin = noise_free_obs
    with pytest.raises(ValueError, match="vision_scale"):
        displacement_gaps(obs, twin.geometry.truth, vision_scale=0.0)
