"""``sim://HOST:PORT``: the simulated camera (and operator) of a :class:`drivers.sim.bench.SimBench`.

Frames come from the bench's frame endpoint on loopback (protocol in :mod:`drivers.sim.bench`); they
show the TRUE mechanism at the axes' actual positions. This module never imports the simulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import zlib
from typing import Any

import numpy as np

from drivers.devices.interfaces import Frame
from drivers.errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, FrameError


class _LineClient:
    def __init__(self, host: str, port: int, connect_timeout_s: float = 2.0) -> None:
        self.host, self.port = host, int(port)
        self.connect_timeout_s = connect_timeout_s
        self._r: asyncio.StreamReader | None = None
        self._w: asyncio.StreamWriter | None = None
        self._lock = asyncio.Lock()

    async def _ensure(self) -> None:
        if self._w is None or self._w.is_closing():
            try:
                self._r, self._w = await asyncio.wait_for(
                    asyncio.open_connection(self.host, self.port), self.connect_timeout_s
                )
            except (OSError, TimeoutError) as exc:
                raise DeviceConnectionError(
                    f"cannot reach the simulated bench at {self.host}:{self.port} ({exc or type(exc).__name__})"
                ) from None

    def _drop(self) -> None:
        if self._w is not None:
            with contextlib.suppress(Exception):
                self._w.transport.abort()
        self._r = self._w = None

    async def request(self, line: str, timeout_s: float) -> tuple[dict[str, Any], bytes | None]:
        async with self._lock:
            await self._ensure()
            assert self._r is not None and self._w is not None  # connected by _ensure
            try:
                self._w.write(line.encode() + b"\n")
                await self._w.drain()
                raw = await asyncio.wait_for(self._r.readline(), timeout_s)
                if not raw:
                    raise ConnectionResetError("connection closed")
                status, _, rest = raw.decode(errors="replace").strip().partition(" ")
                if status == "ERR":
                    raise DeviceError(f"simulated bench: {rest}")
                if status != "OK":
                    raise FrameError(f"simulated bench: unexpected reply {raw[:60]!r}")
                hdr = json.loads(rest or "{}")
                payload = None
                if "nbytes" in hdr:
                    payload = await asyncio.wait_for(self._r.readexactly(int(hdr["nbytes"])), timeout_s)
                return hdr, payload
            except TimeoutError:
                self._drop()  # a late reply must not answer the next request
                raise DeviceTimeoutError(
                    f"no reply from the simulated bench at {self.host}:{self.port} within {timeout_s:.3f} s"
                ) from None
            except (ConnectionError, OSError, asyncio.IncompleteReadError) as exc:
                self._drop()
                raise DeviceConnectionError(
                    f"link to the simulated bench at {self.host}:{self.port} lost ({exc or type(exc).__name__})"
                ) from None
            except json.JSONDecodeError as exc:
                self._drop()
                raise FrameError(f"simulated bench: malformed header ({exc})") from None

    def close(self) -> None:
        self._drop()


class SimCamera:
    """:class:`drivers.devices.interfaces.Camera` for ``sim://HOST:PORT``."""

    def __init__(self, host: str = "127.0.0.1", port: int = 5022, timeout_s: float = 2.0) -> None:
        self._client = _LineClient(host, port)
        self.default_timeout_s = timeout_s
        self._info: dict[str, Any] = {"uri": f"sim://{host}:{port}"}
        self._index = 0

    async def open(self) -> None:
        hdr, _ = await self._client.request("INFO", self.default_timeout_s)
        self._info.update(hdr)

    async def configure(self, **settings: Any) -> None:
        self._info["ignored_settings"] = sorted(k for k, v in settings.items() if v is not None)

    async def grab(self, timeout_s: float | None = None) -> Frame:
        t = self.default_timeout_s if timeout_s is None else timeout_s
        hdr, payload = await self._client.request("GRAB", t)
        if payload is None or len(payload) != int(hdr["nbytes"]) or zlib.crc32(payload) != int(hdr["crc32"]):
            raise FrameError(f"corrupt frame from the simulated camera (seq {hdr.get('seq')}): checksum mismatch")
        shape = (int(hdr["height"]), int(hdr["width"])) + (() if int(hdr["channels"]) == 1 else (int(hdr["channels"]),))
        img = np.frombuffer(payload, dtype=np.dtype(hdr["dtype"])).reshape(shape)
        self._index += 1
        meta: dict[str, Any] = {k: hdr[k] for k in ("seq", "q_true", "pose_true") if k in hdr}
        return Frame(image=img, index=self._index, timestamp_s=time.monotonic(), meta=meta)

    async def close(self) -> None:
        self._client.close()

    @property
    def info(self) -> dict[str, Any]:
        return dict(self._info)


class SimOperator:
    """:class:`drivers.devices.interfaces.Operator` for ``sim://HOST:PORT``: the simulated operator guides the line."""

    def __init__(self, host: str = "127.0.0.1", port: int = 5022, timeout_s: float = 2.0) -> None:
        self._client = _LineClient(host, port)
        self.timeout_s = timeout_s

    async def begin_line(self, start_pose, end_pose, samples: int, rate_hz: float) -> None:
        arg = json.dumps(
            {
                "start_pose": list(map(float, start_pose)),
                "end_pose": list(map(float, end_pose)),
                "samples": int(samples),
                "rate_hz": float(rate_hz),
            }
        )
        await self._client.request("LINE " + arg, self.timeout_s)

    async def end_line(self) -> None:
        await self._client.request("ENDLINE", self.timeout_s)

    async def present_board(self, placement) -> None:
        """The simulated operator holds the board where ``placement`` (a
        :class:`calib.camera.views.BoardPlacement`)
        asks, until :meth:`board_done`."""
        await self._client.request("BOARD " + json.dumps(placement.to_dict()), self.timeout_s)

    async def board_done(self) -> None:
        await self._client.request("ENDBOARD", self.timeout_s)

    async def close(self) -> None:
        self._client.close()
