"""Extraction benchmark (not a timed test).

Run:  /work/venv/bin/python benchmarks/bench_extraction.py [--frames 30] [--dataset DIR] [--workers 2]

Reports
1. the median time per 1024x768 frame of board pose + eight rods, single process (target <= 20 ms);
2. the time of ``extract`` (all cores) + ``calibrate --method all`` on the paper-sized dataset
   (rendered once into a temporary directory unless --dataset is given; target <= 5 s on 2 cores);
3. the peak memory (RSS, this process and its workers) of the extraction (target <= 500 MB).
"""

from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def per_frame(n: int) -> list[float]:
    from calib.plan import make_plan
    from calib.vision.board import BoardDetector
    from calib.vision.rods import image_ideal_bbox, measure_rods, predict_rods
    from drivers.sim.render import BenchRenderer, RenderSettings
    from drivers.sim.twin import BenchGeometry, GeometricTwin

    g = BenchGeometry()
    r = BenchRenderer(g, RenderSettings(), seed=0)
    cam = r.camera
    det = BoardDetector(r.settings.board)
    box = image_ideal_bbox(cam)
    tp = GeometricTwin(g).true_poses(make_plan("full", g.nominal))[:n]
    imgs = [(q, r.render(q, pose)) for _, q, pose in tp]
    times = []
    for q, img in imgs:
        t0 = time.perf_counter()
        bp = det.measure(img, cam)
        occ = []
        if not isinstance(bp, str):
            oc = det.outline_camera(bp.R, bp.t, margin_m=0.028)
            occ.append(cam.to_ideal_pixels(oc[:, :2] / oc[:, 2:3]))
        preds = predict_rods(g.nominal, q, g.camera_from_base, g.rod_spacing_m)
        measure_rods(img, cam, preds, g.rod_radius_m, occluders=occ, ideal_bbox=box)
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--dataset", default=None, help="existing dataset v1 (default: render the paper's plan)")
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args()

    t = per_frame(args.frames)
    print(f"board + 8 rods, single process: median {statistics.median(t) * 1e3:.1f} ms/frame "
          f"(min {min(t) * 1e3:.1f}, max {max(t) * 1e3:.1f}; {len(t)} frames; target <= 20 ms)")

    from calib.observations import Observations
    from calib.pipeline import calibrate
    from calib.vision.extract import extract_dataset
    from drivers.sim.imaging import simulate_dataset

    with tempfile.TemporaryDirectory() as tmp:
        ds = Path(args.dataset) if args.dataset else None
        if ds is None:
            t0 = time.perf_counter()
            ds = simulate_dataset(Path(tmp) / "ds", seed=0)
            print(f"(rendered the paper-sized dataset in {time.perf_counter() - t0:.1f} s)")
        t0 = time.perf_counter()
        res = extract_dataset(ds, workers=args.workers)
        t1 = time.perf_counter()
        obs = Observations.from_dict(res.observations)
        calibrate(obs)
        t2 = time.perf_counter()
    n = len(res.observations["frames"])
    print(f"extract ({n} frames + camera phase): {t1 - t0:.2f} s; calibrate --method all: {t2 - t1:.2f} s; "
          f"total {t2 - t0:.2f} s (target <= 5 s on 2 cores)")
    self_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(f"peak RSS: main process {self_mb:.0f} MB, largest worker {child_mb:.0f} MB (target <= 500 MB)")
    _ = np


if __name__ == "__main__":
    main()
