"""The schedule's policy without a bench (cheap): when a check is due (every N hours; once per idle period, a
scheduled check's own hold not counting as activity), and what the action ``record`` stores (the update withheld).
The scheduler on the simulated bench: tests/service/test_check_schedule.py."""

from __future__ import annotations

from service.checks.manager import HOLDER_PREFIX, scheduled
from service.checks.schedule import CheckScheduler
from service.settings import CheckSchedule


class _Checks:
    """Only who holds the bench (what the scheduler asks of the check manager before it starts a check)."""

    def __init__(self) -> None:
        self.holder_now: str | None = None

    def holder(self) -> str | None:
        return self.holder_now


def test_idle_check_once_per_idle_period_its_own_hold_not_activity():
    s = CheckScheduler(_Checks(), CheckSchedule(idle_minutes=1.0), lambda: None)  # type: ignore[arg-type]
    t0 = s.last_busy
    assert s.due(t0 + 59) is None and s.due(t0 + 61) == "idle"
    s.last_started = t0 + 61  # the idle check started
    assert s.due(t0 + 200) is None  # still idle: no second check in the same idle period
    s.last_busy = t0 + 300  # a run held the bench
    assert s.due(t0 + 330) is None and s.due(t0 + 361) == "idle"


async def test_a_run_holding_the_bench_is_activity_and_defers_the_due_check():
    checks = _Checks()
    s = CheckScheduler(checks, CheckSchedule(every_hours=1.0), lambda: None)  # type: ignore[arg-type]
    s.since -= 3601.0  # an hour has passed: due
    checks.holder_now = "run abc"
    assert await s.tick() is None
    assert s.deferred == "run abc" and s.events[-1]["type"] == "deferred"
    assert "run abc holds the bench" in s.events[-1]["message"]
    busy = s.last_busy
    checks.holder_now = HOLDER_PREFIX + "x"  # a check holding the bench: deferred, but not activity
    await s.tick()
    assert s.last_busy == busy and s.deferred == HOLDER_PREFIX + "x"


def test_every_hours():
    s = CheckScheduler(_Checks(), CheckSchedule(every_hours=2.0), lambda: None)  # type: ignore[arg-type]
    assert s.due(s.since + 7199) is None and s.due(s.since + 7201) == "every"
    s.last_started = s.since + 7201
    assert s.due(s.since + 7300) is None and s.due(s.since + 14402) == "every"


def test_record_withholds_the_update_propose_keeps_it():
    update = {"format": "i4cal.calibration/1"}
    doc = {"update": {"accepted": True}}
    assert scheduled(doc, update, {"trigger": "every", "action": "record"}) is None
    assert doc["schedule"]["action"] == "record" and "withheld" in doc["update"]
    doc = {"update": {"accepted": True}}
    assert scheduled(doc, update, {"trigger": "idle", "action": "propose"}) is update
    assert doc["schedule"] == {"trigger": "idle", "action": "propose"} and "withheld" not in doc["update"]
    assert scheduled({}, update, None) is update
