"""The legs method's uncertainty beyond the measurement noise: the camera intrinsics' effect, the rod-pair consistency
check, identifiability per direction and the a priori tolerance.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from calib.errors import InputError
from calib.formats.camera import CameraModel
from calib.formats.observations import Observations, PhaseArrays
from calib.identify import intrinsics as intr
from calib.identify.legs.constants import _PAIR_FLOOR_M
from calib.identify.legs.joints import PlaneObservation, _rod_field
from calib.model.parameters import PARAMETER_NAMES, I4Parameters
from calib.numerics.robust import chi2_gate, robust_chi2_scale
from calib.numerics.transforms import cross


class IntrinsicsEffect:
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
        fit_idx: tuple[np.ndarray, ...],  # (frame, leg, rod) indices of the used rods (np.nonzero)
        fit_limbs: np.ndarray,
        fit_h: np.ndarray,
    ) -> None:
        self.camera, self.steps, self.lock = camera, steps, lock
        self.fit_idx, self.fit_limbs, self.fit_h = fit_idx, fit_limbs, fit_h

    @classmethod
    def build(cls, obs: Observations, lock_data: list[PhaseArrays], data: PhaseArrays) -> IntrinsicsEffect | None:
        """The effect of the intrinsics on the lock phases' and fit poses' rods, or None when the camera's covariance or
        any rod's ``limbs_px`` or ``h`` is missing.

        Parameters
        ----------
        obs : Observations
            The observations (the extraction's camera and its covariance, the rods' fields).
        lock_data : list of PhaseArrays
            The four lock phases' frames.
        data : PhaseArrays
            The fit poses' frames.

        Returns
        -------
        IntrinsicsEffect or None
            The effect.
        """
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
        cam = intr.perturbed_camera(self.camera, self.steps.T @ z[:n])
        if z.size <= n or not np.any(z[n:]):
            return intr.limb_planes_for(cam, limbs, h)
        # the edge bias in image pixels (where the detector makes it), as the combined method models it
        xn = cam.undistort_points(limbs.reshape(-1, 2)).reshape(limbs.shape)
        xn = xn + z[n:][None, :, None, None] * intr.outward_shift_normalized(cam, limbs)
        return intr.planes_through(xn, h)

    def lock_planes(
        self, z: np.ndarray, planes: list[list[list[PlaneObservation]]]
    ) -> list[list[list[PlaneObservation]]]:
        """``planes`` (step 1, [4][2] lists) with every plane normal as measured for ``z``.

        Parameters
        ----------
        z : ndarray, shape (n,) or (n + 2,)
            Intrinsics in standard deviations along their principal directions, then optionally the limb-edge bias per
            limb, px.
        planes : list of list of list of PlaneObservation
            Step 1's planes, per leg and rod, one per frame.

        Returns
        -------
        list of list of list of PlaneObservation
            The same with their normals moved.
        """
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
        """The fit phases' rod directions (N, 4, 2, 3) as measured for ``z``, signed like ``rod_u``.

        Parameters
        ----------
        z : ndarray, shape (n,) or (n + 2,)
            Intrinsics in standard deviations along their principal directions, then optionally the limb-edge bias per
            limb, px.
        rod_u : ndarray, shape (N, 4, 2, 3)
            The measured rod directions, unit.

        Returns
        -------
        ndarray, shape (N, 4, 2, 3)
            The directions, unit (the unused rods' as given).
        """
        hz = self._planes(z, self.fit_limbs, self.fit_h)
        u = cross(hz[:, 0], hz[:, 1])
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        ref = rod_u[self.fit_idx]
        u *= np.where(np.sum(u * ref, axis=1) < 0, -1.0, 1.0)[:, None]
        out = rod_u.copy()
        out[self.fit_idx] = u
        return out


def joint_depth_systematic(P: np.ndarray, std_m: float, leg_share: float) -> np.ndarray:
    """Covariance (24, 24) of the lock phases' joints' systematic error along their lines of sight.

    Parameters
    ----------
    P : ndarray, shape (4, 2, 3)
        The joints (leg, rod), camera frame, metres.
    std_m : float
        RMS of each joint's systematic error along its line of sight, metres (:data:`.constants.JOINT_DEPTH_SYS_M`).
    leg_share : float
        The share of its variance common to a leg's two joints, within [0, 1]; none is common between legs.

    Returns
    -------
    ndarray, shape (24, 24)
        In the (leg, rod, xyz) order of the method's joints, m^2.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (4, 2, 3):
        raise ValueError(f"P must have shape (4, 2, 3), got {P.shape}")
    if not (np.isfinite(std_m) and std_m >= 0 and 0.0 <= leg_share <= 1.0):
        raise ValueError(f"std_m must be finite and >= 0 and leg_share within [0, 1], got {std_m}, {leg_share}")
    los = (P / np.linalg.norm(P, axis=-1, keepdims=True)).reshape(8, 3)
    # the eight joints' correlation: 1 on the diagonal, leg_share between a leg's two joints, 0 between legs
    R = np.kron(np.eye(4), np.array([[1.0, leg_share], [leg_share, 1.0]]))
    return std_m**2 * np.einsum("ab,ai,bj->aibj", R, los, los).reshape(24, 24)


def _pair_consistency(P: np.ndarray, covP: np.ndarray) -> tuple[np.ndarray, list[dict], list[str]]:
    """The two upper joints of each leg against the other legs': their separations (4, 3) must agree.

    Every leg's two rods are the same distance apart along x_B, so ``P[i, 1] - P[i, 0]`` is the same vector for
    the four legs. Each leg's separation is compared with the covariance-weighted mean of the other legs' by its
    chi-square with 3 dof under the covariance of both (the leg's two joints', plus the mean's, plus a 1 um floor).
    The leg with the largest chi-square is the one a wrong joint would single out; the others are then compared with
    each other without it (a wrong leg pulls every mean it is in). It is flagged when its chi-square is beyond the
    chi-square 99.9% quantile times the other legs' common scale (their median chi-square over chi-square(3)'s
    median, at least 1): its two joint covariances are scaled by chi-square / 3, so that its std covers the
    disagreement (the joints' error is then visible to the propagation, and the prior can act on it).

    The reference's own covariance matters: a joint's covariance is long along its line of sight (the rod's depth
    comes from its apparent width) and the four legs are seen along different lines, so the other legs' error lies
    where this leg's covariance is thin: against the component-wise median of the four with the leg's covariance
    alone the statistic would be far above chi-square(3) on clean data; against the others' mean with both
    covariances it follows chi-square(3).

    Returns
    -------
    covP : ndarray, shape (4, 2, 3, 3)
        The joints' covariances, scaled where needed.
    check : list of dict
        Per leg: ``separation_mm``, ``deviation_mm`` (from the other legs' mean), ``chi2``, ``gate`` (the flag's
        threshold on it), ``scale``.
    warnings : list of str
    """
    sep = P[:, 1] - P[:, 0]
    C = covP[:, 0] + covP[:, 1] + _PAIR_FLOOR_M**2 * np.eye(3)[None]

    def against(i: int, others: list[int]) -> tuple[np.ndarray, float]:
        """Leg i's separation minus the others' weighted mean, and its chi-square."""
        try:
            W = [np.linalg.inv(C[k]) for k in others]
            C_ref = np.linalg.inv(sum(W))
            e = sep[i] - C_ref @ sum(w @ sep[k] for w, k in zip(W, others, strict=True))
            return e, float(e @ np.linalg.solve(C[i] + C_ref, e))
        except np.linalg.LinAlgError:
            return np.full(3, np.nan), float("nan")

    loo = [against(i, [k for k in range(4) if k != i]) for i in range(4)]
    c2_loo = [c for _, c in loo]
    worst = int(np.nanargmax(c2_loo)) if np.any(np.isfinite(c2_loo)) else 0
    # the other legs against each other, without the worst: their common scale sets the gate
    rows = [loo[i] if i == worst else against(i, [k for k in range(4) if k not in (i, worst)]) for i in range(4)]
    finite = [c for i, (_, c) in enumerate(rows) if i != worst and np.isfinite(c)]
    common = max(1.0, robust_chi2_scale(finite, 3)) if finite else 1.0
    limit = float(chi2_gate(3)) * common
    out = covP.copy()
    check, warnings = [], []
    for i, (e, c2) in enumerate(rows):
        scale = c2 / 3.0 if i == worst and np.isfinite(c2) and c2 > limit else 1.0
        out[i] *= scale
        check.append(
            {
                "leg": i + 1,
                "separation_mm": float(np.linalg.norm(sep[i]) * 1e3),
                "deviation_mm": float(np.linalg.norm(e) * 1e3),
                "chi2": c2,
                "gate": limit,
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
    dirs: list[dict[str, Any]] = []
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


def with_prior(
    seven: np.ndarray,
    cov: np.ndarray,
    parts: dict[str, np.ndarray],
    nom: I4Parameters,
    prior_std_m: float,
    idx: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The legs' estimate with the prior N(nominal, prior_std_m^2 I) in the directions the data do not pin.

    Along each principal direction k of the data covariance C (variance w_k): when the data know it better than
    the prior (w_k < prior_std_m^2) the data's estimate is kept as it is (unbiased, and better than the a priori
    value in expectation); otherwise the linear-Gaussian posterior of the two, the data weighed by the factor
    ``a_k = s^2 / (w_k + s^2)``. With ``A = V diag(a) V^T``, ``posterior = A seven + (I - A) nominal``; its error is
    ``A (data error) + (I - A) (nominal - truth)``, hence the covariance ``A C A^T + (I - A) P (I - A)^T``, each data
    part mapped by A and the prior's part named ``a_priori``. In every direction the result is then no worse than
    the a priori value in expectation, and noise-free data still give back the truth exactly.

    ``idx``: the parameters (indices into the seven) the data estimate; the others are the a priori values already
    (with ``prior_std_m``, in ``parts["a_priori"]``) and are left as they are. Default: all seven.

    Parameters
    ----------
    seven : ndarray, shape (7,)
        The data's estimate, PARAMETER_NAMES order, m.
    cov : ndarray, shape (7, 7)
        Its covariance, m^2.
    parts : dict of str to ndarray (7, 7)
        The covariance's named parts, m^2.
    nom : I4Parameters
        The a priori geometry.
    prior_std_m : float
        The a priori tolerance, m.
    idx : ndarray of int, optional
        The parameters the data estimate.

    Returns
    -------
    seven : ndarray, shape (7,)
        The posterior estimate, m.
    cov : ndarray, shape (7, 7)
        Its covariance, m^2.
    parts : dict of str to ndarray (7, 7)
        The parts mapped by A, with ``a_priori``, m^2.
    """
    idx = np.arange(7) if idx is None else np.asarray(idx)
    ix = np.ix_(idx, idx)
    n = idx.size
    s2 = prior_std_m**2
    C = 0.5 * (cov[ix] + cov[ix].T)
    w, V = np.linalg.eigh(C)
    w = np.maximum(w, 0.0)
    a = np.where(w < s2, 1.0, s2 / (w + s2))
    A = np.eye(7)
    A[ix] = (V * a) @ V.T
    post = np.asarray(seven, dtype=np.float64).copy()
    post[idx] = A[ix] @ post[idx] + (np.eye(n) - A[ix]) @ np.asarray(nom.vector())[idx]
    out = {k: A @ v @ A.T for k, v in parts.items()}
    IA = np.zeros((7, 7))
    IA[ix] = np.eye(n) - A[ix]
    out["a_priori"] = out.get("a_priori", np.zeros((7, 7))) + IA @ (s2 * np.eye(7)) @ IA.T
    total = sum(out.values())
    return post, 0.5 * (total + total.T), out


def _prior_conflict(
    seven: np.ndarray, cov: np.ndarray, nom: I4Parameters, prior_std_m: float, idx: np.ndarray | None = None
) -> float:
    """Chi-square of the data's estimate against the a priori tolerance: ``d^T (C + P)^-1 d`` (7 dof, or len(idx)).

    ``d`` = data estimate - nominal, ``C`` its covariance, ``P = prior_std_m^2 I``. When both are right, ``d``'s
    covariance is ``C + P`` (the truth within the tolerance of nominal, the estimate within C of the truth) and this
    is chi-square(7); far beyond it, the data or the tolerance is wrong, and the data, which have been (a wrong joint
    the rod-pair check could not see), are not to be blended as if they were right. ``idx``: only those parameters
    (their marginal).
    """
    idx = np.arange(7) if idx is None else np.asarray(idx)
    d = (np.asarray(seven, dtype=np.float64) - np.asarray(nom.vector()))[idx]
    C = 0.5 * (cov + cov.T)[np.ix_(idx, idx)] + prior_std_m**2 * np.eye(idx.size)
    return float(d @ np.linalg.solve(C, d))


def combinations_null_space() -> np.ndarray:
    """An orthonormal basis (7, 3), PARAMETER_NAMES order, of the directions of the seven parameters that leave the
    four combinations unchanged (the null space of :data:`calib.model.parameters.SEVEN_TO_FOUR`): H and D together; q03
    and q04 together; then q02 and q04 - q03 by twice what S moves (the base's and the plate's widths together),
    made orthogonal to the second. The kinematics, hence the fit poses, do not see them; only the lock phases'
    joints do.

    Returns
    -------
    ndarray, shape (7, 3)
        Unit columns, dimensionless.
    """
    idx = {n: i for i, n in enumerate(PARAMETER_NAMES)}
    raw = np.zeros((3, 7))
    raw[0, [idx["H"], idx["D"]]] = 1.0
    raw[1, [idx["q03"], idx["q04"]]] = 1.0
    raw[2, [idx["q02"], idx["q03"], idx["q04"], idx["S"]]] = [2.0, -1.0, 1.0, 1.0]
    return raw.T / np.linalg.norm(raw, axis=1)


def null_space_to_prior(
    seven: np.ndarray, parts: dict[str, np.ndarray], nom: I4Parameters, prior_std_m: float
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], list[dict]]:
    """The seven with their component along :func:`combinations_null_space` the a priori values', with the a priori
    tolerance ``prior_std_m`` as its std (``parts["a_priori"]``): the legs' image data do not pin these directions.

    Along these directions the lock phases' joints carry an error common to every run, several times the data's std
    and millimetres to centimetres in size: the rods' shading, which offsets a rod's limb edges alike in every frame
    of a lock phase, and the camera calibration's error on top (docs/model.md). The data's estimate along them is
    therefore no better than the a priori value. With
    ``P = N N^T`` (N the basis): ``seven - P (seven - nominal)``, each part ``(I - P) C (I - P)``, plus
    ``prior_std_m^2 P``. The four combinations and their covariance are unchanged (``SEVEN_TO_FOUR P = 0``).

    Returns
    -------
    seven : ndarray, shape (7,)
    cov : ndarray, shape (7, 7)
    parts : dict of ndarray (7, 7)
    directions : list of dict
        Per null direction: ``direction`` (unit, per parameter), ``label``, ``data_estimate_m`` (the data's
        coordinate along it, relative to the nominal), ``data_std_m`` (what the data's covariance gave there),
        ``reason``.

    Parameters
    ----------
    seven : ndarray, shape (7,)
        The estimate, PARAMETER_NAMES order, m.
    parts : dict of str to ndarray (7, 7)
        The covariance's named parts, m^2.
    nom : I4Parameters
        The a priori geometry.
    prior_std_m : float
        The a priori tolerance, m.
    """
    N = combinations_null_space()
    P = N @ N.T
    IP = np.eye(7) - P
    nom7 = np.asarray(nom.vector(), dtype=np.float64)
    d = np.asarray(seven, dtype=np.float64) - nom7
    data_cov = sum(parts.values())
    out = {k: IP @ v @ IP for k, v in parts.items()}
    out["a_priori"] = out.get("a_priori", np.zeros((7, 7))) + prior_std_m**2 * P
    total = sum(out.values())
    dirs = []
    for k in range(N.shape[1]):
        v = N[:, k] * np.sign(N[np.argmax(np.abs(N[:, k])), k])
        big = np.argsort(-np.abs(v))
        dirs.append(
            {
                "direction": {n: float(x) for n, x in zip(PARAMETER_NAMES, v, strict=True)},
                "label": " ".join(f"{v[j]:+.2f} {PARAMETER_NAMES[j]}" for j in big if abs(v[j]) > 0.2),
                "data_estimate_m": float(v @ d),
                "data_std_m": float(np.sqrt(max(v @ data_cov @ v, 0.0))),
                "reason": "leaves the four combinations unchanged: only the lock phases' joints see it, and on images "
                "they carry an error common to every run",
            }
        )
    return nom7 + IP @ d, 0.5 * (total + total.T), out, dirs


#: the former private name (tests read it)
