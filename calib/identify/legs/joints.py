"""Step 1 of the legs method: each leg's joint centres from the rods' limb (interpretation) planes over the poses of a
locked actuator, the planes' noise model and the trimming of outlying rods.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from calib.errors import IdentifiabilityError
from calib.formats.observations import LEG_KEYS, Observations, PhaseArrays, RodArrayField
from calib.numerics.robust import chi2_gate, robust_chi2_scale
from calib.numerics.transforms import cross, unit


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
        Variances of each limb line's angle (rad^2) and offset (px^2), independent between frames.
    """

    h: np.ndarray
    r: float
    dh: np.ndarray | None = None
    var: np.ndarray | None = None

    def variances(self, X: np.ndarray) -> np.ndarray:
        """Variances (2,) of the two equations ``h_q . X - r`` at X (m^2; 1 without a noise model).

        Parameters
        ----------
        X : ndarray, shape (3,)
            A point on the rod's axis, camera frame, m.

        Returns
        -------
        ndarray, shape (2,)
            The variances, m^2 (dimensionless ones without a noise model).
        """
        if self.dh is None or self.var is None:
            return np.ones(2)
        g = self.dh @ X  # (2, 2)
        return np.sum(g**2 * self.var, axis=1) + 1e-30


def planes_direction_covariance(h: np.ndarray, dh: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Covariance of ``u = normalize(h1 x h2)`` from independent perturbations of the two planes.

    Parameters
    ----------
    h : ndarray, shape (2, 3)
        The planes' unit normals.
    dh : ndarray, shape (2, 2, 3)
        Per plane, its change per unit of its two noise parameters (angle, rad; offset, px).
    var : ndarray, shape (2, 2)
        Their variances (rad^2, px^2).

    Returns
    -------
    ndarray, shape (3, 3)
        The direction's covariance, rad^2.
    """
    m = cross(h[0], h[1])
    nm = float(np.linalg.norm(m))
    u = m / nm
    Pu = np.eye(3) - np.outer(u, u)
    C = np.zeros((3, 3))
    for q in range(2):
        for p in range(2):
            dm = cross(dh[0, p], h[1]) if q == 0 else cross(h[0], dh[1, p])
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
    frame_bias: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise model of a rod's two limb lines: plane-normal derivatives and line variances.

    Each limb line (image, ideal pixels: ``l ~ K^-T h``) is perturbed by a rotation about its
    centroid (the foot of the rod point's image on it) and a shift along its normal. The variances
    are those of a TLS line through ``n_points`` edge points ``step_px`` apart with residual RMS
    ``rms_px`` (angle ``s^2 / sum t^2``, offset ``s^2 / N``) plus a slowly varying edge bias
    (``edge_bias_px`` end to end); with ``cov_u`` they are scaled so that the direction covariance
    they imply has the trace of ``cov_u`` (which accounts for the edges' correlation along a limb).

    ``frame_bias=False`` (the legs method's lock phases): the edge bias is left out and the edge scatter's variances
    are scaled so that with the bias they would give ``cov_u``'s trace (never below the scatter's own). In a lock
    phase the rod barely moves against its background and light, so its edge bias does not vary between the frames:
    counted per frame it weighs the frames as if it averaged out, which inflates the joint's std along the rod
    (where the frames' independent noise decides) and says nothing of the bias itself, which the method propagates
    apart (``std_breakdown.limb_edge_bias``). Left out, the lock phases' plane residuals have a chi-square per dof
    near 1 and the joints' errors along their weakest direction match their std; counted per frame, both fall well
    below (the std is overstated).

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
    frame_bias : bool
        Count the edge bias in each frame's variances (False: leave it out and scale the scatter to ``cov_u``).

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
    bias = np.zeros((2, 2))
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
        var[q] = [s2 / st2, s2 / npts]
        bias[q] = [(edge_bias_px / span) ** 2, (0.5 * edge_bias_px) ** 2]
    if frame_bias:
        var = var + bias
        if cov_u is not None:
            tm = float(np.trace(planes_direction_covariance(h, dh, var)))
            if tm > 0 and np.all(np.isfinite(cov_u)):
                var = var * (float(np.trace(cov_u)) / tm)
    elif cov_u is not None and np.all(np.isfinite(cov_u)):
        t_noise = float(np.trace(planes_direction_covariance(h, dh, var)))
        t_bias = float(np.trace(planes_direction_covariance(h, dh, bias)))
        if t_noise > 0:
            var = var * max((float(np.trace(cov_u)) - t_bias) / t_noise, 1.0)
    return dh, var


def joint_from_planes(obs: list[PlaneObservation], iterations: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares point X of ``h_q . X = r`` over a rod's frames.

    Parameters
    ----------
    obs : list of PlaneObservation
        At least 2 frames.
    iterations : int
        Re-weighting passes (the equations' variances depend on X).

    Returns
    -------
    X : ndarray, shape (3,)
        Metres, camera frame.
    normal_matrix : ndarray, shape (3, 3)
        ``sum w h h^T`` with ``w`` the inverse equation variances; X's covariance is its inverse
        (times the chi-square scale when the variances are relative).
    d2 : ndarray, shape (M,)
        Each frame's two residuals squared, each divided by its variance, summed.

    Raises
    ------
    IdentifiabilityError
        The planes do not locate the point (the rod barely moved between the frames).
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


def _rod_field(
    obs: Observations, data: PhaseArrays, k: int | np.integer, leg: int, rod: int, name: RodArrayField
) -> np.ndarray | None:
    """A declared array field of one rod (``h``, ``cov_u``, ``rms_px``, ``n_points``, ``limbs_px``; see
    :class:`calib.formats.observations.Rod`: shape and finite values checked on reading) as float64, or None when the
    rod
    or the field is absent."""
    frame = obs.frames[int(data.index[k])]
    rods = frame.legs.get(LEG_KEYS[leg]) if frame.legs else None
    if not rods or rod >= len(rods):
        return None
    r = rods[rod]
    if r is None:
        return None
    v = getattr(r, name)
    return None if v is None else np.asarray(v, dtype=np.float64)


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
                K, h, point, rms, npts, cov if cov is not None and cov.shape == (3, 3) else None, step, bias, False
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


@dataclass(frozen=True)
class Step1Planes:
    """Step 1's joints from the lock phases' plane equations.

    Attributes
    ----------
    P : ndarray, shape (4, 2, 3)
        The upper joints (leg, rod), camera frame, m.
    cov : ndarray, shape (4, 2, 3, 3)
        Their covariances, m^2 (scaled by ``s2``).
    s2 : float
        The chi-square per dof that scales them (at least 1 with absolute variances).
    rejected : list of dict
        Dropped frames: lock phase (1-4), rod (0-1), index among the rod's frames.
    residual_rms_m : float
        RMS of the kept equations' residuals, m.
    keep : list of list of ndarray of bool
        The frames kept per rod, [4][2].
    s2_raw : float
        The residuals' chi-square per dof (before the floor at 1 of absolute variances).
    """

    P: np.ndarray
    cov: np.ndarray
    s2: float
    rejected: list[dict[str, int]]
    residual_rms_m: float
    keep: list[list[np.ndarray]]
    s2_raw: float


def step1_planes(
    planes: list[list[list[PlaneObservation]]], frames: list[list[np.ndarray]] | None = None
) -> Step1Planes:
    """Step 1 with plane equations: every rod's joint by weighted least squares over its lock phase's frames, gross
    single rods and outlying frames dropped against a robust noise scale.

    Parameters
    ----------
    planes : list of list of list of PlaneObservation
        Per lock phase i (leg i locked) and rod j, the rod's frames ([4][2] lists).
    frames : list of list of ndarray of int, optional
        Per lock phase and rod, the frame index of each observation (to find the frames with both rods); None: no
        single-rod check.

    Returns
    -------
    Step1Planes
    """
    absolute = _absolute_variances(planes)
    s_rob = _step1_noise_scale(planes, absolute)
    keep = [_kept_frames(planes[i], None if frames is None else frames[i], s_rob) for i in range(4)]
    rejected = [
        {"lock": i + 1, "rod": j, "frame_of_rod": int(m)}
        for i in range(4)
        for j in range(2)
        for m in np.nonzero(~keep[i][j])[0]
    ]
    fits = [[joint_from_planes(_kept(planes[i][j], keep[i][j])) for j in range(2)] for i in range(4)]
    P = np.array([[fits[i][j][0] for j in range(2)] for i in range(4)])
    A = np.array([[fits[i][j][1] for j in range(2)] for i in range(4)])
    chi = sum(float(np.sum(fits[i][j][2])) for i in range(4) for j in range(2))
    dof = sum(2 * int(keep[i][j].sum()) - 3 for i in range(4) for j in range(2))
    s2 = chi / dof if dof > 0 else 1.0
    s2_raw = s2
    if _absolute_variances(planes):
        # absolute variances (from the extraction's edge scatter): what the residuals show beyond it scales them
        # up; never down (an under-dispersed lock phase of few frames is no evidence of less noise)
        s2 = max(s2, 1.0)
    rms = _step1_residual_rms(planes, keep, P)
    return Step1Planes(P, s2 * np.linalg.inv(A), s2, rejected, rms, keep, s2_raw)


def _absolute_variances(planes: list[list[list[PlaneObservation]]]) -> bool:
    """Every plane observation carries its variances (from the extraction's edge scatter)."""
    return all(o.var is not None for row in planes for rod in row for o in rod)


def _kept(obs: list[PlaneObservation], keep: np.ndarray) -> list[PlaneObservation]:
    return [o for o, kk in zip(obs, keep, strict=True) if kk]


def _step1_noise_scale(planes: list[list[list[PlaneObservation]]], absolute: bool) -> float:
    """Robust noise scale from every frame's chi-square drop; absolute variances: at least 1; relative ones: residuals
    below a nanometre are never outliers."""
    pool = np.concatenate(
        [
            _deleted_d2(planes[i][j], np.ones(len(planes[i][j]), dtype=bool))
            for i in range(4)
            for j in range(2)
            if len(planes[i][j]) > 3
        ]
        or [np.zeros(0)]
    )
    return max(robust_chi2_scale(pool, 2) if pool.size else 0.0, 1.0 if absolute else 1e-18)


def _kept_frames(row: list[list[PlaneObservation]], frames: list[np.ndarray] | None, s_rob: float) -> list[np.ndarray]:
    """One lock phase's frames kept per rod (bool, [2]): single rods far off the joint located from the frames with
    both rods dropped first, then each rod trimmed (:func:`_trim_rod`)."""
    gross = (
        _gross_single_rods(row, frames, 100.0 * float(chi2_gate(2)) * s_rob)
        if frames is not None
        else [np.zeros(len(row[j]), dtype=bool) for j in range(2)]
    )
    out = []
    for j in range(2):
        k_ok = np.nonzero(~gross[j])[0]
        kk = np.zeros(len(row[j]), dtype=bool)
        kk[k_ok[_trim_rod([row[j][m] for m in k_ok], s_rob)]] = True
        out.append(kk)
    return out


def _step1_residual_rms(
    planes: list[list[list[PlaneObservation]]], keep: list[list[np.ndarray]], P: np.ndarray
) -> float:
    """RMS (m) of the kept plane equations' residuals at the joints ``P`` (4, 2, 3)."""
    sq, n_eq = 0.0, 0
    for i in range(4):
        for j in range(2):
            used = _kept(planes[i][j], keep[i][j])
            sq += float(sum(np.sum((o.h @ P[i, j] - o.r) ** 2) for o in used))
            n_eq += 2 * len(used)
    return float(np.sqrt(sq / max(n_eq, 1)))


def _step1_planes(
    planes: list[list[list[PlaneObservation]]], frames: list[list[np.ndarray]] | None = None
) -> tuple[np.ndarray, np.ndarray, float, list[dict[str, int]], float, list[list[np.ndarray]], float]:
    """:func:`step1_planes` as a tuple ``(P, cov, s2, rejected, residual_rms_m, keep, s2_raw)``."""
    r = step1_planes(planes, frames)
    return r.P, r.cov, r.s2, r.rejected, r.residual_rms_m, r.keep, r.s2_raw
