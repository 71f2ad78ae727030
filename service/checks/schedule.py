"""Scheduled checks (the service setting ``check_schedule``, docs/check.md): a check of the bench's current
calibration every ``every_hours``, and/or once the bench has been idle (no run holding it) for ``idle_minutes``; its
``action`` says what becomes of it: ``record`` (stored; no update proposed), ``propose`` (stored with its proposed
update, as a check over REST) or ``notify`` (as ``propose``, and the check's summary POSTed as JSON to
``notify_url``). A check due while a run (or another check) holds the bench is deferred, and said so, until the bench
is free; it goes through the same check manager as a check over REST (the same motion safety)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from calib.errors import I4calError
from service.checks.manager import HOLDER_PREFIX, CheckManager
from service.runs import RunConflictError
from service.settings import CheckSchedule
from service.timefmt import iso_utc

log = logging.getLogger(__name__)


class CheckScheduler:
    """Starts the checks ``schedule`` asks for on ``checks``' bench; ``in_force`` gives the bench's current
    calibration ``(document, calibration id, run id)``, None when none is applied."""

    def __init__(
        self, checks: CheckManager, schedule: CheckSchedule, in_force: Callable[[], tuple[Any, int, str] | None]
    ) -> None:
        self.checks, self.schedule, self.in_force = checks, schedule, in_force
        now = time.monotonic()
        self.last_started: float | None = None
        self.since = now  # the schedule's start: the first 'every' check is due every_hours after it
        self.last_busy = now  # when a run last held the bench (the start counts as activity)
        self.deferred = ""  # why the due check waits ("" when none waits)
        #: what the scheduler did, newest last: {t, type (started, deferred, skipped, notified, notify_failed), ...}
        self.events: deque[dict[str, Any]] = deque(maxlen=200)
        self._task: asyncio.Task | None = None
        self._follow: set[asyncio.Task] = set()

    # -- lifecycle ------------------------------------------------------------------------------------
    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._loop(), name="check-schedule")

    async def stop(self) -> None:
        for t in [self._task, *self._follow]:
            if t is not None:
                t.cancel()
                with contextlib.suppress(BaseException):
                    await t

    async def _loop(self) -> None:
        while True:
            await asyncio.sleep(self.schedule.poll_s)
            try:
                await self.tick()
            except Exception:  # the schedule goes on; the next tick tries again
                log.exception("scheduled check")

    # -- one look -----------------------------------------------------------------------------------
    def _note(self, kind: str, message: str, **data: Any) -> None:
        self.events.append({"t": iso_utc(datetime.now(UTC)), "type": kind, "message": message, **data})
        (log.warning if kind in ("deferred", "skipped", "notify_failed") else log.info)("%s", message)

    def due(self, now: float) -> str | None:
        """Why a check is due now (``every`` or ``idle``), None when none is."""
        s = self.schedule
        if s.every_hours is not None and now - (self.last_started or self.since) >= s.every_hours * 3600:
            return "every"
        if (
            s.idle_minutes is not None
            and now - self.last_busy >= s.idle_minutes * 60
            and (self.last_started is None or self.last_started < self.last_busy)
        ):
            return "idle"
        return None

    async def tick(self) -> str | None:
        """Start the check that is due, if the bench is free; the started check's id."""
        now = time.monotonic()
        holder = self.checks.holder()
        if holder is not None and not holder.startswith(HOLDER_PREFIX):
            self.last_busy = now  # a run holds the bench: it is not idle
        trigger = self.due(now)
        if trigger is None:
            return None
        if holder is not None:
            if self.deferred != holder:
                self.deferred = holder
                self._note("deferred", f"scheduled check ({trigger}) deferred: {holder} holds the bench")
            return None
        self.deferred = ""
        current = await asyncio.to_thread(self.in_force)
        if current is None:
            self.last_started = now
            self._note("skipped", f"scheduled check ({trigger}) skipped: no calibration applied to this bench")
            return None
        doc, cal_id, run_id = current
        from service.checks.run import CheckSettings

        s = self.schedule
        try:
            self.checks.require_free_bench(doc)
            plan, source = await asyncio.to_thread(self.checks.prepare_plan, None, s.max_seconds)
            row = self.checks.create(
                doc,
                calibration_id=cal_id,
                calibration_run_id=run_id,
                plan=plan,
                plan_source=source,
                settings=CheckSettings(alpha=s.alpha),
                schedule={"trigger": trigger, "action": s.action},
            )
        except RunConflictError as exc:  # taken by a run meanwhile: deferred to the next look
            self._note("deferred", f"scheduled check ({trigger}) deferred: {exc}")
            return None
        except I4calError as exc:
            self.last_started = now
            self._note("skipped", f"scheduled check ({trigger}) not started: {exc}")
            return None
        self.last_started = time.monotonic()
        self._note("started", f"scheduled check ({trigger}, {s.action}) started", check=row.id)
        t = asyncio.get_running_loop().create_task(self._finish(row.id), name=f"check-schedule-{row.id}")
        self._follow.add(t)
        t.add_done_callback(self._follow.discard)
        return row.id

    async def _finish(self, check_id: str) -> None:
        await self.checks.wait(check_id)
        if self.schedule.action == "notify":
            await self.notify(check_id)

    async def notify(self, check_id: str) -> None:
        """POST the check's summary to ``notify_url``; what happened is noted and stored in the check's document
        (``schedule.notified``)."""
        import httpx

        row = self.checks.get(check_id)
        doc = row.result or {}
        body = {
            "check": row.id,
            "bench": row.bench,
            "state": row.state,
            "verdict": row.verdict,
            "drifted": doc.get("drifted"),
            "update": doc.get("update"),
            "error": row.error,
            "trigger": ((doc.get("schedule") or {}).get("trigger")),
        }
        url = str(self.schedule.notify_url)
        try:
            async with httpx.AsyncClient(timeout=10.0) as client:
                r = await client.post(url, json=body)
            r.raise_for_status()
            outcome: dict[str, Any] = {"url": url, "status": r.status_code}
            self._note("notified", f"check {row.id} ({row.verdict or row.state}) notified to {url}", check=row.id)
        except httpx.HTTPError as exc:
            outcome = {"url": url, "error": f"{type(exc).__name__}: {exc}"}
            self._note("notify_failed", f"check {row.id}: notifying {url} failed: {exc}", check=row.id)
        if row.result is not None:
            self.checks.set_result(
                check_id, {**row.result, "schedule": {**doc.get("schedule", {}), "notified": outcome}}
            )

    def status(self) -> dict[str, Any]:
        """The schedule, what is due and what the scheduler did (``GET /api/v1/checks/schedule``)."""
        now = time.monotonic()
        s = self.schedule
        next_s = None
        if s.every_hours is not None:
            next_s = max(0.0, (self.last_started or self.since) + s.every_hours * 3600 - now)
        return {
            "schedule": s.model_dump(mode="json"),
            "next_every_s": next_s,
            "idle_s": now - self.last_busy,
            "deferred": self.deferred or None,
            "events": list(self.events),
        }
