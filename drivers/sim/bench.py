"""The simulated bench: a Modbus controller and a camera frame server sharing one true mechanism.

In process (tests, demos)::

    async with SimBench(port=0) as bench:          # free ports on 127.0.0.1
        bench.actuators_uri   # "modbus+tcp://127.0.0.1:P"
        bench.camera_uri      # "sim://127.0.0.1:F"
        bench.operator_uri    # "sim://127.0.0.1:F"

As a process: ``i4cal sim-bench [--port N]`` (Modbus TCP on N, RTU-over-TCP on N+1, frames on N+2).

Frame endpoint (loopback TCP, one request per line, any number per connection):

* ``GRAB\\n`` -> ``OK {json}\\n`` + payload, where json = ``{"height", "width", "channels", "dtype",
  "nbytes", "crc32", "seq", "q_true", "pose_true", "t"}`` and the payload is the raw image (C order);
  or ``ERR message\\n``.
* ``LINE {"start_pose", "end_pose", "samples", "rate_hz"}\\n`` -> ``OK {}\\n``: the simulated operator
  starts guiding the free mechanism along the truly straight segment; ``ENDLINE\\n`` -> ``OK {}\\n``.
* ``INFO\\n`` -> ``OK {"width", "height", "renderer"}\\n``.
* ``BOARD {"centre", "fill", "tilt_deg", ...}\\n`` -> ``OK {"camera_from_board"}\\n``: the simulated operator holds
  the calibration board up where asked (a :class:`calib.camera.views.BoardPlacement`, :mod:`drivers.sim.hand`);
  until ``ENDBOARD\\n`` every ``GRAB`` shows that board alone (its true pose in the header, ``board_pose_true``).
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import json
import logging
import time
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drivers.devices.registermap import DEFAULT_MAP, RegisterMap
from drivers.sim.controller import SimController
from drivers.sim.mechanism import AxisConfig, Mechanism
from drivers.sim.twin import BenchGeometry

log = logging.getLogger(__name__)


class FallbackRenderer:
    """Used when :mod:`drivers.sim.render` is not available: a grey image with the true joint values."""

    def __init__(self, geometry: BenchGeometry | None = None, width: int = 1024, height: int = 768) -> None:
        self.geometry = geometry
        self.width, self.height = width, height

    def render(self, q_true: np.ndarray, pose_true: np.ndarray) -> np.ndarray:
        import cv2

        img = np.full((self.height, self.width), 64, np.uint8)
        for k, v in enumerate(q_true):
            cv2.putText(img, f"q{k + 1}={v * 1e3:9.3f}", (40, 80 + 60 * k), cv2.FONT_HERSHEY_SIMPLEX, 1.5, 255, 2)
        x = int(np.clip((pose_true[0] - 0.5) / 1.0 * self.width, 0, self.width - 1))
        cv2.circle(img, (x, self.height // 2 + 100), 20, 200, -1)
        return img


def default_renderer(geometry: BenchGeometry, seed: int = 0) -> Any:
    """The image-level twin's renderer when importable, else :class:`FallbackRenderer`."""
    try:
        from drivers.sim.render import BenchRenderer
    except Exception as exc:  # not there yet, or broken: the bench still runs
        log.warning("drivers.sim.render unavailable (%s); using the fallback renderer", exc)
        return FallbackRenderer(geometry)
    return BenchRenderer(geometry, seed=seed)


@dataclass
class CameraFaults:
    timeouts: int = 0  # ignore this many GRAB requests (the client times out)
    corrupt: int = 0  # corrupt this many frames (payload no longer matches its CRC)
    render_errors: int = 0
    #: the scene's faults (drivers.acquisition.suspenders): after ``scene_after`` more frames served as they are, this
    #: many
    #: frames come dark (the light switched off: 5% of the brightness) or occluded (a person in the view: the
    #: image's centre covered, the board unseen)
    dark: int = 0
    occluded: int = 0
    scene_after: int = 0

    def scene(self, img: np.ndarray) -> np.ndarray:
        """``img`` as the scene's faults show it (one frame served: the counters move on)."""
        if not (self.dark or self.occluded):
            return img
        if self.scene_after > 0:
            self.scene_after -= 1
            return img
        if self.dark > 0:
            self.dark -= 1
            img = (img.astype(np.float32) * 0.05).astype(img.dtype)
        elif self.occluded > 0:
            self.occluded -= 1
            img = img.copy()
            h, w = img.shape[:2]
            img[h // 8 : h - h // 8, w // 8 : w - w // 8] = np.median(img)
        return img


class FrameServer:
    """Serves rendered frames of the mechanism's TRUE state (actual axis positions -> truth DKM).

    A renderer whose ``render`` takes an ``rng`` (the image-level twin's) gets one seeded by ``seed`` and
    the true joint values: a frame's sensor noise depends on what it shows, not on how many frames were
    rendered before it (a grab retried after a timeout renders the same image; runs are reproducible).
    """

    def __init__(self, mechanism: Mechanism, renderer: Any, seed: int = 0) -> None:
        self.mechanism = mechanism
        self.renderer = renderer
        self.seed = int(seed)
        try:
            self._takes_rng = "rng" in inspect.signature(renderer.render).parameters
        except (TypeError, ValueError, AttributeError):
            self._takes_rng = False
        self.faults = CameraFaults()
        self.seq = 0
        #: the hand-held board's true pose while the simulated operator holds it up (BOARD ... ENDBOARD)
        self.held_board: Any = None
        self._boards = 0
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._handle, host, port)
        return self._server.sockets[0].getsockname()[:2]

    async def close(self) -> None:
        for w in list(self._writers):
            with contextlib.suppress(Exception):
                w.transport.abort()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)

    def render_now(self) -> tuple[np.ndarray, dict[str, Any]]:
        if self.held_board is not None and hasattr(self.renderer, "render_board_view"):
            pose = self.held_board
            rng = np.random.default_rng([self.seed, 5, self._boards, self.seq])
            img = np.ascontiguousarray(self.renderer.render_board_view(pose, rng))
            self.seq += 1
            return img, {"seq": self.seq, "board_pose_true": pose.to_dict(), "t": time.monotonic()}
        q = self.mechanism.q_true()
        self.mechanism.frame_taken()
        pose = self.mechanism.pose_true(q)
        if self._takes_rng:
            key = np.asarray(q, dtype=np.float64).view(np.uint32).tolist()
            img = self.renderer.render(q, pose, rng=np.random.default_rng([self.seed, 3, *key]))
        else:
            img = self.renderer.render(q, pose)
        img = np.ascontiguousarray(img)
        self.seq += 1
        return img, {"seq": self.seq, "q_true": q.tolist(), "pose_true": pose.tolist(), "t": time.monotonic()}

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            while line := await reader.readline():
                cmd, _, arg = line.decode(errors="replace").strip().partition(" ")
                try:
                    if cmd == "GRAB":
                        if self.faults.timeouts > 0:
                            self.faults.timeouts -= 1
                            continue  # never answer this one
                        if self.faults.render_errors > 0:
                            self.faults.render_errors -= 1
                            raise RuntimeError("sensor readout error (injected)")
                        img, meta = await asyncio.to_thread(self.render_now)
                        img = np.ascontiguousarray(self.faults.scene(img))
                        payload = img.tobytes()
                        hdr = {
                            "height": img.shape[0],
                            "width": img.shape[1],
                            "channels": 1 if img.ndim == 2 else img.shape[2],
                            "dtype": str(img.dtype),
                            "nbytes": len(payload),
                            "crc32": zlib.crc32(payload),
                            **meta,
                        }
                        if self.faults.corrupt > 0:
                            self.faults.corrupt -= 1
                            b = bytearray(payload)
                            b[len(b) // 3 : len(b) // 3 + 4096] = bytes(4096)[: len(b) - len(b) // 3]
                            b[len(b) // 2] ^= 0xFF
                            payload = bytes(b)
                        writer.write(b"OK " + json.dumps(hdr).encode() + b"\n" + payload)
                    elif cmd == "LINE":
                        a = json.loads(arg)
                        self.mechanism.begin_line(
                            a["start_pose"], a["end_pose"], int(a["samples"]), float(a["rate_hz"])
                        )
                        writer.write(b"OK {}\n")
                    elif cmd == "ENDLINE":
                        self.mechanism.end_line()
                        writer.write(b"OK {}\n")
                    elif cmd == "BOARD":
                        from drivers.sim.hand import held_board_pose

                        self._boards += 1
                        rng = np.random.default_rng([self.seed, 4, self._boards])
                        self.held_board = held_board_pose(json.loads(arg or "{}"), self.renderer, rng)
                        reply = {"camera_from_board": self.held_board.to_dict()}
                        writer.write(b"OK " + json.dumps(reply).encode() + b"\n")
                    elif cmd == "ENDBOARD":
                        self.held_board = None
                        writer.write(b"OK {}\n")
                    elif cmd == "INFO":
                        r = self.renderer
                        writer.write(b"OK " + json.dumps({"renderer": type(r).__name__}).encode() + b"\n")
                    else:
                        writer.write(f"ERR unknown command {cmd!r}\n".encode())
                except Exception as exc:
                    writer.write(f"ERR {type(exc).__name__}: {exc}".replace("\n", " ").encode() + b"\n")
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            self._writers.discard(writer)
            with contextlib.suppress(Exception):
                writer.close()


class SimBench:
    """Mechanism + Modbus controller (TCP, and RTU over TCP) + frame server, all on 127.0.0.1.

    ``port=0`` picks free ports; otherwise Modbus TCP on ``port``, RTU-over-TCP on ``port + 1`` and the
    frame endpoint on ``port + 2``.
    """

    def __init__(
        self,
        *,
        port: int = 0,
        geometry: BenchGeometry | None = None,
        axis_config: AxisConfig | None = None,
        regmap: RegisterMap = DEFAULT_MAP,
        renderer: Any = None,
        seed: int = 0,
        rtu: bool = True,
        initial_q: Any = None,
        watchdog_s: float = 0.5,
        drift_m: Mapping[str, float] | None = None,
    ) -> None:
        self._undrifted = geometry or BenchGeometry()
        self.geometry = drifted(self._undrifted, drift_m or {})
        if initial_q is None:
            from calib.formats.plan import Workspace
            from calib.model.kinematics import ikm

            initial_q = ikm(self.geometry.truth, Workspace().centre())
        self.mechanism = Mechanism(self.geometry, axis_config or fast_axis_config(), initial_q=initial_q, seed=seed)
        self.controller = SimController(self.mechanism, regmap, watchdog_s=watchdog_s)
        self.renderer = renderer if renderer is not None else default_renderer(self.geometry, seed)
        self.frames = FrameServer(self.mechanism, self.renderer, seed)
        self.port = port
        self.rtu = rtu
        self.tcp_address: tuple[str, int] | None = None
        self.rtu_url: str | None = None
        self.frame_address: tuple[str, int] | None = None

    def set_drift(self, drift_m: Mapping[str, float]) -> None:
        """Move the true geometry by ``drift_m`` from the bench's own (:func:`drifted`; ``{}``: back to it) while
        the bench serves: what a crash or a warm afternoon does between two checks. Takes effect at the next frame
        and the next move."""
        self.geometry = drifted(self._undrifted, drift_m)
        self.mechanism.geometry = self.geometry
        if hasattr(self.renderer, "geometry"):
            self.renderer.geometry = self.geometry

    async def start(self) -> SimBench:
        p = self.port
        self.tcp_address = await self.controller.serve_tcp("127.0.0.1", p)
        if self.rtu:
            self.rtu_url = await self.controller.serve_rtu(f"socket://127.0.0.1:{p + 1}" if p else None)
        self.frame_address = await self.frames.start("127.0.0.1", p + 2 if p else 0)
        return self

    async def stop(self) -> None:
        await self.frames.close()
        await self.controller.shutdown()

    async def __aenter__(self) -> SimBench:
        return await self.start()

    async def __aexit__(self, *exc: Any) -> None:
        await self.stop()

    # -- URIs ---------------------------------------------------------------------------------------
    @property
    def actuators_uri(self) -> str:
        assert self.tcp_address is not None, "the bench is not started"
        h, p = self.tcp_address
        return f"modbus+tcp://{h}:{p}"

    @property
    def actuators_rtu_uri(self) -> str | None:
        if not self.rtu_url:
            return None
        return "modbus+rtu+tcp://" + self.rtu_url.removeprefix("socket://")

    @property
    def camera_uri(self) -> str:
        assert self.frame_address is not None, "the bench is not started"
        h, p = self.frame_address
        return f"sim://{h}:{p}"

    @property
    def operator_uri(self) -> str:
        return self.camera_uri

    def uris(self) -> dict[str, str]:
        out = {"actuators": self.actuators_uri, "camera": self.camera_uri, "operator": self.operator_uri}
        if self.actuators_rtu_uri:
            out["actuators_rtu"] = self.actuators_rtu_uri
        return out

    def bench_config(self, **overrides: Any):
        """A :class:`drivers.acquisition.config.BenchConfig` pointing at this bench, with fast sim speeds."""
        from drivers.acquisition.config import BenchConfig

        data: dict[str, Any] = {
            "actuators": {
                "uri": self.actuators_uri,
                "speed_m_s": 10.0,
                "accel_m_s2": 1000.0,
                "timeout_s": 0.5,
                "poll_s": 0.001,
            },
            "camera": {"uri": self.camera_uri},
            "operator": {"uri": self.operator_uri},
        }
        for k, v in overrides.items():
            if isinstance(v, dict) and isinstance(data.get(k), dict):
                data[k] = {**data[k], **v}
            else:
                data[k] = v
        return BenchConfig.model_validate(data)


#: the seven parameters a drift may move (docs/model.md)
DRIFT_PARAMETERS = ("H", "q02", "q03", "q04", "S", "D", "L")


def drifted(geometry: BenchGeometry, drift_m: Mapping[str, float]) -> BenchGeometry:
    """``geometry`` whose true parameters moved by ``drift_m`` (parameter name -> change, metres): what a week of
    production, a crash or a re-homing does to a real bench's geometry, for the check to catch.

    Raises
    ------
    ValueError
        A name that is not one of :data:`DRIFT_PARAMETERS`, or a change that is not finite.
    """
    if not drift_m:
        return geometry
    bad = [k for k in drift_m if k not in DRIFT_PARAMETERS]
    if bad:
        raise ValueError(f"unknown parameter {', '.join(bad)}: a drift moves {', '.join(DRIFT_PARAMETERS)}")
    if not all(np.isfinite(float(v)) for v in drift_m.values()):
        raise ValueError("a drift must be a finite length")
    truth = geometry.truth
    moved = replace(truth, **{k: getattr(truth, k) + float(v) for k, v in drift_m.items()})
    return replace(geometry, truth=moved)


def fast_axis_config() -> AxisConfig:
    """Sim speeds high enough that a full plan acquires in a few seconds."""
    return AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0)


async def serve_forever(
    port: int = 5020,
    *,
    seed: int = 0,
    watchdog_s: float = 0.5,
    print_fn=print,
    on_start=None,
    drift_m: Mapping[str, float] | None = None,
) -> None:
    """Run a :class:`SimBench` until cancelled (the body of ``i4cal sim-bench``); ``watchdog_s``: the
    controller's communication watchdog (s, 0 = off); ``on_start(bench)``: called once it serves, before its URIs
    are printed; ``drift_m``: the true geometry's drift (:func:`drifted`)."""
    bench = SimBench(port=port, axis_config=fast_axis_config(), seed=seed, watchdog_s=watchdog_s, drift_m=drift_m)
    await bench.start()
    try:
        if on_start is not None:
            on_start(bench)
        for k, v in bench.uris().items():
            print_fn(f"{k} = {v}")
        await asyncio.Event().wait()
    finally:
        await bench.stop()
