"""The camera's coarse placement (``camera_from_base``) from the board poses and the encoders (hand-eye)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from calib.model.kinematics import dkm
from calib.numerics.transforms import Rigid, cross, matrix_to_rotvec, rot_z, rotvec_to_matrix


# ---------------------------------------------------------------------------------------------
def fit_placement(
    q: np.ndarray, board_R: np.ndarray, board_t: np.ndarray, nominal, board_height_m: float = 0.0
) -> tuple[Rigid, Rigid, float]:
    """Coarse ``camera_from_base`` and ``ee_from_board`` from board poses and the nominal model.

    Solves ``camera_from_base * base_from_ee(dkm(nominal, q_k)) * ee_from_board = camera_from_board_k``
    in the least-squares sense (rotation residuals weighted as 0.1 m/rad). All end-effector rotations
    are about z_B, so the height of the board's origin above E (along z_E) and the camera's height
    trade off exactly: the former is fixed to ``board_height_m`` (a ruler measurement is enough).

    Parameters
    ----------
    q : ndarray, shape (N, 4)
        Encoder values (metres), one row per frame.
    board_R : ndarray, shape (N, 3, 3)
        Rotations of the measured ``camera_from_board_k``.
    board_t : ndarray, shape (N, 3)
        Translations of the measured ``camera_from_board_k`` (metres).
    nominal : I4Parameters
        The nominal model (metres, radians).
    board_height_m : float
        Height of the board's origin above E along z_E (metres), held fixed.

    Returns
    -------
    camera_from_base, ee_from_board : Rigid
    rms_m : float
        RMS of the translation residuals, metres.
    """
    poses = dkm(nominal, q)
    th = poses[:, 3] / nominal.T_per_rad
    RB = rot_z(th)
    tB = np.column_stack([poses[:, 0], nominal.H + poses[:, 1], poses[:, 2]])
    # z_B in the camera: axis of the relative rotation between the most rotated pair
    # (the pair whose rotation is closest to 90 deg: its rotation vector is unambiguous)
    k0 = int(np.argmin(th))
    k1 = int(np.argmin(np.abs(np.abs(th - th[k0]) - np.pi / 2)))
    if abs(th[k1] - th[k0]) > 0.05:
        rv = matrix_to_rotvec(board_R[k1] @ board_R[k0].T)
        z = rv / np.linalg.norm(rv) * np.sign(th[k1] - th[k0])
    else:
        z = None
    best = None
    candidates = []
    if z is not None:
        for zz in (z, -z):
            a = cross(zz, [1.0, 0, 0])
            if np.linalg.norm(a) < 0.1:
                a = cross(zz, [0, 1.0, 0])
            a /= np.linalg.norm(a)
            b = cross(zz, a)
            for phi in np.deg2rad(np.arange(0, 360, 5)):
                x = np.cos(phi) * a + np.sin(phi) * b
                candidates.append(np.column_stack([x, cross(zz, x), zz]))
    else:
        candidates = [rotvec_to_matrix(v) for v in np.random.default_rng(0).normal(0, 2.0, (200, 3))]
    n = len(q)
    hz = np.array([0.0, 0.0, board_height_m])
    A = np.zeros((n, 3, 5))
    A[:, :, 2:] = np.eye(3)
    for RC in candidates:
        # o_k - RC tB_k = RC RB_k e + tC
        M = np.einsum("ij,njk->nik", RC, RB)
        A[:, :, :2] = M[:, :, :2]
        rhs = (board_t - tB @ RC.T - M @ hz).reshape(-1)
        Af = A.reshape(3 * n, 5)
        sol, *_ = np.linalg.lstsq(Af, rhs, rcond=None)
        r = float(np.sum((Af @ sol - rhs) ** 2))
        sol = np.array([sol[0], sol[1], board_height_m, *sol[2:]])
        if best is None or r < best[0]:
            RE = np.einsum("nji,njk->ik", M, board_R) / n
            U, _, Vt = np.linalg.svd(RE)
            RE = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
            best = (r, RC, sol[3:], RE, sol[:3])

    assert best is not None  # candidates is never empty
    _, RC, tC, RE, tE = best
    bRT = np.transpose(board_R, (0, 2, 1))

    def resid(p: np.ndarray) -> np.ndarray:
        Rc = rotvec_to_matrix(p[:3])
        Re = rotvec_to_matrix(p[6:9])
        Rp = np.einsum("ij,njk,kl->nil", Rc, RB, Re)
        tp = (RB @ np.array([p[9], p[10], board_height_m]) + tB) @ Rc.T + p[3:6]
        out = np.empty((n, 2, 3))
        out[:, 0] = 0.1 * matrix_to_rotvec(Rp @ bRT)
        out[:, 1] = tp - board_t
        return out.reshape(-1)

    p0 = np.concatenate([matrix_to_rotvec(RC), tC, matrix_to_rotvec(RE), tE[:2]])
    sol = least_squares(resid, p0, method="lm")
    C = Rigid(rotvec_to_matrix(sol.x[:3]), sol.x[3:6])
    E = Rigid(rotvec_to_matrix(sol.x[6:9]), np.array([sol.x[9], sol.x[10], board_height_m]))
    rt = sol.fun.reshape(-1, 2, 3)[:, 1]
    return C, E, float(np.sqrt(np.mean(np.sum(rt**2, axis=1))))
