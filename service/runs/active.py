"""A run the service is executing: what is left of it and the handles of its stage under way."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

from service.runs.lifecycle import Remaining


@dataclass
class ActiveRun:
    """A run the service is executing (kept in memory while it is active)."""

    id: str
    remaining: Remaining
    task: asyncio.Task | None = None
    acq: Any = None
    holds_bench: bool = False
    aborting: bool = False
    paused: bool = False
    #: why the acquisition suspended itself (drivers.acquisition.suspenders), "" when it is not
    suspended: str = ""
    last_frame: int | None = None
    pose: list[float] | None = None
    started: float = field(default_factory=time.monotonic)
    #: extraction's detections per dataset frame (observations v1 frame layout), while the run is active
    detections: dict[int, dict[str, Any]] = field(default_factory=dict)
    last_extracted: int | None = None
    job: Any = None  # service.jobs.Job: the extraction or fit process
    #: the frames measured during the acquisition (drivers.acquisition.streaming: the file the stream worker wrote), if
    #: any
    streamed: str | None = None
