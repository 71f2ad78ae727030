"""The service's checks: one at a time on the bench (never while a run holds it, and no run starts while a check
does), each stored (``checks`` table) with its verdict, its document and the proposed update; an accepted update
applied as the bench's current calibration like a run's result."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import select

from calib.errors import I4calError, InputError
from service.checks.plan import check_plan_for_bench, require_check_phases
from service.checks.run import CheckSettings, predicted_check_std, run_check
from service.db import Calibration, Check
from service.runs import RunConflictError, RunManager
from service.timefmt import iso_utc

log = logging.getLogger(__name__)

#: what the service's bench holder is set to while a check moves the robot (a run is refused meanwhile)
HOLDER_PREFIX = "check "


def scheduled(doc: dict[str, Any], update: dict[str, Any] | None, schedule: dict[str, Any] | None):
    """The update a check stores: a scheduled check's document (``doc``, changed in place) records its
    ``schedule`` (trigger, action), and the action ``record`` withholds the proposed update (saying so)."""
    if schedule is None:
        return update
    doc["schedule"] = dict(schedule)
    if schedule.get("action") == "record" and update is not None:
        doc["update"] = {**doc.get("update", {}), "withheld": "the schedule's action is 'record': no update proposed"}
        return None
    return update


class CheckNotFoundError(LookupError):
    pass


class CheckManager:
    """Checks of the bench a :class:`service.runs.RunManager` drives (its database, data directory, bench)."""

    def __init__(self, runs: RunManager) -> None:
        self.runs = runs
        self.tasks: dict[str, asyncio.Task] = {}
        #: why a running check holds the robot by itself (drivers.acquisition.suspenders), by check id
        self.suspended: dict[str, str] = {}
        self.recover()

    def recover(self) -> list[str]:
        """This service's checks left ``running`` by a stop or a crash become ``failed`` (their frames are kept):
        a check is short, it is started again rather than resumed."""
        from sqlalchemy import or_

        with self.runs.db.session() as s:
            mine = (
                Check.service.is_(None)
                if self.runs.name is None
                else or_(Check.service == self.runs.name, Check.service.is_(None))
            )
            rows = list(s.scalars(select(Check).where(Check.state == "running", mine)))
            for row in rows:
                if row.id not in self.tasks:
                    row.state, row.finished_at = "failed", datetime.now(UTC)
                    row.error = "the service stopped during the check; start another"
            return [r.id for r in rows]

    @property
    def data_dir(self) -> Path:
        return self.runs.data_dir

    # -- rows ------------------------------------------------------------------------------------
    def get(self, check_id: str) -> Check:
        with self.runs.db.session() as s:
            row = s.get(Check, check_id)
            if row is None:
                raise CheckNotFoundError(check_id)
            return row

    def list(self, limit: int = 100, offset: int = 0, bench: str | None = None) -> list[Check]:
        with self.runs.db.session() as s:
            q = select(Check).order_by(Check.created_at.desc(), Check.id.desc())
            if bench:
                q = q.where(Check.bench == bench)
            return list(s.scalars(q.limit(limit).offset(offset)))

    def set_result(self, check_id: str, result: dict[str, Any]) -> None:
        """Replace a finished check's document (a scheduled check's notification recorded in it)."""
        self._update(check_id, result=result)

    def _update(self, check_id: str, **values: Any) -> None:
        with self.runs.db.session() as s:
            row = s.get(Check, check_id)
            assert row is not None
            for k, v in values.items():
                setattr(row, k, v)

    # -- start -----------------------------------------------------------------------------------
    def require_free_bench(self, in_force: Any) -> None:
        """Refuse a check now, before its plan is designed: no bench, a run or a check holding it, a calibration
        without covariance.

        Raises
        ------
        InputError, RunConflictError
        """
        from calib.check.drift import in_force_estimate

        if self.runs.bench is None:
            raise InputError("this service has no bench configured: nothing to check", field="bench")
        if self.runs.bench_holder is not None:
            raise RunConflictError(f"{self._holder()} holds the bench")
        in_force_estimate(in_force)

    def prepare_plan(self, plan: Any, max_seconds: float = 60.0, repeat: int | None = None) -> tuple[Any, str]:
        """The check plan (blocking: in a thread): ``plan`` checked for the check's phases, or the bench's designed
        one (cached in the data directory), its fit poses revisited ``repeat`` times when given; validated against
        the bench's soft limits before anything moves."""
        from calib.design.drift_check import with_repeats
        from calib.formats.plan import validate_plan

        bench = self.runs.bench
        if bench is None:
            raise InputError("this service has no bench configured: nothing to check", field="bench")
        cfg = bench.config
        source = "given"
        if plan is None:
            plan, _, source = check_plan_for_bench(
                cfg, max_seconds, self.data_dir / "check-plans", camera=bench.camera_model
            )
        else:
            require_check_phases(plan, "plan")
        if repeat is not None:
            plan = with_repeats(plan, repeat)
            source += f", each fit pose visited {repeat} times"
        validate_plan(plan, cfg.nominal_parameters(), cfg.calib_limits())
        return plan, source

    def create(
        self,
        in_force: Any,
        *,
        calibration_id: int | None,
        calibration_run_id: str | None,
        plan: Any,
        plan_source: str = "given",
        settings: CheckSettings | None = None,
        schedule: dict[str, Any] | None = None,
    ) -> Check:
        """Start checking ``in_force`` (an ``i4cal.calibration/1`` document) with ``plan`` (:meth:`prepare_plan`):
        the bench taken, the acquisition, fit and test in a task.

        Raises
        ------
        RunConflictError
            A run (or another check) holds the bench.
        """
        self.require_free_bench(in_force)
        bench = self.runs.bench
        assert bench is not None
        cid = uuid.uuid4().hex
        row = Check(
            id=cid,
            state="running",
            created_at=datetime.now(UTC),
            bench=bench.name,
            service=self.runs.name,
            calibration_id=calibration_id,
            calibration_run_id=calibration_run_id,
            in_force=in_force.model_dump(mode="json"),
            plan={**plan.model_dump(mode="json", exclude_none=True), "source": plan_source},
            dataset_dir=f"checks/{cid}/dataset",
        )
        with self.runs.db.session() as s:
            s.add(row)
        self.runs.bench_holder = HOLDER_PREFIX + cid
        self.tasks[cid] = asyncio.get_running_loop().create_task(
            self._execute(cid, plan, in_force, settings or CheckSettings(), schedule), name=f"check-{cid}"
        )
        return row

    def holder(self) -> str | None:
        """Who holds the bench (``run ID`` or ``check ID``), None when it is free."""
        h = self.runs.bench_holder
        if h is None:
            return None
        return h if h.startswith(HOLDER_PREFIX) else f"run {h}"

    def _holder(self) -> str:
        return self.holder() or ""

    async def _execute(
        self, cid: str, plan: Any, in_force: Any, settings: CheckSettings, schedule: dict[str, Any] | None = None
    ) -> None:
        from service import __version__

        bench = self.runs.bench
        assert bench is not None
        out = self.data_dir / "checks" / cid / "dataset"
        try:
            outcome = await run_check(
                bench.config,
                plan,
                in_force,
                out,
                settings,
                camera_spec=dict(bench.camera_spec),
                progress=lambda p: self._progress(cid, p),
                software_version=__version__,
                now=lambda: iso_utc(datetime.now(UTC)),
            )
            outcome.predicted_std_m = await asyncio.to_thread(
                predicted_check_std, bench.config, plan, bench.camera_model
            )
            outcome.calibration = {"run": in_force.run, "date": in_force.date}
            outcome.plan = {"frames": len(plan.steps), **plan.count()}
            doc = outcome.to_dict()
            doc["id"] = cid
            doc["dataset"] = f"checks/{cid}/dataset"
            update = scheduled(doc, outcome.update_document, schedule)
            self._update(
                cid,
                state="done",
                verdict=outcome.verdict,
                result=doc,
                update=update,
                finished_at=datetime.now(UTC),
            )
        except (I4calError, OSError) as exc:
            self._update(cid, state="failed", error=str(exc) or type(exc).__name__, finished_at=datetime.now(UTC))
        except asyncio.CancelledError:
            self._update(
                cid, state="failed", error="the service stopped during the check", finished_at=datetime.now(UTC)
            )
            raise
        except Exception as exc:  # a bug must not leave the check running or the bench held
            log.exception("check %s failed", cid)
            self._update(cid, state="failed", error=f"{type(exc).__name__}: {exc}", finished_at=datetime.now(UTC))
        finally:
            self.suspended.pop(cid, None)
            if self.runs.bench_holder == HOLDER_PREFIX + cid:
                self.runs.bench_holder = None

    def _progress(self, cid: str, p: Any) -> None:
        """The acquisition's progress: a suspension (drivers.acquisition.suspenders) noted while it lasts."""
        if p.state == "suspended":
            if self.suspended.get(cid) != p.message:
                log.warning("check %s suspended: %s", cid, p.message)
            self.suspended[cid] = p.message
        elif p.state == "running" and self.suspended.pop(cid, None):
            log.info("check %s: %s", cid, p.message)

    async def wait(self, check_id: str) -> None:
        t = self.tasks.get(check_id)
        if t is not None:
            with contextlib.suppress(BaseException):
                await asyncio.shield(t)

    async def shutdown(self) -> None:
        for t in self.tasks.values():
            t.cancel()
        for t in self.tasks.values():
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(t, 10)

    # -- apply -----------------------------------------------------------------------------------
    def apply(self, check_id: str) -> Calibration:
        """Make the check's proposed update the bench's current calibration.

        Raises
        ------
        RunConflictError
            The check is not done, proposed no update (its reason said), was applied already, or tested a document
            that is not one of this service's calibrations (no run to descend from).
        """
        from service import __version__
        from service.runs import calibrations

        row = self.get(check_id)
        if row.state != "done":
            raise RunConflictError(f"the check is {row.state}: nothing to apply")
        if row.update is None:
            why = ((row.result or {}).get("update") or {}).get("reason") or "no update proposed"
            raise RunConflictError(f"the check proposed no update ({why})")
        if row.applied_calibration_id is not None:
            raise RunConflictError(f"the update was applied already (calibration {row.applied_calibration_id})")
        if row.calibration_run_id is None:
            raise RunConflictError(
                "the check tested a calibration given in the request, not one applied by this service: load the "
                "update (GET /api/v1/checks/{id}) into the controller yourself"
            )
        doc = {**row.update, "check": row.id}
        payload = {
            "bench": row.bench,
            "run_id": row.calibration_run_id,
            "check_id": row.id,
            "method": doc.get("method"),
            "software_version": __version__,
            "combinations": doc.get("combinations"),
            "combinations_std": doc.get("combinations_std"),
            "parameters": None,
            "parameters_std": None,
            "nominal": doc.get("nominal"),
            "document": doc,
        }
        cal = calibrations.store(
            self.runs.db,
            Calibration(
                bench=row.bench or self.runs.name or "bench",
                run_id=row.calibration_run_id,
                method=str(doc.get("method") or "combined"),
                software_version=__version__,
                applied_at=datetime.now(UTC),
                payload=payload,
            ),
        )
        self._update(check_id, applied_calibration_id=cal.id)
        return cal
