"""Process-wide counters of the device drivers (Modbus requests, retries, timeouts, ...), read by the service's
``GET /metrics`` (:mod:`service.metrics`). Plain Python, no dependency: the drivers count, the service exports.

A driver counts with :func:`inc` (``inc("modbus_retries")``), or keeps its per-instance ``stats`` dict as a
:class:`CountingStats`, whose increments are also added here under ``<prefix>_<key>``:

>>> stats = CountingStats("modbus", {"requests": 0, "retries": 0})
>>> stats["retries"] += 1  # stats["retries"] == 1, and counter "modbus_retries" grew by 1

Counter names: lower case with underscores, without the ``_total`` suffix (the exporter adds it). Counts only grow.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import Any

_lock = threading.Lock()
_counts: dict[str, float] = {}


def inc(name: str, amount: float = 1.0) -> None:
    """Add ``amount`` (>= 0) to counter ``name``."""
    if amount < 0:
        raise ValueError(f"counter {name}: a count only grows (got {amount})")
    with _lock:
        _counts[name] = _counts.get(name, 0.0) + amount


def snapshot() -> dict[str, float]:
    """Every counter's value now."""
    with _lock:
        return dict(_counts)


class CountingStats(dict):
    """A driver's ``stats`` dict whose increments also go to the process-wide counters as ``<prefix>_<key>``."""

    def __init__(self, prefix: str, initial: Mapping[str, Any] | None = None) -> None:
        super().__init__(initial or {})
        self.prefix = prefix

    def __setitem__(self, key: str, value: Any) -> None:
        delta = value - self.get(key, 0)
        super().__setitem__(key, value)
        if delta > 0:
            inc(f"{self.prefix}_{key}", delta)


__all__ = ["CountingStats", "inc", "snapshot"]
