"""Shared fixtures: seeded simulated observations on the geometric twin."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

# One thread per numerical library in every test process and the processes it starts (services, extraction workers
# and the browser inherit the environment): pytest-xdist already runs a worker per core (and one more), and
# OpenBLAS's or OpenCV's own thread pools on top of it only contend for the same cores (OpenBLAS's threads spin
# while they wait: ~30% more CPU for the same tests). Set before numpy and cv2 are first imported; a value already
# set is kept. A test of what a user runs as they run it (the demo) removes them again from its subprocess's
# environment: the workers' own limits must hold without them (calib/numerics/threads.py).
NUMERICS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")
for _var in NUMERICS_THREAD_VARS:
    os.environ.setdefault(_var, "1")

import numpy as np
import pytest

from calib.formats.observations import Observations
from calib.formats.plan import make_plan
from calib.model.parameters import NOMINAL
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
    fixture for every package's tests: rendered once per run, whatever the workers)."""
    return shared_between_workers(tmp_path_factory, "rendered_zip.zip", lambda: _render_zip(tmp_path_factory))


def _render_zip(tmp_path_factory) -> bytes:
    import io
    import zipfile

    from calib.formats.plan import make_plan
    from drivers.sim.rendered_dataset import simulate_dataset
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


#: How the suite runs on several cores (pyproject.toml's addopts): ``-n auto --dist loadscope``, every test module on
#: one pytest-xdist worker, so a module-scoped fixture (a Monte-Carlo study, a rendered dataset) is built once per run.
#: (``--dist loadgroup`` with ``xdist_group`` marks no longer groups anything under pytest 9.2: xdist writes the group
#: into a node id field pytest no longer reads, pytest-xdist issue 1386; nothing fails, the fixtures are built once per
#: worker.) Session fixtures shared by several modules and costly to build are shared between the workers through a
#: file and a lock (:func:`shared_between_workers`).
#:
#: The modules go to the workers costliest first (longest-processing-time order, which ``--no-loadscope-reorder``
#: keeps), so that no long one starts last while the other worker idles: the CPU seconds per test are in
#: ``tests/cpu_costs.json``, written from a CPU report (below). A test missing from it counts as cheap; a stale file
#: costs speed only, never a result.
COSTS_FILE = Path(__file__).with_name("cpu_costs.json")


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker more than the cores. Many tests wait on their own processes (a service, a simulated
    bench's motion, a browser, extraction workers) while their worker's core idles; the extra worker fills those waits
    (on 2 idle cores: 524-558 s with 2 workers, 491-494 s with 3, 486 s with 4)."""
    return (os.cpu_count() or 1) + 1


def _scope(nodeid: str) -> str:
    """xdist's loadscope unit of a test: its module (or class)."""
    return nodeid.rsplit("::", 1)[0]


def pytest_collection_modifyitems(config, items):
    costs = json.loads(COSTS_FILE.read_text()) if COSTS_FILE.exists() else {}
    scope_cost: dict[str, float] = {}
    for item in items:
        scope_cost[_scope(item.nodeid)] = scope_cost.get(_scope(item.nodeid), 0.0) + costs.get(item.nodeid, 0.0)
    items.sort(key=lambda it: -scope_cost[_scope(it.nodeid)])


def shared_between_workers(tmp_path_factory, name: str, make) -> bytes:
    """The bytes ``make()`` returns, computed once per run whatever the number of xdist workers: the first worker to
    ask computes them under a file lock in the run's temporary directory (shared by its workers), the others wait for
    them and read them."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # pytest-N/, this run's
    target = shared / name
    with FileLock(str(target) + ".lock"):
        if not target.exists():
            part = target.with_name(name + ".part")
            part.write_bytes(make())
            part.replace(target)
    return target.read_bytes()


# --- CPU time per test (opt-in) -----------------------------------------------------------------------------------
#: ``I4CAL_TEST_CPU_REPORT=PATH pytest ...`` writes, per test, the CPU seconds (user + system of the test process and
#: of the child processes it reaped: extraction workers, subprocess services, the browser) spent in its setup, call
#: and teardown, and the worker (pytest-xdist) that ran it, to PATH as JSON, and prints the costliest tests and each
#: worker's sum. On a loaded machine wall times say little; the CPU sums do: the run's wall time on an idle machine is
#: about the largest worker's CPU (or the total over the cores, if larger). Each worker also appends its records as
#: they come to ``PATH.<worker>.jsonl``. ``python -m tests.conftest PATH`` writes ``tests/cpu_costs.json`` (the
#: scheduling order above) from a report.
CPU_REPORT_ENV = "I4CAL_TEST_CPU_REPORT"
_cpu_records: dict[str, dict] = {}


_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _descendants_cpu() -> float:
    """CPU seconds of this process's live descendants, each with the children it reaped (Linux ``/proc``; 0
    elsewhere): a service's multiprocessing forkserver outlives the test and reaps the extraction and fit jobs it
    forks, so they never reach ``os.times()``'s children; counted here, at each snapshot, a job that ended in between
    appears in its reaper's figure (and one this process reaped, in ``os.times()``), so differences stay exact."""
    stats: dict[int, tuple[int, float]] = {}
    try:
        pids = [int(d) for d in os.listdir("/proc") if d.isdigit()]
    except OSError:
        return 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        # after the name: state, ppid, ..., utime (14th field of the line), stime, cutime, cstime
        stats[pid] = (int(fields[1]), sum(int(x) for x in fields[11:15]) / _CLK_TCK)
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0.0, list(children.get(os.getpid(), []))
    while todo:
        pid = todo.pop()
        total += stats[pid][1]
        todo.extend(children.get(pid, []))
    return total


def _cpu_now() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system + _descendants_cpu()


def _cpu_phase(item, phase: str):
    if not os.environ.get(CPU_REPORT_ENV):
        yield
        return
    c0, w0 = _cpu_now(), time.perf_counter()
    try:
        yield
    finally:
        nodeid = item.nodeid
        rec = _cpu_records.setdefault(nodeid, {"nodeid": nodeid, "cpu": 0.0, "wall": 0.0})
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


if __name__ == "__main__":  # python -m tests.conftest REPORT.json [MORE.json ...]: the costs file from CPU reports
    import sys

    costs: dict[str, float] = {}
    for path in sys.argv[1:]:  # a later report's figure replaces an earlier one's
        costs.update({t["nodeid"]: round(t["cpu"], 1) for t in json.loads(Path(path).read_text())["tests"]})
    costs = {k: v for k, v in sorted(costs.items(), key=lambda kv: -kv[1]) if v >= 1.0}
    COSTS_FILE.write_text(json.dumps(costs, indent=0) + "\n")
    print(f"{COSTS_FILE}: {len(costs)} tests, {sum(costs.values()):.0f} s CPU")
