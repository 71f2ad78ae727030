"""Benchmark (not a timed test): does the service keep answering while a run acquires, extracts and fits?

    /work/venv/bin/python benchmarks/bench_service.py [--paper-plan] [--workers 2] [--hz 20] [--worst 10]
                                                      [--sim-process] [--predict-clients N]

Starts ``i4cal serve`` (a real process, ``sim_bench = true``: the service starts the simulated bench, image-level
renderer, as its child process; with ``--sim-process`` the bench is ``i4cal sim-bench`` started beside the service and
named in a bench file, as real devices would be), starts a
'full' run with all three methods, and polls ``GET /api/v1/runs/{id}`` and ``GET /healthz`` at ``--hz`` from
this process until the run ends. Prints the latency p50/p99/max per run state (acquiring, extracting,
calibrating) and the worst samples with their time since the run started (to find what caused them). The goal is
< 50 ms. ``--predict-clients N``: meanwhile N clients post ``POST /api/v1/plans/predict`` (the paper plan, seconds of
CPU each) back to back with a token, as a heavy load of requests; their answers are counted (200, 429 when the
heavy-request pool's queue is full).
"""

from __future__ import annotations

import argparse
import gc
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

from service.auth import hash_token

TOKEN = "bench-token-0123456789"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--paper-plan", action="store_true", help="the paper-size plan (default: a reduced one)")
    ap.add_argument("--workers", type=int, default=2, help="extraction processes")
    ap.add_argument("--hz", type=float, default=20.0)
    ap.add_argument("--worst", type=int, default=10, help="print this many of the slowest samples")
    ap.add_argument(
        "--sim-process",
        action="store_true",
        help="start the simulated bench separately (i4cal sim-bench) and give the service a bench file",
    )
    ap.add_argument("--predict-clients", type=int, default=0, help="clients posting plan predictions during the run")
    args = ap.parse_args()
    samples: list[Sample] = []
    lat = measure(
        args.paper_plan,
        args.workers,
        args.hz,
        samples=samples,
        sim_process=args.sim_process,
        predict_clients=args.predict_clients,
    )
    print_latencies(lat)
    print_worst(samples, args.worst)
    return 0


@dataclass
class Sample:
    """One poll: seconds since the run was started, the run's state, the two latencies (ms), and how long the
    service's main thread (its event loop) waited for a CPU during the poll (ms, Linux schedstat; None elsewhere):
    a slow poll that waited as long for a CPU was slowed by the machine's load, not by the service's own work."""

    t_s: float
    state: str
    status_ms: float
    health_ms: float
    cpu_wait_ms: float | None = None
    where: str = ""  # the run's phase and progress at the poll


def runqueue_wait_ms(pid: int) -> float | None:
    """Total time the main thread of ``pid`` has waited on a run queue, ms (``/proc/PID/schedstat``)."""
    try:
        return int(Path(f"/proc/{pid}/schedstat").read_text().split()[1]) / 1e6
    except (OSError, IndexError, ValueError):
        return None


def cpu_seconds(pid: int) -> float | None:
    """CPU time (user + system, s) the process ``pid`` itself used so far, its children not included."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def free_port(span: int = 1) -> int:
    """A loopback TCP port ``p`` such that ``p .. p + span - 1`` are free (at the time of asking)."""
    for _ in range(100):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port + span > 65535:
            continue
        try:
            for k in range(1, span):
                with socket.socket() as s2:
                    s2.bind(("127.0.0.1", port + k))
        except OSError:
            continue
        return port
    raise RuntimeError("no free port range")


def start_sim_bench(tmp: Path) -> tuple[subprocess.Popen, Path, Path]:
    """``i4cal sim-bench`` as its own process; returns it, a bench file pointing at it and its camera file."""
    from drivers.sim.render import RenderSettings

    base = free_port(3)
    sim = subprocess.Popen(
        [sys.executable, "-m", "service", "sim-bench", "--port", str(base)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert sim.stdout is not None
    uris: dict[str, str] = {}
    while len(uris) < 3:
        line = sim.stdout.readline()
        if not line:
            raise RuntimeError("i4cal sim-bench exited")
        if " = " in line:
            k, v = line.strip().split(" = ", 1)
            uris[k] = v
    bench = tmp / "bench.toml"
    bench.write_text(
        f'name = "sim"\n[actuators]\nuri = "{uris["actuators"]}"\nspeed_m_s = 10.0\n'
        f'accel_m_s2 = 1000.0\ntimeout_s = 0.5\npoll_s = 0.001\n[camera]\nuri = "{uris["camera"]}"\n'
        f'timeout_s = 10.0\n[operator]\nuri = "{uris["operator"]}"\n[acquisition]\nline_rate_hz = 50.0\n'
    )
    camera = tmp / "camera.json"
    RenderSettings().camera().save(camera)
    return sim, bench, camera


def start_full_run(c: httpx.Client, ready_s: float = 60.0) -> str:
    """Wait for the service behind ``c`` to be ready (``/readyz``, up to ``ready_s``), start a run of the full plan
    with the three methods and return its id."""
    for _ in range(int(ready_s / 0.05)):
        try:
            if c.get("/readyz").status_code == 200:
                break
        except httpx.TransportError:
            pass
        time.sleep(0.05)
    r = c.post(
        "/api/v1/runs",
        json={"plan": "full", "methods": ["combined", "end-effector", "legs"]},
        headers={"Authorization": f"Bearer {TOKEN}"},
    )
    r.raise_for_status()
    return str(r.json()["id"])


def measure(
    paper_plan: bool = False,
    workers: int = 2,
    hz: float = 20.0,
    *,
    samples: list[Sample] | None = None,
    sim_process: bool = False,
    predict_clients: int = 0,
) -> dict[str, dict[str, list[float]]]:
    """Latencies (ms) of ``{run state: {"status" | "health": [...]}}`` polled while a run goes (also used by
    ``i4cal bench speed``); ``samples``, when given, receives every poll in order. ``sim_process``: the simulated
    bench is started here (``i4cal sim-bench``) and the service gets a bench file, instead of ``sim_bench = true``.
    ``predict_clients``: that many threads post plan predictions back to back while the run goes."""
    port = free_port()
    tmp = Path(tempfile.mkdtemp(prefix="i4cal-bench-"))
    sizes = (
        ""
        if paper_plan
        else ("[plan_sizes]\nn_base = 6\nn_fit = 10\nn_lock = 4\nn_validation = 4\nline_samples = 11\n")
    )
    sim = None
    if sim_process:
        sim, bench_file, camera_file = start_sim_bench(tmp)
        where = f'bench_file = "{bench_file}"\ncamera_file = "{camera_file}"\n'
    else:
        where = "sim_bench = true\n"
    cfg = tmp / "service.toml"
    cfg.write_text(
        f'data_dir = "{tmp / "data"}"\nport = {port}\n{where}'
        f'extraction_workers = {workers}\ntoken_hashes = ["{hash_token(TOKEN)}"]\n{sizes}'
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", "serve", "--config", str(cfg), "--log-level", "warning"],
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    url = f"http://127.0.0.1:{port}"
    lat: dict[str, dict[str, list[float]]] = {}
    try:
        with httpx.Client(base_url=url, timeout=10) as c:
            rid = start_full_run(c)
            stop = threading.Event()
            answers: dict[int, int] = {}
            loaders = [
                threading.Thread(target=_predict_load, args=(url, stop, answers), daemon=True)
                for _ in range(predict_clients)
            ]
            for t in loaders:
                t.start()
            # this process's own garbage collections (~150 ms for a full one) would be counted as the service's
            gc.collect()
            gc.disable()
            cpu0 = cpu_seconds(proc.pid)
            t_start = time.perf_counter()
            state = "queued"
            while True:
                w0 = runqueue_wait_ms(proc.pid)
                t0 = time.perf_counter()
                run = c.get(f"/api/v1/runs/{rid}").json()
                t1 = time.perf_counter()
                c.get("/healthz")
                t2 = time.perf_counter()
                state = run["state"]
                d = lat.setdefault(state, {"status": [], "health": []})
                d["status"].append((t1 - t0) * 1e3)
                d["health"].append((t2 - t1) * 1e3)
                if samples is not None:
                    w1 = runqueue_wait_ms(proc.pid)
                    pr = run.get("progress") or {}
                    samples.append(
                        Sample(
                            t0 - t_start,
                            state,
                            (t1 - t0) * 1e3,
                            (t2 - t1) * 1e3,
                            None if w0 is None or w1 is None else w1 - w0,
                            f"{pr.get('phase', '')} {pr.get('done', '')}/{pr.get('total', '')}",
                        )
                    )
                if state in ("done", "failed", "aborted", "interrupted"):
                    break
                time.sleep(max(0.0, 1.0 / hz - (time.perf_counter() - t0)))
            gc.enable()
            stop.set()
            for t in loaders:
                t.join(60)
            total = time.perf_counter() - t_start
            cpu1 = cpu_seconds(proc.pid)
            print(f"run {rid}: {state} in {total:.1f} s; timings {run['timings']}")
            if cpu0 is not None and cpu1 is not None:
                print(f"CPU time of the server process during the run: {cpu1 - cpu0:.1f} s (its children not counted)")
            if predict_clients:
                print(f"predictions posted by {predict_clients} clients during the run, by status: {answers}")
            if run.get("error"):
                print("error:", run["error"])
    finally:
        gc.enable()
        for p in (proc, sim):
            if p is None:
                continue
            p.send_signal(signal.SIGTERM if p is proc else signal.SIGINT)
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)  # the run's dataset (~100 MB of frames for the paper plan)
    return lat


def _predict_load(url: str, stop: threading.Event, answers: dict[int, int]) -> None:
    """Post plan predictions back to back until ``stop``; count the answers by status (a 429 waits Retry-After)."""
    with httpx.Client(base_url=url, timeout=120) as c:
        while not stop.is_set():
            try:
                r = c.post(
                    "/api/v1/plans/predict",
                    json={"plan": "full", "methods": ["combined", "end-effector", "legs"]},
                    headers={"Authorization": f"Bearer {TOKEN}"},
                )
            except httpx.TransportError:
                return
            answers[r.status_code] = answers.get(r.status_code, 0) + 1
            if r.status_code == 429:
                stop.wait(float(r.headers.get("retry-after", "1")))


def print_latencies(lat: dict[str, dict[str, list[float]]]) -> None:
    print(f"{'state':<12} {'endpoint':<8} {'n':>5} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for st, d in lat.items():
        for ep, xs in d.items():
            xs = sorted(xs)
            p99 = xs[min(len(xs) - 1, round(0.99 * (len(xs) - 1)))]
            print(f"{st:<12} {ep:<8} {len(xs):>5} {statistics.median(xs):>8.1f} {p99:>8.1f} {xs[-1]:>8.1f}")


def print_worst(samples: list[Sample], n: int = 10) -> None:
    """The ``n`` slowest polls (by the slower of the two requests), with when they happened."""
    if n <= 0 or not samples:
        return
    print(f"slowest {n} polls:  t (s)  state        status ms  health ms  waited for a CPU ms  phase")
    for s in sorted(samples, key=lambda s: -max(s.status_ms, s.health_ms))[:n]:
        wait = "" if s.cpu_wait_ms is None else f"{s.cpu_wait_ms:>9.1f}"
        print(f"{'':>18}{s.t_s:>6.1f}  {s.state:<12} {s.status_ms:>9.1f}  {s.health_ms:>9.1f}  {wait:>19}  {s.where}")


if __name__ == "__main__":
    sys.exit(main())
