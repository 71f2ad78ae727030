"""The harvesters driver against real GenTL producers (no hardware).

* viky.cti from the installed genicam 1.6 wheel: no exposure, gain or trigger nodes, the driver must run
  without them (free-running fetch).
* TLSimu.cti from the genicam 1.4.0 wheel (software trigger: TriggerMode, TriggerSource=Software,
  TriggerSoftware): harvesters with genicam 1.6 loads it. The wheel is fetched once with pip (pinned
  by its SHA-256) into ``~/.cache/i4cal/genicam-1.4.0/`` (``$XDG_CACHE_HOME`` respected), and TLSimu.cti
  is extracted with the one library it needs (libVirtualFG.so, found next to it). Without network the
  test fails and says so; ``I4CAL_TLSIMU_CTI=/path/TLSimu.cti`` points at a copy fetched elsewhere.
"""

from __future__ import annotations

import asyncio
import glob
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("harvesters")
genicam = pytest.importorskip("genicam")

from drivers.acquisition.config import open_camera  # noqa: E402
from drivers.errors import DeviceConnectionError, DeviceTimeoutError  # noqa: E402

VIKY = glob.glob(os.path.join(os.path.dirname(genicam.__file__), "viky.cti"))
needs_viky = pytest.mark.skipif(not VIKY, reason="viky.cti not in this genicam wheel (genicam < 1.6)")

TLSIMU_WHEEL = "genicam-1.4.0-cp311-cp311-manylinux2014_x86_64.whl"
TLSIMU_WHEEL_SHA256 = "ede848faa23bb4e20cff98b685d73cc3e6fc4b82b2ab98ffabd7831dd41da9aa"
TLSIMU_FILES = ("TLSimu.cti", "libVirtualFG.so")  # the producer and the library it links ($ORIGIN rpath)


def fetch_tlsimu(cache: Path) -> Path:
    """TLSimu.cti in ``cache`` (fetched from the genicam 1.4.0 wheel by pip the first time)."""
    if all((cache / f).is_file() for f in TLSIMU_FILES):
        return cache / "TLSimu.cti"
    cache.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache.parent) as tmp:
        cmd = [
            sys.executable,
            "-m",
            "pip",
            "download",
            "genicam==1.4.0",
            "--no-deps",
            "--only-binary=:all:",
            "--python-version",
            "3.11",
            "--implementation",
            "cp",
            "--abi",
            "cp311",
            "--platform",
            "manylinux2014_x86_64",
            "--quiet",
            "-d",
            tmp,
        ]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        wheel = Path(tmp) / TLSIMU_WHEEL
        if r.returncode != 0 or not wheel.is_file():
            pytest.fail(
                f"could not fetch the genicam 1.4.0 wheel (TLSimu.cti) with `{' '.join(cmd[2:])}` "
                f"(exit {r.returncode}): {(r.stderr or r.stdout).strip()[-600:]}\nNo network? Fetch it "
                "elsewhere and set I4CAL_TLSIMU_CTI=/path/TLSimu.cti (libVirtualFG.so next to it).",
                pytrace=False,
            )
        digest = hashlib.sha256(wheel.read_bytes()).hexdigest()
        if digest != TLSIMU_WHEEL_SHA256:
            pytest.fail(f"{TLSIMU_WHEEL} has SHA-256 {digest}, expected {TLSIMU_WHEEL_SHA256}", pytrace=False)
        staging = Path(tmp) / "out"
        staging.mkdir()
        with zipfile.ZipFile(wheel) as z:
            for f in TLSIMU_FILES:
                (staging / f).write_bytes(z.read(f"genicam-1.4.0.data/purelib/genicam/{f}"))
        try:
            staging.rename(cache)  # atomic: a concurrent run either sees nothing or all of it
        except OSError:
            if not (cache / "TLSimu.cti").is_file():
                shutil.rmtree(cache, ignore_errors=True)
                staging.rename(cache)
    return cache / "TLSimu.cti"


@pytest.fixture(scope="module")
def tlsimu() -> str:
    """Path of TLSimu.cti: $I4CAL_TLSIMU_CTI, the installed genicam (1.4.x ships it), or the cached wheel."""
    if env := os.environ.get("I4CAL_TLSIMU_CTI"):
        if not os.path.isfile(env):
            pytest.fail(f"I4CAL_TLSIMU_CTI={env}: no such file", pytrace=False)
        return env
    installed = os.path.join(os.path.dirname(genicam.__file__), "TLSimu.cti")
    if os.path.isfile(installed):
        return installed
    if sys.platform != "linux" or platform.machine() != "x86_64":
        pytest.skip(
            f"TLSimu.cti is fetched for Linux x86_64 only (this is {sys.platform} {platform.machine()}); "
            "set I4CAL_TLSIMU_CTI to a producer built for this machine"
        )
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return str(fetch_tlsimu(root / "i4cal" / "genicam-1.4.0"))


@needs_viky
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


@needs_viky
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


@needs_viky
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


async def test_software_trigger_gives_a_frame_made_after_each_grab(tlsimu):
    """TLSimu stamps a frame with the wall clock's nanoseconds within the second when it makes it. With the
    software trigger each grab gets a frame made after it was asked for; a streamed frame waiting in a buffer
    (made before the grab) would show a lag close to 1 s."""
    cam = open_camera(f"genicam://?cti={tlsimu}&serial=SN_InterfaceA_0")
    await cam.open()
    try:
        info = cam.info
        assert info["model"] == "TLSimuMono" and info["serial"] == "SN_InterfaceA_0"
        assert info["software_trigger"] is True and info["trigger_mode"] == "On"
        await cam.configure(pixel_format="Mono8", exposure_us=5000, gain_db=1.0)  # restarts the stream
        assert set(cam.info["ignored_settings"]) == {"exposure_us", "gain_db"}
        ramps = []
        for k in range(5):
            if k:
                await asyncio.sleep(0.25)  # a free-running camera would queue frames meanwhile
            asked = time.time()
            f = await cam.grab(timeout_s=2.0)
            lag = (f.timestamp_s - asked) % 1.0
            assert lag < 0.2, f"grab {k}: frame made {1 - lag:.3f} s before it was asked for"
            assert f.image.shape == (512, 512) and f.image.dtype == np.uint8 and f.index == k + 1
            ramps.append(int(f.image[0, 0]))
        # TLSimu draws a ramp shifted by one per frame it makes: one frame made per trigger
        assert np.all(np.diff(ramps) == 1), ramps
        assert cam.stats["fetched"] == 5
    finally:
        await cam.close()


async def test_software_trigger_colour_device_and_buffers_returned(tlsimu):
    cam = open_camera(f"genicam://?cti={tlsimu}&serial=SN_InterfaceB_1")
    await cam.open()
    try:
        assert cam.info["model"] == "TLSimuColor" and cam.info["PixelFormat"] == "RGB8"
        assert cam.info["software_trigger"] is True
        f = await cam.grab(timeout_s=2.0)
        assert f.image.shape == (572, 768, 3)
        with pytest.raises(DeviceTimeoutError, match="no complete frame from GenICam camera SN_InterfaceB_1"):
            await cam.grab(timeout_s=1e-4)
        for _ in range(12):  # more grabs than the producer's buffers: every buffer comes back
            assert (await cam.grab(timeout_s=2.0)).image.shape == (572, 768, 3)
    finally:
        await cam.close()
