"""The stream worker beside the acquisition (drivers.acquisition.streaming): it never delays a motion or a grab, and a
frame it
fails on is reported and measured at the end, not lost.

A real acquisition on the simulated bench (Modbus TCP on loopback, rendered 1024x768 frames, the camera's
intrinsics recorded as a bench file's camera file does) feeds a real worker process. The worker is made slow (and
made to fail on one frame) by wrapping its measurement: a worker process is forked with the wrapper in place.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import time

import pytest

from calib.formats.plan import Plan, pose_set
from calib.model.parameters import NOMINAL
from calib.vision import stream as stream_mod
from calib.vision.extract import extract_dataset
from drivers.acquisition.acquire import acquisition_from_config, close_devices
from drivers.acquisition.settings import DatasetHeader
from drivers.acquisition.streaming import FrameStream, _finite, load_streamed
from drivers.sim.bench import SimBench, fast_axis_config

SLOW_S = 1.5  # the worker's time per frame: far longer than a pose takes on the fast simulated bench
FAILS_ON = 2  # the frame the worker fails on
POSES = 6


def _run(tmp_path, with_stream: bool) -> dict:
    events: list[tuple[float, str, dict]] = []
    ds = tmp_path / ("ds-stream" if with_stream else "ds-plain")
    stream = None
    if with_stream:
        stream = FrameStream(
            ds,
            tmp_path / "streamed.json",
            on_event=lambda kind, data: events.append((time.monotonic(), kind, data)),
            nice=0,
            context=multiprocessing.get_context("fork"),  # the wrapped measurement goes with the fork
        ).start()

    async def main():
        async with SimBench(port=0, axis_config=fast_axis_config(), rtu=False, seed=2) as b:
            cam = b.renderer.camera
            plan = Plan(name="pose-set", steps=pose_set(NOMINAL, POSES, seed=4))
            acq = acquisition_from_config(
                plan,
                b.bench_config(),
                ds,
                header=DatasetHeader(camera={"K": cam.K.tolist(), "dist": cam.dist.tolist()}),
                on_frame=None if stream is None else stream.submit,
            )
            try:
                t0 = time.monotonic()
                await acq.run()
                return acq, t0, time.monotonic()
            finally:
                await close_devices(acq)

    acq, t0, t1 = asyncio.run(main())
    out = {"acq": acq, "t0": t0, "t1": t1, "ds": ds, "events": events}
    if stream is not None:
        out["measured_at_end_of_acquisition"] = stream.measured
        out["summary"] = stream.finish(60)
        out["stream"] = stream
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("streaming")
    original = stream_mod.FrameStreamer.add

    def slow_and_failing(self, i):
        time.sleep(SLOW_S)
        if i == FAILS_ON:
            raise RuntimeError("measurement failed (test)")
        return original(self, i)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(stream_mod.FrameStreamer, "add", slow_and_failing)
        streamed = _run(tmp, with_stream=True)
    plain = _run(tmp, with_stream=False)
    return {"streamed": streamed, "plain": plain}


def test_a_slow_worker_never_delays_the_acquisition(runs):
    s, p = runs["streamed"], runs["plain"]
    acq_s = s["t1"] - s["t0"]
    # waiting for the worker would have taken POSES * SLOW_S; the run ended while the worker was still behind
    assert acq_s < POSES * SLOW_S / 2, acq_s
    assert s["measured_at_end_of_acquisition"] < POSES - 1
    # each pose's grab-and-write took as long as without a worker (the handover is a queue put)
    rec_s = sorted(t[2] - t[1] for t in s["acq"].timings)
    rec_p = sorted(t[2] - t[1] for t in p["acq"].timings)
    assert rec_s[len(rec_s) // 2] < rec_p[len(rec_p) // 2] + 0.25, (rec_s, rec_p)
    # and then every frame handed over was measured or reported
    summ = s["summary"]
    assert summ["submitted"] == POSES and summ["measured"] == POSES - 1


def test_a_frame_the_worker_fails_on_is_reported_and_measured_at_the_end(runs):
    s = runs["streamed"]
    failed = [d for _t, kind, d in s["events"] if kind == "failed"]
    assert [d["frame"] for d in failed] == [FAILS_ON] and "measurement failed" in failed[0]["reason"]
    assert s["summary"]["failed"] == {str(FAILS_ON): "RuntimeError: measurement failed (test)"}
    frames = load_streamed(s["summary"]["file"])
    assert FAILS_ON not in frames.boards and frames.failed == {FAILS_ON: "RuntimeError: measurement failed (test)"}
    # the extraction measures it: with the stream (rods all measured again: reuse 0) the same bytes as without
    frames.reuse_px = 0.0
    with_stream = extract_dataset(s["ds"], workers=1, streamed=frames)
    without = extract_dataset(s["ds"], workers=1)
    assert frames.used["boards"] == POSES - 1
    f = with_stream.observations["frames"][FAILS_ON]
    assert f["board"] is not None  # measured at the end
    dump = lambda r: json.dumps(_finite(r.observations), sort_keys=True)  # noqa: E731
    assert dump(with_stream) == dump(without)


def test_the_worker_reports_each_frame_as_it_measures_it(runs):
    s = runs["streamed"]
    frames = [d for _t, kind, d in s["events"] if kind == "frame"]
    assert [d["frame"] for d in frames] == [i for i in range(POSES) if i != FAILS_ON]
    assert [d["measured"] for d in frames] == list(range(1, POSES))
    assert all(d["board"] for d in frames)
    assert all(d["rods"] is None for d in frames[:2]) and all(d["rods"] is not None for d in frames[2:])
