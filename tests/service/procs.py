"""The service as a real process (``python -m service serve``) against a simulated bench of the test's process: for
tests that kill it with SIGKILL and start it again on the same data directory."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx

from service.auth import hash_token
from tests.service.conftest import TOKEN


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(path: Path, sim: Any, data_dir: Path, port: int, *, plan_sizes: dict[str, int], **extra: Any) -> Path:
    """A service TOML driving ``sim`` (its bench configuration; ``actuators``, ``camera`` overrides in ``extra``)."""
    bench = sim.bench_config(acquisition={"line_rate_hz": 50.0}).model_dump(mode="json", exclude={"source"})
    bench["actuators"].update(extra.pop("actuators", {}))
    bench["camera"].update(extra.pop("camera", {}))
    lines = [f"data_dir = {json.dumps(str(data_dir))}", f"port = {port}", f'token_hashes = ["{hash_token(TOKEN)}"]']
    lines += [f"{k} = {json.dumps(str(v) if isinstance(v, Path) else v)}" for k, v in extra.items()]
    lines += ["[plan_sizes]", *(f"{k} = {v}" for k, v in plan_sizes.items())]
    lines += ["[bench]", f"name = {json.dumps(bench['name'])}"]
    for sec in ("actuators", "camera", "operator", "acquisition"):
        lines.append(f"[bench.{sec}]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in bench[sec].items() if v is not None and not isinstance(v, dict)]
    path.write_text("\n".join(lines) + "\n")
    return path


class ServiceProcess:
    """``python -m service serve --config CONFIG``, optionally with crash points (``I4CAL_CRASH_AT``)."""

    def __init__(self, config: Path, port: int) -> None:
        self.config, self.url = config, f"http://127.0.0.1:{port}"
        self.proc: subprocess.Popen | None = None

    async def start(self, crash_at: str = "") -> ServiceProcess:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "I4CAL_CRASH_AT": crash_at}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service", "serve", "--config", str(self.config), "--log-level", "warning"], env=env
        )
        async with httpx.AsyncClient(base_url=self.url) as c:
            for _ in range(600):
                with contextlib.suppress(httpx.TransportError):
                    if (await c.get("/readyz")).status_code == 200:
                        return self
                assert self.proc.poll() is None, "the service exited while starting"
                await asyncio.sleep(0.05)
        raise AssertionError("the service did not start")

    async def wait_exit(self, timeout_s: float = 120.0) -> int:
        """Wait until the process ends (a crash point killed it); its return code (-9 for SIGKILL)."""
        assert self.proc is not None
        async with asyncio.timeout(timeout_s):
            while self.proc.poll() is None:
                await asyncio.sleep(0.05)
        return self.proc.returncode

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
