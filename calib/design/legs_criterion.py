"""The legs method's accuracy as a criterion for choosing fit poses: additive per-pose statistics.

The legs method (:mod:`calib.identify.legs`) estimates ``(L, S, D)`` in its steps 3-4 by generalised least squares
over the fit poses' leg directions, given the joints that step 1 finds in the lock phases. Its error has two parts
that the fit poses change:

* the leg directions' own errors: ``A^-1 M A^-1`` with ``A = sum_k J_k^T C_k^-1 J_k`` (``J_k`` (4, 3): the pose's four
  equations' derivatives in ``(L, S, D)``, ``C_k`` (4, 4): their covariance from the pose's leg directions' ``cov_u``,
  the fit's weights) and ``M = sum_k J_k^T C_k^-1 C_own,k C_k^-1 J_k`` (``C_own,k`` from their ``cov_u_own``, what
  they err by: the method's sandwich), times the prediction's levels;
* the joints' error (the lock phases' noise and their systematic depth, covariance ``Sigma_P`` (24, 24)), carried
  into ``(L, S, D)`` by the fit's gain ``-A^-1 B`` with ``B = sum_k J_k^T C_k^-1 R_k`` (``R_k`` (4, 24): the
  equations' derivatives in the eight joints). Steps 2's ``(H, q02, q03, q04)`` depend on the joints alone (gain
  ``G2`` (4, 24), the same for every pose set).

``A`` and ``B`` add over poses, so every swap of the exchange is evaluated at once as for the other methods
(:mod:`.optimize`). Each pose's statistic is packed as one (3, 30) array ``[A_k | M_k | B_k]``. With the a priori
tolerance applied as the method does, these are the plan's prediction (:func:`.predict_images.predict_legs_images`)
without its intrinsics and limb-edge-bias parts (on the twin's designed plans 0.04-0.12 mm of a combination's
0.3-0.8 mm), which the criterion leaves out. Units: metres.
"""

from __future__ import annotations

import numpy as np

from calib.design.predict import mark_undetermined, scaled_inverse
from calib.design.predict_images import ImageNoise, legs_fit_directions, legs_lock_joints
from calib.design.scene import Scene
from calib.model.parameters import SEVEN_TO_FOUR, I4Parameters
from calib.numerics.numdiff import central_jacobian

__all__ = ["LegsCriterion"]

#: rows of (S, D, L) in the seven parameters (H, q02, q03, q04, S, D, L); (L, S, D) is the steps 3-4 order
_LSD_ROWS = np.array([6, 4, 5])
#: a pose's statistic: A (3 columns), the own errors' M (3), B (24)
_WIDTH = 30
#: joint displacement for the equations' derivatives, metres
_STEP_M = 1e-7


class LegsCriterion:
    """The legs method's predicted covariance of the four combinations as a function of additive pose statistics.

    Parameters
    ----------
    nominal : I4Parameters
        The nominal geometry (the design's linearisation point).
    q_lock : list of 4 ndarray, each (n_i, 4)
        The plan's lock phases (actuator values, metres).
    scene : Scene
    noise : ImageNoise
        The image-level noise model (the prediction's levels: the lock phases' chi-square, the joints' systematic
        depth, the leg directions' chi-square and the rods' covariance ratio).
    """

    def __init__(self, nominal: I4Parameters, q_lock: list[np.ndarray], scene: Scene, noise: ImageNoise) -> None:
        from calib.identify.legs import LegsModel, fit_step2, joint_depth_systematic

        self.nominal, self.scene, self.noise = nominal, scene, noise
        lk = legs_lock_joints(nominal, q_lock, scene, noise)
        self.q_locked, self.P = lk.q_locked, lk.P
        sigma = noise.legs_lock_chi2 * lk.covP
        if noise.legs_joint_depth_sys_m > 0:
            sigma = sigma + joint_depth_systematic(
                lk.P, noise.legs_joint_depth_sys_m, noise.legs_joint_depth_sys_leg_share
            )
        self.sigma_P = sigma  # (24, 24) m^2
        self.dir_scale = noise.legs_directions_chi2 * noise.legs_rod_cov_ratio
        x0 = np.array([nominal.q02, nominal.q03, nominal.q04, nominal.H])
        pipe = LegsModel(
            self.q_locked,
            np.zeros((1, 4)),
            np.full((1, 4, 3), np.nan),
            np.ones((1, 4), bool),
            np.zeros((1, 4, 3, 3)),
            nominal,
        )

        def step2(p: np.ndarray) -> np.ndarray:
            _x, A0, _ = pipe.frame(p.reshape(4, 2, 3))
            q02, q03, q04, H = fit_step2(A0[1:] - A0[0], x0)
            return np.array([H, q02, q03, q04])

        self.G2 = central_jacobian(step2, self.P.ravel(), _STEP_M)  # (4, 24): (H, q02, q03, q04) per joint coordinate
        self.prior_var = noise.legs_prior_std_m**2 if noise.legs_prior_std_m else 0.0

    def pose_statistics(self, q: np.ndarray) -> np.ndarray:
        """Per fit pose (N, 3, 30) the additive statistic ``[J^T C^-1 J | J^T C^-1 C_own C^-1 J | J^T C^-1 R]`` (see the
        module); zero for a pose without the four legs in view.

        Parameters
        ----------
        q : ndarray, shape (N, 4)
            Encoder values of the candidate fit poses, metres.

        Returns
        -------
        ndarray, shape (N, 3, 30)
            The per-pose statistic (in the units of ``(L, S, D)``, metres, and the 24 joint coordinates, metres).
        """
        from calib.identify.legs import LegsModel, pair_own_covariances

        q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
        out = np.zeros((len(q), 3, _WIDTH))
        if not len(q):
            return out
        fd = legs_fit_directions(self.nominal, q, self.scene, self.noise)
        ok = fd.has_leg.all(axis=1)
        if not ok.any():
            return out
        CU_own = np.nan_to_num(pair_own_covariances(fd.u, fd.has, fd.cov_u, fd.cov_u_own))[ok]
        pipe = LegsModel(self.q_locked, q[ok], fd.pts[ok], fd.has_leg[ok], fd.CU[ok], self.nominal)
        nom = self.nominal
        theta = np.array([nom.L, nom.S, nom.D])
        U = fd.U[ok]
        Aq, Uo, y = pipe.geometry(self.P, U)
        J = pipe.jacobian(theta, Aq, Uo, y)  # (n, 4, 3)
        Ci = np.linalg.inv(pipe.covariances(theta, Aq, Uo, y))  # (n, 4, 4): the fit's weights (``cov_u``)
        own = LegsModel(self.q_locked, q[ok], fd.pts[ok], fd.has_leg[ok], CU_own, self.nominal)
        C_own = own.covariances(theta, Aq, Uo, y)  # (n, 4, 4): the directions' own errors (``cov_u_own``)
        # the orientation of each leg direction as at the nominal joints, so that a moved joint does not flip it
        sgn = np.sign(np.einsum("nij,nij->ni", Uo, U))[..., None]

        def residuals(p: np.ndarray) -> np.ndarray:
            x, A0, _ = pipe.frame(p.reshape(4, 2, 3))
            Aqp = A0[None, :, :] + pipe.q_fit[:, :, None] * x[None, None, :]
            return pipe.residuals(theta, Aqp, U * sgn, pipe.y_axis(x, A0))  # (n, 4)

        p0 = self.P.ravel()
        R = np.empty((int(ok.sum()), 4, 24))
        for c in range(24):
            e = np.zeros(24)
            e[c] = _STEP_M
            R[:, :, c] = (residuals(p0 + e) - residuals(p0 - e)) / (2 * _STEP_M)
        JtCi = np.einsum("nei,nef->nif", J, Ci)  # (n, 3, 4)
        out[ok, :, :3] = JtCi @ J
        out[ok, :, 3:6] = JtCi @ C_own @ np.swapaxes(JtCi, -1, -2)
        out[ok, :, 6:] = JtCi @ R
        return out

    def _with_prior(self, cov7: np.ndarray) -> np.ndarray:
        """Batched (..., 7, 7): the method's a priori tolerance in the directions the data pin worse than it
        (:func:`calib.identify.legs.uncertainty._with_prior`: data weighed by ``s^2 / (w + s^2)`` there)."""
        if not self.prior_var:
            return cov7
        w, V = np.linalg.eigh(0.5 * (cov7 + np.swapaxes(cov7, -1, -2)))
        w = np.maximum(w, 0.0)
        a = np.where(w < self.prior_var, 1.0, self.prior_var / (w + self.prior_var))
        # A C A^T + (I - A) s^2 (I - A)^T in the eigenbasis of C: diag(a^2 w + (1 - a)^2 s^2)
        v = a**2 * w + (1.0 - a) ** 2 * self.prior_var
        return np.einsum("...ik,...k,...jk->...ij", V, v, V)

    def cov4(self, stats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Batched: summed statistics (..., 3, 30) -> the four combinations' covariance (..., 4, 4), m^2, and the log
        det of its inverse (-inf where ``A`` is singular, and the variances inf), as :func:`.optimize._cov4` gives them
        for the other methods.

        Parameters
        ----------
        stats : ndarray, shape (..., 3, 30)
            Sums of :meth:`pose_statistics` over the poses of each selection.

        Returns
        -------
        cov : ndarray, shape (..., 4, 4)
            The four combinations' covariance, m^2 (inf variances where undetermined).
        logdet : ndarray, shape (...)
            Log det of its inverse (-inf where undetermined).
        """
        A = stats[..., :3]
        M = stats[..., 3:6]
        B = stats[..., 6:]
        Ai, ok = scaled_inverse(A)
        # the seven's gain in the joints: G2 for (H, q02, q03, q04), -A^-1 B for (L, S, D)
        G = np.zeros((*A.shape[:-2], 7, 24))
        G[..., :4, :] = self.G2
        G[..., _LSD_ROWS, :] = -(Ai @ B)
        cov7 = G @ self.sigma_P @ np.swapaxes(G, -1, -2)
        cov7[..., _LSD_ROWS[:, None], _LSD_ROWS[None, :]] += self.dir_scale * (Ai @ M @ Ai)
        return mark_undetermined(SEVEN_TO_FOUR @ self._with_prior(cov7) @ SEVEN_TO_FOUR.T, ok)
