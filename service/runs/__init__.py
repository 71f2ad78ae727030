"""Runs: the bench (:mod:`.bench`), the lifecycle state machine (:mod:`.lifecycle`), events (:mod:`.events`), the run
manager (:mod:`.manager`), the stages acquire -> extract -> calibrate (:mod:`.stages`) and calibrations
(:mod:`.calibrations`)."""

from .bench import Bench, DeviceState, bench_name
from .events import LIVE_INTERVAL_S, EventBus
from .lifecycle import IllegalTransitionError, RunConflictError, RunEvent, RunNotFoundError, RunState
from .manager import ACTIVE_STATES, STATES, TERMINAL_STATES, ActiveRun, RunManager, new_id, now, plan_units

__all__ = [
    "ACTIVE_STATES",
    "LIVE_INTERVAL_S",
    "STATES",
    "TERMINAL_STATES",
    "ActiveRun",
    "Bench",
    "DeviceState",
    "EventBus",
    "IllegalTransitionError",
    "RunConflictError",
    "RunEvent",
    "RunManager",
    "RunNotFoundError",
    "RunState",
    "bench_name",
    "new_id",
    "now",
    "plan_units",
]
