"""Shared fixtures: seeded simulated observations on the geometric twin."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from calib.observations import Observations
from calib.parameters import NOMINAL
from calib.plan import make_plan
from drivers.sim.twin import GeometricTwin, NoiseSpec


@pytest.fixture(scope="session")
def paper_plan():
    return make_plan("full", NOMINAL, seed=0)


@pytest.fixture(scope="session")
def noise_free_obs(paper_plan) -> tuple[Observations, GeometricTwin]:
    twin = GeometricTwin(noise=NoiseSpec.zero())
    return Observations.from_dict(twin.observations(plan=paper_plan, seed=0)), twin


@pytest.fixture(scope="session")
def noisy_obs(paper_plan) -> tuple[Observations, GeometricTwin]:
    twin = GeometricTwin()
    return Observations.from_dict(twin.observations(plan=paper_plan, seed=7)), twin


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def rendered_zip(tmp_path_factory) -> bytes:
    """A reduced 'full' plan rendered by the image-level twin, its true intrinsics written in, as a zip (one
    fixture for every package's tests: rendered once per run)."""
    import io
    import zipfile

    from calib.plan import make_plan
    from drivers.sim.imaging import simulate_dataset
    from drivers.sim.twin import BenchGeometry

    g = BenchGeometry()
    plan = make_plan("full", g.nominal, seed=2, n_base=6, n_fit=10, n_lock=4, n_validation=4, line_samples=11)
    root = simulate_dataset(tmp_path_factory.mktemp("rendered") / "ds", seed=2, geometry=g, plan=plan, n_camera_views=0)
    doc = json.loads((root / "dataset.json").read_text())
    doc["camera"]["K"], doc["camera"]["dist"] = doc["truth"]["K"], doc["truth"]["dist"]
    (root / "dataset.json").write_text(json.dumps(doc))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for f in sorted(root.rglob("*")):
            if f.is_file():
                zf.write(f, f"dataset/{f.relative_to(root).as_posix()}")
    return buf.getvalue()


#: Session fixtures that are costly to build (a rendered dataset, a PostgreSQL cluster): with pytest-xdist
#: (``--dist loadgroup``) every test using one of them runs on the same worker, so each is built once per run.
XDIST_GROUPS = {"rendered_zip": "rendered", "postgres_url": "postgres"}
#: The project's module-scoped fixtures (Monte-Carlo studies, rendered datasets) are grouped the same way, named by
#: fixture and module: one built in a module fixture ran once per worker that got one of its tests (2 x 115 s).
SHARED_SCOPES = ("module",)


def _shared_fixture_group(item) -> str | None:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return None
    for name in info.names_closure:
        defs = info.name2fixturedefs.get(name)
        if not defs:
            continue
        fd = defs[-1]
        if fd.scope in SHARED_SCOPES and str(fd.baseid).startswith("tests"):
            return f"{name}@{fd.baseid}"
    return None


#: CPU seconds of the costliest tests (``tests/cpu_costs.json``, written from a CPU report, below): the work units
#: (a group, or a test alone) go to the xdist workers costliest first, so no long one starts last while the other
#: worker idles (``--no-loadscope-reorder`` keeps this order). A test missing from the file counts as cheap; a stale
#: file costs speed only, never a result.
COSTS_FILE = Path(__file__).with_name("cpu_costs.json")


def pytest_collection_modifyitems(config, items):
    scope_of = {}
    for item in items:
        group = next((g for f, g in XDIST_GROUPS.items() if f in getattr(item, "fixturenames", ())), None)
        group = group or _shared_fixture_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
        scope_of[item.nodeid] = group or item.nodeid
    costs = json.loads(COSTS_FILE.read_text()) if COSTS_FILE.exists() else {}
    scope_cost: dict[str, float] = {}
    for nodeid, scope in scope_of.items():
        scope_cost[scope] = scope_cost.get(scope, 0.0) + costs.get(nodeid, 0.0)
    items.sort(key=lambda it: -scope_cost[scope_of[it.nodeid]])


# --- CPU time per test (opt-in) -----------------------------------------------------------------------------------
#: ``I4CAL_TEST_CPU_REPORT=PATH pytest ...`` writes, per test, the CPU seconds (user + system of the test process and
#: of the child processes it reaped: extraction workers, subprocess services, the browser) spent in its setup, call
#: and teardown, and the worker (pytest-xdist) that ran it, to PATH as JSON, and prints the costliest tests and each
#: worker's sum. On a loaded machine wall times say little; the CPU sums do: the run's wall time on an idle machine is
#: about the largest worker's CPU (or the total over the cores, if larger). Each worker also appends its records as
#: they come to ``PATH.<worker>.jsonl``. ``python tests/conftest.py PATH`` writes ``tests/cpu_costs.json`` (the
#: scheduling order above) from a report.
CPU_REPORT_ENV = "I4CAL_TEST_CPU_REPORT"
_cpu_records: dict[str, dict] = {}


def _cpu_now() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _cpu_phase(item, phase: str):
    if not os.environ.get(CPU_REPORT_ENV):
        yield
        return
    c0, w0 = _cpu_now(), time.perf_counter()
    try:
        yield
    finally:
        rec = _cpu_records.setdefault(item.nodeid, {"nodeid": item.nodeid, "cpu": 0.0, "wall": 0.0})
        rec[phase] = round(_cpu_now() - c0, 3)
        rec["cpu"] = round(rec["cpu"] + rec[phase], 3)
        rec["wall"] = round(rec["wall"] + time.perf_counter() - w0, 3)
        if phase == "teardown":  # as it goes, one line a test: a run stopped early still leaves its records
            worker = getattr(item.config, "workerinput", {}).get("workerid", "main")
            with open(f"{os.environ[CPU_REPORT_ENV]}.{worker}.jsonl", "a") as f:
                f.write(json.dumps(rec) + "\n")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item):
    return (yield from _cpu_phase(item, "setup"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    return (yield from _cpu_phase(item, "call"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):
    return (yield from _cpu_phase(item, "teardown"))


def _worker_summary(config) -> dict:
    worker = getattr(config, "workerinput", {}).get("workerid", "main")
    for rec in _cpu_records.values():
        rec["worker"] = worker
    return {
        "worker": worker,
        "process_cpu": round(_cpu_now(), 3),
        "tests_cpu": round(sum(r["cpu"] for r in _cpu_records.values()), 3),
        "tests": list(_cpu_records.values()),
    }


_cpu_workers: list[dict] = []


def pytest_sessionfinish(session, exitstatus):
    if not os.environ.get(CPU_REPORT_ENV):
        return
    if hasattr(session.config, "workeroutput"):  # an xdist worker: the controller gathers
        session.config.workeroutput["cpu_report"] = json.dumps(_worker_summary(session.config))
    elif not _cpu_workers:  # no xdist
        _cpu_workers.append(_worker_summary(session.config))


def pytest_testnodedown(node, error):
    out = getattr(node, "workeroutput", {}).get("cpu_report")
    if out:
        _cpu_workers.append(json.loads(out))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    path = os.environ.get(CPU_REPORT_ENV)
    if not path or hasattr(config, "workerinput"):
        return
    if not _cpu_workers:
        _cpu_workers.append(_worker_summary(config))
    tests = sorted((t for w in _cpu_workers for t in w["tests"]), key=lambda t: -t["cpu"])
    total = sum(w["process_cpu"] for w in _cpu_workers)
    cores = os.cpu_count() or 1
    report = {
        "workers": [{k: v for k, v in w.items() if k != "tests"} for w in _cpu_workers],
        "total_cpu": round(total, 3),
        "cores": cores,
        "tests": tests,
    }
    with open(path, "w") as f:
        json.dump(report, f, indent=1)
    tr = terminalreporter
    tr.write_sep("=", f"CPU seconds per test (user+system, with reaped children) -> {path}")
    for t in tests[:25]:
        phases = ", ".join(f"{p} {t.get(p, 0):.1f}" for p in ("setup", "call", "teardown"))
        tr.write_line(f"{t['cpu']:8.1f} s  {t['worker']:>5}  {t['nodeid']}  ({phases}; wall {t['wall']:.1f} s)")
    for w in sorted(_cpu_workers, key=lambda w: w["worker"]):
        n = len(w["tests"])
        tr.write_line(
            f"worker {w['worker']}: {n} tests, tests {w['tests_cpu']:.1f} s CPU, process {w['process_cpu']:.1f} s"
        )
    largest = max(w["process_cpu"] for w in _cpu_workers)
    tr.write_line(
        f"total {total:.1f} s CPU; idle-machine wall estimate max(largest worker {largest:.1f}, "
        f"total / {cores} cores {total / cores:.1f}) = {max(largest, total / cores):.1f} s"
    )


if __name__ == "__main__":  # python tests/conftest.py REPORT.json: the costs file from a CPU report
    import sys

    report = json.loads(Path(sys.argv[1]).read_text())
    costs = {t["nodeid"]: round(t["cpu"], 1) for t in report["tests"] if t["cpu"] >= 1.0}
    COSTS_FILE.write_text(json.dumps(dict(sorted(costs.items(), key=lambda kv: -kv[1])), indent=0) + "\n")
    print(f"{COSTS_FILE}: {len(costs)} tests, {sum(costs.values()):.0f} s CPU")
