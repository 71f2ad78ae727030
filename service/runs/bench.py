"""The bench a service drives: its configuration, its devices' states, optionally a simulated bench in its own
process."""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from calib.errors import I4calError, InputError
from service.settings import Settings
from service.timefmt import now_utc as now


@dataclass
class DeviceState:
    name: str
    uri: str
    state: str = "unknown"  # unknown, connected, idle, error
    last_error: str | None = None
    last_seen: datetime | None = None

    def ok(self) -> None:
        self.state, self.last_seen = "connected", now()

    def fail(self, msg: str) -> None:
        self.state, self.last_error = "error", msg


class Bench:
    """The bench this service drives: a configuration, optionally an in-process simulated bench."""

    def __init__(
        self, name: str, config: Any, *, sim: Any = None, camera_spec: dict | None = None, camera_model: Any = None
    ) -> None:
        self.name = name
        self.config = config  # drivers.acquisition.config.BenchConfig
        self.sim = sim
        self.camera_spec = camera_spec or {}
        #: the camera file's model (``camera_file``: intrinsics, lens, image size), which the predictions use in
        #: place of the simulated bench's camera; None without a camera file
        self.camera_model = camera_model
        self.devices = {k: DeviceState(k, getattr(config, k).uri) for k in ("actuators", "camera", "operator")}

    @classmethod
    async def from_settings(cls, settings: Settings) -> Bench | None:
        from drivers.acquisition.config import BenchConfig, load_bench

        camera_spec: dict[str, Any] = {}
        cam = None
        if settings.camera_file:
            from calib.formats.camera import CameraModel

            cam = CameraModel.load(settings.camera_file)
            camera_spec = {"K": cam.K.tolist(), "dist": cam.dist.tolist()}
        if settings.sim_bench:
            from service.simproc import SimBenchProcess

            # its own process, as hardware would be: its rendering does not compete with requests for the GIL
            sim = await SimBenchProcess(
                settings.sim_port,
                settings.sim_fast_renderer,
                name=settings.bench_name or "sim",
                acquisition={"line_rate_hz": 50.0},
                camera={"timeout_s": 10.0},
            ).start()
            cfg = BenchConfig.model_validate(sim.config)
            if sim.camera is not None and not camera_spec:
                camera_spec = sim.camera
            return cls(bench_name(settings, cfg), cfg, sim=sim, camera_spec=camera_spec, camera_model=cam)
        if settings.bench is not None:
            cfg = BenchConfig.model_validate(settings.bench)
        elif settings.bench_file is not None:
            cfg = load_bench(settings.bench_file)
        else:
            return None
        if cam is None:  # the bench file's own camera file ([camera] intrinsics): the predictions' camera too
            known = (
                cfg.camera_intrinsics()
            )  # checked at start-up; every acquisition records it (drivers.acquisition.acquire)
            cam = known.camera if known is not None else None
        return cls(bench_name(settings, cfg), cfg, camera_spec=camera_spec, camera_model=cam)

    async def close(self) -> None:
        if self.sim is not None:
            await self.sim.stop()

    def preload(self) -> None:
        """Import the acquisition and the device backends now (blocking: in a thread at start-up), so that the first
        run does not import them in the event loop."""
        import drivers.acquisition.acquire  # noqa: F401
        from drivers.acquisition.config import open_actuators, open_camera

        with contextlib.suppress(I4calError):
            open_actuators(self.config)  # constructed, not connected: imports the backend's module
        with contextlib.suppress(I4calError):
            open_camera(self.config)

    async def probe(self, timeout_s: float = 3.0) -> None:
        """Connect to each device briefly and record its state (only while no run holds the bench)."""
        from drivers.acquisition.config import open_actuators, open_camera

        act = open_actuators(self.config)
        try:
            await asyncio.wait_for(act.connect(), timeout_s)
            await asyncio.wait_for(act.status(), timeout_s)
            self.devices["actuators"].ok()
        except (I4calError, OSError, TimeoutError) as exc:
            self.devices["actuators"].fail(str(exc) or type(exc).__name__)
        finally:
            with contextlib.suppress(Exception):
                await act.close()
        cam = open_camera(self.config)
        try:
            await asyncio.wait_for(cam.open(), timeout_s)
            self.devices["camera"].ok()
        except (I4calError, OSError, TimeoutError) as exc:
            self.devices["camera"].fail(str(exc) or type(exc).__name__)
        finally:
            with contextlib.suppress(Exception):
                await cam.close()


def bench_name(settings: Settings, cfg: Any) -> str:
    """The bench's name: ``bench_name`` of the settings, else the bench configuration's ``name``.

    Raises
    ------
    InputError
        A name that cannot identify a bench (see :data:`service.settings.BENCH_NAME_PATTERN`).
    """
    import re

    from service.settings import BENCH_NAME_PATTERN

    name = settings.bench_name or str(getattr(cfg, "name", "") or "bench")
    if not re.fullmatch(BENCH_NAME_PATTERN, name):
        raise InputError(
            f"bench name {name!r} must be 1-64 letters, digits, spaces, '.', '_' or '-' "
            "(set bench_name in the service configuration)",
            field="bench_name",
        )
    return name
