"""Motion plans as data: the paper's scripted phases in joint space.

A plan is a list of typed steps that can be inspected, edited, saved, validated against
soft limits and the nominal model, and dry-run without hardware. Generators follow the
paper's set-up (section IV.C): a rotation sweep and an equal-actuator translation for the
base frame, a pose set for the fit, poses with one actuator locked for the legs-only
method, a guided 500 mm line for straightness, and separate validation poses.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .errors import InputError, UnreachableError
from .jsonio import read_json
from .kinematics import dkm, ikm
from .parameters import I4Parameters

PLAN_FORMAT = "i4cal.plan/1"
PLAN_NAMES = ("full", "rotation-sweep", "equal-translation", "pose-set", "lock-actuator", "line", "validation")

Vec4 = Annotated[list[float], Field(min_length=4, max_length=4)]


class Workspace(BaseModel):
    """Box of poses used to draw plans (metres; T in metres of the rack)."""

    model_config = ConfigDict(frozen=True)
    X: tuple[float, float] = (0.75, 1.15)
    Y: tuple[float, float] = (-0.12, 0.12)
    Z: tuple[float, float] = (-0.78, -0.55)
    T: tuple[float, float] = (-0.045, 0.045)
    min_leg_x_m: float = Field(0.25, description="smallest horizontal leg reach f = u_x L kept in plans")

    def centre(self) -> np.ndarray:
        return np.array([np.mean(self.X), np.mean(self.Y), np.mean(self.Z), 0.0])


class SoftLimits(BaseModel):
    """Per-axis soft limits on encoder values, metres."""

    model_config = ConfigDict(frozen=True)
    q_min: Vec4 = [-0.10, -0.10, -0.10, -0.10]
    q_max: Vec4 = [0.80, 0.80, 0.80, 0.80]


class LineSpec(BaseModel):
    """A guided straight line: on a real bench the drives are free and an operator follows a ruler."""

    start_pose: Vec4
    end_pose: Vec4
    samples: int = Field(51, ge=3)
    rate_hz: float = Field(10.0, gt=0)


class Step(BaseModel):
    """One plan step: move to ``q`` and record a frame, or record a guided line."""

    model_config = ConfigDict(extra="allow")
    phase: Literal[
        "rotation", "translation", "poses", "lock-1", "lock-2", "lock-3", "lock-4", "line", "validation", "camera"
    ]
    q: Vec4 | None = Field(None, description="joint targets q1..q4 in metres")
    line: LineSpec | None = None


class Plan(BaseModel):
    model_config = ConfigDict(extra="allow")
    format: Literal["i4cal.plan/1"] = PLAN_FORMAT
    name: str
    steps: list[Step]

    def count(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in self.steps:
            out[s.phase] = out.get(s.phase, 0) + (s.line.samples if s.line else 1)
        return out

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.model_dump_json(indent=1, exclude_none=True), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> Plan:
        return cls.from_dict(read_json(path, "plan file"), source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> Plan:
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = list(err["loc"])
            frame = None
            if len(loc) >= 2 and loc[0] == "steps" and isinstance(loc[1], int):
                frame = loc[1]
                loc = loc[2:]
            raise InputError(err["msg"], file=source, frame=frame, field=".".join(map(str, loc)) or None) from None


def validate_plan(plan: Plan, nominal: I4Parameters, limits: SoftLimits | None = None) -> None:
    """Check every step against soft limits and the nominal model before anything moves.

    Raises
    ------
    InputError
        Names the step (as ``frame``), the axis and by how much a limit is exceeded, or why
        the nominal model cannot reach it.
    """
    limits = limits or SoftLimits()
    lo = np.asarray(limits.q_min)
    hi = np.asarray(limits.q_max)
    for i, step in enumerate(plan.steps):
        if step.line is not None:
            try:
                qs = ikm(nominal, _line_poses(step.line))
            except UnreachableError as exc:
                raise InputError(
                    f"guided line not reachable by the nominal model: {exc}", frame=i, field="line"
                ) from None
        elif step.q is not None:
            qs = np.asarray(step.q, dtype=np.float64)[None, :]
        else:
            raise InputError("a step needs 'q' or 'line'", frame=i, field="q")
        for qv in qs:
            for ax in range(4):
                if qv[ax] < lo[ax] or qv[ax] > hi[ax]:
                    bound = lo[ax] if qv[ax] < lo[ax] else hi[ax]
                    raise InputError(
                        f"q{ax + 1} = {qv[ax] * 1e3:.3f} mm is outside the soft limits "
                        f"[{lo[ax] * 1e3:.1f}, {hi[ax] * 1e3:.1f}] mm by {abs(qv[ax] - bound) * 1e3:.3f} mm",
                        frame=i,
                        field=f"q[{ax}]",
                    )
            try:
                dkm(nominal, qv)
            except UnreachableError as exc:
                raise InputError(f"not reachable by the nominal model: {exc}", frame=i, field="q") from None


def _line_poses(line: LineSpec) -> np.ndarray:
    s = np.linspace(0.0, 1.0, line.samples)[:, None]
    return (1 - s) * np.asarray(line.start_pose) + s * np.asarray(line.end_pose)


def line_poses(line: LineSpec) -> np.ndarray:
    """Poses of a guided line's samples, shape (samples, 4)."""
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
    """``n`` poses drawn uniformly in the workspace box, reachable and within limits (nominal model)."""
    ws = ws or Workspace()
    limits = limits or SoftLimits()
    out: list[np.ndarray] = []
    for _ in range(200):
        cand = np.column_stack([rng.uniform(*getattr(ws, k), size=4 * n) for k in "XYZT"])
        out.extend(cand[_good(params, cand, ws, limits)])
        if len(out) >= n:
            return np.asarray(out[:n])
    raise InputError(f"could not draw {n} reachable poses in the workspace")


def rotation_sweep(
    nominal: I4Parameters, n: int = 10, span_rad: float = np.deg2rad(300), ws: Workspace | None = None
) -> list[Step]:
    """T varies at fixed X, Y, Z: q1, q2 up and q3, q4 down by the same amount."""
    ws = ws or Workspace()
    c = ws.centre()
    q0 = ikm(nominal, c)
    dT = np.linspace(-span_rad / 2, span_rad / 2, n) * nominal.T_per_rad
    return [Step(phase="rotation", q=(q0 + d * np.array([1, 1, -1, -1])).tolist()) for d in dT]


def equal_translation(
    nominal: I4Parameters, n: int = 10, length_m: float = 0.35, ws: Workspace | None = None
) -> list[Step]:
    """All four actuators move equally: the end-effector translates along x_B."""
    ws = ws or Workspace()
    q0 = ikm(nominal, ws.centre())
    return [Step(phase="translation", q=(q0 + d).tolist()) for d in np.linspace(-length_m / 2, length_m / 2, n)]


def pose_set(
    nominal: I4Parameters,
    n: int = 20,
    seed: int = 0,
    phase: str = "poses",
    ws: Workspace | None = None,
    limits: SoftLimits | None = None,
) -> list[Step]:
    """``n`` poses spread over the workspace, reachable by the nominal model (seeded)."""
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
    """For each actuator in turn, ``n_per_axis`` poses with that actuator fixed."""
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
        steps += [Step(phase=f"lock-{axis + 1}", q=q.tolist()) for q in got]
    return steps


def guided_line(
    nominal: I4Parameters, length_m: float = 0.5, samples: int = 51, ws: Workspace | None = None
) -> list[Step]:
    """The paper's straightness test: a 500 mm line mostly along x_B, through the workspace centre."""
    ws = ws or Workspace()
    c = ws.centre()
    d = np.array([0.96, 0.25, 0.12, 0.0])
    d[:3] /= np.linalg.norm(d[:3])
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
) -> Plan:
    """Build one of the named plans (see :data:`PLAN_NAMES`)."""
    ws = ws or Workspace()
    parts = {
        "rotation-sweep": lambda: rotation_sweep(nominal, n_base, ws=ws),
        "equal-translation": lambda: equal_translation(nominal, n_base, ws=ws),
        "pose-set": lambda: pose_set(nominal, n_fit, seed, ws=ws),
        "lock-actuator": lambda: lock_actuator(nominal, n_lock, seed + 1, ws=ws),
        "line": lambda: guided_line(nominal, samples=line_samples, ws=ws),
        "validation": lambda: pose_set(nominal, n_validation, seed + 2, phase="validation", ws=ws),
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
