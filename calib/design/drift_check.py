"""A check's plan: the short plan that tests whether a calibration still holds (:mod:`calib.check.drift`).

A check fits the combined method to its own frames, so its plan has the three phases that method needs: the
base-frame sweeps (``rotation``, ``translation``) and fit poses (``poses``). The fit poses are chosen by the same
design as a full plan (:func:`.optimize.design_plan`, D-optimal on the combined method's four combinations), with
fewer sweep frames, no lock phases, line or validation poses; the count is the largest of :data:`CHECK_COUNTS` whose
motion time at the bench's speeds fits the budget.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from calib.design.motion import MotionSpec, plan_motion_time
from calib.design.optimize import DesignRequest, design_plan
from calib.design.predict import DesignNoise
from calib.design.predict_images import ImageNoise
from calib.design.scene import Scene
from calib.errors import InputError
from calib.formats.plan import Plan, SoftLimits, Step
from calib.model.parameters import I4Parameters

__all__ = [
    "CHECK_COUNTS",
    "CHECK_PHASES",
    "CheckPlanDesign",
    "CheckPlanRequest",
    "design_check_plan",
    "missing_phases",
    "with_repeats",
]

#: the phases the check's combined fit needs
CHECK_PHASES = ("rotation", "translation", "poses")
#: fit-pose counts tried, smallest first (a check is short: at most 20 fit poses)
CHECK_COUNTS = (4, 6, 8, 10, 12, 16, 20)


@dataclass(frozen=True)
class CheckPlanRequest:
    """What check plan to design.

    Attributes
    ----------
    budget_s : float
        Longest motion time of the check, seconds (at the bench's speeds).
    counts : tuple of int
        Fit-pose counts tried, ascending; the largest that fits the budget is kept.
    n_base : int
        Frames of each base-frame sweep (3..100).
    seed : int
        Seed of the candidate poses.
    """

    budget_s: float = 60.0
    counts: tuple[int, ...] = CHECK_COUNTS
    n_base: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        if not (self.budget_s > 0 and self.budget_s < 1e5):
            raise InputError(f"the motion budget must be in (0, 1e5) s, got {self.budget_s}", field="max_seconds")
        if not self.counts or list(self.counts) != sorted(self.counts) or self.counts[0] < 2:
            raise InputError("fit-pose counts must be ascending, from 2", field="counts")

    def key(self) -> dict[str, Any]:
        """What identifies the design (with the bench's inputs): for a cache of designed check plans."""
        return {"budget_s": self.budget_s, "counts": list(self.counts), "n_base": self.n_base, "seed": self.seed}


@dataclass
class CheckPlanDesign:
    """A designed check plan.

    Attributes
    ----------
    plan : Plan
        Named ``check``, phases :data:`CHECK_PHASES`.
    n_fit : int
        Fit poses.
    motion_time_s : float
        Its motion time at the bench's speeds, seconds.
    notes : list of str
    """

    plan: Plan
    n_fit: int
    motion_time_s: float
    notes: list[str] = field(default_factory=list)


def missing_phases(plan: Plan) -> list[str]:
    """The phases of :data:`CHECK_PHASES` a plan lacks (a check's combined fit needs every one).

    Parameters
    ----------
    plan : Plan
        The check plan.

    Returns
    -------
    list of str
        The phases missing, in :data:`CHECK_PHASES`' order (empty: none).
    """
    have = {s.phase for s in plan.steps}
    return [p for p in CHECK_PHASES if p not in have]


def design_check_plan(
    nominal: I4Parameters,
    scene: Scene,
    request: CheckPlanRequest | None = None,
    *,
    limits: SoftLimits | None = None,
    motion: MotionSpec | None = None,
    noise: DesignNoise | ImageNoise | None = None,
) -> CheckPlanDesign:
    """Design the check plan: the most fit poses of ``request.counts`` whose motion fits ``request.budget_s``.

    Parameters
    ----------
    nominal : I4Parameters
        The bench's nominal geometry (m).
    scene : Scene
        Camera, mounting, board and rods.
    request : CheckPlanRequest, optional
    limits, motion, noise
        As :func:`.optimize.design_plan` takes them (soft limits, speeds, the measurement noise).

    Returns
    -------
    CheckPlanDesign

    Raises
    ------
    InputError
        Not even the smallest count fits the budget (``field="max_seconds"``).
    """
    req = request or CheckPlanRequest()
    motion = motion or MotionSpec()
    cache: dict[Any, Any] = {}
    best: CheckPlanDesign | None = None
    smallest_s = None
    for n in req.counts:
        dreq = DesignRequest(
            n_fit=n,
            methods=("combined",),
            with_line=False,
            n_validation=0,
            n_lock=2,
            n_base=req.n_base,
            seed=req.seed,
            n_min=min(4, n),
        )
        res = design_plan(nominal, scene, dreq, limits=limits, motion=motion, noise=noise, cache=cache)
        plan = Plan(name="check", steps=[s for s in res.plan.steps if s.phase in CHECK_PHASES])
        total = float(plan_motion_time(plan, motion, nominal)["total_s"])
        smallest_s = total if smallest_s is None else smallest_s
        if total > req.budget_s:
            break
        best = CheckPlanDesign(plan, n, total, list(res.notes))
    if best is None:
        raise InputError(
            f"the shortest check plan ({req.counts[0]} fit poses) moves for {smallest_s:.0f} s, more than the "
            f"{req.budget_s:g} s budget",
            field="max_seconds",
        )
    return best


def with_repeats(plan: Plan, n: int) -> Plan:
    """``plan`` with its fit poses revisited: ``n - 1`` more tours of them as ``validation`` steps (the combined fit
    leaves them out), each tour starting one pose further on (every revisit comes from another pose), the first
    taking two frames at each pose without moving between them (:mod:`calib.check.repeatability`: the measurement
    floor).

    Parameters
    ----------
    plan : Plan
        The plan whose fit poses are revisited.
    n : int
        Visits of each fit pose in all, 2..20.

    Returns
    -------
    Plan
        Named ``<plan>-repeat-<n>``: the plan's steps, then the revisits.

    Raises
    ------
    InputError
        ``n`` below 2, or fewer than 3 fit poses (``field="repeat"``).
    """
    fit = [list(s.q) for s in plan.steps if s.phase == "poses" and s.q is not None]
    if n < 2 or n > 20:
        raise InputError(f"must be in 2..20, got {n}", field="repeat")
    if len(fit) < 3:
        raise InputError(f"revisiting needs at least 3 fit poses, the plan has {len(fit)}", field="repeat")
    extra: list[Step] = []
    for r in range(1, n):
        k = r % len(fit)
        for q in [*fit[k:], *fit[:k]]:
            extra += [Step(phase="validation", q=list(q)) for _ in range(2 if r == 1 else 1)]
    return Plan(name=f"{plan.name}-repeat-{n}", steps=[*plan.steps, *extra])
