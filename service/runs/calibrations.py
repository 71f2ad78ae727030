"""Calibrations: a run's result (one method) made a bench's current calibration, and the history."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import select

from calib.errors import InputError
from calib.formats.resultdoc import ResultDocument
from service.db import Calibration, Database, Run
from service.jobs import clean_json
from service.runs.lifecycle import RunConflictError, RunState


def calibration_from_run(run: Run, method: str | None, default_bench: str | None) -> Calibration:
    """The calibration row that applies ``method`` of ``run`` (not yet stored).

    Raises
    ------
    RunConflictError
        The run has no result, or the method did not converge.
    InputError
        The run has no result for ``method``.
    """
    from service import __version__

    if run.state != RunState.DONE or not run.result:
        raise RunConflictError(f"run is {run.state} without a result; nothing to apply")
    doc = ResultDocument.of(run.result)
    if method is None:
        from calib.identify.verdict import verdict

        chosen = verdict(doc)
        if chosen.method is None:
            raise RunConflictError(f"{chosen.reason}; nothing to apply (name a method to apply one)")
        method = chosen.method
    entry = doc.methods.get(method)
    if entry is None:
        raise InputError(f"run has no result for method {method!r}", field="method")
    if not entry.converged or not entry.parameters:
        raise RunConflictError(f"method {method!r} did not converge in this run; nothing to apply")
    bench = run.bench or default_bench or "bench"
    payload = {
        "bench": bench,
        "run_id": run.id,
        "method": method,
        "software_version": __version__,
        "combinations": entry.parameters,
        "combinations_std": entry.std,
        "parameters": entry.seven,
        "parameters_std": entry.seven_std,
        "nominal": doc.nominal if "nominal" in run.result else None,
    }
    return Calibration(
        bench=bench,
        run_id=run.id,
        method=method,
        software_version=__version__,
        applied_at=datetime.now(UTC),
        payload=clean_json(payload),
    )


def store(db: Database, cal: Calibration) -> Calibration:
    with db.session() as s:
        s.add(cal)
    return cal


def current(db: Database, bench: str | None) -> Calibration | None:
    """The newest calibration applied to ``bench`` (None: of any bench)."""
    with db.session() as s:
        q = select(Calibration).order_by(Calibration.applied_at.desc(), Calibration.id.desc()).limit(1)
        if bench:
            q = q.where(Calibration.bench == bench)
        return s.scalar(q)


def history(db: Database, limit: int = 100, offset: int = 0, bench: str | None = None) -> list[Calibration]:
    """Applied calibrations, newest first: of ``bench``, or of every bench."""
    with db.session() as s:
        q = select(Calibration).order_by(Calibration.applied_at.desc(), Calibration.id.desc())
        if bench:
            q = q.where(Calibration.bench == bench)
        return list(s.scalars(q.limit(limit).offset(offset)))
