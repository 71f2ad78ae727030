"""``GET /metrics``: the service's figures in the Prometheus text format (``prometheus_client``).

Read at each scrape, nothing kept in the service that a restart would lose:

* ``i4cal_runs{state}``: runs by state (every state, zeros included), from the database;
* ``i4cal_run_duration_seconds``: histogram of the finished runs' durations (``timings.total_s``);
* ``i4cal_run_stage_duration_seconds{stage}``: histogram of the stages' durations (acquisition, extraction,
  calibration);
* ``i4cal_frames_extracted_total``: frames the extraction went through, over every run (its summary's phases);
* ``i4cal_modbus_*_total`` (requests, retries, timeouts, reconnects, stale, unrequested), ``i4cal_serial_*_total``:
  the drivers' process-wide counters (:mod:`drivers.acquisition.metrics`), since this service started;
* the last finished check's statistic (docs/check.md): ``i4cal_check_statistic`` (its largest ``|z|``),
  ``i4cal_check_threshold``, ``i4cal_check_z{combination}``, ``i4cal_check_change_meters{combination}``,
  ``i4cal_check_verdict{verdict}`` (1 for its verdict), ``i4cal_check_timestamp_seconds``; ``i4cal_checks{verdict}``:
  finished checks by verdict;
* the process's CPU, memory and file descriptors (``process_*``).

A finished run's figures are cached by run id (they no longer change); only active and new runs are read again.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import select

from service.db import Check, Run

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
#: Bucket bounds (s) of the run and stage duration histograms.
BUCKETS = (1.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)
STAGES = ("acquisition", "extraction", "calibration")


def _histogram(name: str, doc: str, label: str | None, series: dict[str, list[float]]) -> HistogramMetricFamily:
    h = HistogramMetricFamily(name, doc, labels=[label] if label else None)
    for key, values in series.items():
        buckets = [(str(b), float(sum(v <= b for v in values))) for b in BUCKETS]
        buckets.append(("+Inf", float(len(values))))
        h.add_metric([key] if label else [], buckets, float(sum(values)))
    return h


class RunCollector(Collector):
    """Runs by state, run and stage durations and frames extracted, from the database of ``manager``."""

    def __init__(self, manager: Any) -> None:
        self.manager = manager
        self._done: dict[str, tuple[dict[str, float], int]] = {}  # finished run id -> (durations, frames)
        self._lock = threading.Lock()

    def _figures(self, run: Any) -> tuple[dict[str, float], int]:
        t = run.timings or {}
        durations = {k: float(t[f"{k}_s"]) for k in (*STAGES, "total") if isinstance(t.get(f"{k}_s"), int | float)}
        phases = (run.extraction or {}).get("phases") or {}
        frames = sum(int(p.get("frames", 0)) for p in phases.values() if isinstance(p, dict))
        return durations, frames

    def collect(self) -> Iterator[Metric]:
        from service.runs import STATES, TERMINAL_STATES

        with self._lock, self.manager.db.session() as s:
            rows = s.execute(select(Run.id, Run.state)).all()
            by_state = dict.fromkeys(STATES, 0)
            figures: list[tuple[dict[str, float], int]] = []
            for rid, state in rows:
                by_state[state] = by_state.get(state, 0) + 1
                if rid in self._done:
                    figures.append(self._done[rid])
                    continue
                run = s.get(Run, rid)
                if run is None:
                    continue
                fig = self._figures(run)
                if state in TERMINAL_STATES:
                    self._done[rid] = fig
                figures.append(fig)
        g = GaugeMetricFamily("i4cal_runs", "Runs by state", labels=["state"])
        for state, n in by_state.items():
            g.add_metric([state], float(n))
        yield g
        total = [d["total"] for d, _ in figures if "total" in d]
        yield _histogram("i4cal_run_duration_seconds", "Duration of the runs (all stages)", None, {"": total})
        yield _histogram(
            "i4cal_run_stage_duration_seconds",
            "Duration of the runs' stages",
            "stage",
            {st: [d[st] for d, _ in figures if st in d] for st in STAGES},
        )
        yield CounterMetricFamily(
            "i4cal_frames_extracted", "Frames the extraction went through", value=float(sum(f for _, f in figures))
        )


class DriverCollector(Collector):
    """The drivers' process-wide counters (:mod:`drivers.acquisition.metrics`) as ``i4cal_<name>_total``."""

    #: Always exported (0 until counted), so that a dashboard's query finds them.
    ALWAYS = ("modbus_requests", "modbus_retries", "modbus_timeouts", "modbus_reconnects")

    def collect(self) -> Iterator[Metric]:
        from drivers.acquisition.metrics import snapshot

        counts = {**dict.fromkeys(self.ALWAYS, 0.0), **snapshot()}
        for name, value in sorted(counts.items()):
            yield CounterMetricFamily(f"i4cal_{name}", f"Driver counter {name}", value=value)


class CheckCollector(Collector):
    """The last finished check's statistic and the checks by verdict, from the database of ``manager`` (its
    service's checks; every check without a service name)."""

    VERDICTS = ("holds", "drifted", "inconclusive")

    def __init__(self, manager: Any) -> None:
        self.manager = manager

    def collect(self) -> Iterator[Metric]:
        from sqlalchemy import func

        name = getattr(self.manager, "name", None)
        with self.manager.db.session() as s:
            mine = Check.service == name if name is not None else Check.service.is_(None)
            counts = dict(
                s.execute(
                    select(Check.verdict, func.count()).where(Check.state == "done", mine).group_by(Check.verdict)
                ).all()
            )
            last = s.scalars(
                select(Check)
                .where(Check.state == "done", mine)
                .order_by(Check.finished_at.desc(), Check.id.desc())
                .limit(1)
            ).first()
            doc = dict(last.result or {}) if last is not None else None
            when = last.finished_at if last is not None else None
        g = GaugeMetricFamily("i4cal_checks", "Finished checks by verdict", labels=["verdict"])
        for v in self.VERDICTS:
            g.add_metric([v], float(counts.get(v, 0)))
        yield g
        if doc is None:
            return
        yield GaugeMetricFamily("i4cal_check_statistic", "The last check's largest |z|", value=float(doc["statistic"]))
        yield GaugeMetricFamily(
            "i4cal_check_threshold", "The |z| above which the last check says drifted", value=float(doc["threshold"])
        )
        z = GaugeMetricFamily("i4cal_check_z", "The last check's standardised change", labels=["combination"])
        ch = GaugeMetricFamily(
            "i4cal_check_change_meters", "The last check's estimated change, m", labels=["combination"]
        )
        for k, c in (doc.get("changes") or {}).items():
            z.add_metric([k], float(c["z"]))
            ch.add_metric([k], float(c["change_m"]))
        yield z
        yield ch
        vg = GaugeMetricFamily("i4cal_check_verdict", "The last check's verdict (1)", labels=["verdict"])
        for v in self.VERDICTS:
            vg.add_metric([v], 1.0 if doc.get("verdict") == v else 0.0)
        yield vg
        if when is not None:
            yield GaugeMetricFamily(
                "i4cal_check_timestamp_seconds", "When the last check finished, Unix time", value=when.timestamp()
            )


def make_registry(manager_getter: Any) -> CollectorRegistry:
    """A registry of this service's collectors (one per app: several apps in one process do not mix)."""

    class _Lazy(Collector):
        def __init__(self) -> None:
            self._c: RunCollector | None = None

        def collect(self) -> Iterator[Metric]:
            m = manager_getter()
            if m is None:
                return iter(())
            if self._c is None or self._c.manager is not m:
                self._c = RunCollector(m)
            return self._c.collect()

    class _Checks(Collector):
        def collect(self) -> Iterator[Metric]:
            m = manager_getter()
            return iter(()) if m is None else CheckCollector(m).collect()

    reg = CollectorRegistry(auto_describe=False)
    reg.register(_Lazy())
    reg.register(_Checks())
    reg.register(DriverCollector())
    ProcessCollector(registry=reg)
    return reg


def render(registry: CollectorRegistry) -> bytes:
    """The registry's metrics in the Prometheus text format."""
    return generate_latest(registry)
