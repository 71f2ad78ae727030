"""Compatibility: the run machinery moved to :mod:`service.runs` (bench, lifecycle, events, manager, stages,
calibrations). Import from there."""

from .runs import (  # noqa: F401
    ACTIVE_STATES,
    LIVE_INTERVAL_S,
    STATES,
    TERMINAL_STATES,
    ActiveRun,
    Bench,
    DeviceState,
    RunConflictError,
    RunManager,
    RunNotFoundError,
    bench_name,
    new_id,
    now,
    plan_units,
)
