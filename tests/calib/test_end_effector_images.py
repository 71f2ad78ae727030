"""End-effector method with per-pose board covariances (what the image extraction reports as ``board.cov``).

The geometric twin's board poses are re-drawn from heteroscedastic, anisotropic covariances shaped like a
PnP pose's (depth the noisiest, rotation and lateral translation correlated, a few poses much worse than the
others); the covariance written into each pose is the true one divided by a common factor (the extraction's
covariances are optimistic by an unknown factor that the method must measure).
"""

import numpy as np
import pytest

from calib.formats.observations import Observations
from calib.identify import calibrate_end_effector
from calib.identify.end_effector import _left_jacobian, board_covariances
from calib.model.parameters import COMBINATION_NAMES
from calib.numerics.transforms import matrix_to_rotvec, rotvec_to_matrix
from drivers.sim.twin import GeometricTwin, NoiseSpec

N_TRIALS = 40
OPTIMISM = 3.0  # true board-pose std / the std the written covariance claims


def _pnp_like_cov(rng: np.random.Generator) -> np.ndarray:
    """A (left rotation [rad], t [m]) covariance (6, 6): tilt <-> lateral translation correlated, depth noisy."""
    s = np.array([1e-3, 1e-3, 2e-4, 1.5e-4, 1.5e-4, 8e-4]) * rng.lognormal(0.0, 0.4)
    C = np.diag(s**2)
    for rot, tra, sign in ((0, 4, -1.0), (1, 3, 1.0)):  # a tilt about x moves the board along y, etc.
        C[rot, tra] = C[tra, rot] = sign * 0.8 * s[rot] * s[tra]
    return C


def _documents(seed: int, outliers: int = 0) -> tuple[dict, dict]:
    """Observations with per-pose covariances, and the same without them (``cov`` removed)."""
    doc = GeometricTwin(noise=NoiseSpec.zero()).observations(seed=0)
    rng = np.random.default_rng(seed)
    k = 0
    for fr in doc["frames"]:
        if not fr.get("board"):
            continue
        C = _pnp_like_cov(rng)
        if fr["phase"] == "poses" and k < 2:
            C *= 30.0  # two poses far worse than the others (few corners, grazing view)
        if fr["phase"] == "poses":
            k += 1
        e = rng.multivariate_normal(np.zeros(6), C)
        if fr["phase"] == "poses" and k <= outliers:
            e[:3] += np.array([0.0, 0.05, 0.0])  # a gross error its covariance does not announce (3 deg)
        R = rotvec_to_matrix(e[:3]) @ np.asarray(fr["board"]["R"])
        T = np.eye(6)
        T[:3, :3] = np.linalg.inv(_left_jacobian(matrix_to_rotvec(R)))  # left rotation -> rotation vector
        fr["board"] = {
            "R": R.tolist(),
            "t": (np.asarray(fr["board"]["t"]) + e[3:]).tolist(),
            "cov": (T @ C @ T.T / OPTIMISM**2).tolist(),
        }
        fr["q"] = (np.asarray(fr["q"]) + rng.normal(0.0, 1e-6, 4)).tolist()
    plain = {
        **doc,
        "frames": [
            {**fr, "board": {k: v for k, v in fr["board"].items() if k != "cov"}} if fr.get("board") else fr
            for fr in doc["frames"]
        ],
    }
    return doc, plain


def test_board_covariance_is_converted_to_left_rotation():
    rng = np.random.default_rng(3)
    doc, _ = _documents(1)
    obs = Observations.from_dict(doc)
    data = obs.arrays("poses")
    C = board_covariances(obs, data)
    assert C is not None and C.shape == (len(data), 6, 6)
    # the conversion is J_l: a small change d of the rotation vector is the left rotation J_l d
    rv = matrix_to_rotvec(data.board_R[0])
    d = rng.normal(0.0, 1e-6, 3)
    left = matrix_to_rotvec(rotvec_to_matrix(rv + d) @ data.board_R[0].T)
    np.testing.assert_allclose(left, _left_jacobian(rv) @ d, rtol=1e-5, atol=1e-13)
    # and C (left) carries the written one back: T C_rvec T^T
    T = np.eye(6)
    T[:3, :3] = _left_jacobian(rv)
    np.testing.assert_allclose(C[0], T @ np.asarray(doc["frames"][int(data.index[0])]["board"]["cov"]) @ T.T)


def test_no_covariance_falls_back_to_the_residual_model():
    _, plain = _documents(2)
    r = calibrate_end_effector(Observations.from_dict(plain))
    assert r.diagnostics["board_noise_model"] == "diagonal, from residuals"
    assert r.diagnostics["board_cov_factor"] is None


def test_gross_pose_error_is_rejected():
    doc, _ = _documents(4, outliers=1)
    obs = Observations.from_dict(doc)
    r = calibrate_end_effector(obs)
    first_pose = int(obs.arrays("poses").index[0])
    assert first_pose in r.diagnostics["rejected_poses"]


@pytest.fixture(scope="module")
def monte_carlo():
    truth = GeometricTwin().geometry.truth.combinations()
    t = np.array([truth[k] for k in COMBINATION_NAMES])
    out = {"cov": {"err": [], "std": [], "factor": []}, "plain": {"err": [], "std": []}}
    for seed in range(200, 200 + N_TRIALS):
        doc, plain = _documents(seed)
        r = calibrate_end_effector(Observations.from_dict(doc))
        out["cov"]["err"].append(r.vector() - t)
        out["cov"]["std"].append(r.std_vector())
        out["cov"]["factor"].append(r.diagnostics["board_cov_factor"])
        p = calibrate_end_effector(Observations.from_dict(plain))
        out["plain"]["err"].append(p.vector() - t)
        out["plain"]["std"].append(p.std_vector())
    return {m: {k: np.asarray(v) for k, v in d.items()} for m, d in out.items()}


@pytest.mark.slow
def test_per_pose_covariances_give_honest_std(monte_carlo):
    d = monte_carlo["cov"]
    rms = np.sqrt(np.mean(d["err"] ** 2, axis=0))
    ratio = rms / np.sqrt(np.mean(d["std"] ** 2, axis=0))
    assert np.all((ratio > 1 / 1.3) & (ratio < 1.3)), f"RMS error / reported std = {np.round(ratio, 3)}"
    assert (np.abs(d["err"]) / d["std"]).max() < 4.0
    # the factor measured from the residuals is the covariances' optimism
    assert abs(np.median(d["factor"]) / OPTIMISM - 1.0) < 0.15, np.median(d["factor"])


@pytest.mark.slow
def test_per_pose_covariances_beat_one_noise_for_all_poses(monte_carlo):
    rms_cov = np.sqrt(np.mean(monte_carlo["cov"]["err"] ** 2, axis=0))
    rms_plain = np.sqrt(np.mean(monte_carlo["plain"]["err"] ** 2, axis=0))
    assert np.all(rms_cov < 0.8 * rms_plain), f"{np.round(rms_cov * 1e3, 3)} vs {np.round(rms_plain * 1e3, 3)} mm"
