"""Pose-set optimisation: choose the fit poses (and the base-frame sweeps' extents) before any motion.

Candidates are poses drawn uniformly in the workspace box (:class:`calib.formats.plan.Workspace`), reachable by the
nominal model, within the soft limits, and visible (:func:`.scene.visibility`: board and eight rods in view);
the paper's own pose set for the same count is added as candidates too, so a designed set is never worse
than it. Every fit pose's information on a method's unknowns is additive (:mod:`.predict`), so a pose set's
criterion is cheap to evaluate for hundreds of swaps at once.

Criteria, on the four combinations' information of each selected method (the Schur complement of the
nuisance unknowns; the combined method with its base-frame prior):

* ``"d"``: D-optimal, maximise ``sum_m log det F_m`` (the volume of the confidence ellipsoids);
* ``"a"``: A-optimal, minimise ``sum_m trace(C_m / t^2)`` (the sum of the variances, relative to the target
  ``t`` per combination when given, else per mm^2);
* ``"target"``: minimise the worst ratio ``std / target`` over methods and combinations (A as tie-break).

Selection: greedy (one pose at a time, a tiny ridge while the set is too small to determine everything),
then Fedorov exchange (the best swap of a selected pose for a candidate, until no swap improves); the start
is the better of the greedy set and the paper's set. Sweeps: the rotation span and translation length are
the valid extents (in limits, board in view in every frame) of largest base-frame information. Count:
fixed (``n_fit``), or the smallest that meets the target within ``max_time_s`` (the motion time of the whole
plan, trapezoidal profiles, fit poses ordered by a nearest-neighbour tour with 2-opt).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from calib.design.beyond_count import DesignedCount, count_std, past_the_count_search
from calib.design.legs_criterion import LegsCriterion
from calib.design.motion import MotionSpec, order_tour, plan_motion_time
from calib.design.predict import (
    DesignNoise,
    Prediction,
    base_frame_information,
    combined_pose_information,
    end_effector_pose_information,
    mark_undetermined,
    phase_q,
    predict_plan,
    ratio_to_target,
    scaled_inverse,
)
from calib.design.predict_images import (
    ImageNoise,
    base_frame_images,
    combined_images_pose_information,
    combined_images_prior,
    end_effector_images_pose_information,
)
from calib.design.scene import Scene, visibility
from calib.errors import InputError
from calib.formats.plan import (
    Plan,
    SoftLimits,
    Step,
    Workspace,
    equal_translation,
    guided_line,
    lock_actuator,
    pose_set,
    random_poses,
    rotation_sweep,
)
from calib.model.kinematics import ikm
from calib.model.parameters import COMBINATION_NAMES, I4Parameters

__all__ = [
    "BenchSettings",
    "DesignRequest",
    "DesignResult",
    "design_plan",
    "locks_joints",
    "log_det_information",
    "select_poses",
    "uses_sweeps",
    "validate_request",
]

Criterion = Literal["d", "a", "target"]
OPTIMISED_METHODS = ("combined", "end-effector", "legs")
#: choices of the count at most, while the plan's prediction misses the target
DESIGN_ROUNDS = 4
#: the exchange's targets are tightened by the prediction's miss times this
TIGHTEN_MARGIN = 1.02
#: the most fit poses a plan takes (``n_fit``, ``n_max``; past ``n_max`` when a target needs them: :mod:`.beyond_count`)
N_FIT_MOST = 200
SPANS_DEG = (120.0, 180.0, 240.0, 300.0, 330.0)
LENGTHS_M = (0.15, 0.25, 0.35, 0.45)

#: ``run(design_draw, n)``: ``[design_draw(0), ..., design_draw(n - 1)]``, each entry the draw's design or the
#: exception it raised (e.g. fanned out over processes or machines by the caller; each draw is seeded by its index)
DrawsRunner = Callable[[Callable[[int], "DesignResult"], int], "list[DesignResult | BaseException]"]


@dataclass(frozen=True)
class DesignRequest:
    """What to design (lengths in metres, times in seconds).

    Attributes
    ----------
    n_fit : int or None
        Fit poses; None: the smallest count that meets ``target_std_m`` within ``max_time_s`` (20 without a
        target).
    target_std_m : float, tuple of 4 floats, or None
        Wanted standard deviation of each combination (one value for all four, or per combination).
    max_time_s : float or None
        Longest motion time of the whole plan.
    criterion : {"d", "a", "target"}
    methods : tuple of str
        Methods whose predicted accuracy the selection optimises (combined, end-effector).
    draws : int
        Independent draws of the ``n_candidates`` candidate poses, each designed in full, the best kept (by the
        criterion on its prediction: the exchange finds a local optimum of the poses drawn, and another draw can
        hold a better one). 1: the one draw of ``seed``.
    candidate_draw : int
        Which draw of the candidates this is (0: the ``seed``'s own; the lock, validation and reference poses
        do not change with it).
    method_targets_m : tuple of (str, 4 floats)
        Per optimised method, its own target std per combination (m) in place of ``target_std_m``, which the others
        keep (``--better-than``: the reference plan's predicted std of each method, the legs method's being 5-20x the
        combined one's); needs ``target_std_m``.
    """

    n_fit: int | None = None
    target_std_m: float | tuple[float, float, float, float] | None = None
    max_time_s: float | None = None
    criterion: Criterion = "d"
    methods: tuple[str, ...] = ("combined",)
    seed: int = 0
    n_candidates: int = 300
    n_base: int = 10
    n_lock: int = 5
    n_validation: int = 10
    with_line: bool = True
    n_min: int = 4
    n_max: int = 60
    weighting: str = "gls"
    draws: int = 1
    candidate_draw: int = 0
    method_targets_m: tuple[tuple[str, tuple[float, ...]], ...] = ()

    def __post_init__(self) -> None:
        validate_request(self)

    def targets(self) -> np.ndarray | None:
        if self.target_std_m is None:
            return None
        t = np.atleast_1d(np.asarray(self.target_std_m, dtype=np.float64))
        return np.repeat(t, 4) if t.size == 1 else t

    def targets_by_method(self) -> dict[str, np.ndarray] | None:
        """Each optimised method's target std per combination (4,), m; None without a target."""
        t = self.targets()
        if t is None:
            return None
        own = {m: np.asarray(v, dtype=np.float64) for m, v in self.method_targets_m}
        return {m: own.get(m, t) for m in self.methods}


def validate_request(req: DesignRequest) -> None:
    """Check a request's fields, each against its range, in the order of the fields.

    Parameters
    ----------
    req : DesignRequest
        The request (lengths in m, times in s).

    Raises
    ------
    InputError
        The first field out of range, naming it (``n_fit``, ``criterion``, ``target_std``, ``max_time``, ``methods``,
        ``n_candidates``, ``n_base``, ``n_lock``, ``n_validation``, ``n_max``, ``draws``, ``method_targets``).
    """
    _check_targets(req)
    _check_methods(req)
    _check_counts(req)
    _check_method_targets(req)


def _check_targets(req: DesignRequest) -> None:
    """The fixed count, the criterion, the target std (m) and the time allowed (s)."""
    if req.n_fit is not None and not (2 <= req.n_fit <= N_FIT_MOST):
        raise InputError(f"n_fit must be in 2..{N_FIT_MOST}, got {req.n_fit}", field="n_fit")
    if req.criterion not in ("d", "a", "target"):
        raise InputError(f"criterion must be d, a or target, got {req.criterion!r}", field="criterion")
    if req.criterion == "target" and req.target_std_m is None:
        raise InputError("criterion 'target' needs a target std", field="target_std")
    t = req.targets()
    if t is not None and not np.all(np.isfinite(t) & (t > 0)):
        raise InputError("target std must be finite and > 0", field="target_std")
    if req.max_time_s is not None and not (np.isfinite(req.max_time_s) and req.max_time_s > 0):
        raise InputError("max time must be finite and > 0", field="max_time")


def _check_methods(req: DesignRequest) -> None:
    """The methods to optimise: at least one, each of :data:`OPTIMISED_METHODS`."""
    bad = [m for m in req.methods if m not in OPTIMISED_METHODS]
    if bad or not req.methods:
        raise InputError(
            f"methods to optimise: {', '.join(OPTIMISED_METHODS)} (got {', '.join(req.methods) or 'none'})",
            field="methods",
        )


def _check_counts(req: DesignRequest) -> None:
    """The candidates, the phases' frames, the count search's range and the draws."""
    if not (20 <= req.n_candidates <= 5000):
        raise InputError("n_candidates must be in 20..5000", field="n_candidates")
    for name, lo, hi in (("n_base", 3, 100), ("n_lock", 2, 50), ("n_validation", 0, 200)):
        if not (lo <= getattr(req, name) <= hi):
            raise InputError(f"must be in {lo}..{hi}, got {getattr(req, name)}", field=name)
    if not (2 <= req.n_min <= req.n_max <= N_FIT_MOST):
        raise InputError(f"need 2 <= n_min <= n_max <= {N_FIT_MOST}", field="n_max")
    if not (1 <= req.draws <= 20) or req.candidate_draw < 0:
        raise InputError("draws must be in 1..20 (and candidate_draw >= 0)", field="draws")


def _check_method_targets(req: DesignRequest) -> None:
    """Each method's own target: an optimised method's, four finite std > 0 (m), with ``target_std_m`` given."""
    for m, v in req.method_targets_m:
        if m not in req.methods:
            raise InputError(f"a target for {m!r}, which is not optimised", field="method_targets")
        tv = np.asarray(v, dtype=np.float64)
        if tv.shape != (4,) or not np.all(np.isfinite(tv) & (tv > 0)):
            raise InputError(f"{m}: four finite std > 0 needed, got {v!r}", field="method_targets")
    if req.method_targets_m and req.target_std_m is None:
        raise InputError("method targets need target_std_m (the other methods' target)", field="target_std")


@dataclass
class DesignResult:
    """The designed plan, its prediction and what the design found."""

    plan: Plan
    prediction: Prediction
    motion: dict[str, Any]
    n_fit: int
    sweeps: dict[str, float]
    target_met: bool | None
    time_met: bool | None
    criterion: dict[str, float]
    candidates: dict[str, int]
    notes: list[str] = field(default_factory=list)
    count_trend: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        return {
            "n_fit": self.n_fit,
            "counts": self.plan.count(),
            "sweeps": self.sweeps,
            "prediction": self.prediction.to_dict(),
            "motion": self.motion,
            "target_met": self.target_met,
            "time_met": self.time_met,
            "criterion": self.criterion,
            "candidates": self.candidates,
            "notes": self.notes,
            **({"count_trend": self.count_trend} if self.count_trend is not None else {}),
        }


def _worst_miss(pred: Prediction, targets: dict[str, np.ndarray]) -> str:
    """``"; worst: <method> <combination> 0.066 mm predicted for 0.050 mm (1.33x)"``, the combination furthest over
    its target among the optimised methods (``targets``: per method, (4,) m; "" when none is predicted)."""
    worst = None
    for m, target_m in targets.items():
        for i, c in enumerate(COMBINATION_NAMES):
            s = (pred.std.get(m) or {}).get(c)
            if s is None:
                continue
            r = float(ratio_to_target(s, target_m[i]))
            if worst is None or r > worst[0]:
                worst = (r, m, c, float(s), float(target_m[i]))
    if worst is None:
        return ""
    r, m, c, s, tm = worst
    ratio = f"{r:.2f}x" if r < 1e3 else f"{r:.3g}x" if np.isfinite(r) else "no finite ratio"
    want = f"{tm * 1e3:.3f}" if tm >= 1e-6 else f"{tm * 1e3:.3g}"
    return f"; worst: {m} {c} {s * 1e3:.3f} mm predicted for {want} mm ({ratio})"


def _worst_ratio(excess: dict[str, np.ndarray]) -> float:
    """The largest predicted std over its target among the methods' combinations (inf: not predicted)."""
    return float(np.max(np.stack(list(excess.values()))))


#: How far the legs method's image-level prediction (predicted std over RMS error, per combination) may fall from
#: one on a plan of the paper's kind, low and high: its model of the rods' shading is right on average over plans,
#: not plan by plan. The design's notes quote it; ``i4cal bench design`` measures it on the simulated bench.
LEGS_PREDICTION_RATIO_RANGE = (0.78, 1.25)
#: The same range on plans designed for the legs method, wider: their poses are those its predicted std is
#: smallest for, so what its model leaves out weighs more there.
LEGS_DESIGNED_PREDICTION_RATIO_RANGE = (0.58, 1.42)
#: the share of a legs combination's predicted variance from the lock phases' shading above which a design says so
SHADING_NOTE_SHARE = 0.1


def shading_note(pred: Prediction) -> str | None:
    """A note when the legs prediction leans on its model of the rods' shading (the lock phases' systematic depth
    error), which is right on average over plans but not plan by plan.

    Parameters
    ----------
    pred : Prediction
        A plan's prediction (its ``parts``: per method and source, std per combination in m).

    Returns
    -------
    str or None
        The note; None when the shading's share of every legs combination's variance is below
        :data:`SHADING_NOTE_SHARE`.
    """
    sys_part = (pred.parts.get("legs") or {}).get("joint_depth_systematic")
    std = pred.std.get("legs")
    if not sys_part or not std:
        return None
    share = max((sys_part[c] / std[c]) ** 2 for c in COMBINATION_NAMES if std[c] > 0)
    if share < SHADING_NOTE_SHARE:
        return None
    lo, hi = LEGS_PREDICTION_RATIO_RANGE
    return (
        f"legs: up to {share:.0%} of a combination's predicted variance is the lock phases' shading, a model of its "
        f"average over plans; on the simulated bench's ten benched plans the legs prediction was {lo:.2f}-{hi:.2f}x "
        "its RMS error from one plan to another (docs/design.md)"
    )


# -- criteria ---------------------------------------------------------------------------------------------------
Cov4 = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class _Infos:
    """Per-candidate additive statistics of each optimised method, with the priors (base frame, tiny ridge), and how
    a sum of them gives the four combinations' covariance (``cov4``: :func:`_cov4` for an information matrix, the
    legs method's :meth:`.legs_criterion.LegsCriterion.cov4`)."""

    def __init__(
        self, per: dict[str, np.ndarray], prior: dict[str, np.ndarray], cov4: dict[str, Cov4] | None = None
    ) -> None:
        self.per = per
        self.prior = prior
        self.cov4 = {m: (cov4 or {}).get(m, _cov4) for m in per}

    def total(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        return {m: self.prior[m] + F[idx].sum(axis=0) for m, F in self.per.items()}

    def ridge(self, m: str) -> np.ndarray:
        """A tiny ridge on the information part of ``m``'s statistic, for the greedy start."""
        F = self.per[m]
        r = np.zeros(F.shape[1:])
        k = F.shape[1]
        r[:, :k] = np.diag(1e-9 * np.mean(np.einsum("kii->ki", F[:, :, :k]), axis=0))
        return r


def _cov4(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched: (..., p, p) information -> (..., 4, 4) covariance of the first four and log det of their
    information (-inf where singular, and the variances inf)."""
    Ci, ok = scaled_inverse(F)
    return mark_undetermined(Ci[..., :4, :4], ok)


def _score(
    infos: _Infos, F: dict[str, np.ndarray], criterion: Criterion, t: dict[str, np.ndarray] | None
) -> np.ndarray:
    """Lower is better; batched over the leading axes. ``t``: per method its targets (4,), m."""
    # 0.0, then arrays over the leading axes once a method's information is added (F holds at least one)
    d: Any
    a: Any
    worst: Any
    d = a = worst = 0.0
    for m, Fm in F.items():
        ref = t[m] if t is not None else np.full(4, 1e-3)
        C4, ld = infos.cov4[m](Fm)
        var = np.einsum("...ii->...i", C4)
        d = d - ld
        with np.errstate(divide="ignore", over="ignore"):  # a target of 1e-300 m: an infinite score, as intended
            a = a + np.sum(var / ref**2, axis=-1)
            worst = np.maximum(worst, np.max(np.sqrt(np.maximum(var, 0)) / ref, axis=-1))
        a = np.where(np.isfinite(ld), a, np.inf)
        worst = np.where(np.isfinite(ld), worst, np.inf)
    if criterion == "d":
        return d
    if criterion == "a":
        return a
    return worst + 1e-6 * a


def select_poses(
    infos: _Infos,
    n: int,
    criterion: Criterion,
    targets: dict[str, np.ndarray] | None,
    start: np.ndarray | None = None,
    max_passes: int = 50,
) -> np.ndarray:
    """Indices of ``n`` candidates: greedy, then Fedorov exchange (the start is the better of the greedy set
    and ``start``).

    Parameters
    ----------
    infos : _Infos
        Per method, the candidates' additive statistics (M candidates) and their priors.
    n : int
        Fit poses to choose.
    criterion : {"d", "a", "target"}
        What is minimised (:func:`_score`).
    targets : dict of str to ndarray, shape (4,), or None
        Per method, the target std per combination, m.
    start : ndarray of int, shape (n,), optional
        A selection to start the exchange from when it scores better than the greedy one.
    max_passes : int
        Most swaps of the exchange (0: the greedy selection).

    Returns
    -------
    ndarray of int, shape (n,)
        Indices into the candidates.

    Raises
    ------
    InputError
        Fewer than ``n`` candidates.
    """
    M = next(iter(infos.per.values())).shape[0]
    if n > M:
        raise InputError(f"only {M} visible candidate poses for {n} fit poses (more candidates or fewer poses)")
    ridge = {m: infos.ridge(m) for m in infos.per}
    chosen: list[int] = []
    for _ in range(n):
        base = infos.total(np.array(chosen, dtype=int))
        cand = np.setdiff1d(np.arange(M), chosen)
        F = {m: base[m][None] + infos.per[m][cand] + ridge[m][None] for m in base}
        s = _score(infos, F, criterion, targets)
        chosen.append(int(cand[int(np.argmin(s))]))
    sel = np.array(chosen, dtype=int)
    best = float(_score(infos, infos.total(sel), criterion, targets))
    if start is not None and len(start) == n:
        s0 = float(_score(infos, infos.total(np.asarray(start)), criterion, targets))
        if s0 < best:
            sel, best = np.asarray(start, dtype=int).copy(), s0
    for _ in range(max_passes):
        base = infos.total(sel)
        out = np.setdiff1d(np.arange(M), sel)
        if out.size == 0:
            break
        # every (remove i, add c) swap at once: base - F_i + F_c
        F = {m: base[m][None, None] - infos.per[m][sel][:, None] + infos.per[m][out][None, :] for m in base}
        s = _score(infos, F, criterion, targets)
        i, c = np.unravel_index(int(np.argmin(s)), s.shape)
        if not s[i, c] < best - 1e-10 * max(abs(best), 1.0):
            break
        sel = sel.copy()
        sel[i] = out[c]
        best = float(s[i, c])
    return sel


def locks_joints(method: str) -> bool:
    """Whether a method locates the legs' joints from the lock phases (its registry entry's phases name them): the
    design's statistic for it is then the lock phases' criterion (:class:`.legs_criterion.LegsCriterion`).

    Parameters
    ----------
    method : str
        A registered method's name (:mod:`calib.identify.registry`).

    Returns
    -------
    bool
    """
    from calib.identify.registry import get_method

    return any(p.startswith("lock-") for p in get_method(method).required_phases)


def uses_sweeps(method: str) -> bool:
    """Whether a method takes the base frame from the rotation and translation sweeps (its registry entry's phases
    name both): the design couples its information to the base frame's, the sweeps being its prior.

    Parameters
    ----------
    method : str
        A registered method's name (:mod:`calib.identify.registry`).

    Returns
    -------
    bool
    """
    from calib.identify.registry import get_method

    return {"rotation", "translation"} <= set(get_method(method).required_phases)


def log_det_information(
    plan: Plan,
    nominal: I4Parameters,
    scene: Scene,
    noise: DesignNoise | ImageNoise | None = None,
    methods: tuple[str, ...] = ("combined",),
) -> dict[str, float]:
    """D-criterion of a plan: per method, log det of the four combinations' information.

    Parameters
    ----------
    plan : Plan
        Its sweeps, fit poses and (for a method locating joints) lock phases' joint values (m).
    nominal : I4Parameters
        The nominal geometry (m, rad).
    scene : Scene
        The camera, its mounting, the board and the rods.
    noise : DesignNoise or ImageNoise, optional
        The measurement noise (default: ``DesignNoise()``; a method locating joints needs ``ImageNoise``).
    methods : tuple of str
        Methods of :data:`OPTIMISED_METHODS`.

    Returns
    -------
    dict of str to float
        Per method, log det of its four combinations' information (m^-2; higher better).
    """
    noise = noise or DesignNoise()
    q_fit = phase_q(plan, "poses")
    out = {}
    for m in methods:
        q_rot, q_tra = phase_q(plan, "rotation"), phase_q(plan, "translation")
        legs = None
        if locks_joints(m):
            if not isinstance(noise, ImageNoise):
                raise InputError(f"the {m} criterion needs the image-level noise model", field="methods")
            legs = LegsCriterion(nominal, [phase_q(plan, f"lock-{i}") for i in range(1, 5)], scene, noise)
        F = _method_information(m, nominal, q_fit, scene, noise, q_rot, q_tra, legs).sum(axis=0) + _method_prior(
            m, nominal, q_rot, q_tra, scene, noise
        )
        out[m] = float((legs.cov4 if legs is not None else _cov4)(F)[1])
    return out


def _method_information(
    m: str, nominal, q, scene: Scene, noise: DesignNoise | ImageNoise, q_rot=None, q_tra=None, legs=None
) -> np.ndarray:
    """Per fit pose (N, p, p) information of method ``m`` (on images, for a method using the sweeps, its nuisances,
    whose base-frame coupling needs the sweeps ``q_rot``, ``q_tra``); for a method locating joints (N, 3, 30), its
    :class:`.legs_criterion.LegsCriterion`'s statistics."""
    if locks_joints(m):
        return legs.pose_statistics(q)
    if isinstance(noise, ImageNoise):
        if uses_sweeps(m):
            _P, steps, G = combined_images_prior(nominal, q_rot, q_tra, scene, noise)
            return combined_images_pose_information(nominal, q, scene, noise, steps, G)
        return end_effector_images_pose_information(nominal, q, scene, noise)
    if uses_sweeps(m):
        return combined_pose_information(nominal, q, scene.camera_from_base.R, noise)
    return end_effector_pose_information(nominal, q, scene, noise)


def _method_prior(m: str, nominal, q_rot, q_tra, scene: Scene, noise: DesignNoise | ImageNoise) -> np.ndarray:
    """Method ``m``'s prior statistic: the base frame's information from the sweeps for a method using them, else
    zeros of its statistic's shape."""
    if locks_joints(m):
        return np.zeros((3, 30))
    if not uses_sweeps(m):
        return np.zeros((16, 16))
    if isinstance(noise, ImageNoise):
        return combined_images_prior(nominal, q_rot, q_tra, scene, noise)[0]
    P = np.zeros((7, 7))
    P[4:, 4:] = base_frame_information(nominal, q_rot, q_tra, scene.camera_from_base.R, noise)
    return P


# -- the plan ---------------------------------------------------------------------------------------------------
def _in_limits(q: np.ndarray, limits: SoftLimits) -> np.ndarray:
    return np.all((q >= np.asarray(limits.q_min)) & (q <= np.asarray(limits.q_max)), axis=-1)


def _sweeps(nominal, scene, limits, ws, noise, n_base) -> tuple[float, float, list[Step], list[Step], float]:
    best = None
    for span in SPANS_DEG:
        rot = rotation_sweep(nominal, n_base, np.deg2rad(span), ws=ws)
        qr = np.array([s.q for s in rot])
        if not (_in_limits(qr, limits).all() and visibility(scene, nominal, qr)["board"].all()):
            continue
        for length in LENGTHS_M:
            tra = equal_translation(nominal, n_base, length, ws=ws)
            qt = np.array([s.q for s in tra])
            if not (_in_limits(qt, limits).all() and visibility(scene, nominal, qt)["board"].all()):
                continue
            Fw = (
                base_frame_images(nominal, qr, qt, scene, noise)[0]
                if isinstance(noise, ImageNoise)
                else base_frame_information(nominal, qr, qt, scene.camera_from_base.R, noise)
            )
            ld = float(np.linalg.slogdet(Fw)[1])
            if best is None or ld > best[4] + 1e-9:
                best = (span, length, rot, tra, ld)
    if best is None:
        raise InputError("no rotation and translation sweep keeps the board in view within the soft limits")
    return best


def _visible_steps(steps: list[Step], scene, nominal, need: str, n: int) -> list[Step]:
    q = np.array([s.q for s in steps])
    v = visibility(scene, nominal, q)
    keep = v["ok"] if need == "all" else v["board"]
    return [s for s, k in zip(steps, keep, strict=True) if k][:n]


def _lock_steps(nominal, scene, limits, ws, n_lock: int, seed: int) -> list[Step]:
    out: list[Step] = []
    steps = lock_actuator(nominal, 4 * n_lock, seed + 1, ws=ws, limits=limits)
    for i in range(4):
        ph = [s for s in steps if s.phase == f"lock-{i + 1}"]
        q = np.array([s.q for s in ph])
        v = visibility(scene, nominal, q)
        ok = v["board"] & np.all(v["rod_px"][:, i] >= scene.limits.min_rod_px, axis=1)
        got = [s for s, k in zip(ph, ok, strict=True) if k][:n_lock]
        if len(got) < n_lock:
            raise InputError(f"could not draw {n_lock} visible poses with actuator {i + 1} locked")
        out += got
    return out


def _line_steps(nominal, limits: SoftLimits, ws: Workspace, notes: list[str]) -> list[Step]:
    """The paper's 500 mm guided line through ``ws``'s centre, shortened until every sample is within the soft limits
    (:func:`calib.formats.plan.guided_line`); left out, and said, when not even 100 mm fits."""
    try:
        steps = guided_line(nominal, ws=ws, limits=limits)
    except InputError:
        notes.append("no guided line (straightness) fits within the soft limits: left out")
        return []
    line = steps[0].line
    assert line is not None
    length = float(np.linalg.norm(np.subtract(line.end_pose[:3], line.start_pose[:3])))
    if length < 0.5 - 1e-9:
        notes.append(f"guided line shortened to {length * 1e3:.0f} mm to stay within the soft limits")
    return steps


#: shifts (m) of the centre about which the sweeps, lock phases and line are placed, tried in this order when the
#: workspace's own centre keeps no sweep's or lock phase's board in view (a camera that sees less than the twin's)
CENTRE_SHIFTS_M = tuple(
    sorted(
        (
            (dx, dy, dz)
            for dx in (0.0, -0.05, 0.05, -0.1, 0.1)
            for dy in (0.0, -0.05, 0.05)
            for dz in (0.0, -0.05, 0.05, -0.1, 0.1)
        ),
        key=lambda d: (d[0] ** 2 + d[1] ** 2 + d[2] ** 2, d),
    )
)


def _shifted(ws: Workspace, d: tuple[float, float, float]) -> Workspace:
    """``ws`` moved by ``d`` (its box, hence its centre)."""
    return ws.model_copy(
        update={k: (lo + dk, hi + dk) for k, (lo, hi), dk in zip("XYZ", (ws.X, ws.Y, ws.Z), d, strict=True)}
    )


def _placed_phases(
    nominal, scene, limits, ws, noise, req
) -> tuple[tuple[float, float, list[Step], list[Step], float], list[Step], Workspace]:
    """The sweeps and lock phases about ``ws``'s centre, or, when the camera sees neither there, about the nearest
    centre of :data:`CENTRE_SHIFTS_M` where it sees both; the workspace they are placed in."""
    first: InputError | None = None
    for d in CENTRE_SHIFTS_M:
        at = _shifted(ws, d) if any(d) else ws
        try:
            sweeps = _sweeps(nominal, scene, limits, at, noise, req.n_base)
            lock = _lock_steps(nominal, scene, limits, at, req.n_lock, req.seed)
        except InputError as exc:
            first = first or exc
            continue
        return sweeps, lock, at
    assert first is not None
    raise InputError(f"{first.reason} (about the workspace centre or within 100 mm of it)", field=first.field)


@dataclass
class _Pool:
    """What a design computes before it knows its count: the sweeps and the drawn candidates (their visibility, and
    each optimised method's information per visible candidate and prior)."""

    span: float
    length: float
    rot: list[Step]
    tra: list[Step]
    qr: np.ndarray
    qt: np.ndarray
    cand_q: np.ndarray
    visible: np.ndarray
    lock: list[Step]
    information: dict[str, np.ndarray]
    prior: dict[str, np.ndarray]
    cov4: dict[str, Cov4]
    legs: LegsCriterion | None
    #: the workspace whose centre the sweeps, lock phases and line are placed about (``ws``, or one moved by
    #: :data:`CENTRE_SHIFTS_M` when the camera sees them nowhere else)
    placed: Workspace


def _candidate_pool(
    nominal: I4Parameters,
    scene: Scene,
    req: DesignRequest,
    limits: SoftLimits,
    ws: Workspace,
    noise: DesignNoise | ImageNoise,
    cache: dict[Any, Any] | None,
) -> _Pool:
    key = ("pool", req.seed, req.candidate_draw, req.n_candidates, req.n_base, req.n_lock, req.methods)
    if cache is not None and key in cache:
        return cache[key]
    (span, length, rot, tra, _), lock, placed = _placed_phases(nominal, scene, limits, ws, noise, req)
    legs = None
    locking = [m for m in req.methods if locks_joints(m)]
    if locking:
        if not isinstance(noise, ImageNoise):
            raise InputError(
                f"optimising for the {locking[0]} method needs the image-level noise model (the default, or a run's)",
                field="methods",
            )
        legs = LegsCriterion(
            nominal, [np.array([s.q for s in lock if s.phase == f"lock-{i}"]) for i in range(1, 5)], scene, noise
        )
    rng = np.random.default_rng(req.seed if req.candidate_draw == 0 else [req.seed, req.candidate_draw])
    cand_q = ikm(nominal, random_poses(nominal, req.n_candidates, rng, ws, limits))
    visible = visibility(scene, nominal, cand_q)["ok"]
    qr = np.array([s.q for s in rot])
    qt = np.array([s.q for s in tra])
    pool = _Pool(
        span=span,
        length=length,
        rot=rot,
        tra=tra,
        qr=qr,
        qt=qt,
        cand_q=cand_q,
        visible=visible,
        lock=lock,
        information={
            m: _method_information(m, nominal, cand_q[visible], scene, noise, qr, qt, legs) for m in req.methods
        },
        prior={m: _method_prior(m, nominal, qr, qt, scene, noise) for m in req.methods},
        cov4={m: legs.cov4 for m in locking} if legs is not None else {},
        legs=legs,
        placed=placed,
    )
    if cache is not None:
        cache[key] = pool
    return pool


@dataclass(frozen=True)
class BenchSettings:
    """The bench side of a design: what :func:`design_plan` takes besides the geometry, the scene and the request.

    Attributes
    ----------
    limits : SoftLimits
        The joints' soft limits (m).
    motion : MotionSpec
        Speeds (m/s), accelerations (m/s^2) and settle times (s).
    noise : DesignNoise or ImageNoise
        The measurement noise the prediction assumes.
    ws : Workspace
        The box the candidate poses are drawn in (m, rad).
    """

    limits: SoftLimits = field(default_factory=SoftLimits)
    motion: MotionSpec = field(default_factory=MotionSpec)
    noise: DesignNoise | ImageNoise = field(default_factory=DesignNoise)
    ws: Workspace = field(default_factory=Workspace)


class _Space:
    """What a design chooses from: the candidates (those drawn and visible, then the reference sets' visible poses),
    their statistics per method (:class:`_Infos`), and the plan's fixed phases (sweeps, lock, line, validation); how a
    selection of candidates becomes a plan."""

    def __init__(
        self, nominal: I4Parameters, scene: Scene, req: DesignRequest, bench: BenchSettings, pool: _Pool
    ) -> None:
        self.nominal, self.scene, self.req, self.bench, self.pool = nominal, scene, req, bench, pool
        self.refs: dict[int, np.ndarray] = {}
        fixed = [req.n_fit] if req.n_fit else []
        ref_q = np.concatenate([self.reference(n) for n in (fixed or [20])])
        vis_ref = visibility(scene, nominal, ref_q)["ok"]
        #: (M, 4) joint values of the candidates, m
        self.cq = np.concatenate([pool.cand_q[pool.visible], ref_q[vis_ref]])
        self.n_vis_ref = int(vis_ref.sum())
        self.infos = _Infos(
            {
                m: np.concatenate(
                    [
                        pool.information[m],
                        _method_information(
                            m, nominal, ref_q[vis_ref], scene, bench.noise, pool.qr, pool.qt, pool.legs
                        ),
                    ]
                )
                for m in req.methods
            },
            pool.prior,
            pool.cov4,
        )
        self.val = _validation_steps(nominal, scene, req, bench)
        self.notes: list[str] = []
        if pool.placed is not bench.ws:
            shift = np.subtract(pool.placed.centre()[:3], bench.ws.centre()[:3]) * 1e3
            self.notes.append(
                "the sweeps, lock phases and line are placed about a centre moved by ("
                + ", ".join(f"{v:+.0f}" for v in shift)
                + ") mm in (X, Y, Z): about the workspace's own centre the camera does not see their board"
            )
        self.line = _line_steps(nominal, bench.limits, pool.placed, self.notes) if req.with_line else []
        #: the most fit poses the count search tries
        self.n_hi = min(req.n_max, len(self.cq))

    def reference(self, n: int) -> np.ndarray:
        """The paper's pose set of ``n`` fit poses for the request's seed, (n, 4) joint values, m."""
        if n not in self.refs:
            req, b = self.req, self.bench
            self.refs[n] = np.array([s.q for s in pose_set(self.nominal, n, req.seed, ws=b.ws, limits=b.limits)])
        return self.refs[n]

    def start_index(self, n: int) -> np.ndarray | None:
        """The candidates' indices of the reference set of ``n`` poses (None: not all of it is a candidate)."""
        r = self.reference(n) if n in self.refs else None
        if r is None:
            return None
        cq = self.cq
        idx = [int(np.argmin(np.abs(cq - q).sum(axis=1))) for q in r]
        ok = [np.abs(cq[i] - q).sum() < 1e-12 for i, q in zip(idx, r, strict=True)]
        return np.array(idx) if all(ok) and len(set(idx)) == n else None

    def build(self, sel: np.ndarray) -> tuple[Plan, dict[str, Any]]:
        """The plan of the candidates ``sel`` (fit poses in tour order) and its motion time (s)."""
        pool, motion = self.pool, self.bench.motion
        q = self.cq[sel]
        order = order_tour(q, motion, start=np.asarray(pool.tra[-1].q))
        fit = [Step(phase="poses", q=q[i].tolist()) for i in order]
        plan = Plan(name="designed", steps=[*pool.rot, *pool.tra, *fit, *pool.lock, *self.line, *self.val])
        return plan, plan_motion_time(plan, motion, self.nominal)

    def meets(self, sel: np.ndarray, tt: dict[str, np.ndarray] | None) -> bool:
        """Whether the information of ``sel`` gives every method a std within its targets ``tt`` ((4,) m each)."""
        if tt is None:
            return True
        infos = self.infos
        for m, F in infos.total(sel).items():
            C = infos.cov4[m](F)[0]
            if np.any(np.sqrt(np.maximum(np.diag(C), 0)) > tt[m]):
                return False
        return True

    def predict(self, plan: Plan) -> Prediction:
        """The plan's prediction for the request's weighting."""
        return predict_plan(plan, self.nominal, self.scene, self.bench.noise, weighting=self.req.weighting)


def _validation_steps(nominal: I4Parameters, scene: Scene, req: DesignRequest, bench: BenchSettings) -> list[Step]:
    """The validation poses: ``req.n_validation`` of the paper's validation set with the board in view."""
    if not req.n_validation:
        return []
    steps = pose_set(nominal, 3 * req.n_validation, req.seed + 2, phase="validation", ws=bench.ws, limits=bench.limits)
    return _visible_steps(steps, scene, nominal, "board", req.n_validation)


@dataclass
class _Choice:
    """A chosen count and its plan: ``n`` fit poses (candidates ``sel``), the plan, its motion time and prediction;
    ``reduced``: fewer poses than the target wanted, to fit the time allowed; ``rounds``: choices of the count made;
    ``tt``: the exchange's targets of the last choice (per method (4,) m)."""

    n: int
    sel: np.ndarray
    plan: Plan
    mt: dict[str, Any]
    pred: Prediction
    reduced: bool
    rounds: int
    tt: dict[str, np.ndarray] | None


def _choose(space: _Space, tt: dict[str, np.ndarray] | None, n_from: int, fewer: bool) -> tuple[int, np.ndarray]:
    """The count (from ``n_from`` up; ``fewer``: then down while the exchange still meets it) and the poses for
    the exchange's targets ``tt``."""
    req, infos, crit, n_hi = space.req, space.infos, space.req.criterion, space.n_hi
    if req.n_fit:
        return req.n_fit, select_poses(infos, req.n_fit, crit, tt, space.start_index(req.n_fit))
    if tt is None:
        space.reference(20)
        return 20, select_poses(infos, 20, crit, tt, None)
    greedy = select_poses(infos, n_hi, crit, tt, None, max_passes=0)
    n = next((k for k in range(n_from, n_hi + 1) if space.meets(greedy[:k], tt)), None)
    if n is None:
        return n_hi, select_poses(infos, n_hi, crit, tt, None)
    sel = select_poses(infos, n, crit, tt, greedy[:n])
    while fewer and n > req.n_min:  # the exchange may meet the target with fewer poses
        s2 = select_poses(infos, n - 1, crit, tt, greedy[: n - 1])
        if not space.meets(s2, tt):
            break
        n, sel = n - 1, s2
    return n, sel


def _fit_time(
    space: _Space, n: int, sel: np.ndarray, tt: dict[str, np.ndarray] | None
) -> tuple[int, np.ndarray, Plan, dict[str, Any], bool]:
    """The plan of ``sel``; when it takes longer than allowed, the largest that fits the time."""
    req = space.req
    plan, mt = space.build(sel)
    reduced = False
    if req.max_time_s is not None and mt["total_s"] > req.max_time_s and not req.n_fit:
        while n > req.n_min and mt["total_s"] > req.max_time_s:
            n -= 1
            reduced = True
            sel = select_poses(space.infos, n, req.criterion, tt, sel[:n])
            plan, mt = space.build(sel)
    return n, sel, plan, mt, reduced


def _excess(pred: Prediction, req: DesignRequest) -> dict[str, np.ndarray]:
    """Per optimised method and combination, the predicted std over the target (inf: no prediction)."""
    tmap = req.targets_by_method()
    assert tmap is not None
    return {
        m: ratio_to_target([pred.std[m][c] for c in COMBINATION_NAMES], tmap[m])
        if m in pred.std
        else np.full(4, np.inf)
        for m in req.methods
    }


def _choose_count(space: _Space, say: Callable[[str], None]) -> _Choice:
    """The count and the fit poses: chosen on the information, then predicted; while the prediction misses the target,
    the exchange's targets tightened by the miss and the count chosen again (:data:`DESIGN_ROUNDS` at most).

    The exchange ranks poses by their information (no correlations between rods); the plan's prediction is the
    methods' own uncertainty (their rod correlations, the camera's calibration), somewhat larger: the target is judged
    on the prediction.
    """
    req = space.req
    tt_sel, n, rounds = req.targets_by_method(), req.n_min, 0
    while True:
        say(f"choosing the fit poses{'' if req.n_fit else ' and their count'} (choice {rounds + 1})")
        n, sel = _choose(space, tt_sel, n, fewer=rounds == 0)
        n, sel, plan, mt, reduced = _fit_time(space, n, sel, tt_sel)
        say(f"predicting {n} fit poses")
        pred = space.predict(plan)
        rounds += 1
        if req.target_std_m is None or req.n_fit or reduced or n >= space.n_hi or rounds >= DESIGN_ROUNDS:
            break
        miss = _excess(pred, req)
        worst = np.max(np.stack(list(miss.values())))
        if worst <= 1.0 + 1e-9 or not np.isfinite(worst):
            break
        # tightened by the miss and a margin, so that a near miss does not take every round
        assert tt_sel is not None
        tt_sel = {m: tt_sel[m] / np.maximum(miss[m] * TIGHTEN_MARGIN, 1.0) for m in tt_sel}
    return _Choice(n, sel, plan, mt, pred, reduced, rounds, tt_sel)


@dataclass
class _PastCount:
    """What the search past ``n_max`` found: ``count_trend`` (None: not searched or nothing found), ``why`` (why the
    target is missed, "" when it says nothing) and its notes."""

    count_trend: dict[str, Any] | None = None
    why: str = ""
    notes: list[str] = field(default_factory=list)


def _past_the_count(space: _Space, ch: _Choice, say: Callable[[str], None]) -> _PastCount:
    """When the count search's most poses miss the target: :func:`.beyond_count.past_the_count_search` (``ch``
    updated in place to its choice)."""
    req = space.req
    tmap = req.targets_by_method()
    if tmap is None or req.n_fit or ch.reduced or ch.n < space.n_hi:
        return _PastCount()
    worst_hi = _worst_ratio(_excess(ch.pred, req))
    if not (np.isfinite(worst_hi) and worst_hi > 1.0 + 1e-9):
        return _PastCount()

    def design_at(k: int) -> DesignedCount:
        say(f"past the count search: {k} fit poses")
        sel_k = select_poses(space.infos, k, req.criterion, ch.tt, None)
        plan_k, mt_k = space.build(sel_k)
        return DesignedCount(k, sel_k, plan_k, mt_k, space.predict(plan_k))

    past = past_the_count_search(
        DesignedCount(ch.n, ch.sel, ch.plan, ch.mt, ch.pred),
        design_at,
        lambda p: _worst_ratio(_excess(p, req)),
        tmap,
        req.max_time_s,
        min(N_FIT_MOST, len(space.cq)),
    )
    if past is None:
        return _PastCount()
    best, count_trend, trend_why, note = past
    ch.n, ch.sel, ch.plan, ch.mt, ch.pred = best
    return _PastCount(count_trend, trend_why, [note] if note else [])


def _miss_reason(space: _Space, ch: _Choice, trend_why: str) -> str:
    """Why the target is missed: the time, the fixed count, the trend past the count search, the most poses tried or
    the rounds of the count's choice."""
    if ch.reduced:
        return "within the time allowed"
    if space.req.n_fit:
        return f"with {ch.n} fit poses"
    if trend_why:
        return trend_why
    if ch.n >= space.n_hi:
        return f"with {ch.n} fit poses (the most tried; more candidate poses may reach it)"
    return f"with {ch.n} fit poses after {ch.rounds} choices of the count"


def _outcome_notes(space: _Space, ch: _Choice, past: _PastCount) -> tuple[bool | None, bool | None, list[str]]:
    """Whether the target and the time are met (None: not asked for) and the notes on the outcome."""
    req = space.req
    tmap = req.targets_by_method()
    notes: list[str] = []
    if not req.n_fit and req.max_time_s is not None and ch.mt["total_s"] > req.max_time_s:
        fixed_part = ch.mt["total_s"] - ch.mt["per_phase_s"].get("poses", 0.0)
        notes.append(f"the plan without fit poses already takes {fixed_part / 60:.1f} min")
    if not req.n_fit and req.target_std_m is None:
        notes.append("no target and no count: 20 fit poses (the paper's count)")
    target_met = None if tmap is None else bool(all(np.all(v <= 1.0 + 1e-9) for v in _excess(ch.pred, req).values()))
    time_met = None if req.max_time_s is None else ch.mt["total_s"] <= req.max_time_s
    if target_met is False:
        assert tmap is not None
        notes.append(
            "the target is not met (predicted): " + _miss_reason(space, ch, past.why) + _worst_miss(ch.pred, tmap)
        )
    shading = shading_note(ch.pred)
    if shading:
        notes.append(shading)
    if "legs" in req.methods:
        lo, hi = LEGS_DESIGNED_PREDICTION_RATIO_RANGE
        notes.append(
            "designed for the legs method: the poses are those its predicted std is smallest for, so what its model "
            "leaves out weighs more there; on the simulated bench's five plans designed so its prediction was "
            f"{lo:.2f}-{hi:.2f}x its RMS error (docs/design.md)"
        )
    return target_met, time_met, notes


def _request_summary(req: DesignRequest) -> dict[str, Any]:
    """The request as the plan's ``design.request`` records it."""
    t = req.targets()
    return {
        "n_fit": req.n_fit,
        "target_std_m": None if t is None else t.tolist(),
        **({"method_targets_m": {m: list(v) for m, v in req.method_targets_m}} if req.method_targets_m else {}),
        "max_time_s": req.max_time_s,
        "criterion": req.criterion,
        "methods": list(req.methods),
        "seed": req.seed,
        "draws": req.draws,
        "candidate_draw": req.candidate_draw,
    }


def _result(space: _Space, ch: _Choice, past: _PastCount) -> DesignResult:
    """The design's result: the plan (its ``design`` field the summary and the request), prediction, figures, notes."""
    target_met, time_met, outcome = _outcome_notes(space, ch, past)
    infos, pool = space.infos, space.pool
    F = infos.total(ch.sel)
    result = DesignResult(
        plan=ch.plan,
        prediction=ch.pred,
        motion=ch.mt,
        n_fit=int(ch.n),
        sweeps={"rotation_span_deg": float(pool.span), "translation_length_m": float(pool.length)},
        target_met=target_met,
        time_met=time_met,
        criterion={f"logdet_{m}": float(infos.cov4[m](F[m])[1]) for m in F},
        candidates={
            "drawn": len(pool.cand_q),
            "visible": int(pool.visible.sum()),
            "reference_visible": space.n_vis_ref,
        },
        notes=[*space.notes, *past.notes, *outcome],
        count_trend=past.count_trend,
    )
    design = result.summary()
    design["request"] = _request_summary(space.req)
    result.plan = Plan.model_validate({**ch.plan.model_dump(exclude_none=True), "design": design})
    return result


def design_plan(
    nominal: I4Parameters,
    scene: Scene,
    request: DesignRequest | None = None,
    *,
    limits: SoftLimits | None = None,
    motion: MotionSpec | None = None,
    noise: DesignNoise | ImageNoise | None = None,
    ws: Workspace | None = None,
    cache: dict[Any, Any] | None = None,
    status: Callable[[str], None] | None = None,
    draws_runner: DrawsRunner | None = None,
) -> DesignResult:
    """Design a plan: sweeps, fit poses (count, choice, order), lock and validation poses; predict it.

    The stages: the candidate pool (:func:`_candidate_pool`: sweeps, lock phases, the candidates' visibility and
    information), the design space (:class:`_Space`: the reference poses, validation, line), the count and the poses
    (:func:`_choose_count`), past the count search when its most poses miss the target (:func:`_past_the_count`),
    the result and its notes (:func:`_result`).

    Parameters
    ----------
    nominal : I4Parameters
        The bench's nominal geometry (m, rad).
    scene : Scene
        The camera, its mounting, the board and the rods.
    request : DesignRequest, optional
        What to design (default: ``DesignRequest()``).
    limits, motion, noise, ws : optional
        The bench's soft limits, motion figures, measurement noise and workspace (:class:`BenchSettings`' fields;
        defaults: theirs).
    cache : dict, optional
        Shared by designs that differ only in their count, target or criterion (a trade-off,
        :func:`.tradeoff.design_tradeoff`; the same ``limits``, ``motion``, ``noise`` and ``ws``): the sweeps, the
        drawn candidates' visibility and information are computed once per candidate draw (the same design, faster).
    status : callable, optional
        Called with a line saying what the design is doing (a long design's progress: the candidates' draw, each
        count designed and predicted).
    draws_runner : DrawsRunner, optional
        Runs the ``request.draws`` candidate draws' designs (:data:`DrawsRunner`, e.g. fanned out over processes or
        machines; default one after the other here); a draw that fails there is left out and said in the notes, the
        best of the others kept.

    Returns
    -------
    DesignResult
        ``plan`` (a :class:`calib.formats.plan.Plan` named ``designed``, its ``design`` field holding the summary)
        that :func:`calib.formats.plan.validate_plan` accepts for ``limits``.
    """
    req = request or DesignRequest()
    bench = BenchSettings(
        limits=limits or SoftLimits(), motion=motion or MotionSpec(), noise=noise or DesignNoise(), ws=ws or Workspace()
    )
    if req.draws > 1:
        return _best_of_draws(nominal, scene, req, draws_runner, bench=bench, cache=cache, status=status)
    say = status or (lambda _line: None)
    say(f"{req.n_candidates} candidate poses: sweeps, visibility, information")
    pool = _candidate_pool(nominal, scene, req, bench.limits, bench.ws, bench.noise, cache)
    space = _Space(nominal, scene, req, bench, pool)
    choice = _choose_count(space, say)
    past = _past_the_count(space, choice, say)
    return _result(space, choice, past)


def design_score(result: DesignResult, request: DesignRequest) -> tuple[float, ...]:
    """How good a design is, lower better: a met target first, then fewer fit poses when the count was free,
    then the criterion on the plan's prediction (``"target"``: the worst predicted std over its target among the
    optimised methods; ``"a"``: the sum of their predicted variances, over the targets' squares when given, else
    per mm^2; ``"d"``: minus the sum of their information's log-determinants), then the motion time.

    Parameters
    ----------
    result : DesignResult
        A design.
    request : DesignRequest
        What it was designed for (criterion, methods, targets in m, whether the count was fixed).

    Returns
    -------
    tuple of 4 float
        (target missed, fit poses, criterion, motion time in s), compared in that order; all inf when an optimised
        method has no prediction.
    """
    pred, t = result.prediction, request.targets_by_method()
    if any(m not in pred.std for m in request.methods):  # a method the plan cannot determine: last, whatever else
        return (np.inf, np.inf, np.inf, np.inf)
    stds = count_std(pred.std, request.methods)
    if request.criterion == "target":
        assert t is not None
        crit = float(max(np.max(ratio_to_target(sd, t[m])) for m, sd in stds.items()))
    elif request.criterion == "a":
        with np.errstate(over="ignore"):  # the ratios' squares: infinite for the tiniest targets, as intended
            crit = float(
                sum(
                    np.sum(ratio_to_target(sd, t[m] if t is not None else np.full(4, 1e-3)) ** 2)
                    for m, sd in stds.items()
                )
            )
    else:
        crit = -float(sum(v for k, v in result.criterion.items() if k.startswith("logdet_")))
    return (
        float(result.target_met is False),
        float(result.n_fit if request.n_fit is None else 0),
        crit,
        float(result.motion["total_s"]),
    )


def _one_draw(nominal: I4Parameters, scene: Scene, req: DesignRequest, kw: dict[str, Any], k: int) -> DesignResult:
    """Draw ``k``'s design (its candidates seeded from the request's seed and ``k`` alone, wherever it runs)."""
    return design_plan(nominal, scene, replace(req, draws=1, candidate_draw=k), **kw)


def _best_of_draws(
    nominal: I4Parameters,
    scene: Scene,
    req: DesignRequest,
    runner: DrawsRunner | None,
    bench: BenchSettings,
    cache: dict[Any, Any] | None,
    status: Callable[[str], None] | None,
) -> DesignResult:
    """:func:`design_plan` for each of ``req.draws`` draws of the candidates; the best by :func:`design_score`.
    With ``runner``: the draws run there, a failed one is left out (said in the notes) unless all failed."""
    kw: dict[str, Any] = {
        "limits": bench.limits,
        "motion": bench.motion,
        "noise": bench.noise,
        "ws": bench.ws,
        "cache": cache,
    }
    outcomes: list[DesignResult | BaseException] = []
    if runner is None:
        for k in range(req.draws):
            tell = None if status is None else (lambda line, k=k: status(f"draw {k + 1}/{req.draws}: {line}"))
            outcomes.append(design_plan(nominal, scene, replace(req, draws=1, candidate_draw=k), status=tell, **kw))
    else:
        outcomes = runner(functools.partial(_one_draw, nominal, scene, req, kw), req.draws)
    failed = [(k, r) for k, r in enumerate(outcomes) if isinstance(r, BaseException)]
    drawn = [k for k, r in enumerate(outcomes) if not isinstance(r, BaseException)]
    results = [r for r in outcomes if not isinstance(r, BaseException)]
    if not results:
        raise failed[0][1]
    scores = [design_score(r, req) for r in results]
    i = min(range(len(results)), key=lambda j: scores[j])
    best, k = results[i], drawn[i]
    best.notes.append(
        f"best of {req.draws} draws of {req.n_candidates} candidate poses (draw {k}; "
        + ", ".join(f"{s[2]:.4g}" for s in scores)
        + " by the criterion)"
    )
    best.notes += [f"draw {j} failed, left out: {type(e).__name__}: {e}" for j, e in failed]
    design = dict((best.plan.model_extra or {}).get("design") or {})
    design["request"] = {**design.get("request", {}), "draws": req.draws, "candidate_draw": k}
    design["notes"] = best.notes
    by_draw = dict(zip(drawn, (s[2] for s in scores), strict=True))
    design["draws_criterion"] = [by_draw.get(j) for j in range(req.draws)]
    best.plan = Plan.model_validate({**best.plan.model_dump(exclude_none=True), "design": design})
    return best
