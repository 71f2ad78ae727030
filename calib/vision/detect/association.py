"""Detection step 5: association of leg candidates to legs 1..4 and the camera's placement (weighted Kabsch, linear
translation, Levenberg-Marquardt), with rival hypotheses.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import cast

import numpy as np
from numpy.typing import NDArray

from calib.model.kinematics import dkm, joint_points
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import Rigid, cross, kabsch, matrix_to_rotvec, rotvec_to_matrix
from calib.vision.detect.hypotheses import DetectSettings, Hypothesis, LegCandidate, RodCandidate
from calib.vision.detect.rays import _line_point, _rotation_angle

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
# 5. association and placement
def _kabsch(U: Array, D: Array, w: Array) -> tuple[Array, float]:
    """Rotation R minimising sum w_k |R U_k - D_k|^2 (rows unit vectors) and the weighted RMS misfit.

    With ``w_k = 1 / sigma_k^2`` the misfit is in sigmas.
    """
    R = kabsch(D, U, w)
    r = np.linalg.norm(U @ R.T - D, axis=1)
    return R, float(np.sqrt(np.mean(w * r**2)))


def _assignments(
    model_ang: Array, cand_ang: Array, n_cand: int, min_legs: int, tol: Array
) -> list[tuple[int | None, ...]]:
    """Injective partial maps leg -> candidate whose pairwise angles agree within tol."""
    out: list[tuple[int | None, ...]] = []

    def rec(leg: int, cur: list[int | None]) -> None:
        if leg == 4:
            if sum(c is not None for c in cur) >= min_legs:
                out.append(tuple(cur))
            return
        if sum(c is None for c in cur) < 4 - min_legs:
            rec(leg + 1, [*cur, None])
        for k in range(n_cand):
            if k in cur:
                continue
            if all(c is None or abs(cand_ang[k, c] - model_ang[leg, lg]) < tol[k, c] for lg, c in enumerate(cur)):
                rec(leg + 1, [*cur, k])

    rec(0, [])
    return out


def _rod_model(nominal: I4Parameters, q: Array, spacing: float) -> tuple[Array, Array]:
    """Rod top points (4, 2, 3) and leg directions (4, 3), base frame."""
    pose = dkm(nominal, q)
    A, B = joint_points(nominal, q[None], pose[None])
    u = B[0] - A[0]
    u = u / np.linalg.norm(u, axis=1)[:, None]
    off = np.array([-0.5, 0.5])[:, None] * spacing * np.array([1.0, 0.0, 0.0])
    return A[0][:, None, :] + off[None], u


class _Fitter:
    """Limb end-point residuals (ideal px) of assigned rods for a placement (vectorised over rods)."""

    def __init__(self, rods: list[RodCandidate], tops: Array, u: Array, radius: float, K: Array) -> None:
        self.rods = rods
        self.tops = tops
        self.u = u
        self.r = radius
        self.K = K
        self.KiT = np.linalg.inv(K).T
        self.Ki = cast("Array", np.linalg.inv(K))  # float64 (numpy's stubs: any floating)
        # per rod candidate: limb end points (2 limbs, 2 ends, homogeneous) and limb planes
        self.ends = (
            np.array(
                [
                    [[np.append(_line_point(limb, s_, rc.t), 1.0) for s_ in (rc.s0, rc.s1)] for limb in rc.limbs]
                    for rc in rods
                ]
            )
            if rods
            else np.zeros((0, 2, 2, 3))
        )
        self.h = np.array([np.vstack(rc.h) for rc in rods]) if rods else np.zeros((0, 2, 3))

    def setup(self, legs: dict[int, tuple[int, int]]) -> tuple[Array, Array, Array]:
        """Model tops (M, 3), leg directions (M, 3) and candidate indices (M,) of the assigned rods."""
        idx, tops, us = [], [], []
        for leg, pair in legs.items():
            for rod, ci in enumerate(pair):
                idx.append(ci)
                tops.append(self.tops[leg, rod])
                us.append(self.u[leg])
        return np.asarray(tops), np.asarray(us), np.asarray(idx, dtype=int)

    def predicted_planes(self, X: Array, tops: Array, us: Array) -> tuple[Array, Array]:
        """Predicted limb planes (P, M, 2, 3) and the camera-centre distance to each axis (P, M).

        ``X`` (P, 6): rotation vectors and translations of P placements.
        """
        R = rotvec_to_matrix(X[:, :3])  # (P, 3, 3)
        P = np.einsum("pij,mj->pmi", R, tops) + X[:, None, 3:]  # (P, M, 3)
        U = np.einsum("pij,mj->pmi", R, us)
        p = P - np.sum(P * U, axis=-1)[..., None] * U
        d = np.linalg.norm(p, axis=-1)
        e1 = p / d[..., None]
        e2 = cross(U, e1)
        c = np.clip(self.r / d, 0.0, 0.999)[..., None]
        sn = np.sqrt(1.0 - c * c)
        return np.stack([c * e1 + sn * e2, c * e1 - sn * e2], axis=-2), d

    def residuals(self, X: Array, tops: Array, us: Array, idx: Array) -> Array:
        """Signed distances (ideal px) of the measured limb end points to the predicted limb lines.

        ``X`` (P, 6) -> (P, M * 4); each measured limb is matched to the predicted limb whose
        interpretation plane it is closest to.
        """
        h, _ = self.predicted_planes(X, tops, us)
        lines = h @ self.KiT.T  # (P, M, 2, 3): l = K^-T h
        lines = lines / np.linalg.norm(lines[..., :2], axis=-1)[..., None]
        hd = self.h[idx][None]  # measured planes (1, M, 2, 3)
        straight = np.sum(hd * h, axis=(-2, -1))
        crossed = np.sum(hd * h[..., ::-1, :], axis=(-2, -1))
        lines = np.where((crossed > straight)[..., None, None], lines[..., ::-1, :], lines)
        ends = self.ends[idx]  # (M, 2 limbs, 2 ends, 3)
        return np.einsum("pmkj,mkej->pmke", lines, ends).reshape(len(X), -1)


def _levenberg_marquardt(
    f: Callable[[Array], Array], x0: Array, steps: Array, iters: int = 40, tol: float = 1e-6
) -> tuple[Array, Array]:
    """Minimise |f(x)|^2, f batched ((P, n) -> (P, m)): each forward-difference Jacobian is one call.

    Returns the solution (n,) and its residuals (m,); stops when a step is below ``tol`` in every
    coordinate or none decreases the cost.
    """
    x = x0.astype(np.float64).copy()
    r = f(x[None])[0]
    cost = float(r @ r)
    lam = 1e-3
    eye = np.diag(steps)
    for _ in range(iters):
        F = f(np.vstack([x[None], x[None] + eye]))
        r = F[0]
        J = (F[1:] - r[None]) / steps[:, None]  # (n, m)
        A = J @ J.T
        g = J @ r
        improved = False
        for _ in range(8):
            try:
                dx = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            rn = f((x + dx)[None])[0]
            cn = float(rn @ rn)
            if np.isfinite(cn) and cn < cost:
                x, r, cost = x + dx, rn, cn
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or np.all(np.abs(dx) < tol):
            break
    return x, r


def _differences(best: Hypothesis, other: Hypothesis) -> tuple[bool, set[int]]:
    """How ``other`` labels the rods differently from ``best``.

    Returns
    -------
    legs_swapped : bool
        Some rod candidate belongs to another leg, or some leg to another rod pair.
    orders : set of int
        Legs (0-based) whose two rods are the same pair in the other order.
    """
    la, lb = best.labels(), other.labels()
    swapped = any(c in lb and lb[c][0] != v[0] for c, v in la.items())
    orders = set()
    for leg in set(best.legs) & set(other.legs):
        if set(best.legs[leg]) != set(other.legs[leg]):
            swapped = True
        elif best.legs[leg] != other.legs[leg]:
            orders.add(leg)
    return swapped, orders


def associate(
    rods: list[RodCandidate],
    legs_c: list[LegCandidate],
    nominal: I4Parameters,
    q: Array,
    radius: float,
    spacing: float,
    K: Array,
    settings: DetectSettings,
    prior: Rigid | None = None,
) -> tuple[list[Hypothesis], list[Hypothesis]]:
    """Accepted hypotheses (legs -> rod candidates, placement), best first, and the best's rivals.

    A rival labels the rods differently and explains them about as well (see :func:`_rivals`).
    Stages: rotation seeds (:func:`_rotation_seeds`), a quick linear placement of each
    (:func:`_quick_placements`), the best few refined (:func:`_refined_hypotheses`), duplicates merged.

    Parameters
    ----------
    rods : list of RodCandidate
        Rod candidates of the frame (ideal px).
    legs_c : list of LegCandidate
        Leg candidates among them.
    nominal : I4Parameters
        The nominal model (metres, radians).
    q : ndarray, shape (4,)
        Encoder values of the frame (metres).
    radius : float
        Rod radius (metres).
    spacing : float
        Distance between the axes of a leg's two rods (metres).
    K : ndarray, shape (3, 3)
        Camera matrix (px).
    settings : DetectSettings
        Tolerances and counts of the association.
    prior : Rigid, optional
        A known ``camera_from_base`` (metres, radians): hypotheses rotated farther than
        ``settings.prior_tol_rad`` from it are dropped.

    Returns
    -------
    accepted : list of Hypothesis
        Best first.
    rivals : list of Hypothesis
        Hypotheses that label the rods differently from the best and fit about as well.
    """
    tops, u = _rod_model(nominal, q, spacing)
    if len(legs_c) < settings.min_legs:
        return [], []
    seeds = _rotation_seeds(rods, legs_c, u, settings, prior)
    fitter = _Fitter(rods, tops, u, radius, K)
    quick = _quick_placements(fitter, seeds, legs_c, rods, radius)
    hyps = _refined_hypotheses(fitter, quick, radius, settings, prior)
    uniq = _unique(hyps)
    if not uniq:
        return [], []
    return uniq, _rivals(uniq, fitter, radius, settings)


#: a rotation seed: (Kabsch misfit in sigmas, leg -> candidate map, rotation base -> camera (3, 3))
_Seed = tuple[float, tuple[int | None, ...], Array]
#: a quick placement: (legs assigned, RMS px of the linear placement, Kabsch misfit, leg -> rod pair, x0 (6,))
_Quick = tuple[int, float, float, dict[int, tuple[int, int]], Array]


def _rotation_seeds(
    rods: list[RodCandidate],
    legs_c: list[LegCandidate],
    u: Array,
    settings: DetectSettings,
    prior: Rigid | None,
) -> list[_Seed]:
    """Assignments of leg candidates to legs whose directions agree, each with its signs' Kabsch rotation.

    ``u``: the model's leg directions (4, 3), base frame.
    """
    D = np.array([lc.d for lc in legs_c])
    cand_ang = np.arccos(np.clip(np.abs(D @ D.T), 0.0, 1.0))
    model_ang = np.arccos(np.clip(np.abs(u @ u.T), 0.0, 1.0))
    sig = np.array([np.hypot(lc.sigma, settings.model_direction_rad) for lc in legs_c])
    tol = settings.pair_angle_tol_rad + 3.0 * (sig[:, None] + sig[None, :])
    seeds: list[_Seed] = []
    for mp in _assignments(model_ang, cand_ang, len(legs_c), settings.min_legs, tol):
        legs = [lg for lg in range(4) if mp[lg] is not None]
        cand = cast("list[int]", [mp[lg] for lg in legs])  # legs: those mp assigns a candidate to
        # no two candidates may share a rod; one polarity for all rods
        used = [r for k in cand for r in legs_c[k].rods]
        if len(set(used)) != len(used) or len({rods[r].bright for r in used}) > 1:
            continue
        for signs in itertools.product((1.0, -1.0), repeat=len(legs)):
            R, res = _kabsch(u[legs], D[cand] * np.asarray(signs)[:, None], 1.0 / sig[cand] ** 2)
            if res > settings.kabsch_tol:
                continue
            if prior is not None and _rotation_angle(R, prior.R) > settings.prior_tol_rad:
                continue
            seeds.append((res, mp, R))
    return seeds


def _quick_placements(
    fitter: _Fitter, seeds: list[_Seed], legs_c: list[LegCandidate], rods: list[RodCandidate], radius: float
) -> list[_Quick]:
    """Every seed (and rod-order variant) with its linear translation and a quick residual, duplicates once."""
    quick: list[_Quick] = []
    seen: set[tuple] = set()
    for res, mp, R in sorted(seeds, key=lambda x: x[0]):
        for lv in _rod_orders(mp, legs_c, rods, R[:, 0], fitter.Ki):
            key = (tuple(sorted(lv.items())), tuple(np.round(matrix_to_rotvec(R), 1)))
            if key in seen:
                continue
            seen.add(key)
            x0 = _initial(fitter, lv, R, radius)
            r0 = fitter.residuals(x0[None], *fitter.setup(lv))[0]
            quick.append((len(lv), float(np.sqrt(np.mean(r0**2))), res, lv, x0))
    return quick


def _refined_hypotheses(
    fitter: _Fitter, quick: list[_Quick], radius: float, settings: DetectSettings, prior: Rigid | None
) -> list[Hypothesis]:
    """The best ``settings.max_hypotheses`` quick placements of each leg count refined and kept when they fit,
    sorted by legs (most first) then RMS."""
    hyps: list[Hypothesis] = []
    for n in sorted({qk[0] for qk in quick}, reverse=True):
        group = sorted((qk for qk in quick if qk[0] == n), key=lambda qk: qk[1])
        for _, _, res, lv, x0 in group[: settings.max_hypotheses]:
            h = _solve_placement(fitter, lv, x0, radius)
            if h is None or h.rms_px > settings.max_rms_px:
                continue
            if prior is not None and _rotation_angle(h.camera_from_base.R, prior.R) > settings.prior_tol_rad:
                continue
            h.kabsch_misfit = res
            hyps.append(h)
    hyps.sort(key=lambda h: (-len(h.legs), h.rms_px))
    return hyps


def _unique(hyps: list[Hypothesis]) -> list[Hypothesis]:
    """The same labels and about the same placement: one hypothesis (the first)."""
    uniq: list[Hypothesis] = []
    for h in hyps:
        if any(h.legs == g.legs and _rotation_angle(h.camera_from_base.R, g.camera_from_base.R) < 0.05 for g in uniq):
            continue
        uniq.append(h)
    return uniq


def _rivals(hyps: list[Hypothesis], fitter: _Fitter, radius: float, settings: DetectSettings) -> list[Hypothesis]:
    """Hypotheses that label the rods differently and fit about as well as the best.

    "About as well": RMS <= ``ambiguity_ratio`` x the best's + ``ambiguity_px``. A rival with one
    leg fewer is compared with the best refitted on the legs they share (fewer legs fit better).
    """
    best = hyps[0]
    x_best = np.concatenate([matrix_to_rotvec(best.camera_from_base.R), best.camera_from_base.t])
    out = []
    for h in hyps[1:]:
        swapped, orders = _differences(best, h)
        if (not swapped and not orders) or len(h.legs) < len(best.legs) - 1:
            continue
        ref = best.rms_px
        shared = set(h.labels())
        common = {lg: pair for lg, pair in best.legs.items() if set(pair) <= shared}
        if 2 <= len(common) < len(best.legs):
            sub = _solve_placement(fitter, common, x_best, radius)
            if sub is not None:
                ref = sub.rms_px
        if h.rms_px <= settings.ambiguity_ratio * ref + settings.ambiguity_px:
            out.append(h)
    return out


def _rod_orders(
    mp: tuple[int | None, ...], legs_c: list[LegCandidate], rods: list[RodCandidate], xb: Array, K_inv: Array
) -> list[dict[int, tuple[int, int]]]:
    """Leg -> (rod0, rod1) candidates, rod0 on the -x_B side (both orders when it cannot be told).

    Rod j is on the +x_B side of rod i when the ray to j's image and x_B (camera frame) lie on the
    same side of i's axis plane: directions only, no depth needed.
    """
    legs: dict[int, tuple[int, int]] = {}
    unsure = []
    for lg in range(4):
        k = mp[lg]
        if k is None:
            continue
        i, j = legs_c[k].rods
        ray_j = K_inv @ np.append(0.5 * (rods[j].centre[0] + rods[j].centre[1]), 1.0)
        side_x = float(rods[i].m @ xb)
        side_j = float(rods[i].m @ (ray_j / np.linalg.norm(ray_j)))
        legs[lg] = (i, j) if side_x * side_j > 0 else (j, i)
        if abs(side_x) < 0.1:
            unsure.append(lg)
    variants = [legs]
    for lg in unsure:
        variants += [{**v, lg: v[lg][::-1]} for v in variants]
    return variants


def _initial(fitter: _Fitter, legs: dict[int, tuple[int, int]], R: Array, radius: float) -> Array:
    """Rotation vector and the linear translation: h . (R top + t) = r for every limb plane h."""
    tops, _, idx = fitter.setup(legs)
    H = fitter.h[idx].reshape(-1, 3)
    b = radius - np.einsum("mkj,mj->mk", fitter.h[idx], tops @ R.T).ravel()
    t, *_ = np.linalg.lstsq(H, b, rcond=None)
    return np.concatenate([matrix_to_rotvec(R), t])


def _solve_placement(fitter: _Fitter, legs: dict[int, tuple[int, int]], x0: Array, radius: float) -> Hypothesis | None:
    """Refine a placement on the assigned rods' limb lines; None when it puts a rod behind the camera."""
    tops, us, idx = fitter.setup(legs)
    x, r = _levenberg_marquardt(lambda X: fitter.residuals(X, tops, us, idx), x0, np.full(6, 1e-6))
    if not np.all(np.isfinite(r)):
        return None
    C = Rigid(rotvec_to_matrix(x[:3]), x[3:])
    _, d = fitter.predicted_planes(x[None], tops, us)
    if np.any(d <= radius):
        return None
    # the axis point seen at the middle of each rod's image must be in front of the camera
    P = tops @ C.R.T + C.t
    U = us @ C.R.T
    for k, ci in enumerate(idx):
        rc = fitter.rods[ci]
        ray = fitter.Ki @ np.append(0.5 * (rc.centre[0] + rc.centre[1]), 1.0)
        # closest points of the axis P + a U and of the ray b ray
        A2 = np.array([[U[k] @ U[k], -U[k] @ ray], [U[k] @ ray, -ray @ ray]])
        try:
            _, lam = np.linalg.solve(A2, np.array([-(P[k] @ U[k]), -(P[k] @ ray)]))
        except np.linalg.LinAlgError:
            return None
        if lam <= 0:
            return None
    return Hypothesis(legs, C, float(np.sqrt(np.mean(r**2))), 0.0)
