"""``calibrate_legs``: the legs method end to end (steps 1-4, uncertainty, diagnostics)."""

from __future__ import annotations

from typing import cast

import numpy as np
from scipy.linalg import block_diag

from ...camera import intrinsics_names
from ...errors import I4calError, IdentifiabilityError
from ...observations import Observations
from ...parameters import COMBINATION_NAMES, PARAMETER_NAMES, SEVEN_TO_FOUR, I4Parameters
from ...robust import chi2_gate
from ..combined import EDGE_BIAS_STD_PX
from ..edge_bias import MeasuredEdgeBias
from ..iterations import IterationCallback
from ..measured_intrinsics import MeasuredIntrinsics
from ..result import MethodResult, combos_dict, std_dict
from .constants import JOINT_DEPTH_SYS_LEG_SHARE, JOINT_DEPTH_SYS_M, PRIOR_STD_M
from .joints import PlaneObservation, _plane_observations, _step1_planes, intersect_lines, joint_from_planes
from .pipeline import (
    _gate_poses,
    _leg_directions,
    _LegsPipeline,
    _pair_means,
    _pair_own_covariances,
    _rod_own_covariances,
    _steps34_covariance,
    _steps34_sandwich,
)
from .repair import REPAIR_CHI2_MAX, REPAIR_PAIR_FACTOR, repair_joint
from .uncertainty import (
    _identifiability,
    _IntrinsicsEffect,
    _null_space_to_prior,
    _pair_consistency,
    _prior_conflict,
    _with_prior,
    joint_depth_systematic,
)

#: step 2's parameters (H, q02, q03, q04; indices into PARAMETER_NAMES): from the lock phases' joints alone
_STEP2 = np.array([PARAMETER_NAMES.index(n) for n in ("H", "q02", "q03", "q04")])
#: the others (S, D, L): also from the fit poses' leg directions
_STEPS34 = np.setdiff1d(np.arange(len(PARAMETER_NAMES)), _STEP2)


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
        The limb-edge bias the combined fit measured on the same rods (``diagnostics.limb_edge_bias`` of
        :func:`calib.methods.combined.calibrate_combined`: per limb, outward px, and its covariance). Every rod's
        limbs are corrected by it (the whole estimate redone, as for the intrinsics) and its covariance replaces the
        ``edge_bias_std_px`` allowance. True (default): measured here with the combined fit when the rods carry
        limb samples and the camera its covariance; None or False: the allowance only.
    joint_depth_sys_m : float
        RMS (m) of each lock-phase joint's systematic error along its line of sight when the joints come from image
        planes (:data:`.constants.JOINT_DEPTH_SYS_M`, half of its variance common to a leg's two joints): the rods'
        shading biases their limb edges the same way in every frame of a lock phase. Propagated like the joints'
        noise (``std_breakdown.joint_depth_systematic``); 0: left out.
    intrinsics : MeasuredIntrinsics, True or None
        The intrinsics as the combined fit re-estimates them on the same rods (:mod:`calib.methods.measured_intrinsics`:
        the shift from the extraction's camera and its posterior covariance). Every rod is re-measured through them
        (the whole estimate redone, with the edge-bias correction) and their posterior is the intrinsics' part of the
        std. The extraction's camera is the rods' refinement's first step only, off beyond its covariance where the
        calibration was far off. True (default): re-estimated here with the combined fit (the one that measures the
        edge bias); None or False: the extraction's camera and its ``covariance_refined``.
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
    # read only when use_planes: then no rod's observations are None
    planes_ok = cast("list[list[list[PlaneObservation]]]", planes)
    rejected_lock: list[dict[str, int]] = []
    if use_planes:
        frames1 = [[np.nonzero(lock_data[i].has_rod[:, i, j])[0] for j in range(2)] for i in range(4)]
        P, covPij, s2_1, rejected_lock, res_rms, keep1, s2_1_raw = _step1_planes(planes_ok, frames1)
        n_lines = sum(len(planes_ok[i][j]) for i in range(4) for j in range(2))
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
        s2_1 = s2_1_raw = ss / dof1 if dof1 > 0 else 0.0
        covPij = s2_1 * np.linalg.inv(Acc)
        res_rms = float(np.sqrt(s2_1))

    # ---- step 1b: the two rods of a leg are parallel and the same distance apart on every leg: their joints'
    #      separations agree when the joints are right. A leg whose separation is off beyond its covariance has a
    #      joint wrong beyond its std (a rod's frames taken for another edge, a weakly conditioned lock phase):
    #      its joints' covariance is scaled to cover that disagreement
    covPij_measured = covPij
    covPij, pair_check, warnings = _pair_consistency(P, covPij)

    # ---- steps 2-4
    data = obs.arrays(*fit_phases)
    U, CU, pts, has_leg, measured, rejected_pairs, C_rods = _leg_directions(obs, data, direction_std_rad)
    pipe = _LegsPipeline(q_lock, data.q, pts, has_leg, CU, nom)
    U_filled = np.where(has_leg[..., None], U, 0.0)
    # ---- step 1c: one flagged leg whose wrong joint the fit poses single out is repaired from its partner and the
    #      other legs' separation (:mod:`.repair`); the joints' covariance follows the linear map exactly
    covP = block_diag(*covPij.reshape(8, 3, 3))  # the joints' (24, 24), (leg, rod, xyz) order
    has_rod = data.has_rod

    def fit_data(leg: int, rod: int | None) -> tuple[_LegsPipeline, np.ndarray]:
        if rod is None:
            return pipe, U_filled
        hr = has_rod.copy()
        hr[:, leg, rod] = False
        hl = has_leg & hr.any(axis=2)
        U_r, CU_r, _ = _pair_means(data.rod_u, hr, C_rods)
        return _LegsPipeline(q_lock, data.q, pts, hl, CU_r, nom), np.where(hl[..., None], U_r, 0.0)

    flagged = [c["leg"] - 1 for c in pair_check if c["scale"] > 1.0 and c["chi2"] >= REPAIR_PAIR_FACTOR * c["gate"]]
    repair = repair_joint(P, flagged, fit_data, chi2_max=REPAIR_CHI2_MAX if measured else None)
    if repair is not None and repair.left_out_of_fit_poses:
        pipe, U_filled = fit_data(repair.leg, repair.rod)
        has_rod = has_rod.copy()
        has_rod[:, repair.leg, repair.rod] = False
    if repair is not None:
        P_measured = P
        P = repair.apply(P_measured)
        covP = repair.T @ block_diag(*covPij_measured.reshape(8, 3, 3)) @ repair.T.T
        pair_check[repair.leg]["repaired_rod"] = repair.rod
        warnings = [w for w in warnings if not w.startswith(f"lock-{repair.leg + 1}:")]
        warnings.append(repair.warning(pair_check[repair.leg]["deviation_mm"]))
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
    lsd = seven[[6, 4, 5]]  # (L, S, D): the re-runs below start at the estimate

    # ---- uncertainty: (i) the joints, propagated through steps 2-4 (numerical derivatives, weights fixed)
    def f(Pv: np.ndarray) -> np.ndarray:
        return pipe.run(Pv, U_filled, x2, theta_init=lsd)

    h = 1e-7
    GP = np.zeros((7, 24))
    for a in range(24):
        dP = np.zeros(24)
        dP[a] = h
        GP[:, a] = (f(P + dP.reshape(4, 2, 3)) - f(P - dP.reshape(4, 2, 3))) / (2 * h)
    cov_joints = GP @ covP @ GP.T
    # (i') the joints' systematic depth error from the rods' shading (image planes only), which the lock phases'
    #      frames cannot average and their chi-square does not show
    cov_jsys = np.zeros((7, 7))
    if use_planes and joint_depth_sys_m > 0:
        cov_jsys = GP @ joint_depth_systematic(P, joint_depth_sys_m, JOINT_DEPTH_SYS_LEG_SHARE) @ GP.T
    # (ii) the leg directions of the fit poses: GLS covariance of (L, S, D), scaled by the chi-square
    c34, chi34, dof34 = _steps34_covariance(pipe, P, U_filled, seven)
    s2_34_raw = chi34 / dof34 if dof34 > 0 else 1.0
    s2_34 = 1.0 if (not measured and direction_std_rad is not None) else s2_34_raw
    C_own = _rod_own_covariances(obs, data) if measured else None
    expected34 = None
    if C_own is not None:
        # the directions' own errors (cov_u_own) through the fit's gain; their level is the chi-square over what
        # those errors and the joints' together make it expect, never below 1 (both are absolute)
        CU_own = np.nan_to_num(_pair_own_covariances(data.rod_u, has_rod, C_rods, C_own))
        c34, chi_w, expected34 = _steps34_sandwich(pipe, P, U_filled, seven, CU_own, covP)
        s2_34 = max(chi_w / expected34, 1.0) if expected34 > 0 else 1.0
    elif measured:  # cov_u is absolute (with the extraction's edge-bias allowance): scaled up, never down
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
    edge_note: dict | None = None
    intr_note: dict = {"applied": False}
    if eff is not None:

        def seven_for(z: np.ndarray) -> np.ndarray:
            pz = eff.lock_planes(z, planes_ok)
            Pz = np.array(
                [
                    [
                        joint_from_planes([o for o, kk in zip(pz[i][j], keep1[i][j], strict=True) if kk])[0]
                        for j in range(2)
                    ]
                    for i in range(4)
                ]
            )
            if repair is not None:
                Pz = repair.apply(Pz)
            Uz = _pair_means(eff.rod_u(z, data.rod_u), has_rod, C_rods)[0]
            return pipe.run(Pz, np.where(pipe.has_leg[..., None], Uz, 0.0), x2, theta_init=lsd)

        # one standard deviation along each principal direction, then the limb-edge bias common to every rod
        # (per limb, the combined method's prior: shading and optics bias every rod's limb alike, so it does
        # not average out over rods)
        nz = eff.steps.shape[0]
        E = np.zeros((nz + 2, nz + 2))
        E[:nz, :nz] = np.eye(nz)
        step_px = edge_bias_std_px if edge_bias_std_px > 0 else EDGE_BIAS_STD_PX
        E[nz:, nz:] = step_px * np.eye(2)
        Jz = np.stack([(seven_for(e) - seven_for(-e)) / 2.0 for e in E], axis=1)
        cov_intr = Jz[:, :nz] @ Jz[:, :nz].T
        J_px = Jz[:, nz:] / step_px  # the seven's change per px of outward bias on each limb
        fit = _combined_fit(obs) if (edge_bias is True or intrinsics is True) else None
        measured_edge = (None if fit is None else MeasuredEdgeBias.from_result(fit)) if edge_bias is True else edge_bias
        measured_intr = (
            (None if fit is None else MeasuredIntrinsics.from_result(fit)) if intrinsics is True else intrinsics
        )
        # the intrinsics re-estimated by the combined fit on these rods: the rods re-measured through them, their
        # posterior as the intrinsics' part (the extraction's refined camera is that fit's first step only)
        z_intr = np.zeros(nz)
        got = measured_intr.along(intrinsics_names(eff.camera)) if measured_intr else None
        if got is not None:
            A = np.linalg.pinv(eff.steps.T)  # the principal steps' coordinates of a move of the intrinsics
            z_intr = A @ got[0]
            cov_intr = Jz[:, :nz] @ (A @ got[1] @ A.T) @ Jz[:, :nz].T
            # got is set only when measured_intr is
            intr_note = measured_intr.to_dict() | {"applied": True}  # type: ignore[union-attr]
        if measured_edge:
            # the limbs corrected by the measured bias (moved inward by it), the whole estimate redone; its
            # remaining uncertainty is the measurement's
            cov_edge = J_px @ measured_edge.covariance_px2 @ J_px.T
            edge_note = measured_edge.to_dict() | {"applied": True}
        else:
            cov_edge = (edge_bias_std_px**2) * (J_px @ J_px.T)
            edge_note = {"applied": False, "allowance_std_px": edge_bias_std_px}
        if measured_edge or got is not None:
            seven = seven_for(np.concatenate([z_intr, -measured_edge.estimate_px if measured_edge else np.zeros(2)]))
    cov = cov_joints + cov_jsys + cov_dirs + cov_intr + cov_edge
    parts7 = {
        "joint_centres": cov_joints,
        "joint_depth_systematic": cov_jsys,
        "leg_directions": cov_dirs,
        "intrinsics": cov_intr,
        "limb_edge_bias": cov_edge,
    }
    seven_data = seven.copy()
    ident = _identifiability(cov, prior_std_m)
    conflict = _prior_conflict(seven, cov, nom, prior_std_m) if prior_std_m else None
    conflict_joints = None
    fallback = None
    if prior_std_m and conflict is not None and conflict > float(chi2_gate(7)):
        # the data's estimate is beyond the a priori tolerance by more than both uncertainties allow: a wrong
        # joint or rod the checks above did not catch. Blended, it would still be far off with a small std.
        # Step 2's four (H, q02, q03, q04) come from the lock phases' joints alone; (L, S, D) also from the fit
        # poses' leg directions. When the four agree with the tolerance, the contradiction is in the fit poses
        # (trial 47 of the 50-trial study: legs hidden in most poses, (L, S, D) slid 100 mm along the valley
        # (1, u_x, u_y) with the true joints as well): the four are kept (with the prior where they need it) and
        # (L, S, D) are the a priori values. Otherwise the a priori values are returned for all seven. Either way
        # with their tolerance as std, and the warning says why.
        conflict_joints = _prior_conflict(seven, cov, nom, prior_std_m, _STEP2)
        kept = conflict_joints <= float(chi2_gate(_STEP2.size))
        fallback = "L, S, D" if kept else "all seven"
        warnings.append(
            f"the legs' data contradict the a priori tolerance (chi-square {conflict:.0f} for 7 dof, gate "
            f"{float(chi2_gate(7)):.0f}; their estimate is in diagnostics.identifiability.data_estimate): "
            + (
                f"H, q02, q03, q04 from the lock phases agree with it (chi-square {conflict_joints:.1f} for 4 dof) "
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
            seven, cov, parts7 = _with_prior(seven, sum(parts7.values()), parts7, nom, prior_std_m, _STEP2)
        else:
            seven = nom7
            cov = prior_cov
            parts7 = {k: np.zeros((7, 7)) for k in parts7} | {"a_priori": cov.copy()}
    elif prior_std_m:
        seven, cov, parts7 = _with_prior(seven, cov, parts7, nom, prior_std_m)
        if ident["unpinned"]:
            worst = ident["unpinned"][0]
            warnings.append(
                f"the legs' data do not pin {len(ident['unpinned'])} direction(s) of the seven parameters (weakest: "
                f"{worst['label']}, data std {worst['data_std_m'] * 1e3:.1f} mm against the a priori "
                f"{prior_std_m * 1e3:.1f} mm): the result stays near the a priori values there, with their std"
            )
    not_identified: list[dict] = []
    if use_planes and prior_std_m and fallback != "all seven":
        # the directions the four combinations do not see rest on the lock phases' joints alone, which on images carry
        # an error common to every run (docs/model.md): the a priori values there, with their tolerance
        seven, cov, parts7, not_identified = _null_space_to_prior(seven, parts7, nom, prior_std_m)
        warnings.append(
            "the legs' image data do not identify the seven parameters beyond the four combinations: along "
            + "; ".join(d["label"] for d in not_identified)
            + f" the result is the a priori geometry with its {prior_std_m * 1e3:.1f} mm tolerance "
            "(diagnostics.identifiability.not_identified)"
        )
    params = I4Parameters.from_mapping({**dict(zip(PARAMETER_NAMES, seven, strict=True)), "T_per_rad": nom.T_per_rad})
    cov4 = SEVEN_TO_FOUR @ cov @ SEVEN_TO_FOUR.T
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
            "step1_residual_chi2_per_dof": float(s2_1_raw),
            "step1_frames_rejected": rejected_lock,
            "steps34_weighting": (
                "measured rod covariances (GLS; cov_u_own through its gain)"
                if expected34 is not None
                else "measured rod covariances (GLS)"
                if measured
                else "isotropic"
            ),
            "steps34_chi2_per_dof": float(s2_34),
            "steps34_residual_chi2_per_dof": float(s2_34_raw),
            "steps34_expected_chi2_per_dof": None if expected34 is None or dof34 <= 0 else expected34 / dof34,
            "rod_direction_noise_rad": scale if not measured else None,
            "rod_pairs_rejected": rejected_pairs,
            "poses_rejected": rejected_poses,
            "line_residual_rms_mm": res_rms * 1e3,
            "joint_centres_camera": P.mean(axis=1).tolist(),
            "limb_edge_bias": edge_note,
            "intrinsics_refit": intr_note,
            "locked_q": q_lock.tolist(),
            "rod_pair_check": pair_check,
            "joint_repaired": None if repair is None else repair.to_dict(),
            "identifiability": {
                **ident,
                "prior_std_m": prior_std_m,
                "prior_conflict_chi2": conflict,
                "prior_conflict_chi2_step2": conflict_joints,
                "a_priori_fallback": fallback,
                "not_identified": not_identified,
                "data_estimate": {k: float(v) for k, v in zip(PARAMETER_NAMES, seven_data, strict=True)},
            },
        },
        residuals=None,
    )


def _combined_fit(obs: Observations) -> MethodResult | None:
    """The combined fit of the same observations (its edge-bias and intrinsics measurements); None when it fails."""
    from ..combined import calibrate_combined

    try:
        return calibrate_combined(obs)
    except I4calError:
        return None
