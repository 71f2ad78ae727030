"""``i4cal bench speed``: the speed figures of this machine in one table (and ``--json PATH``).

Sections (``--only a,b``; all by default), each with the target of the issue it comes from:

* ``extraction``: board pose + eight rods on one rendered 1024x768 frame, single process (median ms;
  target <= 20 ms).
* ``extract-calibrate``: ``extract`` (all cores) + ``calibrate --method all`` of the paper-sized rendered
  dataset (s; target <= 5 s), and the peak memory of that run (resident memory of the process and its
  extraction workers together, sampled; target <= 500 MB). It runs in a fresh process, so that what the
  other sections allocated is not counted.
* ``fit``: each method's fit on the paper-sized observations of the geometric twin (median ms).
* ``acquisition``: time per pose beyond the simulated motion itself (command, polling, grab, write) on the
  simulated bench over Modbus TCP (median ms; target <= 30 ms); the camera serves a constant image unless
  ``--real-renderer``.
* ``modbus``: round trip of a 4-register read over TCP loopback, plain pymodbus client and through the
  checked driver (median ms).
* ``service``: latency of ``GET /api/v1/runs/{id}`` while a run acquires, extracts and calibrates in
  ``i4cal serve`` (p50 / p99 ms; target p99 <= 50 ms); measured by ``benchmarks/bench_service.py`` of a
  source checkout.
* ``result-after-motion``: a service run (``i4cal serve``, ``i4cal sim-bench`` in its own process, a camera file made
  by ``i4cal camera calibrate`` on it, which the rods refine) of the paper's plan (``--service-plan``) at the speeds
  of ``deploy/bench-real.example.toml``, all three methods: seconds from the run's last frame event to its stored
  result, with the frames measured during the motion (``stream_extraction``, ``fit_workers = 2``; target <= 2 s) and
  without (the extraction and fits after the motion, one fit at a time); ``--stream-runs off,on`` picks them.

Figures in ms, s and MB (display units); a section that fails is reported and the others still run.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import importlib.util
import json
import math
import os
import platform
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, cast

from pydantic import BaseModel, Field, computed_field

from calib.errors import I4calError, InputError

FORMAT = "i4cal.bench-speed/1"
SECTIONS = ("extraction", "extract-calibrate", "fit", "acquisition", "modbus", "service", "result-after-motion")
ALIASES = {
    "extract_calibrate": "extract-calibrate",
    "calibrate": "extract-calibrate",
    "memory": "extract-calibrate",
    "frame": "extraction",
    "acquire": "acquisition",
    "stream": "result-after-motion",
    "streaming": "result-after-motion",
}
FINAL_STATES = ("done", "failed", "aborted", "interrupted")

#: ``step(description, done, total)``: what a section is doing (``total`` None: no known end).
Step = Callable[[str, float, "float | None"], None]


def _no_step(description: str, done: float, total: float | None) -> None:
    return None


class Figure(BaseModel):
    """One measured figure, in display units, with the target it must not exceed (if any)."""

    key: str
    section: str
    label: str
    value: float
    unit: str
    target: float | None = None
    detail: str = ""

    @computed_field  # type: ignore[prop-decorator]
    @property
    def met(self) -> bool | None:
        return None if self.target is None else self.value <= self.target


class SpeedOptions(BaseModel):
    """Sizes of the measurements (defaults: the figures reported in the README)."""

    frames: int = Field(30, ge=1, description="rendered frames timed one by one (extraction)")
    dataset: str | None = Field(None, description="dataset v1 to extract (default: render the paper's plan)")
    workers: int | None = Field(None, ge=1, description="extraction processes (default: all cores)")
    poses: int = Field(40, ge=2, description="poses of the acquisition run")
    real_renderer: bool = Field(False, description="acquisition: render frames instead of a constant image")
    reads: int = Field(1000, ge=10, description="Modbus reads timed per client")
    fit_repeats: int = Field(5, ge=1, description="fits timed per method")
    service_plan: str = Field("paper", pattern="^(paper|reduced)$")
    service_hz: float = Field(20.0, gt=0, description="status polls per second during the service run")
    stream_runs: list[Literal["on", "off"]] = Field(
        default_factory=lambda: cast(list[Literal["on", "off"]], ["on", "off"]),
        description="result-after-motion: the runs, streaming on and/or off",
    )
    seed: int = 0


class SpeedReport(BaseModel):
    """What ``i4cal bench speed`` measured (``--json``: :meth:`to_json`)."""

    format: str = FORMAT
    machine: dict[str, Any]
    sections: list[str]
    options: SpeedOptions
    figures: list[Figure] = Field(default_factory=list)
    details: dict[str, dict[str, Any]] = Field(default_factory=dict)
    errors: dict[str, str] = Field(default_factory=dict)
    elapsed_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        """The JSON document: ``figures`` keyed by figure key."""
        d = self.model_dump()
        d["figures"] = {f.pop("key"): f for f in d["figures"]}
        return d


# -- helpers ---------------------------------------------------------------------------------------
def machine_info() -> dict[str, Any]:
    """Where the figures come from: CPU, cores, OS, Python, i4cal version, date."""
    from service import __version__

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu": cpu,
        "cores": cores,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "i4cal": __version__,
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }


def percentile(xs: list[float], q: float) -> float:
    """Linear-interpolated percentile ``q`` (0-100) of ``xs``."""
    import numpy as np

    return float(np.percentile(np.asarray(xs, dtype=float), q))


def _children(pid: int) -> list[int]:
    out: list[int] = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(x) for x in f.read().split()]
    except OSError:
        pass
    return out


def tree_rss_bytes(pid: int) -> int:
    """Resident memory (bytes) of process ``pid`` and all its descendants (Linux ``/proc``; 0 elsewhere)."""
    page = os.sysconf("SC_PAGE_SIZE")
    total, todo, seen = 0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * page
        except (OSError, ValueError, IndexError):
            continue
        todo += _children(p)
    return total


class RssSampler:
    """Samples :func:`tree_rss_bytes` of this process every ``period_s`` in a thread; ``peak_mb`` is the maximum."""

    def __init__(self, period_s: float = 0.02) -> None:
        self.period_s = period_s
        self.peak_bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)

    def _run(self) -> None:
        pid = os.getpid()
        while True:
            self.peak_bytes = max(self.peak_bytes, tree_rss_bytes(pid))
            if self._stop.wait(self.period_s):
                return

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        self.peak_bytes = max(self.peak_bytes, tree_rss_bytes(os.getpid()))

    @property
    def peak_mb(self) -> float:
        return self.peak_bytes / 2**20


class ConstantRenderer:
    """A constant 1024x768 8-bit image (seeded noise): the acquisition figure without rendering time."""

    def __init__(self, seed: int = 0) -> None:
        import numpy as np

        rng = np.random.default_rng(seed)
        self.img = (rng.random((768, 1024)) * 40 + 100).astype(np.uint8)

    def render(self, q_true: Any, pose_true: Any) -> Any:
        return self.img


# -- extraction --------------------------------------------------------------------------------------
def frame_times(n: int, step: Step = _no_step, seed: int = 0, floor: list[float] | None = None) -> list[float]:
    """Board pose + eight rods on ``n`` rendered 1024x768 frames of the paper's plan, single process; ``floor``, when
    given, receives OpenCV's ``detectBoard`` time on each of the same frames (:func:`opencv_board_times`).

    Returns
    -------
    list of float
        Seconds per frame (rendering excluded).
    """
    from calib.formats.plan import make_plan
    from calib.vision.board import BoardDetector
    from calib.vision.rods import image_ideal_bbox, measure_rods, predict_rods
    from drivers.sim.render import BenchRenderer, RenderSettings
    from drivers.sim.twin import BenchGeometry, GeometricTwin

    g = BenchGeometry()
    r = BenchRenderer(g, RenderSettings(), seed=seed)
    cam = r.camera
    det = BoardDetector(r.settings.board)
    box = image_ideal_bbox(cam)
    tp = GeometricTwin(g).true_poses(make_plan("full", g.nominal, seed=seed))[:n]
    imgs = []
    for k, (_, q, pose) in enumerate(tp):
        step("extraction: rendering frames", k, len(tp))
        imgs.append((q, r.render(q, pose)))
    times = []
    for k, (q, img) in enumerate(imgs):
        step("extraction: board + 8 rods per frame", k, len(imgs))
        t0 = time.perf_counter()
        bp = det.measure(img, cam)
        occ = []
        if not isinstance(bp, str):
            oc = det.outline_camera(bp.R, bp.t, margin_m=0.028)
            occ.append(cam.to_ideal_pixels(oc[:, :2] / oc[:, 2:3]))
        preds = predict_rods(g.nominal, q, g.camera_from_base, g.rod_spacing_m)
        measure_rods(img, cam, preds, g.rod_radius_m, occluders=occ, ideal_bbox=box)
        times.append(time.perf_counter() - t0)
    if floor is not None:  # the same frames, OpenCV alone
        floor.extend(opencv_board_times([img for _, img in imgs], r.settings.board, step))
    return times


def opencv_board_times(images: list[Any], board: Any, step: Step = _no_step) -> list[float]:
    """OpenCV's own ``cv2.aruco.CharucoDetector.detectBoard`` on each image (the library's floor for a frame): the
    detector :class:`calib.vision.board.BoardDetector` builds (its board, sub-pixel corner refinement, markers
    refined), called alone: no pose, no rods.

    Returns
    -------
    list of float
        Seconds per frame.
    """
    from calib.vision.board import BoardDetector

    detector = BoardDetector(board).detector
    out = []
    for k, img in enumerate(images):
        step("extraction: OpenCV detectBoard per frame", k, len(images))
        t0 = time.perf_counter()
        detector.detectBoard(img)
        out.append(time.perf_counter() - t0)
    return out


def bench_extraction(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    floor: list[float] = []
    t = frame_times(opts.frames, step, seed=opts.seed, floor=floor)
    ms = [x * 1e3 for x in t]
    floor_ms = [x * 1e3 for x in floor]
    cv_fig = Figure(
        key="extraction_opencv_detect_board_median_ms",
        section="extraction",
        value=statistics.median(floor_ms),
        unit="ms",
        label="OpenCV CharucoDetector.detectBoard alone on the same frames (median; the library floor)",
        detail=f"extraction / detectBoard: {statistics.median(ms) / statistics.median(floor_ms):.1f}x",
    )
    fig = Figure(
        key="extraction_frame_median_ms",
        section="extraction",
        value=statistics.median(ms),
        unit="ms",
        label="board + 8 rods per 1024x768 frame, one process (median)",
        target=20.0,
        detail=f"{len(ms)} frames, min {min(ms):.1f}, max {max(ms):.1f} ms",
    )
    return [fig, cv_fig], {"frame_ms": ms, "opencv_detect_board_ms": floor_ms}


def _extract_calibrate_job(queue: Any, dataset: str, workers: int | None, start_method: str | None = None) -> None:
    """Body of the fresh process of :func:`extract_calibrate`: puts ("progress", done, total) messages, then
    ("result", dict) or ("error", text).

    ``start_method``: how the extraction starts its worker processes, the caller's (what ``i4cal extract`` does on
    this platform), not the "spawn" of this process, which would time interpreter start-ups instead of extraction.
    """
    try:
        if start_method:
            import multiprocessing as mp

            mp.set_start_method(start_method, force=True)
        from calib.formats.observations import Observations
        from calib.identify.pipeline import calibrate
        from calib.vision.extract import extract_dataset

        def progress(done: int, total: int) -> None:
            queue.put(("progress", done, total))

        with RssSampler() as rss:
            t0 = time.perf_counter()
            res = extract_dataset(dataset, workers=workers, progress=progress)
            t1 = time.perf_counter()
            queue.put(("progress", -1, None))
            doc = calibrate(Observations.from_dict(res.observations))
            t2 = time.perf_counter()
        failed = {k: e.get("error") for k, e in doc["methods"].items() if not e.get("parameters")}
        n_workers = workers or os.cpu_count() or 1
        main_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        worker_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        queue.put(
            (
                "result",
                {
                    "extract_s": t1 - t0,
                    "calibrate_s": t2 - t1,
                    "frames": len(res.observations["frames"]),
                    "workers": n_workers,
                    "peak_main_mb": main_mb,
                    "peak_largest_worker_mb": worker_mb,
                    # without /proc: the upper bound (every worker at its largest peak at the main's peak)
                    "peak_tree_mb": rss.peak_mb or main_mb + (n_workers if n_workers > 1 else 0) * worker_mb,
                    "peak_sampled": rss.peak_mb > 0,
                    "methods_failed": failed,
                },
            )
        )
    except BaseException as exc:
        queue.put(("error", f"{type(exc).__name__}: {exc}"))


def extract_calibrate(dataset: str | Path, workers: int | None = None, step: Step = _no_step) -> dict[str, Any]:
    """Time ``extract`` + ``calibrate --method all`` of ``dataset`` in a fresh (spawned) process.

    Returns
    -------
    dict
        ``extract_s``, ``calibrate_s`` (s), ``frames``, ``workers``, ``peak_tree_mb`` (peak resident memory of
        the process and its workers together, MB), ``peak_main_mb``, ``peak_largest_worker_mb``.
    """
    import multiprocessing as mp
    import queue as queue_mod

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(
        target=_extract_calibrate_job,
        args=(q, str(dataset), workers, mp.get_start_method()),
        name="i4cal-bench-extract",
    )
    proc.start()
    try:
        while True:
            try:
                msg = q.get(timeout=1.0)
            except queue_mod.Empty:
                if not proc.is_alive():
                    raise I4calError(f"the extract + calibrate process died (exit code {proc.exitcode})") from None
                continue
            if msg[0] == "progress":
                if msg[1] < 0:
                    step("extract-calibrate: calibrate --method all", 0, None)
                else:
                    step("extract-calibrate: extract", msg[1], msg[2])
            elif msg[0] == "error":
                raise I4calError(f"extract + calibrate: {msg[1]}")
            else:
                return msg[1]
    finally:
        proc.join(timeout=30)
        if proc.is_alive():
            proc.kill()


def bench_extract_calibrate(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="i4cal-bench-") as tmp:
        details: dict[str, Any] = {}
        if opts.dataset:
            ds = Path(opts.dataset)
            details["dataset"] = str(ds)
        else:
            from drivers.sim.rendered_dataset import simulate_dataset

            t0 = time.perf_counter()
            ds = simulate_dataset(
                Path(tmp) / "ds",
                seed=opts.seed,
                progress=lambda d, n: step("extract-calibrate: rendering the dataset", d, n),
            )
            details["dataset"] = "paper's plan, rendered"
            details["render_s"] = time.perf_counter() - t0
        r = extract_calibrate(ds, opts.workers, step)
    details.update(r)
    total = r["extract_s"] + r["calibrate_s"]
    figs = [
        Figure(
            key="extract_calibrate_s",
            section="extract-calibrate",
            value=total,
            unit="s",
            target=5.0,
            label=f"extract ({r['workers']} processes) + calibrate all, paper-sized dataset",
            detail=f"{r['frames']} frames; extract {r['extract_s']:.2f} s, calibrate {r['calibrate_s']:.2f} s",
        ),
        Figure(
            key="peak_memory_mb",
            section="extract-calibrate",
            value=r["peak_tree_mb"],
            unit="MB",
            target=500.0,
            label="peak memory of extract + calibrate (process + workers)",
            detail=f"main {r['peak_main_mb']:.0f} MB, largest worker {r['peak_largest_worker_mb']:.0f} MB",
        ),
    ]
    if r["methods_failed"]:
        details["warning"] = f"methods failed: {r['methods_failed']}"
    return figs, details


# -- fits ----------------------------------------------------------------------------------------------
def fit_times(repeats: int = 5, seed: int = 0, step: Step = _no_step) -> dict[str, list[float]]:
    """Seconds per fit of each method on the paper-sized observations of the geometric twin (default noise)."""
    from calib.formats.observations import Observations
    from calib.formats.plan import make_plan
    from calib.identify.baseframe import base_frame_from_observations
    from calib.identify.pipeline import METHOD_NAMES, run_method
    from calib.model.parameters import NOMINAL
    from drivers.sim.twin import GeometricTwin

    obs = Observations.from_dict(GeometricTwin().observations(plan=make_plan("full", NOMINAL, seed=seed), seed=seed))
    bf = base_frame_from_observations(obs)
    out: dict[str, list[float]] = {}
    n = len(METHOD_NAMES) * repeats
    for i, name in enumerate(METHOD_NAMES):
        out[name] = []
        for k in range(repeats):
            step(f"fit: {name}", i * repeats + k, n)
            t0 = time.perf_counter()
            run_method(name, obs, bf)
            out[name].append(time.perf_counter() - t0)
    return out


def bench_fit(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    t = fit_times(opts.fit_repeats, opts.seed, step)
    figs = [
        Figure(
            key=f"fit_{name.replace('-', '_')}_ms",
            section="fit",
            unit="ms",
            value=statistics.median(xs) * 1e3,
            label=f"fit, {name} method (median)",
            detail=f"{len(xs)} fits, paper-sized observations (geometric twin)",
        )
        for name, xs in t.items()
    ]
    return figs, {"fit_ms": {k: [x * 1e3 for x in v] for k, v in t.items()}}


# -- Modbus and acquisition on the simulated bench -------------------------------------------------------
async def modbus_round_trips(reads: int = 1000, step: Step = _no_step) -> dict[str, list[float]]:
    """Seconds per read of 4 holding registers over TCP loopback from the simulated controller.

    Returns
    -------
    dict
        ``raw`` (a plain pymodbus client), ``driver`` (:class:`drivers.devices.modbus.ModbusActuators`, checked
        replies),
        ``status`` (the driver's status of the four axes: four reads).
    """
    from pymodbus.client import AsyncModbusTcpClient

    from drivers.acquisition.config import open_actuators
    from drivers.devices.modbus import ModbusActuators
    from drivers.sim.bench import SimBench, fast_axis_config

    out: dict[str, list[float]] = {"raw": [], "driver": [], "status": []}
    async with SimBench(port=0, axis_config=fast_axis_config(), renderer=ConstantRenderer(), rtu=False) as b:
        if b.tcp_address is None:
            raise I4calError("the simulated controller serves no TCP port")
        host, port = b.tcp_address
        client = AsyncModbusTcpClient(host, port=port, timeout=1.0)
        if not await client.connect():
            raise I4calError(f"cannot connect to the simulated controller at {host}:{port}")
        try:
            for k in range(reads):
                if k % 50 == 0:
                    step("modbus: plain pymodbus client", k, reads)
                t = time.perf_counter()
                rr = await client.read_holding_registers(5, count=4, device_id=1)
                out["raw"].append(time.perf_counter() - t)
                if rr.isError() or len(rr.registers) != 4:
                    raise I4calError(f"bad reply from the simulated controller: {rr}")
        finally:
            client.close()
        act = open_actuators(b.bench_config())
        if not isinstance(act, ModbusActuators):
            raise I4calError(f"the simulated bench's actuators are no Modbus driver: {type(act).__name__}")
        await act.connect()
        try:
            for k in range(reads):
                if k % 50 == 0:
                    step("modbus: through the driver", k, reads)
                t = time.perf_counter()
                await act.read(1, 5, 4)
                out["driver"].append(time.perf_counter() - t)
            for _ in range(max(10, reads // 5)):
                t = time.perf_counter()
                await act.status()
                out["status"].append(time.perf_counter() - t)
        finally:
            await act.close()
    return out


def bench_modbus(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    r = asyncio.run(modbus_round_trips(opts.reads, step))
    ms = {k: [x * 1e3 for x in v] for k, v in r.items()}
    figs = [
        Figure(
            key="modbus_round_trip_median_ms",
            section="modbus",
            unit="ms",
            value=statistics.median(ms["raw"]),
            label="Modbus TCP loopback round trip, read 4 registers (median)",
            detail=f"plain pymodbus client, {len(ms['raw'])} reads, p90 {percentile(ms['raw'], 90):.3f} ms",
        ),
        Figure(
            key="modbus_driver_round_trip_median_ms",
            section="modbus",
            unit="ms",
            value=statistics.median(ms["driver"]),
            label="the same through the checked driver (median)",
            detail=f"status of the 4 axes {statistics.median(ms['status']):.2f} ms",
        ),
    ]
    return figs, {
        k: {"median_ms": statistics.median(v), "p90_ms": percentile(v, 90), "n": len(v)} for k, v in ms.items()
    }


def motion_time(d: float, v: float, a: float) -> float:
    """Duration (s) of a trapezoidal (or triangular) move of ``d`` m at speed ``v`` m/s, acceleration ``a`` m/s^2."""
    if d <= 0:
        return 0.0
    return d / v + v / a if d >= v * v / a else 2 * math.sqrt(d / a)


async def acquisition_overheads(
    n_poses: int = 40, real_renderer: bool = False, seed: int = 0, step: Step = _no_step
) -> dict[str, Any]:
    """Run a ``pose-set`` plan on the simulated bench (Modbus TCP) and time each pose.

    Returns
    -------
    dict
        ``overhead_s`` (per pose after the first: wall time minus the simulated motion of the axis that travels
        furthest), ``record_s`` (in position -> written), ``total_s``, ``poses``.
    """
    import numpy as np

    from calib.formats.plan import Plan, pose_set
    from calib.model.parameters import NOMINAL
    from drivers.acquisition.acquire import acquisition_from_config, close_devices
    from drivers.sim.bench import SimBench, fast_axis_config

    cfgax = fast_axis_config()
    renderer = None if real_renderer else ConstantRenderer(seed)
    async with SimBench(port=0, axis_config=cfgax, renderer=renderer, rtu=False, seed=seed) as b:
        cfg = b.bench_config()
        plan = Plan(name="pose-set", steps=pose_set(NOMINAL, n_poses, seed=3 + seed))
        with tempfile.TemporaryDirectory(prefix="i4cal-bench-") as tmp:
            acq = acquisition_from_config(
                plan, cfg, Path(tmp) / "ds", progress=lambda p: step("acquisition: poses", p.done, p.total)
            )
            try:
                t0 = time.perf_counter()
                await acq.run()
                total = time.perf_counter() - t0
            finally:
                await close_devices(acq)
    v, a = cfg.actuators.speed_m_s, cfgax.accel
    qs = [np.asarray(s.q) for s in plan.steps]
    over, rec = [], []
    for k in range(1, len(qs)):  # the first pose starts from home: skipped
        t_start, t_moved, t_end = acq.timings[k]
        d = float(np.max(np.abs(qs[k] - qs[k - 1])))
        over.append((t_end - t_start) - motion_time(d, v, a))
        rec.append(t_end - t_moved)
    return {"overhead_s": over, "record_s": rec, "total_s": total, "poses": len(qs)}


def bench_acquisition(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    r = asyncio.run(acquisition_overheads(opts.poses, opts.real_renderer, opts.seed, step))
    over = [x * 1e3 for x in r["overhead_s"]]
    rec = [x * 1e3 for x in r["record_s"]]
    image = "rendered frames" if opts.real_renderer else "constant 1024x768 image"
    fig = Figure(
        key="acquisition_overhead_median_ms",
        section="acquisition",
        unit="ms",
        value=statistics.median(over),
        target=30.0,
        label="acquisition overhead per pose beyond the motion (median)",
        detail=f"{r['poses']} poses, {image}; p90 {percentile(over, 90):.1f} ms; grab {statistics.median(rec):.1f} ms",
    )
    return [fig], {"overhead_ms": over, "record_ms": rec, "total_s": r["total_s"], "camera": image}


# -- service -------------------------------------------------------------------------------------------
def bench_service_module() -> Any:
    """``benchmarks/bench_service.py`` of the source checkout this package runs from (imported, not copied)."""
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_service.py"
    if not path.is_file():
        raise I4calError(
            f"the service latency benchmark is benchmarks/bench_service.py of a source checkout "
            f"(not found at {path}); install i4cal from a checkout (pip install -e .)"
        )
    name = "i4cal_bench_service"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # before running it: dataclasses look their module up there
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        del sys.modules[name]
        raise
    return mod


def bench_service(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    mod = bench_service_module()
    step(f"service: a run of the {opts.service_plan} plan in i4cal serve, status polled", 0, None)
    lat: dict[str, dict[str, list[float]]] = mod.measure(
        paper_plan=opts.service_plan == "paper", workers=opts.workers or os.cpu_count() or 1, hz=opts.service_hz
    )
    final = [s for s in lat if s in FINAL_STATES]
    if final != ["done"]:
        raise I4calError(
            f"the service run ended {', '.join(final) or 'without a final state'} (states seen: {', '.join(lat)})"
        )
    active = [x for s, d in lat.items() if s not in FINAL_STATES for x in d["status"]]
    if not active:
        raise I4calError("no status sample while the run was going")
    per_state = {
        s: {
            ep: {"n": len(xs), "p50_ms": percentile(xs, 50), "p99_ms": percentile(xs, 99), "max_ms": max(xs)}
            for ep, xs in d.items()
        }
        for s, d in lat.items()
    }
    worst = max((s for s in per_state if s not in FINAL_STATES), key=lambda s: per_state[s]["status"]["p99_ms"])
    detail = (
        f"{len(active)} polls at {opts.service_hz:g} Hz, {opts.service_plan} plan; worst p99 while "
        f"{worst}: {per_state[worst]['status']['p99_ms']:.1f} ms"
    )
    figs = [
        Figure(
            key="service_status_p50_ms",
            section="service",
            unit="ms",
            value=percentile(active, 50),
            label="service status latency while a run goes (p50)",
            detail=detail,
        ),
        Figure(
            key="service_status_p99_ms",
            section="service",
            unit="ms",
            value=percentile(active, 99),
            target=50.0,
            label="service status latency while a run goes (p99)",
            detail=f"max {max(active):.1f} ms",
        ),
    ]
    return figs, {"per_state": per_state, "plan": opts.service_plan}


# -- result after the motion ------------------------------------------------------------------------------
#: the real bench's example file, whose speeds the result-after-motion run uses
REAL_BENCH_EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "bench-real.example.toml"


def real_bench_speeds(path: Path = REAL_BENCH_EXAMPLE) -> dict[str, float]:
    """The motion settings of a bench file (``speed_m_s``, ``accel_m_s2``, ``poll_s``, ``settle_s``)."""
    import tomllib

    if not path.is_file():
        raise I4calError(f"the real bench's example file is {path} of a source checkout (not found)")
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    act = doc.get("actuators", {})
    return {
        "speed_m_s": float(act["speed_m_s"]),
        "accel_m_s2": float(act["accel_m_s2"]),
        "poll_s": float(act.get("poll_s", 0.01)),
        "settle_s": float(doc.get("acquisition", {}).get("settle_s", act.get("settle_s", 0.0))),
    }


def _event_s(ev: dict[str, Any]) -> float:
    return dt.datetime.fromisoformat(ev["t"].replace("Z", "+00:00")).timestamp()


def _after_motion_config(
    tmp: Path, mod: Any, speeds: dict[str, float], streaming: bool, paper_plan: bool, workers: int
) -> tuple[Any, Path, int]:
    """The simulated bench at ``speeds`` (:func:`real_bench_speeds`) and a service configuration for it: ``(sim
    process, service.toml, port)``. The camera file is made as a user makes it, ``i4cal camera calibrate`` on the
    bench: it carries its calibration's covariance, so the extraction refines the camera by the rods."""
    sim, bench_file, _ = mod.start_sim_bench(tmp)
    camera_file = tmp / "camera-calibrated.json"
    subprocess.run(
        [sys.executable, "-m", "service", "camera", "calibrate", "--bench", str(bench_file), "-o", str(camera_file)],
        check=True,
        capture_output=True,
    )
    text = bench_file.read_text()
    text = text.replace("speed_m_s = 10.0", f"speed_m_s = {speeds['speed_m_s']}")
    text = text.replace("accel_m_s2 = 1000.0", f"accel_m_s2 = {speeds['accel_m_s2']}")
    text = text.replace("poll_s = 0.001", f"poll_s = {speeds['poll_s']}\nhome_timeout_s = 120.0")
    text = text.replace("line_rate_hz = 50.0", f"settle_s = {speeds['settle_s']}")
    bench_file.write_text(text)
    port = mod.free_port()
    sizes = (
        "" if paper_plan else "[plan_sizes]\nn_base = 6\nn_fit = 10\nn_lock = 4\nn_validation = 4\nline_samples = 11\n"
    )
    cfg = tmp / "service.toml"
    cfg.write_text(
        f'data_dir = "{tmp / "data"}"\nport = {port}\nbench_file = "{bench_file}"\ncamera_file = "{camera_file}"\n'
        f"extraction_workers = {workers}\nfit_workers = {2 if streaming else 1}\n"
        f"stream_extraction = {'true' if streaming else 'false'}\n"
        f'token_hashes = ["{mod.hash_token(mod.TOKEN)}"]\n{sizes}'
    )
    return sim, cfg, port


def _run_to_the_end(port: int, mod: Any, label: str, step: Step) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A full-plan run of all three methods on the service at ``port``, followed to its end: ``(run, events)``."""
    import httpx

    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as c:
        rid = mod.start_full_run(c)
        while True:
            run = c.get(f"/api/v1/runs/{rid}").json()
            step(f"result-after-motion ({label}): {run['state']}", run["progress"]["done"], run["progress"]["total"])
            if run["state"] in FINAL_STATES:
                break
            time.sleep(0.5)
        if run["state"] != "done":
            raise I4calError(f"the run ({label}) ended {run['state']}: {run.get('error')}")
        events = []
        with c.stream("GET", f"/api/v1/runs/{rid}/events", params={"follow": "false"}) as resp:
            for line in resp.iter_lines():
                if line.startswith("data: "):
                    events.append(json.loads(line[6:]))
    return run, events


def _stop(proc: subprocess.Popen, sim: Any, tmp: Path) -> None:
    proc.terminate()
    proc.wait(30)
    sim.send_signal(signal.SIGINT)
    try:
        sim.wait(10)
    except Exception:
        sim.kill()
    shutil.rmtree(tmp, ignore_errors=True)


def _after_motion_timings(run: dict[str, Any], events: list[dict[str, Any]], label: str) -> dict[str, Any]:
    """The times of a finished run from its events: the last frame's progress event is the first that counts every
    frame written (frames are written behind the next move, the run's end waits for the last write)."""
    frames = [e for e in events if e["type"] == "progress" and e["data"].get("stage") == "acquisition"]
    total = max(e["data"]["total"] for e in frames)
    last = next((e for e in frames if e["data"]["done"] == total), None)
    first = next((e for e in frames if e["data"]["done"] >= 1), None)
    end = next((e for e in events if e["type"] == "state" and e["data"]["state"] == "done"), None)
    if last is None or first is None or end is None:
        raise I4calError(f"the run ({label}) has no last frame or end event: {[e['type'] for e in events][-20:]}")
    extraction: dict[str, Any] = next((e["data"] for e in events if e["type"] == "extraction"), {})
    streamed_items = [it for e in events if e["type"] == "streamed" for it in e["data"]["items"]]
    return {
        "after_last_frame_s": _event_s(end) - _event_s(last),
        "motion_s": _event_s(last) - _event_s(first),
        "frames": total,
        "timings": run.get("timings"),
        "streamed": extraction.get("streamed"),
        "measured_during_motion": len(streamed_items),
    }


def result_after_motion(
    streaming: bool, paper_plan: bool = True, workers: int = 2, step: Step = _no_step
) -> dict[str, Any]:
    """One service run on the simulated bench at the real bench's example speeds, all three methods.

    ``streaming``: frames measured during the motion (``stream_extraction``) and two fits at once (``fit_workers``);
    else the extraction and the fits one after the other once the motion is over.

    Returns
    -------
    dict
        ``after_last_frame_s`` (from the last frame's ``progress`` event to the ``state: done`` event, whose result is
        stored just before), ``motion_s`` (first to last frame event), ``frames``, ``timings`` (the run's stage times),
        ``streamed`` (what the extraction took from the stream), ``speeds``.
    """
    mod = bench_service_module()
    tmp = Path(tempfile.mkdtemp(prefix="i4cal-bench-"))
    speeds = real_bench_speeds()
    sim, cfg, port = _after_motion_config(tmp, mod, speeds, streaming, paper_plan, workers)
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", "serve", "--config", str(cfg), "--log-level", "warning"],
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    label = "streaming" if streaming else "no streaming"
    try:
        run, events = _run_to_the_end(port, mod, label, step)
    finally:
        _stop(proc, sim, tmp)
    return {**_after_motion_timings(run, events, label), "speeds": speeds}


def bench_result_after_motion(opts: SpeedOptions, step: Step = _no_step) -> tuple[list[Figure], dict[str, Any]]:
    figs: list[Figure] = []
    details: dict[str, Any] = {}
    for mode in opts.stream_runs:
        on = mode == "on"
        r = result_after_motion(on, opts.service_plan == "paper", opts.workers or 2, step)
        details[mode] = r
        sp = r["speeds"]
        figs.append(
            Figure(
                key=f"result_after_last_frame_stream_{mode}_s",
                section="result-after-motion",
                unit="s",
                value=r["after_last_frame_s"],
                target=2.0 if on else None,
                label=f"last frame event -> result stored, all methods, streaming {mode}",
                detail=(
                    f"{opts.service_plan} plan, camera file from `i4cal camera calibrate`, {r['frames']} frames over "
                    f"{r['motion_s']:.0f} s of motion at "
                    f"{sp['speed_m_s']} m/s, {sp['accel_m_s2']} m/s^2, settle {sp['settle_s']} s; "
                    + (f"{r['measured_during_motion']} frames measured during it" if on else "fits one at a time")
                ),
            )
        )
    return figs, details


BENCHES: dict[str, Callable[[SpeedOptions, Step], tuple[list[Figure], dict[str, Any]]]] = {
    "extraction": bench_extraction,
    "extract-calibrate": bench_extract_calibrate,
    "fit": bench_fit,
    "acquisition": bench_acquisition,
    "modbus": bench_modbus,
    "service": bench_service,
    "result-after-motion": bench_result_after_motion,
}


def parse_sections(text: str | None) -> list[str]:
    """Section names of ``--only`` (comma-separated, aliases allowed) in the canonical order."""
    if not text:
        return list(SECTIONS)
    names = set()
    for raw in text.split(","):
        name = ALIASES.get(raw.strip().lower(), raw.strip().lower())
        if not name:
            continue
        if name not in SECTIONS:
            raise InputError(
                f"unknown benchmark section {raw.strip()!r}; sections are {', '.join(SECTIONS)}", field="--only"
            )
        names.add(name)
    return [s for s in SECTIONS if s in names]


def run_speed(
    sections: list[str],
    opts: SpeedOptions | None = None,
    step: Step = _no_step,
    on_section: Callable[[str, int], None] | None = None,
) -> SpeedReport:
    """Run the named sections in order; a failing section is recorded in ``errors`` and the others still run."""
    opts = opts or SpeedOptions()
    report = SpeedReport(machine=machine_info(), sections=sections, options=opts)
    t0 = time.perf_counter()
    for i, name in enumerate(sections):
        if on_section:
            on_section(name, i)
        try:
            figs, details = BENCHES[name](opts, step)
        except Exception as exc:
            if os.environ.get("I4CAL_DEBUG"):
                raise
            report.errors[name] = str(exc) if isinstance(exc, I4calError) else f"{type(exc).__name__}: {exc}"
            continue
        report.figures += figs
        report.details[name] = details
    report.elapsed_s = time.perf_counter() - t0
    return report


# -- terminal ------------------------------------------------------------------------------------------
def _fmt(v: float) -> str:
    return f"{v:.3f}" if abs(v) < 1 else f"{v:.1f}" if abs(v) < 1000 else f"{v:.0f}"


def print_report(report: SpeedReport, console: Any = None) -> None:
    """The figures as a rich table: measured, target, met."""
    from rich.table import Table

    from service.cli._output import make_console

    con = console or make_console()
    m = report.machine
    t = Table(
        title=f"i4cal bench speed - {m['cpu']}, {m['cores']} cores, Python {m['python']}, {m['date']}",
        title_justify="left",
    )
    for col, just in (
        ("section", "left"),
        ("figure", "left"),
        ("measured", "right"),
        ("target", "right"),
        ("vs target", "center"),
        ("notes", "left"),
    ):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    for f in report.figures:
        met = "" if f.met is None else ("[green]met[/green]" if f.met else "[red]not met[/red]")
        target = "-" if f.target is None else f"<= {_fmt(f.target)} {f.unit}"
        t.add_row(f.section, f.label, f"{_fmt(f.value)} {f.unit}", target, met, f"[dim]{f.detail}[/dim]")
    for name, err in report.errors.items():
        t.add_row(name, "[red]failed[/red]", "-", "-", "", f"[red]{err}[/red]")
    con.print(t)
    con.print(f"[dim]{len(report.figures)} figures in {report.elapsed_s:.1f} s[/dim]")


# -- command line --------------------------------------------------------------------------------------
def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "speed",
        help="speed figures of this machine (extraction, fits, acquisition, Modbus, service, memory)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--only",
        metavar="LIST",
        default=None,
        help=f"comma-separated sections to run (default all): {','.join(SECTIONS)}",
    )
    p.add_argument("--json", metavar="PATH", default=None, help="also write the figures as JSON")
    p.add_argument("--frames", type=int, default=30, metavar="N", help="frames timed for extraction (default 30)")
    p.add_argument(
        "--dataset",
        metavar="DIR",
        default=None,
        help="dataset v1 to extract and calibrate (default: render the paper's plan)",
    )
    p.add_argument("--workers", type=int, default=None, metavar="N", help="extraction processes (default: all cores)")
    p.add_argument("--poses", type=int, default=40, metavar="N", help="poses of the acquisition run (default 40)")
    p.add_argument(
        "--real-renderer", action="store_true", help="acquisition: the bench renders frames (default: a constant image)"
    )
    p.add_argument("--reads", type=int, default=1000, metavar="N", help="Modbus reads timed per client (default 1000)")
    p.add_argument("--fit-repeats", type=int, default=5, metavar="N", help="fits timed per method (default 5)")
    p.add_argument(
        "--service-plan", choices=("paper", "reduced"), default="paper", help="plan of the service run (default paper)"
    )
    p.add_argument(
        "--stream-runs",
        default="on,off",
        metavar="LIST",
        help="result-after-motion: the runs, streaming on and/or off (default on,off)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from calib.numerics.jsonio import write_json_atomic

    sections = parse_sections(args.only)
    try:
        opts = SpeedOptions(
            frames=args.frames,
            dataset=args.dataset,
            workers=args.workers,
            poses=args.poses,
            real_renderer=args.real_renderer,
            reads=args.reads,
            fit_repeats=args.fit_repeats,
            service_plan=args.service_plan,
            stream_runs=[x.strip() for x in args.stream_runs.split(",") if x.strip()],
            seed=args.seed,
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(err["msg"], field="--" + str(err["loc"][0]).replace("_", "-")) from None
    if opts.dataset and not Path(opts.dataset).exists():
        raise InputError(f"no dataset at {opts.dataset}", field="--dataset")
    if args.quiet:
        report = run_speed(sections, opts)
    else:
        with Progress(
            SpinnerColumn(),
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        ) as bar:
            overall = bar.add_task("sections", total=len(sections))
            current = bar.add_task("", total=None)

            def on_section(name: str, i: int) -> None:
                bar.update(overall, completed=i, description=f"section {i + 1}/{len(sections)}: {name}")
                bar.reset(current, total=None, description=name)

            def step(description: str, done: float, total: float | None) -> None:
                bar.update(current, description=description, completed=done, total=total)

            report = run_speed(sections, opts, step, on_section)
    print_report(report)
    if args.json:
        write_json_atomic(args.json, report.to_json(), indent=1)
        Console(stderr=True).print(f"wrote {args.json}")
    return 1 if report.errors else 0
