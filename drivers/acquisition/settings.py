"""What an acquisition run is told besides its plan and its devices: how it moves, grabs and checks each frame
(:class:`AcquisitionSettings`, the bench file's) and what its dataset records of the bench (:class:`DatasetHeader`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from calib.formats.dataset import BoardSpec, LegsSpec


@dataclass(frozen=True)
class AcquisitionSettings:
    """How a run moves, grabs and checks its frames (:meth:`from_config`: the bench file's ``[acquisition]``,
    ``[camera]`` and ``[actuators]`` settings of the same names).

    settle_s:
        Wait after each move before the frame's first encoder reading (s).
    grab_timeout_s:
        One grab's timeout (s).
    grab_retries:
        A grab that times out or fails is tried again this many times.
    line_rate_hz:
        The guided line's sampling rate (Hz), capped to what grab + write sustain; ``None``: the plan's.
    home:
        Home the axes before the first move when they are not homed.
    line_still_m:
        A frame's encoder readings before and after its grab agree within this (m), or it is read again.
    frame_reads:
        A pose's frame whose encoder readings fail their checks is read again, at most this many times in all.
    """

    settle_s: float = 0.0
    grab_timeout_s: float = 2.0
    grab_retries: int = 1
    line_rate_hz: float | None = None
    home: bool = True
    line_still_m: float = 1e-5
    frame_reads: int = 3

    @classmethod
    def from_config(cls, cfg: Any) -> AcquisitionSettings:
        """The settings a bench file (:class:`drivers.acquisition.config.BenchConfig`) gives."""
        return cls(
            settle_s=cfg.acquisition.settle_s,
            grab_timeout_s=cfg.camera.timeout_s,
            grab_retries=cfg.camera.grab_retries,
            line_rate_hz=cfg.acquisition.line_rate_hz,
            home=cfg.actuators.home_on_connect,
        )


def _default_legs() -> LegsSpec:
    return LegsSpec(rod_radius_m=0.008, rods_per_leg=2, rod_spacing_m=0.06)


@dataclass(frozen=True)
class DatasetHeader:
    """What the dataset records of the bench besides its frames (docs/dataset.md).

    board:
        The calibration board on the traveling plate.
    legs:
        The legs' rods (radius, rods per leg, spacing; metres).
    camera:
        The camera's fields beyond the image size (``K``, ``dist``, ``intrinsics``, ``lens_model``).
    extra:
        Free fields of the dataset (``truth`` of a simulated run, ``service_run``).
    """

    board: BoardSpec = field(default_factory=BoardSpec)
    legs: LegsSpec = field(default_factory=_default_legs)
    camera: Mapping[str, Any] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)
