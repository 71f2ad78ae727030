"""Service fixtures: an in-process simulated bench on loopback and the service served by uvicorn on a free
port (real HTTP, real Modbus), driven with httpx."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest

from drivers.sim.bench import SimBench
from drivers.sim.mechanism import AxisConfig
from service.auth import hash_token
from service.main import create_app
from service.settings import Settings

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SMALL = {"n_base": 6, "n_fit": 10, "n_lock": 4, "n_validation": 4, "line_samples": 11}


class TinyRenderer:
    """A fast stand-in for the image-level twin where images do not matter."""

    def render(self, q_true, pose_true):
        img = np.full((48, 64), 40, np.uint8)
        img[0, :4] = np.clip(np.round(np.asarray(q_true) * 100), 0, 255).astype(np.uint8)
        return img


@dataclass
class Service:
    url: str
    app: Any
    settings: Settings
    sim: SimBench
    client: httpx.AsyncClient
    server: Any
    task: asyncio.Task

    async def stop(self) -> None:
        self.server.should_exit = True
        await asyncio.wait_for(self.task, 20)


async def start_service(settings: Settings, sim: SimBench) -> Service:
    import uvicorn

    app = create_app(settings)
    config = uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", lifespan="on")
    server = uvicorn.Server(config)
    task = asyncio.get_running_loop().create_task(server.serve())
    for _ in range(500):
        if server.started:
            break
        if task.done():
            task.result()
        await asyncio.sleep(0.01)
    port = server.servers[0].sockets[0].getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    client = httpx.AsyncClient(base_url=url, timeout=30.0)
    return Service(url, app, settings, sim, client, server, task)


def make_settings(tmp_path, sim: SimBench, **over: Any) -> Settings:
    bench = sim.bench_config(acquisition={"line_rate_hz": 50.0}).model_dump(mode="json", exclude={"source"})
    for k, v in over.pop("bench_overrides", {}).items():
        bench[k] = {**bench.get(k, {}), **v}
    data = dict(
        data_dir=tmp_path / "data",
        bench=bench,
        token_hashes=[hash_token(TOKEN)],
        plan_sizes=SMALL,
        extraction_workers=1,
    )
    data.update(over)
    return Settings(**data)


@pytest.fixture
async def sim() -> AsyncIterator[SimBench]:
    b = SimBench(
        port=0,
        renderer=TinyRenderer(),
        seed=1,
        axis_config=AxisConfig(default_speed=10.0, accel=1000.0, home_speed=10.0),
    )
    await b.start()
    try:
        yield b
    finally:
        await b.stop()


@pytest.fixture
async def service(tmp_path, sim) -> AsyncIterator[Service]:
    svc = await start_service(make_settings(tmp_path, sim), sim)
    try:
        yield svc
    finally:
        await svc.client.aclose()
        await svc.stop()


async def wait_state(
    client: httpx.AsyncClient, run_id: str, states=("done", "failed", "aborted", "interrupted"), timeout: float = 120.0
) -> dict:
    """Follow the run's Server-Sent Events until it ends; return the run."""
    async with asyncio.timeout(timeout):
        while True:
            r = await client.get(f"/api/v1/runs/{run_id}")
            run = r.json()
            if run["state"] in states:
                return run
            async with client.stream("GET", f"/api/v1/runs/{run_id}/events") as resp:
                async for line in resp.aiter_lines():
                    if (
                        line.startswith("data: ")
                        and json.loads(line[6:]).get("type") == "state"
                        and json.loads(line[6:])["data"]["state"] in states
                    ):
                        break
            await asyncio.sleep(0.01)


async def read_events(client: httpx.AsyncClient, run_id: str) -> list[dict]:
    out = []
    async with client.stream("GET", f"/api/v1/runs/{run_id}/events", params={"follow": "false"}) as resp:
        async for line in resp.aiter_lines():
            if line.startswith("data: "):
                out.append(json.loads(line[6:]))
    return out


@pytest.fixture(scope="session")
def postgres_url():
    """A throwaway PostgreSQL cluster's URL (tests/service/pgcluster.py); skips, saying why, when none can start."""
    from tests.service.pgcluster import ClusterUnavailableError, temporary_cluster

    pytest.importorskip("psycopg", reason="psycopg is not installed (pip install -e '.[test]')")
    try:
        with temporary_cluster() as url:
            yield url
    except ClusterUnavailableError as exc:
        pytest.skip(str(exc))


def empty_database_url(request, tmp_path, name: str) -> str:
    """An empty database for ``request.param`` ("sqlite": a file ``name`` in tmp_path; "postgres": the
    throwaway cluster's database with its schema dropped and recreated)."""
    from sqlalchemy import text

    from service.db import Database

    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / name}"
    url = request.getfixturevalue("postgres_url")
    db = Database(url)
    with db.engine.begin() as conn:
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    db.dispose()
    return url
