"""Predicted covariance of each method's estimate for a plan, before any motion (linearised at nominal).

Every prediction is the covariance of the method's own estimator, linearised at the nominal geometry and
the plan's joint values, for measurement noise of known level (:class:`DesignNoise`; the geometric twin's
default, or the noise measured in a run). Units: metres and radians.

* **combined** (:func:`predict_combined`): the base frame's rotation from the rotation and translation
  phases (the board-only part of :func:`calib.identify.bound.combined_fisher`: its information on the camera
  rotation ``w``, the other board unknowns marginalised) is the prior of a fit of the rods' Jacobian entries
  ``(u_y/u_x, u_z/u_x)`` (eq. 8) over the four combinations and ``w``. ``weighting="gls"`` (each rod whitened
  by its direction noise, what the method does when rods carry their covariance, as extracted from images):
  the covariance is the inverse of the information, i.e. the Cramer-Rao bound of the combined model.
  ``"frobenius"`` (the paper's eq. 8, what the method does on rods without a covariance): the sandwich
  ``H^-1 (J^T S J / s^2 + P) H^-1`` with ``H = J^T J / s^2 + P``, S the rods' relative noise covariance.
* **end-effector** (:func:`predict_end_effector`): the method's IKM residuals
  (:class:`calib.identify.end_effector._Model`: four joint residuals and two tilt residuals per fit pose, 16
  unknowns with the camera and board transforms and the board's scale), weighted by their covariance from
  the board-pose noise (rotation ``board_rotation_rad`` per axis, translation ``board_translation_m`` along
  the camera axes) and the encoders: the GLS covariance ``(sum_k J_k^T C_k^-1 J_k)^-1``.
* **legs** (:func:`predict_legs`): step 1 locates each rod's upper joint as the least-squares intersection
  of its axis lines in the ``lock-i`` frames; each line's offset at the joint has the variance
  ``rod_point_m^2 + s^2 rod_direction_rad^2`` (s the distance along the axis from the measured point, the
  foot of the camera centre's perpendicular, to the joint), so the joint's covariance is
  ``A^-1 (sum (sigma_p^2 + s_k^2 sigma_u^2) M_k) A^-1``. It goes through steps 2-4 (the method's own
  pipeline, numerical derivatives) and adds the GLS covariance of (L, S, D) from the fit poses' leg
  directions (two rods averaged): the method's own error propagation, with the true noise instead of the
  residuals' estimate. All seven parameters and the four combinations.

The per-pose information matrices (:func:`combined_pose_information`, :func:`end_effector_pose_information`)
are additive over fit poses: the pose-set optimiser (:mod:`.optimize`) works on them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from calib.design.information import board_pose_sensitivity, end_effector_problem, invert_information
from calib.design.scene import Scene, rod_segments
from calib.errors import IdentifiabilityError, InputError
from calib.formats.plan import Plan
from calib.model.kinematics import dkm
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, SEVEN_TO_FOUR, I4Parameters
from calib.numerics.numdiff import central_jacobian
from calib.numerics.transforms import matrix_to_rotvec, rotvec_to_matrix, unit

if TYPE_CHECKING:
    from calib.design.predict_images import ImageNoise

__all__ = [
    "METHODS",
    "SEVEN_TO_FOUR",
    "DesignNoise",
    "base_frame_information",
    "combined_pose_information",
    "end_effector_pose_information",
    "phase_q",
    "predict_combined",
    "predict_end_effector",
    "predict_legs",
    "predict_plan",
    "schur",
]

METHODS = ("combined", "end-effector", "legs")


@dataclass(frozen=True)
class DesignNoise:
    """Measurement noise the prediction assumes (standard deviations; defaults: the geometric twin's).

    Attributes
    ----------
    rod_direction_rad : float
        Rod axis direction, per tangent axis (rad).
    rod_point_m : float
        Rod axis point (the foot of the camera centre's perpendicular), per perpendicular axis (m).
    board_rotation_rad : float
        Board orientation, per axis, left perturbation in the camera frame (rad).
    board_translation_m : tuple of float
        Board position along the camera's x, y and depth axes (m).
    encoder_m : float
        Encoders (m).
    """

    rod_direction_rad: float = 5e-4
    rod_point_m: float = 5e-4
    board_rotation_rad: float = 3e-4
    board_translation_m: tuple[float, float, float] = (1e-4, 1e-4, 3e-4)
    encoder_m: float = 1e-6

    def __post_init__(self) -> None:
        vals = [self.rod_direction_rad, self.rod_point_m, self.board_rotation_rad, *self.board_translation_m]
        if len(self.board_translation_m) != 3 or not all(np.isfinite(v) and v > 0 for v in vals):
            raise InputError("design noise levels must be finite and > 0 (board_translation_m: 3 values)")
        if not (np.isfinite(self.encoder_m) and self.encoder_m >= 0):
            raise InputError("design noise: encoder_m must be finite and >= 0")

    @classmethod
    def from_mapping(cls, data: dict[str, Any] | None) -> DesignNoise:
        """From a dict with the same keys (e.g. an observations document's ``noise``); missing keys: default.

        Parameters
        ----------
        data : dict, optional
            ``rod_direction_rad``, ``rod_point_m``, ``board_rotation_rad``, ``encoder_m`` (radians, metres) and
            ``board_translation_m`` (3 values, or one for all axes, metres); None or missing entries: default.

        Returns
        -------
        DesignNoise
            The noise levels.

        Raises
        ------
        InputError
            A level not finite and > 0 (``encoder_m`` >= 0).
        """
        if not data:
            return cls()
        base = cls()
        kw: dict[str, Any] = {}
        for k in ("rod_direction_rad", "rod_point_m", "board_rotation_rad", "encoder_m"):
            if data.get(k) is not None:
                kw[k] = float(data[k])
        if data.get("board_translation_m") is not None:
            t = data["board_translation_m"]
            kw["board_translation_m"] = tuple(float(v) for v in (t if isinstance(t, list | tuple) else [t] * 3))
        return cls(**{**base.to_dict(), **kw})

    def to_dict(self) -> dict[str, Any]:
        return {
            "rod_direction_rad": self.rod_direction_rad,
            "rod_point_m": self.rod_point_m,
            "board_rotation_rad": self.board_rotation_rad,
            "board_translation_m": tuple(self.board_translation_m),
            "encoder_m": self.encoder_m,
        }


def ratio_to_target(std_m: Any, target_m: Any) -> np.ndarray:
    """``std_m / target_m`` (float64, broadcast): a target as small as the API accepts (down to 5e-324 m) gives an
    infinite ratio, as intended, without an overflow warning.

    Parameters
    ----------
    std_m : array_like
        Predicted standard deviations, metres.
    target_m : array_like
        Target standard deviations, metres (> 0), broadcast against ``std_m``.

    Returns
    -------
    ndarray
        The ratios (dimensionless; <= 1 meets the target).
    """
    with np.errstate(over="ignore", divide="ignore"):
        return np.asarray(std_m, dtype=np.float64) / target_m


def scaled_inverse(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched inverse of symmetric (..., p, p) matrices, scaled to unit diagonal first (information in m^-2 and
    rad^-2 side by side), and whether each is determined (its eigenvalues within 1e-13 of the largest, a positive
    diagonal). Undetermined ones get a finite stand-in: the callers mark them (log det -inf, variances inf).

    Parameters
    ----------
    F : ndarray, shape (..., p, p)
        Symmetric information matrices (inverse squared units of the unknowns).

    Returns
    -------
    inverse : ndarray, shape (..., p, p)
        Their inverses (the covariances, squared units of the unknowns).
    ok : ndarray of bool, shape (...)
        Whether each is determined.
    """
    d = np.sqrt(np.einsum("...ii->...i", F))
    good = np.all(d > 0, axis=-1)
    d = np.where(good[..., None], d, 1.0)
    Fs = F / (d[..., :, None] * d[..., None, :])
    w, V = np.linalg.eigh(0.5 * (Fs + np.swapaxes(Fs, -1, -2)))
    ok = good & (w[..., 0] > 1e-13 * w[..., -1])
    w = np.where(ok[..., None], w, 1.0)
    return np.einsum("...ik,...k,...jk->...ij", V, 1.0 / w, V) / (d[..., :, None] * d[..., None, :]), ok


def mark_undetermined(C: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched covariances (..., k, k) and the log det of their inverses, both marked where undetermined (``ok``
    False, :func:`scaled_inverse`): variances inf, log det -inf.

    Parameters
    ----------
    C : ndarray, shape (..., k, k)
        Covariances (m^2 for the combinations).
    ok : ndarray of bool, shape (...)
        Whether each is determined.

    Returns
    -------
    cov : ndarray, shape (..., k, k)
        ``C``, all inf where undetermined.
    logdet : ndarray, shape (...)
        Log det of the inverse of ``C`` (the information), -inf where undetermined.
    """
    sign, logdet = np.linalg.slogdet(C)
    ld = np.where(ok & (sign > 0), -logdet, -np.inf)
    return np.where(ok[..., None, None], C, np.inf), ld


def phase_q(plan: Plan, *phases: str) -> np.ndarray:
    """Joint values (N, 4) of a plan's steps in ``phases`` (metres; guided lines are left out).

    Parameters
    ----------
    plan : Plan
        The plan.
    *phases : str
        The phases wanted.

    Returns
    -------
    ndarray, shape (N, 4)
        Joint targets of those steps in plan order, metres.
    """
    qs = [s.q for s in plan.steps if s.phase in phases and s.q is not None]
    return np.asarray(qs, dtype=np.float64).reshape(-1, 4)


def schur(F: np.ndarray, k: int = 4) -> np.ndarray:
    """Information on the first ``k`` unknowns with the others marginalised, ``F_aa - F_ab F_bb^+ F_ba``.

    Parameters
    ----------
    F : ndarray, shape (p, p)
        Information matrix (inverse squared units of the unknowns).
    k : int, optional
        Number of unknowns kept (the first ones).

    Returns
    -------
    ndarray, shape (k, k)
        Their marginal information.
    """
    if F.shape[0] == k:
        return F
    Fbb = F[k:, k:]
    return F[:k, :k] - F[:k, k:] @ np.linalg.pinv(Fbb, rcond=1e-13, hermitian=True) @ F[k:, :k]


# -- combined ------------------------------------------------------------------------------------------------
def base_frame_information(
    nominal: I4Parameters, q_rot: np.ndarray, q_tra: np.ndarray, camera_from_base_R: np.ndarray, noise: DesignNoise
) -> np.ndarray:
    """Information (3, 3) on the camera rotation ``w`` (left, camera frame) from the base-frame phases.

    The board orientations of the rotation phase (the rotation axis z_B) and the board positions of the
    translation phase (the direction x_B); their reference orientation, angles and start position are
    marginalised. Units: rad^-2.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres; ``T_per_rad`` gives the rotation phase's angles).
    q_rot, q_tra : ndarray, shape (N, 4)
        Joint values of the rotation and translation phases, metres (at least 2 each).
    camera_from_base_R : ndarray, shape (3, 3)
        The camera's orientation (base axes in the camera frame).
    noise : DesignNoise
        Board pose noise (radians, metres).

    Returns
    -------
    ndarray, shape (3, 3)
        Information on ``w``, rad^-2.

    Raises
    ------
    IdentifiabilityError
        Fewer than 2 frames in a phase.
    """
    q_rot = np.asarray(q_rot, dtype=np.float64).reshape(-1, 4)
    q_tra = np.asarray(q_tra, dtype=np.float64).reshape(-1, 4)
    if len(q_rot) < 2 or len(q_tra) < 2:
        raise IdentifiabilityError("the base frame needs at least 2 rotation and 2 translation frames")
    R_cb = np.asarray(camera_from_base_R, dtype=np.float64)
    n_r = len(q_rot)
    T_rot = (q_rot[:, 0] + q_rot[:, 1] - q_rot[:, 2] - q_rot[:, 3]) / 4.0
    th0 = (T_rot - T_rot[0]) / nominal.T_per_rad
    s = q_tra.mean(axis=1)
    sig_t = np.asarray(noise.board_translation_m, dtype=np.float64)

    def model(x: np.ndarray) -> np.ndarray:
        w, rho, th, t0 = x[:3], x[3:6], x[6 : 6 + n_r], x[6 + n_r :]
        R = rotvec_to_matrix(w) @ R_cb
        Rk = rotvec_to_matrix(R[:, 2][None, :] * th[:, None]) @ rotvec_to_matrix(rho)
        rot = matrix_to_rotvec(Rk).ravel() / noise.board_rotation_rad
        tra = ((t0[None, :] + s[:, None] * R[:, 0][None, :]) / sig_t).ravel()
        return np.concatenate([rot, tra])

    x0 = np.concatenate([np.zeros(6), th0, np.zeros(3)])
    J = central_jacobian(model, x0, 1e-7)
    return schur(J.T @ J, 3)


def _combined_rods(
    nominal: I4Parameters, q_fit: np.ndarray, camera_from_base_R: np.ndarray, min_ux: float = 0.05
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per rod observation (2 per leg and pose): Jacobian (M, 2, 7) of eq. 8's raw residuals over
    (combinations, w), their relative noise covariance (M, 2, 2) for unit direction noise, pose index (M,)."""
    from calib.identify.combined import model_ratios, ratio_gradient

    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    R0 = np.asarray(camera_from_base_R, dtype=np.float64)
    xi0 = np.array([nominal.combinations()[k] for k in COMBINATION_NAMES])
    from calib.identify.bound import leg_directions_reduced

    uB = leg_directions_reduced(xi0, q_fit)  # (N, 4, 3)
    u_cam = np.repeat((uB @ R0.T)[:, :, None, :], 2, axis=2).reshape(-1, 3)  # two rods per leg
    k_idx = np.repeat(np.arange(len(q_fit)), 8)
    leg = np.tile(np.repeat(np.arange(4), 2), len(q_fit))
    keep = np.abs((u_cam @ R0)[:, 0]) >= min_ux
    u_cam, k_idx, leg = u_cam[keep], k_idx[keep], leg[keep]

    def raw(v: np.ndarray) -> np.ndarray:
        R = rotvec_to_matrix(v[4:7]) @ R0
        ub = u_cam @ R
        return (model_ratios(v[:4], q_fit)[k_idx, leg] - ub[:, 1:] / ub[:, :1]).ravel()

    x0 = np.concatenate([xi0, np.zeros(3)])
    J = central_jacobian(raw, x0, 1e-7).reshape(-1, 2, 7)
    ub = u_cam @ R0
    G = ratio_gradient(ub)
    P = np.eye(3)[None] - ub[:, :, None] * ub[:, None, :]
    S = np.einsum("mij,mjk,mlk->mil", G, P, G)
    return J, S, k_idx


def combined_pose_information(
    nominal: I4Parameters, q_fit: np.ndarray, camera_from_base_R: np.ndarray, noise: DesignNoise
) -> np.ndarray:
    """GLS information (N, 7, 7) of each fit pose's rods on (four combinations, w), per m^2 and rad^2.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres).
    q_fit : ndarray, shape (N, 4)
        Joint values of the fit poses, metres.
    camera_from_base_R : ndarray, shape (3, 3)
        The camera's orientation (base axes in the camera frame).
    noise : DesignNoise
        Rod direction noise (radians).

    Returns
    -------
    ndarray, shape (N, 7, 7)
        Per pose, information on the four combinations (m^-2) and ``w`` (rad^-2).
    """
    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    J, S, k = _combined_rods(nominal, q_fit, camera_from_base_R)
    Si = np.linalg.inv(S + 1e-30 * np.eye(2)) / noise.rod_direction_rad**2
    Fm = np.einsum("mai,mab,mbj->mij", J, Si, J)
    out = np.zeros((len(q_fit), 7, 7))
    np.add.at(out, k, Fm)
    return out


def predict_combined(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    q_rot: np.ndarray,
    q_tra: np.ndarray,
    camera_from_base_R: np.ndarray,
    noise: DesignNoise | None = None,
    weighting: str = "gls",
) -> np.ndarray:
    """Predicted covariance (4, 4) of the combined method's four combinations (m^2).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit, q_rot, q_tra : ndarray, shape (N, 4)
        Joint values of the fit poses, the rotation and the translation phases (m).
    camera_from_base_R : ndarray, shape (3, 3)
        The camera's orientation (base axes in the camera frame).
    noise : DesignNoise, optional
        Noise levels (radians, metres); :class:`DesignNoise`'s defaults if None.
    weighting : {"gls", "frobenius"}
        The method's weighting (module docstring).

    Returns
    -------
    ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.

    Raises
    ------
    IdentifiabilityError
        The plan does not determine the four combinations.
    InputError
        An unknown ``weighting``.
    """
    noise = noise or DesignNoise()
    Pw = np.zeros((7, 7))
    Pw[4:, 4:] = base_frame_information(nominal, q_rot, q_tra, camera_from_base_R, noise)
    if weighting == "gls":
        F = combined_pose_information(nominal, q_fit, camera_from_base_R, noise).sum(axis=0) + Pw
        return invert_information(F, "combined")[:4, :4]
    if weighting != "frobenius":
        raise InputError(f"weighting must be 'gls' or 'frobenius', got {weighting!r}", field="weighting")
    J, S, _ = _combined_rods(nominal, q_fit, camera_from_base_R)
    s2 = noise.rod_direction_rad**2
    Jf = J.reshape(-1, 7)
    H = Jf.T @ Jf / s2 + Pw
    Hi = invert_information(H, "combined")
    mid = np.einsum("mai,mab,mbj->ij", J, S, J) / s2 + Pw
    return (Hi @ mid @ Hi)[:4, :4]


# -- end-effector ---------------------------------------------------------------------------------------------
def end_effector_pose_information(
    nominal: I4Parameters, q_fit: np.ndarray, scene: Scene, noise: DesignNoise | None = None
) -> np.ndarray:
    """GLS information (N, 16, 16) of each fit pose's board pose and encoders on the end-effector method's
    unknowns (four combinations first; then the offsets, camera and board transforms and the board's scale).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit : ndarray, shape (N, 4)
        Joint values of the fit poses, metres.
    scene : Scene
        The camera's and the board's mounting.
    noise : DesignNoise, optional
        Board pose and encoder noise (radians, metres).

    Returns
    -------
    ndarray, shape (N, 16, 16)
        Per pose, information on the unknowns (inverse squared metres and radians).
    """
    noise = noise or DesignNoise()
    model, x0, R, t = end_effector_problem(nominal, q_fit, scene)
    n = len(R)
    r0 = model.residuals(x0)
    if np.max(np.abs(r0)) > 1e-9:
        raise RuntimeError(f"end-effector design model does not close at nominal ({np.max(np.abs(r0)):.2e})")
    J = central_jacobian(lambda x: model.residuals(x).ravel(), x0, 1e-7).reshape(n, 6, -1)
    G = board_pose_sensitivity(model, x0, R, t)
    Sb = np.diag([noise.board_rotation_rad**2] * 3 + [v**2 for v in noise.board_translation_m])
    C = np.einsum("nij,jk,nlk->nil", G, Sb, G)
    C[:, :4, :4] += noise.encoder_m**2 * np.eye(4)
    C += 1e-24 * np.eye(6)
    Ci = np.linalg.inv(C)
    return np.einsum("nai,nab,nbj->nij", J, Ci, J)


def predict_end_effector(
    nominal: I4Parameters, q_fit: np.ndarray, scene: Scene, noise: DesignNoise | None = None
) -> np.ndarray:
    """Predicted covariance (4, 4) of the end-effector method's four combinations (m^2).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit : ndarray, shape (N, 4)
        Joint values of the fit poses, metres.
    scene : Scene
        The camera's and the board's mounting.
    noise : DesignNoise, optional
        Board pose and encoder noise (radians, metres).

    Returns
    -------
    ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.

    Raises
    ------
    IdentifiabilityError
        The plan does not determine the four combinations.
    """
    F = end_effector_pose_information(nominal, q_fit, scene, noise).sum(axis=0)
    return invert_information(F, "end-effector")[:4, :4]


# -- legs -----------------------------------------------------------------------------------------------------
def _rod_lines(scene: Scene, nominal: I4Parameters, q: np.ndarray):
    pose = dkm(nominal, q)
    top, bot = rod_segments(scene, nominal, q, pose)  # (N, 4, 2, 3) camera frame
    u = unit(bot - top)
    s = -np.einsum("...k,...k->...", top, u)  # foot of the camera centre's perpendicular: top + s u
    p = top + s[..., None] * u
    return top, bot, u, p


def predict_legs(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    q_lock: list[np.ndarray],
    scene: Scene,
    noise: DesignNoise | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted covariances of the legs method: the seven parameters (7, 7) and the four combinations (4, 4).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit : ndarray, shape (N, 4)
        Fit poses (steps 3-4), metres.
    q_lock : list of 4 ndarrays, shape (N_i, 4)
        Frames of the ``lock-1`` .. ``lock-4`` phases (actuator i fixed), metres.
    scene : Scene
        The camera's mounting and the rods' geometry.
    noise : DesignNoise, optional
        Rod direction (radians) and point (metres) noise.

    Returns
    -------
    cov7 : ndarray, shape (7, 7)
        Covariance of the seven parameters, m^2.
    cov4 : ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.

    Raises
    ------
    IdentifiabilityError
        Fewer than 2 frames in a lock phase.
    """
    from calib.identify.legs import LegsModel, steps34_covariance

    noise = noise or DesignNoise()
    if len(q_lock) != 4 or any(len(np.atleast_2d(q)) < 2 for q in q_lock):
        raise IdentifiabilityError("the legs method needs at least 2 frames in each of lock-1 .. lock-4")
    su2, sp2 = noise.rod_direction_rad**2, noise.rod_point_m**2
    P = np.zeros((4, 2, 3))
    covP = np.zeros((24, 24))
    q_locked = np.zeros(4)
    for i in range(4):
        q = np.atleast_2d(np.asarray(q_lock[i], dtype=np.float64))
        q_locked[i] = float(np.mean(q[:, i]))
        top, _bot, u, p = _rod_lines(scene, nominal, q)
        for j in range(2):
            uu = u[:, i, j]
            M = np.eye(3)[None] - uu[:, :, None] * uu[:, None, :]
            A = M.sum(axis=0)
            s = np.einsum("nk,nk->n", top[:, i, j] - p[:, i, j], uu)
            Ai = np.linalg.inv(A)
            k = (2 * i + j) * 3
            covP[k : k + 3, k : k + 3] = Ai @ np.einsum("n,nij->ij", sp2 + s**2 * su2, M) @ Ai
            P[i, j] = top[:, i, j].mean(axis=0)
    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    top, bot, u, _p = _rod_lines(scene, nominal, q_fit)
    U = unit(u.mean(axis=2))  # (N, 4, 3)
    CU = (su2 / 2.0) * (np.eye(3)[None, None] - U[..., :, None] * U[..., None, :])
    pts = 0.5 * (top + bot).mean(axis=2)
    pipe = LegsModel(q_locked, q_fit, pts, np.ones((len(q_fit), 4), dtype=bool), CU, nominal)
    seven = pipe.run(P, U)
    x2 = np.array([*seven[1:4].tolist(), seven[0]])
    GP = central_jacobian(lambda p: pipe.run(p.reshape(4, 2, 3), U, x2), P.ravel(), 1e-7)  # (7, 24)
    c34, _chi, _dof = steps34_covariance(pipe, P, U, seven)
    cov7 = GP @ covP @ GP.T
    idx = np.array([6, 4, 5])
    cov7[np.ix_(idx, idx)] += c34
    return cov7, SEVEN_TO_FOUR @ cov7 @ SEVEN_TO_FOUR.T


def _parts_std(parts: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Each part's (4, 4) covariance (m^2) as its std (m) per combination."""
    return {
        name: {k: float(np.sqrt(max(c[i, i], 0.0))) for i, k in enumerate(COMBINATION_NAMES)}
        for name, c in parts.items()
    }


# -- a whole plan ---------------------------------------------------------------------------------------------
@dataclass
class Prediction:
    """Predicted standard deviations per method (metres), with the covariances they come from."""

    std: dict[str, dict[str, float]] = field(default_factory=dict)
    covariance: dict[str, list[list[float]]] = field(default_factory=dict)
    legs_seven_std: dict[str, float] | None = None
    errors: dict[str, str] = field(default_factory=dict)
    noise: dict[str, Any] = field(default_factory=dict)
    weighting: str = "gls"
    #: per method, the std (m) per combination that each independent source of error contributes (their variances
    #: add up to ``std``'s): the image-level prediction of the end-effector (board poses and encoders, intrinsics) and
    #: legs methods (the lock phases' joint centres and their systematic depth error, the fit poses' leg directions,
    #: intrinsics, limb-edge bias, a priori), what tells which phase limits a combination
    parts: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "std_m": self.std,
            "covariance_m2": self.covariance,
            "parts_std_m": self.parts,
            "legs_seven_std_m": self.legs_seven_std,
            "errors": self.errors,
            "noise": self.noise,
            "combined_weighting": self.weighting,
        }


def predict_plan(
    plan: Plan,
    nominal: I4Parameters,
    scene: Scene,
    noise: DesignNoise | ImageNoise | None = None,
    methods: tuple[str, ...] = METHODS,
    weighting: str = "gls",
) -> Prediction:
    """Predicted standard deviations of ``methods`` for a plan (fit poses: the ``poses`` phase).

    ``noise``: a :class:`DesignNoise` (measurements with known noise, the geometric twin's models) or a
    :class:`.predict_images.ImageNoise` (what the image extraction measures and the methods' image-level
    uncertainty: :mod:`.predict_images`; ``weighting`` is then the method's own, GLS on the rods' ``cov_u``).
    A method the plan cannot feed (e.g. no ``lock-i`` phase for the legs method) is reported in ``errors``
    with the reason, not raised.

    Parameters
    ----------
    plan : Plan
        The plan.
    nominal : I4Parameters
        The geometry the models are linearised at (metres).
    scene : Scene
        The camera, its mounting and the board.
    noise : DesignNoise or ImageNoise, optional
        The noise model (see above); :class:`DesignNoise`'s defaults if None.
    methods : tuple of str, optional
        Methods predicted, among :data:`METHODS`.
    weighting : {"gls", "frobenius"}, optional
        The combined method's weighting with a :class:`DesignNoise`.

    Returns
    -------
    Prediction
        Standard deviations per method and combination (metres), covariances (m^2), the reasons of the methods
        the plan cannot feed.

    Raises
    ------
    InputError
        An unknown method.
    """
    from calib.design.predict_images import ImageNoise

    noise = noise or DesignNoise()
    if isinstance(noise, ImageNoise):
        return _predict_plan_images(plan, nominal, scene, noise, methods)
    out = Prediction(noise=noise.to_dict(), weighting=weighting)
    q_fit = phase_q(plan, "poses")
    for m in methods:
        try:
            if len(q_fit) < 2:
                raise IdentifiabilityError("the plan has fewer than 2 fit poses")
            if m == "combined":
                cov = predict_combined(
                    nominal,
                    q_fit,
                    phase_q(plan, "rotation"),
                    phase_q(plan, "translation"),
                    scene.camera_from_base.R,
                    noise,
                    weighting,
                )
            elif m == "end-effector":
                cov = predict_end_effector(nominal, q_fit, scene, noise)
            elif m == "legs":
                cov7, cov = predict_legs(
                    nominal, q_fit, [phase_q(plan, f"lock-{i}") for i in range(1, 5)], scene, noise
                )
                out.legs_seven_std = {k: float(np.sqrt(max(cov7[i, i], 0.0))) for i, k in enumerate(PARAMETER_NAMES)}
            else:
                raise InputError(f"unknown method {m!r}; methods are {', '.join(METHODS)}", field="methods")
        except IdentifiabilityError as exc:
            out.errors[m] = str(exc)
            continue
        out.std[m] = {k: float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(COMBINATION_NAMES)}
        out.covariance[m] = np.asarray(cov).tolist()
    return out


def _predict_plan_images(
    plan: Plan, nominal: I4Parameters, scene: Scene, noise: ImageNoise, methods: tuple[str, ...]
) -> Prediction:
    """:func:`predict_plan` with the image-level models (:mod:`.predict_images`)."""
    from calib.design.predict_images import (
        predict_combined_images_posteriors,
        predict_end_effector_images,
        predict_legs_images,
    )

    out = Prediction(noise=noise.to_dict(), weighting="gls")
    q_fit = phase_q(plan, "poses")
    posterior = None  # the intrinsics after the rods (the combined fit's), which the other methods use
    edge_post = None  # the limb-edge bias after the rods (the combined fit's), which the legs method uses
    for m in methods:
        if m not in METHODS:
            raise InputError(f"unknown method {m!r}; methods are {', '.join(METHODS)}", field="methods")
    try:
        if len(q_fit) < 2:
            raise IdentifiabilityError("the plan has fewer than 2 fit poses")
        cov_c, posterior, edge_post = predict_combined_images_posteriors(
            nominal, q_fit, phase_q(plan, "rotation"), phase_q(plan, "translation"), scene, noise
        )
    except IdentifiabilityError as exc:
        cov_c, edge_post, why = None, None, str(exc)
    for m in methods:
        try:
            if m == "combined":
                if cov_c is None:
                    raise IdentifiabilityError(why)
                cov = cov_c
            elif len(q_fit) < 2:
                raise IdentifiabilityError("the plan has fewer than 2 fit poses")
            elif m == "end-effector":
                cov, parts = predict_end_effector_images(nominal, q_fit, scene, noise, posterior)
                out.parts[m] = _parts_std(parts)
            else:
                q_lock = [phase_q(plan, f"lock-{i}") for i in range(1, 5)]
                cov7, cov, parts7 = predict_legs_images(nominal, q_fit, q_lock, scene, noise, posterior, edge_post)
                out.parts[m] = _parts_std({k: SEVEN_TO_FOUR @ v @ SEVEN_TO_FOUR.T for k, v in parts7.items()})
                out.legs_seven_std = {k: float(np.sqrt(max(cov7[i, i], 0.0))) for i, k in enumerate(PARAMETER_NAMES)}
        except IdentifiabilityError as exc:
            out.errors[m] = str(exc)
            continue
        out.std[m] = {k: float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(COMBINATION_NAMES)}
        out.covariance[m] = np.asarray(cov).tolist()
    return out
