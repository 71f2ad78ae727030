"""``genicam://?cti=PATH&serial=SN``: GenICam cameras through harvesters 1.4 (a GenTL producer ``.cti``).

The producer comes from the URI's ``cti`` or from ``GENICAM_GENTL64_PATH`` (every ``.cti`` in those
directories). The device is selected by serial number (first device when none is given). Pixel format,
exposure and gain are set when the device has the nodes; a software trigger is used when the device
has one (``TriggerMode``/``TriggerSource``/``TriggerSoftware``), else the next streamed frame is taken.
Incomplete buffers are requeued and fetched again; a buffer is always given back to the producer
(``with ia.fetch(...)``). harvesters is blocking: its calls run in a worker thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import glob
import os
import time
from typing import Any

import numpy as np

from drivers.devices.interfaces import Frame
from drivers.errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, FrameError, MissingExtraError


def find_producers(cti: str | None = None) -> list[str]:
    if cti:
        if not os.path.isfile(cti):
            raise DeviceConnectionError(f"GenTL producer not found: {cti}")
        return [cti]
    out: list[str] = []
    for d in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if d:
            out += sorted(glob.glob(os.path.join(d, "*.cti")))
    if not out:
        raise DeviceConnectionError("no GenTL producer: give ?cti=PATH in the camera URI or set GENICAM_GENTL64_PATH")
    return out


def _to_image(component) -> np.ndarray:
    fmt = str(component.data_format)
    h, w = int(component.height), int(component.width)
    data = np.asarray(component.data)
    n = data.size
    if n == h * w:
        return data.reshape(h, w).copy()
    ch = n // (h * w)
    if ch * h * w != n:
        raise FrameError(f"buffer of {n} values does not fit {w}x{h} ({fmt})")
    img = data.reshape(h, w, ch).copy()
    if fmt.upper().startswith("RGB") and ch >= 3:
        img = img[:, :, 2::-1].copy()  # to OpenCV's BGR; alpha dropped
    return img


class GenICamCamera:
    """:class:`drivers.devices.interfaces.Camera` through harvesters."""

    def __init__(
        self, cti: str | None = None, serial: str | None = None, timeout_s: float = 2.0, incomplete_retries: int = 3
    ) -> None:
        self.cti = cti
        self.serial = serial
        self.default_timeout_s = timeout_s
        self.incomplete_retries = incomplete_retries
        self._h: Any = None  # harvesters.core.Harvester (no type information)
        self._ia: Any = None  # its ImageAcquirer
        self._trigger = False
        self._index = 0
        self._info: dict[str, Any] = {}
        self.stats = {"incomplete": 0, "fetched": 0}

    # -- blocking parts (worker thread) ---------------------------------------------------------------
    def _open(self) -> None:
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise MissingExtraError("harvesters (GenICam)", "genicam") from None
        producers = find_producers(self.cti)
        h = Harvester()
        for p in producers:
            h.add_file(p)
        h.update()
        devices = list(h.device_info_list)
        if not devices:
            h.reset()
            raise DeviceConnectionError(f"no GenICam device found by {', '.join(producers)}")
        if self.serial:
            serials = [str(d.serial_number) for d in devices]
            if self.serial not in serials:
                h.reset()
                raise DeviceConnectionError(
                    f"no GenICam device with serial {self.serial!r}; found {', '.join(serials)}"
                )
            ia = h.create({"serial_number": self.serial})
        else:
            ia = h.create(0)
        self._h, self._ia = h, ia
        info = devices[[str(x.serial_number) for x in devices].index(self.serial)] if self.serial else devices[0]
        self._info = {
            "vendor": str(info.vendor),
            "model": str(info.model),
            "serial": str(info.serial_number),
            "producer": producers[0],
        }
        nm = ia.remote_device.node_map
        self._trigger = self._setup_trigger(nm)
        self._info["software_trigger"] = self._trigger
        self._info["trigger_mode"] = self._get(nm, "TriggerMode")  # read back from the device
        for name in ("Width", "Height", "PixelFormat"):
            v = self._get(nm, name)
            if v is not None:
                self._info[name] = v
        ia.start()

    @staticmethod
    def _get(nm, name: str) -> Any:
        try:
            return getattr(nm, name).value
        except Exception:
            return None

    @staticmethod
    def _set(nm, name: str, value: Any) -> bool:
        try:
            node = getattr(nm, name)
        except AttributeError:
            return False
        try:
            node.value = value
            return True
        except Exception as exc:
            raise DeviceError(f"cannot set {name} = {value!r}: {exc}") from None

    def _setup_trigger(self, nm) -> bool:
        try:
            nm.TriggerMode  # noqa: B018
            nm.TriggerSoftware  # noqa: B018
        except AttributeError:
            return False
        try:
            if hasattr(nm, "TriggerSelector"):
                with contextlib.suppress(Exception):
                    nm.TriggerSelector.value = "FrameStart"
            nm.TriggerMode.value = "On"
            nm.TriggerSource.value = "Software"
            return True
        except Exception:
            return False

    def _configure(self, settings: dict[str, Any]) -> None:
        nm = self._ia.remote_device.node_map
        names = {
            "exposure_us": "ExposureTime",
            "gain_db": "Gain",
            "pixel_format": "PixelFormat",
            "width": "Width",
            "height": "Height",
        }
        ignored = []
        need_restart = any(settings.get(k) is not None for k in ("pixel_format", "width", "height"))
        if need_restart:
            self._ia.stop()
        try:
            for key, value in settings.items():
                if value is None:
                    continue
                if not self._set(nm, names[key], value):
                    if key == "exposure_us" and self._set(nm, "ExposureTimeAbs", value):
                        continue
                    if key == "gain_db" and self._set(nm, "GainRaw", value):
                        continue
                    ignored.append(key)
        finally:
            if need_restart:
                self._ia.start()
        self._info["ignored_settings"] = ignored
        for name in ("Width", "Height", "PixelFormat"):
            v = self._get(nm, name)
            if v is not None:
                self._info[name] = v

    def _grab(self, timeout_s: float) -> Frame:
        from genicam.gentl import TimeoutException

        ia = self._ia
        t_end = time.monotonic() + timeout_s
        if self._trigger:
            # drop frames already queued, then trigger one
            while (b := ia.try_fetch(timeout=0.0001)) is not None:
                b.queue()
            ia.remote_device.node_map.TriggerSoftware.execute()
        for _ in range(self.incomplete_retries + 1):
            left = t_end - time.monotonic()
            if left <= 0:
                break
            try:
                with ia.fetch(timeout=left) as buf:
                    self.stats["fetched"] += 1
                    incomplete = False
                    with contextlib.suppress(Exception):
                        incomplete = bool(buf._buffer.is_incomplete)
                    if incomplete or not buf.payload.components:
                        self.stats["incomplete"] += 1
                        continue  # leaving the block requeues the buffer
                    img = _to_image(buf.payload.components[0])
                    try:
                        ts = buf.timestamp_ns * 1e-9
                    except Exception:
                        ts = time.monotonic()
            except TimeoutException:
                break
            self._index += 1
            return Frame(image=img, index=self._index, timestamp_s=ts, meta={})
        raise DeviceTimeoutError(
            f"no complete frame from GenICam camera {self._info.get('serial', '?')} within {timeout_s:.3f} s"
        )

    def _close(self) -> None:
        if self._ia is not None:
            try:
                self._ia.stop()
            finally:
                self._ia.destroy()
                self._ia = None
        if self._h is not None:
            self._h.reset()
            self._h = None

    # -- async interface ----------------------------------------------------------------------------
    async def open(self) -> None:
        if self._ia is None:
            await asyncio.to_thread(self._open)

    async def configure(self, **settings: Any) -> None:
        await asyncio.to_thread(self._configure, settings)

    async def grab(self, timeout_s: float | None = None) -> Frame:
        if self._ia is None:
            raise DeviceError("camera not open")
        return await asyncio.to_thread(self._grab, self.default_timeout_s if timeout_s is None else timeout_s)

    async def close(self) -> None:
        await asyncio.to_thread(self._close)

    @property
    def info(self) -> dict[str, Any]:
        return dict(self._info)
