"""A simulated camera the test can hold at a chosen frame, so that a run is certainly mid-acquisition when the test
acts on it (stops the service, kills it, pauses the run, starts another), whatever the machine's load: no motion
slowed down in real time to outlast the test's action, and the rest of the run goes at the simulator's speed.

The simulated bench renders a frame in a worker thread for each grab (``drivers.sim.bench.FrameServer``): a held
frame keeps that grab waiting, the run stays in ``acquiring``, and nothing else of the bench stops (Modbus answers,
the axes are at rest at the pose, as they are during any grab). Give the bench's camera a ``timeout_s`` longer than
any hold (:data:`HELD_GRAB`): a held frame is late, not lost.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

from drivers.sim.bench import SimBench
from tests.service.conftest import TinyRenderer

#: Bench override for a held camera: the run's grab waits for the held frame instead of timing out.
HELD_GRAB = {"camera": {"timeout_s": 60.0}}


class HeldRenderer(TinyRenderer):
    """:class:`TinyRenderer` that counts its frames (``frames``: 1 is the first frame rendered), calls ``on_frame``
    with each frame's number, and from frame ``hold_from`` on waits (``held`` set) until ``release`` is set.

    A run's first grab is one frame before anything moves, then one frame per pose: frame ``k + 1`` is pose ``k``'s.
    """

    def __init__(self) -> None:
        self.frames = 0
        self.hold_from: int | None = None
        self.on_frame: Callable[[int], None] | None = None
        self.held, self.release = threading.Event(), threading.Event()

    def hold_at_pose(self, pose: int) -> None:
        """Hold the frame of the next run's pose ``pose`` (1-based; the run must start after this call): poses
        ``1 .. pose - 1`` are grabbed, ``pose`` waits with the axes at rest. The run's progress counts the frames
        written, and a frame is written while the next pose moves: at least ``pose - 2`` are reported while held."""
        self.held.clear()
        self.release.clear()
        self.hold_from = self.frames + 1 + pose

    async def wait_held(self, timeout_s: float = 60.0) -> None:
        """Wait until a frame is held (the run is waiting on it)."""
        if not await asyncio.to_thread(self.held.wait, timeout_s):
            raise AssertionError(f"no frame held within {timeout_s} s (the run never reached the held pose)")

    def render(self, q_true, pose_true):
        self.frames += 1
        if self.on_frame is not None:
            self.on_frame(self.frames)
        if self.hold_from is not None and self.frames >= self.hold_from and not self.release.is_set():
            self.held.set()
            self.release.wait(60.0)
        return super().render(q_true, pose_true)


def hold_camera(sim: SimBench) -> HeldRenderer:
    """Give ``sim``'s camera a :class:`HeldRenderer` (the tiny images the ``sim`` fixture renders) and return it."""
    cam = HeldRenderer()
    sim.renderer = sim.frames.renderer = cam
    return cam
