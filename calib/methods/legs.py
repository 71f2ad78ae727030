"""Legs observation only (the paper's reference [9], section IV.A.2), in four steps.

1. ``lock-i`` phases: with actuator i locked, each rod of leg i turns about its fixed upper spherical
   joint, so its axis passes through that joint in every frame: the joint is the point that best
   satisfies every frame's axis constraint; the two joints' midpoint is A_i at the locked encoder value.
   x_B is the direction A1 -> A2 (and A3 -> A4); ``A_i(q_i = 0) = A_i - q_i x_B``.
2. (q02, q03, q04, H) from the scalar products of ``V = (OA2, OA3, OA4)|q=0`` (eq. 9, 10), O = A1(q1 = 0).
3. L from the invariance of |B1 B2| and |B3 B4| over the fit poses (eq. 11), with
   ``B_i = A_i(q_i) + L u_i``.
4. S from |B1 B2| = |B3 B4| = 2S; D from the distance 2D between B1 and B3 (and B2, B4) along y_B.

All seven parameters are identified.

Weighting. When the rods carry what the image extraction measures (extra fields ``h``, the two
interpretation-plane normals, and ``cov_u``, the direction's covariance; observations v1), the
method uses the measurement's real noise, which is far from isotropic: a rod's image position is
precise, its depth (from its apparent width) tens of times less so.

* Step 1 solves the two plane equations ``h_q . X = r`` of every frame (r the rod radius, read as
  ``h . point``) for the joint X by weighted least squares, each equation weighed by the variance of
  its limb line (angle and offset, from the limb's edge scatter ``rms_px`` over ``n_points``, the
  extraction's edge-bias allowance, scaled per rod so that it reproduces the rod's ``cov_u``),
  propagated to the distance of X from the plane. Frames whose two equations are beyond the
  chi-square(2) 99.9% quantile of a robust scale are dropped. Without ``h``: the least-squares
  intersection of the axis lines (direction and point), all lines weighing the same.
* Steps 3 and 4 are solved together (poses judged for the gating below by a robust fit from the a
  priori values, a Cauchy loss on each pose's whitened equations, then the least-squares fit of the
  poses kept): per fit pose, ``|B1 B2| - 2S``, ``|B3 B4| - 2S``,
  ``(B3 - B1) . y_B - 2D`` and ``(B4 - B2) . y_B - 2D`` vanish (eq. 11 and step 4 with the constant
  made explicit); (L, S, D) minimise these residuals whitened by their covariance from the leg
  directions' covariance (generalised least squares). A leg's direction is the covariance-weighted
  mean of its two rods (``cov_u``; isotropic without it); a pair of rods that disagree beyond the
  chi-square(2) 99.9% quantile, or a pose whose whitened residuals are beyond their chi-square
  99.9% quantile, is dropped.

Standard deviations: the joints' covariance (from the weighted fit, scaled by its residual
chi-square per degree of freedom) propagated linearly through steps 2-4 (numerical derivatives),
plus the GLS covariance of (L, S, D), scaled by its residual chi-square per degree of freedom.
The two parts come from different frames (``lock-i`` and fit phases) and are independent.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from ..camera import CameraModel
from ..errors import ConvergenceError, IdentifiabilityError, InputError
from ..numdiff import central_jacobian
from ..observations import Observations, PhaseArrays
from ..parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters
from ..robust import chi2_gate, chi2_outliers, robust_chi2_scale
from ..transforms import tangent_basis, unit
from . import intrinsics as intr
from .combined import EDGE_BIAS_STD_PX
from .iterations import IterationCallback, traced
from .result import MethodResult, combos_dict, std_dict

_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: Default std (m) of each of the seven parameters around the nominal geometry (:func:`calibrate_legs`'s prior): a
#: bench built to its drawings within about +/-10 mm per length (the twin's default truth is 5.3 mm RMS and at most
#: 8.4 mm from nominal; the accuracy benchmark draws its truths with 5.3 mm std)
PRIOR_STD_M = 0.01
#: Floor (m) of the rod-pair check's separation std: below any measurement (noise-free data are never flagged)
_PAIR_FLOOR_M = 1e-6
#: the four step-3/4 equations of a pose: (leg a, leg b) of |Ba Bb| - 2S, then of (Bb - Ba) . y - 2D
_EQ_LEGS = ((0, 1), (2, 3), (0, 2), (1, 3))


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


@dataclass(frozen=True)
class PlaneObservation:
    """One rod seen in one frame: its two interpretation planes and their noise model.

    Attributes
    ----------
    h : ndarray, shape (2, 3)
        Unit plane normals (camera frame), signed so that the axis is on their positive side.
    r : float
        Rod radius, metres: ``h_q . X = r`` for every axis point X.
    dh : ndarray, shape (2, 2, 3) or None
        ``d h_q / d(angle, offset)`` of limb q's image line (rad, px); None: no noise model.
    var : ndarray, shape (2, 2) or None
        Variances of each limb line's angle (rad^2) and offset (px^2).
    """

    h: np.ndarray
    r: float
    dh: np.ndarray | None = None
    var: np.ndarray | None = None

    def variances(self, X: np.ndarray) -> np.ndarray:
        """Variances (2,) of the two equations ``h_q . X - r`` at X (m^2; 1 without a noise model)."""
        if self.dh is None or self.var is None:
            return np.ones(2)
        g = self.dh @ X  # (2, 2)
        return np.sum(g**2 * self.var, axis=1) + 1e-30


def planes_direction_covariance(h: np.ndarray, dh: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of ``u = normalize(h1 x h2)`` from independent perturbations of the two planes.

    ``h`` (2, 3): the planes' unit normals; ``dh`` (2, 2, 3): per plane, its change per unit of its
    two noise parameters (angle, offset); ``var`` (2, 2): their variances.
    """
    m = np.cross(h[0], h[1])
    nm = float(np.linalg.norm(m))
    u = m / nm
    Pu = np.eye(3) - np.outer(u, u)
    C = np.zeros((3, 3))
    for q in range(2):
        for p in range(2):
            dm = np.cross(dh[0, p], h[1]) if q == 0 else np.cross(h[0], dh[1, p])
            du = Pu @ dm / nm
            C += var[q, p] * np.outer(du, du)
    return C


def limb_line_noise(
    K: np.ndarray,
    h: np.ndarray,
    point: np.ndarray,
    rms_px: np.ndarray,
    n_points: np.ndarray,
    cov_u: np.ndarray | None = None,
    step_px: float = 3.0,
    edge_bias_px: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise model of a rod's two limb lines: plane-normal derivatives and line variances.

    Each limb line (image, ideal pixels: ``l ~ K^-T h``) is perturbed by a rotation about its
    centroid (the foot of the rod point's image on it) and a shift along its normal. The variances
    are those of a TLS line through ``n_points`` edge points ``step_px`` apart with residual RMS
    ``rms_px`` (angle ``s^2 / sum t^2``, offset ``s^2 / N``) plus a slowly varying edge bias
    (``edge_bias_px`` end to end); with ``cov_u`` they are scaled so that the direction covariance
    they imply has the trace of ``cov_u`` (which accounts for the edges' correlation along a limb).

    Parameters
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix (ideal pixels).
    h : ndarray, shape (2, 3)
        Interpretation-plane normals, camera frame.
    point : ndarray, shape (3,)
        An axis point in view (camera frame, metres).
    rms_px, n_points : ndarray, shape (2,)
        Each limb's edge residual RMS (px) and number of edge points.
    cov_u : ndarray, shape (3, 3), optional
        The rod direction's covariance.
    step_px, edge_bias_px : float
        The extraction's profile spacing and edge-bias allowance (px).

    Returns
    -------
    dh : ndarray, shape (2, 2, 3)
        ``d h_q / d angle`` (per rad) and ``d h_q / d offset`` (per px) for each limb q.
    var : ndarray, shape (2, 2)
        Variances of (angle, offset) per limb, rad^2 and px^2.
    """
    x = K @ point
    c0 = x[:2] / x[2]
    KinvT = np.linalg.inv(K).T
    dh = np.zeros((2, 2, 3))
    var = np.zeros((2, 2))
    for q in range(2):
        line = KinvT @ h[q]
        line = line / np.linalg.norm(line[:2])
        n = line[:2]
        c = c0 - (n @ c0 + line[2]) * n

        def plane(dth: float, doff: float, n: np.ndarray = n, c: np.ndarray = c, q: int = q) -> np.ndarray:
            cs, sn = np.cos(dth), np.sin(dth)
            n2 = np.array([cs * n[0] - sn * n[1], sn * n[0] + cs * n[1]])
            hh = K.T @ np.array([n2[0], n2[1], -(n2 @ c) - doff])
            hh = hh / np.linalg.norm(hh)
            return hh if hh @ h[q] > 0 else -hh

        dh[q, 0] = (plane(1e-6, 0.0) - plane(-1e-6, 0.0)) / 2e-6
        dh[q, 1] = (plane(0.0, 1e-3) - plane(0.0, -1e-3)) / 2e-3
        npts = max(float(n_points[q]), 3.0)
        s2 = float(rms_px[q]) ** 2
        span = step_px * (npts - 1.0)
        st2 = step_px**2 * npts * (npts**2 - 1.0) / 12.0
        var[q] = [s2 / st2 + (edge_bias_px / span) ** 2, s2 / npts + (0.5 * edge_bias_px) ** 2]
    if cov_u is not None:
        tm = float(np.trace(planes_direction_covariance(h, dh, var)))
        if tm > 0 and np.all(np.isfinite(cov_u)):
            var = var * (float(np.trace(cov_u)) / tm)
    return dh, var


def joint_from_planes(obs: list[PlaneObservation], iterations: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares point X of ``h_q . X = r`` over a rod's frames.

    Parameters
    ----------
    obs : list of PlaneObservation
        At least 2 frames.

    Returns
    -------
    X : ndarray, shape (3,)
        Metres, camera frame.
    normal_matrix : ndarray, shape (3, 3)
        ``sum w h h^T`` with ``w`` the inverse equation variances; X's covariance is its inverse
        (times the chi-square scale when the variances are relative).
    d2 : ndarray, shape (M,)
        Each frame's two residuals squared, each divided by its variance, summed.
    """
    Hm = np.stack([o.h for o in obs])  # (M, 2, 3)
    r = np.array([o.r for o in obs])
    X = np.linalg.lstsq(Hm.reshape(-1, 3), np.repeat(r, 2), rcond=None)[0]
    A = np.eye(3)
    v = np.ones((len(obs), 2))
    for _ in range(iterations):
        v = np.stack([o.variances(X) for o in obs])
        w = 1.0 / v
        A = np.einsum("mq,mqi,mqj->ij", w, Hm, Hm)
        if np.linalg.cond(A) > 1e12:
            raise IdentifiabilityError("the rod planes of a locked leg do not locate its joint (rod barely moved)")
        X = np.linalg.solve(A, np.einsum("mq,mqi,m->i", w, Hm, r))
    res = Hm @ X - r[:, None]
    return X, A, np.sum(res**2 / v, axis=1)


def _step2(V: np.ndarray, x0: np.ndarray, on_iteration: IterationCallback | None = None) -> np.ndarray:
    """(q02, q03, q04, H) from V (3, 3) rows OA2, OA3, OA4 at zero encoder (eq. 9)."""
    G = V @ V.T
    meas = np.array([G[a, b] for a, b in _PAIRS])

    def model(x: np.ndarray) -> np.ndarray:
        q02, q03, q04, H = x
        Vb = np.array([[q02, 0.0], [q03, 2 * H], [q04, 2 * H]])
        Gb = Vb @ Vb.T
        return np.array([Gb[a, b] for a, b in _PAIRS])

    sol = least_squares(
        traced(lambda x: model(x) - meas, on_iteration, "step 2"), x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
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


class _LegsPipeline:
    """Steps 2-4 as a function of the joint points (step 1 output) and the fit-pose leg directions."""

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
        """Legs used per pose (N, 4) and the equations they allow (N, 4)."""
        self.has_leg = has_leg
        self.mask = np.stack([has_leg[:, a] & has_leg[:, b] for a, b in _EQ_LEGS], axis=1)
        self.W = None

    def frame(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x_B and A_i(q=0) in the camera frame from the 8 upper joint points (4, 2, 3)."""
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
    ) -> np.ndarray:
        """Seven parameters (PARAMETER_NAMES order) from joint points P (4,2,3) and leg directions U (N,4,3)."""
        nom = self.nominal
        x, A0, _ = self.frame(P)
        V = A0[1:] - A0[0]
        x2 = _step2(V, np.array([nom.q02, nom.q03, nom.q04, nom.H]) if x2_init is None else x2_init, on_iteration)
        q02, q03, q04, H = x2
        y = self.y_axis(x, A0)
        theta0 = np.array([nom.L, nom.S, nom.D])
        L, S, D = self.robust34(x, y, A0, U, theta0) if robust else self.steps34(x, y, A0, U, theta0, on_iteration)
        return np.array([H, q02, q03, q04, S, D, L])

    @staticmethod
    def y_axis(x: np.ndarray, A0: np.ndarray) -> np.ndarray:
        V1 = A0[2] - A0[0]
        return unit(V1 - (V1 @ x) * x)

    def oriented(self, x: np.ndarray, A0: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A_i(q_i) per fit pose (N, 4, 3) and the leg directions oriented from A to B (N, 4, 3)."""
        Aq = A0[None, :, :] + self.q_fit[:, :, None] * x[None, None, :]
        sgn = np.sign(np.einsum("nij,nij->ni", U, np.where(np.isnan(self.rod_p), 0.0, self.rod_p - Aq)))
        sgn[sgn == 0] = 1.0
        return Aq, U * sgn[..., None]

    def residuals(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The four equations of every pose (N, 4), zero where not available."""
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

    def covariances(self, theta: np.ndarray, Aq: np.ndarray, Uo: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Covariance (N, 4, 4) of each pose's equations from its leg directions' (identity where unused)."""
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
        assert self.W is not None
        return np.einsum("nij,nj->ni", self.W, self.residuals(theta, Aq, Uo, y))

    def robust34(self, x: np.ndarray, y: np.ndarray, A0: np.ndarray, U: np.ndarray, theta0: np.ndarray) -> np.ndarray:
        """(L, S, D) that a few wild poses cannot drag: a Cauchy loss on each pose's whitened equations (weights at
        ``theta0``), from ``theta0``, its scale the median pose's. For judging the poses: a leg taken for another
        edge in a few poses pulls the least-squares fit along the valley (L, S, D) ~ (1, u_x, u_y) that only the
        leg directions' variation pins (on a rendered trial to L 104 mm off with a 9.6 mm std, which the gating,
        judging the poses by that fit, could not undo); the robust fit from the a priori values stays in the
        right valley."""
        Aq, Uo = self.oriented(x, A0, U)
        theta = np.asarray(theta0, dtype=np.float64)
        self.W = np.linalg.cholesky(np.linalg.inv(self.covariances(theta, Aq, Uo, y))).transpose(0, 2, 1)
        used = self.mask.any(axis=1)

        def per_pose(t: np.ndarray) -> np.ndarray:
            return np.sqrt(np.sum(self.whitened(t, Aq, Uo, y) ** 2, axis=1)[used] + 1e-300)

        scale = float(np.median(per_pose(theta)))
        if not scale > 0:
            return theta
        sol = least_squares(
            per_pose,
            theta,
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
        """(L, S, D) by GLS; the whitening is computed (iterated) on the first call and then kept fixed."""
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
            sol = least_squares(
                traced(lambda t: self.whitened(t, Aq, Uo, y).ravel(), on_iteration, stage),
                theta,
                method="lm",
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            )
            if sol.status <= 0 or not np.all(np.isfinite(sol.x)):
                raise ConvergenceError(f"legs steps 3-4 (eq. 11) did not converge: {sol.message}")
            theta = sol.x
        return theta


def _rod_field(obs: Observations, data: PhaseArrays, k: int, leg: int, rod: int, name: str) -> np.ndarray | None:
    """An extra field of one rod (``h``, ``cov_u``, ``rms_px``, ``n_points``) as float64, or None."""
    frame = obs.frames[int(data.index[k])]
    rods = frame.legs.get(str(leg + 1)) if frame.legs else None
    if not rods or rod >= len(rods) or rods[rod] is None:
        return None
    v = getattr(rods[rod], name, None)
    if v is None:
        return None
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return a if np.all(np.isfinite(a)) else None


def _extraction_settings(obs: Observations) -> tuple[np.ndarray | None, float, float]:
    """The extraction's camera matrix (or None), profile spacing and edge-bias allowance (px)."""
    extra = obs.document.model_extra or {}
    ex = extra.get("extraction") or {}
    K = (ex.get("camera") or {}).get("K")
    rs = ex.get("rod_settings") or {}
    try:
        Km = np.asarray(K, dtype=np.float64) if K is not None else None
    except (TypeError, ValueError):
        Km = None
    if Km is not None and (Km.shape != (3, 3) or not np.all(np.isfinite(Km))):
        Km = None
    return Km, float(rs.get("step_px", 3.0)), float(rs.get("edge_bias_px", 0.05))


def _plane_observations(obs: Observations, data: PhaseArrays, leg: int, rod: int) -> list[PlaneObservation] | None:
    """The rod's frames as plane observations, None when a frame lacks ``h`` or ``point``."""
    K, step, bias = _extraction_settings(obs)
    out = []
    for k in np.nonzero(data.has_rod[:, leg, rod])[0]:
        h = _rod_field(obs, data, k, leg, rod, "h")
        if h is None or h.shape != (2, 3) or not data.has_point[k, leg, rod]:
            return None
        h = h / np.linalg.norm(h, axis=1, keepdims=True)
        point = data.rod_p[k, leg, rod]
        r = float(h[0] @ point)
        rms = _rod_field(obs, data, k, leg, rod, "rms_px")
        npts = _rod_field(obs, data, k, leg, rod, "n_points")
        if K is not None and rms is not None and npts is not None and rms.shape == (2,) and npts.shape == (2,):
            cov = _rod_field(obs, data, k, leg, rod, "cov_u")
            dh, var = limb_line_noise(
                K, h, point, rms, npts, cov if cov is not None and cov.shape == (3, 3) else None, step, bias
            )
            out.append(PlaneObservation(h, r, dh, var))
        else:
            out.append(PlaneObservation(h, r))
    return out


def _deleted_d2(obs: list[PlaneObservation], keep: np.ndarray) -> np.ndarray:
    """For each kept frame, the drop of the rod's chi-square when the joint is fitted without it, (M,).

    About chi-square(2) for a good frame; a frame whose rod was taken for another edge pulls the fit
    that includes it, and removing it lowers the chi-square most. Frames not kept get NaN.
    """
    out = np.full(len(obs), np.nan)
    idx = np.nonzero(keep)[0]
    total = float(np.sum(joint_from_planes([obs[k] for k in idx])[2]))
    for m in idx:
        out[m] = total - float(np.sum(joint_from_planes([obs[k] for k in idx if k != m])[2]))
    return out


def _trim_rod(obs: list[PlaneObservation], s_rob: float, max_subsets: int = 200) -> np.ndarray:
    """Frames kept (bool, (M,)) for one rod: the fewest dropped (at most M - 3) whose best remaining subset's
    chi-square is within its 99.9% quantile (times ``s_rob``); subsets searched exhaustively while small,
    else the frame whose removal lowers the chi-square most is dropped one at a time."""
    n = len(obs)
    keep = np.ones(n, dtype=bool)
    for k in range(0, n - 2):
        if k > 0:
            subsets = list(itertools.combinations(range(n), n - k))
            if len(subsets) > max_subsets:
                v = _deleted_d2(obs, keep)
                keep[int(np.nanargmax(v))] = False
                cand = keep
            else:
                chis = [float(np.sum(joint_from_planes([obs[i] for i in sub])[2])) for sub in subsets]
                cand = np.zeros(n, dtype=bool)
                cand[list(subsets[int(np.argmin(chis))])] = True
        else:
            cand = keep
        chi = float(np.sum(joint_from_planes([obs[i] for i in np.nonzero(cand)[0]])[2]))
        dof = 2 * int(cand.sum()) - 3
        if dof <= 0 or chi <= chi2_gate(dof) * s_rob or cand.sum() <= 3:
            return cand
        keep = cand.copy()
    return keep


def _gross_single_rods(
    planes: list[list[PlaneObservation]], frames: list[np.ndarray], limit: float
) -> list[np.ndarray]:
    """Frames (bool per observation, one array per rod) of one locked leg that are gross outliers.

    When only one of a leg's rods is found in a frame, the two often overlap in the image and the one
    found may be a mix of both (its width, hence its depth, wrong): such frames can outnumber the good
    ones and agree among themselves. The frames where both rods are seen locate each joint; a
    single rod whose equations miss it by a chi-square above ``limit`` is flagged. Without two frames
    with both rods, nothing is flagged.
    """
    out = [np.zeros(len(planes[j]), dtype=bool) for j in range(2)]
    both = np.intersect1d(frames[0], frames[1])
    if both.size < 2:
        return out
    for j in range(2):
        try:
            X = joint_from_planes([o for o, f in zip(planes[j], frames[j], strict=True) if f in both])[0]
        except IdentifiabilityError:
            continue
        for m, (o, f) in enumerate(zip(planes[j], frames[j], strict=True)):
            if f not in both:
                out[j][m] = float(np.sum((o.h @ X - o.r) ** 2 / o.variances(X))) > limit
        if (~out[j]).sum() < 2:  # too few left for a joint: keep them all
            out[j][:] = False
    return out


def _step1_planes(
    planes: list[list[list[PlaneObservation]]], frames: list[list[np.ndarray]] | None = None
) -> tuple[np.ndarray, np.ndarray, float, list[dict[str, int]], float, list[list[np.ndarray]]]:
    """Step 1 with plane equations: joints (4, 2, 3), covariances (4, 2, 3, 3), chi-square per dof,
    dropped frames (lock phase, rod, index among the rod's frames), the residual RMS (m) and the
    frames kept per rod (bool, [4][2])."""
    absolute = all(o.var is not None for row in planes for rod in row for o in rod)
    # robust noise scale from every frame's chi-square drop; absolute variances: at least 1; relative
    # ones: residuals below a nanometre are never outliers
    pool = np.concatenate(
        [
            _deleted_d2(planes[i][j], np.ones(len(planes[i][j]), dtype=bool))
            for i in range(4)
            for j in range(2)
            if len(planes[i][j]) > 3
        ]
        or [np.zeros(0)]
    )
    s_rob = max(robust_chi2_scale(pool, 2) if pool.size else 0.0, 1.0 if absolute else 1e-18)
    keep = []
    for i in range(4):
        # single rods far off the joint located from the frames with both rods: dropped before trimming
        gross = (
            _gross_single_rods(planes[i], frames[i], 100.0 * float(chi2_gate(2)) * s_rob)
            if frames is not None
            else [np.zeros(len(planes[i][j]), dtype=bool) for j in range(2)]
        )
        row = []
        for j in range(2):
            k_ok = np.nonzero(~gross[j])[0]
            kk = np.zeros(len(planes[i][j]), dtype=bool)
            kk[k_ok[_trim_rod([planes[i][j][m] for m in k_ok], s_rob)]] = True
            row.append(kk)
        keep.append(row)
    rejected = [
        {"lock": i + 1, "rod": j, "frame_of_rod": int(m)}
        for i in range(4)
        for j in range(2)
        for m in np.nonzero(~keep[i][j])[0]
    ]
    fits = [
        [joint_from_planes([o for o, kk in zip(planes[i][j], keep[i][j], strict=True) if kk]) for j in range(2)]
        for i in range(4)
    ]
    P = np.array([[fits[i][j][0] for j in range(2)] for i in range(4)])
    A = np.array([[fits[i][j][1] for j in range(2)] for i in range(4)])
    chi = sum(float(np.sum(fits[i][j][2])) for i in range(4) for j in range(2))
    dof = sum(2 * int(keep[i][j].sum()) - 3 for i in range(4) for j in range(2))
    s2 = chi / dof if dof > 0 else 1.0
    if all(o.var is not None for row in planes for rod in row for o in rod):
        # absolute variances (from the extraction's edge scatter and its edge-bias allowance): a bias
        # common to a rod's frames does not show in the residuals, so they may scale them up, never down
        s2 = max(s2, 1.0)
    sq, n_eq = 0.0, 0
    for i in range(4):
        for j in range(2):
            used = [o for o, kk in zip(planes[i][j], keep[i][j], strict=True) if kk]
            sq += float(sum(np.sum((o.h @ P[i, j] - o.r) ** 2) for o in used))
            n_eq += 2 * len(used)
    return P, s2 * np.linalg.inv(A), s2, rejected, float(np.sqrt(sq / max(n_eq, 1))), keep


def _pair_means(u: np.ndarray, has: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    for k in range(N):
        for leg in range(4):
            if has[k, leg].all():
                U[k, leg], CU[k, leg], pair_d2[k, leg] = _gls_pair(u[k, leg], C[k, leg])
            elif has[k, leg].any():
                j = int(np.argmax(has[k, leg]))
                U[k, leg], CU[k, leg] = unit(u[k, leg, j]), C[k, leg, j]
    return U, CU, pair_d2


def _leg_directions(
    obs: Observations, data: PhaseArrays, direction_std_rad: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool, list[dict[str, int]], np.ndarray]:
    """Per pose and leg: direction (N,4,3), its covariance (N,4,3,3), a rod point (N,4,3), mask (N,4).

    Also whether the covariances are the rods' measured ones (``cov_u``; else ``sigma^2 (I - u u^T)``
    with sigma ``direction_std_rad`` or 1, relative), the rod pairs rejected as disagreeing and the
    rods' covariances (N, 4, 2, 3, 3).
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
    U, CU, pair_d2 = _pair_means(u, has, C)
    has_leg = has.any(axis=2)
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


class _IntrinsicsEffect:
    """The rods' planes and directions as measured through other intrinsics (the camera's error).

    The intrinsics are ``camera + steps^T z`` (``steps`` (n, 8): one standard deviation along each
    principal direction of their covariance, :func:`.intrinsics.principal_steps`); every used rod's
    planes are recomputed from its limb samples (``limbs_px``) for those intrinsics
    (:func:`.intrinsics.limb_planes_for`), its direction as their planes' intersection.
    """

    def __init__(
        self,
        camera: CameraModel,
        steps: np.ndarray,
        lock: list[list[tuple[np.ndarray, np.ndarray]]],
        fit_idx: tuple[np.ndarray, np.ndarray, np.ndarray],
        fit_limbs: np.ndarray,
        fit_h: np.ndarray,
    ) -> None:
        self.camera, self.steps, self.lock = camera, steps, lock
        self.fit_idx, self.fit_limbs, self.fit_h = fit_idx, fit_limbs, fit_h

    @classmethod
    def build(cls, obs: Observations, lock_data: list[PhaseArrays], data: PhaseArrays) -> _IntrinsicsEffect | None:
        """None when the camera's covariance or any rod's ``limbs_px`` or ``h`` is missing."""
        try:
            prior = intr.intrinsics_prior(obs)
        except InputError:  # an extraction camera without its size: no calibration to carry
            return None
        if prior is None:
            return None
        camera, cov = prior
        steps = intr.principal_steps(cov)
        if steps.shape[0] == 0:
            return None

        def fields(
            d: PhaseArrays, ks: np.ndarray, legs: np.ndarray, rods: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray] | None:
            limbs, hs = [], []
            for k, leg, rod in zip(ks, legs, rods, strict=True):
                lm = _rod_field(obs, d, int(k), int(leg), int(rod), "limbs_px")
                h = _rod_field(obs, d, int(k), int(leg), int(rod), "h")
                if lm is None or h is None or lm.ndim != 3 or lm.shape[0] != 2 or h.shape != (2, 3):
                    return None
                limbs.append(lm)
                hs.append(h / np.linalg.norm(h, axis=1, keepdims=True))
            if len({lm.shape for lm in limbs}) > 1:
                return None
            return (np.asarray(limbs), np.asarray(hs)) if limbs else (np.zeros((0, 2, 1, 2)), np.zeros((0, 2, 3)))

        lock = []
        for i, d in enumerate(lock_data):
            row = []
            for j in range(2):
                ks = np.nonzero(d.has_rod[:, i, j])[0]
                f = fields(d, ks, np.full(len(ks), i), np.full(len(ks), j))
                if f is None:
                    return None
                row.append(f)
            lock.append(row)
        idx = np.nonzero(data.has_rod)
        f = fields(data, *idx)
        if f is None:
            return None
        return cls(camera, steps, lock, idx, f[0], f[1])

    def _planes(self, z: np.ndarray, limbs: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Planes for ``z``: the intrinsics' part (its first ``steps`` entries), then, when ``z`` is longer, a
        limb-edge bias common to every rod (outward, per limb, px)."""
        if limbs.shape[0] == 0:
            return h
        n = self.steps.shape[0]
        out = intr.limb_planes_for(intr.perturbed_camera(self.camera, self.steps.T @ z[:n]), limbs, h)
        if z.size > n:
            out = intr.shift_limbs(out, z[n:] / self.camera.focal_px)
        return out

    def lock_planes(
        self, z: np.ndarray, planes: list[list[list[PlaneObservation]]]
    ) -> list[list[list[PlaneObservation]]]:
        """``planes`` (step 1, [4][2] lists) with every plane normal as measured for ``z``."""
        out = []
        for i in range(4):
            row = []
            for j in range(2):
                limbs, h = self.lock[i][j]
                hz = self._planes(z, limbs, h)
                row.append([replace(o, h=hz[m]) for m, o in enumerate(planes[i][j])])
            out.append(row)
        return out

    def rod_u(self, z: np.ndarray, rod_u: np.ndarray) -> np.ndarray:
        """The fit phases' rod directions (N, 4, 2, 3) as measured for ``z``, signed like ``rod_u``."""
        hz = self._planes(z, self.fit_limbs, self.fit_h)
        u = np.cross(hz[:, 0], hz[:, 1])
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        ref = rod_u[self.fit_idx]
        u *= np.where(np.sum(u * ref, axis=1) < 0, -1.0, 1.0)[:, None]
        out = rod_u.copy()
        out[self.fit_idx] = u
        return out


def _gate_poses(pipe: _LegsPipeline, P: np.ndarray, U: np.ndarray, seven: np.ndarray) -> np.ndarray:
    """Poses (bool, (N,)) whose whitened equations exceed their chi-square 99.9% quantile (robust scale)."""
    x, A0, _ = pipe.frame(P)
    Aq, Uo = pipe.oriented(x, A0, U)
    theta = seven[[6, 4, 5]]
    d2 = np.sum(pipe.whitened(theta, Aq, Uo, pipe.y_axis(x, A0)) ** 2, axis=1)
    m = pipe.mask.sum(axis=1)
    used = m > 0
    if used.sum() < 4:
        return np.zeros(len(m), dtype=bool)
    s_rob = robust_chi2_scale(d2[used], m[used])
    if s_rob <= 0:
        return np.zeros(len(m), dtype=bool)
    return used & chi2_outliers(d2, np.maximum(m, 1), s_rob)


def _steps34_covariance(
    pipe: _LegsPipeline, P: np.ndarray, U: np.ndarray, seven: np.ndarray
) -> tuple[np.ndarray, float, int]:
    """GLS covariance (3, 3) of (L, S, D) for unit-scaled weights, the chi-square and its dof."""
    x, A0, _ = pipe.frame(P)
    y = pipe.y_axis(x, A0)
    Aq, Uo = pipe.oriented(x, A0, U)
    theta = seven[[6, 4, 5]]
    J = central_jacobian(lambda t: pipe.whitened(t, Aq, Uo, y).ravel(), theta, h=1e-7)
    r = pipe.whitened(theta, Aq, Uo, y)
    dof = int(pipe.mask.sum()) - 3
    return np.linalg.inv(J.T @ J), float(np.sum(r**2)), dof


def calibrate_legs(
    obs: Observations,
    *,
    fit_phases: tuple[str, ...] = ("poses",),
    direction_std_rad: float | None = None,
    on_iteration: IterationCallback | None = None,
    edge_bias_std_px: float = EDGE_BIAS_STD_PX,
    prior_std_m: float | None = PRIOR_STD_M,
) -> MethodResult:
    """Identify all seven parameters from leg observations only (four steps).

    Parameters
    ----------
    obs : Observations
        Needs rods with points (the rod radius known) in the ``lock-1`` .. ``lock-4`` phases and
        rod directions in the fit phases; uses the rods' ``h``, ``cov_u``, ``rms_px`` and ``n_points``
        (image extraction) when every rod has them (module docstring).
    fit_phases : tuple of str
        Phases used for steps 3 and 4 (the paper reuses the 20-pose set).
    direction_std_rad : float, optional
        Rod direction noise per tangent axis, rad, for rods without ``cov_u``: then taken as known
        (not rescaled by the residuals). Not given: the fit's residual chi-square sets the scale.
    on_iteration : callable, optional
        Receives ``{"stage", "iteration", "cost"}`` after each iteration of the fits of steps 2 and 3-4 (not
        of the uncertainty propagation; :mod:`.iterations`).
    edge_bias_std_px : float
        Standard deviation (px) of a limb-edge bias common to every rod (per limb), propagated into the
        standard deviations like the intrinsics (the combined method estimates it; here it is not
        identifiable apart from the joints and the rod radius).
    prior_std_m : float or None
        Standard deviation (m) of each of the seven parameters around the nominal (a priori) geometry: the
        bench's manufacturing tolerance. Along the directions the legs' data know less well than it (their
        variance above its square), the estimate is combined with it (linear-Gaussian posterior), so that such a
        direction stays near the a priori value with about its tolerance as std instead of wherever the data
        drift (``std_breakdown.a_priori``; ``diagnostics.identifiability``; a warning names the directions);
        elsewhere the data's estimate is kept unchanged (:func:`_with_prior`). None or 0: no prior.

    Returns
    -------
    MethodResult
        With ``parameters`` (seven) and ``parameters_std``.
    """
    nom = obs.nominal
    q_lock = np.zeros(4)
    lock_data = []
    for i in range(4):
        d = obs.arrays(f"lock-{i + 1}")
        if len(d) == 0:
            raise IdentifiabilityError(
                f"the legs method needs the lock-{i + 1} phase (actuator {i + 1} locked)", parameter=f"A{i + 1}"
            )
        spread = float(np.ptp(d.q[:, i]))
        if spread > 1e-4:
            raise IdentifiabilityError(
                f"in phase lock-{i + 1}, q{i + 1} moves by {spread * 1e3:.3f} mm: the actuator is not locked",
                parameter=f"A{i + 1}",
            )
        q_lock[i] = float(np.mean(d.q[:, i]))
        for j in range(2):
            ok = d.has_rod[:, i, j] & d.has_point[:, i, j]
            if ok.sum() < 2:
                raise IdentifiabilityError(
                    f"phase lock-{i + 1}: rod {j} of leg {i + 1} has {int(ok.sum())} observation(s) with a point; "
                    "at least 2 (5 recommended) are needed to locate its joint (rod radius known)",
                    parameter=f"A{i + 1}",
                )
        lock_data.append(d)

    # ---- step 1: the joints
    planes = [[_plane_observations(obs, lock_data[i], i, j) for j in range(2)] for i in range(4)]
    use_planes = all(p is not None for row in planes for p in row)
    rejected_lock: list[dict[str, int]] = []
    if use_planes:
        frames1 = [[np.nonzero(lock_data[i].has_rod[:, i, j])[0] for j in range(2)] for i in range(4)]
        P, covPij, s2_1, rejected_lock, res_rms, keep1 = _step1_planes(planes, frames1)  # type: ignore[arg-type]
        n_lines = sum(len(planes[i][j]) for i in range(4) for j in range(2))  # type: ignore[arg-type]
    else:
        P = np.zeros((4, 2, 3))
        covPij = np.zeros((4, 2, 3, 3))
        Acc = np.zeros((4, 2, 3, 3))
        ss, dof1, n_lines = 0.0, 0, 0
        for i in range(4):
            d = lock_data[i]
            for j in range(2):
                ok = d.has_rod[:, i, j] & d.has_point[:, i, j]
                P[i, j], Acc[i, j], res = intersect_lines(d.rod_p[ok, i, j], d.rod_u[ok, i, j])
                ss += float(np.sum(res**2))
                dof1 += 2 * int(ok.sum()) - 3
                n_lines += int(ok.sum())
        s2_1 = ss / dof1 if dof1 > 0 else 0.0
        covPij = s2_1 * np.linalg.inv(Acc)
        res_rms = float(np.sqrt(s2_1))

    # ---- step 1b: the two rods of a leg are parallel and the same distance apart on every leg: their joints'
    #      separations agree when the joints are right. A leg whose separation is off beyond its covariance has a
    #      joint wrong beyond its std (a rod's frames taken for another edge, a weakly conditioned lock phase):
    #      its joints' covariance is scaled to cover that disagreement
    covPij, pair_check, warnings = _pair_consistency(P, covPij)

    # ---- steps 2-4
    data = obs.arrays(*fit_phases)
    U, CU, pts, has_leg, measured, rejected_pairs, C_rods = _leg_directions(obs, data, direction_std_rad)
    pipe = _LegsPipeline(q_lock, data.q, pts, has_leg, CU, nom)
    U_filled = np.where(has_leg[..., None], U, 0.0)
    # poses judged by a robust fit (each round), then the least-squares fit of the poses kept
    seven = pipe.run(P, U_filled, robust=True)
    rejected_poses: list[int] = []
    for _ in range(5):
        bad = _gate_poses(pipe, P, U_filled, seven)
        if not bad.any() or (pipe.mask.sum() - pipe.mask[bad].sum()) < 6:
            break
        rejected_poses += [int(data.index[k]) for k in np.nonzero(bad)[0]]
        pipe.set_legs(pipe.has_leg & ~bad[:, None])
        seven = pipe.run(P, U_filled, robust=True)
    pipe.W = None
    seven = pipe.run(P, U_filled, on_iteration=on_iteration)
    x2 = np.array([*seven[1:4].tolist(), seven[0]])

    # ---- uncertainty: (i) the joints, propagated through steps 2-4 (numerical derivatives, weights fixed)
    def f(Pv: np.ndarray) -> np.ndarray:
        return pipe.run(Pv, U_filled, x2)

    h = 1e-7
    GP = np.zeros((7, 24))
    for a in range(24):
        dP = np.zeros(24)
        dP[a] = h
        GP[:, a] = (f(P + dP.reshape(4, 2, 3)) - f(P - dP.reshape(4, 2, 3))) / (2 * h)
    covP = np.zeros((24, 24))
    for i in range(4):
        for j in range(2):
            k = (i * 2 + j) * 3
            covP[k : k + 3, k : k + 3] = covPij[i, j]
    cov_joints = GP @ covP @ GP.T
    # (ii) the leg directions of the fit poses: GLS covariance of (L, S, D), scaled by the chi-square
    c34, chi34, dof34 = _steps34_covariance(pipe, P, U_filled, seven)
    s2_34 = 1.0 if (not measured and direction_std_rad is not None) else (chi34 / dof34 if dof34 > 0 else 1.0)
    if measured:  # cov_u is absolute (with the extraction's edge-bias allowance): scaled up, never down
        s2_34 = max(s2_34, 1.0)
    cov_dirs = np.zeros((7, 7))
    idx = np.array([6, 4, 5])
    cov_dirs[np.ix_(idx, idx)] = s2_34 * c34
    # (iii) the camera's intrinsics, common to every frame: the whole estimate redone (frames, gating and
    #       weights fixed) with the rods measured through the intrinsics moved by one standard deviation
    #       along each principal direction of their covariance
    eff = _IntrinsicsEffect.build(obs, lock_data, data) if use_planes else None
    cov_intr = np.zeros((7, 7))
    cov_edge = np.zeros((7, 7))
    if eff is not None:

        def seven_for(z: np.ndarray) -> np.ndarray:
            pz = eff.lock_planes(z, planes)  # type: ignore[arg-type]
            Pz = np.array(
                [
                    [
                        joint_from_planes([o for o, kk in zip(pz[i][j], keep1[i][j], strict=True) if kk])[0]
                        for j in range(2)
                    ]
                    for i in range(4)
                ]
            )
            Uz = _pair_means(eff.rod_u(z, data.rod_u), data.has_rod, C_rods)[0]
            return pipe.run(Pz, np.where(pipe.has_leg[..., None], Uz, 0.0), x2)

        # one standard deviation along each principal direction, then the limb-edge bias common to every rod
        # (per limb, the combined method's prior: shading and optics bias every rod's limb alike, so it does
        # not average out over rods)
        nz = eff.steps.shape[0]
        E = np.zeros((nz + 2, nz + 2))
        E[:nz, :nz] = np.eye(nz)
        E[nz:, nz:] = edge_bias_std_px * np.eye(2)
        Jz = np.stack([(seven_for(e) - seven_for(-e)) / 2.0 for e in E], axis=1)
        cov_intr = Jz[:, :nz] @ Jz[:, :nz].T
        cov_edge = Jz[:, nz:] @ Jz[:, nz:].T
    cov = cov_joints + cov_dirs + cov_intr + cov_edge
    parts7 = {
        "joint_centres": cov_joints,
        "leg_directions": cov_dirs,
        "intrinsics": cov_intr,
        "limb_edge_bias": cov_edge,
    }
    seven_data = seven.copy()
    ident = _identifiability(cov, prior_std_m)
    if prior_std_m:
        seven, cov, parts7 = _with_prior(seven, cov, parts7, nom, prior_std_m)
        if ident["unpinned"]:
            worst = ident["unpinned"][0]
            warnings.append(
                f"the legs' data do not pin {len(ident['unpinned'])} direction(s) of the seven parameters (weakest: "
                f"{worst['label']}, data std {worst['data_std_m'] * 1e3:.1f} mm against the a priori "
                f"{prior_std_m * 1e3:.1f} mm): the result stays near the a priori values there, with their std"
            )
    params = I4Parameters.from_mapping({**dict(zip(PARAMETER_NAMES, seven, strict=True)), "T_per_rad": nom.T_per_rad})
    M = np.array(
        [
            [0, 0, 0, 0, 0, 0, 1],  # L
            [1, 0, 0, 0, 0, -1, 0],  # H - D
            [0, -0.5, 0, 0, 1, 0, 0],  # S - q02/2
            [0, 0, 0.5, -0.5, 1, 0, 0],  # S - (q04 - q03)/2
        ],
        dtype=float,
    )
    cov4 = M @ cov @ M.T
    std7 = {k: float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(PARAMETER_NAMES)}
    combos = params.combinations()
    scale = float(np.sqrt(s2_34)) * (1.0 if measured else (direction_std_rad or 1.0))
    return MethodResult(
        method="legs",
        combinations=combos_dict(np.array([combos[k] for k in COMBINATION_NAMES])),
        combinations_std=std_dict(cov4),
        covariance=cov4,
        residual_rms=res_rms,
        residual_unit="m (rod axis constraint to joint distance)",
        n_observations=n_lines + int(pipe.has_leg.sum()),
        n_poses=len(data) + len(np.concatenate([d.index for d in lock_data])),
        iterations=1,
        converged=True,
        parameters={k: float(v) for k, v in zip(PARAMETER_NAMES, seven, strict=True)},
        parameters_std=std7,
        std_breakdown={
            name: {k: float(np.sqrt(max(c[i, i], 0))) for i, k in enumerate(PARAMETER_NAMES)}
            for name, c in parts7.items()
        },
        warnings=warnings,
        diagnostics={
            "step1": "weighted plane equations" if use_planes else "line intersection (unweighted)",
            "step1_chi2_per_dof": float(s2_1),
            "step1_frames_rejected": rejected_lock,
            "steps34_weighting": "measured rod covariances (GLS)" if measured else "isotropic",
            "steps34_chi2_per_dof": float(s2_34),
            "rod_direction_noise_rad": scale if not measured else None,
            "rod_pairs_rejected": rejected_pairs,
            "poses_rejected": rejected_poses,
            "line_residual_rms_mm": res_rms * 1e3,
            "joint_centres_camera": P.mean(axis=1).tolist(),
            "locked_q": q_lock.tolist(),
            "rod_pair_check": pair_check,
            "identifiability": {
                **ident,
                "prior_std_m": prior_std_m,
                "data_estimate": {k: float(v) for k, v in zip(PARAMETER_NAMES, seven_data, strict=True)},
            },
        },
        residuals=None,
    )


def _pair_consistency(P: np.ndarray, covP: np.ndarray) -> tuple[np.ndarray, list[dict], list[str]]:
    """The two upper joints of each leg against the other legs': their separations (4, 3) must agree.

    Every leg's two rods are the same distance apart along x_B, so ``P[i, 1] - P[i, 0]`` is the same vector for
    the four legs. Each leg's separation is compared with the component-wise median of the four (robust to one
    wrong leg) by its chi-square with 3 dof under the joints' covariance (plus a 1 um floor); beyond the
    chi-square 99.9% quantile times the legs' common scale (the median leg's chi-square over chi-square(3)'s
    median, at least 1) the leg's two joint covariances are scaled by chi-square / 3, so that its std covers
    the disagreement (the joints' error is then visible to the propagation, and the prior can act on it).

    Returns
    -------
    covP : ndarray, shape (4, 2, 3, 3)
        The joints' covariances, scaled where needed.
    check : list of dict
        Per leg: ``separation_mm``, ``deviation_mm`` (from the median), ``chi2``, ``scale``.
    warnings : list of str
    """
    sep = P[:, 1] - P[:, 0]
    ref = np.median(sep, axis=0)
    out = covP.copy()
    check, warnings = [], []
    c2s = []
    for i in range(4):
        e = sep[i] - ref
        C = covP[i, 0] + covP[i, 1] + _PAIR_FLOOR_M**2 * np.eye(3)
        try:
            c2s.append(float(e @ np.linalg.solve(C, e)))
        except np.linalg.LinAlgError:
            c2s.append(float("nan"))
    # the legs' common scale (robust: the median leg's) sets the gate, so that only a leg far beyond the others
    # is flagged; four chi-squares are too few to rescale every leg by
    finite = [c for c in c2s if np.isfinite(c)]
    common = max(1.0, robust_chi2_scale(finite, 3)) if finite else 1.0
    limit = float(chi2_gate(3)) * common
    for i in range(4):
        e = sep[i] - ref
        c2 = c2s[i]
        scale = c2 / 3.0 if np.isfinite(c2) and c2 > limit else 1.0
        out[i] *= scale
        check.append(
            {
                "leg": i + 1,
                "separation_mm": float(np.linalg.norm(sep[i]) * 1e3),
                "deviation_mm": float(np.linalg.norm(e) * 1e3),
                "chi2": c2,
                "scale": scale,
            }
        )
        if scale > 1.0:
            warnings.append(
                f"lock-{i + 1}: the two rods' joints are {np.linalg.norm(sep[i]) * 1e3:.1f} mm apart, "
                f"{np.linalg.norm(e) * 1e3:.1f} mm off the other legs' (chi-square {c2:.0f} for 3 dof): the joints' "
                f"covariance is scaled by {scale:.0f}"
            )
    return out, check, warnings


def _identifiability(cov: np.ndarray, prior_std_m: float | None) -> dict:
    """How well the legs' data pin the seven parameters, per principal direction of their covariance.

    ``information_ratio`` = prior variance / data variance along each direction (sorted, weakest first): below 1
    the a priori tolerance knows that direction better than the data (``unpinned``, labelled by the parameters it
    mostly involves). ``condition_number``: of the data covariance (largest / smallest variance).
    """
    C = 0.5 * (cov + cov.T)
    w, V = np.linalg.eigh(C)
    w = np.maximum(w, 1e-30)
    order = np.argsort(-w)  # weakest (largest variance) first
    ps2 = (prior_std_m or 0.0) ** 2
    dirs = []
    for k in order:
        v = V[:, k] * np.sign(V[np.argmax(np.abs(V[:, k])), k])
        big = np.argsort(-np.abs(v))[:3]
        label = " ".join(f"{v[j]:+.2f} {PARAMETER_NAMES[j]}" for j in big if abs(v[j]) > 0.2)
        dirs.append(
            {
                "direction": {n: float(x) for n, x in zip(PARAMETER_NAMES, v, strict=True)},
                "label": label,
                "data_std_m": float(np.sqrt(w[k])),
                "information_ratio": float(ps2 / w[k]) if ps2 else None,
            }
        )
    return {
        "condition_number": float(w.max() / w.min()),
        "directions": dirs,
        "unpinned": [d for d in dirs if d["information_ratio"] is not None and d["information_ratio"] < 1.0],
    }


def _with_prior(
    seven: np.ndarray, cov: np.ndarray, parts: dict[str, np.ndarray], nom: I4Parameters, prior_std_m: float
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The legs' estimate with the prior N(nominal, prior_std_m^2 I) in the directions the data do not pin.

    Along each principal direction k of the data covariance C (variance w_k): when the data know it better than
    the prior (w_k < prior_std_m^2) the data's estimate is kept as it is (unbiased, and better than the a priori
    value in expectation); otherwise the linear-Gaussian posterior of the two, the data weighed by the factor
    ``a_k = s^2 / (w_k + s^2)``. With ``A = V diag(a) V^T``, ``posterior = A seven + (I - A) nominal``; its error is
    ``A (data error) + (I - A) (nominal - truth)``, hence the covariance ``A C A^T + (I - A) P (I - A)^T``, each data
    part mapped by A and the prior's part named ``a_priori``. In every direction the result is then no worse than
    the a priori value in expectation, and noise-free data still give back the truth exactly.
    """
    nom7 = np.array([getattr(nom, k) for k in PARAMETER_NAMES])
    s2 = prior_std_m**2
    Pp = s2 * np.eye(7)
    C = 0.5 * (cov + cov.T)
    w, V = np.linalg.eigh(C)
    w = np.maximum(w, 0.0)
    a = np.where(w < s2, 1.0, s2 / (w + s2))
    A = (V * a) @ V.T
    post = A @ seven + (np.eye(7) - A) @ nom7
    out = {k: A @ v @ A.T for k, v in parts.items()}
    IA = np.eye(7) - A
    out["a_priori"] = IA @ Pp @ IA.T
    total = sum(out.values())
    return post, 0.5 * (total + total.T), out
