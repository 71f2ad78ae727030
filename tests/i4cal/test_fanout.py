"""Studies fanned out over Dask (``service.fanout``): a small accuracy study on a LocalCluster of two workers gives the
numbers of the same study in one process; ``plan design --draws`` on a running scheduler (``--scheduler``) the plan
of one process; a task that raises is reported with its error while the others complete; progress as tasks finish.

Real Dask clusters on this machine (worker processes, TCP on loopback); nothing is mocked.
"""

from __future__ import annotations

import io
import json
import os
import sys
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

from calib.errors import InputError
from i4cal.benchmarks.accuracy import AccuracyOptions, run_accuracy
from i4cal.cli import main
from service.fanout import Fanout, FanoutSettings, finished_line, progress_display, settings_from

# the workers import this module's functions by value: the test tree is not installed where they start
cloudpickle.register_pickle_by_value(sys.modules[__name__])

BENCH_SIM = Path(__file__).resolve().parents[2] / "deploy" / "bench-sim.toml"
#: the cheapest study that still renders, extracts and calibrates: two trials of a 19-frame plan with the renderer's
#: own intrinsics (no camera phase), about 2.5 CPU s a trial
TINY = {
    "trials": 2,
    "n_base": 3,
    "n_fit": 4,
    "n_lock": 2,
    "n_validation": 2,
    "camera": "true",
}


@pytest.fixture(scope="module")
def cluster():
    """A running Dask scheduler with two single-threaded worker processes (what ``--scheduler`` points at)."""
    import logging

    from distributed import LocalCluster

    with LocalCluster(
        n_workers=2, threads_per_worker=1, dashboard_address=None, memory_limit=0, silence_logs=logging.WARNING
    ) as c:
        yield c.scheduler_address


def _without_timings(x: Any) -> Any:
    """A study's records without their wall and CPU times (``*_s``): what differs between two runs of it."""
    if isinstance(x, dict):
        return {k: _without_timings(v) for k, v in x.items() if not k.endswith("_s")}
    if isinstance(x, list):
        return [_without_timings(v) for v in x]
    return x


def test_accuracy_study_on_a_local_cluster_of_two_workers_gives_the_numbers_of_one_process():
    seen: list[tuple[str, int, int]] = []
    dask = run_accuracy(AccuracyOptions(**TINY, workers=2), lambda d, done, total: seen.append((d, done, total)))
    alone = run_accuracy(AccuracyOptions(**TINY, workers=1))
    assert dask["engine"] == "Dask LocalCluster (2 workers, 1 thread each)" and dask["workers"] == 2
    assert alone["engine"] == "in this process (no Dask)" and alone["workers"] == 1
    trials = dask["study"]["trials"]
    assert [t["index"] for t in trials] == [0, 1] and all(t["error"] is None for t in trials)
    assert all(t["methods"]["combined"]["ok"] for t in trials)
    # every number of every trial, and the summaries computed from them, to the last bit
    assert _without_timings(dask["study"]) == _without_timings(alone["study"])
    # progress as each trial finished, naming it
    assert [s[1:] for s in seen] == [(0, 2), (1, 2), (2, 2)]
    assert {s[0].split(" ")[0] for s in seen[1:]} == {"noise=2,fit=4,k=0", "noise=2,fit=4,k=1"}


def _square_or_fail(x: int) -> int:
    if x == 2:
        raise ValueError(f"trial {x} cannot run")
    return x * x


def test_a_task_that_raises_is_reported_with_its_error_and_the_others_complete(cluster):
    done: list[tuple[str, int, int]] = []
    with Fanout(FanoutSettings(scheduler=cluster), n_tasks=4) as fan:
        assert fan.description == f"Dask scheduler {cluster} (2 workers)"
        outcomes = fan.map(
            _square_or_fail,
            [0, 1, 2, 3],
            names=[f"trial {k}" for k in range(4)],
            on_done=lambda o, i, n: done.append((finished_line(o), i, n)),
        )
    assert [o.value for o in outcomes] == [0, 1, None, 9]
    assert [o.ok for o in outcomes] == [True, True, False, True]
    assert outcomes[2].error_text() == "ValueError: trial 2 cannot run"
    assert sorted(d[0] for d in done) == [
        "trial 0 done",
        "trial 1 done",
        "trial 2 FAILED: ValueError: trial 2 cannot run",
        "trial 3 done",
    ]
    assert [d[1:] for d in done] == [(1, 4), (2, 4), (3, 4), (4, 4)]


def test_in_process_the_tasks_run_one_by_one_as_progress_asks_for_them():
    """``--workers 1``: no Dask; each task runs when the study waits for one, so progress follows every task."""
    ran: list[int] = []

    def note(o, i, n):
        ran.append(i)
        assert o.index == i - 1  # in submission order, reported before the next one starts

    with Fanout(FanoutSettings(workers=1)) as fan:
        assert fan.in_process and fan.description == "in this process (no Dask)"
        outcomes = fan.map(_square_or_fail, [3, 2, 1], on_done=note)
    assert ran == [1, 2, 3]
    assert [o.value for o in outcomes] == [9, None, 1] and outcomes[1].error_text() == "ValueError: trial 2 cannot run"


def test_progress_is_plain_lines_when_not_a_terminal():
    out = io.StringIO()
    with progress_display("accuracy study", stream=out) as shown:
        shown("noise=2,fit=4,k=1 done", 1, 2)
        shown("noise=2,fit=4,k=0 FAILED: ValueError: x", 2, 2)
    assert out.getvalue().splitlines() == [
        "accuracy study: 1/2 noise=2,fit=4,k=1 done",
        "accuracy study: 2/2 noise=2,fit=4,k=0 FAILED: ValueError: x",
    ]


def test_plan_design_draws_on_a_scheduler_give_the_plan_of_one_process(cluster, capsys):
    small = ["plan", "design", "--bench", str(BENCH_SIM), "--n-fit", "4", "--no-line", "--candidates", "60"]
    assert main([*small, "--draws", "3", "--scheduler", cluster, "--json"]) == 0
    remote = json.loads(capsys.readouterr().out)
    assert main([*small, "--draws", "3", "--workers", "1", "--json"]) == 0
    alone = json.loads(capsys.readouterr().out)
    assert any("best of 3 draws" in n for n in remote["notes"]), remote["notes"]
    assert remote == alone


def test_a_bad_scheduler_address_is_refused_naming_the_option(capsys):
    with pytest.raises(InputError, match="scheduler address"):
        settings_from(None, "somewhere:8786")
    assert main(["plan", "design", "--bench", str(BENCH_SIM), "--draws", "2", "--scheduler", "host-without-port"]) == 2
    assert "--scheduler" in capsys.readouterr().err
    assert main(["bench", "accuracy", "--trials", "1", "--scheduler", "8786"]) == 2
    assert "--scheduler" in capsys.readouterr().err


def test_benchmark_is_an_alias_of_bench(capsys):
    assert main(["benchmark"]) == 1  # the benchmarks' usage, as `i4cal bench` alone
    assert "i4cal bench accuracy" in capsys.readouterr().out
    assert main(["benchmark", "accuracy", "--trials", "0"]) == 2  # a benchmark's own checks: nothing to run
    assert "--trials" in capsys.readouterr().err


def test_a_design_draw_that_failed_is_left_out_and_said_the_best_of_the_others_kept():
    """``design_plan``'s ``draws_runner`` hands back each draw's design or its error (here the runner itself stands for
    an engine whose worker died on draw 1: the two other draws are real designs)."""
    from calib.design import DesignRequest, design_plan, design_score
    from calib.model.parameters import NOMINAL
    from service.design import twin_scene

    scene = twin_scene()
    req = DesignRequest(n_fit=4, n_lock=2, n_validation=0, with_line=False, n_candidates=40, draws=3)
    res = design_plan(NOMINAL, scene, req, draws_runner=lambda fn, n: [fn(0), RuntimeError("worker lost"), fn(2)])
    design = res.plan.model_extra["design"]
    assert "draw 1 failed, left out: RuntimeError: worker lost" in res.notes
    assert design["draws_criterion"][1] is None and None not in (
        design["draws_criterion"][0],
        design["draws_criterion"][2],
    )
    k = design["request"]["candidate_draw"]
    assert k in (0, 2) and design["draws_criterion"][k] == min(
        design["draws_criterion"][0], design["draws_criterion"][2]
    )
    assert design_score(res, req)[2] == design["draws_criterion"][k]
    with pytest.raises(RuntimeError, match="worker lost"):  # no draw left: the first error, not an empty design
        design_plan(NOMINAL, scene, req, draws_runner=lambda fn, n: [RuntimeError("worker lost")] * n)


def _square_or_die(x: int) -> int:
    if x == 1:
        os._exit(3)  # the worker process dies under the task, as when the machine's memory runs out
    return x * x


def test_a_trial_whose_worker_died_is_reported_and_the_others_complete(cluster):
    """Run after the cluster's other tests: each worker that dies is restarted by its nanny; Dask gives the task to
    another worker three more times (``distributed.scheduler.allowed-failures``; a task that was only waiting on the
    dying worker runs again elsewhere), then reports it."""
    with Fanout(FanoutSettings(scheduler=cluster)) as fan:
        outcomes = fan.map(_square_or_die, [0, 1, 2])
    assert [o.value for o in outcomes] == [0, None, 4]
    assert outcomes[1].error_text().startswith("KilledWorker:"), outcomes[1].error_text()
