"""One wrong upper joint, repaired from its partner and the other legs' rod spacing.

A rod whose lock phase is measured wrong in the same way in every frame (a limb biased by something the extraction
took for its edge; on the image-level twin, 6 of 50 trials of a designed 12-pose plan, joints 35-71 mm off with
their covariance claiming 0.1-0.3 mm) gives a joint that the lock phase's own frames cannot question: they agree
with each other. The rod-pair check (:func:`.uncertainty._pair_consistency`) sees it: the two joints of every leg
are the same vector apart (the rods' spacing along x_B), and that leg's is not. Which of its two joints is wrong, the
pair alone cannot say; the fit poses can: with the right joint, their leg directions fit steps 3-4 at their noise;
with the wrong one, at tens to hundreds of times it.

So for a single flagged leg each of its joints in turn is replaced by its partner's plus (or minus) the mean
separation of the other three legs, a linear function of the other joints (:func:`joint_repair_map`, so the joints'
covariance follows exactly), and the replacement kept if the fit poses' robust chi-square per degree of freedom
falls to a small fraction of the unrepaired one (:data:`REPAIR_GAIN`); otherwise nothing changes (the check's
covariance scaling stands).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ConvergenceError, IdentifiabilityError
from ...robust import robust_chi2_scale
from .pipeline import _LegsPipeline

#: a repair is kept when it divides the fit poses' robust chi-square per degree of freedom by at least this (clean
#: trials of the twin: 1-2; with one joint 35-71 mm off: 26-380)
REPAIR_GAIN = 4.0


@dataclass(frozen=True)
class JointRepair:
    """A replaced joint: leg and rod (0-based), the map from the measured joints to the used ones, the evidence."""

    leg: int
    rod: int
    T: np.ndarray  #: (24, 24): used joints (flattened (4, 2, 3)) = T @ measured joints
    moved_m: float  #: how far the joint moved
    chi2_before: float  #: fit poses' robust chi-square per dof with the measured joints
    chi2_after: float  #: with the repaired joint
    chi2_other: float  #: with the other joint of the leg replaced instead

    def apply(self, P: np.ndarray) -> np.ndarray:
        """The used joints (4, 2, 3) from measured ones (4, 2, 3)."""
        return (self.T @ np.asarray(P).reshape(24)).reshape(4, 2, 3)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "leg": self.leg + 1,
            "rod": self.rod,
            "moved_mm": self.moved_m * 1e3,
            "chi2_per_dof_before": self.chi2_before,
            "chi2_per_dof_after": self.chi2_after,
            "chi2_per_dof_other_rod": self.chi2_other,
        }


def joint_repair_map(leg: int, rod: int) -> np.ndarray:
    """(24, 24) linear map replacing joint (leg, rod) by its partner's plus the other legs' mean separation.

    The separation of a leg is ``P[k, 1] - P[k, 0]``; joint (leg, 1) becomes ``P[leg, 0] + mean separation``,
    joint (leg, 0) becomes ``P[leg, 1] - mean separation``. Every other joint is kept.
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


def _fit_chi2(pipe: _LegsPipeline, P: np.ndarray, U: np.ndarray) -> float:
    """Robust chi-square per degree of freedom of the fit poses' equations after a robust steps 3-4 fit with ``P``."""
    seven = pipe.run(P, U, robust=True)
    x, A0, _ = pipe.frame(P)
    Aq, Uo = pipe.oriented(x, A0, U)
    d2 = np.sum(pipe.whitened(seven[[6, 4, 5]], Aq, Uo, pipe.y_axis(x, A0)) ** 2, axis=1)
    m = pipe.mask.sum(axis=1)
    used = m > 0
    return float(robust_chi2_scale(d2[used], m[used])) if used.sum() >= 4 else float("nan")


def repair_joint(pipe: _LegsPipeline, P: np.ndarray, U: np.ndarray, flagged: list[int]) -> JointRepair | None:
    """The repair of the one flagged leg's wrong joint, when the fit poses confirm it (module docstring); else None.

    Parameters
    ----------
    pipe : _LegsPipeline
        Steps 2-4 over the fit poses (its weights are recomputed by every robust run).
    P : ndarray, shape (4, 2, 3)
        Measured upper joints, camera frame, m.
    U : ndarray, shape (N, 4, 3)
        Leg directions of the fit poses (zero where missing).
    flagged : list of int
        Legs (0-based) whose two joints disagree with the other legs' separation.
    """
    if len(flagged) != 1:
        return None
    leg = flagged[0]
    try:
        before = _fit_chi2(pipe, P, U)
        maps = [joint_repair_map(leg, j) for j in (0, 1)]
        after = [_fit_chi2(pipe, (T @ P.reshape(24)).reshape(4, 2, 3), U) for T in maps]
    except (ConvergenceError, IdentifiabilityError, np.linalg.LinAlgError):  # no repair; the check's scaling stands
        return None
    if not all(np.isfinite([before, *after])):
        return None
    rod = int(np.argmin(after))
    if after[rod] * REPAIR_GAIN > before:
        return None
    T = maps[rod]
    moved = float(np.linalg.norm((T @ P.reshape(24)).reshape(4, 2, 3)[leg, rod] - P[leg, rod]))
    return JointRepair(leg, rod, T, moved, before, after[rod], after[1 - rod])
