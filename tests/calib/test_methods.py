"""The three methods: exact recovery without noise, honest standard deviations with noise."""

import numpy as np
import pytest

from calib.errors import IdentifiabilityError
from calib.formats.observations import Observations
from calib.identify import calibrate_combined, calibrate_end_effector, calibrate_legs
from calib.identify.baseframe import base_frame_from_observations
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES
from drivers.sim.twin import GeometricTwin, NoiseSpec

N_TRIALS = 60


def test_noise_free_combined_recovers_truth(noise_free_obs):
    obs, twin = noise_free_obs
    r = calibrate_combined(obs)
    truth = twin.geometry.truth.combinations()
    for k in COMBINATION_NAMES:
        assert abs(r.combinations[k] - truth[k]) < 1e-8, k
    assert r.converged and r.n_poses == 20


def test_noise_free_end_effector_recovers_truth(noise_free_obs):
    obs, twin = noise_free_obs
    r = calibrate_end_effector(obs)
    truth = twin.geometry.truth.combinations()
    for k in COMBINATION_NAMES:
        assert abs(r.combinations[k] - truth[k]) < 1e-8, k


def test_end_effector_recovers_a_board_printed_at_the_wrong_scale(paper_plan):
    """A board 0.3% too large in its print (every board pose's translation scaled by 1.003, which a camera
    calibration on that board cannot tell): the end-effector method finds the scale and the truth."""
    twin = GeometricTwin(noise=NoiseSpec.zero())
    doc = twin.observations(plan=paper_plan, seed=0)
    for f in doc["frames"]:
        if f.get("board"):
            f["board"]["t"] = [1.003 * v for v in f["board"]["t"]]
    r = calibrate_end_effector(Observations.from_dict(doc))
    truth = twin.geometry.truth.combinations()
    for k in COMBINATION_NAMES:
        assert abs(r.combinations[k] - truth[k]) < 1e-8, k
    # t_measured = 1.003 t_true, and the model scales the measured t by (1 + s): s = 1/1.003 - 1
    assert r.diagnostics["board_scale_ppm"] == pytest.approx((1 / 1.003 - 1) * 1e6, abs=1e-3)


def test_noise_free_legs_recovers_all_seven(noise_free_obs):
    obs, twin = noise_free_obs
    r = calibrate_legs(obs)
    truth = twin.geometry.truth.seven()
    for k in PARAMETER_NAMES:
        assert abs(r.parameters[k] - truth[k]) < 1e-8, k
    t4 = twin.geometry.truth.combinations()
    for k in COMBINATION_NAMES:
        assert abs(r.combinations[k] - t4[k]) < 1e-8, k


@pytest.fixture(scope="module")
def monte_carlo(paper_plan):
    """Every method on N_TRIALS noisy data sets (same poses, seeded noise on rods, boards and encoders)."""
    twin = GeometricTwin(noise=NoiseSpec())
    out = {m: {"err": [], "std": []} for m in ("combined", "end-effector", "legs")}
    t4 = twin.geometry.truth.combinations()
    truth = np.array([t4[k] for k in COMBINATION_NAMES])
    for seed in range(100, 100 + N_TRIALS):
        obs = Observations.from_dict(twin.observations(plan=paper_plan, seed=seed))
        for name, fn in (
            ("combined", calibrate_combined),
            ("end-effector", calibrate_end_effector),
            ("legs", calibrate_legs),
        ):
            r = fn(obs)
            out[name]["err"].append(r.vector() - truth)
            out[name]["std"].append(r.std_vector())
    return {m: {k: np.asarray(v) for k, v in d.items()} for m, d in out.items()}


@pytest.mark.parametrize("method", ["combined", "end-effector", "legs"])
def test_errors_lie_within_four_reported_std(monte_carlo, method):
    d = monte_carlo[method]
    z = np.abs(d["err"]) / d["std"]
    assert z.max() < 4.0, f"{method}: max |error|/std = {z.max():.2f}"


@pytest.mark.parametrize("method", ["combined", "end-effector", "legs"])
def test_reported_std_matches_monte_carlo_spread(monte_carlo, method):
    d = monte_carlo[method]
    empirical = d["err"].std(axis=0, ddof=1)
    reported = np.sqrt(np.mean(d["std"] ** 2, axis=0))
    ratio = empirical / reported
    assert np.all((ratio > 1 / 1.3) & (ratio < 1.3)), f"{method}: empirical/reported = {np.round(ratio, 3)}"


def test_combined_refines_the_base_frame_jointly(noisy_obs):
    r = calibrate_combined(noisy_obs[0])
    assert r.diagnostics["joint_base_frame"]
    assert set(r.std_breakdown) == {"legs_and_encoders", "base_frame"}
    for k in COMBINATION_NAMES:
        assert r.combinations_std[k] >= r.std_breakdown["legs_and_encoders"][k] * (1 - 1e-6)


def test_std_stays_honest_when_board_poses_are_noisy(paper_plan):
    """Noisy board poses (a poor base frame) and precise rods: the base frame's error does not average
    over the poses; the reported std must still match the Monte-Carlo spread."""
    noise = NoiseSpec(
        rod_direction_rad=5e-5,
        rod_point_m=5e-5,
        board_rotation_rad=2e-3,
        board_translation_m=(5e-4, 5e-4, 1.5e-3),
        encoder_m=1e-6,
    )
    twin = GeometricTwin(noise=noise)
    t4 = twin.geometry.truth.combinations()
    truth = np.array([t4[k] for k in COMBINATION_NAMES])
    errs, stds = [], []
    for seed in range(40):
        r = calibrate_combined(Observations.from_dict(twin.observations(plan=paper_plan, seed=seed)))
        errs.append(r.vector() - truth)
        stds.append(r.std_vector())
        assert np.all(np.abs(errs[-1]) < 4 * stds[-1])
    ratio = np.std(errs, axis=0, ddof=1) / np.sqrt(np.mean(np.square(stds), axis=0))
    assert np.all((ratio > 1 / 1.3) & (ratio < 1.3)), np.round(ratio, 3)


def test_gls_weighting_is_also_honest_and_no_worse(paper_plan):
    twin = GeometricTwin()
    t4 = twin.geometry.truth.combinations()
    truth = np.array([t4[k] for k in COMBINATION_NAMES])
    e_f, e_g, s_g = [], [], []
    for seed in range(40):
        obs = Observations.from_dict(twin.observations(plan=paper_plan, seed=500 + seed))
        bf = base_frame_from_observations(obs)  # the same for both weightings: estimated once
        e_f.append(calibrate_combined(obs, base_frame=bf).vector() - truth)
        rg = calibrate_combined(obs, base_frame=bf, weighting="gls")
        e_g.append(rg.vector() - truth)
        s_g.append(rg.std_vector())
    ratio = np.std(e_g, axis=0, ddof=1) / np.sqrt(np.mean(np.square(s_g), axis=0))
    assert np.all((ratio > 1 / 1.3) & (ratio < 1.3))
    assert np.sqrt(np.mean(np.square(e_g))) <= 1.05 * np.sqrt(np.mean(np.square(e_f)))


def _drop_phase(obs: Observations, phase: str) -> Observations:
    d = obs.to_dict()
    d["frames"] = [f for f in d["frames"] if f["phase"] != phase]
    return Observations.from_dict(d)


def test_degenerate_pose_set_names_the_parameter(noise_free_obs):
    obs, _ = noise_free_obs
    d = obs.to_dict()
    poses = [f for f in d["frames"] if f["phase"] == "poses"]
    for f in poses:  # every fit pose identical: nothing varies
        f["q"] = poses[0]["q"]
        f["legs"] = poses[0]["legs"]
    with pytest.raises(IdentifiabilityError) as ei:
        calibrate_combined(Observations.from_dict(d))
    assert ei.value.parameter in COMBINATION_NAMES
    assert "does not excite parameter" in str(ei.value)


def test_missing_phases_give_clear_errors(noise_free_obs):
    obs, _ = noise_free_obs
    with pytest.raises(IdentifiabilityError, match="rotation phase"):
        calibrate_combined(_drop_phase(obs, "rotation"))
    with pytest.raises(IdentifiabilityError, match="translation phase"):
        calibrate_combined(_drop_phase(obs, "translation"))
    with pytest.raises(IdentifiabilityError, match="lock-3"):
        calibrate_legs(_drop_phase(obs, "lock-3"))
    with pytest.raises(IdentifiabilityError, match="board pose"):
        calibrate_end_effector(_drop_phase(obs, "poses"))


def test_unlocked_actuator_is_refused(noise_free_obs):
    d = noise_free_obs[0].to_dict()
    lock = [f for f in d["frames"] if f["phase"] == "lock-2"]
    lock[0]["q"][1] += 0.01
    with pytest.raises(IdentifiabilityError, match="not locked"):
        calibrate_legs(Observations.from_dict(d))


def test_outward_shift_moves_each_limb_away_from_the_other_in_the_image():
    from calib.formats.camera import CameraModel
    from calib.identify.intrinsics import outward_shift_normalized

    cam = CameraModel(
        np.array([[800.0, 0, 512], [0, 800.0, 384], [0, 0, 1]]), np.array([-0.3, 0.1, 0, 0, 0]), 1024, 768
    )
    t = np.linspace(0.0, 1.0, 5)[:, None]
    limbs = np.stack([np.array([100.0, 80.0]) + t * [300.0, 120.0], np.array([90.0, 104.0]) + t * [300.0, 120.0]])[None]
    dxn = outward_shift_normalized(cam, limbs)
    n = np.array([-120.0, 300.0]) / np.hypot(120.0, 300.0)  # the limbs' normal, from limb 0 towards limb 1
    for j, sign in ((0, -1.0), (1, 1.0)):
        moved = limbs[0, j] + 0.2 * sign * n  # 0.2 px outward in the image
        exact = cam.undistort_points(moved) - cam.undistort_points(limbs[0, j])
        assert np.allclose(0.2 * dxn[0, j], exact, rtol=2e-3, atol=0)  # linear to 0.1% over 0.2 px
    # near the corner the undistortion magnifies a pixel: a constant in normalized coordinates is not one in pixels
    mag = np.linalg.norm(dxn[0, 0], axis=1) * cam.focal_px
    assert mag.max() > 1.1 * mag.min() and mag.min() > 1.0  # 1.18 px per px at (100, 80), 1.04 at (400, 200)
