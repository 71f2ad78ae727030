"""Benchmark (not a timed test): does the service keep answering while a run acquires, extracts and fits?

    /work/venv/bin/python benchmarks/bench_service.py [--paper-plan] [--workers 2] [--hz 20]

Starts ``i4cal serve`` (a real process, in-process simulated bench with the image-level renderer), starts a
'full' run with all three methods, and polls ``GET /api/v1/runs/{id}`` and ``GET /healthz`` at ``--hz`` from
this process until the run ends. Prints the latency p50/p99/max per run state (acquiring, extracting,
calibrating). The goal is < 50 ms.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

from service.auth import hash_token

TOKEN = "bench-token-0123456789"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--paper-plan", action="store_true", help="the paper-size plan (default: a reduced one)")
    ap.add_argument("--workers", type=int, default=2, help="extraction processes")
    ap.add_argument("--hz", type=float, default=20.0)
    args = ap.parse_args()
    print_latencies(measure(args.paper_plan, args.workers, args.hz))
    return 0


def measure(paper_plan: bool = False, workers: int = 2, hz: float = 20.0) -> dict[str, dict[str, list[float]]]:
    """Latencies (ms) of ``{run state: {"status" | "health": [...]}}`` polled while a run goes (also used by
    ``i4cal bench speed``)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    tmp = Path(tempfile.mkdtemp(prefix="i4cal-bench-"))
    sizes = "" if paper_plan else ("[plan_sizes]\nn_base = 6\nn_fit = 10\nn_lock = 4\nn_validation = 4\n"
                                        "line_samples = 11\n")
    cfg = tmp / "service.toml"
    cfg.write_text(f'data_dir = "{tmp / "data"}"\nport = {port}\nsim_bench = true\n'
                   f'extraction_workers = {workers}\ntoken_hashes = ["{hash_token(TOKEN)}"]\n{sizes}')
    proc = subprocess.Popen([sys.executable, "-m", "service", "serve", "--config", str(cfg), "--log-level", "warning"],
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{port}"
    lat: dict[str, dict[str, list[float]]] = {}
    try:
        with httpx.Client(base_url=url, timeout=10) as c:
            for _ in range(600):
                try:
                    if c.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    time.sleep(0.05)
            r = c.post("/api/v1/runs", json={"plan": "full", "methods": ["combined", "end-effector", "legs"]},
                       headers={"Authorization": f"Bearer {TOKEN}"})
            r.raise_for_status()
            rid = r.json()["id"]
            t_start = time.perf_counter()
            state = "queued"
            while True:
                t0 = time.perf_counter()
                run = c.get(f"/api/v1/runs/{rid}").json()
                t1 = time.perf_counter()
                c.get("/healthz")
                t2 = time.perf_counter()
                state = run["state"]
                d = lat.setdefault(state, {"status": [], "health": []})
                d["status"].append((t1 - t0) * 1e3)
                d["health"].append((t2 - t1) * 1e3)
                if state in ("done", "failed", "aborted", "interrupted"):
                    break
                time.sleep(max(0.0, 1.0 / hz - (time.perf_counter() - t0)))
            total = time.perf_counter() - t_start
            print(f"run {rid}: {state} in {total:.1f} s; timings {run['timings']}")
            if run.get("error"):
                print("error:", run["error"])
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    return lat


def print_latencies(lat: dict[str, dict[str, list[float]]]) -> None:
    print(f"{'state':<12} {'endpoint':<8} {'n':>5} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for st, d in lat.items():
        for ep, xs in d.items():
            xs = sorted(xs)
            p99 = xs[min(len(xs) - 1, round(0.99 * (len(xs) - 1)))]
            print(f"{st:<12} {ep:<8} {len(xs):>5} {statistics.median(xs):>8.1f} {p99:>8.1f} {xs[-1]:>8.1f}")


if __name__ == "__main__":
    sys.exit(main())
