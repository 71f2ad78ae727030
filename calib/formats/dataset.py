"""Dataset format v1 (``i4cal.dataset/1``): a recorded run on disk.

A directory with ``dataset.json`` and lossless PNG images (8 or 16 bit, mono or colour) under
``frames/``. See docs/dataset.md; the JSON Schema ships as ``calib/formats/schemas/dataset-v1.schema.json``.

Writing is incremental and crash-safe: each frame's image is written to a temporary file and
renamed, then ``dataset.json`` is rewritten to a temporary file, flushed and atomically renamed.
A run cut off at any instant leaves a valid dataset of the frames written so far.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from calib.errors import InputError
from calib.numerics.jsonio import dumps_readable, fsync_dir

if TYPE_CHECKING:
    from calib.formats.camera import CameraModel
from calib.formats.observations import PHASES, Nominal

DATASET_FORMAT: Final = "i4cal.dataset/1"
DATASET_PHASES = ("camera", *PHASES)  # the observations' phases, and the camera calibration's views

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class CameraSpec(BaseModel):
    """Image size, and intrinsics + distortion (OpenCV's model) when already known."""

    model_config = ConfigDict(extra="allow")
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    K: Annotated[list[Vec3], Field(min_length=3, max_length=3)] | None = Field(
        None, description="camera matrix, pixels"
    )
    dist: list[float] | None = Field(None, description="OpenCV distortion coefficients (k1 k2 p1 p2 [k3 ...])")
    pixel_size_m: float | None = None

    def camera_model(self) -> CameraModel | None:
        """The known camera (``K``, ``dist`` and, when the acquisition recorded a camera file, its ``calibration``:
        covariance, refined board points, lens model), or None when the intrinsics are to be calibrated."""
        from calib.formats.camera import CameraModel

        if self.K is None or self.dist is None:
            return None
        known = (self.model_extra or {}).get("intrinsics")
        calibration = known.get("calibration") if isinstance(known, dict) else None
        extra = {"calibration": calibration} if isinstance(calibration, dict) else {}
        return CameraModel(np.asarray(self.K, dtype=np.float64), np.asarray(self.dist), self.width, self.height, extra)


class BoardSpec(BaseModel):
    """A ChArUco board as OpenCV defines it."""

    model_config = ConfigDict(extra="allow")
    dictionary: str = Field("DICT_4X4_50", description="cv2.aruco predefined dictionary name")
    squares_x: int = Field(6, ge=2)
    squares_y: int = Field(4, ge=2)
    square_length_m: float = Field(0.04, gt=0)
    marker_length_m: float = Field(0.03, gt=0)
    legacy_pattern: bool = False

    @field_validator("dictionary")
    @classmethod
    def _dict(cls, v: str) -> str:
        if not v.startswith("DICT_"):
            raise ValueError(f"unknown ArUco dictionary {v!r} (expected a name like DICT_4X4_50)")
        return v

    @property
    def size_m(self) -> tuple[float, float]:
        return (self.squares_x * self.square_length_m, self.squares_y * self.square_length_m)


class LegsSpec(BaseModel):
    model_config = ConfigDict(extra="allow")
    rod_radius_m: float = Field(gt=0)
    rods_per_leg: int = Field(2, ge=1, le=2)
    rod_spacing_m: float | None = Field(None, description="distance between the two rods of a leg (along x_B)")


class DatasetFrame(BaseModel):
    model_config = ConfigDict(extra="allow")
    phase: Literal[
        "camera", "rotation", "translation", "poses", "lock-1", "lock-2", "lock-3", "lock-4", "line", "validation"
    ]
    q: Annotated[list[float], Field(min_length=4, max_length=4)] = Field(
        description="encoder values q1..q4 as read, metres"
    )
    image: str | None = Field(None, description="image path relative to the dataset directory")
    t: float = Field(0.0, description="seconds since the start of the run")

    @field_validator("image")
    @classmethod
    def _rel(cls, v: str | None) -> str | None:
        if v is None:
            return v
        p = Path(v)
        if p.is_absolute() or ".." in p.parts:
            raise ValueError(f"image path must be relative and inside the dataset, got {v!r}")
        return v


class DatasetDocument(BaseModel):
    model_config = ConfigDict(extra="allow", title="i4cal dataset v1")
    format: Literal["i4cal.dataset/1"]
    camera: CameraSpec
    board: BoardSpec
    legs: LegsSpec
    nominal: Nominal
    frames: list[DatasetFrame] = []


def dataset_json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of ``dataset.json`` (``i4cal.dataset/1``).

    Returns
    -------
    dict
        The schema, with its ``$schema`` and ``$id``.
    """
    schema = DatasetDocument.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = "https://i4cal.invalid/schemas/dataset-v1.schema.json"
    return schema


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


class Dataset:
    """A dataset directory opened for reading."""

    def __init__(self, root: Path, document: DatasetDocument) -> None:
        self.root = root
        self.document = document

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Dataset:
        """Open a dataset directory and validate its ``dataset.json``.

        Parameters
        ----------
        path : str or path-like
            The directory, or its ``dataset.json``.

        Returns
        -------
        Dataset
            The dataset (images are read on demand).

        Raises
        ------
        InputError
            No ``dataset.json``, invalid JSON, another format, or an invalid field (names the frame and field).
        """
        root = Path(path)
        if root.is_file() and root.name == "dataset.json":
            root = root.parent
        meta = root / "dataset.json"
        if not meta.exists():
            raise InputError("not a dataset directory (no dataset.json)", file=str(root))
        try:
            data = json.loads(meta.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}", file=str(meta)) from None
        if not isinstance(data, dict) or data.get("format") != DATASET_FORMAT:
            raise InputError(
                f"unsupported format {data.get('format') if isinstance(data, dict) else None!r}, "
                f"expected {DATASET_FORMAT!r}",
                file=str(meta),
                field="format",
            )
        try:
            doc = DatasetDocument.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = list(err["loc"])
            frame = None
            if len(loc) >= 2 and loc[0] == "frames" and isinstance(loc[1], int):
                frame = loc[1]
                loc = loc[2:]
            msg = err["msg"].removeprefix("Value error, ")
            raise InputError(msg, file=str(meta), frame=frame, field=".".join(map(str, loc)) or None) from None
        return cls(root, doc)

    @property
    def frames(self) -> list[DatasetFrame]:
        return self.document.frames

    def image_path(self, index: int) -> Path | None:
        """Path of a frame's image file.

        Parameters
        ----------
        index : int
            The frame's index.

        Returns
        -------
        Path or None
            The image's path (which may not exist), None for a frame without image.
        """
        img = self.frames[index].image
        return None if img is None else self.root / img

    def load_image(self, index: int) -> np.ndarray:
        """Read a frame's image unchanged (8 or 16 bit, mono or colour); InputError when missing or corrupt.

        Parameters
        ----------
        index : int
            The frame's index.

        Returns
        -------
        ndarray, shape (H, W) or (H, W, C)
            The pixels, uint8 or uint16, as stored.

        Raises
        ------
        InputError
            The frame has no image, or its file is missing or corrupt (names the frame, ``field="image"``).
        """
        import cv2

        path = self.image_path(index)
        if path is None:
            raise InputError("frame has no image", frame=index, field="image")
        if not path.exists():
            raise InputError(f"image file missing: {self.frames[index].image}", frame=index, field="image")
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"image file corrupt or truncated: {self.frames[index].image}", frame=index, field="image")
        return img


class DatasetWriter:
    """Incremental, crash-safe writer of a dataset directory.

    Examples
    --------
    >>> w = DatasetWriter(path, camera=CameraSpec(width=1024, height=768), board=BoardSpec(),
    ...                   legs=LegsSpec(rod_radius_m=0.008), nominal=NOMINAL.as_dict())
    >>> w.add_frame("poses", q, image)          # doctest: +SKIP
    """

    def __init__(
        self,
        path: str | Path,
        *,
        camera: CameraSpec,
        board: BoardSpec,
        legs: LegsSpec,
        nominal: dict[str, float],
        extra: dict[str, Any] | None = None,
        resume: bool = False,
    ) -> None:
        self.root = Path(path)
        (self.root / "frames").mkdir(parents=True, exist_ok=True)
        #: one writer of the document at a time: frames are written from a worker thread while the run's own thread
        #: records its state (set_extra); both rewrite dataset.json through the same temporary file
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        if resume and (self.root / "dataset.json").exists():
            ds = Dataset.open(self.root)
            self._doc = ds.document.model_dump(mode="json")
            if ds.frames:
                self._t0 -= ds.frames[-1].t
        else:
            self._doc = DatasetDocument(
                format=DATASET_FORMAT,
                camera=camera,
                board=board,
                legs=legs,
                nominal=Nominal.model_validate(nominal),
                frames=[],
            ).model_dump(mode="json")
            if extra:
                self._doc.update(extra)
            self._flush()

    def __len__(self) -> int:
        return len(self._doc["frames"])

    def set_extra(self, key: str, value: Any) -> None:
        """Set a top-level entry of ``dataset.json`` and write the document.

        Parameters
        ----------
        key : str
            The entry's name.
        value : Any
            A JSON-serialisable value.
        """
        with self._lock:
            self._doc[key] = value
            self._flush()

    def add_frame(self, phase: str, q: Any, image: np.ndarray | None, t: float | None = None, **extra: Any) -> int:
        """Write the image (PNG, lossless) then append the frame to ``dataset.json``; returns its index.

        Parameters
        ----------
        phase : str
            One of ``DATASET_PHASES``.
        q : array_like, shape (4,)
            Encoder values, metres.
        image : ndarray, shape (H, W) or (H, W, C), optional
            uint8 or uint16 pixels; None for a frame without image.
        t : float, optional
            Time of the frame, seconds from the dataset's start (now by default).
        **extra : Any
            Further JSON-serialisable fields of the frame.

        Returns
        -------
        int
            The frame's index.

        Raises
        ------
        InputError
            An unknown phase, a ``q`` without 4 values, or an image of another depth.
        """
        import cv2

        if phase not in DATASET_PHASES:
            raise InputError(f"unknown phase {phase!r}", field="phase")
        qv = [float(v) for v in np.asarray(q, dtype=np.float64).reshape(-1)]
        if len(qv) != 4:
            raise InputError(f"q must have 4 values, got {len(qv)}", field="q")
        with self._lock:
            index = len(self._doc["frames"])
            rel = None
            if image is not None:
                if image.dtype not in (np.uint8, np.uint16):
                    raise InputError(f"image must be 8 or 16 bit, got {image.dtype}", frame=index, field="image")
                rel = f"frames/{index:06d}.png"
                ok, buf = cv2.imencode(".png", image)
                if not ok:
                    raise InputError("PNG encoding failed", frame=index, field="image")
                _atomic_write_bytes(self.root / rel, buf.tobytes())
            frame = {
                "phase": phase,
                "q": qv,
                "image": rel,
                "t": float(time.monotonic() - self._t0) if t is None else float(t),
                **extra,
            }
            self._doc["frames"].append(frame)
            self._flush()
            return index

    def _flush(self) -> None:
        _atomic_write_bytes(self.root / "dataset.json", dumps_readable(self._doc).encode())

    def close(self) -> None:
        with self._lock:
            self._flush()
