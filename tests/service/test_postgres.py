"""The service on a real PostgreSQL server (a throwaway cluster, tests/service/pgcluster.py): Alembic migrations, an
offline run with real images through extraction and the three methods, apply, a restart on the same database, and
an interrupted acquisition resumed.

Skipped, with the reason, when no cluster can be started here (no server binaries: run
deploy/install-test-system-deps.sh; no psycopg: pip install -e '.[test]').
"""

from __future__ import annotations

import asyncio

import pytest
from sqlalchemy import inspect, text

from service.db import Database
from service.settings import Settings, normalize_database_url
from tests.service.conftest import AUTH, make_settings, read_events, start_service, wait_state
from tests.service.held import HELD_GRAB, hold_camera

API = "/api/v1"
METHODS = ["combined", "end-effector", "legs"]


@pytest.fixture
def fresh_db(postgres_url):
    """The cluster's database emptied (no tables, no Alembic version) before the test."""
    db = Database(postgres_url)
    with db.engine.begin() as conn:
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    db.dispose()
    return postgres_url


def test_database_urls_are_normalized_or_refused(tmp_path):
    assert normalize_database_url("postgresql://u:p@db:5432/i4cal") == "postgresql+psycopg://u:p@db:5432/i4cal"
    assert normalize_database_url("postgres://db/i4cal") == "postgresql+psycopg://db/i4cal"
    assert normalize_database_url(" ") is None
    assert Settings(data_dir=tmp_path, database_url="postgresql://db/x").db_url == "postgresql+psycopg://db/x"
    for bad in ("mysql://db/x", "postgresql+psycopg2://db/x", "i4cal.db"):
        with pytest.raises(ValueError, match="unsupported database URL"):
            normalize_database_url(bad)


def test_alembic_migrations_on_postgres(fresh_db):
    from alembic.script import ScriptDirectory

    from service.db.session import MIGRATIONS

    db = Database(fresh_db)
    try:
        db.upgrade()
        db.upgrade()  # idempotent: at head already
        insp = inspect(db.engine)
        tables = set(insp.get_table_names())
        assert {"runs", "events", "datasets", "calibrations", "tokens", "alembic_version"} <= tables
        head = ScriptDirectory(str(MIGRATIONS)).get_current_head()
        with db.engine.connect() as conn:
            assert conn.execute(text("SELECT version_num FROM alembic_version")).scalar() == head
        cols = {c["name"]: c for c in insp.get_columns("runs")}
        assert type(cols["result"]["type"]).__name__ == "JSON"
        assert cols["created_at"]["type"].timezone
    finally:
        db.dispose()


async def test_offline_run_on_postgres_then_restart(tmp_path, sim, fresh_db, rendered_zip):
    settings = make_settings(tmp_path, sim, database_url=fresh_db, extraction_workers=2)
    assert settings.db_url.startswith("postgresql+psycopg://")
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        r = await c.post(f"{API}/datasets", content=rendered_zip, headers={"Content-Type": "application/zip", **AUTH})
        assert r.status_code == 201, r.text
        r = await c.post(f"{API}/runs", json={"dataset": r.json()["id"], "methods": METHODS}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        run = await wait_state(c, rid, timeout=300)
        assert run["state"] == "done", run
        res = (await c.get(f"{API}/runs/{rid}/result")).json()
        assert all(res["methods"][m]["converged"] for m in METHODS)
        evs = await read_events(c, rid)
        assert [e["seq"] for e in evs] == list(range(1, len(evs) + 1))
        assert {"state", "progress", "frames", "fit", "iterations", "extraction"} <= {e["type"] for e in evs}
        r = await c.post(f"{API}/runs/{rid}/apply", headers=AUTH)
        assert r.status_code == 201, r.text
        cur = (await c.get(f"{API}/calibration/current")).json()
        assert cur["run_id"] == rid and cur["combinations"] == res["methods"]["combined"]["parameters"]
        evs = await read_events(c, rid)
        assert evs[-1]["type"] == "applied"
    finally:
        await c.aclose()
        await svc.stop()
    with Database(fresh_db).engine.connect() as conn:  # it really is in PostgreSQL
        assert conn.execute(text("SELECT state FROM runs WHERE id = :i"), {"i": rid}).scalar() == "done"
        assert conn.execute(text("SELECT count(*) FROM events WHERE run_id = :i"), {"i": rid}).scalar() == len(evs)
    svc = await start_service(settings, sim)  # migrations at start-up: already at head
    c = svc.client
    try:
        run = (await c.get(f"{API}/runs/{rid}")).json()
        assert run["state"] == "done" and run["has_result"]
        assert (await c.get(f"{API}/runs/{rid}/result")).json() == res
        assert (await c.get(f"{API}/calibration/current")).json()["id"] == cur["id"]
        assert len(await read_events(c, rid)) == len(evs)
    finally:
        await c.aclose()
        await svc.stop()


async def test_interrupted_acquisition_resumes_on_postgres(tmp_path, sim, fresh_db):
    settings = make_settings(
        tmp_path,
        sim,
        database_url=fresh_db,
        plan_sizes={"n_fit": 30},
        bench_overrides=HELD_GRAB,
    )
    camera = hold_camera(sim)
    camera.hold_at_pose(5)  # the run waits on its fifth pose's frame while the service stops
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        rid = (await c.post(f"{API}/runs", json={"plan": "pose-set", "methods": []}, headers=AUTH)).json()["id"]
        await camera.wait_held()
        async with asyncio.timeout(30):
            while (await c.get(f"{API}/runs/{rid}")).json()["progress"]["done"] < 3:
                await asyncio.sleep(0.02)
    finally:
        await c.aclose()
        await svc.stop()  # a stop mid-run: the run is interrupted, resumable
        camera.release.set()
    svc = await start_service(settings, sim)
    c = svc.client
    try:
        run = (await c.get(f"{API}/runs/{rid}")).json()
        assert run["state"] == "interrupted", run
        kept = len((await c.get(f"{API}/runs/{rid}/frames")).json())
        assert 3 <= kept < 30
        assert (await c.post(f"{API}/runs/{rid}/resume", headers=AUTH)).status_code == 202
        run = await wait_state(c, rid, timeout=120)
        assert run["state"] == "done", run
        assert len((await c.get(f"{API}/runs/{rid}/frames")).json()) == 30
    finally:
        await c.aclose()
        await svc.stop()
