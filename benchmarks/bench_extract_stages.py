"""Where extraction spends its time (a benchmark, not a timed test): per stage and per part of a rod measurement.

Run:  python benchmarks/bench_extract_stages.py DATASET [--workers 2] [--profile N]

* Stages of ``extract_dataset`` on DATASET (wall s per stage, CPU s of this process and of its workers), then
  ``calibrate --method all`` on the observations (wall s).
* ``--profile N``: the N functions with the most own time over the whole extraction in one process (cProfile).

``i4cal bench speed --only extraction,extract-calibrate`` gives the figures with targets; this script says where
they go. Render a dataset with ``i4cal simulate --images --out DIR`` first.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import resource
import sys
import time
from typing import Any

import calib.vision.extract as ex
from calib.formats.observations import Observations
from calib.identify.pipeline import calibrate


def _cpu() -> tuple[float, float]:
    s = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime, c.ru_utime + c.ru_stime


def stage_times(dataset: str, workers: int) -> tuple[list[tuple[str, int, float]], dict[str, Any]]:
    """Wall time of each stage of one extraction (name, items, s) and the run's totals (s)."""
    stages: list[tuple[str, int, float]] = []
    run, calib_intr, placement = ex._Pool.run, ex.calibrate_intrinsics, ex.fit_placement

    def timed_run(self: ex._Pool, fn: Any, items: list, *a: Any, **k: Any) -> list:
        t0 = time.perf_counter()
        out = run(self, fn, items, *a, **k)
        stages.append((fn.__name__.removeprefix("_task_"), len(items), time.perf_counter() - t0))
        return out

    def timed(name: str, f: Any) -> Any:
        def g(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            out = f(*a, **k)
            stages.append((name, 0, time.perf_counter() - t0))
            return out

        return g

    ex._Pool.run = timed_run  # type: ignore[method-assign]
    ex.calibrate_intrinsics = timed("calibrate_intrinsics", calib_intr)
    ex.fit_placement = timed("fit_placement", placement)
    try:
        s0, c0 = _cpu()
        t0 = time.perf_counter()
        res = ex.extract_dataset(dataset, workers=workers)
        t1 = time.perf_counter()
        s1, c1 = _cpu()
        calibrate(Observations.from_dict(res.observations))
        t2 = time.perf_counter()
    finally:
        ex._Pool.run, ex.calibrate_intrinsics, ex.fit_placement = run, calib_intr, placement  # type: ignore[method-assign]
    return stages, {
        "extract_s": t1 - t0,
        "cpu_main_s": s1 - s0,
        "cpu_workers_s": c1 - c0,
        "calibrate_s": t2 - t1,
        "frames": len(res.observations["frames"]),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="top N functions by own time (1 process)")
    args = ap.parse_args(argv)
    stages, tot = stage_times(args.dataset, args.workers)
    print(
        f"extract {tot['extract_s']:.2f} s ({tot['frames']} frames, {args.workers} processes; CPU main "
        f"{tot['cpu_main_s']:.2f} s, workers {tot['cpu_workers_s']:.2f} s), calibrate {tot['calibrate_s']:.2f} s"
    )
    for name, n, s in stages:
        print(f"  {name:22s} {n:4d} items {s:7.3f} s")
    if args.profile:
        prof = cProfile.Profile()
        prof.runcall(ex.extract_dataset, args.dataset, workers=1)
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(args.profile)
        print(buf.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
