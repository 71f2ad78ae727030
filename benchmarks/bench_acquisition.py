"""Benchmark (not a timed test): acquisition overhead per pose on the simulated bench, Modbus round trip.

    /work/venv/bin/python benchmarks/bench_acquisition.py [--poses 40] [--real-renderer]

Overhead per pose = wall time of a pose (command, polling, settle, encoders, grab, PNG write) minus the
simulated motion itself (the trapezoidal profile's duration of the axis that travels furthest).
By default the camera serves a constant 1024x768 8-bit image, so the figure is the drivers' and the
dataset writer's own cost; ``--real-renderer`` adds drivers.sim.render's rendering time.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import statistics
import tempfile
import time

import numpy as np

from calib.parameters import NOMINAL
from calib.plan import Plan, pose_set
from drivers.acquisition import Acquisition
from drivers.config import open_actuators, open_camera, open_operator
from drivers.sim.bench import SimBench, fast_axis_config


class ConstantRenderer:
    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        self.img = (rng.random((768, 1024)) * 40 + 100).astype(np.uint8)

    def render(self, q_true, pose_true):
        return self.img


def motion_time(d: float, v: float, a: float) -> float:
    if d <= 0:
        return 0.0
    return d / v + v / a if d >= v * v / a else 2 * math.sqrt(d / a)


async def main(n_poses: int, real: bool) -> None:
    cfgax = fast_axis_config()
    async with SimBench(port=0, axis_config=cfgax, renderer=None if real else ConstantRenderer(), rtu=False) as b:
        cfg = b.bench_config()
        act = open_actuators(cfg)
        await act.connect()
        # -- Modbus round trip ---------------------------------------------------------------------
        client = act._client  # the pymodbus client itself
        raw, checked = [], []
        for _ in range(1000):
            t = time.perf_counter()
            await client.read_holding_registers(5, count=4, device_id=1)
            raw.append(time.perf_counter() - t)
        for _ in range(1000):
            t = time.perf_counter()
            await act.read(1, 5, 4)
            checked.append(time.perf_counter() - t)
        t = time.perf_counter()
        for _ in range(200):
            await act.status()
        status_ms = (time.perf_counter() - t) / 200 * 1e3
        print(f"Modbus TCP loopback round trip (read 4 registers): median {statistics.median(raw) * 1e3:.3f} ms raw "
              f"client, {statistics.median(checked) * 1e3:.3f} ms through the checked driver; "
              f"status of 4 axes {status_ms:.2f} ms")
        # -- acquisition ----------------------------------------------------------------------------
        plan = Plan(name="pose-set", steps=pose_set(NOMINAL, n_poses, seed=3))
        with tempfile.TemporaryDirectory() as tmp:
            acq = Acquisition(plan, act, open_camera(cfg), f"{tmp}/ds", operator=open_operator(cfg),
                              nominal=NOMINAL, limits=cfg.calib_limits())
            t0 = time.perf_counter()
            await acq.run()
            total = time.perf_counter() - t0
        v, a = cfg.actuators.speed_m_s, cfgax.accel
        qs = [np.asarray(s.q) for s in plan.steps]
        over, rec = [], []
        for k in range(1, len(qs)):  # the first pose starts from home: skip it
            t_start, t_moved, t_end = acq.timings[k]
            d = float(np.max(np.abs(qs[k] - qs[k - 1])))
            over.append((t_end - t_start) - motion_time(d, v, a))
            rec.append(t_end - t_moved)
        print(f"{n_poses} poses in {total:.2f} s ({'real renderer' if real else 'constant 1024x768 image'})")
        print(f"overhead per pose beyond the simulated motion: median {statistics.median(over) * 1e3:.1f} ms, "
              f"p90 {np.percentile(over, 90) * 1e3:.1f} ms (target <= 30 ms); "
              "of which the grab (the PNG write overlaps the next move) "
              f"median {statistics.median(rec) * 1e3:.1f} ms")
        await act.close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=40)
    ap.add_argument("--real-renderer", action="store_true")
    a = ap.parse_args()
    asyncio.run(main(a.poses, a.real_renderer))
