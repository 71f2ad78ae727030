"""A run's events: persisted in the database (numbered per run) and pushed to live subscribers (Server-Sent Events).

High-rate reports (extraction progress, per-frame results, fit iterations) are batched: at most one event of each
kind per :data:`LIVE_INTERVAL_S` and run.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import func, select, update

from service.db import Database, Event, Run
from service.jobs import clean_json
from service.timefmt import iso_utc

#: Events a live subscriber (a Server-Sent Events stream) can be behind; beyond, it is told to reconnect (below).
SUBSCRIBER_QUEUE_MAX = 10_000


class Subscription(asyncio.Queue):
    """A live subscriber's queue of events. When it is full (the client reads more slowly than the run emits) the
    next events are not queued but ``overflowed`` is set: the stream then sends an ``overflow`` event and ends, and
    the client reconnects with ``Last-Event-ID`` and reads what it missed from the database (every event is stored):
    nothing is lost silently."""

    def __init__(self, maxsize: int) -> None:
        super().__init__(maxsize=maxsize)
        self.overflowed = False

    def offer(self, item: Any) -> None:
        try:
            self.put_nowait(item)
        except asyncio.QueueFull:
            self.overflowed = True


#: Seconds between two batches of high-rate events of a run (progress, frames, iterations): with at most two kinds
#: at a time (progress + frames, or iterations), a run writes at most ~10 such events per second.
LIVE_INTERVAL_S = 0.2


class EventBus:
    """Events of every run of one service: :meth:`emit` stores and pushes, :meth:`subscribe` follows."""

    def __init__(self, db: Database, clock: Callable[[], datetime] = lambda: datetime.now(UTC)) -> None:
        self.db = db
        self.clock = clock
        self._subs: dict[str, set[Subscription]] = {}
        self._seq: dict[str, int] = {}
        self._live: dict[str, dict[str, Any]] = {}  # run id -> kind -> pending batch
        self._live_timer: dict[str, asyncio.TimerHandle] = {}
        self._live_last: dict[str, float] = {}

    def _next_seq(self, run_id: str) -> int:
        if run_id not in self._seq:
            with self.db.session() as s:
                self._seq[run_id] = int(s.scalar(select(func.max(Event.seq)).where(Event.run_id == run_id)) or 0)
        self._seq[run_id] += 1
        return self._seq[run_id]

    def emit(self, run_id: str, type_: str, data: dict[str, Any], t: datetime | None = None) -> None:
        """Store and push an event (``t``: its time, default now)."""
        data = clean_json(data)
        seq = self._next_seq(run_id)
        t = self.clock() if t is None else t
        try:
            with self.db.session() as s:
                s.add(Event(run_id=run_id, seq=seq, t=t, type=type_, data=data))
        except BaseException:
            if self._seq.get(run_id) == seq:  # not stored (e.g. disk full): the next event takes its number
                self._seq[run_id] = seq - 1
            raise
        ev = {"seq": seq, "t": iso_utc(t), "type": type_, "data": data}
        for q in list(self._subs.get(run_id, ())):
            q.offer(ev)

    def forget(self, run_id: str) -> None:
        """Drop what is kept in memory of a deleted run (its next number, pending batches)."""
        self._seq.pop(run_id, None)
        self._live.pop(run_id, None)
        self._live_last.pop(run_id, None)
        timer = self._live_timer.pop(run_id, None)
        if timer is not None:
            timer.cancel()

    def subscribe(self, run_id: str) -> Subscription:
        q = Subscription(SUBSCRIBER_QUEUE_MAX)
        self._subs.setdefault(run_id, set()).add(q)
        return q

    def unsubscribe(self, run_id: str, q: Subscription) -> None:
        subs = self._subs.get(run_id)
        if subs is not None:
            subs.discard(q)
            if not subs:
                self._subs.pop(run_id, None)

    def close_subscribers(self, run_id: str) -> None:
        """Tell the live subscribers of ``run_id`` that no more events come (the run ended)."""
        for q in list(self._subs.get(run_id, ())):
            q.offer(None)  # a full queue: overflowed, the stream ends at its next event anyway

    def events(self, run_id: str, after: int = 0) -> list[dict[str, Any]]:
        with self.db.session() as s:
            rows = s.scalars(select(Event).where(Event.run_id == run_id, Event.seq > after).order_by(Event.seq))
            return [{"seq": e.seq, "t": iso_utc(e.t), "type": e.type, "data": e.data} for e in rows]

    # -- high-rate reports: batched ------------------------------------------------------------------
    def queue_live(self, run_id: str, kind: str, data: dict[str, Any]) -> None:
        """Queue a high-rate report; :meth:`flush_live` writes the batch at most every :data:`LIVE_INTERVAL_S`.

        ``kind``: ``progress`` (the latest replaces the previous), ``frames`` or ``iterations`` (appended).
        """
        pending = self._live.setdefault(run_id, {})
        if kind == "progress":
            pending["progress"] = data
        else:
            pending.setdefault(kind, []).append(data)
        if run_id not in self._live_timer:
            loop = asyncio.get_running_loop()
            delay = max(0.0, self._live_last.get(run_id, 0.0) + LIVE_INTERVAL_S - time.monotonic())
            self._live_timer[run_id] = loop.call_later(delay, self.flush_live, run_id)

    def flush_live(self, run_id: str) -> None:
        timer = self._live_timer.pop(run_id, None)
        if timer is not None:
            timer.cancel()
        pending = self._live.pop(run_id, None)
        if not pending:
            return
        self._live_last[run_id] = time.monotonic()
        t = self.clock()  # one time for the batch: the database writes before an event do not shift its time
        p = pending.pop("progress", None)
        if p is not None:
            with self.db.session() as s:
                s.execute(update(Run).where(Run.id == run_id).values(done=p["done"], total=p["total"]))
            self.emit(run_id, "progress", p, t)
        for kind, items in pending.items():
            self.emit(run_id, kind, {"count": len(items), "items": items}, t)

    def end_live(self, run_id: str) -> None:
        self.flush_live(run_id)
        self._live_last.pop(run_id, None)
