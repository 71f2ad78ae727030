"""Observations format v1 (``i4cal.observations/1``): the geometric-level input of calibration.

What image processing produces and what a user can inspect, edit or re-fit without the images:
encoder values, board poses ``camera_from_board`` and rod axes in the camera frame, per frame.
See docs/observations.md; the JSON Schema ships as ``calib/formats/schemas/observations-v1.schema.json``.

Reading validates every frame and reports the first bad field with its frame index
(:class:`~calib.errors.InputError`); extra fields are allowed and kept on a round trip.

Besides ``u``/``point`` and ``R``/``t``, :class:`Rod` and :class:`Board` declare the optional fields the image
extraction writes and the methods read (the vision -> methods contract: limb planes ``h``, the direction's
covariance ``cov_u``, limb samples ``limbs_px``, the board pose's ``cov`` and ``d_intrinsics``, quality figures).
Each is validated (shape, finite values) when present; a field a document does not carry stays absent when it
is written back (no ``null`` is added), so a document without them round-trips unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from calib.errors import InputError
from calib.model.parameters import PARAMETER_NAMES, I4Parameters
from calib.numerics.jsonio import read_json, write_json_atomic

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
LegKey = Literal["1", "2", "3", "4"]
LEG_KEYS: tuple[LegKey, ...] = ("1", "2", "3", "4")

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vec4 = Annotated[list[float], Field(min_length=4, max_length=4)]


Pair = Annotated[list[float], Field(min_length=2, max_length=2)]
Mat33 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]
Mat66 = Annotated[list[Annotated[list[float], Field(min_length=6, max_length=6)]], Field(min_length=6, max_length=6)]
NormalPair = Annotated[list[Vec3], Field(min_length=2, max_length=2)]
LimbSamples = Annotated[
    list[Annotated[list[Annotated[list[float], Field(min_length=2, max_length=2)]], Field(min_length=2)]],
    Field(min_length=2, max_length=2),
]
PoseSensitivity = Annotated[list[Annotated[list[float], Field(min_length=1)]], Field(min_length=6, max_length=6)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


def _finite(values: Iterable[float], what: str) -> None:
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f"{what} contains a non-finite value")


def _plain(v: Any) -> Any:
    """A numpy array or scalar as Python lists and numbers (the extraction's arrays validate as they are)."""
    return v.tolist() if isinstance(v, np.ndarray | np.generic) else v


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("n" if d is None else str(d) for d in shape) + ("," if len(shape) == 1 else "") + ")"


def _shaped(v: Any, name: str, shape: tuple[int | None, ...], what: str) -> Any:
    """Check that ``v`` (None, a nested list or an array) is a finite array of ``shape`` (None: any length >= 1).

    Raises ValueError naming the field, the expected and the actual shape (pydantic adds the frame and the path).
    """
    if v is None:
        return None
    try:
        a = np.asarray(_plain(v), dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers of shape {_shape_text(shape)} ({what})") from None
    if a.ndim != len(shape) or any(d != e if e is not None else d < 1 for d, e in zip(a.shape, shape, strict=True)):
        raise ValueError(f"{name} must have shape {_shape_text(shape)} ({what}), got {tuple(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains a non-finite value")
    return _plain(v)


def _drop_unset(model: BaseModel, data: dict[str, Any], optional: tuple[str, ...]) -> dict[str, Any]:
    """``data`` without the declared optional fields the document did not carry (they are written as before:
    absent, never ``null``)."""
    for name in optional:
        if name not in model.model_fields_set:
            data.pop(name, None)
    return data


#: the optional, typed rod fields written by the image extraction (:class:`calib.vision.rods.RodMeasurement`)
ROD_FIELDS: tuple[str, ...] = ("rms_px", "n_points", "plane_angle_rad", "cov_u", "cov_u_own", "h", "limbs_px")
RodArrayField = Literal["rms_px", "n_points", "cov_u", "cov_u_own", "h", "limbs_px"]
#: the optional, typed board fields written by the image extraction (:class:`calib.vision.board.BoardPose`)
BOARD_FIELDS: tuple[str, ...] = ("rms_px", "n_corners", "corners_rejected", "cov", "d_intrinsics")


class Rod(BaseModel):
    """One rod's axis in the camera frame: unit direction (sign arbitrary) and optionally a point.

    The other declared fields are optional: the image extraction writes them, a geometric twin or a foreign tool
    may not (they stay absent on a round trip).
    """

    model_config = ConfigDict(extra="allow")
    u: Vec3 = Field(description="axis direction in the camera frame (unit vector, sign arbitrary)")
    point: Vec3 | None = Field(default=None, description="a point of the axis in the camera frame, metres")
    rms_px: Pair | None = Field(
        default=None, description="shape (2,), px: RMS residual of the edge points about each fitted limb line"
    )
    n_points: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=2, max_length=2)] | None = Field(
        default=None, description="shape (2,), count: edge points kept on each limb line"
    )
    plane_angle_rad: FiniteFloat | None = Field(
        default=None, description="rad: angle between the rod's two interpretation planes (small: ill-conditioned)"
    )
    cov_u: Mat33 | None = Field(
        default=None,
        description="shape (3, 3), dimensionless (rad^2 across u): covariance of u in the camera frame, "
        "from the limb edges' scatter and the edge-bias allowance",
    )
    cov_u_own: Mat33 | None = Field(
        default=None,
        description="shape (3, 3), dimensionless (rad^2 across u): covariance of u without the limb-edge bias every "
        "rod shares (which a fit measures: the combined method's diagnostics.limb_edge_bias), the allowance "
        "averaged along the limb over the extraction's rod_settings.edge_bias_length_px; fits that measure the "
        "shared bias weigh the rod by it, by cov_u when it is absent",
    )
    h: NormalPair | None = Field(
        default=None,
        description="shape (2, 3), unit normals: the two limb lines' interpretation planes (through the camera "
        "centre), camera frame, in limb order (as rms_px, n_points, limbs_px)",
    )
    limbs_px: LimbSamples | None = Field(
        default=None,
        description="shape (2, P, 2), distorted px (x, y): per limb, P points of its fitted line (the extraction "
        "writes P = 5, the quantiles 0, 1/4, 1/2, 3/4, 1 of its edge points): the raw measurement the planes are "
        "recomputed from for other intrinsics",
    )

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

    @field_validator("rms_px", mode="before")
    @classmethod
    def _rms(cls, v: Any) -> Any:
        return _shaped(v, "rms_px", (2,), "RMS per limb, px")

    @field_validator("n_points", mode="before")
    @classmethod
    def _npts(cls, v: Any) -> Any:
        return _shaped(v, "n_points", (2,), "edge points per limb")

    @field_validator("plane_angle_rad", mode="before")
    @classmethod
    def _angle(cls, v: Any) -> Any:
        return _plain(v)

    @field_validator("cov_u", mode="before")
    @classmethod
    def _cov_u(cls, v: Any) -> Any:
        return _shaped(v, "cov_u", (3, 3), "covariance of u")

    @field_validator("cov_u_own", mode="before")
    @classmethod
    def _cov_u_own(cls, v: Any) -> Any:
        return _shaped(v, "cov_u_own", (3, 3), "covariance of u without the shared edge bias")

    @field_validator("h", mode="before")
    @classmethod
    def _h(cls, v: Any) -> Any:
        v = _shaped(v, "h", (2, 3), "two plane normals")
        if v is not None and float(np.linalg.norm(np.asarray(v, dtype=np.float64), axis=1).min()) < 1e-12:
            raise ValueError("h must hold two non-zero plane normals")
        return v

    @field_validator("limbs_px", mode="before")
    @classmethod
    def _limbs(cls, v: Any) -> Any:
        v = _shaped(v, "limbs_px", (2, None, 2), "P points of each of the two limb lines, px")
        if v is not None and len(v[0]) < 2:
            raise ValueError("limbs_px must hold at least 2 points per limb line")
        return v

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        return _drop_unset(self, handler(self), ROD_FIELDS)


class Board(BaseModel):
    """``camera_from_board``: ``p_cam = R p_board + t`` (metres); optionally the extraction's quality and covariance."""

    model_config = ConfigDict(extra="allow")
    R: Annotated[list[Vec3], Field(min_length=3, max_length=3)] = Field(
        description="rotation camera_from_board, 3x3, rows"
    )
    t: Vec3 = Field(description="translation camera_from_board, metres")
    rms_px: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = Field(
        default=None, description="px: RMS reprojection error of the corners used for the pose"
    )
    n_corners: Annotated[int, Field(ge=0)] | None = Field(default=None, description="count: ChArUco corners used")
    corners_rejected: Annotated[int, Field(ge=0)] | None = Field(
        default=None,
        description="count: corners detected but left out of the pose, their residual beyond the others' scatter "
        "(a corner next to an occluding rod, a glint)",
    )
    cov: Mat66 | None = Field(
        default=None,
        description="shape (6, 6): covariance of (rotation vector [rad], t [m]) of the pose, from the PnP Jacobian",
    )
    d_intrinsics: PoseSensitivity | None = Field(
        default=None,
        description="shape (6, n): the pose's first-order change per unit change of the camera's n intrinsics "
        "(fx, fy, cx, cy [px], then the lens model's distortion terms; n = 8 for k1, k2, p1, p2): rows are a left "
        "rotation R' = exp([w]) R (rad), then the change of t (m)",
    )

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

    @field_validator("rms_px", "n_corners", "corners_rejected", mode="before")
    @classmethod
    def _scalar(cls, v: Any) -> Any:
        return _plain(v)

    @field_validator("cov", mode="before")
    @classmethod
    def _cov(cls, v: Any) -> Any:
        return _shaped(v, "cov", (6, 6), "covariance of (rotation vector, t)")

    @field_validator("d_intrinsics", mode="before")
    @classmethod
    def _d_intrinsics(cls, v: Any) -> Any:
        return _shaped(v, "d_intrinsics", (6, None), "pose change per unit change of each intrinsic")

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        return _drop_unset(self, handler(self), BOARD_FIELDS)


class Frame(BaseModel):
    """One acquired frame: encoder values and what the camera saw."""

    model_config = ConfigDict(extra="allow")
    phase: Phase
    q: Vec4 = Field(description="encoder values q1..q4, metres")
    board: Board | None = None
    legs: dict[LegKey, Annotated[list[Rod | None], Field(max_length=2)]] | None = Field(
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
        """The frames selected by ``mask``, every array alike.

        Parameters
        ----------
        mask : ndarray of bool, shape (N,), or of int
            The frames kept (a boolean mask or indices).

        Returns
        -------
        PhaseArrays
            The selected frames.
        """
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
        """Validate a parsed JSON document; raise :class:`InputError` naming the first bad field.

        Parameters
        ----------
        data : Any
            The parsed JSON document.
        source : str, optional
            The file it came from, named in errors.

        Returns
        -------
        Observations
            The validated observations.

        Raises
        ------
        InputError
            Not an object, another format, or an invalid field (names the frame and field).
        """
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
        """Read and validate an observations file (:meth:`from_dict`).

        Parameters
        ----------
        path : str or Path
            The file (JSON).

        Returns
        -------
        Observations
            The validated observations.

        Raises
        ------
        InputError
            Names the file, and the frame and field of an invalid value.
        """
        return cls.from_dict(read_json(path), source=str(path))

    def to_dict(self) -> dict[str, Any]:
        return self.document.model_dump(mode="json", exclude_none=False)

    def save(self, path: str | Path) -> None:
        """Write the document as JSON, atomically (:func:`~calib.numerics.jsonio.write_json_atomic`).

        Parameters
        ----------
        path : str or Path
            The destination file.
        """
        write_json_atomic(path, self.to_dict(), readable=True)

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
        """Numeric arrays of the frames of the given phases (all frames when none given).

        Parameters
        ----------
        *phases : str
            Phases among ``PHASES``; none: every frame.

        Returns
        -------
        PhaseArrays
            The frames in document order (encoder values and positions in metres, NaN where not observed).

        Raises
        ------
        ValueError
            If a phase is unknown.
        """
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
    """The JSON Schema of observations v1 (as shipped in ``calib/formats/schemas``).

    Returns
    -------
    dict
        The schema (draft 2020-12), with its ``$schema`` and ``$id``.
    """
    schema = ObservationsDocument.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = "https://i4cal.invalid/schemas/observations-v1.schema.json"
    return schema


def new_document(nominal: I4Parameters, frames: list[dict[str, Any]], **extra: Any) -> dict[str, Any]:
    """Assemble an observations v1 dict from plain frame dicts.

    Parameters
    ----------
    nominal : I4Parameters
        The nominal geometry recorded in the document (metres).
    frames : list of dict
        The frames (``phase``, ``q`` in metres, ``board``, ``legs``, ...).
    **extra : Any
        Further top-level entries.

    Returns
    -------
    dict
        The document, to validate with :meth:`Observations.from_dict`.
    """
    return {"format": FORMAT, "nominal": nominal.as_dict(), "frames": frames, **extra}
