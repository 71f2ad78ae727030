"""The suspenders on frames of the image-level twin: the board suspender objects to a frame where a person hides the
board (``CameraFaults.occluded``) and passes the lit one; the brightness suspender objects to a jump from the
recorded frames' brightness; a suspension returns only a frame grabbed after the scene cleared, waits for the user's
resume when asked to, and gives up after ``max_wait_s``. The acquisition's hook is tested over REST
(tests/service/test_suspenders_api.py)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from calib.formats.plan import make_plan
from drivers.acquisition.suspenders import (
    BoardSuspender,
    BrightnessSuspender,
    SuspendedTooLongError,
    SuspendersConfig,
    Suspension,
)
from drivers.devices.interfaces import Frame
from drivers.sim.bench import CameraFaults
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin


@pytest.fixture(scope="module")
def lit() -> np.ndarray:
    g = BenchGeometry()
    _, q, pose = GeometricTwin(g).true_poses(make_plan("rotation-sweep", g.nominal, n_base=3))[0]
    return BenchRenderer(g, RenderSettings(), seed=3).render(q, pose, np.random.default_rng(0))


def test_board_suspender_sees_the_board_hidden_by_a_person(lit):
    s = BoardSuspender()
    assert s.check(Frame(lit)) == ""
    hidden = CameraFaults(occluded=1).scene(lit)
    assert "does not see the board" in s.check(Frame(hidden))


def test_brightness_suspender_objects_to_a_jump_from_the_recorded_frames(lit):
    s = BrightnessSuspender(max_change=0.3)
    s.accept(Frame(lit))
    assert s.check(Frame(lit)) == ""
    brighter = np.clip(lit.astype(float) * 1.6, 0, 255).astype(np.uint8)  # a lamp switched on beside the bench
    assert "jumped +" in s.check(Frame(brighter))
    assert "dark" in s.check(Frame(CameraFaults(dark=1).scene(lit)))


class _Scene:
    """Frames as a camera sees them while the light is off for ``dark`` grabs."""

    def __init__(self, lit: np.ndarray, dark: int) -> None:
        self.lit, self.faults, self.grabs = lit, CameraFaults(dark=dark), 0

    async def grab(self) -> Frame:
        self.grabs += 1
        return Frame(self.faults.scene(self.lit), index=self.grabs)


async def test_a_suspension_returns_a_frame_grabbed_after_the_scene_cleared(lit):
    sus = Suspension.from_config(SuspendersConfig(poll_s=0.001, clear_frames=2))
    assert sus is not None
    scene = _Scene(lit, dark=3)
    reports: list[tuple[str, str]] = []
    frame = await sus.clear(await scene.grab(), scene.grab, lambda *r: reports.append(r), asyncio.Event())
    assert frame.index == 5 == scene.grabs  # 3 dark grabs, then 2 lit ones: the second lit one is returned
    assert [r[0] for r in reports] == ["suspended", "cleared"] and "dark" in reports[0][1]
    assert sus.reason == "" and sus.count == 1


async def test_resume_user_waits_for_the_user_once_cleared(lit):
    sus = Suspension.from_config(SuspendersConfig(poll_s=0.001, clear_frames=1, resume="user"))
    assert sus is not None
    scene, go = _Scene(lit, dark=2), asyncio.Event()
    go.set()
    task = asyncio.ensure_future(sus.clear(await scene.grab(), scene.grab, lambda *r: None, go))
    await asyncio.sleep(0.1)
    assert not task.done() and not go.is_set()  # cleared, held until the user resumes
    go.set()
    frame = await asyncio.wait_for(task, 5)
    assert np.array_equal(frame.image, lit)


async def test_a_suspension_gives_up_after_max_wait_s(lit):
    sus = Suspension.from_config(SuspendersConfig(poll_s=0.01, max_wait_s=0.05))
    assert sus is not None
    scene = _Scene(lit, dark=10**6)
    with pytest.raises(SuspendedTooLongError, match="max_wait_s"):
        await sus.clear(await scene.grab(), scene.grab, lambda *r: None, asyncio.Event())


def test_off_switch():
    assert Suspension.from_config(SuspendersConfig(enabled=False)) is None
    assert Suspension.from_config(SuspendersConfig(brightness=False)) is None
