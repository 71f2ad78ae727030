"""ORM models. Schema changes go through Alembic (``service/migrations``)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import JSON, DateTime, ForeignKey, Index, Integer, String, Text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

from service.timefmt import as_utc


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator):
    """``DateTime(timezone=True)`` that stores UTC and always gives back aware UTC datetimes.

    SQLite has no time zones: SQLAlchemy writes the wall-clock digits and reads naive datetimes back; PostgreSQL's
    ``timestamptz`` comes back in the session's time zone. Bound values are converted to UTC first (naive ones are
    taken as UTC), results are made aware UTC: the API and the events write them with ``Z``.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect) -> datetime | None:
        if value is None:
            return None
        value = as_utc(value)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect) -> datetime | None:
        return None if value is None else as_utc(value)


class Base(DeclarativeBase):
    pass


class Run(Base):
    __tablename__ = "runs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    state: Mapped[str] = mapped_column(String(16), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    #: the bench the run's data and results belong to (acquisition: the service's bench; offline: as requested)
    bench: Mapped[str | None] = mapped_column(String(64), index=True)
    #: the service that executes the run, named by its bench (several services can share one database)
    service: Mapped[str | None] = mapped_column(String(64), index=True)
    note: Mapped[str] = mapped_column(Text, default="")
    plan_name: Mapped[str | None] = mapped_column(String(64))
    plan: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    methods: Mapped[list[str]] = mapped_column(JSON, default=list)
    source_dataset: Mapped[str | None] = mapped_column(String(32))
    dataset_dir: Mapped[str] = mapped_column(Text)  # relative to the data directory
    phase: Mapped[str] = mapped_column(String(32), default="")
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    error: Mapped[str | None] = mapped_column(Text)
    timings: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    extraction: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    #: the plan's prediction before motion (``service.design.run_prediction``): predicted std per method and
    #: combination (m), motion time; None until computed (offline runs: never)
    prediction: Mapped[dict[str, Any] | None] = mapped_column(JSON)


class Event(Base):
    __tablename__ = "events"
    __table_args__ = (Index("ix_events_run_seq", "run_id", "seq"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    seq: Mapped[int] = mapped_column(Integer)
    t: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    type: Mapped[str] = mapped_column(String(32))
    data: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)


class DatasetRecord(Base):
    __tablename__ = "datasets"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    name: Mapped[str] = mapped_column(String(255), default="")
    path: Mapped[str] = mapped_column(Text)  # relative to the data directory
    frames: Mapped[int] = mapped_column(Integer, default=0)
    size_bytes: Mapped[int] = mapped_column(Integer, default=0)


class Calibration(Base):
    __tablename__ = "calibrations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    applied_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)
    bench: Mapped[str] = mapped_column(String(64), index=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id"))
    method: Mapped[str] = mapped_column(String(32))
    software_version: Mapped[str] = mapped_column(String(32))
    payload: Mapped[dict[str, Any]] = mapped_column(JSON)


class Token(Base):
    """A bearer token: only its sha256 is stored, with the first characters of the token to recognise it."""

    __tablename__ = "tokens"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(128), default="")
    sha256: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    #: the token's first characters ("i4c_" and 4 of its 43 random ones), shown by ``i4cal token list``
    prefix: Mapped[str | None] = mapped_column(String(16))
    #: refused from this time on (None: never expires)
    expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    #: refused from this time on (``i4cal token revoke``)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    #: last accepted request (updated at most once a minute)
    last_used_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class Check(Base):
    """A check of a bench's calibration in force (``POST /api/v1/checks``, docs/check.md)."""

    __tablename__ = "checks"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    #: running, done (a verdict: ``result``), failed (``error``)
    state: Mapped[str] = mapped_column(String(16), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    bench: Mapped[str | None] = mapped_column(String(64), index=True)
    service: Mapped[str | None] = mapped_column(String(64), index=True)
    #: holds, drifted, inconclusive (None until done)
    verdict: Mapped[str | None] = mapped_column(String(16), index=True)
    #: the applied calibration tested (None: a document given in the request)
    calibration_id: Mapped[int | None] = mapped_column(Integer)
    #: the run that calibration descends from (an applied update's row names it too)
    calibration_run_id: Mapped[str | None] = mapped_column(String(32))
    in_force: Mapped[dict[str, Any]] = mapped_column(JSON)
    plan: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    dataset_dir: Mapped[str] = mapped_column(Text)  # relative to the data directory
    #: the check's document (``i4cal.check/1``)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    #: the proposed update's ``i4cal.calibration/1`` document (None: none proposed)
    update: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    #: the calibration row made of the update (``POST /api/v1/checks/{id}/apply``)
    applied_calibration_id: Mapped[int | None] = mapped_column(Integer)
    error: Mapped[str | None] = mapped_column(Text)
