"""Cramer-Rao lower bound of the combined method's four parameters, from a plan alone.

The measurement model is the one the combined method uses, written for every noisy input:

* rod directions in the fit poses: ``u_cam = R_cb u_B(xi, q)`` with ``u_B`` from the DKM
  (2 tangent components per rod; isotropic noise ``rod_direction_rad`` per axis, or a per-rod
  covariance);
* board rotations in the rotation phase: ``R_k = Rot(R_cb z_B, theta_k) R_ref`` (3 per frame,
  ``board_rotation_rad`` per axis, left perturbation in the camera frame);
* board positions in the translation phase: ``t_k = t_0 + s_k R_cb x_B`` (3 per frame,
  ``board_translation_m`` along the camera axes), ``s_k`` the common encoder increment.

Unknowns: the four combinations ``xi``, the camera rotation ``R_cb`` (3), the rotation phase's
reference orientation (3) and angles (one per frame), and ``t_0`` (3). The Fisher information is
``J^T J`` of the whitened model; the bound is the top-left 4x4 block of its inverse. Encoder noise
(micrometres) is negligible against the direction noise and is not modelled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.formats.plan import Plan
from calib.model.kinematics import pose_from_joints_reduced
from calib.model.parameters import COMBINATION_NAMES, I4Parameters
from calib.numerics.transforms import matrix_to_rotvec, rotvec_to_matrix, tangent_basis, unit

_SX = np.array([1.0, -1.0, 1.0, -1.0])


@dataclass(frozen=True)
class MeasurementNoise:
    """Noise of the combined method's inputs (standard deviations, per axis)."""

    rod_direction_rad: float = 5e-4
    board_rotation_rad: float = 3e-4
    board_translation_m: tuple[float, float, float] = (1e-4, 1e-4, 3e-4)
    rods_per_leg: int = 2


def leg_directions_reduced(combos: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Unit leg directions in the base frame from the four combinations, shape (N, 4, 3).

    Parameters
    ----------
    combos : ndarray, shape (4,)
        The four combinations in :data:`~calib.model.parameters.COMBINATION_NAMES` order, metres.
    q : ndarray, shape (N, 4)
        Encoder values, metres.

    Returns
    -------
    ndarray, shape (N, 4, 3)
        Unit direction of each leg at each pose, base frame (dimensionless).
    """
    L, c = combos[0], combos[1]
    Y, Z, f1, f3 = pose_from_joints_reduced(combos, q)
    u = np.empty((q.shape[0], 4, 3))
    for i, (f, yo) in enumerate(((f1, Y + c), (f1, Y + c), (f3, Y - c), (f3, Y - c))):
        u[:, i] = np.stack([_SX[i] * f, yo, Z], axis=1) / L
    return unit(u)


def _phase_q(plan: Plan, phase: str) -> np.ndarray:
    qs = [s.q for s in plan.steps if s.phase == phase and s.q is not None]
    return np.asarray(qs, dtype=np.float64).reshape(-1, 4)


def combined_fisher(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    q_rot: np.ndarray,
    q_tra: np.ndarray,
    noise: MeasurementNoise,
    camera_from_base_R: np.ndarray | None = None,
    rod_cov: np.ndarray | None = None,
) -> np.ndarray:
    """Fisher information of all unknowns (the four combinations first).

    Parameters
    ----------
    nominal : I4Parameters
        Geometry the model is linearised at (metres).
    q_fit, q_rot, q_tra : ndarray, shape (N, 4)
        Encoder values of the fit poses, the rotation phase and the translation phase (metres).
    noise : MeasurementNoise
        Standard deviations of the rods' directions (radians) and the board's poses (radians, metres).
    camera_from_base_R : ndarray, shape (3, 3), optional
        Rotation from the base frame to the camera's; identity by default.
    rod_cov : ndarray, shape (N_fit, 4, 3, 3), optional
        Per-leg direction covariance (camera frame) of one rod, radians^2; default isotropic.

    Returns
    -------
    ndarray, shape (17 + N_rot, 17 + N_rot)
        ``J^T J`` of the whitened model; unknowns in the order: the four combinations (metres), the camera rotation
        (3, radians), the rotation phase's reference orientation (3, radians), its angles (``N_rot``, radians) and
        ``t_0`` (3, metres).
    """
    R_cb = np.eye(3) if camera_from_base_R is None else np.asarray(camera_from_base_R, dtype=np.float64)
    xi0 = np.array([nominal.combinations()[k] for k in COMBINATION_NAMES])
    n_r = q_rot.shape[0]
    T_rot = (q_rot[:, 0] + q_rot[:, 1] - q_rot[:, 2] - q_rot[:, 3]) / 4.0
    th0 = (T_rot - T_rot[0]) / nominal.T_per_rad
    s = q_tra.mean(axis=1)
    x0 = np.concatenate([xi0, np.zeros(3), np.zeros(3), th0, np.zeros(3)])
    u0 = leg_directions_reduced(xi0, q_fit) @ R_cb.T  # (N, 4, 3) camera frame
    # whitening of each leg direction: tangent basis scaled by the noise (rods of a leg averaged)
    Wl = np.empty((*u0.shape[:2], 2, 3))
    for k in range(u0.shape[0]):
        for i in range(4):
            T = tangent_basis(u0[k, i]).T
            C = noise.rod_direction_rad**2 * np.eye(2) if rod_cov is None else T @ rod_cov[k, i] @ T.T
            C = C / noise.rods_per_leg
            Wl[k, i] = np.linalg.cholesky(np.linalg.inv(C)).T @ T
    sig_t = np.asarray(noise.board_translation_m, dtype=np.float64)

    def model(x: np.ndarray) -> np.ndarray:
        xi, w, rho, th, t0 = x[:4], x[4:7], x[7:10], x[10 : 10 + n_r], x[10 + n_r :]
        R = rotvec_to_matrix(w) @ R_cb
        u = leg_directions_reduced(xi, q_fit) @ R.T
        rods = np.einsum("kiab,kib->kia", Wl, u).ravel()
        z = R[:, 2]
        Rref = rotvec_to_matrix(rho)
        Rk = rotvec_to_matrix(z[None, :] * th[:, None]) @ Rref
        rot = matrix_to_rotvec(Rk).ravel() / noise.board_rotation_rad
        tk = t0[None, :] + s[:, None] * R[:, 0][None, :]
        tra = (tk / sig_t).ravel()
        return np.concatenate([rods, rot, tra])

    h = 1e-7
    cols = []
    for j in range(x0.size):
        e = np.zeros_like(x0)
        e[j] = h
        cols.append((model(x0 + e) - model(x0 - e)) / (2 * h))
    J = np.column_stack(cols)
    return J.T @ J


def _spd_inverse(F: np.ndarray) -> np.ndarray:
    """Inverse of a Fisher information matrix whose unknowns have very different scales (rad, m, rotations).

    Jacobi-scaled (unit diagonal) before an eigen-decomposition, so that the scale disparity does not
    turn into negative variances; directions without information are left out when they do not involve
    the first four unknowns (the combinations), else ValueError.
    """
    d = np.sqrt(np.maximum(np.diag(F), 1e-300))
    Fs = F / np.outer(d, d)
    w, V = np.linalg.eigh(0.5 * (Fs + Fs.T))
    keep = w > 1e-12 * w[-1]
    # directions the measurements leave free (e.g. a nuisance angle no phase excites) are harmless
    # when they do not involve the four combinations
    if np.any(np.abs(V[:4, ~keep]) > 1e-6):
        raise ValueError("the measurements do not determine the four combinations (singular information matrix)")
    return (V[:, keep] / w[keep]) @ V[:, keep].T / np.outer(d, d)


def crlb_combined(
    nominal: I4Parameters,
    plan: Plan,
    noise: MeasurementNoise | None = None,
    camera_from_base_R: np.ndarray | None = None,
    rod_cov: np.ndarray | None = None,
) -> dict:
    """Predicted standard deviations (the bound) of the four combinations for a plan, before any motion.

    Parameters
    ----------
    nominal : I4Parameters
        Geometry the model is linearised at (metres).
    plan : Plan
        The plan; its ``poses``, ``rotation`` and ``translation`` phases (at least two steps each) are used.
    noise : MeasurementNoise, optional
        Standard deviations of the inputs (radians, metres); the defaults of :class:`MeasurementNoise` if None.
    camera_from_base_R : ndarray, shape (3, 3), optional
        Rotation from the base frame to the camera's; identity by default.
    rod_cov : ndarray, shape (N_fit, 4, 3, 3), optional
        Per fit pose and leg, the covariance (camera frame, radians^2) of the leg's direction measurement (with
        ``noise.rods_per_leg`` rods averaged in it), e.g. from the rods' ``cov_u``; default isotropic
        ``noise.rod_direction_rad``.

    Returns
    -------
    dict
        ``{"std": {name: metres}, "covariance": 4x4 nested list (metres^2), "noise": {...}}``.

    Raises
    ------
    ValueError
        If a phase has fewer than two steps, or the measurements do not determine the four combinations.
    """
    noise = noise or MeasurementNoise()
    q_fit = _phase_q(plan, "poses")
    q_rot = _phase_q(plan, "rotation")
    q_tra = _phase_q(plan, "translation")
    if len(q_fit) < 2 or len(q_rot) < 2 or len(q_tra) < 2:
        raise ValueError("the bound needs a plan with rotation, translation and pose-set steps")
    F = combined_fisher(nominal, q_fit, q_rot, q_tra, noise, camera_from_base_R, rod_cov)
    cov = _spd_inverse(F)[:4, :4]
    return {
        "std": {k: float(np.sqrt(cov[i, i])) for i, k in enumerate(COMBINATION_NAMES)},
        "covariance": cov.tolist(),
        "noise": {
            "rod_direction_rad": noise.rod_direction_rad,
            "board_rotation_rad": noise.board_rotation_rad,
            "board_translation_m": list(noise.board_translation_m),
        },
    }
