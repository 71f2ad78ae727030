"""Timestamps are timezone-aware UTC everywhere: the database layer gives back aware UTC
datetimes on SQLite (which has no time zones) and on PostgreSQL (whose timestamptz comes back in the session's zone,
here a server set to New York), the API's JSON and the Server-Sent Events write them with ``Z``."""

from __future__ import annotations

import asyncio
import json
from datetime import UTC, datetime, timedelta, timezone

import pytest
from sqlalchemy import select, text

from service.db import Database
from service.db.models import Event, Run
from service.timefmt import iso_utc
from tests.service.conftest import AUTH, empty_database_url, make_settings, read_events, start_service, wait_state

API = "/api/v1"
ZONE = "America/New_York"


@pytest.fixture(params=["sqlite", "postgres"])
def db_url(request, tmp_path):
    """An empty database; on PostgreSQL, the database's time zone set to New York (not UTC) for the test."""
    url = empty_database_url(request, tmp_path, "t.db")
    if request.param == "sqlite":
        yield url
        return
    db = Database(url)
    with db.engine.begin() as conn:
        name = conn.execute(text("SELECT current_database()")).scalar()
        conn.execute(text(f"ALTER DATABASE \"{name}\" SET timezone TO '{ZONE}'"))
    db.dispose()
    try:
        yield url
    finally:
        db = Database(url)
        with db.engine.begin() as conn:
            conn.execute(text(f'ALTER DATABASE "{name}" RESET timezone'))
        db.dispose()


def test_iso_utc():
    t = datetime(2026, 11, 23, 16, 20, 41, 123456, tzinfo=timezone(timedelta(hours=1)))
    assert iso_utc(t) == "2026-11-23T15:20:41.123456Z"
    assert iso_utc(t.astimezone(UTC).replace(tzinfo=None)) == "2026-11-23T15:20:41.123456Z"


def test_database_gives_back_aware_utc(db_url):
    db = Database(db_url)
    try:
        db.upgrade()
        if db_url.startswith("postgresql"):
            with db.engine.connect() as conn:
                assert conn.execute(text("SHOW timezone")).scalar() == ZONE
        paris = datetime(2026, 11, 23, 16, 20, 41, 123456, tzinfo=timezone(timedelta(hours=1)))
        naive_utc = datetime(2026, 11, 23, 15, 21, 0)
        with db.session() as s:
            s.add(Run(id="a" * 32, state="done", dataset_dir="x", created_at=paris, started_at=naive_utc))
            s.flush()
            s.add(Event(run_id="a" * 32, seq=1, t=paris, type="state", data={}))
        with db.session() as s:
            run = s.get(Run, "a" * 32)
            ev = s.scalars(select(Event)).one()
            for got, want in ((run.created_at, paris), (run.started_at, naive_utc.replace(tzinfo=UTC)), (ev.t, paris)):
                assert got.tzinfo is not None and got.utcoffset() == timedelta(0), got
                assert got == want
            # comparisons in queries see the same instants
            assert s.scalar(select(Run.id).where(Run.created_at < paris + timedelta(seconds=1))) == "a" * 32
            assert s.scalar(select(Run.id).where(Run.created_at > paris)) is None
    finally:
        db.dispose()


async def test_api_and_events_write_utc_with_z(tmp_path, sim, db_url):
    svc = await start_service(make_settings(tmp_path, sim, database_url=db_url), sim)
    c = svc.client
    try:
        r = await c.post(f"{API}/runs", json={"plan": "rotation-sweep", "methods": []}, headers=AUTH)
        assert r.status_code == 202, r.text
        rid = r.json()["id"]
        assert r.json()["created_at"].endswith("Z"), r.json()["created_at"]
        live: list[dict] = []
        async with asyncio.timeout(60), c.stream("GET", f"{API}/runs/{rid}/events") as resp:
            async for line in resp.aiter_lines():
                if line.startswith("data: "):
                    live.append(json.loads(line[6:]))
        assert (await wait_state(c, rid))["state"] == "done"
        run = (await c.get(f"{API}/runs/{rid}")).json()
        for key in ("created_at", "started_at", "finished_at"):
            assert run[key].endswith("Z"), (key, run[key])
        created = datetime.fromisoformat(run["created_at"])
        assert abs(created - datetime.now(UTC)) < timedelta(minutes=5)
        assert all(x["created_at"].endswith("Z") for x in (await c.get(f"{API}/runs")).json())
        past = await read_events(c, rid)
        assert live and past
        for ev in live + past:
            assert ev["t"].endswith("Z"), ev
            assert abs(datetime.fromisoformat(ev["t"]) - created) < timedelta(minutes=5)
        assert [e["t"] for e in past[: len(live)]] == [e["t"] for e in live[: len(past)]]
    finally:
        await c.aclose()
        await svc.stop()
