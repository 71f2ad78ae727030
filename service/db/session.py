"""Engine, sessions and migrations (Alembic, run at start-up)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import create_engine, event
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from calib.errors import InputError

MIGRATIONS = Path(__file__).resolve().parent.parent / "migrations"

#: SQLite's ``synchronous`` in WAL mode. FULL: every commit (a run's state change, an applied calibration, an event
#: batch) is on disk when it returns, a power cut loses none (NORMAL could lose the last commits). Cost measured on
#: this machine's ext4 disk: docs/service.md, Persistence.
SQLITE_SYNCHRONOUS = "FULL"


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute(f"PRAGMA synchronous={SQLITE_SYNCHRONOUS}")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=5000")
    cur.close()


def _disk_full_failpoint(db_file: str):
    """The disk-full failpoint's database seam (:mod:`service.failpoints`, tests only): while the failpoint covers the
    database file, a statement that writes fails as SQLite's does on a full disk (``SQLITE_FULL``)."""
    import sqlite3

    from service import failpoints

    def before_cursor_execute(conn, cursor, statement, parameters, context, executemany) -> None:
        verb = statement.lstrip().split(None, 1)[0].upper() if statement.strip() else ""
        if verb in ("INSERT", "UPDATE", "DELETE", "REPLACE") and failpoints.is_full(db_file):
            raise sqlite3.OperationalError("database or disk is full")

    return before_cursor_execute


class Database:
    """One engine + session factory; ``upgrade()`` brings the schema to Alembic's head."""

    def __init__(self, url: str) -> None:
        self.url = url
        kw: dict = {}
        if url.startswith("sqlite"):
            kw["connect_args"] = {"check_same_thread": False}
        try:
            self.engine: Engine = create_engine(url, future=True, pool_pre_ping=True, **kw)
        except ModuleNotFoundError as exc:  # the URL's driver is not installed
            raise InputError(
                f"the database driver {exc.name!r} is not installed (PostgreSQL: pip install 'i4cal[postgres]')",
                field="database_url",
            ) from None
        if url.startswith("sqlite"):
            event.listen(self.engine, "connect", _sqlite_pragmas)
            db_file = self.engine.url.database
            if os.environ.get("I4CAL_DISK_FULL") and db_file:
                event.listen(self.engine, "before_cursor_execute", _disk_full_failpoint(db_file))
        self.sessions = sessionmaker(self.engine, expire_on_commit=False)

    def upgrade(self) -> None:
        from alembic import command
        from alembic.config import Config

        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        cfg.set_main_option("sqlalchemy.url", self.url.replace("%", "%%"))
        with self.engine.begin() as conn:
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, "head")

    @contextmanager
    def session(self) -> Iterator[Session]:
        with self.sessions() as s, s.begin():
            yield s

    def dispose(self) -> None:
        self.engine.dispose()
