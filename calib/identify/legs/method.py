"""``calibrate_legs``: the legs method end to end, one function per stage.

The stages, in order (each a function with typed inputs and outputs):

1. :func:`lock_phases`: the four lock phases, each actuator checked locked;
2. :func:`locate_joints`: step 1, the eight upper joints (image planes when every rod carries them, else line
   intersections), then the rod-pair check (:func:`.uncertainty._pair_consistency`);
3. :func:`fit_directions` (the fit poses' leg directions) and :func:`repair_stage` (one wrong joint repaired);
4. :func:`fit_seven`: steps 2-4 with the poses gated by a robust fit;
5. the uncertainty: :func:`joints_part`, :func:`directions_part`, :func:`camera_part` (the intrinsics and the
   limb-edge bias, corrected by the combined fit's measurements when given);
6. :func:`apply_prior`: the a priori tolerance, then :func:`legs_result` assembles the :class:`MethodResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from scipy.linalg import block_diag

from calib.camera.intrinsics import intrinsics_names
from calib.errors import IdentifiabilityError
from calib.formats.observations import Observations, PhaseArrays
from calib.identify.combined import EDGE_BIAS_STD_PX
from calib.identify.combined_measurements import CombinedMeasurements, measure_with_combined
from calib.identify.edge_bias import MeasuredEdgeBias
from calib.identify.iterations import IterationCallback
from calib.identify.legs.constants import JOINT_DEPTH_SYS_LEG_SHARE, JOINT_DEPTH_SYS_M, PRIOR_STD_M
from calib.identify.legs.joints import (
    PlaneObservation,
    _plane_observations,
    intersect_lines,
    joint_from_planes,
    step1_planes,
)
from calib.identify.legs.repair import REPAIR_CHI2_MAX, REPAIR_PAIR_FACTOR, JointRepair, repair_joint
from calib.identify.legs.steps import (
    LegsModel,
    gate_poses,
    leg_directions,
    pair_means,
    pair_own_covariances,
    rod_own_covariances,
    steps34_covariance,
    steps34_sandwich,
)
from calib.identify.legs.uncertainty import (
    IntrinsicsEffect,
    _identifiability,
    _pair_consistency,
    _prior_conflict,
    joint_depth_systematic,
    null_space_to_prior,
    with_prior,
)
from calib.identify.measured_intrinsics import MeasuredIntrinsics
from calib.identify.result import MethodResult, combos_dict, std_dict
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, SEVEN_TO_FOUR, I4Parameters
from calib.numerics.robust import chi2_gate

#: step 2's parameters (H, q02, q03, q04; indices into PARAMETER_NAMES): from the lock phases' joints alone
_STEP2 = np.array([PARAMETER_NAMES.index(n) for n in ("H", "q02", "q03", "q04")])
#: the others (S, D, L): also from the fit poses' leg directions
_STEPS34 = np.setdiff1d(np.arange(len(PARAMETER_NAMES)), _STEP2)
#: (L, S, D) in the seven parameters (PARAMETER_NAMES order)
_LSD = np.array([6, 4, 5])
#: a joint coordinate's step for the numerical derivatives of steps 2-4 (m)
_JOINT_STEP_M = 1e-7


@dataclass(frozen=True)
class LegsSettings:
    """The legs method's settings (see :func:`calibrate_legs` for each).

    Attributes
    ----------
    fit_phases : tuple of str
        Phases of steps 3-4's fit poses.
    direction_std_rad : float or None
        Rod direction noise per tangent axis (rad) for rods without ``cov_u``; None: from the residuals.
    edge_bias_std_px : float
        Allowance (px, per limb) for a limb-edge bias common to every rod when none is measured.
    prior_std_m : float or None
        A priori tolerance (m) of each of the seven parameters; None or 0: no prior.
    joint_depth_sys_m : float
        RMS (m) of each lock-phase joint's systematic error along its line of sight; 0: left out.
    """

    fit_phases: tuple[str, ...] = ("poses",)
    direction_std_rad: float | None = None
    edge_bias_std_px: float = EDGE_BIAS_STD_PX
    prior_std_m: float | None = PRIOR_STD_M
    joint_depth_sys_m: float = JOINT_DEPTH_SYS_M


@dataclass(frozen=True)
class LockPhases:
    """The four lock phases: ``q_lock`` (4,) each locked actuator's value (m), ``data`` their frames."""

    q_lock: np.ndarray
    data: list[PhaseArrays]


@dataclass
class Joints:
    """Step 1's output.

    Attributes
    ----------
    P : ndarray, shape (4, 2, 3)
        Upper joints, camera frame (m).
    cov : ndarray, shape (4, 2, 3, 3)
        Their covariances (m^2), scaled by ``s2``.
    s2, s2_raw : float
        Chi-square per dof that scales them, and the residuals' own (before the floor at 1 of absolute variances).
    rejected : list of dict
        Lock-phase frames dropped (``lock``, ``rod``, ``frame_of_rod``).
    residual_rms_m : float
    n_lines : int
        Rod observations used.
    planes : list or None
        The plane observations ([4][2] lists) when step 1 used image planes, else None (line intersections).
    keep : list or None
        The frames kept per rod ([4][2] bool arrays) with planes.
    """

    P: np.ndarray
    cov: np.ndarray
    s2: float
    s2_raw: float
    rejected: list[dict[str, int]]
    residual_rms_m: float
    n_lines: int
    planes: list[list[list[PlaneObservation]]] | None = None
    keep: list[list[np.ndarray]] | None = None

    @property
    def use_planes(self) -> bool:
        return self.planes is not None


@dataclass(frozen=True)
class FitDirections:
    """The fit poses' leg directions (:func:`.pipeline.leg_directions`): ``U`` (N, 4, 3), ``CU`` (N, 4, 3, 3), ``pts``
    (N, 4, 3) a point on each leg, ``has_leg`` (N, 4), ``measured`` (the rods' own covariances used),
    ``rejected_pairs``, ``C_rods`` (N, 4, 2, 3, 3) the rods' covariances."""

    data: PhaseArrays
    U: np.ndarray
    CU: np.ndarray
    pts: np.ndarray
    has_leg: np.ndarray
    measured: bool
    rejected_pairs: list[dict[str, int]]
    C_rods: np.ndarray


@dataclass
class RepairedFit:
    """Steps 2-4's model over the fit poses after the repair stage: ``model``, ``U`` (N, 4, 3, zero where unused),
    ``has_rod`` (N, 4, 2), the used joints ``P`` (4, 2, 3) and their covariance ``covP`` (24, 24), ``repair``, the
    updated rod-pair check and warnings."""

    model: LegsModel
    U: np.ndarray
    has_rod: np.ndarray
    P: np.ndarray
    covP: np.ndarray
    repair: JointRepair | None
    pair_check: list[dict]
    warnings: list[str]


@dataclass(frozen=True)
class SevenFit:
    """Steps 2-4's estimate: ``seven`` (7,) PARAMETER_NAMES order (m), ``x2`` (q02, q03, q04, H), ``lsd`` (L, S, D),
    ``rejected_poses`` (frame indices)."""

    seven: np.ndarray
    x2: np.ndarray
    lsd: np.ndarray
    rejected_poses: list[int]


@dataclass(frozen=True)
class DirectionsPart:
    """The fit poses' leg directions' part of the seven's covariance ``cov`` (7, 7), m^2, with its chi-square levels:
    ``s2`` (applied), ``s2_raw`` (residuals), ``expected`` (the chi-square the own errors and the joints' make it
    expect; None without ``cov_u_own``) and ``dof``."""

    cov: np.ndarray
    s2: float
    s2_raw: float
    expected: float | None
    dof: int


@dataclass
class CameraPart:
    """The camera's part: the intrinsics' and the limb-edge bias's covariances (7, 7), m^2, their notes for the
    diagnostics, and the seven re-estimated with the measured corrections (unchanged without them)."""

    cov_intrinsics: np.ndarray
    cov_edge: np.ndarray
    edge_note: dict | None
    intrinsics_note: dict
    seven: np.ndarray


@dataclass
class PriorOutcome:
    """The estimate after the a priori tolerance: ``seven``, ``cov`` (7, 7), ``parts`` (named (7, 7) parts), the
    identifiability report and the prior-conflict figures."""

    seven: np.ndarray
    cov: np.ndarray
    parts: dict[str, np.ndarray]
    ident: dict
    conflict: float | None = None
    conflict_joints: float | None = None
    fallback: str | None = None
    not_identified: list[dict] = field(default_factory=list)


def calibrate_legs(
    obs: Observations,
    *,
    fit_phases: tuple[str, ...] = ("poses",),
    direction_std_rad: float | None = None,
    on_iteration: IterationCallback | None = None,
    edge_bias_std_px: float = EDGE_BIAS_STD_PX,
    prior_std_m: float | None = PRIOR_STD_M,
    edge_bias: MeasuredEdgeBias | bool | None = True,
    joint_depth_sys_m: float = JOINT_DEPTH_SYS_M,
    intrinsics: MeasuredIntrinsics | bool | None = True,
    combined: CombinedMeasurements | None = None,
    settings: LegsSettings | None = None,
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
        standard deviations like the intrinsics when no measured bias is used (here it is not identifiable apart
        from the joints and the rod radius).
    edge_bias : MeasuredEdgeBias, True or None
        The limb-edge bias the combined fit measured on the same rods (per limb, outward px, and its covariance).
        Every rod's limbs are corrected by it (the whole estimate redone, as for the intrinsics) and its covariance
        replaces the ``edge_bias_std_px`` allowance. True (default): ``combined``'s; None or False: the allowance
        only.
    joint_depth_sys_m : float
        RMS (m) of each lock-phase joint's systematic error along its line of sight when the joints come from image
        planes (:data:`.constants.JOINT_DEPTH_SYS_M`, half of its variance common to a leg's two joints): the rods'
        shading biases their limb edges the same way in every frame of a lock phase. Propagated like the joints'
        noise (``std_breakdown.joint_depth_systematic``); 0: left out.
    intrinsics : MeasuredIntrinsics, True or None
        The intrinsics as the combined fit re-estimates them on the same rods
        (:mod:`calib.identify.measured_intrinsics`:
        the shift from the extraction's camera and its posterior covariance). Every rod is re-measured through them
        (the whole estimate redone, with the edge-bias correction) and their posterior is the intrinsics' part of the
        std. True (default): ``combined``'s; None or False: the extraction's camera and its ``covariance_refined``.
    prior_std_m : float or None
        Standard deviation (m) of each of the seven parameters around the nominal (a priori) geometry: the
        bench's manufacturing tolerance. Along the directions the legs' data know less well than it (their
        variance above its square), the estimate is combined with it (linear-Gaussian posterior), so that such a
        direction stays near the a priori value with about its tolerance as std instead of wherever the data
        drift (``std_breakdown.a_priori``; ``diagnostics.identifiability``; a warning names the directions);
        elsewhere the data's estimate is kept unchanged (:func:`with_prior`). None or 0: no prior.
    combined : CombinedMeasurements, optional
        What the combined fit of the same run measured (the pipeline passes it forward). Not given while
        ``edge_bias`` or ``intrinsics`` is True and the rods carry limb samples and the camera its covariance: the
        combined fit is run once here, before the stages (:func:`.combined_measurements.measure_with_combined`).
    settings : LegsSettings, optional
        All the numeric settings at once; given, it replaces ``fit_phases``, ``direction_std_rad``,
        ``edge_bias_std_px``, ``prior_std_m`` and ``joint_depth_sys_m``.

    Returns
    -------
    MethodResult
        With ``parameters`` (seven) and ``parameters_std``.
    """
    cfg = settings or LegsSettings(fit_phases, direction_std_rad, edge_bias_std_px, prior_std_m, joint_depth_sys_m)
    lock = lock_phases(obs)
    planes = plane_observations(obs, lock)
    data = obs.arrays(*cfg.fit_phases)
    eff = IntrinsicsEffect.build(obs, lock.data, data) if planes is not None else None
    if eff is not None and combined is None and (edge_bias is True or intrinsics is True):
        combined = measure_with_combined(obs)  # the standalone method: the combined fit once, before the stages
    joints = locate_joints(lock, planes)
    cov_checked, pair_check, warnings = _pair_consistency(joints.P, joints.cov)
    dirs = fit_directions(obs, data, cfg.direction_std_rad)
    fit = repair_stage(lock, joints, cov_checked, dirs, pair_check, warnings, obs.nominal)
    est = fit_seven(fit, dirs.data, on_iteration)
    cov_joints, cov_jsys = joints_part(fit, est, joints.use_planes, cfg.joint_depth_sys_m)
    dpart = directions_part(obs, fit, est, dirs, cfg.direction_std_rad)
    cam = CameraPart(np.zeros((7, 7)), np.zeros((7, 7)), None, {"applied": False}, est.seven)
    if eff is not None:
        measurements = combined or CombinedMeasurements()
        measured_edge = measurements.edge_bias if edge_bias is True else edge_bias
        measured_intr = measurements.intrinsics if intrinsics is True else intrinsics
        cam = camera_part(eff, joints, fit, est, dirs, cfg.edge_bias_std_px, measured_edge, measured_intr)
    parts7 = {
        "joint_centres": cov_joints,
        "joint_depth_systematic": cov_jsys,
        "leg_directions": dpart.cov,
        "intrinsics": cam.cov_intrinsics,
        "limb_edge_bias": cam.cov_edge,
    }
    prior = apply_prior(cam.seven, parts7, obs.nominal, cfg.prior_std_m, joints.use_planes, fit.warnings)
    return legs_result(obs, cfg, lock, joints, dirs, fit, est, dpart, cam, prior, seven_data=cam.seven.copy())


def lock_phases(obs: Observations) -> LockPhases:
    """The four lock phases' frames and locked values, checked.

    Parameters
    ----------
    obs : Observations

    Returns
    -------
    LockPhases

    Raises
    ------
    IdentifiabilityError
        A lock phase missing, its actuator moving (more than 0.1 mm) or a rod with fewer than 2 observations with a
        point.
    """
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
    return LockPhases(q_lock, lock_data)


def plane_observations(obs: Observations, lock: LockPhases) -> list[list[list[PlaneObservation]]] | None:
    """Every lock-phase rod's frames as plane observations.

    Parameters
    ----------
    obs : Observations
    lock : LockPhases

    Returns
    -------
    list of list of list of PlaneObservation, or None
        Per lock phase and rod ([4][2]), its frames' planes (normals in the camera frame, the rod radius in m); None
        when a rod's frame lacks them (``h`` or a point).
    """
    planes = [[_plane_observations(obs, lock.data[i], i, j) for j in range(2)] for i in range(4)]
    if not all(p is not None for row in planes for p in row):
        return None
    return cast("list[list[list[PlaneObservation]]]", planes)


def locate_joints(lock: LockPhases, planes: list[list[list[PlaneObservation]]] | None) -> Joints:
    """Step 1: the eight upper joints from the image planes (weighted, gated; :func:`.joints.step1_planes`) or, without
    planes, as the least-squares intersections of each rod's axis lines (unweighted).

    Parameters
    ----------
    lock : LockPhases
    planes : list or None
        :func:`plane_observations`'s output.

    Returns
    -------
    Joints
    """
    if planes is not None:
        frames = [[np.nonzero(lock.data[i].has_rod[:, i, j])[0] for j in range(2)] for i in range(4)]
        s1 = step1_planes(planes, frames)
        n_lines = sum(len(planes[i][j]) for i in range(4) for j in range(2))
        return Joints(s1.P, s1.cov, s1.s2, s1.s2_raw, s1.rejected, s1.residual_rms_m, n_lines, planes, s1.keep)
    P = np.zeros((4, 2, 3))
    Acc = np.zeros((4, 2, 3, 3))
    ss, dof1, n_lines = 0.0, 0, 0
    for i in range(4):
        d = lock.data[i]
        for j in range(2):
            ok = d.has_rod[:, i, j] & d.has_point[:, i, j]
            P[i, j], Acc[i, j], res = intersect_lines(d.rod_p[ok, i, j], d.rod_u[ok, i, j])
            ss += float(np.sum(res**2))
            dof1 += 2 * int(ok.sum()) - 3
            n_lines += int(ok.sum())
    s2 = ss / dof1 if dof1 > 0 else 0.0
    return Joints(P, s2 * np.linalg.inv(Acc), s2, s2, [], float(np.sqrt(s2)), n_lines)


def fit_directions(obs: Observations, data: PhaseArrays, direction_std_rad: float | None) -> FitDirections:
    """The fit poses' leg directions and their covariances (:func:`.pipeline.leg_directions`).

    Parameters
    ----------
    obs : Observations
    data : PhaseArrays
        The fit poses (N frames).
    direction_std_rad : float or None
        Rod direction noise (rad) for rods without ``cov_u``; None: relative (scaled by the residuals).

    Returns
    -------
    FitDirections
    """
    U, CU, pts, has_leg, measured, rejected, C_rods = leg_directions(obs, data, direction_std_rad)
    return FitDirections(data, U, CU, pts, has_leg, measured, rejected, C_rods)


def repair_stage(
    lock: LockPhases,
    joints: Joints,
    cov_checked: np.ndarray,
    dirs: FitDirections,
    pair_check: list[dict],
    warnings: list[str],
    nominal: I4Parameters,
) -> RepairedFit:
    """Step 1c: one flagged leg whose wrong joint the fit poses single out is repaired from its partner and the other
    legs' separation (:mod:`.repair`); the joints' covariance follows the linear map exactly.

    Parameters
    ----------
    lock : LockPhases
    joints : Joints
        Step 1's joints, with their measured covariance.
    cov_checked : ndarray, shape (4, 2, 3, 3)
        Their covariances after the rod-pair check (m^2).
    dirs : FitDirections
    pair_check, warnings : list
        The rod-pair check's report and warnings (updated by a repair).
    nominal : I4Parameters
        The a priori geometry (the fits' start).

    Returns
    -------
    RepairedFit
    """
    data = dirs.data
    model = LegsModel(lock.q_lock, data.q, dirs.pts, dirs.has_leg, dirs.CU, nominal)
    U_filled = np.where(dirs.has_leg[..., None], dirs.U, 0.0)
    covP = block_diag(*cov_checked.reshape(8, 3, 3))  # the joints' (24, 24), (leg, rod, xyz) order
    has_rod = data.has_rod

    def fit_data(leg: int, rod: int | None) -> tuple[LegsModel, np.ndarray]:
        if rod is None:
            return model, U_filled
        hr = has_rod.copy()
        hr[:, leg, rod] = False
        hl = dirs.has_leg & hr.any(axis=2)
        U_r, CU_r, _ = pair_means(data.rod_u, hr, dirs.C_rods)
        return LegsModel(lock.q_lock, data.q, dirs.pts, hl, CU_r, model.nominal), np.where(hl[..., None], U_r, 0.0)

    flagged = [c["leg"] - 1 for c in pair_check if c["scale"] > 1.0 and c["chi2"] >= REPAIR_PAIR_FACTOR * c["gate"]]
    P = joints.P
    repair = repair_joint(P, flagged, fit_data, chi2_max=REPAIR_CHI2_MAX if dirs.measured else None)
    if repair is not None and repair.left_out_of_fit_poses:
        model, U_filled = fit_data(repair.leg, repair.rod)
        has_rod = has_rod.copy()
        has_rod[:, repair.leg, repair.rod] = False
    if repair is not None:
        P = repair.apply(joints.P)
        covP = repair.T @ block_diag(*joints.cov.reshape(8, 3, 3)) @ repair.T.T
        pair_check[repair.leg]["repaired_rod"] = repair.rod
        warnings = [w for w in warnings if not w.startswith(f"lock-{repair.leg + 1}:")]
        warnings.append(repair.warning(pair_check[repair.leg]["deviation_mm"]))
    return RepairedFit(model, U_filled, has_rod, P, covP, repair, pair_check, warnings)


def fit_seven(fit: RepairedFit, data: PhaseArrays, on_iteration: IterationCallback | None = None) -> SevenFit:
    """Steps 2-4: poses judged by a robust fit (each round, at most 5), then the least-squares fit of the poses kept.

    Parameters
    ----------
    fit : RepairedFit
        Its model's legs are narrowed to the poses kept.
    data : PhaseArrays
        The fit poses (for the rejected frames' indices).
    on_iteration : callable, optional

    Returns
    -------
    SevenFit
    """
    model, P, U = fit.model, fit.P, fit.U
    seven = model.run(P, U, robust=True)
    rejected_poses: list[int] = []
    for _ in range(5):
        bad = gate_poses(model, P, U, seven)
        if not bad.any() or (model.mask.sum() - model.mask[bad].sum()) < 6:
            break
        rejected_poses += [int(data.index[k]) for k in np.nonzero(bad)[0]]
        model.set_legs(model.has_leg & ~bad[:, None])
        seven = model.run(P, U, robust=True)
    model.W = None
    seven = model.run(P, U, on_iteration=on_iteration)
    x2 = np.array([*seven[1:4].tolist(), seven[0]])
    return SevenFit(seven, x2, seven[_LSD], rejected_poses)


def joints_part(
    fit: RepairedFit, est: SevenFit, use_planes: bool, joint_depth_sys_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The joints' part of the seven's covariance: their noise propagated through steps 2-4 (numerical derivatives,
    weights fixed) and, with image planes, their systematic depth error from the rods' shading, which the lock phases'
    frames cannot average and their chi-square does not show.

    Returns
    -------
    cov_joints, cov_systematic : ndarray, shape (7, 7)
        m^2.

    Parameters
    ----------
    fit : RepairedFit
        Steps 2-4's model over the fit poses, with the used joints and their covariance ``covP`` (24, 24), m^2.
    est : SevenFit
        Steps 2-4's estimate (the re-runs start there).
    use_planes : bool
        Whether the joints come from image planes (then the systematic depth error is added).
    joint_depth_sys_m : float
        Std of the joints' systematic depth error, m.
    """

    def f(Pv: np.ndarray) -> np.ndarray:
        return fit.model.run(Pv, fit.U, est.x2, theta_init=est.lsd)

    h = _JOINT_STEP_M
    GP = np.zeros((7, 24))
    for a in range(24):
        dP = np.zeros(24)
        dP[a] = h
        GP[:, a] = (f(fit.P + dP.reshape(4, 2, 3)) - f(fit.P - dP.reshape(4, 2, 3))) / (2 * h)
    cov_joints = GP @ fit.covP @ GP.T
    cov_jsys = np.zeros((7, 7))
    if use_planes and joint_depth_sys_m > 0:
        cov_jsys = GP @ joint_depth_systematic(fit.P, joint_depth_sys_m, JOINT_DEPTH_SYS_LEG_SHARE) @ GP.T
    return cov_joints, cov_jsys


def directions_part(
    obs: Observations, fit: RepairedFit, est: SevenFit, dirs: FitDirections, direction_std_rad: float | None
) -> DirectionsPart:
    """The fit poses' leg directions' part: the GLS covariance of (L, S, D) scaled by the chi-square, or, with the rods'
    own errors (``cov_u_own``), those through the fit's gain at the level the chi-square shows beyond what they and
    the joints' make it expect (never below 1: both are absolute).

    Parameters
    ----------
    obs : Observations
    fit : RepairedFit
    est : SevenFit
    dirs : FitDirections
    direction_std_rad : float or None
        Known rod direction noise (rad) for rods without ``cov_u`` (then the scale is 1).

    Returns
    -------
    DirectionsPart
        Its covariance (7, 7), m^2, in the (L, S, D) block.
    """
    c34, chi34, dof34 = steps34_covariance(fit.model, fit.P, fit.U, est.seven)
    s2_raw = chi34 / dof34 if dof34 > 0 else 1.0
    s2 = 1.0 if (not dirs.measured and direction_std_rad is not None) else s2_raw
    C_own = rod_own_covariances(obs, dirs.data) if dirs.measured else None
    expected = None
    if C_own is not None:
        CU_own = np.nan_to_num(pair_own_covariances(dirs.data.rod_u, fit.has_rod, dirs.C_rods, C_own))
        c34, chi_w, expected = steps34_sandwich(fit.model, fit.P, fit.U, est.seven, CU_own, fit.covP)
        s2 = max(chi_w / expected, 1.0) if expected > 0 else 1.0
    elif dirs.measured:  # cov_u is absolute (with the extraction's edge-bias allowance): scaled up, never down
        s2 = max(s2, 1.0)
    cov = np.zeros((7, 7))
    cov[np.ix_(_LSD, _LSD)] = s2 * c34
    return DirectionsPart(cov, s2, s2_raw, expected, dof34)


def camera_part(
    eff: IntrinsicsEffect,
    joints: Joints,
    fit: RepairedFit,
    est: SevenFit,
    dirs: FitDirections,
    edge_bias_std_px: float,
    measured_edge: MeasuredEdgeBias | bool | None,
    measured_intr: MeasuredIntrinsics | bool | None,
) -> CameraPart:
    """The camera's intrinsics and the limb-edge bias common to every rod: the whole estimate redone (frames, gating
    and weights fixed) with the rods measured through the intrinsics moved by one standard deviation along each
    principal direction of their covariance, and through a limb-edge bias of one step per limb; then, with the
    combined fit's measurements, the rods corrected by them and their covariances as these parts.

    Parameters
    ----------
    eff : IntrinsicsEffect
        The rods as measured through other intrinsics (needs image planes and limb samples).
    joints, fit, est, dirs
        The earlier stages' outputs.
    edge_bias_std_px : float
        Allowance (px per limb) when no bias is measured.
    measured_edge : MeasuredEdgeBias, bool or None
        The combined fit's limb-edge bias (falsy: the allowance).
    measured_intr : MeasuredIntrinsics, bool or None
        The combined fit's intrinsics (falsy: the extraction's camera).

    Returns
    -------
    CameraPart
    """
    planes, keep1 = joints.planes, joints.keep
    assert planes is not None and keep1 is not None  # eff is built only with image planes
    repair, model = fit.repair, fit.model

    def seven_for(z: np.ndarray) -> np.ndarray:
        pz = eff.lock_planes(z, planes)
        Pz = np.array(
            [
                [joint_from_planes([o for o, kk in zip(pz[i][j], keep1[i][j], strict=True) if kk])[0] for j in range(2)]
                for i in range(4)
            ]
        )
        if repair is not None:
            Pz = repair.apply(Pz)
        Uz = pair_means(eff.rod_u(z, dirs.data.rod_u), fit.has_rod, dirs.C_rods)[0]
        return model.run(Pz, np.where(model.has_leg[..., None], Uz, 0.0), est.x2, theta_init=est.lsd)

    # one standard deviation along each principal direction, then the limb-edge bias common to every rod (per limb,
    # the combined method's prior: shading and optics bias every rod's limb alike, so it does not average out)
    nz = eff.steps.shape[0]
    E = np.zeros((nz + 2, nz + 2))
    E[:nz, :nz] = np.eye(nz)
    step_px = edge_bias_std_px if edge_bias_std_px > 0 else EDGE_BIAS_STD_PX
    E[nz:, nz:] = step_px * np.eye(2)
    Jz = np.stack([(seven_for(e) - seven_for(-e)) / 2.0 for e in E], axis=1)
    cov_intr = Jz[:, :nz] @ Jz[:, :nz].T
    J_px = Jz[:, nz:] / step_px  # the seven's change per px of outward bias on each limb
    # the intrinsics re-estimated by the combined fit on these rods: the rods re-measured through them, their
    # posterior as the intrinsics' part (the extraction's refined camera is that fit's first step only)
    z_intr = np.zeros(nz)
    intr_note: dict = {"applied": False}
    got = measured_intr.along(intrinsics_names(eff.camera)) if isinstance(measured_intr, MeasuredIntrinsics) else None
    if got is not None:
        A = np.linalg.pinv(eff.steps.T)  # the principal steps' coordinates of a move of the intrinsics
        z_intr = A @ got[0]
        cov_intr = Jz[:, :nz] @ (A @ got[1] @ A.T) @ Jz[:, :nz].T
        intr_note = cast(MeasuredIntrinsics, measured_intr).to_dict() | {"applied": True}
    edge = measured_edge if isinstance(measured_edge, MeasuredEdgeBias) else None
    if edge is not None:
        # the limbs corrected by the measured bias (moved inward by it), the whole estimate redone; its remaining
        # uncertainty is the measurement's
        cov_edge = J_px @ edge.covariance_px2 @ J_px.T
        edge_note: dict = edge.to_dict() | {"applied": True}
    else:
        cov_edge = (edge_bias_std_px**2) * (J_px @ J_px.T)
        edge_note = {"applied": False, "allowance_std_px": edge_bias_std_px}
    seven = est.seven
    if edge is not None or got is not None:
        seven = seven_for(np.concatenate([z_intr, -edge.estimate_px if edge is not None else np.zeros(2)]))
    return CameraPart(cov_intr, cov_edge, edge_note, intr_note, seven)


def apply_prior(
    seven: np.ndarray,
    parts7: dict[str, np.ndarray],
    nom: I4Parameters,
    prior_std_m: float | None,
    use_planes: bool,
    warnings: list[str],
) -> PriorOutcome:
    """The a priori tolerance: blended where the data do not pin a direction; when the data contradict it, the fit
    poses' (L, S, D) or all seven fall back on it; with image planes, the four combinations' null space is the a
    priori geometry's (:func:`.uncertainty.null_space_to_prior`). Appends to ``warnings`` what the user must know.

    Parameters
    ----------
    seven : ndarray, shape (7,)
        The data's estimate (m).
    parts7 : dict of str to ndarray, shape (7, 7)
        Its covariance's parts (m^2).
    nom : I4Parameters
        The a priori geometry.
    prior_std_m : float or None
        The tolerance (m); None or 0: the data's estimate as it is.
    use_planes : bool
        Step 1 used image planes.
    warnings : list of str

    Returns
    -------
    PriorOutcome
    """
    cov = cast(np.ndarray, sum(parts7.values()))
    out = PriorOutcome(seven, cov, parts7, _identifiability(cov, prior_std_m))
    if prior_std_m:
        out.conflict = _prior_conflict(seven, cov, nom, prior_std_m)
    if prior_std_m and out.conflict is not None and out.conflict > float(chi2_gate(7)):
        _prior_fallback(out, nom, prior_std_m, warnings)
    elif prior_std_m:
        out.seven, out.cov, out.parts = with_prior(seven, cov, parts7, nom, prior_std_m)
        if out.ident["unpinned"]:
            worst = out.ident["unpinned"][0]
            warnings.append(
                f"the legs' data do not pin {len(out.ident['unpinned'])} direction(s) of the seven parameters "
                f"(weakest: {worst['label']}, data std {worst['data_std_m'] * 1e3:.1f} mm against the a priori "
                f"{prior_std_m * 1e3:.1f} mm): the result stays near the a priori values there, with their std"
            )
    if use_planes and prior_std_m and out.fallback != "all seven":
        # the directions the four combinations do not see rest on the lock phases' joints alone, which on images carry
        # an error common to every run (docs/model.md): the a priori values there, with their tolerance
        out.seven, out.cov, out.parts, out.not_identified = null_space_to_prior(out.seven, out.parts, nom, prior_std_m)
        warnings.append(
            "the legs' image data do not identify the seven parameters beyond the four combinations: along "
            + "; ".join(d["label"] for d in out.not_identified)
            + f" the result is the a priori geometry with its {prior_std_m * 1e3:.1f} mm tolerance "
            "(diagnostics.identifiability.not_identified)"
        )
    return out


def _prior_fallback(out: PriorOutcome, nom: I4Parameters, prior_std_m: float, warnings: list[str]) -> None:
    """The data's estimate is beyond the a priori tolerance by more than both uncertainties allow: a wrong joint or rod
    the checks did not catch; blended, it would still be far off with a small std. Step 2's four (H, q02, q03, q04)
    come from the lock phases' joints alone, (L, S, D) also from the fit poses' leg directions. When the four agree
    with the tolerance, the contradiction is in the fit poses: the four are kept (with the prior where they need it)
    and (L, S, D) are the a priori values; otherwise the a priori values are returned for all seven. Either way with
    their tolerance as std, and the warning says why. ``out`` is updated in place."""
    seven, cov, parts7 = out.seven, out.cov, out.parts
    conflict = cast(float, out.conflict)
    out.conflict_joints = _prior_conflict(seven, cov, nom, prior_std_m, _STEP2)
    kept = out.conflict_joints <= float(chi2_gate(_STEP2.size))
    out.fallback = "L, S, D" if kept else "all seven"
    warnings.append(
        f"the legs' data contradict the a priori tolerance (chi-square {conflict:.0f} for 7 dof, gate "
        f"{float(chi2_gate(7)):.0f}; their estimate is in diagnostics.identifiability.data_estimate): "
        + (
            f"H, q02, q03, q04 from the lock phases agree with it (chi-square {out.conflict_joints:.1f} for 4 dof) "
            f"and are kept; L, S, D are the a priori values with their {prior_std_m * 1e3:.1f} mm tolerance"
            if kept
            else f"the result is the a priori values with their {prior_std_m * 1e3:.1f} mm tolerance"
        )
    )
    nom7 = np.asarray(nom.vector())
    prior_cov = prior_std_m**2 * np.eye(7)
    if kept:
        seven = seven.copy()
        seven[_STEPS34] = nom7[_STEPS34]
        keep2 = np.zeros((7, 7))
        keep2[np.ix_(_STEP2, _STEP2)] = 1.0
        parts7 = {k: v * keep2 for k, v in parts7.items()}
        parts7["a_priori"] = prior_cov * (1.0 - keep2)  # the L, S, D block
        total = cast(np.ndarray, sum(parts7.values()))
        out.seven, out.cov, out.parts = with_prior(seven, total, parts7, nom, prior_std_m, _STEP2)
    else:
        out.seven = nom7
        out.cov = prior_cov
        out.parts = {k: np.zeros((7, 7)) for k in parts7} | {"a_priori": prior_cov.copy()}


def legs_result(
    obs: Observations,
    cfg: LegsSettings,
    lock: LockPhases,
    joints: Joints,
    dirs: FitDirections,
    fit: RepairedFit,
    est: SevenFit,
    dpart: DirectionsPart,
    cam: CameraPart,
    prior: PriorOutcome,
    seven_data: np.ndarray,
) -> MethodResult:
    """The :class:`MethodResult` of the stages' outputs (``seven_data``: the data's estimate before the prior).

    Parameters
    ----------
    obs : Observations
        The observations (the a priori geometry, the frames).
    cfg : LegsSettings
        The method's settings.
    lock : LockPhases
        The lock phases.
    joints : Joints
        Step 1's output.
    dirs : FitDirections
        The fit poses' leg directions.
    fit : RepairedFit
        Steps 2-4's model after the repair stage.
    est : SevenFit
        Steps 2-4's estimate.
    dpart : DirectionsPart
        The leg directions' part of the covariance, m^2.
    cam : CameraPart
        The camera's part of the covariance, m^2, and the corrected seven.
    prior : PriorOutcome
        The estimate after the a priori tolerance (m, m^2).
    seven_data : ndarray, shape (7,)
        The data's estimate before the prior, PARAMETER_NAMES order, m.

    Returns
    -------
    MethodResult
        The legs method's result.
    """
    nom = obs.nominal
    seven, cov = prior.seven, prior.cov
    params = I4Parameters.from_mapping({**dict(zip(PARAMETER_NAMES, seven, strict=True)), "T_per_rad": nom.T_per_rad})
    cov4 = SEVEN_TO_FOUR @ cov @ SEVEN_TO_FOUR.T
    combos = params.combinations()
    return MethodResult(
        method="legs",
        combinations=combos_dict(np.array([combos[k] for k in COMBINATION_NAMES])),
        combinations_std=std_dict(cov4),
        covariance=cov4,
        residual_rms=joints.residual_rms_m,
        residual_unit="m (rod axis constraint to joint distance)",
        n_observations=joints.n_lines + int(fit.model.has_leg.sum()),
        n_poses=len(dirs.data) + len(np.concatenate([d.index for d in lock.data])),
        iterations=1,
        converged=True,
        parameters={k: float(v) for k, v in zip(PARAMETER_NAMES, seven, strict=True)},
        parameters_std={k: float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(PARAMETER_NAMES)},
        std_breakdown={
            name: {k: float(np.sqrt(max(c[i, i], 0))) for i, k in enumerate(PARAMETER_NAMES)}
            for name, c in prior.parts.items()
        },
        warnings=fit.warnings,
        diagnostics=_legs_diagnostics(cfg, lock, joints, dirs, fit, est, dpart, cam, prior, seven_data),
    )


def _legs_diagnostics(
    cfg: LegsSettings,
    lock: LockPhases,
    joints: Joints,
    dirs: FitDirections,
    fit: RepairedFit,
    est: SevenFit,
    dpart: DirectionsPart,
    cam: CameraPart,
    prior: PriorOutcome,
    seven_data: np.ndarray,
) -> dict[str, Any]:
    """The result's ``diagnostics`` (docs/result.md)."""
    scale = float(np.sqrt(dpart.s2)) * (1.0 if dirs.measured else (cfg.direction_std_rad or 1.0))
    if dpart.expected is not None:
        weighting = "measured rod covariances (GLS; cov_u_own through its gain)"
    else:
        weighting = "measured rod covariances (GLS)" if dirs.measured else "isotropic"
    return {
        "step1": "weighted plane equations" if joints.use_planes else "line intersection (unweighted)",
        "step1_chi2_per_dof": float(joints.s2),
        "step1_residual_chi2_per_dof": float(joints.s2_raw),
        "step1_frames_rejected": joints.rejected,
        "steps34_weighting": weighting,
        "steps34_chi2_per_dof": float(dpart.s2),
        "steps34_residual_chi2_per_dof": float(dpart.s2_raw),
        "steps34_expected_chi2_per_dof": None
        if dpart.expected is None or dpart.dof <= 0
        else dpart.expected / dpart.dof,
        "rod_direction_noise_rad": scale if not dirs.measured else None,
        "rod_pairs_rejected": dirs.rejected_pairs,
        "poses_rejected": est.rejected_poses,
        "line_residual_rms_mm": joints.residual_rms_m * 1e3,
        "joint_centres_camera": fit.P.mean(axis=1).tolist(),
        "limb_edge_bias": cam.edge_note,
        "intrinsics_refit": cam.intrinsics_note,
        "locked_q": lock.q_lock.tolist(),
        "rod_pair_check": fit.pair_check,
        "joint_repaired": None if fit.repair is None else fit.repair.to_dict(),
        "identifiability": {
            **prior.ident,
            "prior_std_m": cfg.prior_std_m,
            "prior_conflict_chi2": prior.conflict,
            "prior_conflict_chi2_step2": prior.conflict_joints,
            "a_priori_fallback": prior.fallback,
            "not_identified": prior.not_identified,
            "data_estimate": {k: float(v) for k, v in zip(PARAMETER_NAMES, seven_data, strict=True)},
        },
    }
