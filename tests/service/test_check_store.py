"""Stored checks on a real SQLite database: a check left running by a stop is failed when the service comes back
(the bench is not held by it), and an update is applied only from a finished check that proposed one, once, for a
calibration this service applied."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from service.checks.manager import CheckManager
from service.db import Check, Database
from service.runs import RunConflictError, RunManager
from service.settings import Settings


@pytest.fixture
def runs(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'c.db'}")
    db.upgrade()
    yield RunManager(Settings(data_dir=tmp_path / "data", bench_name="bench-1"), db, None)
    db.dispose()


def _row(runs: RunManager, cid: str, **values) -> None:
    row = Check(
        id=cid,
        state="done",
        created_at=datetime.now(UTC),
        bench="bench-1",
        service="bench-1",
        in_force={},
        dataset_dir=f"checks/{cid}/dataset",
    )
    for k, v in values.items():
        setattr(row, k, v)
    with runs.db.session() as s:
        s.add(row)


def test_a_check_left_running_is_failed_on_restart(runs):
    _row(runs, "a" * 32, state="running")
    _row(runs, "b" * 32, state="running", service="other-bench")
    cm = CheckManager(runs)
    mine = cm.get("a" * 32)
    assert mine.state == "failed" and "stopped during the check" in mine.error
    assert cm.get("b" * 32).state == "running"  # another service's, on a shared database
    assert runs.bench_holder is None


def test_an_update_is_applied_only_when_proposed_once_for_a_calibration_of_this_service(runs):
    cm = CheckManager(runs)
    _row(runs, "c" * 32, state="running")
    _row(
        runs,
        "d" * 32,
        verdict="holds",
        result={"update": {"accepted": False, "reason": "the verdict is 'holds': no update proposed"}},
    )
    _row(runs, "e" * 32, verdict="drifted", update={"method": "combined"}, calibration_run_id=None)
    with pytest.raises(RunConflictError, match="running"):
        cm.apply("c" * 32)
    with pytest.raises(RunConflictError, match="holds"):
        cm.apply("d" * 32)
    with pytest.raises(RunConflictError, match="given in the request"):
        cm.apply("e" * 32)


def test_metrics_carry_the_last_checks_statistic(runs):
    from service.metrics import make_registry, render

    changes = {
        k: {"change_m": 1e-5 * i, "std_m": 1e-4, "z": 0.1 * i}
        for i, k in enumerate(("L", "H-D", "S-q02/2", "S-(q04-q03)/2"))
    }
    old = {"verdict": "holds", "statistic": 0.3, "threshold": 2.4, "changes": changes}
    new = {**old, "verdict": "drifted", "statistic": 5.25, "changes": {**changes, "L": {**changes["L"], "z": 5.25}}}
    _row(runs, "f" * 32, verdict="holds", result=old, finished_at=datetime(2026, 1, 1, tzinfo=UTC))
    _row(runs, "0" * 32, verdict="drifted", result=new, finished_at=datetime(2026, 1, 2, tzinfo=UTC))
    _row(runs, "1" * 32, state="running")
    text = render(make_registry(lambda: runs)).decode()
    assert "i4cal_check_statistic 5.25" in text
    assert 'i4cal_check_z{combination="L"} 5.25' in text
    assert 'i4cal_check_verdict{verdict="drifted"} 1.0' in text
    assert 'i4cal_checks{verdict="holds"} 1.0' in text and 'i4cal_checks{verdict="drifted"} 1.0' in text
