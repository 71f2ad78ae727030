"""``replay://DATASET``: the frames of a recorded dataset (calib.formats.dataset v1), in order."""

from __future__ import annotations

import time
from typing import Any

from calib.formats.dataset import Dataset
from drivers.devices.interfaces import Frame
from drivers.errors import DeviceConnectionError, DeviceTimeoutError


class ReplayCamera:
    """Replays a dataset's images in order; after the last one ``grab`` times out (or loops, ``loop=True``)."""

    def __init__(self, path: str, loop: bool = False) -> None:
        self.path = path
        self.loop = loop
        self._ds: Dataset | None = None
        self._next = 0
        self._indices: list[int] = []

    async def open(self) -> None:
        try:
            self._ds = Dataset.open(self.path)
        except Exception as exc:
            raise DeviceConnectionError(f"cannot replay {self.path}: {exc}") from None
        self._indices = [i for i, f in enumerate(self._ds.frames) if f.image is not None]
        self._next = 0

    async def configure(self, **settings: Any) -> None:
        return None

    async def grab(self, timeout_s: float | None = None) -> Frame:
        if self._ds is None:
            await self.open()
        if self._next >= len(self._indices):
            if not self.loop or not self._indices:
                raise DeviceTimeoutError(f"replay of {self.path}: no more frames ({len(self._indices)} replayed)")
            self._next = 0
        i = self._indices[self._next]
        self._next += 1
        assert self._ds is not None  # opened above
        f = self._ds.frames[i]
        img = self._ds.load_image(i)
        return Frame(
            image=img, index=i, timestamp_s=time.monotonic(), meta={"phase": f.phase, "q": list(f.q), "t": f.t}
        )

    async def close(self) -> None:
        self._ds = None

    @property
    def info(self) -> dict[str, Any]:
        out: dict[str, Any] = {"uri": f"replay://{self.path}", "frames": len(self._indices)}
        if self._ds is not None:
            out.update(width=self._ds.document.camera.width, height=self._ds.document.camera.height)
        return out
