"""``v4l2:///dev/video0`` or ``v4l2://0``: a UVC/V4L2 camera through OpenCV (``cv2.CAP_V4L2``).

OpenCV only warns when a device cannot be opened: this driver raises a clear
:class:`~drivers.errors.DeviceConnectionError` instead. Resolution and exposure are requested through
``CAP_PROP_FRAME_WIDTH/HEIGHT`` and ``CAP_PROP_AUTO_EXPOSURE`` (1 = manual on V4L2) +
``CAP_PROP_EXPOSURE`` (V4L2 units of 100 us).
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np

from drivers.devices.interfaces import Frame
from drivers.errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, FrameError


class V4L2Camera:
    def __init__(self, device: str | int, timeout_s: float = 2.0) -> None:
        self.device = device
        self.default_timeout_s = timeout_s
        self._cap: Any = None  # cv2.VideoCapture once open
        self._index = 0
        self._info: dict[str, Any] = {"device": device}

    def _open(self) -> None:
        import cv2

        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            raise DeviceConnectionError(
                f"cannot open V4L2 camera {self.device!r} (no such device, busy, or no "
                "permission: check `v4l2-ctl --list-devices` and the video group)"
            )
        self._cap = cap
        self._info.update(width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))

    async def open(self) -> None:
        if self._cap is None:
            await asyncio.to_thread(self._open)

    def _configure(self, settings: dict[str, Any]) -> None:
        import cv2

        cap = self._cap
        ignored = []
        if settings.get("width") and settings.get("height"):
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, int(settings["width"]))
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, int(settings["height"]))
            w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            if (w, h) != (int(settings["width"]), int(settings["height"])):
                raise DeviceError(
                    f"camera {self.device!r} refused {settings['width']}x{settings['height']}; it gives {w}x{h}"
                )
            self._info.update(width=w, height=h)
        if settings.get("exposure_us") is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
            if not cap.set(cv2.CAP_PROP_EXPOSURE, float(settings["exposure_us"]) / 100.0):
                ignored.append("exposure_us")
        for k in ("gain_db", "pixel_format"):
            if settings.get(k) is not None:
                ignored.append(k)
        self._info["ignored_settings"] = ignored

    async def configure(self, **settings: Any) -> None:
        if self._cap is None:
            raise DeviceError("camera not open")
        await asyncio.to_thread(self._configure, settings)

    def _read(self) -> np.ndarray:
        ok, img = self._cap.read()
        if not ok or img is None:
            raise FrameError(f"V4L2 camera {self.device!r} returned no image")
        return img

    async def grab(self, timeout_s: float | None = None) -> Frame:
        if self._cap is None:
            raise DeviceError("camera not open")
        t = self.default_timeout_s if timeout_s is None else timeout_s
        try:
            img = await asyncio.wait_for(asyncio.to_thread(self._read), t)
        except TimeoutError:
            raise DeviceTimeoutError(f"no frame from V4L2 camera {self.device!r} within {t:.3f} s") from None
        self._index += 1
        return Frame(image=img, index=self._index, timestamp_s=time.monotonic())

    async def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    @property
    def info(self) -> dict[str, Any]:
        return dict(self._info)
