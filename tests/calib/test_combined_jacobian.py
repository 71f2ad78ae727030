"""The combined fit's closed-form Jacobian against central differences of the residuals it differentiates.

The combined method's fits (outlier gate, eq. 8, joint passes) and its covariance use the closed-form derivatives of
eq. 8's residuals: the model's Jacobian entries with the combinations, the measured ones with the base frame's
rotation and with the intrinsics' nuisance (each rod's limb samples undistorted for the moved intrinsics, their
planes, the rod's direction). Each piece, and the whole, is pinned here against central differences of the function
itself, on the geometric twin's rods seen through a camera with every lens term the calibration can choose
(OpenCV's rational model, tangential terms): the twin has no images, so the rods' limb samples are their
limb lines projected through that camera.
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.formats.camera import CameraModel
from calib.formats.observations import Observations
from calib.identify import combined as cb
from calib.identify import intrinsics as intr
from calib.model.parameters import COMBINATION_NAMES
from calib.numerics.numdiff import central_jacobian
from calib.numerics.transforms import cross, rotvec_to_matrix
from drivers.sim.twin import GeometricTwin

NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: the intrinsics' std (px for fx..cy): a bench camera's calibration
STD = np.array([0.8, 0.7, 0.6, 0.5, 2e-3, 5e-3, 1e-4, 1e-4, 1e-2, 1e-3, 2e-3, 5e-3])
ROD_RADIUS_M = 0.004


def _camera() -> CameraModel:
    K = np.array([[380.0, 0.0, 515.0], [0.0, 384.0, 380.0], [0.0, 0.0, 1.0]])  # the twin's wide field
    dist = np.array([-0.05, 0.01, 4e-4, -3e-4, 1e-3, 5e-3, -2e-3, 1e-3])
    corr = np.full((len(NAMES), len(NAMES)), 0.3) + 0.7 * np.eye(len(NAMES))
    cal = {"covariance": (np.outer(STD, STD) * corr).tolist(), "covariance_params": list(NAMES)}
    return CameraModel(K, dist, 1024, 768, {"calibration": cal})


def _limbs(camera: CameraModel, p: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Each rod's two limb lines (axis +/- the radius across the view), 5 samples each, in distorted px (M, 2, 5, 2)."""
    view = p / np.linalg.norm(p, axis=1, keepdims=True)
    o = cross(u, view)
    o /= np.linalg.norm(o, axis=1, keepdims=True)
    t = np.linspace(-0.02, 0.02, 5)[None, None, :, None]
    side = np.array([-1.0, 1.0])[None, :, None, None]
    X = p[:, None, None] + side * ROD_RADIUS_M * o[:, None, None] + t * u[:, None, None]
    xn = X[..., :2] / X[..., 2:]
    return camera.distort_normalized(xn.reshape(-1, 2)).reshape(xn.shape)


@pytest.fixture(scope="module")
def eq8() -> cb._Eq8:
    """Eq. 8 over the twin's rods of 20 poses with the intrinsics (and two limb-edge biases) as nuisance."""
    doc = GeometricTwin().observations(seed=3)
    obs = Observations.from_dict(doc)
    data = obs.arrays("poses")
    keep = np.zeros(len(data), bool)
    keep[np.flatnonzero(np.any(data.has_rod, axis=(1, 2)))[:20]] = True
    data = data.subset(keep)
    R0 = rotvec_to_matrix(np.array([0.6, -0.2, 0.1]))
    prob = cb._Problem(data, R0)
    camera = _camera()
    limbs = _limbs(camera, data.rod_p[prob.k, prob.leg, prob.rod], prob.u_cam)
    inside = np.all((limbs >= 0) & (limbs <= [camera.width - 1, camera.height - 1]), axis=(1, 2, 3))
    prob.select(inside)  # the rods the camera sees whole (the twin's field of view is wider)
    p, limbs = data.rod_p[prob.k, prob.leg, prob.rod], limbs[inside]
    assert len(p) >= 40
    H = intr.limb_planes_for(camera, limbs, np.ones((len(p), 2, 3)))
    u = cross(H[:, 0], H[:, 1])
    prob.u_cam = u / np.linalg.norm(u, axis=1, keepdims=True) * np.sign(np.sum(u * prob.u_cam, axis=1))[:, None]
    steps = intr.principal_steps(np.asarray(camera.extra["calibration"]["covariance"]))
    G = np.random.default_rng(0).normal(0.0, 1e-3, (3, steps.shape[0]))
    prob.intrinsics = cb.RodIntrinsicsModel(camera, steps, limbs, H, G, edge_std_px=0.1)
    m, nz = len(p), steps.shape[0] + 2
    eye = np.broadcast_to(np.eye(2), (m, 2, 2))
    return cb._Eq8(prob, eye, R0, True, np.eye(3), np.zeros(nz), eye)


def _unknowns(eq8: cb._Eq8, seed: int) -> np.ndarray:
    """Combinations near nominal, a rotation refinement of a few mrad and the nuisance within 2 std."""
    rng = np.random.default_rng(seed)
    nominal = GeometricTwin().geometry.nominal.combinations()
    xi = np.array([nominal[k] for k in COMBINATION_NAMES])
    return np.concatenate([xi, rng.normal(0.0, 3e-3, 3), rng.normal(0.0, 1.0, eq8.z0.size)])


def _close(J: np.ndarray, ref: np.ndarray, rtol: float) -> None:
    """Each column within ``rtol`` of the reference column's largest entry."""
    scale = np.abs(ref).max(axis=0)
    assert np.all(scale > 0)
    err = np.abs(J - ref).max(axis=0) / scale
    assert err.max() < rtol, err


@pytest.mark.parametrize("seed", [0, 1])
def test_eq8_jacobian_is_the_central_difference_of_its_residuals(eq8, seed):
    """The residuals' closed-form derivatives (combinations, base-frame rotation, intrinsics and edge biases) are
    the central differences' within 1e-6 of each column's scale (their step: the differences' truncation and the
    undistortion's rounding both below that)."""
    v = _unknowns(eq8, seed)
    J = eq8.raw_jacobian(v)
    assert J.shape == (2 * eq8.m, v.size)
    h = np.r_[np.full(4, 1e-6), np.full(3, 1e-6), np.full(eq8.z0.size, 1e-3)]
    ref = np.column_stack([central_jacobian(eq8.raw, v, float(hj))[:, j] for j, hj in enumerate(h)])
    _close(J, ref, 1e-6)
    # weighted and with the priors, as the fits see them
    Je = eq8.eq8_jacobian(v)
    np.testing.assert_allclose(Je, np.einsum("mij,mjk->mik", eq8.Wh, J.reshape(eq8.m, 2, -1)).reshape(J.shape))
    _close(eq8.priors_jacobian()[:, 4:], central_jacobian(eq8.priors, v, 1e-3)[:, 4:], 1e-12)


def test_limb_points_move_as_the_exact_undistortion_does(eq8):
    """The limb samples' derivatives with the intrinsics' principal directions: central differences of the camera's
    own (iterative) undistortion, every lens term of the rational model and the tangential terms."""
    lim = eq8.prob.intrinsics.limbs
    z = np.random.default_rng(5).normal(0.0, 1.0, lim.steps.shape[0])
    D = lim.points_jacobian(z, lim.points(z))
    flat = lim.px.reshape(-1, 2)
    h = 1e-4
    for j in range(lim.steps.shape[0]):
        e = np.zeros_like(z)
        e[j] = h
        plus, minus = (
            intr.perturbed_camera(lim.camera, lim.steps.T @ zz).undistort_points(flat) for zz in (z + e, z - e)
        )
        ref = ((plus - minus) / (2 * h)).reshape(lim.shape)
        assert np.abs(D[j] - ref).max() < 1e-6 * np.abs(ref).max(), j


def test_plane_normals_move_as_the_line_fit_does(eq8):
    """The limbs' planes' derivatives along random moves of their points: central differences of the line fit."""
    lim = eq8.prob.intrinsics.limbs
    xn, H = lim.xn0, eq8.prob.intrinsics.H
    moves = np.random.default_rng(2).normal(0.0, 1e-3, (3, *xn.shape))
    h, dh = intr.planes_through_jacobian(xn, moves, H)
    np.testing.assert_array_equal(h, intr.planes_through(xn, H))
    for k in range(3):
        ref = (intr.planes_through(xn + 1e-4 * moves[k], H) - intr.planes_through(xn - 1e-4 * moves[k], H)) / 2e-4
        assert np.abs(dh[k] - ref).max() < 1e-6 * np.abs(ref).max()


def test_model_and_rotation_derivatives_are_their_central_differences():
    """The model's Jacobian entries with the combinations and a rotation matrix with its rotation vector."""
    twin = GeometricTwin()
    q = np.asarray(Observations.from_dict(twin.observations(seed=1)).arrays("poses").q)
    nominal = twin.geometry.nominal.combinations()
    xi = np.array([nominal[k] for k in COMBINATION_NAMES])
    J = cb.model_ratios_jacobian(xi, q).reshape(-1, 4)
    _close(J, central_jacobian(lambda c: cb.model_ratios(c, q).ravel(), xi, 1e-7), 1e-7)
    for w in (np.array([0.3, -0.5, 0.2]), np.array([1e-9, 0.0, -2e-9]), np.zeros(3)):
        dR = cb.rotvec_derivatives(w)
        ref = central_jacobian(lambda r: rotvec_to_matrix(r).ravel(), w, 1e-6)
        np.testing.assert_allclose(dR.reshape(3, 9).T, ref, atol=1e-9)
