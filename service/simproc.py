"""The service's simulated bench (``sim_bench = true``) in its own process, as real devices would be.

In the service's process, the simulated camera's rendering (the image-level twin) competed with the requests for
the GIL and delayed status and health by tens of ms while a run acquired. In a child process it talks to the
service only through its Modbus controller and camera endpoint on loopback, like hardware.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
from typing import Any

from calib.errors import I4calError

_CTX = multiprocessing.get_context("forkserver")


def _sim_main(conn: Any, port: int, fast_renderer: bool, overrides: dict[str, Any]) -> None:
    """Child: start a :class:`drivers.sim.bench.SimBench`, send its configuration, serve until told to stop."""

    async def run() -> None:
        from drivers.sim.bench import FallbackRenderer, SimBench

        sim = await SimBench(port=port, renderer=FallbackRenderer() if fast_renderer else None).start()
        try:
            cfg = sim.bench_config(**overrides).model_dump(mode="json", exclude={"source"})
            st = getattr(sim.renderer, "settings", None)
            camera = None
            if st is not None and hasattr(st, "camera"):
                cam = st.camera()
                camera = {"K": cam.K.tolist(), "dist": cam.dist.tolist()}
            conn.send({"config": cfg, "camera": camera, "uris": sim.uris()})
            # until the service says stop, or goes away (EOF)
            with contextlib.suppress(EOFError, OSError):
                await asyncio.get_running_loop().run_in_executor(None, conn.recv)
        finally:
            await sim.stop()

    try:
        asyncio.run(run())
    except BaseException as exc:  # reported to the service, which refuses to start without its bench
        with contextlib.suppress(OSError):
            conn.send({"error": f"{type(exc).__name__}: {exc}"})
        raise


class SimBenchProcess:
    """A simulated bench running in a child process.

    Attributes
    ----------
    config : dict
        Its :class:`drivers.acquisition.config.BenchConfig` as JSON (device URIs on loopback, fast simulated speeds).
    camera : dict or None
        ``{"K", "dist"}`` of the rendered camera (None with the fallback renderer).
    uris : dict
    """

    def __init__(self, port: int = 0, fast_renderer: bool = False, **overrides: Any) -> None:
        self._conn, child = _CTX.Pipe()
        self._child = child
        self.process = _CTX.Process(
            target=_sim_main, args=(child, port, fast_renderer, overrides), name="i4cal-sim-bench", daemon=True
        )
        self.config: dict[str, Any] = {}
        self.camera: dict[str, Any] | None = None
        self.uris: dict[str, str] = {}

    def _start_blocking(self, timeout_s: float) -> None:
        from service.jobs import warm_up

        warm_up()
        self.process.start()
        self._child.close()
        if not self._conn.poll(timeout_s):
            self.process.kill()
            raise I4calError(f"the simulated bench did not start within {timeout_s:.0f} s")
        try:
            msg = self._conn.recv()
        except EOFError:
            raise I4calError(f"the simulated bench exited (code {self.process.exitcode})") from None
        if "error" in msg:
            raise I4calError(f"the simulated bench failed to start: {msg['error']}")
        self.config, self.camera, self.uris = msg["config"], msg["camera"], msg["uris"]

    async def start(self, timeout_s: float = 60.0) -> SimBenchProcess:
        await asyncio.to_thread(self._start_blocking, timeout_s)
        return self

    def _stop_blocking(self) -> None:
        with contextlib.suppress(OSError):
            self._conn.send("stop")
        self.process.join(10)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5)
        self._conn.close()

    async def stop(self) -> None:
        if self.process.pid is not None:
            await asyncio.to_thread(self._stop_blocking)
