"""Alembic on SQLite and on a real PostgreSQL server: the migrations at head match the models, and upgrading a
database written at the first revision keeps its rows (a run left active by a crash is recovered after it)."""

from __future__ import annotations

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.config import Config
from alembic.migration import MigrationContext
from sqlalchemy import text

from service.db import Base, Database
from service.db.session import MIGRATIONS
from service.runs import RunManager
from service.settings import Settings
from tests.service.conftest import empty_database_url


@pytest.fixture(params=["sqlite", "postgres"])
def empty_db(request, tmp_path) -> str:
    return empty_database_url(request, tmp_path, "m.db")


def _upgrade(db: Database, rev: str) -> None:
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.set_main_option("sqlalchemy.url", db.url.replace("%", "%%"))
    with db.engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.upgrade(cfg, rev)


def test_head_matches_the_models(empty_db):
    db = Database(empty_db)
    try:
        db.upgrade()
        with db.engine.connect() as conn:
            assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
    finally:
        db.dispose()


def test_upgrade_from_the_first_revision_keeps_rows(empty_db, tmp_path):
    db = Database(empty_db)
    try:
        _upgrade(db, "0001")
        with db.engine.begin() as conn:
            conn.execute(
                text(
                    "INSERT INTO runs (id, state, created_at, bench, note, methods, dataset_dir, phase, done, total, "
                    "timings) VALUES (:id, 'acquiring', CURRENT_TIMESTAMP, 'bench', '', '[]', 'runs/x/dataset', "
                    "'poses', 3, 10, '{}')"
                ),
                {"id": "a" * 32},
            )
        db.upgrade()
        with db.engine.connect() as conn:
            row = conn.execute(text("SELECT state, done, service FROM runs WHERE id = :id"), {"id": "a" * 32}).one()
        assert tuple(row) == ("acquiring", 3, None)
        # a run of the single-service era belongs to whichever service starts on the database
        m = RunManager(Settings(data_dir=tmp_path / "data", database_url=empty_db, bench_name="bench-1"), db, None)
        assert m.recover() == ["a" * 32]
        assert m.get("a" * 32).state == "interrupted"
    finally:
        db.dispose()
