"""Base-frame axes in the camera frame from board observations (the paper's section III.B.1).

* z_B: axis of the board's relative rotations in the ``rotation`` phase (at least two rotations);
  its sign makes positive T turn the end-effector positively.
* x_B: direction of the board's displacement in the ``translation`` phase, when all four actuators
  move equally (the displacement along x_B equals the common encoder increment).
* y_B completes a right-handed frame; x_B is re-orthogonalised against z_B.

The estimate comes with the covariance of its rotation (a small rotation vector applied on the
left, in the camera frame), derived from the fit residuals (full 3x3 residual covariances, so that
the anisotropic noise of PnP poses is accounted for), so that the methods built on it can
propagate it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from calib.errors import IdentifiabilityError
from calib.formats.observations import Observations, PhaseArrays
from calib.numerics.transforms import (
    cross,
    matrix_to_rotvec,
    orthonormalize,
    rotvec_to_matrix,
    so3_left_jacobian,
    so3_left_jacobian_inverse,
    unit,
)

Array = np.ndarray


@dataclass(frozen=True)
class BaseFrameResult:
    """Base frame axes in the camera frame.

    Attributes
    ----------
    camera_from_base_R : ndarray, shape (3, 3)
        Columns are x_B, y_B, z_B expressed in the camera frame.
    cov_rotvec : ndarray, shape (3, 3)
        Covariance (rad^2) of the small rotation ``w`` such that the true rotation is
        ``exp(w) camera_from_base_R`` (camera frame, left perturbation).
    """

    camera_from_base_R: Array
    cov_rotvec: Array
    z_axis: Array
    x_axis_raw: Array
    z_std_rad: float
    x_std_rad: float
    orthogonality_error_deg: float
    rotation_residual_rms_rad: float
    translation_residual_rms_m: float
    #: board displacement measured by vision per encoder metre on the translation phase (the board's print scale
    #: and the camera's, which no camera calibration can tell; 1 for a consistent set-up), and its std
    translation_scale: float
    n_rotation: int
    n_translation: int
    rotation_angles_rad: Array = field(repr=False)
    #: the rotation-axis fit's final state, to re-estimate from slightly moved board poses (``start``)
    axis_state: dict | None = field(default=None, repr=False, compare=False)
    translation_scale_std: float = 0.0

    def summary(self) -> dict:
        return {
            "camera_from_base_R": self.camera_from_base_R.tolist(),
            "z_std_deg": float(np.rad2deg(self.z_std_rad)),
            "x_std_deg": float(np.rad2deg(self.x_std_rad)),
            "orthogonality_error_deg": self.orthogonality_error_deg,
            "rotation_residual_rms_deg": float(np.rad2deg(self.rotation_residual_rms_rad)),
            "translation_residual_rms_mm": self.translation_residual_rms_m * 1e3,
            "translation_scale": self.translation_scale,
            "translation_scale_std": self.translation_scale_std,
            "n_rotation": self.n_rotation,
            "n_translation": self.n_translation,
        }


def fit_rotation_axis(
    R: Array, T: Array | None = None, start: dict | None = None, state: dict | None = None
) -> tuple[Array, Array, Array, Array, float]:
    """Fit a fixed rotation axis to board orientations ``R_k = Rot(z, theta_k) R_ref``.

    Parameters
    ----------
    R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations, N >= 2, with different rotation angles.
    T : ndarray, shape (N,), optional
        The commanded/encoder T of each frame: fixes the sign of z (theta grows with T).

    Returns
    -------
    z : ndarray, shape (3,)
        Unit axis in the camera frame.
    cov_z : ndarray, shape (3, 3)
        Its covariance (rank 2, tangent to the unit sphere).
    theta : ndarray, shape (N,)
        Rotation angles (relative to ``R_ref``).
    residuals : ndarray, shape (N, 3)
        Rotation-vector residuals (rad).
    scale_ok : float
        Angle spread (rad), to detect degenerate sweeps.

    Other Parameters
    ----------------
    state : dict, optional
        Filled with the fit's final state (parametrisation, solution, weights).
    start : dict, optional
        A ``state`` of a fit to nearly the same rotations (the same frames, slightly moved): the
        weighted fit starts from it with its weights, skipping the initial estimate and the
        unweighted fit (first-order propagation through the estimator, as in
        :mod:`calib.identify.combined`).
    """
    R = np.asarray(R, dtype=np.float64)
    n = R.shape[0]
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R must have shape (N, 3, 3), got {R.shape}")
    if n < 2:
        raise IdentifiabilityError("the rotation phase needs at least two board poses to find z_B", parameter="z_B")
    if start is not None:
        return _refit_rotation_axis(R, T, start, state)
    order = np.argsort(np.asarray(T)) if T is not None else np.arange(n)
    # increments between neighbouring frames are small: no wrap-around at +-180 deg
    inc = matrix_to_rotvec(R[order[1:]] @ np.transpose(R[order[:-1]], (0, 2, 1)))
    z0 = np.linalg.eigh(inc.T @ inc)[1][:, -1]
    steps = inc @ z0
    if steps.sum() < 0:
        z0, steps = -z0, -steps
    th0 = np.empty(n)
    th0[order] = np.concatenate([[0.0], np.cumsum(steps)])
    th0 -= th0[0]
    spread = float(th0.max() - th0.min())
    if spread < np.deg2rad(2.0):
        raise IdentifiabilityError(
            f"the rotation phase turns the board by only {np.rad2deg(spread):.2f} deg: z_B is not excited "
            "(need rotations of at least a few degrees)",
            parameter="z_B",
        )
    # local parametrisation of z around z0
    e1 = unit(cross(z0, [1.0, 0.0, 0.0] if abs(z0[0]) < 0.9 else [0.0, 1.0, 0.0]))
    e2 = cross(z0, e1)
    axes = (z0, e1, e2)

    def zfun(a: Array) -> Array:
        return _axis(axes, a)

    def resid(x: Array, W: Array | None = None) -> Array:
        return _axis_residuals(R, axes, x, W)

    x0 = np.concatenate([[0.0, 0.0], [0.0, 0.0, 0.0], th0])

    def jac(x: Array, W: Array | None = None) -> Array:
        return _axis_jacobian(R, axes, x, W)

    sol = least_squares(resid, x0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    W = None
    res = sol.fun.reshape(n, 3)
    p = 5 + n
    dof = 2 * n - 5  # the component along the axis is absorbed by theta_k
    zc = zfun(sol.x[:2])
    Pt = np.eye(3) - np.outer(zc, zc)
    Sigma = Pt @ (res.T @ res) @ Pt / max(dof / 2.0, 0.5)
    w, V = np.linalg.eigh(Sigma)
    if dof >= 2 and w[-2] > 1e-30:
        # whiten the two tangent components; the axial one is zero at the optimum (weight irrelevant)
        wt = np.where(np.abs(V.T @ zc) > 0.9, np.sqrt(w[-2] * w[-1]), w)
        W = (V / np.sqrt(wt)).T
        sol = least_squares(
            lambda x: resid(x, W),
            sol.x,
            jac=lambda x: jac(x, W),
            method="lm",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=2000,
        )
        J = sol.jac
        s2 = float(sol.fun @ sol.fun / dof)
        if state is not None:
            state["J"] = J
        cov_x = np.linalg.pinv(J.T @ J) * s2
    else:  # noise-free data
        cov_x = np.zeros((p, p))
    if state is not None:
        state.update(axes=axes, x=sol.x, W=W, spread=spread, cov_x=cov_x)
    return _axis_result(axes, sol.x, cov_x, T, res, spread)


def _axis(axes: tuple[Array, Array, Array], a: Array) -> Array:
    z0, e1, e2 = axes
    return unit(z0 + a[0] * e1 + a[1] * e2)


def _axis_residuals(R: Array, axes: tuple[Array, Array, Array], x: Array, W: Array | None) -> Array:
    """Rotation-vector residuals (N*3,) of ``R_k = Rot(z, theta_k) R_ref`` for the unknowns x (fit_rotation_axis)."""
    z = _axis(axes, x[:2])
    Rref = rotvec_to_matrix(x[2:5]) @ R[0]
    th = x[5:]
    Q = rotvec_to_matrix(z[None, :] * th[:, None])
    e = matrix_to_rotvec(Q @ Rref @ np.transpose(R, (0, 2, 1)))
    if W is not None:
        e = e @ W.T
    return e.ravel()


def _axis_jacobian(R: Array, axes: tuple[Array, Array, Array], x: Array, W: Array | None) -> Array:
    """Derivatives (N*3, 5+N) of :func:`_axis_residuals` with respect to x (SO(3) left Jacobians, no differences).

    With ``E_k = exp(z theta_k) exp(rho) R_0 R_k^T`` and ``e_k = log E_k``, a left perturbation ``d`` of ``E_k``
    moves ``e_k`` by ``J_l^-1(e_k) d``; theta_k perturbs by ``z dtheta``, rho by ``exp(z theta_k) J_l(rho) drho``
    and the axis by ``J_l(z theta_k) theta_k dz``.
    """
    z0, e1, e2 = axes
    v = z0 + x[0] * e1 + x[1] * e2
    nv = float(np.linalg.norm(v))
    z = v / nv
    dz = (np.eye(3) - np.outer(z, z)) @ np.column_stack([e1, e2]) / nv  # (3, 2)
    rho, th = x[2:5], x[5:]
    n = len(th)
    w = z[None, :] * th[:, None]
    Q = rotvec_to_matrix(w)
    e = matrix_to_rotvec(Q @ rotvec_to_matrix(rho) @ R[0] @ np.transpose(R, (0, 2, 1)))
    Ji = so3_left_jacobian_inverse(e)  # (n, 3, 3)
    J = np.zeros((n, 3, 5 + n))
    J[:, :, :2] = Ji @ so3_left_jacobian(w) @ dz * th[:, None, None]
    J[:, :, 2:5] = Ji @ Q @ so3_left_jacobian(rho)
    J[np.arange(n), :, 5 + np.arange(n)] = Ji @ z
    if W is not None:
        J = np.einsum("ij,njp->nip", W, J)
    return J.reshape(3 * n, 5 + n)


def _axis_result(
    axes: tuple[Array, Array, Array], x: Array, cov_x: Array, T: Array | None, res: Array, spread: float
) -> tuple[Array, Array, Array, Array, float]:
    z = _axis(axes, x[:2])
    Jz = np.column_stack([axes[1], axes[2]])
    cov_z = Jz @ cov_x[:2, :2] @ Jz.T
    theta = x[5:]
    if T is not None and np.corrcoef(theta, np.asarray(T))[0, 1] < 0:
        z = -z
        theta = -theta
    return z, cov_z, theta, res, spread


def _refit_rotation_axis(
    R: Array, T: Array | None, start: dict, state: dict | None
) -> tuple[Array, Array, Array, Array, float]:
    """The weighted fit of :func:`fit_rotation_axis` from a previous fit's state (slightly moved data)."""
    axes, W = start["axes"], start["W"]
    x_start = np.asarray(start["x"], dtype=np.float64).copy()
    if x_start.size != 5 + R.shape[0]:
        raise ValueError(f"the start state has {x_start.size - 5} rotations, the data {R.shape[0]}")
    J = start.get("J")
    if J is not None and J.shape == (3 * R.shape[0], x_start.size):
        # Gauss-Newton steps with the converged fit's Jacobian: the data moved by far less than their noise,
        # so the first step is already the first-order (linear propagation) answer; the second polishes it
        x = x_start
        for _ in range(2):
            x = x - np.linalg.lstsq(J, _axis_residuals(R, axes, x, W), rcond=1e-8)[0]  # the gauge (Rref and
            # every theta turned together about z) is a null direction
    else:
        x = least_squares(
            lambda v: _axis_residuals(R, axes, v, W),
            x_start,
            jac=lambda v: _axis_jacobian(R, axes, v, W),
            method="lm",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=2000,
        ).x
    res = _axis_residuals(R, axes, x, None).reshape(-1, 3)
    if state is not None:
        state.update({**start, "x": x})
    # the covariance is the previous fit's: the data moved by far less than their noise
    return _axis_result(axes, x, start["cov_x"], T, res, start["spread"])


def fit_translation_direction(t: Array, s: Array) -> tuple[Array, Array, Array, float]:
    """Direction of a straight board displacement ``t_k = t_0 + s_k d``.

    Parameters
    ----------
    t : ndarray, shape (N, 3)
        Board positions in the camera frame, metres.
    s : ndarray, shape (N,)
        Known displacement along the line (the common encoder increment), metres.

    Returns
    -------
    x : ndarray, shape (3,)
        Unit direction.
    cov_x : ndarray, shape (3, 3)
        Its covariance (tangent).
    residuals : ndarray, shape (N, 3)
    scale : float
        ``|d|``: the measured displacement per encoder metre (1 for a consistent set-up; see
        :func:`translation_scale_std` for its uncertainty).
    """
    t = np.asarray(t, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    n = t.shape[0]
    if t.shape != (n, 3) or s.shape != (n,):
        raise ValueError(f"t must be (N, 3) and s (N,), got {t.shape} and {s.shape}")
    if n < 2:
        raise IdentifiabilityError("the translation phase needs at least two board poses to find x_B", parameter="x_B")
    sc = s - s.mean()
    Sss = float(sc @ sc)
    if Sss < (1e-3) ** 2:
        raise IdentifiabilityError(
            "the translation phase does not move the actuators: x_B is not excited", parameter="x_B"
        )
    d = (sc @ (t - t.mean(axis=0))) / Sss
    t0 = t.mean(axis=0) - d * s.mean()
    res = t - t0 - s[:, None] * d[None, :]
    cov_d = _displacement_covariance(res, s)
    nd = float(np.linalg.norm(d))
    x = d / nd
    P = np.eye(3) - np.outer(x, x)
    cov_x = P @ cov_d @ P / nd**2
    return x, cov_x, res, nd


def translation_scale_std(residuals: Array, s: Array, x: Array) -> float:
    """Standard deviation of :func:`fit_translation_direction`'s ``scale`` (``|d|`` along ``x``), dimensionless.

    Parameters
    ----------
    residuals : ndarray, shape (N, 3)
        The fit's residuals, metres.
    s : ndarray, shape (N,)
        The encoder increments, metres.
    x : ndarray, shape (3,)
        The fitted unit direction.

    Returns
    -------
    float
        The std of the scale (dimensionless).
    """
    return float(np.sqrt(max(float(x @ _displacement_covariance(residuals, s) @ x), 0.0)))


def _displacement_covariance(residuals: Array, s: Array) -> Array:
    """Covariance (3, 3) of the displacement per encoder metre ``d`` of :func:`fit_translation_direction`, from its
    residuals (N, 3) (their scatter over N - 2 dof) and the encoder increments s (N,)."""
    sc = np.asarray(s, dtype=np.float64) - float(np.mean(s))
    Sigma = residuals.T @ residuals / max(residuals.shape[0] - 2, 1)
    return Sigma / float(sc @ sc)


def frame_from_axes(z: Array, x: Array) -> Array:
    """Right-handed rotation with columns x_B, y_B, z_B (camera frame): z kept, x re-orthogonalised.

    Parameters
    ----------
    z : ndarray, shape (3,)
        The base frame's z axis in the camera frame (any norm).
    x : ndarray, shape (3,)
        Its x axis, approximately orthogonal to ``z`` (any norm).

    Returns
    -------
    ndarray, shape (3, 3)
        ``camera_from_base`` rotation (dimensionless).
    """
    z = unit(z)
    y = unit(cross(z, x))
    xo = cross(y, z)
    return np.column_stack([xo, y, z])


def estimate_base_frame(
    rotation: PhaseArrays, translation: PhaseArrays, start: BaseFrameResult | None = None
) -> BaseFrameResult:
    """Base frame axes in the camera frame from the rotation and translation phases.

    Parameters
    ----------
    rotation : PhaseArrays
        The rotation phase: encoder values (metres) and ``camera_from_board`` poses (radians, metres).
    translation : PhaseArrays
        The translation phase, likewise.
    start : BaseFrameResult, optional
        An estimate from the same frames with slightly different board poses (a propagation step); the rotation
        axis's weighted fit then starts from it with its weights and covariance.

    Returns
    -------
    BaseFrameResult
        ``camera_from_base`` rotation, its 3x3 rotation-vector covariance (radians^2), the axes' stds (radians),
        residuals and the translation phase's scale (dimensionless).

    Raises
    ------
    IdentifiabilityError
        Too few board poses, or a phase that does not move.
    """
    rot = rotation.subset(rotation.has_board)
    tra = translation.subset(translation.has_board)
    if len(rot) < 2:
        raise IdentifiabilityError(
            f"the rotation phase has {len(rot)} frame(s) with a board pose; at least 2 are needed for z_B",
            parameter="z_B",
        )
    if len(tra) < 2:
        raise IdentifiabilityError(
            f"the translation phase has {len(tra)} frame(s) with a board pose; at least 2 are needed for x_B",
            parameter="x_B",
        )
    Tq = (rot.q[:, 0] + rot.q[:, 1] - rot.q[:, 2] - rot.q[:, 3]) / 4.0
    state: dict = {}
    z, cov_z, theta, rres, _ = fit_rotation_axis(
        rot.board_R, Tq, start=start.axis_state if start else None, state=state
    )
    s = tra.q.mean(axis=1)
    x, cov_x, tres, scale = fit_translation_direction(tra.board_t, s)
    R = frame_from_axes(z, x)

    # covariance of the frame rotation from cov_z and cov_x (numerical Jacobians)
    def jac(fun, v: Array) -> Array:
        cols = []
        for k in range(3):
            h = np.zeros(3)
            h[k] = 1e-7
            cols.append((matrix_to_rotvec(fun(v + h) @ R.T) - matrix_to_rotvec(fun(v - h) @ R.T)) / 2e-7)
        return np.column_stack(cols)

    Jz = jac(lambda v: frame_from_axes(v, x), z)
    Jx = jac(lambda v: frame_from_axes(z, v), x)
    cov = Jz @ cov_z @ Jz.T + Jx @ cov_x @ Jx.T
    ortho = float(np.rad2deg(np.arcsin(np.clip(abs(z @ x), 0, 1))))
    return BaseFrameResult(
        camera_from_base_R=orthonormalize(R),
        cov_rotvec=cov,
        z_axis=z,
        x_axis_raw=x,
        z_std_rad=float(np.sqrt(max(np.trace(cov_z), 0.0) / 2)),
        x_std_rad=float(np.sqrt(max(np.trace(cov_x), 0.0) / 2)),
        orthogonality_error_deg=ortho,
        rotation_residual_rms_rad=float(np.sqrt(np.mean(np.sum(rres**2, axis=1)))),
        translation_residual_rms_m=float(np.sqrt(np.mean(np.sum(tres**2, axis=1)))),
        translation_scale=scale,
        n_rotation=len(rot),
        n_translation=len(tra),
        rotation_angles_rad=theta,
        axis_state=state,
        translation_scale_std=translation_scale_std(tres, s, x),
    )


def base_frame_from_observations(obs: Observations) -> BaseFrameResult:
    """:func:`estimate_base_frame` from the ``rotation`` and ``translation`` phases of ``obs``.

    Parameters
    ----------
    obs : Observations
        The observations.

    Returns
    -------
    BaseFrameResult
        The base frame in the camera frame.

    Raises
    ------
    IdentifiabilityError
        Too few board poses, or a phase that does not move.
    """
    return estimate_base_frame(obs.arrays("rotation"), obs.arrays("translation"))


def rotation_axis_point(R: Array, t: Array) -> Array:
    """A point of the board frame that stays fixed while the board turns about a fixed axis.

    Solves ``R_k p + t_k = c`` in the least-squares sense (minimum-norm along the axis).

    Parameters
    ----------
    R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations (dimensionless).
    t : ndarray, shape (N, 3)
        ``camera_from_board`` translations, metres.

    Returns
    -------
    ndarray, shape (3,)
        The point in board coordinates (metres).
    """
    n = R.shape[0]
    A = np.zeros((3 * n, 6))
    b = np.zeros(3 * n)
    for k in range(n):
        A[3 * k : 3 * k + 3, :3] = R[k]
        A[3 * k : 3 * k + 3, 3:] = -np.eye(3)
        b[3 * k : 3 * k + 3] = -t[k]
    sol = np.linalg.lstsq(A, b, rcond=1e-10)[0]
    return sol[:3]
