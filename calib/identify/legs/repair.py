"""One wrong upper joint, repaired from its partner and the other legs' rod spacing.

A rod whose lock phase is measured wrong in the same way in every frame (a limb biased by something the extraction
took for its edge: centimetres off while its covariance claims a fraction of a millimetre) gives a joint that the
lock phase's own frames cannot question: they agree with each other. The rod-pair check
(:func:`.uncertainty._pair_consistency`) sees it: the two joints of every leg are the same vector apart (the rods'
spacing along x_B), and that leg's is not. Which of its two joints is wrong, the
pair alone cannot say; the fit poses can: with the right joint, their leg directions fit steps 3-4 at their noise;
with the wrong one, at tens to hundreds of times it.

So for a single flagged leg each of its joints in turn is replaced by its partner's plus (or minus) the mean
separation of the other three legs, a linear function of the other joints (:func:`joint_repair_map`, so the joints'
covariance follows exactly), with that rod's fit-pose directions kept or left out (a rod measured wrong in its lock
phase is often wrong in the fit poses too), and the best of the four kept if the fit poses' robust chi-square per
degree of freedom falls to a small fraction of the unrepaired one (:data:`REPAIR_GAIN`) and near the noise
(:data:`REPAIR_CHI2_MAX`); otherwise nothing changes (the check's covariance scaling stands).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calib.errors import ConvergenceError, IdentifiabilityError
from calib.identify.legs.steps import LegsModel
from calib.numerics.robust import robust_chi2_scale

#: a repair is kept when it divides the fit poses' robust chi-square per degree of freedom by at least this (right
#: joints leave it near its noise level, a joint centimetres off multiplies it by tens to hundreds)
REPAIR_GAIN = 4.0
#: ... and when that chi-square per dof, with measured rod covariances (absolute weights), is at most this: a fit still
#: far above its noise (a wrong joint replaced by another wrong one) is no repair
REPAIR_CHI2_MAX = 6.0
#: a flagged leg's joints are repaired only when its rod-pair chi-square is this many times the check's gate: a joint
#: tens of standard deviations off, what a rod taken for another edge gives (hundreds to thousands of times the gate);
#: a leg just over the gate is only widened (its joints are usually right, and a repair tried on it can move a right
#: joint)
REPAIR_PAIR_FACTOR = 100.0


@dataclass(frozen=True)
class JointRepair:
    """A replaced joint: leg and rod (0-based), the map from the measured joints to the used ones, the evidence."""

    leg: int
    rod: int
    T: np.ndarray  #: (24, 24): used joints (flattened (4, 2, 3)) = T @ measured joints
    moved_m: float  #: how far the joint moved
    chi2_before: float  #: fit poses' robust chi-square per dof with the measured joints
    chi2_after: float  #: with the repaired joint
    chi2_other: float  #: with the other joint of the leg replaced instead (its best variant)
    left_out_of_fit_poses: bool = False  #: the rod's fit-pose directions are left out too (its leg's is its partner's)

    def apply(self, P: np.ndarray) -> np.ndarray:
        """The used joints (4, 2, 3) from measured ones (4, 2, 3).

        Parameters
        ----------
        P : ndarray, shape (4, 2, 3)
            The measured joints, camera frame, m.

        Returns
        -------
        ndarray, shape (4, 2, 3)
            The used joints, camera frame, m.
        """
        return (self.T @ np.asarray(P).reshape(24)).reshape(4, 2, 3)

    def warning(self, deviation_mm: float) -> str:
        """The result's warning, ``deviation_mm`` the leg's separation off the other legs' (the rod-pair check).

        Parameters
        ----------
        deviation_mm : float
            The leg's joint separation minus the other legs' mean, mm (for display).

        Returns
        -------
        str
            The warning's text.
        """
        text = (
            f"lock-{self.leg + 1}: the joint of rod {self.rod} disagrees with the other legs' rod spacing "
            f"({deviation_mm:.1f} mm); it is taken as its partner's plus that spacing (moved {self.moved_m * 1e3:.1f} "
            f"mm): the fit poses' chi-square per dof falls from {self.chi2_before:.1f} to {self.chi2_after:.1f} "
            f"({self.chi2_other:.1f} with the other rod's joint replaced instead)"
        )
        if self.left_out_of_fit_poses:
            text += f"; the rod is left out of the fit poses too (leg {self.leg + 1}'s direction is its partner's)"
        return text

    def to_dict(self) -> dict[str, float | int]:
        return {
            "leg": self.leg + 1,
            "rod": self.rod,
            "moved_mm": self.moved_m * 1e3,
            "chi2_per_dof_before": self.chi2_before,
            "chi2_per_dof_after": self.chi2_after,
            "chi2_per_dof_other_rod": self.chi2_other,
            "left_out_of_fit_poses": self.left_out_of_fit_poses,
        }


def joint_repair_map(leg: int, rod: int) -> np.ndarray:
    """(24, 24) linear map replacing joint (leg, rod) by its partner's plus the other legs' mean separation.

    The separation of a leg is ``P[k, 1] - P[k, 0]``; joint (leg, 1) becomes ``P[leg, 0] + mean separation``,
    joint (leg, 0) becomes ``P[leg, 1] - mean separation``. Every other joint is kept.

    Parameters
    ----------
    leg : int
        The leg, 0..3.
    rod : int
        The rod whose joint is replaced, 0 or 1.

    Returns
    -------
    ndarray, shape (24, 24)
        The map from the measured joints (flattened (4, 2, 3)) to the used ones, dimensionless.

    Raises
    ------
    ValueError
        ``leg`` or ``rod`` out of range.
    """
    if leg not in range(4) or rod not in (0, 1):
        raise ValueError(f"leg must be in 0..3 and rod 0 or 1, got leg={leg}, rod={rod}")
    T = np.eye(24)
    I3 = np.eye(3)

    def block(k: int, j: int) -> slice:
        return slice((2 * k + j) * 3, (2 * k + j) * 3 + 3)

    row = block(leg, rod)
    T[row, :] = 0.0
    T[row, block(leg, 1 - rod)] = I3
    sign = 1.0 if rod == 1 else -1.0
    for k in range(4):
        if k != leg:
            T[row, block(k, 1)] += sign * I3 / 3.0
            T[row, block(k, 0)] -= sign * I3 / 3.0
    return T


def _fit_chi2(pipe: LegsModel, P: np.ndarray, U: np.ndarray) -> float:
    """Robust chi-square per degree of freedom of the fit poses' equations after a robust steps 3-4 fit with ``P``."""
    seven = pipe.run(P, U, robust=True)
    d2 = np.sum(pipe.whitened(seven[[6, 4, 5]], *pipe.geometry(P, U)) ** 2, axis=1)
    m = pipe.mask.sum(axis=1)
    used = m > 0
    return float(robust_chi2_scale(d2[used], m[used])) if used.sum() >= 4 else float("nan")


#: the fit poses' data, a rod left out of its leg's direction: (leg, rod or None) -> (pipeline, directions (N, 4, 3))
FitData = Callable[[int, "int | None"], tuple[LegsModel, np.ndarray]]


def repair_joint(
    P: np.ndarray, flagged: list[int], fit_data: FitData, chi2_max: float | None = REPAIR_CHI2_MAX
) -> JointRepair | None:
    """The repair of the one flagged leg's wrong joint, when the fit poses confirm it (module docstring); else None.

    Four hypotheses for the flagged leg: either joint wrong, with that rod's fit-pose directions kept or left out
    (a rod measured wrong the same way in every frame is often wrong in the fit poses too: its leg's direction is
    then its partner's alone). The one with the smallest robust chi-square per dof is kept when it is at least
    :data:`REPAIR_GAIN` times below the measured joints' with the same fit-pose data (that rod left out too when the
    hypothesis leaves it out: what leaving a rod out gains is no evidence against its joint).

    Parameters
    ----------
    P : ndarray, shape (4, 2, 3)
        Measured upper joints, camera frame, m.
    flagged : list of int
        Legs (0-based) whose two joints disagree with the other legs' separation.
    fit_data : callable
        ``fit_data(leg, rod)``: steps 2-4's pipeline over the fit poses and their leg directions (zero where
        missing), with ``rod`` of ``leg`` left out of the leg directions (None: every rod).
    chi2_max : float or None
        The largest chi-square per dof a repair may leave (None: no bound, for relative weights whose scale is
        unknown).

    Returns
    -------
    JointRepair or None
        The repair kept; None unless exactly one leg is flagged and a hypothesis passes both tests.
    """
    if len(flagged) != 1:
        return None
    leg = flagged[0]
    try:
        before = _fit_chi2(*_with(fit_data(leg, None), P))
        # the measured joints with each rod left out of the fit poses: what a repair that leaves it out is judged
        # against (a rod wrong in the fit poses alone lowers the chi-square when left out, whatever its joint)
        unrepaired = {None: before} | {rod: _fit_chi2(*_with(fit_data(leg, rod), P)) for rod in (0, 1)}
        cands = []
        for rod in (0, 1):
            T = joint_repair_map(leg, rod)
            Pc = (T @ P.reshape(24)).reshape(4, 2, 3)
            for left_out in (False, True):
                cands.append((_fit_chi2(*_with(fit_data(leg, rod if left_out else None), Pc)), rod, left_out, T))
    except (ConvergenceError, IdentifiabilityError, np.linalg.LinAlgError):  # no repair; the check's scaling stands
        return None
    chi2 = np.array([c[0] for c in cands])
    if not (np.all(np.isfinite(list(unrepaired.values()))) and np.all(np.isfinite(chi2))):
        return None
    best = int(np.argmin(chi2))
    after, rod, left_out, T = cands[best]
    if after * REPAIR_GAIN > unrepaired[rod if left_out else None] or (chi2_max is not None and after > chi2_max):
        return None
    other = float(min(c[0] for c in cands if c[1] != rod))
    moved = float(np.linalg.norm((T @ P.reshape(24)).reshape(4, 2, 3)[leg, rod] - P[leg, rod]))
    return JointRepair(leg, rod, T, moved, before, after, other, left_out)


def _with(fit: tuple[LegsModel, np.ndarray], P: np.ndarray) -> tuple[LegsModel, np.ndarray, np.ndarray]:
    return fit[0], P, fit[1]
