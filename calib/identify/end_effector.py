"""End-effector observation only (the paper's reference [8]): inverse-kinematic residuals.

Each board pose ``camera_from_board_k`` gives, through the unknown ``base_from_camera`` and
``board_from_ee`` transforms, an end-effector pose (X, Y, Z, theta) with ``T = T_per_rad theta``.
The IKM of that pose must reproduce the encoder values. The unknowns are the four identifiable
combinations, two joint offsets (what X and T offsets and S, q03 become once only the combinations
are kept), the camera rotation (3) and its y, z position (2), the board tilt on the end-effector
(2) and its horizontal offset (2): 15 in all. Its x position and the board's height and yaw on the
end-effector are gauge freedoms that the offsets absorb and are held fixed. The board's scale is a 16th unknown:
a printed board's scale is known to its print only (and the camera calibration, which fixes it by two of
its points, cannot tell), and a scale error moves every board pose along its viewing ray by a different
amount (a few tenths of a percent leave the IKM residuals several times the PnP noise and the standard
deviations two to three times too large); the encoders fix it. Besides the four IKM residuals per pose, the pose's tilt
(the end-effector only turns about z_B) gives two more.

Weighting and uncertainty: each pose's residuals are a linear function of its board-pose error
(6 dof) plus encoder noise. When the extraction reports each board pose's covariance (``board.cov``,
rotation vector then t, from the PnP Jacobian), the fit is weighted by it (converted to a left rotation),
times one common factor measured from the residuals (generalised least squares); poses whose
studentized chi-square (leverage-corrected, from the fit with every pose) exceeds its 99.9 % quantile
are rejected once and the fit redone. The camera intrinsics' error, common to every pose, moves the
board poses through their ``d_intrinsics``: its share of the covariance goes through the fit's gain,
and the noise factor is measured with that share removed from the residuals (intrinsics as nuisance
unknowns with their prior), so it is not counted twice. Without per-pose covariances (numbers with
known noise), the board-pose noise is a diagonal covariance estimated from the residuals themselves.
The standard deviations come from the weighted normal matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from calib.errors import ConvergenceError, I4calError, IdentifiabilityError
from calib.formats.observations import Observations, PhaseArrays
from calib.identify import intrinsics as intr
from calib.identify.baseframe import base_frame_from_observations
from calib.identify.iterations import IterationCallback, trf_callback
from calib.identify.pose_set_model import PoseSetModel
from calib.identify.result import MethodResult, check_excitation, combos_dict, std_dict
from calib.model.kinematics import base_from_ee, dkm
from calib.model.parameters import COMBINATION_NAMES, I4Parameters
from calib.numerics.numdiff import central_jacobian
from calib.numerics.robust import chi2_outliers, robust_chi2_scale
from calib.numerics.transforms import kabsch_points, matrix_to_rotvec, orthonormalize, rot_z, rotvec_to_matrix, skew

_NAMES = (
    *COMBINATION_NAMES,
    "o1",
    "o3",
    "w_x",
    "w_y",
    "w_z",
    "t_y",
    "t_z",
    "tilt_x",
    "tilt_y",
    "b_x",
    "b_y",
    "board_scale",
)


def pose_set_model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    """The end-effector method's measurement model at encoder values ``q`` (N, 4), m: the board poses predicted through
    the DKM, per pose the rotation matrix's nine entries then the position (m), (N * 12,), as a function of the seven
    parameters then 12 nuisance unknowns: the camera's placement in the base frame (rotation vector, rad; position, m)
    and the board's on the end-effector (the same).

    Parameters
    ----------
    params : I4Parameters
        The geometry at which the model is linearised (its seven parameters start the vector).
    q : array_like, shape (N, 4)
        Encoder values of the poses, m.

    Returns
    -------
    PoseSetModel
        The prediction (N * 12,) (rotation entries, dimensionless; position, m) as a function of the 19-vector, with 12
        nuisance unknowns.
    """
    q = np.asarray(q, dtype=np.float64)

    def f(v: np.ndarray) -> np.ndarray:
        p = I4Parameters.from_vector(v[:7], T_per_rad=params.T_per_rad)
        pose = dkm(p, q)
        Rc = rotvec_to_matrix(v[7:10])
        tc = v[10:13]
        Rb = rotvec_to_matrix(v[13:16])
        tb = v[16:19]
        Re, pe = base_from_ee(p, pose)
        Rk = Rc @ Re @ Rb
        tk = (Rc @ (np.einsum("nij,j->ni", Re, tb) + pe).T).T + tc
        return np.concatenate([(Rk.reshape(len(q), -1)) * 1.0, tk], axis=1).ravel()

    return PoseSetModel(f, params, 12)


class EndEffectorModel:
    """The end-effector method's model: per board pose, the IKM's four joint residuals (m) and the pose's two tilt
    residuals (rad) as a function of the 16 unknowns ``x`` (:data:`_NAMES`: the four combinations, two joint
    offsets, the camera's rotation (3, rad) and y, z position (m), the board's tilt on the end-effector (2, rad) and
    its offset (2, m), the board's scale).

    Parameters
    ----------
    R, t : ndarray, shape (N, 3, 3), (N, 3)
        The board poses in the camera (rotation; position, m).
    q : ndarray, shape (N, 4)
        Encoder values, m.
    T_per_rad : float
        The end-effector's T per radian of rotation, m/rad.
    R_bc0 : ndarray, shape (3, 3)
        The camera-to-base rotation the camera's rotation unknowns refine.
    t_bc_x : float
        The camera's x position in the base frame (held: a gauge freedom), m.
    R_eb0 : ndarray, shape (3, 3)
        The board-to-end-effector rotation the tilt unknowns refine.
    t_eb_z : float
        The board's height on the end-effector (held), m.
    theta_ref : ndarray, shape (N,)
        Reference rotation angles (rad) that pick each pose's turn.
    """

    def __init__(
        self,
        R: np.ndarray,
        t: np.ndarray,
        q: np.ndarray,
        T_per_rad: float,
        R_bc0: np.ndarray,
        t_bc_x: float,
        R_eb0: np.ndarray,
        t_eb_z: float,
        theta_ref: np.ndarray,
    ) -> None:
        self.R, self.t, self.q = R, t, q
        self.Tpr = T_per_rad
        self.R_bc0, self.t_bc_x = R_bc0, t_bc_x
        self.R_eb0, self.t_eb_z = R_eb0, t_eb_z
        self.theta_ref = theta_ref

    def jacobian(self, x: np.ndarray, h: float = 1e-7) -> np.ndarray:
        """d residuals / d x, shape (N, 6, 16), by central differences of step ``h``.

        Parameters
        ----------
        x : ndarray, shape (16,)
            The unknowns, :data:`_NAMES` order (m, rad; the board's scale dimensionless).
        h : float
            The central differences' step, in the unknowns' units.

        Returns
        -------
        ndarray, shape (N, 6, 16)
            d residual / d x (m or rad per unit of each unknown).
        """
        n = self.R.shape[0]
        return central_jacobian(lambda v: self.residuals(v).ravel(), x, h).reshape(n, 6, -1)

    def pose_sensitivity(self, x: np.ndarray, h: float = 1e-7) -> np.ndarray:
        """d residuals_k / d (board pose error_k), shape (N, 6, 6): rotation (left, camera frame; rad) then
        translation (m).

        Parameters
        ----------
        x : ndarray, shape (16,)
            The unknowns, :data:`_NAMES` order (m, rad; the board's scale dimensionless).
        h : float
            The central differences' step (rad, m).

        Returns
        -------
        ndarray, shape (N, 6, 6)
            d residual / d board-pose error (m or rad of residual per rad or m of pose error).
        """
        return _pose_sensitivity(self, x, h)

    def ee_poses(
        self, x: np.ndarray, R: np.ndarray | None = None, t: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The end-effector poses the board poses give: positions (N, 3), m, rotation angles (N,), rad, tilts (N, 2),
        rad.

        Parameters
        ----------
        x : ndarray, shape (16,)
            The unknowns, :data:`_NAMES` order (m, rad; the board's scale dimensionless).
        R : ndarray, shape (N, 3, 3), optional
            Board rotations in the camera frame (default: the model's).
        t : ndarray, shape (N, 3), optional
            Board positions in the camera frame, m (default: the model's).

        Returns
        -------
        p : ndarray, shape (N, 3)
            End-effector positions in the base frame, m.
        theta : ndarray, shape (N,)
            Rotation angles about z_B, rad, unwrapped near ``theta_ref``.
        tilt : ndarray, shape (N, 2)
            Tilt of the end-effector's z axis (x, y components; small angles, rad).
        """
        R = self.R if R is None else R
        t = self.t if t is None else t
        R_bc = rotvec_to_matrix(x[6:9]) @ self.R_bc0
        t_bc = np.array([self.t_bc_x, x[9], x[10]])
        R_eb = self.R_eb0 @ rotvec_to_matrix(np.array([x[11], x[12], 0.0]))
        t_eb = np.array([x[13], x[14], self.t_eb_z])
        t = t * (1.0 + x[15])  # the board's scale: known to its print and to the calibration's fixed points only
        R_be = R_bc @ R @ R_eb.T  # base_from_ee rotations, (N, 3, 3)
        p = (R_bc @ (t - np.einsum("nij,j->ni", R @ R_eb.T, t_eb)).T).T + t_bc
        theta = np.arctan2(R_be[:, 1, 0], R_be[:, 0, 0])
        theta = self.theta_ref + (theta - self.theta_ref + np.pi) % (2 * np.pi) - np.pi
        tilt = np.column_stack([R_be[:, 2, 1], -R_be[:, 2, 0]])
        return p, theta, tilt

    def residuals(self, x: np.ndarray, R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
        """Per pose (N, 6): 4 IKM residuals (m), 2 tilt residuals (rad), for the unknowns ``x`` (16,) and the board
        poses ``R``, ``t`` (default: the model's).

        Parameters
        ----------
        x : ndarray, shape (16,)
            The unknowns, :data:`_NAMES` order (m, rad; the board's scale dimensionless).
        R : ndarray, shape (N, 3, 3), optional
            Board rotations in the camera frame (default: the model's).
        t : ndarray, shape (N, 3), optional
            Board positions in the camera frame, m (default: the model's).

        Returns
        -------
        ndarray, shape (N, 6)
            IKM residuals (m) then tilt residuals (rad).
        """
        L, c, s1, s3, o1, o3 = x[:6]
        p, theta, tilt = self.ee_poses(x, R, t)
        X, Y, Z = p.T
        T = self.Tpr * theta
        f1 = np.sqrt(np.maximum(L**2 - (Y + c) ** 2 - Z**2, 1e-12))
        f3 = np.sqrt(np.maximum(L**2 - (Y - c) ** 2 - Z**2, 1e-12))
        qm = np.column_stack([X + T - f1 + o1, X + T + f1 + 2 * s1 + o1, X - T - f3 + o3, X - T + f3 + 2 * s3 + o3])
        return np.column_stack([qm - self.q, tilt])


@dataclass(frozen=True)
class EndEffectorSettings:
    """The end-effector method's settings (see :func:`calibrate_end_effector`).

    Attributes
    ----------
    phases : tuple of str
        Phases whose frames enter the fit.
    encoder_std_m : float
        Encoder noise, m.
    iterations : int
        Re-weighting passes.
    """

    phases: tuple[str, ...] = ("poses",)
    encoder_std_m: float = 1e-6
    iterations: int = 2


class WeightedResiduals:
    """The fit's whitened residuals ``Wh_k r_k(x)`` of the kept poses, flattened (6 M,): ``Wh`` (N, 6, 6) each pose's
    whitening, ``keep`` (N,) the poses in the fit (both updated by the fit's passes)."""

    def __init__(self, model: EndEffectorModel) -> None:
        n = model.R.shape[0]
        self.model = model
        self.Wh = np.broadcast_to(np.eye(6), (n, 6, 6)).copy()
        self.keep = np.ones(n, dtype=bool)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.einsum("nij,nj->ni", self.Wh, self.model.residuals(x))[self.keep].ravel()


@dataclass
class _PassesOutcome:
    """The re-weighted fit: unknowns ``x`` (16,), evaluations, the board poses' noise (diagonal ``Sigma_b`` (6, 6) or
    the common factor ``scale2`` of their covariances), whether the data are noise-free, scipy's last solution."""

    x: np.ndarray
    nfev: int
    Sigma_b: np.ndarray
    scale2: float
    noise_free: bool
    sol: Any


def calibrate_end_effector(
    obs: Observations,
    *,
    phases: tuple[str, ...] = ("poses",),
    encoder_std_m: float = 1e-6,
    iterations: int = 2,
    on_iteration: IterationCallback | None = None,
    settings: EndEffectorSettings | None = None,
) -> MethodResult:
    """Identify the four combinations from board poses and encoders (IKM residuals).

    Parameters
    ----------
    obs : Observations
        Needs board poses in ``phases`` (and, for the initial camera orientation, the rotation and
        translation phases when present).
    phases : tuple of str
        Phases whose frames enter the fit (the paper uses the 20-pose set).
    encoder_std_m : float
        Encoder noise, metres.
    iterations : int
        Re-weighting passes (noise covariance estimated from the residuals).
    on_iteration : callable, optional
        Receives ``{"stage", "iteration", "cost"}`` after each iteration of the fits (:mod:`.iterations`).
    settings : EndEffectorSettings, optional
        The settings at once; given, it replaces ``phases``, ``encoder_std_m`` and ``iterations``.

    Returns
    -------
    MethodResult
    """
    cfg = settings or EndEffectorSettings(phases, encoder_std_m, iterations)
    data = obs.arrays(*cfg.phases)
    data = data.subset(data.has_board)
    model, x0 = initial_model(obs, data, cfg.phases)
    C_board = board_covariances(obs, data)  # (n, 6, 6) or None (numbers without the extraction's covariances)
    wres = WeightedResiduals(model)
    check_excitation(central_jacobian(lambda x: model.residuals(x).ravel(), x0), _NAMES)
    fit = fit_passes(wres, x0, C_board, cfg, on_iteration)
    chi2_pose = np.zeros(len(data))
    if C_board is not None and not fit.noise_free:
        chi2_pose = reject_poses(wres, fit, C_board, cfg.encoder_std_m, on_iteration)
    return _end_effector_result(obs, data, wres, fit, C_board, chi2_pose)


def initial_model(obs: Observations, data: PhaseArrays, phases: tuple[str, ...]) -> tuple[EndEffectorModel, np.ndarray]:
    """The model of the board poses ``data`` and the unknowns' start (16,): the nominal combinations, the camera from
    the base frame (or Kabsch on the nominal positions), the translations by linear least squares and the offsets
    where the nominal pose says they are.

    Parameters
    ----------
    obs : Observations
        The observations (their base frame and nominal parameters).
    data : PhaseArrays
        The board poses and encoder values of the fit's frames.
    phases : tuple of str
        The phases the frames come from (for the base frame).

    Returns
    -------
    model : EndEffectorModel
        The model of the board poses.
    x0 : ndarray, shape (16,)
        The unknowns' start, :data:`_NAMES` order (m, rad; scale dimensionless).

    Raises
    ------
    IdentifiabilityError
        Fewer than 4 board poses, or poses the nominal DKM cannot reach.
    """
    nominal = obs.nominal
    n = len(data)
    if n < 4:
        raise IdentifiabilityError(
            f"the end-effector method has {n} board pose(s) in phase(s) {', '.join(phases)}; it needs at least "
            "4 (20 recommended)"
        )
    R, t, q = data.board_R, data.board_t, data.q
    try:
        poses_nom = dkm(nominal, q)
    except I4calError as exc:
        raise IdentifiabilityError(f"cannot initialise the end-effector fit: {exc}") from None
    theta_nom = poses_nom[:, 3] / nominal.T_per_rad
    # initial camera orientation: base frame when available, else Kabsch on positions
    try:
        R_bc0 = base_frame_from_observations(obs).camera_from_base_R.T
    except I4calError:
        R_bc0 = kabsch_points(poses_nom[:, :3], t)
    R_eb0 = orthonormalize(np.sum(rot_z(-theta_nom) @ R_bc0 @ R, axis=0))
    # initial translations: p_k = R_bc R_k (-R_eb^T t_eb) + R_bc t_k + t_bc (linear)
    # the board's height on the end-effector is a gauge freedom (a z offset of the camera): hold it at 0
    A = np.zeros((3 * n, 5))
    b = np.zeros(3 * n)
    for k in range(n):
        A[3 * k : 3 * k + 3, :2] = -(R_bc0 @ R[k] @ R_eb0.T)[:, :2]
        A[3 * k : 3 * k + 3, 2:] = np.eye(3)
        b[3 * k : 3 * k + 3] = poses_nom[k, :3] - R_bc0 @ t[k]
    sol0 = np.linalg.lstsq(A, b, rcond=None)[0]
    t_eb0, t_bc0 = np.array([sol0[0], sol0[1], 0.0]), sol0[2:]
    model = EndEffectorModel(R, t, q, nominal.T_per_rad, R_bc0, t_bc0[0], R_eb0, t_eb0[2], theta_nom)
    combos0 = np.array([nominal.combinations()[k] for k in COMBINATION_NAMES])
    x0 = np.concatenate(
        [combos0, [-nominal.S, -nominal.S - nominal.q03], np.zeros(3), t_bc0[1:], [0.0, 0.0], t_eb0[:2], [0.0]]
    )
    # put the offsets where the nominal pose says they are
    r0 = model.residuals(x0)
    x0[4] -= np.mean(r0[:, :2])
    x0[5] -= np.mean(r0[:, 2:4])
    return model, x0


def fit_passes(
    wres: WeightedResiduals,
    x0: np.ndarray,
    C_board: np.ndarray | None,
    cfg: EndEffectorSettings,
    on_iteration: IterationCallback | None,
) -> _PassesOutcome:
    """The fit, re-weighted each pass: by each pose's own covariance (PnP) times one common factor measured from the
    residuals, or, without covariances, by a diagonal board-pose noise estimated from the residuals.

    Parameters
    ----------
    wres : WeightedResiduals
        The whitened residuals; their whitening is updated each pass.
    x0 : ndarray, shape (16,)
        The unknowns' start.
    C_board : ndarray, shape (N, 6, 6), or None
        Each board pose's covariance (left rotation, rad; t, m), or None.
    cfg : EndEffectorSettings
        The settings (encoder noise, passes).
    on_iteration : IterationCallback or None
        Called at each iteration of the fits, or None.

    Returns
    -------
    _PassesOutcome
        The unknowns (16,), evaluations, the board poses' noise (``Sigma_b`` (6, 6), rad^2 and m^2, or the factor
        ``scale2``, dimensionless), whether the data are noise-free, scipy's last solution.

    Raises
    ------
    ConvergenceError
        A pass did not converge.
    """
    model = wres.model
    n, p = model.R.shape[0], x0.size
    x = x0
    nfev = 0
    Sigma_b = np.zeros((6, 6))
    scale2 = 1.0
    n_passes = max(cfg.iterations, 1) + (1 if C_board is not None else 0)
    noise_free = False
    sol = None
    for npass in range(n_passes):
        if npass > 0:
            r = model.residuals(x)
            if np.sqrt(np.mean(r**2)) < 1e-12:
                noise_free = True
                break  # noise-free data: nothing to weight
            Ak = _pose_sensitivity(model, x)  # (n, 6, 6)
            if C_board is not None:
                # each pose's own covariance (PnP), times one common factor measured from the residuals
                scale2 = _board_noise_factor(Ak, C_board, r, wres.keep, p)
                Cr = scale2 * Ak @ C_board @ Ak.transpose(0, 2, 1)
            else:
                # map residuals back to board-pose errors (rotation left-perturbation, translation), per pose;
                # a diagonal noise covariance (6 variances) stays stable with 20 poses
                eps = np.linalg.solve(Ak, r[..., None])[..., 0]
                Sigma_b = np.diag(np.diag(eps.T @ eps)) / max(n - p / 6.0, 1.0)
                Cr = Ak @ Sigma_b @ Ak.transpose(0, 2, 1)
            wres.Wh = _whitener(Cr, cfg.encoder_std_m)
        sol = _solve_checked(wres, x, on_iteration, f"pass-{npass + 1}")
        x = sol.x
        nfev += sol.nfev
    return _PassesOutcome(x, nfev, Sigma_b, scale2, noise_free, sol)


def reject_poses(
    wres: WeightedResiduals,
    fit: _PassesOutcome,
    C_board: np.ndarray,
    encoder_std_m: float,
    on_iteration: IterationCallback | None,
) -> np.ndarray:
    """Poses whose residual the model does not explain (a wrong board pose): a studentized chi-square test, one round
    from the fit with every pose, then one refit without them and with the factor re-measured (``wres`` and ``fit``
    updated).

    Parameters
    ----------
    wres : WeightedResiduals
        The whitened residuals; ``keep`` and the whitening are updated.
    fit : _PassesOutcome
        The fit with every pose; updated by the refit.
    C_board : ndarray, shape (N, 6, 6)
        Each board pose's covariance (left rotation, rad; t, m).
    encoder_std_m : float
        Encoder noise, m.
    on_iteration : IterationCallback or None
        Called at each iteration of the refit, or None.

    Returns
    -------
    ndarray, shape (N,)
        Each pose's studentized chi-square (dimensionless).

    Raises
    ------
    ConvergenceError
        The refit did not converge.
    """
    model, x = wres.model, fit.x
    n, p = model.R.shape[0], x.size
    chi2_pose = _studentized_chi2(central_jacobian(wres, x), wres(x), n)
    wres.keep = _gate(chi2_pose, p)
    if not wres.keep.all():
        Ak = _pose_sensitivity(model, x)
        fit.scale2 = _board_noise_factor(Ak, C_board, model.residuals(x), wres.keep, p)
        wres.Wh = _whitener(fit.scale2 * Ak @ C_board @ Ak.transpose(0, 2, 1), encoder_std_m)
        sol = _solve_checked(wres, x, on_iteration, "without rejected poses")
        fit.x, fit.sol = sol.x, sol
        fit.nfev += sol.nfev
    return chi2_pose


def _solve_checked(fun: WeightedResiduals, x0: np.ndarray, on_iteration: IterationCallback | None, stage: str) -> Any:
    """:func:`_solve`, raising when it did not converge."""
    sol = _solve(fun, x0, on_iteration, stage)
    if sol.status <= 0 or not np.all(np.isfinite(sol.x)):
        raise ConvergenceError(f"end-effector fit did not converge: {sol.message}")
    return sol


def _end_effector_result(
    obs: Observations,
    data: PhaseArrays,
    wres: WeightedResiduals,
    fit: _PassesOutcome,
    C_board: np.ndarray | None,
    chi2_pose: np.ndarray,
) -> MethodResult:
    """The covariance (from the weighted normal matrix, with the intrinsics' part) and the :class:`MethodResult`."""
    model, x, keep = wres.model, fit.x, wres.keep
    n, p = len(data), x.size
    r = model.residuals(x)
    J = central_jacobian(wres, x)
    check_excitation(J, _NAMES)
    if np.sqrt(np.mean(r**2)) < 1e-12:
        cov_full = np.zeros((p, p))
    else:
        chi2_total = float(np.sum(wres(x) ** 2))
        dof = max(6 * int(keep.sum()) - p, 1)
        cov_full = np.linalg.inv(J.T @ J) * max(chi2_total / dof, 1e-300)
    Sigma_b = fit.Sigma_b
    if C_board is not None:
        Sigma_b = fit.scale2 * np.median(C_board[keep], axis=0)
    cov_poses = cov_full[:4, :4]
    intr_part = None if fit.noise_free else _intrinsics_part(obs, data, model, x, wres.Wh, keep, J)
    cov_intr = None
    noise_factor = None
    if intr_part is not None:
        # the residuals also carry the intrinsics' pose-dependent effect, counted in cov_intr: measure the
        # board poses' noise factor with it removed (intrinsics as nuisance unknowns with their prior)
        D, cov_intr = intr_part
        noise_factor = _noise_factor_without_intrinsics(J, wres(x), D)
        cov_poses = np.linalg.inv(J.T @ J)[:4, :4] * noise_factor
    cov = cov_poses if cov_intr is None else cov_poses + cov_intr
    breakdown = {"board_poses_and_encoders": std_dict(cov_poses)}
    if cov_intr is not None:
        breakdown["intrinsics"] = std_dict(cov_intr)
    return MethodResult(
        method="end-effector",
        combinations=combos_dict(x[:4]),
        combinations_std=std_dict(cov),
        covariance=cov,
        residual_rms=float(np.sqrt(np.mean(r[:, :4] ** 2))),
        residual_unit="m (IKM joint residual)",
        n_observations=6 * n,
        n_poses=n,
        iterations=int(fit.nfev),
        converged=True,
        message=str(fit.sol.message),
        std_breakdown=breakdown,
        diagnostics={
            "tilt_residual_rms_deg": float(np.rad2deg(np.sqrt(np.mean(r[:, 4:] ** 2)))),
            "board_noise_std": {
                "rotation_deg": np.rad2deg(np.sqrt(np.diag(Sigma_b)[:3])).tolist(),
                "translation_mm": (np.sqrt(np.diag(Sigma_b)[3:]) * 1e3).tolist(),
            },
            "board_noise_model": "per-pose covariance x factor" if C_board is not None else "diagonal, from residuals",
            "board_cov_factor": float(np.sqrt(fit.scale2)) if C_board is not None else None,
            "noise_factor_without_intrinsics": noise_factor,
            "rejected_poses": [int(i) for i in data.index[~keep]],
            "pose_chi2": chi2_pose.tolist(),
            "camera_tilt_deg": float(np.rad2deg(np.linalg.norm(x[6:9]))),
            "board_offset_on_ee_m": [float(x[13]), float(x[14])],
            "board_scale_ppm": float(x[15] * 1e6),
        },
        residuals=r,
    )


def _solve(fun, x0: np.ndarray, on_iteration: IterationCallback | None = None, stage: str = ""):
    """Trust-region least squares, then Gauss-Newton polishing to full precision."""
    sol = least_squares(
        fun,
        x0,
        method="trf",
        x_scale="jac",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=3000,
        callback=trf_callback(on_iteration, stage),
    )
    x = sol.x
    r = fun(x)
    cost = float(r @ r)
    polish = 0
    for _ in range(50):
        J = central_jacobian(fun, x, 1e-6)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        improved = False
        for alpha in (1.0, 0.5, 0.25, 0.125, 0.0625):  # backtracking line search
            x_new = x + alpha * step
            r_new = fun(x_new)
            c_new = float(r_new @ r_new)
            sol.nfev += 1
            if c_new < cost:
                improved = True
                break
        sol.nfev += 2 * x.size
        if not improved:
            break
        done = cost - c_new < 1e-14 * max(cost, 1e-300)
        x, r, cost = x_new, r_new, c_new
        if on_iteration is not None:
            polish += 1
            on_iteration({"stage": f"{stage} polish", "iteration": polish, "cost": 0.5 * cost})
        if done:
            break
    sol.x = x
    sol.fun = r
    return sol


def board_covariances(obs: Observations, arrays: PhaseArrays) -> np.ndarray | None:
    """The extraction's covariance of each board pose, as (left rotation [rad], t [m]), shape (N, 6, 6).

    The extraction gives ``board.cov`` for (rotation vector, t) from the PnP Jacobian; a change ``d`` of the
    rotation vector ``r`` is the left rotation ``J_l(r) d``. None when any pose of ``arrays`` lacks it or it is
    not a finite positive-definite 6x6 matrix (numbers with known noise, as the geometric simulator gives).

    Parameters
    ----------
    obs : Observations
        The observations holding the boards.
    arrays : PhaseArrays
        The phase's arrays (which frames).

    Returns
    -------
    ndarray, shape (N, 6, 6), or None
        Covariances, rad^2 (rotation block) and m^2 (translation block).
    """
    out = np.empty((len(arrays), 6, 6))
    for k, i in enumerate(arrays.index):
        board = obs.frames[int(i)].board
        c = board.cov if board is not None else None
        if c is None:
            return None
        C = np.asarray(c, dtype=np.float64)
        if C.shape != (6, 6) or not np.all(np.isfinite(C)):
            return None
        T = np.eye(6)
        T[:3, :3] = _left_jacobian(matrix_to_rotvec(arrays.board_R[k]))
        C = T @ (0.5 * (C + C.T)) @ T.T
        if np.linalg.eigvalsh(C)[0] <= 0:
            return None
        out[k] = C
    return out


def _intrinsics_part(
    obs: Observations,
    data: PhaseArrays,
    model: EndEffectorModel,
    x: np.ndarray,
    Wh: np.ndarray,
    keep: np.ndarray,
    J: np.ndarray,
) -> tuple[np.ndarray, np.ndarray] | None:
    """How the camera intrinsics' error, common to every pose, moves the whitened residuals and the estimate.

    The board poses move by ``d_intrinsics @ step`` for one standard deviation ``step`` along each principal
    direction of the intrinsics' covariance (:mod:`.intrinsics`); the estimate moves by the weighted fit's
    gain times the whitened residuals' change.

    Returns
    -------
    D : ndarray, shape (6 M, S)
        Change of the whitened residuals of the M kept poses per principal step.
    cov : ndarray, shape (4, 4)
        Covariance of the combinations due to the intrinsics (m^2).
    None when the camera's covariance or a pose's ``d_intrinsics`` is unknown.
    """
    prior = intr.intrinsics_prior(obs)
    sens = intr.board_sensitivities(obs, data)
    if prior is None or sens is None:
        return None
    steps = intr.principal_steps(prior[1])
    if steps.shape[0] == 0:
        return None
    WA = Wh[keep] @ _pose_sensitivity(model, x)[keep]  # (M, 6, 6)
    D = np.einsum("nij,njk,sk->nis", WA, sens[keep], steps).reshape(-1, steps.shape[0])  # (6 M, S)
    dx = np.linalg.solve(J.T @ J, J.T @ D)  # (p, S): minus sign irrelevant for a covariance
    return D, (dx @ dx.T)[:4, :4]


def _noise_factor_without_intrinsics(J: np.ndarray, rw: np.ndarray, D: np.ndarray, n_iter: int = 50) -> float:
    """Variance factor of whitened residuals ``rw = J dx + D z + e`` with ``z ~ N(0, I)``, ``e ~ N(0, phi I)``.

    ``phi`` solves ``phi = |rw - J dx - D z|^2 / (n - p - edf_z)`` at the regularised least-squares ``dx, z``
    (``edf_z``: the effective number of degrees of freedom z takes from the residuals).
    """
    n, p = J.shape
    s = D.shape[1]
    phi = max(float(rw @ rw) / max(n - p, 1), 1e-300)
    M = np.hstack([J, D])
    for _ in range(n_iter):
        P = np.zeros((p + s, p + s))
        P[p:, p:] = phi * np.eye(s)
        H = M.T @ M + P
        sol = np.linalg.solve(H, M.T @ rw)
        res = rw - M @ sol
        edf = float(np.trace(np.linalg.solve(H, M.T @ M)))
        new = max(float(res @ res) / max(n - edf, 1.0), 1e-300)
        if abs(new - phi) < 1e-10 * phi:
            phi = new
            break
        phi = new
    return phi


def _left_jacobian(rv: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) at rotation vector ``rv`` (3,): ``exp(rv + d) = exp(J_l d) exp(rv)``, shape (3, 3)."""
    th = float(np.linalg.norm(rv))
    K = skew(rv)
    if th < 1e-8:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K


def _board_noise_factor(Ak: np.ndarray, C_board: np.ndarray, r: np.ndarray, keep: np.ndarray, n_params: int) -> float:
    """Common variance factor ``s^2`` of the board poses' covariances, measured from the residuals.

    Parameters
    ----------
    Ak : ndarray, shape (N, 6, 6)
        d residuals / d board-pose error per pose.
    C_board : ndarray, shape (N, 6, 6)
        The extraction's board-pose covariances (left rotation, t).
    r : ndarray, shape (N, 6)
        Residuals at the current estimate.
    keep : ndarray of bool, shape (N,)
        Poses in the fit.
    n_params : int
        Unknowns of the fit (the degrees of freedom the residuals lost).

    Returns
    -------
    float
        ``s^2``: the board poses' noise is ``s^2 C_board`` (the encoders' share is negligible against it).
    """
    Cr = Ak[keep] @ C_board[keep] @ Ak[keep].transpose(0, 2, 1)
    q = np.einsum("ni,ni->", r[keep], np.linalg.solve(Cr, r[keep][..., None])[..., 0])
    return max(float(q) / max(6 * int(keep.sum()) - n_params, 1), 1e-300)


def _whitener(Cr: np.ndarray, encoder_std_m: float) -> np.ndarray:
    """Per pose, the upper factor ``W`` (N, 6, 6) with ``W^T W = (Cr + encoder noise)^-1``."""
    Cr = Cr.copy()
    Cr[:, :4, :4] += encoder_std_m**2 * np.eye(4)
    Cr += 1e-30 * np.eye(6)
    return np.linalg.cholesky(np.linalg.inv(Cr)).transpose(0, 2, 1)


def _studentized_chi2(J: np.ndarray, rw: np.ndarray, n: int) -> np.ndarray:
    """Each pose's whitened residual chi-square corrected for its leverage, shape (N,).

    ``r_k^T (I - H_kk)^-1 r_k`` with ``H = J (J^T J)^-1 J^T``: chi-square with 6 degrees of freedom times the
    ratio of the true to the assumed noise factor, whatever the pose's weight in the fit.
    """
    G = np.linalg.solve(J.T @ J, J.T)  # (p, 6 n)
    out = np.empty(n)
    for k in range(n):
        sl = slice(6 * k, 6 * k + 6)
        M = np.eye(6) - J[sl] @ G[:, sl]
        out[k] = float(rw[sl] @ np.linalg.solve(M, rw[sl]))
    return out


def _gate(chi2_pose: np.ndarray, n_params: int) -> np.ndarray:
    """Poses kept: studentized chi-square below its 99.9 % quantile at the robust (median) noise factor.

    At most a quarter of the poses are rejected, and never so many that fewer than ``n_params / 6 + 1`` remain.
    """
    robust = max(robust_chi2_scale(chi2_pose, 6), 1e-300)
    keep = ~chi2_outliers(chi2_pose, 6, robust)
    n = chi2_pose.size
    min_keep = max(int(np.ceil(0.75 * n)), int(np.ceil(n_params / 6.0)) + 1)
    if keep.sum() < min_keep:
        keep = chi2_pose <= np.sort(chi2_pose)[min(min_keep, n) - 1]
    return keep


def _pose_sensitivity(model: EndEffectorModel, x: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """d residuals_k / d (board pose error_k), shape (N, 6, 6): rotation (left, camera frame) then translation."""
    n = model.R.shape[0]
    A = np.zeros((n, 6, 6))
    for j in range(6):
        d = np.zeros(6)
        d[j] = h
        outs = []
        for sgn in (1.0, -1.0):
            Rp = rotvec_to_matrix(sgn * d[:3]) @ model.R
            tp = model.t + sgn * d[3:]
            outs.append(model.residuals(x, Rp, tp))
        A[:, :, j] = (outs[0] - outs[1]) / (2 * h)
    return A
