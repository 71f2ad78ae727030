"""V4L2 (OpenCV, mocked), replay and sim cameras; the URI factory."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from calib.formats.dataset import BoardSpec, CameraSpec, DatasetWriter, LegsSpec
from calib.model.parameters import NOMINAL
from drivers.acquisition.config import open_camera
from drivers.errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, FrameError


# -- V4L2 ----------------------------------------------------------------------------------------
# No V4L2 device can exist on the test machines (no kernel modules): cv2.VideoCapture is mocked.
class FakeCapture:
    instances: list[FakeCapture] = []

    def __init__(self, dev, api, opened=True):
        import cv2

        assert api == cv2.CAP_V4L2
        self.dev, self.props, self.opened, self.released = dev, {3: 640.0, 4: 480.0}, opened, False
        FakeCapture.instances.append(self)

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        if prop in (3, 4) and value not in (1024, 768, 640, 480):
            return False
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def read(self):
        h, w = int(self.props[4]), int(self.props[3])
        return True, np.full((h, w, 3), 9, np.uint8)

    def release(self):
        self.released = True


async def test_v4l2_mocked(monkeypatch):
    import cv2

    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    cam = open_camera("v4l2:///dev/video0")
    await cam.open()
    assert FakeCapture.instances[-1].dev == "/dev/video0"
    await cam.configure(width=1024, height=768, exposure_us=8000)
    assert FakeCapture.instances[-1].props[cv2.CAP_PROP_EXPOSURE] == 80.0
    f = await cam.grab(1.0)
    assert f.image.shape == (768, 1024, 3)
    with pytest.raises(DeviceError, match="refused 1000x700"):
        await cam.configure(width=1000, height=700)
    await cam.close()
    assert FakeCapture.instances[-1].released
    cam = open_camera("v4l2://0")
    await cam.open()
    assert FakeCapture.instances[-1].dev == 0
    await cam.close()


async def test_v4l2_unopenable_is_a_clear_error(monkeypatch):
    import cv2

    monkeypatch.setattr(cv2, "VideoCapture", lambda dev, api: FakeCapture(dev, api, opened=False))
    with pytest.raises(DeviceConnectionError, match="cannot open V4L2 camera '/dev/video7'"):
        await open_camera("v4l2:///dev/video7").open()


async def test_v4l2_real_opencv_missing_device():
    """Real OpenCV, no device: OpenCV would only warn; the driver raises."""
    with pytest.raises(DeviceConnectionError, match="cannot open V4L2 camera"):
        await open_camera("v4l2:///dev/video-does-not-exist").open()


# -- replay --------------------------------------------------------------------------------------
async def test_replay_in_order(tmp_path):
    w = DatasetWriter(
        tmp_path / "ds",
        camera=CameraSpec(width=8, height=6),
        board=BoardSpec(),
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=NOMINAL.as_dict(),
    )
    for k in range(3):
        w.add_frame("poses", [0.1 * k] * 4, np.full((6, 8), k, np.uint8))
    cam = open_camera(f"replay://{tmp_path / 'ds'}")
    await cam.open()
    got = [await cam.grab() for _ in range(3)]
    assert [int(f.image[0, 0]) for f in got] == [0, 1, 2]
    assert got[2].meta["q"] == pytest.approx([0.2] * 4)
    with pytest.raises(DeviceTimeoutError, match="no more frames"):
        await cam.grab()
    with pytest.raises(DeviceConnectionError, match="cannot replay"):
        await open_camera(f"replay://{tmp_path / 'nothing'}").open()


# -- sim -----------------------------------------------------------------------------------------
async def test_sim_camera_shows_the_true_state(bench):
    cam = open_camera(bench.camera_uri)
    await cam.open()
    bench.mechanism.axes[0].pos = 0.5
    f = await cam.grab(1.0)
    assert f.meta["q_true"][0] == 0.5 and int(f.image[0, 0]) == 50
    # the camera times out, then delivers again on a fresh link
    bench.frames.faults.timeouts = 1
    with pytest.raises(DeviceTimeoutError):
        await cam.grab(0.1)
    assert (await cam.grab(1.0)).image.shape == (24, 32)
    bench.frames.faults.corrupt = 1
    with pytest.raises(FrameError, match="corrupt frame"):
        await cam.grab(1.0)
    bench.frames.faults.render_errors = 1
    with pytest.raises(DeviceError, match="sensor readout error"):
        await cam.grab(1.0)
    assert (await cam.grab(1.0)).image.shape == (24, 32)
    await cam.close()
    await bench.frames.close()
    await asyncio.sleep(0.01)
    with pytest.raises(DeviceConnectionError):
        await cam.grab(0.5)
