"""The harvesters driver against a real GenTL producer: viky.cti from the genicam 1.6 wheel (no hardware).

viky has no exposure, gain or trigger nodes: the driver must run without them (free-running fetch).
"""

from __future__ import annotations

import glob
import os

import numpy as np
import pytest

pytest.importorskip("harvesters")
genicam = pytest.importorskip("genicam")

from drivers.config import open_camera  # noqa: E402
from drivers.errors import DeviceConnectionError, DeviceTimeoutError  # noqa: E402

VIKY = glob.glob(os.path.join(os.path.dirname(genicam.__file__), "viky.cti"))
pytestmark = pytest.mark.skipif(not VIKY, reason="viky.cti not in this genicam wheel")


async def test_grab_by_serial_and_configure():
    cam = open_camera(f"genicam://?cti={VIKY[0]}&serial=1")
    await cam.open()
    try:
        assert cam.info["serial"] == "1" and cam.info["software_trigger"] is False
        await cam.configure(pixel_format="Mono8", exposure_us=5000, gain_db=1.0)
        assert set(cam.info["ignored_settings"]) == {"exposure_us", "gain_db"}
        frames = [await cam.grab(timeout_s=2.0) for _ in range(3)]
        for f in frames:
            assert f.image.dtype == np.uint8 and f.image.shape == (400, 400)
        assert [f.index for f in frames] == [1, 2, 3]
        await cam.configure(pixel_format="RGBa8")
        f = await cam.grab(timeout_s=2.0)
        assert f.image.shape == (400, 400, 3)
    finally:
        await cam.close()


async def test_timeout_and_buffers_returned():
    cam = open_camera(f"genicam://?cti={VIKY[0]}")
    await cam.open()
    try:
        with pytest.raises(DeviceTimeoutError, match="no complete frame"):
            await cam.grab(timeout_s=0.001)  # 20 fps: nothing within 1 ms ...
        for _ in range(12):  # ... and buffers keep coming back (a leak would starve the default 3 buffers)
            await cam.grab(timeout_s=2.0)
    finally:
        await cam.close()


async def test_unknown_serial_and_missing_producer(monkeypatch):
    with pytest.raises(DeviceConnectionError, match="no GenICam device with serial 'nope'"):
        await open_camera(f"genicam://?cti={VIKY[0]}&serial=nope").open()
    with pytest.raises(DeviceConnectionError, match="GenTL producer not found"):
        await open_camera("genicam://?cti=/nonexistent.cti").open()
    monkeypatch.setenv("GENICAM_GENTL64_PATH", os.path.dirname(VIKY[0]))
    cam = open_camera("genicam://")
    await cam.open()
    try:
        assert (await cam.grab(2.0)).image.size > 0
    finally:
        await cam.close()
