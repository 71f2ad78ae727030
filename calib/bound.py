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

from .kinematics import pose_from_joints_reduced
from .parameters import COMBINATION_NAMES, I4Parameters
from .plan import Plan
from .transforms import matrix_to_rotvec, rotvec_to_matrix, tangent_basis, unit

_SX = np.array([1.0, -1.0, 1.0, -1.0])


@dataclass(frozen=True)
class MeasurementNoise:
    """Noise of the combined method's inputs (standard deviations, per axis)."""

    rod_direction_rad: float = 5e-4
    board_rotation_rad: float = 3e-4
    board_translation_m: tuple[float, float, float] = (1e-4, 1e-4, 3e-4)
    rods_per_leg: int = 2


def leg_directions_reduced(combos: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Unit leg directions in the base frame from the four combinations, shape (N, 4, 3)."""
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
    q_fit, q_rot, q_tra : ndarray, shape (N, 4)
        Encoder values of the fit poses, the rotation phase and the translation phase (metres).
    rod_cov : ndarray, shape (N_fit, 4, 3, 3), optional
        Per-leg direction covariance (camera frame) of one rod; default isotropic.
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

    ``rod_cov`` (N_fit, 4, 3, 3), optional: per fit pose and leg, the covariance (camera frame) of the
    leg's direction measurement (with ``noise.rods_per_leg`` rods averaged in it), e.g. from the
    rods' measured ``cov_u``; default isotropic ``noise.rod_direction_rad``.

    Returns
    -------
    dict
        ``{"std": {name: metres}, "covariance": 4x4, "noise": {...}}``.
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


def ml_combined(obs, noise: MeasurementNoise, *, start=None, base_frame=None) -> np.ndarray:
    """Maximum-likelihood estimate of the four combinations under the bound's measurement model.

    Fits every unknown of :func:`combined_fisher` jointly to all the rods of the fit poses and the
    board poses of the rotation and translation phases, with the noise known. At small noise it is
    efficient: its spread is the bound (tests compare them). ``start`` is a MethodResult of the
    combined method used to initialise (computed when not given); ``base_frame`` the
    :class:`calib.baseframe.BaseFrameResult` of ``obs`` it was computed with (estimated when not given).

    Returns
    -------
    ndarray, shape (4,)
    """
    from scipy.optimize import least_squares

    from .baseframe import base_frame_from_observations
    from .methods.combined import calibrate_combined

    bf = base_frame or base_frame_from_observations(obs)
    start = start or calibrate_combined(obs, base_frame=bf, weighting="gls")
    fit = obs.arrays("poses")
    rot = obs.arrays("rotation")
    rot = rot.subset(rot.has_board)
    tra = obs.arrays("translation")
    tra = tra.subset(tra.has_board)
    k_idx, l_idx, r_idx = np.nonzero(fit.has_rod)
    u_meas = fit.rod_u[k_idx, l_idx, r_idx]
    R_cb0 = bf.camera_from_base_R
    n_r = len(rot)
    th0 = bf.rotation_angles_rad
    Rref0 = rotvec_to_matrix(-bf.z_axis * th0[0]) @ rot.board_R[0]
    s = tra.q.mean(axis=1)
    sig_t = np.asarray(noise.board_translation_m, dtype=np.float64)

    def resid(x: np.ndarray) -> np.ndarray:
        xi, w, rho, th, t0 = x[:4], x[4:7], x[7:10], x[10 : 10 + n_r], x[10 + n_r :]
        R = rotvec_to_matrix(w) @ R_cb0
        u = (leg_directions_reduced(xi, fit.q) @ R.T)[k_idx, l_idx]
        sgn = np.sign(np.sum(u * u_meas, axis=1))[:, None]
        e = u_meas - sgn * u
        e_rods = (e - np.sum(e * u, axis=1, keepdims=True) * u) / noise.rod_direction_rad
        z = R[:, 2]
        Rk = rotvec_to_matrix(z[None, :] * th[:, None]) @ rotvec_to_matrix(rho) @ Rref0
        e_rot = matrix_to_rotvec(rot.board_R @ np.transpose(Rk, (0, 2, 1))) / noise.board_rotation_rad
        e_tra = (tra.board_t - (t0[None, :] + s[:, None] * R[:, 0][None, :])) / sig_t
        return np.concatenate([e_rods.ravel(), e_rot.ravel(), e_tra.ravel()])

    # Forward differences (SciPy's own step, sqrt(eps) max(1, |x|)), one column per evaluation except the angles:
    # each rotation-phase angle moves only its own frame's three rows, so all of them are stepped in one
    # evaluation (the same columns, 4x fewer evaluations of ``resid``).
    n_rods = 2 * k_idx.size
    rot_rows = n_rods + 3 * np.arange(n_r)[:, None] + np.arange(3)[None, :]  # (n_r, 3)

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = resid(x)
        h = np.sqrt(np.finfo(np.float64).eps) * np.maximum(1.0, np.abs(x))
        J = np.zeros((f0.size, x.size))
        for j in (*range(10), *range(10 + n_r, x.size)):
            xj = x.copy()
            xj[j] += h[j]
            J[:, j] = (resid(xj) - f0) / (xj[j] - x[j])
        xt = x.copy()
        xt[10 : 10 + n_r] += h[10 : 10 + n_r]
        dth = xt[10 : 10 + n_r] - x[10 : 10 + n_r]
        d = resid(xt) - f0
        J[rot_rows, (10 + np.arange(n_r))[:, None]] = d[rot_rows] / dth[:, None]
        return J

    w0 = np.zeros(3)  # the camera rotation starts at the base-frame estimate
    t00 = (tra.board_t - s[:, None] * R_cb0[:, 0][None, :]).mean(axis=0)
    x0 = np.concatenate([start.vector(), w0, np.zeros(3), th0, t00])
    # tolerances 1e-10: the estimate moves by < 0.01 nm beyond them (micrometres of spread at the smallest noise)
    sol = least_squares(resid, x0, jac=jac, method="lm", xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=2000)
    return sol.x[:4]
