"""Suspenders: an acquisition pauses itself while the scene is not fit to record, and resumes when it clears.

A suspender looks at every frame a pose grabs, before it is written: :class:`BrightnessSuspender` (the image went
dark, or its brightness jumped: a light switched off, a person in the view) and :class:`BoardSuspender` (the camera
does not see the calibration board). While one of them objects, the acquisition holds the robot where it is (no
motion starts), grabs again every ``poll_s`` and writes nothing; once ``clear_frames`` frames in a row pass, it
resumes by itself (``resume = "auto"``) or waits for the user's resume (``"user"``), and grabs the pose's frame again:
a frame grabbed under the bad condition is never recorded. Suspended longer than ``max_wait_s``, the run fails
saying why (its frames are kept; resume it later). Settings: the bench file's ``[suspenders]`` section
(:class:`SuspendersConfig`)::

    [suspenders]
    enabled = true                 # false: no suspender at all
    brightness = true              # the brightness suspender
    max_brightness_change = 0.3    # relative change of the mean brightness from the recent frames' that suspends
    min_brightness = 0.02          # a mean below this fraction of full scale suspends (dark)
    board = false                  # the board suspender (a ChArUco detection per frame)
    board_min_corners = 6          # fewer board corners than this suspends
    poll_s = 0.5                   # grab again this often while suspended
    clear_frames = 2               # this many good frames in a row clear the suspension
    max_wait_s = 600               # fail the run after this long suspended (0: wait for ever)
    resume = "auto"                # or "user": wait for the user's resume once it cleared
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.devices.interfaces import Frame
from drivers.errors import DeviceError

log = logging.getLogger(__name__)


class SuspendersConfig(BaseModel):
    """The bench file's ``[suspenders]`` section (module docstring)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    enabled: bool = True
    brightness: bool = True
    max_brightness_change: float = Field(0.3, gt=0, le=10)
    min_brightness: float = Field(0.02, ge=0, lt=1)
    board: bool = False
    board_min_corners: int = Field(6, ge=1)
    poll_s: float = Field(0.5, gt=0, le=60)
    clear_frames: int = Field(2, ge=1, le=100)
    max_wait_s: float = Field(600.0, ge=0)
    resume: Literal["auto", "user"] = "auto"


class SuspendedTooLongError(DeviceError):
    """The scene did not clear within ``max_wait_s``: the run stops (its frames are kept)."""


class Suspender(Protocol):
    """Looks at one frame: ``""`` when it may be recorded, else why not (one sentence)."""

    name: str

    def check(self, frame: Frame) -> str: ...

    def accept(self, frame: Frame) -> None:
        """The frame passed every suspender and is recorded (a suspender may learn its reference from it)."""


def mean_level(image: np.ndarray) -> float:
    """Mean brightness of ``image`` as a fraction of its full scale (8 or 16 bit; every 4th pixel)."""
    img = np.asarray(image)
    full = 65535.0 if img.dtype == np.uint16 else 255.0
    return float(img[::4, ::4].mean()) / full


@dataclass
class BrightnessSuspender:
    """Suspends on a dark image (mean below ``min_level`` of full scale) or a jump of the mean brightness beyond
    ``max_change`` (relative) from the recorded frames' (an exponential average of them)."""

    max_change: float = 0.3
    min_level: float = 0.02
    name: str = "brightness"
    reference: float | None = None

    def check(self, frame: Frame) -> str:
        level = mean_level(frame.image)
        if level < self.min_level:
            return (
                f"the image is dark: mean brightness {level:.1%} of full scale, below {self.min_level:.1%} "
                "(a light switched off?)"
            )
        ref = self.reference
        if ref is not None and ref > 0 and abs(level / ref - 1.0) > self.max_change:
            return (
                f"the image brightness jumped {level / ref - 1.0:+.0%} (mean {ref:.1%} -> {level:.1%} of full scale, "
                f"more than {self.max_change:.0%}): a light switched, a person in the view?"
            )
        return ""

    def accept(self, frame: Frame) -> None:
        level = mean_level(frame.image)
        self.reference = level if self.reference is None else 0.7 * self.reference + 0.3 * level


@dataclass
class BoardSuspender:
    """Suspends when the camera sees fewer than ``min_corners`` corners of the board (a ChArUco detection)."""

    board: Any = None  # calib.formats.dataset.BoardSpec (default: the dataset's default board)
    min_corners: int = 6
    name: str = "board"
    _detector: Any = field(default=None, repr=False)

    def check(self, frame: Frame) -> str:
        if self._detector is None:
            from calib.formats.dataset import BoardSpec
            from calib.vision.board import BoardDetector

            self._detector = BoardDetector(self.board or BoardSpec(), min_corners=self.min_corners)
        n = int(self._detector.detect(frame.image).ids.size)
        if n < self.min_corners:
            return f"the camera does not see the board: {n} corners found, fewer than {self.min_corners}"
        return ""

    def accept(self, frame: Frame) -> None:
        return None


#: what a suspension reports: ``(state, message)``, state ``suspended`` or ``cleared``
Report = Callable[[str, str], None]


@dataclass
class Suspension:
    """The suspenders of one acquisition and what to do while one objects (:class:`SuspendersConfig`)."""

    suspenders: Sequence[Suspender]
    poll_s: float = 0.5
    clear_frames: int = 2
    max_wait_s: float = 600.0
    resume: str = "auto"
    #: why the acquisition is suspended now ("" when it is not)
    reason: str = ""
    #: how many times it was suspended, and for how long in all (s)
    count: int = 0
    suspended_s: float = 0.0

    @classmethod
    def from_config(cls, cfg: SuspendersConfig, board: Any = None) -> Suspension | None:
        """The suspension the settings ask for; None when they switch every suspender off."""
        items: list[Suspender] = []
        if cfg.enabled and cfg.brightness:
            items.append(BrightnessSuspender(cfg.max_brightness_change, cfg.min_brightness))
        if cfg.enabled and cfg.board:
            items.append(BoardSuspender(board, cfg.board_min_corners))
        if not items:
            return None
        return cls(items, cfg.poll_s, cfg.clear_frames, cfg.max_wait_s, cfg.resume)

    @property
    def waits_for_user(self) -> bool:
        return self.resume == "user"

    def why(self, frame: Frame) -> str:
        """The first objection of the suspenders to ``frame`` (``"name: why"``), ``""`` when none objects."""
        for s in self.suspenders:
            reason = s.check(frame)
            if reason:
                return f"{s.name}: {reason}"
        return ""

    async def clear(
        self, frame: Frame, grab: Callable[[], Awaitable[Frame]], report: Report, go: asyncio.Event
    ) -> Frame:
        """``frame`` when every suspender passes it; else hold (report why, grab again every ``poll_s``) until the
        scene has cleared (and, with ``resume = "user"``, the user resumed: ``go`` set), and return a frame grabbed
        after it cleared. The caller moves nothing meanwhile.

        Raises
        ------
        SuspendedTooLongError
            Still suspended after ``max_wait_s`` (0: never raised).
        """
        reason = self.why(frame)
        if not reason:
            self._accept(frame)
            return frame
        t0 = time.monotonic()
        self.reason, self.count = reason, self.count + 1
        log.warning("acquisition suspended: %s", reason)
        if self.waits_for_user:
            go.clear()
        report("suspended", reason)
        good = 0
        try:
            while True:
                waited = time.monotonic() - t0
                if self.max_wait_s and waited > self.max_wait_s:
                    raise SuspendedTooLongError(
                        f"suspended for {waited:.0f} s (more than max_wait_s {self.max_wait_s:g} s): {self.reason}; "
                        "the robot was held, no frame of the bad scene was written; resume the run when it cleared"
                    )
                await asyncio.sleep(self.poll_s)
                frame = await grab()
                now = self.why(frame)
                if now:
                    good = 0
                    if now != self.reason:
                        self.reason = now
                        report("suspended", now)
                    continue
                good += 1
                if good < self.clear_frames:
                    continue
                if self.waits_for_user and not go.is_set():
                    report("suspended", f"cleared ({self.reason}); waiting for the user's resume")
                    await go.wait()
                    good = self.clear_frames - 1  # the next frame, grabbed after the resume, must pass too
                    continue
                dt = time.monotonic() - t0
                cleared, self.reason = self.reason, ""
                report("cleared", f"suspension cleared after {dt:.1f} s ({cleared})")
                self._accept(frame)
                return frame
        finally:
            self.suspended_s += time.monotonic() - t0
            self.reason = ""

    def _accept(self, frame: Frame) -> None:
        for s in self.suspenders:
            s.accept(frame)
