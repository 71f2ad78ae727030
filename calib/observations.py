"""Observations format v1 (``i4cal.observations/1``): the geometric-level input of calibration.

What image processing produces and what a user can inspect, edit or re-fit without the images:
encoder values, board poses ``camera_from_board`` and rod axes in the camera frame, per frame.
See docs/observations.md; the JSON Schema ships as ``calib/schemas/observations-v1.schema.json``.

Reading validates every frame and reports the first bad field with its frame index
(:class:`~calib.errors.InputError`); extra fields are allowed and kept on a round trip.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import InputError
from .jsonio import read_json, write_json_atomic
from .parameters import PARAMETER_NAMES, I4Parameters

FORMAT = "i4cal.observations/1"
PHASES: tuple[str, ...] = (
    "rotation",
    "translation",
    "poses",
    "lock-1",
    "lock-2",
    "lock-3",
    "lock-4",
    "line",
    "validation",
)
Phase = Literal["rotation", "translation", "poses", "lock-1", "lock-2", "lock-3", "lock-4", "line", "validation"]
LEG_KEYS: tuple[str, ...] = ("1", "2", "3", "4")

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vec4 = Annotated[list[float], Field(min_length=4, max_length=4)]


def _finite(values: Iterable[float], what: str) -> None:
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f"{what} contains a non-finite value")


class Rod(BaseModel):
    """One rod's axis in the camera frame: unit direction (sign arbitrary) and optionally a point."""

    model_config = ConfigDict(extra="allow")
    u: Vec3 = Field(description="axis direction in the camera frame (unit vector, sign arbitrary)")
    point: Vec3 | None = Field(default=None, description="a point of the axis in the camera frame, metres")

    @field_validator("u")
    @classmethod
    def _unit(cls, v: list[float]) -> list[float]:
        _finite(v, "u")
        n = math.sqrt(sum(x * x for x in v))
        if n < 1e-9:
            raise ValueError("u must be a non-zero direction")
        if abs(n - 1.0) > 1e-3:
            raise ValueError(f"u must be a unit vector (norm is {n:.6g})")
        return [x / n for x in v]

    @field_validator("point")
    @classmethod
    def _pt(cls, v: list[float] | None) -> list[float] | None:
        if v is not None:
            _finite(v, "point")
        return v


class Board(BaseModel):
    """``camera_from_board``: ``p_cam = R p_board + t`` (metres)."""

    model_config = ConfigDict(extra="allow")
    R: Annotated[list[Vec3], Field(min_length=3, max_length=3)] = Field(
        description="rotation camera_from_board, 3x3, rows"
    )
    t: Vec3 = Field(description="translation camera_from_board, metres")

    @field_validator("R")
    @classmethod
    def _rotation(cls, v: list[list[float]]) -> list[list[float]]:
        m = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(m)):
            raise ValueError("R contains a non-finite value")
        err = float(np.abs(m @ m.T - np.eye(3)).max())
        if err > 1e-5:
            raise ValueError(f"R is not orthonormal (|R R^T - I| = {err:.2g})")
        if np.linalg.det(m) < 0:
            raise ValueError("R has determinant -1 (a reflection, not a rotation)")
        return v

    @field_validator("t")
    @classmethod
    def _t(cls, v: list[float]) -> list[float]:
        _finite(v, "t")
        return v


class Frame(BaseModel):
    """One acquired frame: encoder values and what the camera saw."""

    model_config = ConfigDict(extra="allow")
    phase: Phase
    q: Vec4 = Field(description="encoder values q1..q4, metres")
    board: Board | None = None
    legs: dict[Literal["1", "2", "3", "4"], Annotated[list[Rod | None], Field(max_length=2)]] | None = Field(
        default=None, description="per leg, its two rods [rod at -x_B side, rod at +x_B side]; null for a missing rod"
    )

    @field_validator("q")
    @classmethod
    def _q(cls, v: list[float]) -> list[float]:
        _finite(v, "q")
        return v


class Nominal(BaseModel):
    """The a priori geometry (metres) and the rack-and-pinion constant (m/rad)."""

    model_config = ConfigDict(extra="allow")
    H: float
    q02: float
    q03: float
    q04: float
    S: float
    D: float
    L: float
    T_per_rad: float = Field(gt=0, description="metres of T per radian of end-effector rotation about z_B")

    @model_validator(mode="after")
    def _finite_all(self) -> Nominal:
        _finite([getattr(self, n) for n in (*PARAMETER_NAMES, "T_per_rad")], "nominal")
        return self

    def parameters(self) -> I4Parameters:
        return I4Parameters.from_mapping(self.model_dump())


class ObservationsDocument(BaseModel):
    """The whole observations v1 document."""

    model_config = ConfigDict(extra="allow", title="i4cal observations v1")
    format: Literal["i4cal.observations/1"]
    nominal: Nominal
    frames: list[Frame]


# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PhaseArrays:
    """Numeric view of the frames of some phases, for the methods.

    Attributes
    ----------
    index : ndarray, shape (N,)
        Frame indices in the document.
    q : ndarray, shape (N, 4)
        Encoder values, metres.
    board_R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations (NaN where missing).
    board_t : ndarray, shape (N, 3)
        ``camera_from_board`` translations, metres (NaN where missing).
    has_board : ndarray of bool, shape (N,)
    rod_u : ndarray, shape (N, 4, 2, 3)
        Rod directions in the camera frame (NaN where missing).
    rod_p : ndarray, shape (N, 4, 2, 3)
        Points on rod axes in the camera frame, metres (NaN where missing).
    has_rod : ndarray of bool, shape (N, 4, 2)
    has_point : ndarray of bool, shape (N, 4, 2)
    """

    index: np.ndarray
    q: np.ndarray
    board_R: np.ndarray
    board_t: np.ndarray
    has_board: np.ndarray
    rod_u: np.ndarray
    rod_p: np.ndarray
    has_rod: np.ndarray
    has_point: np.ndarray

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def subset(self, mask: np.ndarray) -> PhaseArrays:
        return PhaseArrays(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))


class Observations:
    """A validated observations v1 document with numeric views per phase."""

    def __init__(self, document: ObservationsDocument, source: str | None = None) -> None:
        self.document = document
        self.source = source
        self.nominal: I4Parameters = document.nominal.parameters()

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> Observations:
        """Validate a parsed JSON document; raise :class:`InputError` naming the first bad field."""
        if not isinstance(data, dict):
            raise InputError("the document must be a JSON object", file=source)
        fmt = data.get("format")
        if fmt != FORMAT:
            raise InputError(f"unsupported format {fmt!r}, expected {FORMAT!r}", file=source, field="format")
        try:
            doc = ObservationsDocument.model_validate(data)
        except ValidationError as exc:
            raise _input_error(exc, source) from None
        return cls(doc, source)

    @classmethod
    def load(cls, path: str | Path) -> Observations:
        return cls.from_dict(read_json(path), source=str(path))

    def to_dict(self) -> dict[str, Any]:
        return self.document.model_dump(mode="json", exclude_none=False)

    def save(self, path: str | Path) -> None:
        write_json_atomic(path, self.to_dict())

    # -- views ------------------------------------------------------------------------------
    @property
    def frames(self) -> list[Frame]:
        return self.document.frames

    def phases(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for f in self.frames:
            counts[f.phase] = counts.get(f.phase, 0) + 1
        return counts

    def arrays(self, *phases: str) -> PhaseArrays:
        """Numeric arrays of the frames of the given phases (all frames when none given)."""
        for ph in phases:
            if ph not in PHASES:
                raise ValueError(f"unknown phase {ph!r}; phases are {', '.join(PHASES)}")
        sel = [(i, f) for i, f in enumerate(self.frames) if not phases or f.phase in phases]
        n = len(sel)
        index = np.array([i for i, _ in sel], dtype=int)
        q = np.array([f.q for _, f in sel], dtype=np.float64).reshape(n, 4)
        bR = np.full((n, 3, 3), np.nan)
        bt = np.full((n, 3), np.nan)
        hb = np.zeros(n, dtype=bool)
        ru = np.full((n, 4, 2, 3), np.nan)
        rp = np.full((n, 4, 2, 3), np.nan)
        hr = np.zeros((n, 4, 2), dtype=bool)
        hp = np.zeros((n, 4, 2), dtype=bool)
        for k, (_, f) in enumerate(sel):
            if f.board is not None:
                bR[k] = f.board.R
                bt[k] = f.board.t
                hb[k] = True
            if f.legs:
                for key, rods in f.legs.items():
                    li = int(key) - 1
                    for j, rod in enumerate(rods[:2]):
                        if rod is None:
                            continue
                        ru[k, li, j] = rod.u
                        hr[k, li, j] = True
                        if rod.point is not None:
                            rp[k, li, j] = rod.point
                            hp[k, li, j] = True
        return PhaseArrays(index, q, bR, bt, hb, ru, rp, hr, hp)


_MODEL_TAGS = {"Rod", "Board", "Frame", "Nominal", "list[nullable[Rod]]", "nullable[Rod]", "none", "[key]"}


def _input_error(exc: ValidationError, source: str | None) -> InputError:
    err = exc.errors()[0]
    loc = list(err.get("loc", ()))
    frame = None
    if len(loc) >= 2 and loc[0] == "frames" and isinstance(loc[1], int):
        frame = int(loc[1])
        loc = loc[2:]
    # drop pydantic's union-branch tags (e.g. 'Rod') from the path
    parts = [str(p) for p in loc if p not in _MODEL_TAGS]
    field = ".".join(parts) if parts else None
    msg = err.get("msg", "invalid value")
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    return InputError(msg, file=source, frame=frame, field=field)


def json_schema() -> dict[str, Any]:
    """The JSON Schema of observations v1 (as shipped in ``calib/schemas``)."""
    schema = ObservationsDocument.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = "https://i4cal.invalid/schemas/observations-v1.schema.json"
    return schema


def new_document(nominal: I4Parameters, frames: list[dict[str, Any]], **extra: Any) -> dict[str, Any]:
    """Assemble an observations v1 dict from plain frame dicts."""
    return {"format": FORMAT, "nominal": nominal.as_dict(), "frames": frames, **extra}
