"""Legs observation only (the paper's reference [9], section IV.A.2), in four steps.

1. ``lock-i`` phases: with actuator i locked, each rod of leg i turns about its fixed upper spherical
   joint, so its axis lines (direction and point, from the rod radius) pass through that joint: the
   least-squares intersection gives it; the two joints' midpoint is A_i at the locked encoder value.
   x_B is the direction A1 -> A2 (and A3 -> A4); ``A_i(q_i = 0) = A_i - q_i x_B``.
2. (q02, q03, q04, H) from the scalar products of ``V = (OA2, OA3, OA4)|q=0`` (eq. 9, 10), O = A1(q1 = 0).
3. L from the invariance of |B1 B2| and |B3 B4| over the fit poses (eq. 11), with
   ``B_i = A_i(q_i) + L u_i``.
4. S from |B1 B2| = |B3 B4| = 2S; D from the distance 2D between B1 and B3 (and B2, B4) along y_B.

All seven parameters are identified. Standard deviations propagate (linearly, with numerical
derivatives of steps 2-4) the covariance of the joint centres from step 1 (from the line
residuals) and the noise of the leg directions in the fit poses (estimated from the disagreement
of the two parallel rods of each leg).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..errors import ConvergenceError, IdentifiabilityError
from ..observations import Observations, PhaseArrays
from ..parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters
from ..transforms import unit
from .iterations import IterationCallback, traced
from .result import MethodResult, combos_dict, std_dict

_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def intersect_lines(p: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares point closest to lines ``p_k + s u_k``.

    Parameters
    ----------
    p, u : ndarray, shape (N, 3)

    Returns
    -------
    point : ndarray, shape (3,)
    normal_matrix : ndarray, shape (3, 3)
        ``sum (I - u u^T)``; the point's covariance is ``sigma^2`` times its inverse.
    residuals : ndarray, shape (N, 3)
        Perpendicular offsets of the point from each line.
    """
    u = unit(u)
    M = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
    A = M.sum(axis=0)
    if np.linalg.cond(A) > 1e10:
        raise IdentifiabilityError("the rod lines of a locked leg are parallel: their joint cannot be located")
    P = np.linalg.solve(A, np.einsum("nij,nj->i", M, p))
    res = np.einsum("nij,nj->ni", M, P - p)
    return P, A, res


def _step2(V: np.ndarray, x0: np.ndarray, on_iteration: IterationCallback | None = None) -> np.ndarray:
    """(q02, q03, q04, H) from V (3, 3) rows OA2, OA3, OA4 at zero encoder (eq. 9)."""
    G = V @ V.T
    meas = np.array([G[a, b] for a, b in _PAIRS])

    def model(x: np.ndarray) -> np.ndarray:
        q02, q03, q04, H = x
        Vb = np.array([[q02, 0.0], [q03, 2 * H], [q04, 2 * H]])
        Gb = Vb @ Vb.T
        return np.array([Gb[a, b] for a, b in _PAIRS])

    sol = least_squares(traced(lambda x: model(x) - meas, on_iteration, "step 2"), x0, method="lm", xtol=1e-15,
                        ftol=1e-15, gtol=1e-15)
    if sol.status <= 0:
        raise ConvergenceError(f"legs step 2 (eq. 9) did not converge: {sol.message}")
    return sol.x


class _LegsPipeline:
    """Steps 2-4 as a function of the joint points (step 1 output) and the fit-pose leg directions."""

    def __init__(self, q_lock: np.ndarray, q_fit: np.ndarray, rod_p: np.ndarray, has_leg: np.ndarray,
                 nominal: I4Parameters) -> None:
        self.q_lock = q_lock  # (4,) locked value of each actuator
        self.q_fit = q_fit  # (N, 4)
        self.rod_p = rod_p  # (N, 4, 3) a point on each leg's rods (for the direction sign), NaN if none
        self.has_leg = has_leg  # (N, 4)
        self.nominal = nominal

    def frame(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x_B and A_i(q=0) in the camera frame from the 8 upper joint points (4, 2, 3)."""
        A = P.mean(axis=1)
        nom = self.nominal
        s12 = np.sign(self.q_lock[1] + nom.q02 - self.q_lock[0])
        s34 = np.sign(self.q_lock[3] + nom.q04 - self.q_lock[2] - nom.q03)
        x = unit(unit(s12 * (A[1] - A[0])) + unit(s34 * (A[3] - A[2])))
        A0 = A - self.q_lock[:, None] * x[None, :]
        return x, A0, A

    def run(self, P: np.ndarray, U: np.ndarray, x2_init: np.ndarray | None = None,
            on_iteration: IterationCallback | None = None) -> np.ndarray:
        """Seven parameters (PARAMETER_NAMES order) from joint points P (4,2,3) and leg directions U (N,4,3)."""
        nom = self.nominal
        x, A0, _ = self.frame(P)
        V = A0[1:] - A0[0]
        x2 = _step2(V, np.array([nom.q02, nom.q03, nom.q04, nom.H]) if x2_init is None else x2_init, on_iteration)
        q02, q03, q04, H = x2
        y = unit(V[1] - (V[1] @ x) * x)
        L, S, D = self.steps34(x, y, A0, U, nom.L, on_iteration)
        return np.array([H, q02, q03, q04, S, D, L])

    def steps34(self, x: np.ndarray, y: np.ndarray, A0: np.ndarray, U: np.ndarray, L0: float,
                on_iteration: IterationCallback | None = None):
        Aq = A0[None, :, :] + self.q_fit[:, :, None] * x[None, None, :]  # (N, 4, 3)
        # orient each leg direction from A to B (towards the rod's observed point)
        sgn = np.sign(np.einsum("nij,nij->ni", U, np.where(np.isnan(self.rod_p), 0.0, self.rod_p - Aq)))
        sgn[sgn == 0] = 1.0
        Uo = U * sgn[..., None]
        ok12 = self.has_leg[:, 0] & self.has_leg[:, 1]
        ok34 = self.has_leg[:, 2] & self.has_leg[:, 3]

        def dists(L: float) -> tuple[np.ndarray, np.ndarray]:
            B = Aq + L * Uo
            return np.sum((B[:, 0] - B[:, 1]) ** 2, axis=1), np.sum((B[:, 2] - B[:, 3]) ** 2, axis=1)

        def res(Lv: np.ndarray) -> np.ndarray:
            d12, d34 = dists(Lv[0])
            a, b = d12[ok12], d34[ok34]
            return np.concatenate([np.diff(a), np.diff(b)])  # eq. 11

        if ok12.sum() + ok34.sum() < 3:
            raise IdentifiabilityError("legs step 3 needs both legs of a pair seen in at least 2 fit poses",
                                       parameter="L")
        sol = least_squares(traced(res, on_iteration, "step 3"), [L0], method="lm", xtol=1e-15, ftol=1e-15,
                            gtol=1e-15)
        L = float(sol.x[0])
        B = Aq + L * Uo
        d12 = np.linalg.norm(B[ok12, 0] - B[ok12, 1], axis=1)
        d34 = np.linalg.norm(B[ok34, 2] - B[ok34, 3], axis=1)
        S = float(np.mean(np.concatenate([d12, d34]))) / 2.0
        dy = np.concatenate([((B[:, 2] - B[:, 0]) @ y)[self.has_leg[:, 0] & self.has_leg[:, 2]],
                             ((B[:, 3] - B[:, 1]) @ y)[self.has_leg[:, 1] & self.has_leg[:, 3]]])
        if dy.size == 0:
            raise IdentifiabilityError("legs step 4 needs legs 1 and 3 (or 2 and 4) seen together", parameter="D")
        D = float(np.mean(dy)) / 2.0
        return L, S, D


def _leg_directions(data: PhaseArrays) -> tuple[np.ndarray, np.ndarray, np.ndarray, float | None]:
    """Per pose and leg: mean rod direction (N,4,3), a rod point (N,4,3), a mask (N,4), rod-pair noise."""
    u = data.rod_u.copy()
    has = data.has_rod
    # align the second rod with the first
    dot = np.einsum("nlk,nlk->nl", u[:, :, 0], u[:, :, 1])
    u[:, :, 1] *= np.where(np.isnan(dot), 1.0, np.sign(dot))[..., None]
    both = has[:, :, 0] & has[:, :, 1]
    U = np.where(has[:, :, 0, None], u[:, :, 0], 0.0) + np.where(has[:, :, 1, None], u[:, :, 1], 0.0)
    has_leg = has.any(axis=2)
    U = np.where(has_leg[..., None], U, np.nan)
    U = unit(U)
    pts = np.where(data.has_point[:, :, 0, None], data.rod_p[:, :, 0], data.rod_p[:, :, 1])
    sigma = None
    if both.sum() >= 3:
        d = (u[:, :, 0] - u[:, :, 1])[both]
        sigma = float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)) / 4.0))  # per tangent dof, per rod
    return U, pts, has_leg, sigma


def calibrate_legs(obs: Observations, *, fit_phases: tuple[str, ...] = ("poses",),
                   direction_std_rad: float | None = None,
                   on_iteration: IterationCallback | None = None) -> MethodResult:
    """Identify all seven parameters from leg observations only (four steps).

    Parameters
    ----------
    obs : Observations
        Needs rods with points (the rod radius known) in the ``lock-1`` .. ``lock-4`` phases and
        rod directions in the fit phases.
    fit_phases : tuple of str
        Phases used for steps 3 and 4 (the paper reuses the 20-pose set).
    direction_std_rad : float, optional
        Rod direction noise per tangent axis; estimated from the two rods of each leg when not given.
    on_iteration : callable, optional
        Receives ``{"stage", "iteration", "cost"}`` after each iteration of the fits of steps 2 and 3 (not of the
        uncertainty propagation; :mod:`.iterations`).

    Returns
    -------
    MethodResult
        With ``parameters`` (seven) and ``parameters_std``.
    """
    nom = obs.nominal
    P = np.zeros((4, 2, 3))
    Acc = np.zeros((4, 2, 3, 3))
    q_lock = np.zeros(4)
    ss, dof = 0.0, 0
    n_lines = 0
    for i in range(4):
        d = obs.arrays(f"lock-{i + 1}")
        if len(d) == 0:
            raise IdentifiabilityError(f"the legs method needs the lock-{i + 1} phase (actuator {i + 1} locked)",
                                       parameter=f"A{i + 1}")
        spread = float(np.ptp(d.q[:, i]))
        if spread > 1e-4:
            raise IdentifiabilityError(
                f"in phase lock-{i + 1}, q{i + 1} moves by {spread * 1e3:.3f} mm: the actuator is not locked",
                parameter=f"A{i + 1}")
        q_lock[i] = float(np.mean(d.q[:, i]))
        for j in range(2):
            ok = d.has_rod[:, i, j] & d.has_point[:, i, j]
            if ok.sum() < 2:
                raise IdentifiabilityError(
                    f"phase lock-{i + 1}: rod {j} of leg {i + 1} has {int(ok.sum())} observation(s) with a point; "
                    "at least 2 (5 recommended) are needed to locate its joint (rod radius known)",
                    parameter=f"A{i + 1}")
            Pij, Aij, res = intersect_lines(d.rod_p[ok, i, j], d.rod_u[ok, i, j])
            P[i, j] = Pij
            Acc[i, j] = Aij
            ss += float(np.sum(res ** 2))
            dof += 2 * int(ok.sum()) - 3
            n_lines += int(ok.sum())
    s2_line = ss / max(dof, 1) if dof > 0 else 0.0

    data = obs.arrays(*fit_phases)
    U, pts, has_leg, sigma_pair = _leg_directions(data)
    pipe = _LegsPipeline(q_lock, data.q, pts, has_leg, nom)
    U_filled = np.where(has_leg[..., None], U, 0.0)
    x2 = None
    seven = pipe.run(P, U_filled, on_iteration=on_iteration)
    x2 = [*seven[1:4].tolist(), seven[0]]
    x2 = np.array(x2)

    # ---- uncertainty: linear propagation with numerical derivatives
    def f(Pv: np.ndarray, Uv: np.ndarray) -> np.ndarray:
        return pipe.run(Pv, Uv, x2)

    h = 1e-7
    GP = np.zeros((7, 24))
    for a in range(24):
        dP = np.zeros(24)
        dP[a] = h
        GP[:, a] = (f(P + dP.reshape(4, 2, 3), U_filled) - f(P - dP.reshape(4, 2, 3), U_filled)) / (2 * h)
    covP = np.zeros((24, 24))
    for i in range(4):
        for j in range(2):
            k = (i * 2 + j) * 3
            covP[k:k + 3, k:k + 3] = s2_line * np.linalg.inv(Acc[i, j])
    cov = GP @ covP @ GP.T
    sigma_u = direction_std_rad if direction_std_rad is not None else sigma_pair
    cov_u = np.zeros((7, 7))
    if sigma_u:
        x, A0, _ = pipe.frame(P)
        y = unit((A0[2] - A0[0]) - ((A0[2] - A0[0]) @ x) * x)
        n_rods = data.has_rod.sum(axis=2)
        for kk, ll in zip(*np.nonzero(has_leg), strict=True):
            u = U[kk, ll]
            T = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]  # tangent basis
            for col in range(2):
                Up = U_filled.copy()
                Um = U_filled.copy()
                Up[kk, ll] = unit(u + h * T[:, col])
                Um[kk, ll] = unit(u - h * T[:, col])
                g = np.zeros(7)
                Lp = pipe.steps34(x, y, A0, Up, seven[6])
                Lm = pipe.steps34(x, y, A0, Um, seven[6])
                g[[6, 4, 5]] = (np.array(Lp) - np.array(Lm)) / (2 * h)
                cov_u += np.outer(g, g) * sigma_u ** 2 / n_rods[kk, ll]
    cov += cov_u
    params = I4Parameters.from_mapping({**dict(zip(PARAMETER_NAMES, seven, strict=True)),
                                         "T_per_rad": nom.T_per_rad})
    # combinations and their covariance (linear maps of the seven)
    M = np.array([
        [0, 0, 0, 0, 0, 0, 1],  # L
        [1, 0, 0, 0, 0, -1, 0],  # H - D
        [0, -0.5, 0, 0, 1, 0, 0],  # S - q02/2
        [0, 0, 0.5, -0.5, 1, 0, 0],  # S - (q04 - q03)/2
    ], dtype=float)
    cov4 = M @ cov @ M.T
    std7 = {k: float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(PARAMETER_NAMES)}
    combos = params.combinations()
    return MethodResult(
        method="legs", combinations=combos_dict(np.array([combos[k] for k in COMBINATION_NAMES])),
        combinations_std=std_dict(cov4), covariance=cov4,
        residual_rms=float(np.sqrt(s2_line)), residual_unit="m (rod line to joint distance)",
        n_observations=n_lines + int(has_leg.sum()), n_poses=len(data) + 20, iterations=1, converged=True,
        parameters={k: float(v) for k, v in zip(PARAMETER_NAMES, seven, strict=True)}, parameters_std=std7,
        std_breakdown={"joint_centres": {k: float(np.sqrt(max((GP @ covP @ GP.T)[i, i], 0)))
                                         for i, k in enumerate(PARAMETER_NAMES)},
                       "leg_directions": {k: float(np.sqrt(max(cov_u[i, i], 0)))
                                          for i, k in enumerate(PARAMETER_NAMES)}},
        diagnostics={"rod_direction_noise_rad": sigma_u, "line_residual_rms_mm": float(np.sqrt(s2_line)) * 1e3,
                     "joint_centres_camera": P.mean(axis=1).tolist(), "locked_q": q_lock.tolist()},
        residuals=None)
