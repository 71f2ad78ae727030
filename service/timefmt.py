"""Timestamps of the service: timezone-aware UTC datetimes, written as ISO 8601 with ``Z``."""

from __future__ import annotations

from datetime import UTC, datetime


def now_utc() -> datetime:
    """The current time, aware, in UTC."""
    return datetime.now(UTC)


def as_utc(dt: datetime) -> datetime:
    """``dt`` as an aware UTC datetime; a naive one is taken as UTC (the service stores UTC only)."""
    return dt.replace(tzinfo=UTC) if dt.tzinfo is None else dt.astimezone(UTC)


def iso_utc(dt: datetime) -> str:
    """ISO 8601 in UTC ending with ``Z``, e.g. ``2026-11-23T15:20:41.123456Z`` (what the API's JSON and the
    Server-Sent Events carry; a naive ``dt`` is taken as UTC)."""
    return as_utc(dt).isoformat().replace("+00:00", "Z")
