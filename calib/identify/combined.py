"""The paper's proposal: the Jacobian estimated from the legs in the base frame (eq. 8).

For each fit pose k, vision gives every rod's axis direction in the camera frame; the base frame
(:mod:`calib.identify.baseframe`) turns it into the base frame, where the pose-dependent entries of the
IKM Jacobian are the ratios ``u_iy / u_ix`` and ``u_iz / u_ix`` (eq. 4; sign and norm of u do not
matter). The model computes the same entries from the encoder values through the DKM, as a
function of the four identifiable combinations only. The fit minimises the Frobenius norm of the
difference (eq. 8) with ``scipy.optimize.least_squares``; each rod contributes its own estimate
of its leg's Jacobian row.

Standard deviations combine (i) the per-pose noise (rod directions and encoders), with the
direction-noise level and the rods' shared errors (a leg's same-frame pair, rods seen at nearby places of the
image: :mod:`.rod_correlation`) estimated from the residuals with what the fit absorbs accounted for, and (ii) the
base-frame rotation's, the intrinsics' and the limb-edge bias's covariances propagated through the fit: they are
common to all poses and their errors do not show in the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
from scipy.optimize import least_squares

from calib.errors import IdentifiabilityError
from calib.formats.camera import CameraModel
from calib.formats.observations import LegKey, Observations, PhaseArrays
from calib.identify import intrinsics as intr
from calib.identify import rod_correlation as rc
from calib.identify.baseframe import BaseFrameResult, base_frame_from_observations, estimate_base_frame
from calib.identify.iterations import IterationCallback, traced_jac
from calib.identify.pose_set_model import PoseSetModel
from calib.identify.result import MethodResult, check_excitation, combos_dict, std_dict
from calib.identify.stationary import check_converged
from calib.model.kinematics import dkm, jacobian_ratios, leg_directions, pose_from_joints_reduced
from calib.model.parameters import COMBINATION_NAMES, I4Parameters
from calib.numerics.numdiff import central_jacobian
from calib.numerics.robust import chi2_outliers, robust_chi2_scale
from calib.numerics.transforms import cross, matrix_to_rotvec, rotvec_to_matrix

Weighting = Literal["auto", "frobenius", "gls"]

# sign of u_x in each leg's model direction: u1 = (f1, Y+c, Z), u2 = (-f1, Y+c, Z), ...
_SX = np.array([1.0, -1.0, 1.0, -1.0])

#: Prior std (px) of the limb-edge bias common to every rod: twice the extraction's per-rod allowance
#: (``RodSettings.edge_bias_px``, 0.05 px end to end), since a bias shared by every rod (lighting, optics)
#: is not bounded by what one rod's residuals show
EDGE_BIAS_STD_PX = 0.1


def model_ratios(combos: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Jacobian entries ``(u_iy/u_ix, u_iz/u_ix)`` predicted from encoder values.

    Parameters
    ----------
    combos : ndarray, shape (4,)
        ``(L, H-D, S-q02/2, S-(q04-q03)/2)`` in metres.
    q : ndarray, shape (N, 4)
        Encoder values, m.

    Returns
    -------
    ndarray, shape (N, 4, 2)
        Per pose and leg, ``(u_y/u_x, u_z/u_x)`` (dimensionless).
    """
    c = combos[1]
    Y, Z, f1, f3 = pose_from_joints_reduced(combos, q)
    out = np.empty((q.shape[0], 4, 2))
    for i, (f, yoff) in enumerate(((f1, Y + c), (f1, Y + c), (f3, Y - c), (f3, Y - c))):
        out[:, i, 0] = yoff / (_SX[i] * f)
        out[:, i, 1] = Z / (_SX[i] * f)
    return out


def model_ratios_jacobian(combos: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Derivatives of :func:`model_ratios` with the four combinations (closed form).

    Parameters
    ----------
    combos : ndarray, shape (4,)
        ``(L, H-D, S-q02/2, S-(q04-q03)/2)`` in metres.
    q : ndarray, shape (N, 4)
        Encoder values, m.

    Returns
    -------
    ndarray, shape (N, 4, 2, 4)
        Per pose and leg, d(u_y/u_x, u_z/u_x) / d combination (1/m).
    """
    L, c = float(combos[0]), float(combos[1])
    Y, Z, f1, f3 = pose_from_joints_reduced(combos, q)
    a, b = 2.0 * f1, 2.0 * f3
    n = q.shape[0]
    zero, one = np.zeros(n), np.ones(n)
    # per combination (L, c, s1, s3): dY, da, db, then dZ from Z^2 = L^2 - c^2 - Y^2 - (a^2 + b^2) / 8
    dY = np.stack([zero, -Y / c, a / (4.0 * c), -b / (4.0 * c)], axis=-1)  # (N, 4)
    da = np.stack([zero, zero, -2.0 * one, zero], axis=-1)
    db = np.stack([zero, zero, zero, -2.0 * one], axis=-1)
    dzsq = np.stack([2.0 * L * one, -2.0 * c * one, zero, zero], axis=-1) - 2.0 * Y[:, None] * dY
    dzsq -= (a[:, None] * da + b[:, None] * db) / 4.0
    safe = np.where(Z < 0, Z, -1.0)
    dZ = np.where((Z < 0)[:, None], dzsq / (2.0 * safe[:, None]), 0.0)
    dc = np.array([0.0, 1.0, 0.0, 0.0])
    out = np.empty((n, 4, 2, 4))
    left, right = (f1, da / 2.0, Y + c, dY + dc), (f3, db / 2.0, Y - c, dY - dc)  # legs 1-2 and 3-4
    legs = (left, left, right, right)
    for i, (f, df, yoff, dyoff) in enumerate(legs):
        out[:, i, 0] = (dyoff * f[:, None] - yoff[:, None] * df) / (_SX[i] * f[:, None] ** 2)
        out[:, i, 1] = (dZ * f[:, None] - Z[:, None] * df) / (_SX[i] * f[:, None] ** 2)
    return out


def rotvec_derivatives(w: np.ndarray) -> np.ndarray:
    """The derivatives of ``exp([w]x)`` (:func:`~calib.numerics.transforms.rotvec_to_matrix`) with each entry of the
    rotation vector ``w``: ``[J_l(w) e_j]x exp([w]x)``, ``J_l`` the left Jacobian of SO(3).

    Parameters
    ----------
    w : ndarray, shape (3,)
        Rotation vector, rad.

    Returns
    -------
    ndarray, shape (3, 3, 3)
        ``d R / d w_j`` for j = 0, 1, 2 (per rad).
    """
    w = np.asarray(w, dtype=np.float64)
    th2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th2 < 1e-12:  # series: (1 - cos t)/t^2 ~ 1/2 - t^2/24, (t - sin t)/t^3 ~ 1/6 - t^2/120
        A, B = 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = np.sqrt(th2)
        A, B = (1.0 - np.cos(th)) / th2, (th - np.sin(th)) / (th2 * th)
    Jl = np.eye(3) + A * W + B * (W @ W)
    R = rotvec_to_matrix(w)
    out = np.empty((3, 3, 3))
    for j in range(3):
        v = Jl[:, j]
        out[j] = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]) @ R
    return out


def pose_set_model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    """The combined method's measurement model at encoder values ``q`` (N, 4), m: the Jacobian entries (eq. 4) the
    legs give in the base frame, ``(u_iy/u_ix, u_iz/u_ix)`` per pose and leg, (N * 4 * 2,), as a function of the seven
    parameters (no nuisance: the base frame is measured apart).

    Parameters
    ----------
    params : I4Parameters
        The geometry at which the model is linearised (its seven parameters are the vector).
    q : array_like, shape (N, 4)
        Encoder values of the poses, m.

    Returns
    -------
    PoseSetModel
        The prediction (N * 4 * 2,), dimensionless, as a function of the seven parameters, m, no nuisance.
    """
    q = np.asarray(q, dtype=np.float64)

    def f(v: np.ndarray) -> np.ndarray:
        p = I4Parameters.from_vector(v, T_per_rad=params.T_per_rad)
        return jacobian_ratios(leg_directions(p, dkm(p, q))).ravel()

    return PoseSetModel(f, params, 0)


def ratio_gradient(u: np.ndarray) -> np.ndarray:
    """The Jacobian entries' derivatives in the directions ``u`` (M, 3): d(u_y/u_x, u_z/u_x)/du, shape (M, 2, 3).

    Parameters
    ----------
    u : ndarray, shape (M, 3)
        Leg or rod directions, base frame, unit (u_x nonzero).

    Returns
    -------
    ndarray, shape (M, 2, 3)
        The derivatives (dimensionless per unit of direction).
    """
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    G = np.zeros((u.shape[0], 2, 3))
    G[:, 0, 0] = -uy / ux**2
    G[:, 0, 1] = 1.0 / ux
    G[:, 1, 0] = -uz / ux**2
    G[:, 1, 2] = 1.0 / ux
    return G


def raw_jacobian(prob: _Problem, v: np.ndarray, R0: np.ndarray, joint: bool) -> np.ndarray:
    """Derivatives (2M, 4 + nw + nz) of eq. 8's unweighted residuals ``model - measured`` with the unknowns ``v``:
    the combinations (4, m), the base frame's rotation refinement ``w`` (3 when ``joint``, else none; rad, applied
    on the left of ``R0``) and the nuisance ``z`` (nz).

    Parameters
    ----------
    prob : _Problem
        The rods.
    v : ndarray, shape (4 + nw + nz,)
        The unknowns.
    R0 : ndarray, shape (3, 3)
        The base frame's rotation ``w`` refines.
    joint : bool
        Whether ``v`` holds ``w``.

    Returns
    -------
    ndarray, shape (2M, 4 + nw + nz)
        Dimensionless per m (combinations), per rad (``w``) and per standard deviation (``z``).
    """
    nw = 3 if joint else 0
    w, z = v[4 : 4 + nw], v[4 + nw :]
    if joint:
        R, dR = rotvec_to_matrix(w) @ R0, rotvec_derivatives(w) @ R0
    else:
        R, dR = R0, np.zeros((0, 3, 3))
    Jm = prob.measured_jacobian(R, dR, z)
    return np.concatenate([prob.model_jacobian(v[:4]), -Jm], axis=2).reshape(-1, v.size)


class _Problem:
    """Residuals of eq. 8 for the rods observed in the fit poses."""

    def __init__(self, data: PhaseArrays, R_cb: np.ndarray, min_ux: float = 0.05) -> None:
        k_idx, leg_idx, rod_idx = np.nonzero(data.has_rod)
        u_cam = data.rod_u[k_idx, leg_idx, rod_idx]
        self.u_cam = u_cam
        self.k = k_idx
        self.leg = leg_idx
        self.rod = rod_idx
        self.q = data.q
        self.R_cb = R_cb
        uB = u_cam @ R_cb
        keep = np.abs(uB[:, 0]) >= min_ux
        self.dropped = int((~keep).sum())
        for name in ("u_cam", "k", "leg", "rod"):
            setattr(self, name, getattr(self, name)[keep])
        self.n_poses = len(np.unique(self.k))
        self.intrinsics: RodIntrinsicsModel | None = None

    def select(self, keep: np.ndarray) -> None:
        """Keep only the rods where ``keep`` (bool, (M,)) is set."""
        for name in ("u_cam", "k", "leg", "rod"):
            setattr(self, name, getattr(self, name)[keep])
        if self.intrinsics is not None:
            self.intrinsics.select(keep)
        self.n_poses = len(np.unique(self.k))

    def measured(self, R_cb: np.ndarray | None = None, z: np.ndarray | None = None) -> np.ndarray:
        """The measured Jacobian entries (M, 2); with ``z``, for the intrinsics moved by ``z``."""
        R = self.R_cb if R_cb is None else R_cb
        u = self.u_cam
        if z is not None and z.size and self.intrinsics is not None:
            u, R = self.intrinsics.directions(z, u), self.intrinsics.rotation(z) @ R
        uB = u @ R
        return uB[:, 1:] / uB[:, :1]

    def model(self, combos: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
        r = model_ratios(combos, self.q if q is None else q)
        return r[self.k, self.leg]

    def model_jacobian(self, combos: np.ndarray) -> np.ndarray:
        """Derivatives (M, 2, 4) of :meth:`model` with the combinations (1/m)."""
        return model_ratios_jacobian(combos, self.q)[self.k, self.leg]

    def measured_jacobian(self, R_cb: np.ndarray, dR_cb: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Derivatives (M, 2, k + nz) of :meth:`measured` with the unknowns ``R_cb`` moves with (``dR_cb`` (k, 3, 3),
        its derivatives) and then with the nuisance ``z`` (nz,)."""
        u, R = self.u_cam, R_cb
        dB = [u @ dR_cb]  # (k, M, 3): d(u @ R) per unknown
        if z.size and self.intrinsics is not None:
            A = self.intrinsics.rotation(z)
            u, du = self.intrinsics.directions_jacobian(z, self.u_cam)
            dB = [u @ A @ dR_cb, du @ (A @ R_cb) + u @ (self.intrinsics.rotation_jacobian(z) @ R_cb)]
            R = A @ R_cb
        G = ratio_gradient(u @ R)  # (M, 2, 3)
        return np.einsum("mij,kmj->mik", G, np.concatenate(dB))

    def residuals(self, combos: np.ndarray) -> np.ndarray:
        return (self.model(combos) - self.measured()).ravel()

    def noise_shape(self, use_rod_cov: np.ndarray | None = None) -> np.ndarray:
        """Relative covariance of each rod's 2 ratio residuals for direction noise, (M, 2, 2)."""
        uB = self.u_cam @ self.R_cb
        G = ratio_gradient(uB)
        P = np.eye(3)[None] - uB[:, :, None] * uB[:, None, :]
        if use_rod_cov is not None:
            P = np.einsum("ji,mjk,kl->mil", self.R_cb, use_rod_cov, self.R_cb)
        return np.einsum("mij,mjk,mlk->mil", G, P, G)


@dataclass(frozen=True)
class CombinedSettings:
    """The combined method's settings (see :func:`calibrate_combined` for each).

    Attributes
    ----------
    weighting : {"auto", "frobenius", "gls"}
    phases : tuple of str
        Phases whose frames are fit poses.
    encoder_std_m : float
        Encoder noise, m.
    edge_bias_std_px : float
        Prior std (px) of the limb-edge bias common to every rod (0: not modelled).
    """

    weighting: Weighting = "auto"
    phases: tuple[str, ...] = ("poses",)
    encoder_std_m: float = 1e-6
    edge_bias_std_px: float = EDGE_BIAS_STD_PX


@dataclass
class _Rods:
    """The rods of the fit poses ready for eq. 8: the problem, the observations' arrays, the base frame, the rods'
    measured direction covariances ((M, 3, 3) or None) and the intrinsics' nuisance size."""

    prob: _Problem
    data: PhaseArrays
    bf: BaseFrameResult
    rod_cov: np.ndarray | None
    weighting: str
    ni: int = 0  # intrinsics' principal directions
    nz: int = 0  # and the limb-edge biases

    @property
    def steps(self) -> np.ndarray | None:
        return None if self.prob.intrinsics is None else self.prob.intrinsics.steps

    @property
    def z0(self) -> np.ndarray:
        """The nuisance unknowns' prior mean (the calibration's intrinsics in their units)."""
        return np.zeros(self.nz) if self.prob.intrinsics is None else self.prob.intrinsics.z0


@dataclass
class _Eq8:
    """Eq. 8 with the base frame's refinement ``w`` (3 when its covariance is known) and the intrinsics' ``z`` as
    nuisance unknowns: unknowns ``v = (combinations (4, m), w (nw, rad), z (nz, units of their std))``."""

    prob: _Problem
    Wh: np.ndarray  # (m, 2, 2) each rod's whitening (identity for the Frobenius weighting)
    R0: np.ndarray  # (3, 3) the base frame's board-only rotation
    joint: bool  # the rotation is refined with its prior
    Lw: np.ndarray  # (3, 3) Lw^T Lw = its information (zeros when not joint)
    z0: np.ndarray  # (nz,) the nuisance's prior mean
    shape: np.ndarray  # (m, 2, 2) each rod's relative noise covariance (dimensionless)

    @property
    def m(self) -> int:
        return self.Wh.shape[0]

    @property
    def nw(self) -> int:
        return 3 if self.joint else 0

    def split(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nw = self.nw
        return v[:4], (v[4 : 4 + nw] if self.joint else np.zeros(3)), v[4 + nw :]

    def raw(self, v: np.ndarray) -> np.ndarray:
        """Unweighted residuals (2m,): model minus measured Jacobian entries."""
        xi, w, z = self.split(v)
        return (self.prob.model(xi) - self.prob.measured(rotvec_to_matrix(w) @ self.R0, z)).ravel()

    def eq8(self, v: np.ndarray) -> np.ndarray:
        """Weighted residuals (2m,)."""
        return np.einsum("mij,mj->mi", self.Wh, self.raw(v).reshape(self.m, 2)).ravel()

    def raw_jacobian(self, v: np.ndarray) -> np.ndarray:
        """Derivatives (2m, 4 + nw + nz) of :meth:`raw` with ``v`` (closed form)."""
        return raw_jacobian(self.prob, v, self.R0, self.joint)

    def eq8_jacobian(self, v: np.ndarray) -> np.ndarray:
        """Derivatives (2m, 4 + nw + nz) of :meth:`eq8` with ``v``."""
        J = self.raw_jacobian(v).reshape(self.m, 2, -1)
        return np.einsum("mij,mjk->mik", self.Wh, J).reshape(2 * self.m, -1)

    def priors_jacobian(self) -> np.ndarray:
        """Derivatives (nw + nz, 4 + nw + nz) of :meth:`priors` (constant)."""
        nw, nz = self.nw, self.z0.size
        out = np.zeros((nw + nz, 4 + nw + nz))
        if self.joint:
            out[:nw, 4 : 4 + nw] = self.Lw
        out[nw:, 4 + nw :] = np.eye(nz)
        return out

    def priors(self, v: np.ndarray) -> np.ndarray:
        _xi, w, z = self.split(v)
        return np.concatenate([self.Lw @ w if self.joint else np.zeros(0), z - self.z0])


@dataclass
class _Eq8Solution:
    """The fit's unknowns ``x``, the direction-noise scale ``s2`` (chi-square per dof), evaluations, scipy's last
    solution and the stages that stopped at their minimum out of evaluations."""

    x: np.ndarray
    s2: float
    nfev: int
    sol: Any
    stopped_stationary: list[dict[str, Any]]


@dataclass
class _Covariance:
    """The combinations' covariance (4, 4), m^2, its named parts, the rods' error model and the prior blocks."""

    cov: np.ndarray
    parts: dict[str, np.ndarray]
    errs: rc.RodErrors
    cov_intr: np.ndarray | None
    cov_lens: np.ndarray | None
    n_pairs: int


def calibrate_combined(
    obs: Observations,
    *,
    base_frame: BaseFrameResult | None = None,
    weighting: Weighting = "auto",
    phases: tuple[str, ...] = ("poses",),
    encoder_std_m: float = 1e-6,
    on_iteration: IterationCallback | None = None,
    edge_bias_std_px: float = EDGE_BIAS_STD_PX,
    settings: CombinedSettings | None = None,
) -> MethodResult:
    """Identify the four combinations from leg observations and the base frame (eq. 8).

    Parameters
    ----------
    obs : Observations
        Needs board poses in the ``rotation`` and ``translation`` phases (base frame) and rod
        directions in the fit phases.
    base_frame : BaseFrameResult, optional
        Computed from ``obs`` when not given.
    weighting : {"auto", "frobenius", "gls"}
        ``"auto"`` (default): ``"gls"`` when every rod carries its measured direction covariance
        (``cov_u``, as the image extraction reports it; a rod's depth direction is tens of times
        less precise than its image direction), else ``"frobenius"``.
        ``"frobenius"``: the paper's eq. 8 (every Jacobian entry weighs the same).
        ``"gls"``: each rod's two entries whitened by their predicted direction-noise covariance
        (the maximum-likelihood fit for direction noise; more efficient when legs are steep).
    phases : tuple of str
        Phases whose frames are fit poses.
    encoder_std_m : float
        Encoder noise, metres (propagated; negligible against direction noise in practice).
    on_iteration : callable, optional
        Receives ``{"stage", "iteration", "cost"}`` after each iteration of the fits (:mod:`.iterations`).
    edge_bias_std_px : float
        Prior standard deviation (px) of the limb-edge bias common to every rod (one outward offset per
        limb, nuisance unknowns of the fit with the intrinsics'; 0: not modelled). Needs the rods' limb
        samples (``limbs_px``).
    settings : CombinedSettings, optional
        The settings at once; given, it replaces ``weighting``, ``phases``, ``encoder_std_m`` and
        ``edge_bias_std_px``.

    Returns
    -------
    MethodResult

    Raises
    ------
    IdentifiabilityError
        Missing base-frame phases, too few rods, or a pose set that does not excite a parameter.
    ConvergenceError
        The fit did not converge.
    """
    cfg = settings or CombinedSettings(weighting, phases, encoder_std_m, edge_bias_std_px)
    rods = combined_rods(obs, base_frame, cfg)
    x0 = np.concatenate([np.array([obs.nominal.combinations()[k] for k in COMBINATION_NAMES]), np.zeros(rods.nz)])
    rejected = gate_rods(rods, x0, on_iteration)
    problem = _eq8_problem(rods)
    fit = fit_eq8(problem, x0, on_iteration)
    r = problem.raw(fit.x).reshape(problem.m, 2)
    covariance = combined_covariance(obs, rods, problem, fit, r)
    return _combined_result(rods, problem, fit, covariance, r, rejected)


def combined_rods(obs: Observations, base_frame: BaseFrameResult | None, cfg: CombinedSettings) -> _Rods:
    """The fit poses' rods in the base frame, checked, with their covariances and the intrinsics' model.

    The camera's intrinsics are nuisance unknowns: z (n,) in units of one standard deviation along each principal
    direction of their covariance, prior N(0, I); the measured quantities move by D z to first order
    (:mod:`.intrinsics`). Their error is common to every rod, so it does not average out; the rods also carry
    information on it, which the joint fit uses.

    Parameters
    ----------
    obs : Observations
    base_frame : BaseFrameResult or None
        Computed from ``obs`` when None.
    cfg : CombinedSettings

    Returns
    -------
    _Rods
        M rods (directions in the camera frame, unit), their poses and legs.

    Raises
    ------
    IdentifiabilityError
        No frames in the phases, too few rods, or a pose set that does not excite a parameter.
    ValueError
        An unknown weighting.
    """
    bf = base_frame or base_frame_from_observations(obs)
    data = obs.arrays(*cfg.phases)
    if len(data) == 0:
        raise IdentifiabilityError(f"no frames in phase(s) {', '.join(cfg.phases)} for the combined fit")
    prob = _Problem(data, bf.camera_from_base_R)
    m = prob.u_cam.shape[0]
    if m * 2 < 8 or prob.n_poses < 2:
        raise IdentifiabilityError(
            f"the combined fit has {m} rod observations in {prob.n_poses} pose(s); it needs rods in at least "
            "2 poses (20 recommended)"
        )
    x0 = np.array([obs.nominal.combinations()[k] for k in COMBINATION_NAMES])
    check_excitation(central_jacobian(prob.residuals, x0), COMBINATION_NAMES)
    rod_cov = _rod_covariances(obs, data, prob)
    weighting: str = cfg.weighting
    if weighting == "auto":
        weighting = "gls" if rod_cov is not None else "frobenius"
    if weighting not in ("gls", "frobenius"):
        raise ValueError(f"weighting must be 'auto', 'frobenius' or 'gls', got {weighting!r}")
    prob.intrinsics = RodIntrinsicsModel.build(obs, data, prob, bf, cfg.edge_bias_std_px)
    rods = _Rods(prob, data, bf, rod_cov, weighting)
    if prob.intrinsics is not None:
        rods.ni = prob.intrinsics.steps.shape[0]
        rods.nz = rods.ni + prob.intrinsics.n_edge
    return rods


def gate_rods(rods: _Rods, x0: np.ndarray, on_iteration: IterationCallback | None) -> list[dict[str, int]]:
    """Outlier rods (a limb taken for another edge): a first fit, then every rod whose whitened residual is beyond the
    chi-square(2) 99.9% quantile of a robust noise scale is dropped and the fit repeated, until none is (at most 5
    rounds). ``rods`` keeps the others.

    Parameters
    ----------
    rods : _Rods
        Updated in place (its problem's rods and covariances).
    x0 : ndarray, shape (4 + nz,)
        Start: the combinations (m), then the nuisance unknowns (units of their std).
    on_iteration : callable, optional

    Returns
    -------
    list of dict
        The dropped rods: ``frame``, ``leg`` (1-4), ``rod`` (0-1).
    """
    prob, data = rods.prob, rods.data
    rejected: list[dict[str, int]] = []
    gate: tuple[np.ndarray, float] | None = None  # the previous round's solution and noise level: the next starts there
    for gate_round in range(5):
        shape = prob.noise_shape(rods.rod_cov)
        d2, gate = _whitened_d2(prob, shape, x0, rods.bf.cov_rotvec, on_iteration, start=gate, round_index=gate_round)
        bad = chi2_outliers(d2, 2)
        if not bad.any() or (~bad).sum() * 2 < 8:
            break
        rejected += [
            {"frame": int(data.index[k]), "leg": int(leg) + 1, "rod": int(rod)}
            for k, leg, rod in zip(prob.k[bad], prob.leg[bad], prob.rod[bad], strict=True)
        ]
        prob.select(~bad)
        if rods.rod_cov is not None:
            rods.rod_cov = rods.rod_cov[~bad]
    return rejected


def _eq8_problem(rods: _Rods) -> _Eq8:
    """Eq. 8 over the kept rods with its weighting and the base frame's prior."""
    prob = rods.prob
    m = prob.u_cam.shape[0]
    shape = prob.noise_shape(rods.rod_cov)  # relative covariance of each rod's two entries, (m, 2, 2)
    if rods.weighting == "gls":
        Wh = rc.whitening(shape)  # L^T L = C^-1
    else:
        Wh = np.broadcast_to(np.eye(2), (m, 2, 2))
    cov_w = rods.bf.cov_rotvec
    joint = bool(np.all(np.linalg.eigvalsh(cov_w) > 1e-20))
    Lw = np.linalg.cholesky(np.linalg.inv(cov_w)).T if joint else np.zeros((3, 3))
    return _Eq8(prob, Wh, rods.bf.camera_from_base_R, joint, Lw, rods.z0, shape)


def fit_eq8(problem: _Eq8, x0: np.ndarray, on_iteration: IterationCallback | None) -> _Eq8Solution:
    """1. The paper's fit: eq. 8 with the base frame of step 1 (and the intrinsics' prior). 2. The base frame's
    rotation is common to every pose: its error does not average out and it inflates the residuals; it is
    re-estimated jointly with the parameters (and the intrinsics), each with its prior, so that the fit and its
    covariance account for them; the data are weighed by 1/s2 against the priors (at most 3 passes).

    Parameters
    ----------
    problem : _Eq8
    x0 : ndarray, shape (4 + nz,)
        The combinations' start (m), then the nuisance's (zeros).
    on_iteration : callable, optional

    Returns
    -------
    _Eq8Solution
    """
    nw, nz = problem.nw, problem.z0.size
    x = np.concatenate([x0[:4], np.zeros(nw), x0[4:]])
    free = np.r_[np.ones(4, bool), np.zeros(nw, bool), np.ones(nz, bool)]

    def stage1(vf: np.ndarray) -> np.ndarray:
        v = x.copy()
        v[free] = vf
        return np.concatenate([problem.eq8(v), v[4 + nw :] - problem.z0])

    def stage1_jac(vf: np.ndarray) -> np.ndarray:
        v = x.copy()
        v[free] = vf
        return np.concatenate([problem.eq8_jacobian(v), problem.priors_jacobian()[nw:]])[:, free]

    fun, jac = traced_jac(stage1, stage1_jac, on_iteration, "eq8")
    sol = least_squares(fun, x[free], jac=jac, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=500)
    # out of evaluations at its minimum (crawling on rounding noise) is converged; anywhere else it is not
    note = check_converged(sol, stage1, "combined fit")
    stopped_stationary = [note] if note else []
    x[free] = sol.x
    nfev = sol.nfev
    # direction-noise scale from the whitened residuals: sigma^2 = chi2 / dof
    Cinv = np.linalg.inv(problem.shape + 1e-300 * np.eye(2))
    m = problem.m

    def noise_scale(v: np.ndarray) -> float:
        r = problem.raw(v).reshape(m, 2)
        return float(np.einsum("mi,mij,mj->", r, Cinv, r)) / max(2 * m - 4, 1)

    s2 = noise_scale(x)
    if (problem.joint or nz) and s2 > 0:
        for npass in range(3):
            sc = 1.0 / np.sqrt(s2)

            def full(v: np.ndarray, sc: float = sc) -> np.ndarray:
                return np.concatenate([sc * problem.eq8(v), problem.priors(v)])

            def full_jac(v: np.ndarray, sc: float = sc) -> np.ndarray:
                return np.concatenate([sc * problem.eq8_jacobian(v), problem.priors_jacobian()])

            fun, jac = traced_jac(full, full_jac, on_iteration, f"joint-{npass + 1}")
            sol = least_squares(
                fun,
                x,
                jac=jac,
                method="lm",
                xtol=1e-14,
                ftol=1e-14,
                gtol=1e-14,
                max_nfev=500,
            )
            note = check_converged(sol, full, "combined joint fit")
            if note:
                stopped_stationary.append(note)
            x = sol.x
            nfev += sol.nfev
            s2_new = noise_scale(x)
            if abs(s2_new - s2) <= 1e-3 * s2:
                s2 = s2_new
                break
            s2 = s2_new
    return _Eq8Solution(x, s2, nfev, sol, stopped_stationary)


def combined_covariance(obs: Observations, rods: _Rods, problem: _Eq8, fit: _Eq8Solution, r: np.ndarray) -> _Covariance:
    """The combinations' covariance: a sandwich with the rods' error model and the priors.

    The rods' errors are not independent: the two rods of a leg in one frame, and rods seen at nearby places of the
    image in any frame, share part of theirs (:mod:`.rod_correlation`). The rods' own scale and those correlations are
    estimated from the residuals with what the fit absorbs accounted for. The priors' information: the base frame's
    refinement (Pw), the intrinsics' (Pz) and the limb-edge biases' (Pe). The lens model's error (the board views'
    radial residual beyond their noise) is propagated at one standard deviation through the fit's gain, a Type B
    component.

    Parameters
    ----------
    obs : Observations
    rods : _Rods
    problem : _Eq8
    fit : _Eq8Solution
    r : ndarray, shape (m, 2)
        The raw residuals at the solution.

    Returns
    -------
    _Covariance
    """
    prob, x, s2 = rods.prob, fit.x, fit.s2
    m, nw, ni, nz = problem.m, problem.nw, rods.ni, rods.nz
    Wh, shape, joint, R0 = problem.Wh, problem.shape, problem.joint, problem.R0
    _xi, w, z = problem.split(x)
    Wfull = rc.block_diagonal(np.einsum("mji,mjk->mik", Wh, Wh))  # each rod's weight Wh^T Wh
    Jr = problem.raw_jacobian(x)  # unweighted, (2m, 4 + nw + nz), closed form
    Pw = np.zeros((x.size, x.size))
    if joint:
        Pw[4 : 4 + nw, 4 : 4 + nw] = problem.Lw.T @ problem.Lw
    Pz = np.zeros((x.size, x.size))
    Pz[4 + nw : 4 + nw + ni, 4 + nw : 4 + nw + ni] = np.eye(ni)
    Pe = np.zeros((x.size, x.size))
    Pe[4 + nw + ni :, 4 + nw + ni :] = np.eye(nz - ni)
    pairs = _rod_pairs(prob)
    focal = _focal_px(obs)
    R_sol = rotvec_to_matrix(w) @ R0 if joint else R0
    if prob.intrinsics is not None:
        R_sol = prob.intrinsics.rotation(z) @ R_sol
    rays = _rod_rays(rods.data, prob)
    dist_shape = None
    if rods.rod_cov is not None and focal is not None and rays is not None:
        g = rc.in_image_sensitivity(prob.u_cam, rays, R_sol, ratio_gradient(prob.u_cam @ R_sol), shape)
        dist_shape = rc.distance_shape(rays, focal, g, pairs)
    own = rc.block_diagonal(shape)
    errs = rc.estimate_rod_errors(
        r.ravel(),
        Jr,
        Wfull / s2,
        Pw + Pz + Pe,
        own,
        pair_shape=rc.pair_shape(pairs, np.linalg.inv(Wh), m) if len(pairs) >= rc.MIN_PAIRS else None,
        distance_shape=dist_shape,
    )
    if errs.s2 <= 0:  # the priors explain every residual: fall back on the residuals' own scale
        errs = rc.RodErrors(s2, 0.0, None, errs.dof)
    Sig = errs.covariance(own)
    check_excitation(np.einsum("mij,mjk->mik", Wh, Jr[:, :4].reshape(m, 2, 4)).reshape(2 * m, 4), COMBINATION_NAMES)
    cov_pose_fixed = _sandwich(Jr[:, :4], Wfull, Sig)
    parts = {"legs_and_encoders": cov_pose_fixed}
    cov = cov_pose_fixed.copy()
    cov_intr = None
    if (joint or nz) and s2 > 0:
        cov, parts = _joint_covariance(Jr, Wfull / s2, Sig, Pw, Pz, Pe)
        if nz:
            keep = np.arange(4 + nw)  # the same fit with the intrinsics and edges known: what they add
            cov_known, _ = _joint_covariance(
                Jr[:, keep], Wfull / s2, Sig, Pw[np.ix_(keep, keep)], Pz[np.ix_(keep, keep)]
            )
            cov_intr = cov - cov_known
    cov_lens = None
    lens_err = None if prob.intrinsics is None else intr.lens_model_error(prob.intrinsics.camera)
    if lens_err is not None and s2 > 0:
        assert prob.intrinsics is not None  # lens_err is computed from it
        dx = prob.intrinsics.model_error_shift(w, z, lens_err, R0, joint)
        Hm = Jr.T @ (Wfull / s2) @ Jr + Pw + Pz + Pe
        dtheta = -np.linalg.solve(Hm, Jr.T @ (Wfull / s2) @ dx)[:4]
        cov_lens = np.outer(dtheta, dtheta)
        cov = cov + cov_lens
    return _Covariance(cov, parts, errs, cov_intr, cov_lens, len(pairs))


def _combined_result(
    rods: _Rods, problem: _Eq8, fit: _Eq8Solution, c: _Covariance, r: np.ndarray, rejected: list[dict[str, int]]
) -> MethodResult:
    """The :class:`MethodResult` of the stages' outputs."""
    prob, nw, ni, nz = rods.prob, problem.nw, rods.ni, rods.nz
    xi, w, z = problem.split(fit.x)
    return MethodResult(
        method="combined",
        combinations=combos_dict(xi),
        combinations_std=std_dict(c.cov),
        covariance=c.cov,
        residual_rms=float(np.sqrt(np.mean(r**2))),
        residual_unit="Jacobian entry (dimensionless)",
        n_observations=2 * problem.m,
        n_poses=prob.n_poses,
        iterations=int(fit.nfev),
        converged=True,
        message=str(fit.sol.message),
        std_breakdown=_breakdown(problem.joint, prob.intrinsics is not None, ni, nz, c),
        diagnostics={
            "weighting": rods.weighting,
            "direction_noise_scale": float(np.sqrt(fit.s2)),
            "rods_rejected": rejected,
            "rods_used": int(problem.m),
            "intrinsics_covariance": None if c.cov_intr is None else c.cov_intr.tolist(),
            "intrinsics_refinement": _intrinsics_refinement(rods, z),
            "intrinsics_posterior_covariance": _intrinsics_posterior(rods, c, nw),
            "limb_edge_bias": _edge_bias(rods, c, z, nw),
            "rods_dropped_near_vertical": prob.dropped,
            "base_frame": rods.bf.summary(),
            "base_frame_refinement_deg": float(np.rad2deg(np.linalg.norm(w))),
            "joint_base_frame": problem.joint,
            "rod_pair_correlation": c.errs.pair_rho,
            "rod_errors": c.errs.summary(),
            "rod_pairs": c.n_pairs,
            # the stages that ran out of evaluations at their minimum (calib.identify.stationary), with the decrease
            # one more Gauss-Newton step would have given; empty when scipy's tolerances were met
            "stopped_stationary": fit.stopped_stationary,
        },
        residuals=r,
    )


def _breakdown(joint: bool, has_intrinsics: bool, ni: int, nz: int, c: _Covariance) -> dict[str, dict[str, float]]:
    """The standard deviations' parts (m)."""
    parts = c.parts
    breakdown = {"legs_and_encoders": std_dict(parts["legs_and_encoders"])}
    if joint:
        breakdown["base_frame"] = std_dict(parts.get("base_frame", np.zeros((4, 4))))
    if nz:
        breakdown["intrinsics"] = std_dict(parts.get("intrinsics", np.zeros((4, 4))))
    if nz > ni:
        breakdown["limb_edge_bias"] = std_dict(parts.get("edge_bias", np.zeros((4, 4))))
    if has_intrinsics:
        breakdown["lens_model"] = std_dict(np.zeros((4, 4)) if c.cov_lens is None else c.cov_lens)
    return breakdown


def _edge_bias(rods: _Rods, c: _Covariance, z: np.ndarray, nw: int) -> dict[str, Any] | None:
    """The limb-edge bias the fit measured (per limb, outward px) with its std and covariance; None when not fitted."""
    ni, nz = rods.ni, rods.nz
    if not (nz > ni and "full" in c.parts):
        return None
    assert rods.prob.intrinsics is not None  # nz > 0: the intrinsics are fitted
    e_std = rods.prob.intrinsics.edge_std_px
    full = c.parts["full"]
    return {
        # z moves the measured limbs (the correction); the limbs' bias is the opposite: outward positive, the rods
        # seen wider than they are (checked on images rendered with a known offset: tests/calib/test_edge_bias.py)
        "estimate_px": (-z[ni:] * e_std).tolist(),
        "std_px": (np.sqrt(np.diag(full)[4 + nw + ni :]) * e_std).tolist(),
        "prior_std_px": e_std,
        "covariance_px2": (full[4 + nw + ni :, 4 + nw + ni :] * e_std**2).tolist(),
    }


def _intrinsics_refinement(rods: _Rods, z: np.ndarray) -> dict[str, float] | None:
    """The intrinsics' shift the rods give (px for fx, fy, cx, cy), by name; None when not fitted."""
    steps = rods.steps
    if steps is None:
        return None
    cam = rods.prob.intrinsics.camera if rods.prob.intrinsics is not None else None
    names = intr.intrinsics_names(cam) if cam is not None else intr.INTRINSICS_NAMES
    return dict(zip(names, (steps.T @ z[: rods.ni]).tolist(), strict=True))


def _intrinsics_posterior(rods: _Rods, c: _Covariance, nw: int) -> list | None:
    """The intrinsics after the rods: their posterior covariance (for methods that do not use the rods)."""
    ni = rods.ni
    if not (rods.nz and "full" in c.parts):
        return None
    steps = rods.steps
    assert steps is not None  # nz > 0: the intrinsics' principal steps
    return (steps.T @ c.parts["full"][4 + nw : 4 + nw + ni, 4 + nw : 4 + nw + ni] @ steps).tolist()


def _joint_covariance(
    Jr: np.ndarray, Wd: np.ndarray, Sig: np.ndarray, Pw: np.ndarray, Pz: np.ndarray, Pe: np.ndarray | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Covariance (4, 4) of the combinations of a fit with priors, and its parts.

    The fit minimises ``r^T Wd r + v^T (Pw + Pz + Pe) v`` (data and the priors on the base frame, the
    intrinsics and the limb-edge biases); the estimate's covariance is the data term's sandwich
    ``B Sig B^T`` plus each prior's ``H^-1 P H^-1``.
    """
    Pe = np.zeros_like(Pz) if Pe is None else Pe
    H = Jr.T @ Wd @ Jr + Pw + Pz + Pe
    Hinv = np.linalg.inv(H)
    B = Hinv @ Jr.T @ Wd
    full = B @ Sig @ B.T + Hinv @ (Pw + Pz + Pe) @ Hinv
    parts = {
        "legs_and_encoders": (B @ Sig @ B.T)[:4, :4],
        "base_frame": (Hinv @ Pw @ Hinv)[:4, :4],
        "intrinsics": (Hinv @ Pz @ Hinv)[:4, :4],
        "edge_bias": (Hinv @ Pe @ Hinv)[:4, :4],
        "full": full,
    }
    total = parts["legs_and_encoders"] + parts["base_frame"] + parts["intrinsics"] + parts["edge_bias"]
    return total, parts


class RodIntrinsicsModel:
    """How the measured rods and the base frame move with the camera's intrinsics (the combined method's nuisance
    model; experiment design predicts with it).

    The intrinsics are ``camera + steps^T z`` (``steps`` (n, 8): one standard deviation along each
    principal direction of their covariance, :mod:`.intrinsics`; z the nuisance unknowns, prior
    N(0, I)). Each rod's direction is recomputed exactly from its limb samples (``limbs_px``) for
    those intrinsics; the base frame's rotation moves to first order, ``exp([G z]) R``, G (3, n)
    from re-estimating it with the board poses moved by their ``d_intrinsics`` (one step per
    direction), or not at all when a board lacks them.
    """

    def __init__(
        self,
        camera: CameraModel,
        steps: np.ndarray,
        limbs: np.ndarray,
        H: np.ndarray,
        G: np.ndarray,
        z0: np.ndarray | None = None,
        edge_std_px: float = 0.0,
    ) -> None:
        self.camera, self.steps, self.H, self.G = camera, steps, H, G
        self.n_intr = steps.shape[0]
        #: limb-edge bias common to every rod, per limb (outward, px; prior N(0, edge_std_px^2)): the last two
        #: entries of z when ``edge_std_px`` > 0
        self.edge_std_px = edge_std_px
        self.n_edge = 2 if edge_std_px > 0 else 0
        #: the prior's mean: the calibration's intrinsics in the units of z (zero unless the observations were
        #: extracted with a camera the rods already refined, whose calibration then records the shift: the
        #: prior stays the calibration's, so that the rods' information is not counted twice)
        self.z0 = np.concatenate([np.zeros(self.n_intr) if z0 is None else z0, np.zeros(self.n_edge)])
        self.limbs = intr.LinearizedLimbs(camera, steps, limbs)
        #: the limb samples' normalized move per px of outward edge bias (M, 2, P, 2): the bias is modelled in the
        #: image's pixels, where the edge detector makes it (a constant in normalized coordinates is not: the
        #: undistortion magnifies a pixel with the radius)
        self.edge_dxn = intr.outward_shift_normalized(camera, limbs) if self.n_edge else None
        self._last: tuple[bytes, np.ndarray] | None = None  # the numeric Jacobians move z in few columns
        self._last_points: tuple[bytes, np.ndarray] | None = None

    @classmethod
    def build(
        cls, obs: Observations, data: PhaseArrays, prob: _Problem, bf: BaseFrameResult, edge_bias_std_px: float = 0.0
    ) -> RodIntrinsicsModel | None:
        """The model of the fit's rods, or None when the camera's uncertainty or a rod's limb samples are missing.

        Parameters
        ----------
        obs : Observations
            The observations (the extraction's camera and its covariance, the rods' limb samples).
        data : PhaseArrays
            The fit's frames.
        prob : _Problem
            The combined fit's problem (which rods).
        bf : BaseFrameResult
            The base frame, whose rotation's change with the intrinsics is ``G``.
        edge_bias_std_px : float
            Prior std of the limb-edge bias common to every rod, px (0: no edge-bias nuisance).

        Returns
        -------
        RodIntrinsicsModel or None
            The model.
        """
        prior = intr.intrinsics_prior(obs, refined=False)  # the rods are used again here
        limbs = _rod_field(obs, data, prob, "limbs_px")
        H = _rod_field(obs, data, prob, "h")
        if prior is None or limbs is None or H is None:
            return None
        camera, cov = prior
        steps = intr.principal_steps(cov)
        if steps.shape[0] == 0:
            return None
        rot, tra = obs.arrays("rotation"), obs.arrays("translation")
        n = steps.shape[1]
        s_rot, s_tra = intr.board_sensitivities(obs, rot, n), intr.board_sensitivities(obs, tra, n)
        G = np.zeros((3, steps.shape[0]))
        if s_rot is not None and s_tra is not None:
            R0 = bf.camera_from_base_R
            for j, st in enumerate(steps):  # one-sided: R0 is the estimate from the same board poses
                Rp = estimate_base_frame(
                    intr.perturbed_boards(rot, s_rot, st), intr.perturbed_boards(tra, s_tra, st), start=bf
                ).camera_from_base_R
                G[:, j] = matrix_to_rotvec(Rp @ R0.T)
        offset = intr.calibration_offset(obs)
        z0 = None if offset is None else (steps @ offset) / np.sum(steps * steps, axis=1)
        return cls(camera, steps, limbs, H, G, z0, edge_bias_std_px)

    def select(self, keep: np.ndarray) -> None:
        """Keep only the rods ``keep`` (in place).

        Parameters
        ----------
        keep : ndarray
            Boolean mask (M,) or indices of the rods kept.
        """
        self.limbs, self.H = self.limbs.subset(keep), self.H[keep]
        if self.edge_dxn is not None:
            self.edge_dxn = self.edge_dxn[keep]
        self._last = self._last_points = None

    def _edge_moved(self, xn: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Limb samples' normalized coordinates (M, 2, P, 2) moved by the edge-bias nuisance (px, outward)."""
        if not self.n_edge or self.edge_dxn is None:
            return xn
        eps_px = z[self.n_intr :] * self.edge_std_px
        return xn + eps_px[None, :, None, None] * self.edge_dxn

    def directions(self, z: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Rod directions (M, 3), camera frame, for the intrinsics moved by ``z``; signed like ``reference``.

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance: intrinsics in standard deviations along their principal directions, then, when modelled,
            the limb-edge bias per limb in standard deviations of its prior (``edge_std_px``).
        reference : ndarray, shape (M, 3)
            The measured directions (signs).

        Returns
        -------
        ndarray, shape (M, 3)
            Unit directions.
        """
        key = np.asarray(z, dtype=np.float64).tobytes()
        if self._last is not None and self._last[0] == key and self._last[1].shape == reference.shape:
            return self._last[1]
        h = intr.planes_through(self._edge_moved(self._points(z), z), self.H)
        u = cross(h[:, 0], h[:, 1])
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u *= np.sign(np.sum(u * reference, axis=1))[:, None]
        self._last = (key, u)
        return u

    def _points(self, z: np.ndarray) -> np.ndarray:
        """The limb samples' normalized coordinates (M, 2, P, 2) for the intrinsics' part of ``z`` (the last one
        kept: a fit asks for its residuals and then its Jacobian at the same point)."""
        key = np.asarray(z[: self.n_intr], dtype=np.float64).tobytes()
        if self._last_points is None or self._last_points[0] != key:
            self._last_points = (key, self.limbs.points(z[: self.n_intr]))
        return self._last_points[1]

    def directions_jacobian(self, z: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`directions` and their derivatives with ``z`` (first order, closed form).

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance (see :meth:`directions`).
        reference : ndarray, shape (M, 3)
            The measured directions (signs).

        Returns
        -------
        u : ndarray, shape (M, 3)
            Unit directions, as :meth:`directions` gives them.
        du : ndarray, shape (n, M, 3)
            Their derivatives per unit of each entry of ``z``.
        """
        xi = self._points(z)
        moves = [self.limbs.points_jacobian(z[: self.n_intr], xi)]
        if self.n_edge and self.edge_dxn is not None:
            edge = np.zeros((self.n_edge, *xi.shape))
            for limb in range(self.n_edge):
                edge[limb, :, limb] = self.edge_std_px * self.edge_dxn[:, limb]
            moves.append(edge)
        h, dh = intr.planes_through_jacobian(self._edge_moved(xi, z), np.concatenate(moves), self.H)
        n3 = cross(h[:, 0], h[:, 1])
        norm = np.linalg.norm(n3, axis=1, keepdims=True)
        u = n3 / norm
        u *= np.sign(np.sum(u * reference, axis=1))[:, None]
        dn3 = cross(dh[:, :, 0], h[None, :, 1]) + cross(h[None, :, 0], dh[:, :, 1])
        sign = np.sign(np.sum(n3 * u, axis=1))[None, :, None]
        du = sign * (dn3 - (n3 / norm)[None] * np.sum((n3 / norm)[None] * dn3, axis=-1, keepdims=True)) / norm[None]
        return self.directions(z, reference), du

    def rotation_jacobian(self, z: np.ndarray) -> np.ndarray:
        """Derivatives of :meth:`rotation` with each entry of ``z``, shape (n, 3, 3) (zero for the edge biases).

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance.

        Returns
        -------
        ndarray, shape (n, 3, 3)
            ``d rotation / d z_j`` (per standard deviation).
        """
        out = np.zeros((z.size, 3, 3))
        out[: self.n_intr] = np.einsum("kab,kj->jab", rotvec_derivatives(self.G @ z[: self.n_intr]), self.G)
        return out

    def rotation(self, z: np.ndarray) -> np.ndarray:
        """The base frame's rotation change (3, 3) for ``z``, applied on the left.

        Parameters
        ----------
        z : ndarray, shape (n,)
            The nuisance (its first ``n_intr`` entries, in standard deviations, are used).

        Returns
        -------
        ndarray, shape (3, 3)
            A rotation matrix.
        """
        return rotvec_to_matrix(self.G @ z[: self.n_intr])

    def model_error_shift(
        self, w: np.ndarray, z: np.ndarray, profile: tuple[np.ndarray, np.ndarray], R0: np.ndarray, joint: bool
    ) -> np.ndarray:
        """Change of the fit's raw residuals at the solution when every rod's limb samples are corrected by the lens
        model's error ``profile`` (:func:`.intrinsics.lens_model_error`).

        The base frame is left as it is (the board poses move far less: their corners lie within the views' radius,
        where the profile was measured).

        Parameters
        ----------
        w : ndarray, shape (3,)
            The base frame's rotation refinement, rotation vector, rad.
        z : ndarray, shape (n,)
            The nuisance at the solution.
        profile : tuple of (ndarray, ndarray), each of shape (B,)
            Bin radii and systematic radial residual, px.
        R0 : ndarray, shape (3, 3)
            The base frame's rotation before refinement.
        joint : bool
            Whether ``w`` refines the rotation (the joint fit).

        Returns
        -------
        ndarray, shape (2M,)
            Change of the residuals (Jacobian entries, dimensionless).
        """
        zi = z[: self.n_intr]
        cam = intr.perturbed_camera(self.camera, self.steps.T @ zi)
        ref = self.H
        moved = intr.correct_model_error(cam, self.limbs.px, profile)
        shape = self.limbs.px.shape
        h0, h1 = (
            intr.planes_through(self._edge_moved(cam.undistort_points(px.reshape(-1, 2)).reshape(shape), z), ref)
            for px in (self.limbs.px, moved)
        )
        R = self.rotation(z) @ (rotvec_to_matrix(w) @ R0 if joint else R0)

        def ratios(h: np.ndarray) -> np.ndarray:
            u = cross(h[:, 0], h[:, 1])
            uB = u @ R
            return uB[:, 1:] / uB[:, :1]

        # raw = model - measured: the measured entries move by ratios(h1) - ratios(h0)
        return -(ratios(h1) - ratios(h0)).ravel()


def _whitened_d2(
    prob: _Problem,
    shape: np.ndarray,
    x0: np.ndarray,
    cov_rotvec: np.ndarray | None,
    on_iteration: IterationCallback | None,
    start: tuple[np.ndarray, float] | None = None,
    round_index: int = 0,
) -> tuple[np.ndarray, tuple[np.ndarray, float]]:
    """Each rod's squared whitened residual after a GLS fit of eq. 8, for the outlier gate.

    The base frame's rotation is a nuisance unknown of this fit with its prior, as in the joint fit (step 2): held
    at the board-only estimate, a rotation a few mrad off (within its std) gives the rods most sensitive to it large
    residuals, which the gate would take for outliers (a sizeable share of good rods: fewer rods, a larger noise
    scale and tail errors). The rods' noise level is not known yet; for the priors to weigh right, the data are
    divided by their robust level (:func:`calib.numerics.robust.robust_chi2_scale`, the median chi-square, outliers or
    not),
    estimated from the previous pass (3 passes; the first at level 1).

    Parameters
    ----------
    prob : _Problem
        The rods (M of them) and the base frame's board-only rotation ``prob.R_cb``.
    shape : ndarray, shape (M, 2, 2)
        Relative noise covariance of each rod's two Jacobian entries (dimensionless).
    x0 : ndarray, shape (4 + nz,)
        Start: the combinations (m), then the intrinsics' nuisance unknowns z (units of their std, prior N(z0, I)).
    cov_rotvec : ndarray, shape (3, 3), optional
        Covariance (rad^2) of the base frame's rotation vector; None or singular: the rotation is held.
    on_iteration : callable, optional
        Iteration reports (stage ``"outliers"``).
    start : (ndarray, float), optional
        The previous gating round's solution and noise level (its rods minus the rejected ones): one pass from there
        (the unknowns and the level barely move when a few outliers leave) instead of three from ``x0``.
    round_index : int
        The gating round (0 first): names the iteration reports' stage, ``"outliers"``, ``"outliers pass 2"``, ...,
        ``"outliers round 2"`` (each pass weighs the data by another noise level: its own cost scale).

    Returns
    -------
    d2 : ndarray, shape (M,)
        ``r^T C^-1 r`` per rod (not divided by the noise level): chi-square(2) times the noise factor for good rods.
    state : (ndarray, float)
        The solution and noise level, the next round's ``start``.
    """
    Cinv = np.linalg.inv(shape + 1e-300 * np.eye(2))
    Wh = np.linalg.cholesky(Cinv).transpose(0, 2, 1)
    joint = cov_rotvec is not None and bool(np.all(np.linalg.eigvalsh(cov_rotvec) > 1e-20))
    nw = 3 if joint else 0
    Lw = np.zeros((0, 0))
    if joint and cov_rotvec is not None:
        Lw = np.linalg.cholesky(np.linalg.inv(cov_rotvec)).T  # Lw^T Lw = cov^-1
    R0 = prob.R_cb
    z0 = prob.intrinsics.z0 if prob.intrinsics is not None else np.zeros(0)

    def raw(v: np.ndarray) -> np.ndarray:  # v: combinations (4), rotation refinement w (nw, rad), z
        R = rotvec_to_matrix(v[4 : 4 + nw]) @ R0 if joint else None
        return (prob.model(v[:4]) - prob.measured(R, v[4 + nw :])).reshape(-1, 2)

    v = np.concatenate([x0[:4], np.zeros(nw), x0[4:]])
    prior_jac = np.zeros((nw + z0.size, v.size))  # the priors' rows: constant
    prior_jac[:nw, 4 : 4 + nw] = Lw
    prior_jac[nw:, 4 + nw :] = np.eye(z0.size)
    level = 1.0  # the data's noise level (std factor), re-estimated after each pass
    passes = 3 if joint else 1
    if start is not None and start[0].shape == v.shape:
        v, level, passes = start[0].copy(), start[1], 1
    d2 = np.zeros(0)
    for npass in range(passes):
        stage = (
            "outliers" + (f" round {round_index + 1}" if round_index else "") + (f" pass {npass + 1}" if npass else "")
        )

        def res(v: np.ndarray, level: float = level) -> np.ndarray:
            eq8 = np.einsum("mij,mj->mi", Wh, raw(v)).ravel() / level
            return np.concatenate([eq8, Lw @ v[4 : 4 + nw], v[4 + nw :] - z0])

        def jac(v: np.ndarray, level: float = level) -> np.ndarray:
            J = raw_jacobian(prob, v, R0, joint).reshape(Wh.shape[0], 2, -1)
            return np.concatenate([np.einsum("mij,mjk->mik", Wh, J).reshape(-1, v.size) / level, prior_jac])

        fun, jacobian = traced_jac(res, jac, on_iteration, stage)
        sol = least_squares(fun, v, jac=jacobian, method="lm", xtol=1e-8, ftol=1e-8, max_nfev=200)
        v = sol.x
        r = raw(v)
        d2 = np.einsum("mi,mij,mj->m", r, Cinv, r)
        s2 = robust_chi2_scale(d2, 2)
        if not s2 > 0:  # noise-free data: nothing to weigh against the priors
            break
        level = float(np.sqrt(s2))
    return d2, (v, level)


def _rod_pairs(prob: _Problem) -> list[tuple[int, int]]:
    """Index pairs (a, b) of the two rods of one leg seen in the same frame."""
    return rc.rod_pairs(prob.k, prob.leg)


def _sandwich(J: np.ndarray, W: np.ndarray, Sig: np.ndarray) -> np.ndarray:
    H = J.T @ W @ J
    A = np.linalg.solve(H, J.T @ W)
    return A @ Sig @ A.T


def _rod_covariances(obs: Observations, data: PhaseArrays, prob: _Problem) -> np.ndarray | None:
    """Per-rod direction covariances (camera frame) when every used rod carries one: ``cov_u_own`` (without the
    limb-edge bias every rod shares, which this fit measures as two nuisance unknowns), else ``cov_u``."""
    own = _rod_field(obs, data, prob, "cov_u_own")
    return own if own is not None else _rod_field(obs, data, prob, "cov_u")


def _rod_field(obs: Observations, data: PhaseArrays, prob: _Problem, name: str) -> np.ndarray | None:
    """An extra field of every used rod, stacked as float64 (M, ...); None when a rod lacks it or none is used."""
    values = []
    for k, leg, rod in zip(prob.k, prob.leg, prob.rod, strict=True):
        frame = obs.frames[int(data.index[k])]
        key = cast(LegKey, str(leg + 1))  # leg in 0..3
        rods = frame.legs.get(key) if frame.legs else None
        v = getattr(rods[rod], name, None) if rods and rods[rod] is not None else None
        if v is None:
            return None
        values.append(np.asarray(v, dtype=np.float64))
    return np.asarray(values) if values else None


def _focal_px(obs: Observations) -> float | None:
    """The extraction camera's focal length (px), or None when the observations carry no camera."""
    cam = ((obs.document.model_extra or {}).get("extraction") or {}).get("camera") or {}
    K = cam.get("K")
    if not K:
        return None
    f = float(np.sqrt(abs(float(K[0][0]) * float(K[1][1]))))
    return f if np.isfinite(f) and f > 0 else None


def _rod_rays(data: PhaseArrays, prob: _Problem) -> np.ndarray | None:
    """Unit viewing rays (M, 3) to the rods' measured axis points, camera frame; None when a rod has none."""
    p = data.rod_p[prob.k, prob.leg, prob.rod]
    if not np.all(np.isfinite(p)):
        return None
    n = np.linalg.norm(p, axis=1, keepdims=True)
    if np.any(n <= 0):
        return None
    return p / n
