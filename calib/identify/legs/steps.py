"""Steps 2-4 of the legs method: the legs' geometry from the joint centres and the leg directions, the rods' pair
means, the gating of poses and the steps' covariance.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import block_diag
from scipy.optimize import least_squares

from calib.errors import ConvergenceError, IdentifiabilityError
from calib.formats.observations import Observations, PhaseArrays
from calib.identify.iterations import IterationCallback, traced_jac
from calib.identify.legs.constants import _EQ_LEGS, _PAIRS
from calib.identify.legs.joints import _rod_field
from calib.identify.pose_set_model import PoseSetModel
from calib.model.kinematics import dkm, joint_points
from calib.model.parameters import I4Parameters
from calib.numerics.numdiff import central_jacobian
from calib.numerics.robust import chi2_outliers, robust_chi2_scale
from calib.numerics.transforms import rotvec_to_matrix, tangent_basis, unit


def pose_set_model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    """The legs method's measurement model at encoder values ``q`` (N, 4), m: the joint centres A_i, B_i the rods
    determine, camera frame (m), (N * 8 * 3,), as a function of the seven parameters then 6 nuisance unknowns, the
    camera's placement (rotation vector, rad; position, m).

    Parameters
    ----------
    params : I4Parameters
        The geometry at which the model is linearised (its seven parameters start the vector).
    q : array_like, shape (N, 4)
        Encoder values of the poses, m.

    Returns
    -------
    PoseSetModel
        The prediction (N * 8 * 3,), m, as a function of the 13-vector (seven parameters, m; rotation vector, rad;
        position, m), with 6 nuisance unknowns.
    """
    q = np.asarray(q, dtype=np.float64)

    def f(v: np.ndarray) -> np.ndarray:
        p = I4Parameters.from_vector(v[:7], T_per_rad=params.T_per_rad)
        pose = dkm(p, q)
        A, B = joint_points(p, q, pose)
        R = rotvec_to_matrix(v[7:10])
        return (np.concatenate([A, B], axis=1) @ R.T + v[10:13]).ravel()

    return PoseSetModel(f, params, 6)


def _step2_gram(x: np.ndarray) -> np.ndarray:
    """The Gram entries (6,) (``_PAIRS`` order) of OA2, OA3, OA4 at zero encoder for x = (q02, q03, q04, H), m^2."""
    q02, q03, q04, H = x
    Vb = np.array([[q02, 0.0], [q03, 2 * H], [q04, 2 * H]])
    Gb = Vb @ Vb.T
    return np.array([Gb[a, b] for a, b in _PAIRS])


def _step2_gram_jacobian(x: np.ndarray) -> np.ndarray:
    """Derivatives (6, 4) of :func:`_step2_gram` with respect to (q02, q03, q04, H), m."""
    q02, q03, q04, H = x
    Vb = np.array([[q02, 0.0], [q03, 2 * H], [q04, 2 * H]])
    dV = np.zeros((4, 3, 2))  # d Vb / d (q02, q03, q04, H)
    dV[0, 0, 0] = dV[1, 1, 0] = dV[2, 2, 0] = 1.0
    dV[3, 1, 1] = dV[3, 2, 1] = 2.0
    dG = dV @ Vb.T + Vb @ np.swapaxes(dV, 1, 2)  # (4, 3, 3)
    return np.stack([dG[:, a, b] for a, b in _PAIRS])


def fit_step2(V: np.ndarray, x0: np.ndarray, on_iteration: IterationCallback | None = None) -> np.ndarray:
    """Step 2 (eq. 9): (q02, q03, q04, H) from the Gram matrix of the joint centres' offsets at zero encoder.

    Parameters
    ----------
    V : ndarray, shape (3, 3)
        Rows OA2, OA3, OA4 at zero encoder, camera frame, m.
    x0 : ndarray, shape (4,)
        Starting (q02, q03, q04, H), m.
    on_iteration : IterationCallback or None
        Called at each iteration of the fit (progress), or None.

    Returns
    -------
    ndarray, shape (4,)
        (q02, q03, q04, H), m.

    Raises
    ------
    ConvergenceError
        The least-squares fit did not converge.
    """
    G = V @ V.T
    meas = np.array([G[a, b] for a, b in _PAIRS])
    fun, jac = traced_jac(lambda x: _step2_gram(x) - meas, _step2_gram_jacobian, on_iteration, "step 2")
    sol = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    if sol.status <= 0:
        raise ConvergenceError(f"legs step 2 (eq. 9) did not converge: {sol.message}")
    return sol.x


def _gls_pair(u: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Covariance-weighted mean of two aligned unit directions (2, 3) with covariances (2, 3, 3).

    Returns the mean (3,), its covariance (3, 3) and the pair's disagreement, chi-square with 2 dof.
    """
    m = unit(u[0] + u[1])
    T = tangent_basis(m)  # (3, 2) tangent basis at the mean
    e = u @ T  # (2, 2) tangent coordinates
    Ct = np.einsum("ai,kab,bj->kij", T, C, T) + 1e-18 * np.eye(2)
    Wi = np.linalg.inv(Ct)
    Cm = np.linalg.inv(Wi.sum(axis=0))
    em = Cm @ np.einsum("kij,kj->i", Wi, e)
    de = e[0] - e[1]
    d2 = float(de @ np.linalg.solve(Ct[0] + Ct[1], de))
    return unit(m + T @ em), T @ Cm @ T.T, d2


class LegsModel:
    """The legs method's model: steps 2-4 as a function of the joint points (step 1's output) and the fit poses' leg
    directions, with the residuals of steps 3-4's equations, their Jacobian in (L, S, D) and their covariance from
    the leg directions' (what the fit weighs by and experiment design predicts with).

    Parameters
    ----------
    q_lock : ndarray, shape (4,)
        Each lock phase's locked actuator value, m.
    q_fit : ndarray, shape (N, 4)
        The fit poses' actuator values, m.
    rod_p : ndarray, shape (N, 4, 3)
        A point on each leg's rods, camera frame, m (NaN where none; orients the directions).
    has_leg : ndarray of bool, shape (N, 4)
        The legs seen in each fit pose.
    cov_leg : ndarray, shape (N, 4, 3, 3)
        Each leg direction's covariance, rad^2 (or relative).
    nominal : I4Parameters
        The a priori geometry (the fits' start and the axes' orientation).
    """

    def __init__(
        self,
        q_lock: np.ndarray,
        q_fit: np.ndarray,
        rod_p: np.ndarray,
        has_leg: np.ndarray,
        cov_leg: np.ndarray,
        nominal: I4Parameters,
    ) -> None:
        self.q_lock = q_lock  # (4,) locked value of each actuator
        self.q_fit = q_fit  # (N, 4)
        self.rod_p = rod_p  # (N, 4, 3) a point on each leg's rods (for the direction sign), NaN if none
        self.cov_leg = cov_leg  # (N, 4, 3, 3) covariance (or relative covariance) of each leg direction
        self.nominal = nominal
        self.set_legs(has_leg)
        self.W: np.ndarray | None = None  # (N, 4, 4) whitening of each pose's equations, fixed once fitted

    def set_legs(self, has_leg: np.ndarray) -> None:
        """Legs used per pose (N, 4) and the equations they allow (N, 4).

        Parameters
        ----------
        has_leg : ndarray of bool, shape (N, 4)
            The legs used in each fit pose; resets the whitening.
        """
        self.has_leg = has_leg
        self.mask = np.stack([has_leg[:, a] & has_leg[:, b] for a, b in _EQ_LEGS], axis=1)
        self.W = None

    def frame(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x_B and A_i(q=0) in the camera frame from the 8 upper joint points (4, 2, 3).

        Parameters
        ----------
        P : ndarray, shape (4, 2, 3)
            The upper joint points, two per leg, camera frame, m.

        Returns
        -------
        x : ndarray, shape (3,)
            The actuators' axis x_B, unit, camera frame.
        A0 : ndarray, shape (4, 3)
            Each A_i at zero encoder, camera frame, m.
        A : ndarray, shape (4, 3)
            Each A_i at its lock value, camera frame, m.
        """
        A = P.mean(axis=1)
        nom = self.nominal
        s12 = np.sign(self.q_lock[1] + nom.q02 - self.q_lock[0])
        s34 = np.sign(self.q_lock[3] + nom.q04 - self.q_lock[2] - nom.q03)
        x = unit(unit(s12 * (A[1] - A[0])) + unit(s34 * (A[3] - A[2])))
        A0 = A - self.q_lock[:, None] * x[None, :]
        return x, A0, A

    def run(
        self,
        P: np.ndarray,
        U: np.ndarray,
        x2_init: np.ndarray | None = None,
        on_iteration: IterationCallback | None = None,
        robust: bool = False,
        theta_init: np.ndarray | None = None,
    ) -> np.ndarray:
        """Seven parameters (PARAMETER_NAMES order) from joint points P (4,2,3) and leg directions U (N,4,3).

        ``x2_init`` (q02, q03, q04, H) and ``theta_init`` (L, S, D) start steps 2 and 3-4 (default: nominal); the
        uncertainty's re-runs with slightly moved data start at the estimate.

        Parameters
        ----------
        P : ndarray, shape (4, 2, 3)
            The upper joint points, camera frame, m.
        U : ndarray, shape (N, 4, 3)
            The fit poses' leg directions, unit (NaN where unseen).
        x2_init : ndarray, shape (4,), optional
            Start of step 2, (q02, q03, q04, H), m.
        on_iteration : IterationCallback or None
            Called at each iteration of the fits, or None.
        robust : bool
            Steps 3-4 by :meth:`robust34` (Cauchy loss) instead of :meth:`steps34` (GLS).
        theta_init : ndarray, shape (3,), optional
            Start of steps 3-4, (L, S, D), m.

        Returns
        -------
        ndarray, shape (7,)
            (H, q02, q03, q04, S, D, L), m.

        Raises
        ------
        ConvergenceError
            Step 2 or steps 3-4 did not converge.
        IdentifiabilityError
            Too few poses see the legs steps 3-4 need.
        """
        nom = self.nominal
        x, A0, _ = self.frame(P)
        V = A0[1:] - A0[0]
        x2 = fit_step2(V, np.array([nom.q02, nom.q03, nom.q04, nom.H]) if x2_init is None else x2_init, on_iteration)
        q02, q03, q04, H = x2
        y = self.y_axis(x, A0)
        theta0 = np.array([nom.L, nom.S, nom.D]) if theta_init is None else np.asarray(theta_init, dtype=np.float64)
        L, S, D = self.robust34(x, y, A0, U, theta0) if robust else self.steps34(x, y, A0, U, theta0, on_iteration)
        return np.array([H, q02, q03, q04, S, D, L])

    def geometry(self, P: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For joints ``P`` (4, 2, 3) and leg directions ``U`` (N, 4, 3): A_i(q_i) per fit pose (N, 4, 3), the
        directions oriented from A to B (N, 4, 3) and the base frame's y axis (3,), what the fit's equations take.

        Parameters
        ----------
        P : ndarray, shape (4, 2, 3)
            The upper joint points, camera frame, m.
        U : ndarray, shape (N, 4, 3)
            The fit poses' leg directions, unit.

        Returns
        -------
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, camera frame, m.
        Uo : ndarray, shape (N, 4, 3)
            The leg directions oriented from A to B, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit, camera frame.
        """
        x, A0, _ = self.frame(P)
        Aq, Uo = self.oriented(x, A0, U)
        return Aq, Uo, self.y_axis(x, A0)

    @staticmethod
    def y_axis(x: np.ndarray, A0: np.ndarray) -> np.ndarray:
        """The base frame's y axis: A_3 - A_1 at zero encoder made orthogonal to the actuators' axis.

        Parameters
        ----------
        x : ndarray, shape (3,)
            The actuators' axis, unit.
        A0 : ndarray, shape (4, 3)
            Each A_i at zero encoder, m.

        Returns
        -------
        ndarray, shape (3,)
            The y axis, unit.
        """
        V1 = A0[2] - A0[0]
        return unit(V1 - (V1 @ x) * x)

    def oriented(self, x: np.ndarray, A0: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A_i(q_i) per fit pose (N, 4, 3) and the leg directions oriented from A to B (N, 4, 3).

        Parameters
        ----------
        x : ndarray, shape (3,)
            The actuators' axis, unit.
        A0 : ndarray, shape (4, 3)
            Each A_i at zero encoder, m.
        U : ndarray, shape (N, 4, 3)
            The leg directions, unit, either sign.

        Returns
        -------
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, m.
        Uo : ndarray, shape (N, 4, 3)
            The directions oriented towards the rods' points, unit.
        """
        Aq = A0[None, :, :] + self.q_fit[:, :, None] * x[None, None, :]
        sgn = np.sign(np.einsum("nij,nij->ni", U, np.where(np.isnan(self.rod_p), 0.0, self.rod_p - Aq)))
        sgn[sgn == 0] = 1.0
        return Aq, U * sgn[..., None]

    def residuals(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The four equations of every pose (N, 4), zero where not available.

        Parameters
        ----------
        theta : ndarray, shape (3,)
            (L, S, D), m.
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, m.
        Uo : ndarray, shape (N, 4, 3)
            Leg directions oriented from A to B, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.

        Returns
        -------
        ndarray, shape (N, 4)
            Residuals of |B1 B2| - 2S, |B3 B4| - 2S, (B3 - B1).y - 2D, (B4 - B2).y - 2D, m.
        """
        L, S, D = theta
        B = Aq + L * Uo
        R = np.stack(
            [
                np.linalg.norm(B[:, 0] - B[:, 1], axis=1) - 2 * S,
                np.linalg.norm(B[:, 2] - B[:, 3], axis=1) - 2 * S,
                (B[:, 2] - B[:, 0]) @ y - 2 * D,
                (B[:, 3] - B[:, 1]) @ y - 2 * D,
            ],
            axis=1,
        )
        return np.where(self.mask, R, 0.0)

    def jacobian(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Derivatives (N, 4, 3) of :meth:`residuals` with respect to (L, S, D), zero where not available.

        Parameters
        ----------
        theta : ndarray, shape (3,)
            (L, S, D), m.
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, m.
        Uo : ndarray, shape (N, 4, 3)
            Leg directions oriented from A to B, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.

        Returns
        -------
        ndarray, shape (N, 4, 3)
            d residual / d (L, S, D), dimensionless.
        """
        L = theta[0]
        B = Aq + L * Uo
        n12 = unit(B[:, 0] - B[:, 1])
        n34 = unit(B[:, 2] - B[:, 3])
        J = np.zeros((Aq.shape[0], 4, 3))
        J[:, 0, 0] = np.sum(n12 * (Uo[:, 0] - Uo[:, 1]), axis=1)
        J[:, 1, 0] = np.sum(n34 * (Uo[:, 2] - Uo[:, 3]), axis=1)
        J[:, 2, 0] = (Uo[:, 2] - Uo[:, 0]) @ y
        J[:, 3, 0] = (Uo[:, 3] - Uo[:, 1]) @ y
        J[:, :2, 1] = -2.0
        J[:, 2:, 2] = -2.0
        return np.where(self.mask[:, :, None], J, 0.0)

    def whitened_jacobian(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Derivatives (N, 4, 3) of :meth:`whitened`.

        Parameters
        ----------
        theta : ndarray, shape (3,)
            (L, S, D), m.
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, m.
        Uo : ndarray, shape (N, 4, 3)
            Leg directions oriented from A to B, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.

        Returns
        -------
        ndarray, shape (N, 4, 3)
            d whitened residual / d (L, S, D), 1/m.
        """
        assert self.W is not None
        return np.einsum("nij,njp->nip", self.W, self.jacobian(theta, Aq, Uo, y))

    def covariances(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Covariance (N, 4, 4) of each pose's equations from its leg directions' (identity where unused).

        Parameters
        ----------
        theta : ndarray, shape (3,)
            (L, S, D), m.
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, m.
        Uo : ndarray, shape (N, 4, 3)
            Leg directions oriented from A to B, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.

        Returns
        -------
        ndarray, shape (N, 4, 4)
            Covariance of each pose's four equations, m^2 (relative when the leg covariances are).
        """
        L = theta[0]
        B = Aq + L * Uo
        n12 = unit(B[:, 0] - B[:, 1])
        n34 = unit(B[:, 2] - B[:, 3])
        N = Aq.shape[0]
        G = np.zeros((N, 4, 4, 3))  # d equation / d leg direction
        G[:, 0, 0], G[:, 0, 1] = L * n12, -L * n12
        G[:, 1, 2], G[:, 1, 3] = L * n34, -L * n34
        G[:, 2, 2], G[:, 2, 0] = L * y, -L * y
        G[:, 3, 3], G[:, 3, 1] = L * y, -L * y
        C = np.einsum("neli,nlij,nmlj->nem", G, np.nan_to_num(self.cov_leg), G)
        m = self.mask[:, :, None] & self.mask[:, None, :]
        C = np.where(m, C, 0.0)
        idx = np.arange(4)
        C[:, idx, idx] = np.where(self.mask, C[:, idx, idx], 1.0)
        return C

    def whitened(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The residuals of :meth:`residuals` whitened by the fixed whitening ``W``.

        Parameters
        ----------
        theta : ndarray, shape (3,)
            (L, S, D), m.
        Aq : ndarray, shape (N, 4, 3)
            A_i(q_i) per fit pose, m.
        Uo : ndarray, shape (N, 4, 3)
            Leg directions oriented from A to B, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.

        Returns
        -------
        ndarray, shape (N, 4)
            Whitened residuals, dimensionless (in standard deviations).
        """
        assert self.W is not None
        return np.einsum("nij,nj->ni", self.W, self.residuals(theta, Aq, Uo, y))

    def robust34(self, x: np.ndarray, y: np.ndarray, A0: np.ndarray, U: np.ndarray, theta0: np.ndarray) -> np.ndarray:
        """(L, S, D) that a few wild poses cannot drag: a Cauchy loss on each pose's whitened equations.

        The weights are taken at ``theta0``, the fit starts there and the loss's scale is the median pose's. This fit
        serves to judge the poses: a leg taken for another edge in a few poses pulls the least-squares fit along
        the valley (L, S, D) ~ (1, u_x, u_y) that only the leg directions' variation pins, far enough (centimetres
        in L) that a gating that judges the poses by that fit cannot undo it; the robust fit from the a priori values
        stays in the right valley.

        Parameters
        ----------
        x : ndarray, shape (3,)
            The actuators' axis, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.
        A0 : ndarray, shape (4, 3)
            Each A_i at zero encoder, m.
        U : ndarray, shape (N, 4, 3)
            The leg directions, unit.
        theta0 : ndarray, shape (3,)
            Start and weighting point (L, S, D), m.

        Returns
        -------
        ndarray, shape (3,)
            (L, S, D), m; ``theta0`` when the robust fit fails.
        """
        Aq, Uo = self.oriented(x, A0, U)
        theta = np.asarray(theta0, dtype=np.float64)
        self.W = np.linalg.cholesky(np.linalg.inv(self.covariances(theta, Aq, Uo, y))).transpose(0, 2, 1)
        used = self.mask.any(axis=1)

        def per_pose(t: np.ndarray) -> np.ndarray:
            return np.sqrt(np.sum(self.whitened(t, Aq, Uo, y) ** 2, axis=1)[used] + 1e-300)

        def per_pose_jac(t: np.ndarray) -> np.ndarray:
            w = self.whitened(t, Aq, Uo, y)[used]
            return np.einsum("ni,nip->np", w, self.whitened_jacobian(t, Aq, Uo, y)[used]) / per_pose(t)[:, None]

        scale = float(np.median(per_pose(theta)))
        if not scale > 0:
            return theta
        sol = least_squares(
            per_pose,
            theta,
            jac=per_pose_jac,
            method="trf",
            loss="cauchy",
            f_scale=scale,
            xtol=1e-10,
            ftol=1e-10,
            gtol=1e-10,
            x_scale="jac",
        )
        return sol.x if sol.success and np.all(np.isfinite(sol.x)) else theta

    def steps34(
        self,
        x: np.ndarray,
        y: np.ndarray,
        A0: np.ndarray,
        U: np.ndarray,
        theta0: np.ndarray,
        on_iteration: IterationCallback | None = None,
    ) -> np.ndarray:
        """(L, S, D) by GLS; the whitening is computed (iterated) on the first call and then kept fixed.

        Parameters
        ----------
        x : ndarray, shape (3,)
            The actuators' axis, unit.
        y : ndarray, shape (3,)
            The base frame's y axis, unit.
        A0 : ndarray, shape (4, 3)
            Each A_i at zero encoder, m.
        U : ndarray, shape (N, 4, 3)
            The leg directions, unit.
        theta0 : ndarray, shape (3,)
            Start (L, S, D), m.
        on_iteration : IterationCallback or None
            Called at each iteration of the fits, or None.

        Returns
        -------
        ndarray, shape (3,)
            (L, S, D), m.

        Raises
        ------
        IdentifiabilityError
            Fewer than 3 equations between the legs of a pair, or none between legs 1 and 3 (2 and 4).
        ConvergenceError
            A pass of the fit did not converge.
        """
        if self.mask[:, :2].sum() < 3:
            raise IdentifiabilityError(
                "legs step 3 needs both legs of a pair seen in at least 2 fit poses", parameter="L"
            )
        if self.mask[:, 2:].sum() == 0:
            raise IdentifiabilityError("legs step 4 needs legs 1 and 3 (or 2 and 4) seen together", parameter="D")
        Aq, Uo = self.oriented(x, A0, U)
        theta = np.asarray(theta0, dtype=np.float64)
        passes = 3 if self.W is None else 1
        for npass in range(passes):
            if passes > 1:
                C = self.covariances(theta, Aq, Uo, y)
                self.W = np.linalg.cholesky(np.linalg.inv(C)).transpose(0, 2, 1)
            stage = "steps 3-4" if npass == 0 else f"steps 3-4 pass {npass + 1}"  # each fit's cost falls
            fun, jac = traced_jac(
                lambda t: self.whitened(t, Aq, Uo, y).ravel(),
                lambda t: self.whitened_jacobian(t, Aq, Uo, y).reshape(-1, 3),
                on_iteration,
                stage,
            )
            sol = least_squares(
                fun,
                theta,
                jac=jac,
                method="lm",
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            )
            if sol.status <= 0 or not np.all(np.isfinite(sol.x)):
                raise ConvergenceError(f"legs steps 3-4 (eq. 11) did not converge: {sol.message}")
            theta = sol.x
        return theta


def pair_means(u: np.ndarray, has: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pose and leg, the covariance-weighted mean of its rods' directions.

    Parameters
    ----------
    u : ndarray, shape (N, 4, 2, 3)
        Rod directions (NaN where missing).
    has : ndarray of bool, shape (N, 4, 2)
    C : ndarray, shape (N, 4, 2, 3, 3)
        Rod direction covariances.

    Returns
    -------
    U : ndarray, shape (N, 4, 3)
        Leg directions (NaN without a rod).
    CU : ndarray, shape (N, 4, 3, 3)
        Their covariances.
    pair_d2 : ndarray, shape (N, 4)
        The two rods' disagreement, chi-square with 2 dof (NaN without both rods).
    """
    u = u.copy()
    dot = np.einsum("nlk,nlk->nl", u[:, :, 0], u[:, :, 1])
    u[:, :, 1] *= np.where(np.isnan(dot), 1.0, np.sign(dot))[..., None]
    N = u.shape[0]
    U = np.full((N, 4, 3), np.nan)
    CU = np.full((N, 4, 3, 3), np.nan)
    pair_d2 = np.full((N, 4), np.nan)
    both = has.all(axis=-1)
    if both.any():  # every pair at once
        U[both], CU[both], pair_d2[both] = _gls_pairs(u[both], C[both])
    one = has.any(axis=-1) & ~both
    if one.any():
        j = np.argmax(has[one], axis=-1)
        U[one], CU[one] = unit(u[one][np.arange(j.size), j]), C[one][np.arange(j.size), j]
    return U, CU, pair_d2


def _gls_pairs(u: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_gls_pair` over P pairs at once: directions (P, 2, 3), covariances (P, 2, 3, 3).

    Parameters
    ----------
    u : ndarray, shape (P, 2, 3)
        Each pair's two aligned unit directions.
    C : ndarray, shape (P, 2, 3, 3)
        Their covariances, rad^2.

    Returns
    -------
    mean : ndarray, shape (P, 3)
        The covariance-weighted means, unit.
    cov : ndarray, shape (P, 3, 3)
        Their covariances, rad^2.
    d2 : ndarray, shape (P,)
        Each pair's disagreement, chi-square with 2 dof.
    """
    m = unit(u[:, 0] + u[:, 1])
    T = tangent_basis(m)  # (P, 3, 2) tangent basis at each mean
    e = u @ T  # (P, 2, 2) tangent coordinates
    Ct = np.einsum("pai,pkab,pbj->pkij", T, C, T) + 1e-18 * np.eye(2)
    Wi = np.linalg.inv(Ct)
    Cm = np.linalg.inv(Wi.sum(axis=1))
    em = np.einsum("pij,pj->pi", Cm, np.einsum("pkij,pkj->pi", Wi, e))
    de = e[:, 0] - e[:, 1]
    d2 = np.einsum("pi,pi->p", de, np.linalg.solve(Ct[:, 0] + Ct[:, 1], de[..., None])[..., 0])
    return unit(m + np.einsum("pij,pj->pi", T, em)), T @ Cm @ T.transpose(0, 2, 1), d2


def pair_own_covariances(u: np.ndarray, has: np.ndarray, C: np.ndarray, C_own: np.ndarray) -> np.ndarray:
    """Per pose and leg, the own covariance of :func:`pair_means`'s direction: its two rods weighed by their
    covariances ``C``, their errors' covariances ``C_own`` (``cov_u_own``).

    Parameters
    ----------
    u : ndarray, shape (N, 4, 2, 3)
        Rod directions, unit (NaN where missing).
    has : ndarray of bool, shape (N, 4, 2)
        The rods measured.
    C : ndarray, shape (N, 4, 2, 3, 3)
        Rod direction covariances the mean weighs by, rad^2.
    C_own : ndarray, shape (N, 4, 2, 3, 3)
        The rods' own error covariances, rad^2.

    Returns
    -------
    ndarray, shape (N, 4, 3, 3)
        Each leg direction's own covariance, rad^2; NaN without a rod.
    """
    dot = np.einsum("nlk,nlk->nl", u[:, :, 0], u[:, :, 1])
    sgn = np.where(np.isnan(dot), 1.0, np.sign(dot))
    out = np.full((*u.shape[:2], 3, 3), np.nan)
    for k, leg in zip(*np.nonzero(has.any(axis=2)), strict=True):
        if not has[k, leg].all():
            out[k, leg] = C_own[k, leg, int(np.argmax(has[k, leg]))]
            continue
        m = unit(u[k, leg, 0] + sgn[k, leg] * u[k, leg, 1])
        T = tangent_basis(m)
        Wi = np.linalg.inv(np.einsum("ai,kab,bj->kij", T, C[k, leg], T) + 1e-18 * np.eye(2))
        Cm = np.linalg.inv(Wi.sum(axis=0))
        Co = np.einsum("ai,kab,bj->kij", T, C_own[k, leg], T)
        out[k, leg] = T @ (Cm @ np.einsum("kij,kjl,kml->im", Wi, Co, Wi) @ Cm) @ T.T
    return out


def rod_own_covariances(obs: Observations, data: PhaseArrays) -> np.ndarray | None:
    """Every measured rod's ``cov_u_own`` (N, 4, 2, 3, 3), NaN where no rod; None when a measured rod lacks it.

    Parameters
    ----------
    obs : Observations
        The observations the rods come from.
    data : PhaseArrays
        The phase's arrays (which rods were measured, in which frames).

    Returns
    -------
    ndarray, shape (N, 4, 2, 3, 3), or None
        The covariances, rad^2.
    """
    C = np.full((len(data), 4, 2, 3, 3), np.nan)
    for k, leg, rod in zip(*np.nonzero(data.has_rod), strict=True):
        c = _rod_field(obs, data, k, leg, rod, "cov_u_own")
        if c is None or c.shape != (3, 3):
            return None
        C[k, leg, rod] = c
    return C


def leg_directions(
    obs: Observations, data: PhaseArrays, direction_std_rad: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool, list[dict[str, int]], np.ndarray]:
    """Per pose and leg: direction, its covariance, a rod point and the mask of legs used.

    Also whether the covariances are the rods' measured ones (``cov_u``; else ``sigma^2 (I - u u^T)`` with sigma
    ``direction_std_rad`` or 1, relative), the rod pairs rejected as disagreeing and the rods' covariances.

    Parameters
    ----------
    obs : Observations
        The observations the rods come from.
    data : PhaseArrays
        The phase's arrays (rod directions and points, which rods were measured).
    direction_std_rad : float or None
        Rod direction std used when the rods carry no covariance, rad (None: 1, relative weights).

    Returns
    -------
    U : ndarray, shape (N, 4, 3)
        Leg directions, unit (NaN where unused).
    CU : ndarray, shape (N, 4, 3, 3)
        Their covariances, rad^2 (or relative).
    pts : ndarray, shape (N, 4, 3)
        A point on each leg's rods, camera frame, m.
    has_leg : ndarray of bool, shape (N, 4)
        The legs used.
    measured : bool
        Whether the covariances are the rods' measured ones.
    rejected : list of dict
        The rod pairs rejected as disagreeing, ``{"frame": int, "leg": 1..4}``.
    C : ndarray, shape (N, 4, 2, 3, 3)
        The rods' covariances, rad^2 (or relative).
    """
    N = len(data)
    u = data.rod_u
    has = data.has_rod
    C = np.full((N, 4, 2, 3, 3), np.nan)
    measured = True
    for k, leg, rod in zip(*np.nonzero(has), strict=True):
        c = _rod_field(obs, data, k, leg, rod, "cov_u")
        if c is None or c.shape != (3, 3):
            measured = False
            break
        C[k, leg, rod] = c
    if not measured:
        s = 1.0 if direction_std_rad is None else direction_std_rad
        uu = np.nan_to_num(u)
        C = s**2 * (np.eye(3) - uu[..., :, None] * uu[..., None, :])
    U, CU, pair_d2 = pair_means(u, has, C)
    # (N, 4): a reduction over one axis of the (N, 4, 2) mask is an array (the stubs also allow a scalar)
    has_leg = cast("NDArray[np.bool_]", has.any(axis=2))
    rejected: list[dict[str, int]] = []
    ok = np.isfinite(pair_d2)
    if ok.sum() >= 3:
        s_rob = robust_chi2_scale(pair_d2[ok], 2)
        if s_rob > 0:
            bad = ok & chi2_outliers(np.where(ok, pair_d2, 0.0), 2, s_rob)
            rejected = [
                {"frame": int(data.index[k]), "leg": int(leg) + 1} for k, leg in zip(*np.nonzero(bad), strict=True)
            ]
            has_leg &= ~bad
    pts = np.where(data.has_point[:, :, 0, None], data.rod_p[:, :, 0], data.rod_p[:, :, 1])
    U = np.where(has_leg[..., None], U, np.nan)
    return U, CU, pts, has_leg, measured, rejected, C


def gate_poses(pipe: LegsModel, P: np.ndarray, U: np.ndarray, seven: np.ndarray) -> np.ndarray:
    """Poses whose whitened equations exceed their chi-square 99.9% quantile (robust scale).

    Parameters
    ----------
    pipe : LegsModel
        The model, fitted (its whitening set).
    P : ndarray, shape (4, 2, 3)
        The upper joint points, camera frame, m.
    U : ndarray, shape (N, 4, 3)
        The leg directions, unit.
    seven : ndarray, shape (7,)
        The estimate, PARAMETER_NAMES order, m.

    Returns
    -------
    ndarray of bool, shape (N,)
        The outlying poses.
    """
    Aq, Uo, y = pipe.geometry(P, U)
    d2 = np.sum(pipe.whitened(seven[[6, 4, 5]], Aq, Uo, y) ** 2, axis=1)
    m = pipe.mask.sum(axis=1)
    used = m > 0
    if used.sum() < 4:
        return np.zeros(len(m), dtype=bool)
    s_rob = robust_chi2_scale(d2[used], m[used])
    if s_rob <= 0:
        return np.zeros(len(m), dtype=bool)
    return used & chi2_outliers(d2, np.maximum(m, 1), s_rob)


def steps34_covariance(
    pipe: LegsModel, P: np.ndarray, U: np.ndarray, seven: np.ndarray
) -> tuple[np.ndarray, float, int]:
    """GLS covariance of (L, S, D) for unit-scaled weights, with the fit's chi-square and its degrees of freedom.

    Parameters
    ----------
    pipe : LegsModel
        The model, fitted (its whitening set).
    P : ndarray, shape (4, 2, 3)
        The upper joint points, camera frame, m.
    U : ndarray, shape (N, 4, 3)
        The leg directions, unit.
    seven : ndarray, shape (7,)
        The estimate, PARAMETER_NAMES order, m.

    Returns
    -------
    cov : ndarray, shape (3, 3)
        Covariance of (L, S, D), m^2.
    chi2 : float
        Sum of the squared whitened residuals, dimensionless.
    dof : int
        Equations used minus 3.
    """
    Aq, Uo, y = pipe.geometry(P, U)
    theta = seven[[6, 4, 5]]
    J = central_jacobian(lambda t: pipe.whitened(t, Aq, Uo, y).ravel(), theta, h=1e-7)
    r = pipe.whitened(theta, Aq, Uo, y)
    dof = int(pipe.mask.sum()) - 3
    return np.linalg.inv(J.T @ J), float(np.sum(r**2)), dof


def steps34_sandwich(
    pipe: LegsModel, P: np.ndarray, U: np.ndarray, seven: np.ndarray, cov_leg_own: np.ndarray, covP: np.ndarray
) -> tuple[np.ndarray, float, float]:
    """The leg directions' own part of (L, S, D)'s covariance and the steps 3-4 chi-square against its expectation.

    The fit weighs each pose's equations by the leg directions' ``cov_u`` (its whitening ``pipe.W``), which carries
    the extraction's edge-bias allowance whole; most of that allowance is the limb-edge bias every rod shares, which
    the method corrects by the combined fit's measurement and propagates apart (``limb_edge_bias``). What the
    directions add of their own is ``cov_u_own`` (the allowance averaged along the limb): the covariance here is the
    fit's gain applied to it (a sandwich). The fit's residuals also carry the joints' errors (fixed in steps 3-4 and
    propagated apart), so their chi-square is compared with what the own errors and the joints' together make it
    expect.

    Parameters
    ----------
    pipe : LegsModel
        Fitted (its whitening ``W`` set).
    P : ndarray, shape (4, 2, 3)
        The joints, camera frame (m).
    U : ndarray, shape (N, 4, 3)
        Leg directions (zero where unused).
    seven : ndarray, shape (7,)
        The estimate (PARAMETER_NAMES order).
    cov_leg_own : ndarray, shape (N, 4, 3, 3)
        The leg directions' own covariance (rad^2).
    covP : ndarray, shape (24, 24)
        The joints' covariance ((leg, rod, xyz) order, m^2).

    Returns
    -------
    cov : ndarray, shape (3, 3)
        (L, S, D), m^2.
    chi2 : float
        The whitened residuals' sum of squares.
    expected : float
        Its expectation under ``cov_leg_own`` and ``covP``: ``tr(M W (C_own + G covP G^T) W^T M^T)``, ``M`` the fit's
        residual projector, ``G`` the equations' change with the joints.
    """
    assert pipe.W is not None
    theta = seven[[6, 4, 5]]
    Aq, Uo, y = pipe.geometry(P, U)
    J = pipe.whitened_jacobian(theta, Aq, Uo, y).reshape(-1, 3)
    r = pipe.whitened(theta, Aq, Uo, y).ravel()
    own = LegsModel(pipe.q_lock, pipe.q_fit, pipe.rod_p, pipe.has_leg, cov_leg_own, pipe.nominal)
    C_own = own.covariances(theta, Aq, Uo, y)  # (N, 4, 4), identity on unused equations
    C_own = np.where(pipe.mask[:, :, None] & pipe.mask[:, None, :], C_own, 0.0)
    S = block_diag(*np.einsum("nij,njk,nlk->nil", pipe.W, C_own, pipe.W))
    Ainv = np.linalg.inv(J.T @ J)
    gain = Ainv @ J.T
    cov = gain @ S @ gain.T

    def whitened_at(pv: np.ndarray) -> np.ndarray:
        return pipe.whitened(theta, *pipe.geometry(pv.reshape(4, 2, 3), U)).ravel()

    G = central_jacobian(whitened_at, P.ravel(), h=1e-7)  # (4N, 24)
    M = np.eye(J.shape[0]) - J @ gain
    expected = float(np.trace(M @ (S + G @ covP @ G.T) @ M.T))
    return cov, float(r @ r), expected


#: the former private names (tests read them)
