"""First-frame rod detector benchmark (not a timed test): the figures of docs/vision.md.

Run:  python benchmarks/bench_detect.py [--seeds 51,52,53,54,55,56,61,62,63,64,65,66] [--step 4] [--json PATH]

On every ``step``-th frame of the paper's plan rendered by the image-level twin (default noise, one
render seed per plan seed), :func:`calib.vision.detect.detect_rods` runs with the mounting prior
(camera looking down -z_B, image x along +x_B) and without a prior. Reported: frames associated,
wrong associations (a detected rod direction > 0.3 rad from its true leg's), ambiguous frames, the
detected directions' and the measured rods' (``measure_detected``) angles to the truth, the coarse
placement's error, the detection time per frame (one process). About 2 s per frame.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from rich.console import Console
from rich.progress import Progress

from calib.formats.plan import make_plan
from calib.numerics.transforms import Rigid, matrix_to_rotvec
from calib.vision.detect import detect_rods, measure_detected
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin

MOUNTING = Rigid(np.diag([1.0, -1.0, -1.0]), np.zeros(3))


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))


def run_frame(
    g: BenchGeometry, renderer: BenchRenderer, q: np.ndarray, pose: np.ndarray, img: np.ndarray, seed: int
) -> dict:
    """Both detections of one frame against the truth (angles in rad, distances in m, time in s)."""
    u_true, _ = g.rod_lines_camera(q, pose)
    out: dict = {"Y": float(pose[1])}
    for name, prior in (("prior", MOUNTING), ("none", None)):
        t0 = time.perf_counter()
        det = detect_rods(img, renderer.camera, g.nominal, q, g.rod_radius_m, g.rod_spacing_m, prior=prior)
        res: dict = {"time": time.perf_counter() - t0, "ok": det.ok, "ambiguous": det.ambiguous}
        if det.ok:
            res["dir_err"] = [
                _angle(d, u_true[p.leg, p.rod])
                for p, d in zip(det.predictions, det.directions, strict=True)
                if p is not None
            ]
            res["legs"] = len(res["dir_err"]) // 2
            C = det.camera_from_base
            res["rot_err"] = float(np.linalg.norm(matrix_to_rotvec(C.R @ g.camera_from_base.R.T)))
            res["t_err"] = float(np.linalg.norm(C.t - g.camera_from_base.t))
            ms = measure_detected(img, renderer.camera, det, g.rod_radius_m, seed=seed)
            res["meas_err"] = [_angle(m.u, u_true[m.leg, m.rod]) for m in ms if m.ok]
        out[name] = res
    return out


def summary(rec: list[dict]) -> dict:
    """Counts and percentiles (mrad, mm, ms) per condition."""
    out: dict = {"frames": len(rec)}
    for name in ("prior", "none"):
        rs = [r[name] for r in rec]
        ok = [x for x in rs if x["ok"]]
        s: dict = {
            "associated": len(ok),
            "ambiguous": sum(x["ambiguous"] for x in rs),
            "wrong": sum(max(x["dir_err"]) > 0.3 for x in ok),
            "time_ms": np.percentile([x["time"] * 1e3 for x in rs], [50, 90]).round(0).tolist(),
        }
        if ok:
            e = np.concatenate([x["dir_err"] for x in ok]) * 1e3
            m = np.concatenate([x["meas_err"] for x in ok]) * 1e3
            s["legs_per_frame"] = np.bincount([x["legs"] for x in ok], minlength=5).tolist()
            s["detected_mrad_p50_p90_p99_max"] = [*np.percentile(e, [50, 90, 99]).round(1).tolist(), round(e.max(), 1)]
            s["measured_mrad_p50_p90_p99_max"] = [*np.percentile(m, [50, 90, 99]).round(1).tolist(), round(m.max(), 1)]
            s["rods_measured"] = [len(m), 8 * len(rec)]
            rot = [x["rot_err"] * 1e3 for x in ok]
            s["placement_rot_mrad_p50_p90"] = np.percentile(rot, [50, 90]).round(0).tolist()
            s["placement_t_mm_p50_p90"] = np.percentile([x["t_err"] * 1e3 for x in ok], [50, 90]).round(0).tolist()
        out[name] = s
    bands = ((0.0, 0.02), (0.02, 0.06), (0.06, 0.09), (0.09, 1.0))
    out["none_associated_by_abs_Y_m"] = {
        f"{lo}-{hi}": [
            sum(r["none"]["ok"] for r in rec if lo <= abs(r["Y"]) < hi),
            sum(lo <= abs(r["Y"]) < hi for r in rec),
        ]
        for lo, hi in bands
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="51,52,53,54,55,56,61,62,63,64,65,66")
    ap.add_argument("--step", type=int, default=4, help="every step-th frame of each plan")
    ap.add_argument("--json", help="write the per-frame records and the summary there")
    args = ap.parse_args()
    g = BenchGeometry()
    seeds = [int(x) for x in args.seeds.split(",")]
    jobs = []
    for seed in seeds:
        tp = GeometricTwin(g).true_poses(make_plan("full", g.nominal, seed=seed))
        jobs += [(seed, k, tp[k]) for k in range(seed % args.step, len(tp), args.step)]
    rec = []
    renderers: dict[int, BenchRenderer] = {}
    with Progress(console=Console(stderr=True)) as bar:
        task = bar.add_task("frames", total=len(jobs))
        for seed, k, (phase, q, pose) in jobs:
            r = renderers.setdefault(seed, BenchRenderer(g, RenderSettings(), seed=seed))
            img = r.render(q, pose, np.random.default_rng([seed, k]))
            rec.append({"seed": seed, "frame": k, "phase": phase, **run_frame(g, r, q, pose, img, k)})
            bar.advance(task)
    s = summary(rec)
    Console().print_json(json.dumps(s))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"summary": s, "frames": rec}, f)


if __name__ == "__main__":
    main()
