"""Information-matrix helpers shared by the geometric (:mod:`.predict`) and the image-level
(:mod:`.predict_images`) predictions: inverting an information matrix, and the end-effector method's model and its
sensitivity to the board poses."""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.design.scene import Scene
from calib.errors import IdentifiabilityError
from calib.model.kinematics import dkm
from calib.model.parameters import COMBINATION_NAMES, I4Parameters
from calib.numerics.transforms import rotvec_to_matrix

__all__ = ["board_pose_sensitivity", "end_effector_problem", "invert_information"]


def invert_information(F: np.ndarray, what: str) -> np.ndarray:
    """The covariance of an information matrix ``F`` (k, k), inverted after scaling to unit diagonal.

    Parameters
    ----------
    F : ndarray, shape (k, k)
        Fisher information, in the inverse squared units of the unknowns (1/m^2, 1/rad^2).
    what : str
        The method, named in the error.

    Returns
    -------
    ndarray, shape (k, k)
        The covariance of the unknowns (m^2, rad^2, ...).

    Raises
    ------
    IdentifiabilityError
        ``F`` is singular to 1e-12 relative (the plan does not determine the four combinations; ``what`` names the
        method).
    """
    d = np.sqrt(np.maximum(np.diag(F), 1e-300))
    Fs = F / np.outer(d, d)
    w, V = np.linalg.eigh(0.5 * (Fs + Fs.T))
    if w[0] <= 1e-12 * w[-1]:
        raise IdentifiabilityError(f"{what}: the plan does not determine the four combinations")
    return (V / w) @ V.T / np.outer(d, d)


def board_pose_sensitivity(model: Any, x0: np.ndarray, R: np.ndarray, t: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """The end-effector residuals' sensitivity to each board pose (N, 6, 6): rotation (left rotation vector, rad),
    then position (m), by central differences of step ``h``.

    Parameters
    ----------
    model : Any
        The end-effector method's residual model (``model.residuals(x, R, t)``, whitened, dimensionless).
    x0 : ndarray, shape (P,)
        The unknowns the residuals are taken at (metres, radians).
    R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations of the fit poses.
    t : ndarray, shape (N, 3)
        ``camera_from_board`` translations, metres.
    h : float, optional
        Difference step (radians for the rotation, metres for the position).

    Returns
    -------
    ndarray, shape (N, 6, 6)
        Per pose, d(its 6 residuals) / d(board rotation (rad), board position (m)).
    """
    G = np.zeros((len(R), 6, 6))
    for a in range(6):
        d = np.zeros(3)
        d[a % 3] = h
        if a < 3:
            rp = model.residuals(x0, rotvec_to_matrix(d) @ R, t)
            rm = model.residuals(x0, rotvec_to_matrix(-d) @ R, t)
        else:
            rp = model.residuals(x0, R, t + d)
            rm = model.residuals(x0, R, t - d)
        G[:, :, a] = (rp - rm) / (2 * h)
    return G


def end_effector_problem(nominal: I4Parameters, q_fit: np.ndarray, scene: Scene):
    """The end-effector method's residual model at the nominal geometry for fit poses ``q_fit`` (N, 4), m, seen by
    ``scene``: ``(model, x0, R, t)``, the model, its unknowns at nominal (the four combinations first), and the
    board poses in the camera (N, 3, 3), (N, 3), m.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is taken at (metres).
    q_fit : ndarray, shape (N, 4)
        Encoder values of the fit poses, metres.
    scene : Scene
        The camera's and the board's mounting.

    Returns
    -------
    model : end-effector residual model
        The method's model at these poses.
    x0 : ndarray, shape (16,)
        Its unknowns at nominal, the four combinations (metres) first, then the mounting (metres, radians).
    R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations.
    t : ndarray, shape (N, 3)
        ``camera_from_board`` translations, metres.
    """
    from calib.identify.end_effector import EndEffectorModel

    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    pose = dkm(nominal, q_fit)
    cbs = scene.camera_from_board(nominal, pose)
    R = np.stack([c.R for c in cbs])
    t = np.stack([c.t for c in cbs])
    bc = scene.camera_from_base.inverse()
    eb = scene.ee_from_board
    model = EndEffectorModel(
        R, t, q_fit, nominal.T_per_rad, bc.R, bc.t[0], eb.R, eb.t[2], pose[:, 3] / nominal.T_per_rad
    )
    combos = [nominal.combinations()[k] for k in COMBINATION_NAMES]
    x0 = np.array(
        [
            *combos,
            -nominal.S,
            -nominal.S - nominal.q03,
            0,
            0,
            0,
            bc.t[1] - nominal.H,
            bc.t[2],
            0,
            0,
            eb.t[0],
            eb.t[1],
            0,
        ]
    )
    return model, x0, R, t
