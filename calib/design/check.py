"""A plan the user already has (the routine in use, the paper's, a colleague's file): what it will buy before motion.

:func:`check_plan` gives, for a plan as it is, each method's predicted std per combination, the motion time and the
steps the camera will not see. The prediction counts only what will be measured: a step with fewer than the extraction's
6 board corners in the image (or the board turned away) gives no board pose, so the board phases (the sweeps, the fit
poses, validation) are predicted without it (a board partly in view is measured from the corners in view: counted,
and said), and the rods each method gets are those in view (the image-level model keeps every rod of at least the
extraction's 40 px). A design (:func:`.optimize.design_plan`) only ever picks steps in view; a plan written by hand
or for another camera may not be.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.design.imaging import board_corners
from calib.design.motion import MotionSpec, plan_motion_time
from calib.design.optimize import N_FIT_MOST, shading_note
from calib.design.predict import METHODS, DesignNoise, Prediction, predict_plan
from calib.design.predict_images import ImageNoise
from calib.design.scene import Scene, _inside, visibility
from calib.errors import InputError
from calib.formats.plan import Plan
from calib.model.kinematics import dkm
from calib.model.parameters import COMBINATION_NAMES, I4Parameters

__all__ = [
    "BOARD_PHASES",
    "EXTRACTION_MIN_ROD_PX",
    "MAX_PREDICTED_FRAMES",
    "PlanCheck",
    "check_plan",
    "check_size",
    "measured_plan",
    "targets_from_plan",
]

#: phases whose frames are measured by the board (a frame without the board in view gives them nothing)
BOARD_PHASES = ("rotation", "translation", "poses", "validation")
#: the fewest inner corners the extraction makes a board pose from (``calib.vision.board.DEFAULT_MIN_CORNERS``)
MIN_BOARD_CORNERS = 6
#: margin (px) from the image border within which a corner counts as in view (the corner refinement's window)
_CORNER_MARGIN_PX = 5.0
#: the extraction's shortest rod, pixels (``calib.vision.rods``: a shorter visible part is not measured)
EXTRACTION_MIN_ROD_PX = 40.0
#: the most frames of the predicted phases (sweeps, fit poses, lock phases) a plan is predicted for: the image-level
#: prediction's cost grows faster than the square of the rods (200 fit poses 7.5 s, 1000 fit poses 5 min on 2 cores)
MAX_PREDICTED_FRAMES = 400
_PREDICTED_PHASES = ("rotation", "translation", "poses", "lock-1", "lock-2", "lock-3", "lock-4")
#: steps whose visibility is computed at once (its arrays grow as steps x 64 rod pairs x 64 samples)
_VISIBILITY_CHUNK = 256


@dataclass
class PlanCheck:
    """A plan's prediction before motion (:func:`check_plan`).

    Attributes
    ----------
    plan_name : str
    counts : dict
        Frames per phase as planned.
    measured_counts : dict
        Frames per phase the prediction counts: the board phases without their steps with fewer than
        :data:`MIN_BOARD_CORNERS` of the board's corners in view.
    prediction : Prediction
        Per method, the predicted std per combination (m) and its sources.
    motion : dict
        ``total_s`` and ``per_phase_s``: the motion time as planned, seconds.
    unseen : list of dict
        Per step the camera will not see in full: ``step`` (index in the plan), ``phase``, ``board`` (wholly in
        view, margin included), ``board_corners`` (its inner corners in the image, the board facing the camera;
        fewer than :data:`MIN_BOARD_CORNERS`: no board pose), ``rods_hidden`` (the rods, ``"leg.rod"`` numbered
        from 1, below the extraction's 40 px).
    notes : list of str
    """

    plan_name: str
    counts: dict[str, int]
    measured_counts: dict[str, int]
    prediction: Prediction
    motion: dict[str, Any]
    unseen: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """JSON-ready: what ``i4cal plan predict --json`` prints and ``POST /api/v1/plans/predict`` answers."""
        return {
            "plan": self.plan_name,
            "counts": self.counts,
            "measured_counts": self.measured_counts,
            "prediction": self.prediction.to_dict(),
            "motion": self.motion,
            "unseen": self.unseen,
            "notes": self.notes,
        }


def _corners_in_view(scene: Scene, nominal: I4Parameters, q: np.ndarray) -> np.ndarray:
    """Per pose (N,), how many of the board's inner corners are in the image, the board facing the camera."""
    pts = board_corners(scene)
    cam = scene.camera
    out = np.zeros(len(q), dtype=int)
    for k, cb in enumerate(scene.camera_from_board(nominal, dkm(nominal, q))):
        pc = cb.apply(pts)
        if float(cb.R[:, 2] @ cb.t) <= 0.0 or np.any(pc[:, 2] <= 0.05):  # turned away, or at the camera
            continue
        out[k] = int(np.sum(_inside(cam.project(pc), cam, _CORNER_MARGIN_PX)))
    return out


def _unseen_steps(plan: Plan, nominal: I4Parameters, scene: Scene) -> list[dict[str, Any]]:
    """The steps (with joint values) whose board is not wholly in view or with a rod below the extraction's
    minimum; each with how many of the board's inner corners are in view."""
    idx = [i for i, s in enumerate(plan.steps) if s.q is not None]
    if not idx:
        return []
    q = np.array([plan.steps[i].q for i in idx], dtype=np.float64)
    out: list[dict[str, Any]] = []
    for c0 in range(0, len(idx), _VISIBILITY_CHUNK):
        v = visibility(scene, nominal, q[c0 : c0 + _VISIBILITY_CHUNK])
        for k, i in enumerate(idx[c0 : c0 + _VISIBILITY_CHUNK]):
            legs, rods = np.nonzero(v["rod_px"][k] < EXTRACTION_MIN_ROD_PX)
            hidden = [f"{leg + 1}.{rod + 1}" for leg, rod in zip(legs, rods, strict=True)]
            if not v["board"][k] or hidden:
                out.append(
                    {"step": i, "phase": plan.steps[i].phase, "board": bool(v["board"][k]), "rods_hidden": hidden}
                )
    blind = [u for u in out if not u["board"]]
    if blind:
        qb = np.array([plan.steps[int(u["step"])].q for u in blind], dtype=np.float64)
        n = _corners_in_view(scene, nominal, qb)
        for u, c in zip(blind, n.tolist(), strict=True):
            u["board_corners"] = c
    n_all = len(board_corners(scene))
    for u in out:
        u.setdefault("board_corners", n_all)
    return out


def check_size(plan: Plan) -> None:
    """Refuse a plan too large to predict in reasonable time, naming what is over.

    Parameters
    ----------
    plan : Plan
        The plan to predict.

    Raises
    ------
    InputError
        More than ``N_FIT_MOST`` fit poses, or more than :data:`MAX_PREDICTED_FRAMES` frames in the predicted phases
        (``field="steps"``).
    """
    counts = plan.count()
    if counts.get("poses", 0) > N_FIT_MOST:
        raise InputError(
            f"{counts['poses']} fit poses: a prediction takes at most {N_FIT_MOST} (what a design takes)",
            field="steps",
        )
    n = sum(counts.get(ph, 0) for ph in _PREDICTED_PHASES)
    if n > MAX_PREDICTED_FRAMES:
        raise InputError(
            f"{n} frames in the sweeps, fit poses and lock phases: a prediction takes at most {MAX_PREDICTED_FRAMES}",
            field="steps",
        )


def _no_board_pose(u: dict[str, Any]) -> bool:
    """An unseen step of a board phase from which the extraction gets no board pose."""
    return u["board_corners"] < MIN_BOARD_CORNERS and u["phase"] in BOARD_PHASES


def measured_plan(plan: Plan, nominal: I4Parameters, scene: Scene) -> tuple[Plan, list[dict[str, Any]]]:
    """What the camera will measure of a plan: the plan without its board-phase steps whose board is out of view
    (they give no board pose), and every step not seen in full.

    Parameters
    ----------
    plan : Plan
        The plan as it will run.
    nominal : I4Parameters
        The nominal geometry, which places the parts in the image (m, rad).
    scene : Scene
        The camera, its mounting, the board and rods.

    Returns
    -------
    measured : Plan
        The plan without the board-phase steps that give no board pose.
    unseen : list of dict
        The steps not seen in full (:class:`PlanCheck`'s ``unseen``).
    """
    unseen = _unseen_steps(plan, nominal, scene)
    blind = {u["step"] for u in unseen if _no_board_pose(u)}
    return plan.model_copy(update={"steps": [s for i, s in enumerate(plan.steps) if i not in blind]}), unseen


def check_plan(
    plan: Plan,
    nominal: I4Parameters,
    scene: Scene,
    noise: DesignNoise | ImageNoise,
    motion: MotionSpec,
    methods: tuple[str, ...] = METHODS,
) -> PlanCheck:
    """Predict what a plan will buy: each method's std per combination, its motion time, the steps not in view.

    Parameters
    ----------
    plan : Plan
        The plan as it will run (validated against the bench's limits by the caller).
    nominal : I4Parameters
        The bench's nominal geometry, which places the parts in the image.
    scene : Scene
        The camera, its mounting, the board and rods.
    noise : DesignNoise or ImageNoise
        The measurement noise model (:func:`.predict.predict_plan`).
    motion : MotionSpec
        The bench's speeds, accelerations and settle times.
    methods : tuple of str
        Methods to predict.

    Returns
    -------
    PlanCheck

    Raises
    ------
    InputError
        The plan is too large to predict (more than ``N_FIT_MOST`` fit poses or :data:`MAX_PREDICTED_FRAMES` frames
        in the predicted phases), naming ``steps``.
    """
    check_size(plan)
    measured, unseen = measured_plan(plan, nominal, scene)
    blind = {u["step"] for u in unseen if _no_board_pose(u)}
    partial = [u for u in unseen if not u["board"] and u["step"] not in blind and u["phase"] in BOARD_PHASES]
    pred = predict_plan(measured, nominal, scene, noise, methods=methods)
    notes = []
    if blind:
        per: dict[str, int] = {}
        for i in sorted(blind):
            per[plan.steps[i].phase] = per.get(plan.steps[i].phase, 0) + 1
        notes.append(
            f"fewer than {MIN_BOARD_CORNERS} of the board's corners in view in "
            + ", ".join(f"{n} {ph} step{'s' if n > 1 else ''}" for ph, n in per.items())
            + ": predicted without them (they give no board pose); the steps are listed in 'unseen'"
        )
    if partial:
        notes.append(
            f"the board partly out of view in {len(partial)} step{'s' if len(partial) > 1 else ''} (some corners or "
            "its margin outside the image): the extraction measures the corners in view, the prediction counts them "
            "all there (slightly optimistic for those steps); listed in 'unseen' with 'board_corners'"
        )
    hidden = [u for u in unseen if u["rods_hidden"]]
    if hidden:
        notes.append(
            f"{len(hidden)} step{'s' if len(hidden) > 1 else ''} with a rod hidden or out of the image (shorter than "
            f"the extraction's {EXTRACTION_MIN_ROD_PX:.0f} px): the prediction leaves those rods out"
        )
    sn = shading_note(pred)
    if sn:
        notes.append(sn)
    return PlanCheck(
        plan_name=plan.name,
        counts=plan.count(),
        measured_counts=measured.count(),
        prediction=pred,
        motion=plan_motion_time(plan, motion, nominal),
        unseen=unseen,
        notes=notes,
    )


def targets_from_plan(
    plan: Plan,
    nominal: I4Parameters,
    scene: Scene,
    noise: DesignNoise | ImageNoise | None = None,
    method: str = "combined",
) -> tuple[float, float, float, float]:
    """A reference plan's predicted std (m) of ``method``'s four combinations, in ``COMBINATION_NAMES`` order.

    As ``target_std_m`` with the ``"target"`` criterion, it asks for a plan at least as accurate as the reference on
    every combination (``i4cal plan design --better-than``): a D-optimal set can trade one combination for the
    others (much better on three, no better on the fourth, e.g. H-D). The reference is predicted as the camera will
    measure it: without its steps whose board is out of view (:func:`measured_plan`), which would make the target
    stricter than the reference gives.

    Parameters
    ----------
    plan : Plan
        The reference plan (at most ``N_FIT_MOST`` fit poses).
    nominal : I4Parameters
        The nominal geometry (m, rad).
    scene : Scene
        The camera, its mounting, the board and rods.
    noise : DesignNoise or ImageNoise, optional
        The measurement noise (:func:`.predict.predict_plan`'s default when None).
    method : str
        The method whose std is the target.

    Returns
    -------
    tuple of 4 float
        The predicted std per combination, m.

    Raises
    ------
    InputError
        The plan is too large (``field="steps"``), or gives ``method`` no prediction (``field="better_than"``).
    """
    check_size(plan)
    pred = predict_plan(measured_plan(plan, nominal, scene)[0], nominal, scene, noise)
    if method not in pred.std:
        why = pred.errors.get(method, "no prediction")
        raise InputError(f"the reference plan {plan.name!r} has no {method} prediction: {why}", field="better_than")
    # one per combination: the four the declared tuple has
    return tuple(float(pred.std[method][c]) for c in COMBINATION_NAMES)  # type: ignore[return-value]
