"""The maximum-likelihood estimator of the combined method's four parameters under :mod:`calib.identify.bound`'s
measurement
model: the reference the bound is checked against (an efficient estimator at small noise), for the tests only."""

from __future__ import annotations

import numpy as np

from calib.identify.bound import MeasurementNoise, leg_directions_reduced
from calib.numerics.transforms import matrix_to_rotvec, rotvec_to_matrix


def ml_combined(obs, noise: MeasurementNoise, *, start=None, base_frame=None) -> np.ndarray:
    """Maximum-likelihood estimate of the four combinations under the bound's measurement model.

    Fits every unknown of :func:`calib.identify.bound.combined_fisher` jointly to all the rods of the fit poses and the
    board poses of the rotation and translation phases, with the noise known. At small noise it is
    efficient: its spread is the bound (tests compare them). ``start`` is a MethodResult of the
    combined method used to initialise (computed when not given); ``base_frame`` the
    :class:`calib.identify.baseframe.BaseFrameResult` of ``obs`` it was computed with (estimated when not given).

    Returns
    -------
    ndarray, shape (4,)
    """
    from scipy.optimize import least_squares

    from calib.identify.baseframe import base_frame_from_observations
    from calib.identify.combined import calibrate_combined

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
