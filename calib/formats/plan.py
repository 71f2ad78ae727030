"""Motion plans as data: the paper's scripted phases in joint space.

A plan is a list of typed steps that can be inspected, edited, saved, validated against
soft limits and the nominal model, and dry-run without hardware. Generators follow the
paper's set-up (section IV.C): a rotation sweep and an equal-actuator translation for the
base frame, a pose set for the fit, poses with one actuator locked for the legs-only
method, a guided 500 mm line for straightness, and separate validation poses.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Final, Literal, cast

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError

from calib.errors import InputError, UnreachableError
from calib.model.kinematics import dkm, ikm
from calib.model.parameters import I4Parameters
from calib.numerics.jsonio import read_json

PLAN_FORMAT: Final = "i4cal.plan/1"
PLAN_NAMES = ("full", "rotation-sweep", "equal-translation", "pose-set", "lock-actuator", "line", "validation")

#: Size bounds of a plan, checked before any computation on its steps (a plan is user input: the service validates
#: inline plans of requests). At most this many steps per plan,
MAX_PLAN_STEPS = 10_000
#: this many samples per guided line,
MAX_LINE_SAMPLES = 10_000
#: and this many frames in all (a ``q`` step is one frame, a line step ``samples`` frames).
MAX_PLAN_FRAMES = 100_000

#: A number of a plan: a JSON number (an integer or a float), never a boolean or a numeric string (``false`` or
#: ``"0.3"`` would otherwise be read as 0.0 and 0.3, and executed).
Num = Annotated[float, Strict()]
#: A count of a plan: a JSON integer, never a boolean, a string or a float.
Count = Annotated[int, Strict()]
Vec4 = Annotated[list[Num], Field(min_length=4, max_length=4)]


class Workspace(BaseModel):
    """Box of poses used to draw plans (metres; T in metres of the rack)."""

    model_config = ConfigDict(frozen=True, allow_inf_nan=False)
    X: tuple[Num, Num] = (0.75, 1.15)
    Y: tuple[Num, Num] = (-0.12, 0.12)
    Z: tuple[Num, Num] = (-0.78, -0.55)
    T: tuple[Num, Num] = (-0.045, 0.045)
    min_leg_x_m: Num = Field(0.25, description="smallest horizontal leg reach f = u_x L kept in plans")

    def centre(self) -> np.ndarray:
        """The box's centre ``(X, Y, Z, 0)``, metres, shape (4,)."""
        return np.array([np.mean(self.X), np.mean(self.Y), np.mean(self.Z), 0.0])


class SoftLimits(BaseModel):
    """Per-axis soft limits on encoder values, metres."""

    model_config = ConfigDict(frozen=True, allow_inf_nan=False)
    q_min: Vec4 = [-0.10, -0.10, -0.10, -0.10]
    q_max: Vec4 = [0.80, 0.80, 0.80, 0.80]


class LineSpec(BaseModel):
    """A guided straight line: on a real bench the drives are free and an operator follows a ruler."""

    model_config = ConfigDict(allow_inf_nan=False)
    start_pose: Vec4
    end_pose: Vec4
    samples: Count = Field(51, ge=3, le=MAX_LINE_SAMPLES)
    rate_hz: Num = Field(10.0, gt=0)


StepPhase = Literal[
    "rotation", "translation", "poses", "lock-1", "lock-2", "lock-3", "lock-4", "line", "validation", "camera"
]


class Step(BaseModel):
    """One plan step: move to ``q`` and record a frame, or record a guided line."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    phase: StepPhase
    q: Vec4 | None = Field(None, description="joint targets q1..q4 in metres")
    line: LineSpec | None = None


class Plan(BaseModel):
    """An ``i4cal.plan/1`` document: a named list of steps (joint targets in metres, guided lines)."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    format: Literal["i4cal.plan/1"] = PLAN_FORMAT
    name: str
    steps: list[Step] = Field(max_length=MAX_PLAN_STEPS)

    def count(self) -> dict[str, int]:
        """Frames per phase (a line step counts its samples), ``{phase: count}``."""
        out: dict[str, int] = {}
        for s in self.steps:
            out[s.phase] = out.get(s.phase, 0) + (s.line.samples if s.line else 1)
        return out

    def save(self, path: str | Path) -> None:
        """Write the plan as JSON (fields left unset omitted).

        Parameters
        ----------
        path : str or Path
            The destination file.
        """
        Path(path).write_text(self.model_dump_json(indent=1, exclude_none=True), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> Plan:
        """Read and validate a plan file (:meth:`from_dict`).

        Parameters
        ----------
        path : str or Path
            The plan file (JSON).

        Returns
        -------
        Plan
            The validated plan.

        Raises
        ------
        InputError
            Names the file, and the step and field of an invalid value.
        """
        return cls.from_dict(read_json(path, "plan file"), source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> Plan:
        """Validate a plan document: its size first (:data:`MAX_PLAN_STEPS`, :data:`MAX_LINE_SAMPLES`,
        :data:`MAX_PLAN_FRAMES`), then every field (finite numbers only).

        Parameters
        ----------
        data : Any
            The parsed JSON document.
        source : str, optional
            The file it came from, named in errors.

        Returns
        -------
        Plan
            The validated plan.

        Raises
        ------
        InputError
            Names the step (as ``frame``) and the field, e.g. ``line.samples`` or ``q[2]``.
        """
        steps = data.get("steps") if isinstance(data, dict) else None
        if isinstance(steps, list) and len(steps) > MAX_PLAN_STEPS:
            raise InputError(f"{len(steps)} steps, at most {MAX_PLAN_STEPS} per plan", file=source, field="steps")
        try:
            plan = cls.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = list(err["loc"])
            frame = None
            if len(loc) >= 2 and loc[0] == "steps" and isinstance(loc[1], int):
                frame = loc[1]
                loc = loc[2:]
            raise InputError(_error_message(err), file=source, frame=frame, field=_field_name(loc)) from None
        check_plan_size(plan, source)
        return plan


def _error_message(err: Any) -> str:
    """A validation error's message; a boolean or a string where a number belongs said so."""
    bad = err.get("input")
    if err["type"] in ("float_type", "int_type") and isinstance(bad, bool | str):
        kind = "a boolean" if isinstance(bad, bool) else "a string"
        return f"{err['msg']}: {bad!r} is {kind}, not a JSON number"
    return str(err["msg"])


def _field_name(loc: list[Any]) -> str | None:
    """``["line", "start_pose", 2]`` -> ``"line.start_pose[2]"`` (the form of the limit checks' ``q[3]``)."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or None


def check_plan_size(plan: Plan, source: str | None = None) -> int:
    """The plan's number of frames, after checking its size bounds (cheap: no kinematics).

    Parameters
    ----------
    plan : Plan
        The plan.
    source : str, optional
        The file it came from, named in errors.

    Returns
    -------
    int
        Frames in all (a ``q`` step one, a line step its ``samples``).

    Raises
    ------
    InputError
        More than :data:`MAX_PLAN_STEPS` steps, a line of more than :data:`MAX_LINE_SAMPLES` samples, or more than
        :data:`MAX_PLAN_FRAMES` frames in all (names the step at which the budget is exceeded).
    """
    if len(plan.steps) > MAX_PLAN_STEPS:
        raise InputError(f"{len(plan.steps)} steps, at most {MAX_PLAN_STEPS} per plan", file=source, field="steps")
    total = 0
    for i, step in enumerate(plan.steps):
        n = step.line.samples if step.line is not None else 1
        if n > MAX_LINE_SAMPLES:
            raise InputError(
                f"{n} samples, at most {MAX_LINE_SAMPLES} per line", file=source, frame=i, field="line.samples"
            )
        total += n
        if total > MAX_PLAN_FRAMES:
            raise InputError(
                f"the plan reaches {total} frames at this step, at most {MAX_PLAN_FRAMES} per plan",
                file=source,
                frame=i,
                field="line.samples" if step.line is not None else "steps",
            )
    return total


def validate_plan(plan: Plan, nominal: I4Parameters, limits: SoftLimits | None = None) -> None:
    """Check the plan's size (:func:`check_plan_size`), then every step against soft limits and the nominal model
    before anything moves. The joint vectors of all steps are checked together (vectorised: a plan at its size
    bounds validates in a fraction of a second); the first step found wrong is then checked alone for the message.

    Parameters
    ----------
    plan : Plan
        The plan.
    nominal : I4Parameters
        The geometry the steps must be reachable by (metres).
    limits : SoftLimits, optional
        Per-axis encoder limits (metres); :class:`SoftLimits`' defaults if None.

    Raises
    ------
    InputError
        Names the step (as ``frame``), the axis and by how much a limit is exceeded, a value that is not a finite
        number, or why the nominal model cannot reach it.
    """
    check_plan_size(plan)
    limits = limits or SoftLimits()
    lo = np.asarray(limits.q_min, dtype=np.float64)
    hi = np.asarray(limits.q_max, dtype=np.float64)
    first = _first_bad_step(plan, nominal, lo, hi)
    if first is not None:
        _check_step(first, plan.steps[first], nominal, lo, hi)
        # not reached when the batch and the single step agree (same functions); else: step by step
        for i, step in enumerate(plan.steps):
            _check_step(i, step, nominal, lo, hi)


def _step_joints(step: Step, nominal: I4Parameters) -> np.ndarray:
    """Joint targets of a step, shape (n, 4), metres (a line's samples through the nominal IKM)."""
    if step.line is not None:
        return ikm(nominal, _line_poses(step.line)).reshape(-1, 4)
    if step.q is not None:
        return np.asarray(step.q, dtype=np.float64).reshape(1, 4)
    raise InputError("a step needs 'q' or 'line'", field="q")


def _first_bad_step(plan: Plan, nominal: I4Parameters, lo: np.ndarray, hi: np.ndarray) -> int | None:
    """Index of the first step that fails a check (None: all pass), all steps' joint vectors checked at once."""
    rows: list[np.ndarray] = []
    owner: list[np.ndarray] = []
    cand: int | None = None
    for i, step in enumerate(plan.steps):
        try:
            qs = _step_joints(step, nominal)
        except (InputError, UnreachableError):
            cand = i  # every later step comes after it: no need to look at them
            break
        rows.append(qs)
        owner.append(np.full(len(qs), i))
    if not rows:
        return cand
    qa = np.concatenate(rows)
    own = np.concatenate(owner)
    bad = ~np.all(np.isfinite(qa), axis=1) | np.any((qa < lo) | (qa > hi), axis=1)
    n = int(np.argmax(bad)) if bad.any() else len(qa)  # rows before n pass the cheap checks
    if n > 0 and not _reachable(nominal, qa[:n]):
        lo_n, hi_n = 0, n  # the shortest unreachable prefix: qa[:hi_n] fails, qa[:lo_n] passes
        while hi_n - lo_n > 1:
            mid = (lo_n + hi_n) // 2
            lo_n, hi_n = (mid, hi_n) if _reachable(nominal, qa[:mid]) else (lo_n, mid)
        n = hi_n - 1
    if n < len(qa):
        return int(own[n]) if cand is None else min(int(own[n]), cand)
    return cand


def _reachable(nominal: I4Parameters, Q: np.ndarray) -> bool:
    try:
        dkm(nominal, Q)
    except UnreachableError:
        return False
    return True


def _check_step(i: int, step: Step, nominal: I4Parameters, lo: np.ndarray, hi: np.ndarray) -> None:
    """Check one step; :class:`InputError` names the step ``i``, the field and what is wrong."""
    if step.line is not None:
        for key in ("start_pose", "end_pose"):
            v = np.asarray(getattr(step.line, key), dtype=np.float64)
            if not np.all(np.isfinite(v)):
                ax = int(np.flatnonzero(~np.isfinite(v))[0])
                raise InputError(f"{v[ax]} is not a finite number", frame=i, field=f"line.{key}[{ax}]")
        try:
            qs = ikm(nominal, _line_poses(step.line))
        except UnreachableError as exc:
            raise InputError(f"guided line not reachable by the nominal model: {exc}", frame=i, field="line") from None
    elif step.q is not None:
        qs = np.asarray(step.q, dtype=np.float64)[None, :]
        if not np.all(np.isfinite(qs)):
            ax = int(np.flatnonzero(~np.isfinite(qs[0]))[0])
            raise InputError(f"{qs[0, ax]} is not a finite number", frame=i, field=f"q[{ax}]")
    else:
        raise InputError("a step needs 'q' or 'line'", frame=i, field="q")
    out = (qs < lo) | (qs > hi)
    if out.any():
        k, ax = (int(v) for v in np.argwhere(out)[0])
        qv = qs[k]
        bound = lo[ax] if qv[ax] < lo[ax] else hi[ax]
        raise InputError(
            f"q{ax + 1} = {qv[ax] * 1e3:.3f} mm is outside the soft limits "
            f"[{lo[ax] * 1e3:.1f}, {hi[ax] * 1e3:.1f}] mm by {abs(qv[ax] - bound) * 1e3:.3f} mm",
            frame=i,
            field=f"q[{ax}]",
        )
    try:
        dkm(nominal, qs)
    except UnreachableError as exc:
        raise InputError(f"not reachable by the nominal model: {exc}", frame=i, field="q") from None


def _line_poses(line: LineSpec) -> np.ndarray:
    s = np.linspace(0.0, 1.0, line.samples)[:, None]
    return (1 - s) * np.asarray(line.start_pose) + s * np.asarray(line.end_pose)


def line_poses(line: LineSpec) -> np.ndarray:
    """Poses of a guided line's samples, shape (samples, 4).

    Parameters
    ----------
    line : LineSpec
        The line (start and end poses in metres).

    Returns
    -------
    ndarray, shape (samples, 4)
        Poses ``(X, Y, Z, T)`` evenly spaced from start to end, metres.
    """
    return _line_poses(line)


# ---------------------------------------------------------------------------------------------
def _good(params: I4Parameters, poses: np.ndarray, ws: Workspace, limits: SoftLimits) -> np.ndarray:
    c = params.H - params.D
    _X, Y, Z, _T = poses.T
    f1sq = params.L**2 - (Y + c) ** 2 - Z**2
    f3sq = params.L**2 - (Y - c) ** 2 - Z**2
    ok = (f1sq > ws.min_leg_x_m**2) & (f3sq > ws.min_leg_x_m**2)
    q = np.full((len(poses), 4), np.nan)
    q[ok] = ikm(params, poses[ok])
    lo, hi = np.asarray(limits.q_min), np.asarray(limits.q_max)
    ok &= np.all((q >= lo) & (q <= hi), axis=1)
    return ok


def random_poses(
    params: I4Parameters,
    n: int,
    rng: np.random.Generator,
    ws: Workspace | None = None,
    limits: SoftLimits | None = None,
) -> np.ndarray:
    """``n`` poses drawn uniformly in the workspace box, reachable and within limits (nominal model).

    Parameters
    ----------
    params : I4Parameters
        The geometry (metres).
    n : int
        Number of poses.
    rng : numpy.random.Generator
        The random source.
    ws : Workspace, optional
        The box (metres); :class:`Workspace`'s defaults if None.
    limits : SoftLimits, optional
        Per-axis encoder limits (metres); :class:`SoftLimits`' defaults if None.

    Returns
    -------
    ndarray, shape (n, 4)
        Poses ``(X, Y, Z, T)``, metres.

    Raises
    ------
    InputError
        If ``n`` such poses cannot be drawn (a box mostly out of reach).
    """
    ws = ws or Workspace()
    limits = limits or SoftLimits()
    out: list[np.ndarray] = []
    for _ in range(200):
        # Workspace's X, Y, Z and T are (low, high) pairs
        cand = np.column_stack([rng.uniform(*cast("tuple[float, float]", getattr(ws, k)), size=4 * n) for k in "XYZT"])
        out.extend(cand[_good(params, cand, ws, limits)])
        if len(out) >= n:
            return np.asarray(out[:n])
    raise InputError(f"could not draw {n} reachable poses in the workspace")


def rotation_sweep(
    nominal: I4Parameters, n: int = 10, span_rad: float = np.deg2rad(300), ws: Workspace | None = None
) -> list[Step]:
    """T varies at fixed X, Y, Z: q1, q2 up and q3, q4 down by the same amount.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres; ``T_per_rad`` converts the span).
    n : int, optional
        Number of steps.
    span_rad : float, optional
        End-effector rotation from the first step to the last, radians (300 degrees by default).
    ws : Workspace, optional
        The box whose centre the sweep is about.

    Returns
    -------
    list of Step
        ``n`` steps of phase ``rotation``, joint targets in metres.
    """
    ws = ws or Workspace()
    c = ws.centre()
    q0 = ikm(nominal, c)
    dT = np.linspace(-span_rad / 2, span_rad / 2, n) * nominal.T_per_rad
    return [Step(phase="rotation", q=(q0 + d * np.array([1, 1, -1, -1])).tolist()) for d in dT]


def equal_translation(
    nominal: I4Parameters, n: int = 10, length_m: float = 0.35, ws: Workspace | None = None
) -> list[Step]:
    """All four actuators move equally: the end-effector translates along x_B.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres).
    n : int, optional
        Number of steps.
    length_m : float, optional
        Travel from the first step to the last, metres.
    ws : Workspace, optional
        The box whose centre the translation is about.

    Returns
    -------
    list of Step
        ``n`` steps of phase ``translation``, joint targets in metres.
    """
    ws = ws or Workspace()
    q0 = ikm(nominal, ws.centre())
    return [Step(phase="translation", q=(q0 + d).tolist()) for d in np.linspace(-length_m / 2, length_m / 2, n)]


def pose_set(
    nominal: I4Parameters,
    n: int = 20,
    seed: int = 0,
    phase: StepPhase = "poses",
    ws: Workspace | None = None,
    limits: SoftLimits | None = None,
) -> list[Step]:
    """``n`` poses spread over the workspace, reachable by the nominal model (seeded).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres).
    n : int, optional
        Number of poses.
    seed : int, optional
        Seed of the draw.
    phase : str, optional
        The steps' phase (``poses`` for fit poses, ``validation``).
    ws : Workspace, optional
        The box the poses are drawn in (metres).
    limits : SoftLimits, optional
        Per-axis encoder limits (metres).

    Returns
    -------
    list of Step
        ``n`` steps, joint targets in metres.

    Raises
    ------
    InputError
        If ``n`` reachable poses cannot be drawn.
    """
    rng = np.random.default_rng(seed)
    poses = random_poses(nominal, n, rng, ws, limits)
    return [Step(phase=phase, q=q.tolist()) for q in ikm(nominal, poses)]


def lock_actuator(
    nominal: I4Parameters,
    n_per_axis: int = 5,
    seed: int = 1,
    ws: Workspace | None = None,
    limits: SoftLimits | None = None,
) -> list[Step]:
    """For each actuator in turn, ``n_per_axis`` poses with that actuator fixed.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres).
    n_per_axis : int, optional
        Poses per locked actuator.
    seed : int, optional
        Seed of the draw.
    ws : Workspace, optional
        The box the poses are drawn in (metres; X is free, shifted to hold the lock).
    limits : SoftLimits, optional
        Per-axis encoder limits (metres).

    Returns
    -------
    list of Step
        ``4 n_per_axis`` steps of phases ``lock-1`` .. ``lock-4``, joint targets in metres.

    Raises
    ------
    InputError
        If an actuator's poses cannot be drawn.
    """
    ws = ws or Workspace()
    limits = limits or SoftLimits()
    rng = np.random.default_rng(seed)
    steps: list[Step] = []
    centre_q = ikm(nominal, ws.centre())
    for axis in range(4):
        lock = centre_q[axis]
        got: list[np.ndarray] = []
        for _ in range(400):
            pose = random_poses(nominal, 1, rng, ws, limits)[0]
            q = ikm(nominal, pose)
            pose = pose.copy()
            pose[0] += lock - q[axis]  # q_i is X + const: shift X so that q_i = lock
            if not _good(nominal, pose[None], ws.model_copy(update={"X": (-10.0, 10.0)}), limits)[0]:
                continue
            q = ikm(nominal, pose)
            q[axis] = lock
            got.append(q)
            if len(got) == n_per_axis:
                break
        else:
            raise InputError(f"could not draw {n_per_axis} poses with actuator {axis + 1} locked")
        phase = cast(StepPhase, f"lock-{axis + 1}")  # axis in 0..3: lock-1 .. lock-4
        steps += [Step(phase=phase, q=q.tolist()) for q in got]
    return steps


#: the shortest guided line :func:`guided_line` shortens a line to within a bench's limits (m)
MIN_LINE_LENGTH_M = 0.1


def guided_line(
    nominal: I4Parameters,
    length_m: float = 0.5,
    samples: int = 51,
    ws: Workspace | None = None,
    limits: SoftLimits | None = None,
) -> list[Step]:
    """The paper's straightness test: a 500 mm line mostly along x_B, through the workspace centre.

    With ``limits`` (a bench's soft limits), a line whose samples leave them (or the reachable workspace) is
    shortened about the centre, by 5% at a time, to the longest that stays within; shorter than
    :data:`MIN_LINE_LENGTH_M` is an error naming ``line``.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry (metres).
    length_m : float, optional
        Length of the line, metres.
    samples : int, optional
        Frames recorded along it.
    ws : Workspace, optional
        The box whose centre the line goes through.
    limits : SoftLimits, optional
        A bench's encoder limits (metres); None: the line is not shortened.

    Returns
    -------
    list of Step
        One step of phase ``line``.

    Raises
    ------
    InputError
        If no line of :data:`MIN_LINE_LENGTH_M` or more stays within ``limits`` (``field="line"``).
    """
    ws = ws or Workspace()
    c = ws.centre()
    d = np.array([0.96, 0.25, 0.12, 0.0])
    d[:3] /= np.linalg.norm(d[:3])
    s = np.linspace(-0.5, 0.5, samples)[:, None]
    while limits is not None and not np.all(_good(nominal, c + s * d * length_m, ws, limits)):
        length_m *= 0.95
        if length_m < MIN_LINE_LENGTH_M:
            raise InputError(
                f"no guided line of {MIN_LINE_LENGTH_M * 1e3:.0f} mm or more through the workspace centre stays "
                "within the soft limits",
                field="line",
            )
    a = c - d * length_m / 2
    b = c + d * length_m / 2
    return [Step(phase="line", line=LineSpec(start_pose=a.tolist(), end_pose=b.tolist(), samples=samples))]


def make_plan(
    name: str,
    nominal: I4Parameters,
    seed: int = 0,
    *,
    n_base: int = 10,
    n_fit: int = 20,
    n_lock: int = 5,
    n_validation: int = 10,
    line_samples: int = 51,
    ws: Workspace | None = None,
    limits: SoftLimits | None = None,
) -> Plan:
    """Build one of the named plans (see :data:`PLAN_NAMES`).

    ``limits``: the bench's soft limits, within which the drawn poses (fit poses, lock phases, validation) are
    drawn and the guided line shortened to (:func:`guided_line`); default: no line shortened, the poses drawn
    within :class:`SoftLimits`' (the simulated bench's). The sweeps are placed about the workspace's centre:
    :func:`validate_plan` says when they leave a bench's limits.

    Parameters
    ----------
    name : str
        One of :data:`PLAN_NAMES`.
    nominal : I4Parameters
        The geometry the poses are computed with (metres).
    seed : int, optional
        Seed of the drawn poses (fit poses ``seed``, lock phases ``seed + 1``, validation ``seed + 2``).
    n_base : int, optional
        Steps of each base-frame sweep (rotation, translation).
    n_fit : int, optional
        Fit poses.
    n_lock : int, optional
        Poses per locked actuator.
    n_validation : int, optional
        Validation poses.
    line_samples : int, optional
        Frames along the guided line.
    ws : Workspace, optional
        The box the poses are drawn in (metres).
    limits : SoftLimits, optional
        The bench's encoder limits (metres).

    Returns
    -------
    Plan
        The plan, named ``name``.

    Raises
    ------
    InputError
        If ``name`` is unknown (``field="plan"``) or its poses cannot be drawn.
    """
    ws = ws or Workspace()
    parts = {
        "rotation-sweep": lambda: rotation_sweep(nominal, n_base, ws=ws),
        "equal-translation": lambda: equal_translation(nominal, n_base, ws=ws),
        "pose-set": lambda: pose_set(nominal, n_fit, seed, ws=ws, limits=limits),
        "lock-actuator": lambda: lock_actuator(nominal, n_lock, seed + 1, ws=ws, limits=limits),
        "line": lambda: guided_line(nominal, samples=line_samples, ws=ws, limits=limits),
        "validation": lambda: pose_set(nominal, n_validation, seed + 2, phase="validation", ws=ws, limits=limits),
    }
    if name == "full":
        steps = [
            s
            for key in ("rotation-sweep", "equal-translation", "pose-set", "lock-actuator", "line", "validation")
            for s in parts[key]()
        ]
    elif name in parts:
        steps = parts[name]()
    else:
        raise InputError(f"unknown plan {name!r}; plans are {', '.join(PLAN_NAMES)}", field="plan")
    return Plan(name=name, steps=steps)
