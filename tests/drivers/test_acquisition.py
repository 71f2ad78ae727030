"""Acquisition of plans on the in-process simulated bench (real loopback sockets, tiny fake renderer)."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import time

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.dataset import Dataset
from calib.formats.plan import Plan, Step, make_plan
from calib.model.kinematics import dkm
from calib.model.parameters import NOMINAL
from drivers.acquisition.acquire import Acquisition, AcquisitionError, acquire, plan_units
from drivers.acquisition.config import open_actuators, open_camera, open_operator
from drivers.acquisition.settings import AcquisitionSettings
from drivers.errors import AbortedError
from drivers.sim.mechanism import ALARM_DRIVE_FAULT


def small_plan() -> Plan:
    full = make_plan("full", NOMINAL)
    steps = [s for s in full.steps if s.phase == "rotation"][:3] + [s for s in full.steps if s.phase == "poses"][:4]
    line = make_plan("line", NOMINAL, line_samples=9).steps
    return Plan(name="small", steps=steps + line + [s for s in full.steps if s.phase == "validation"][:2])


def make_acq(bench, plan, out, **kw):
    """An acquisition on the bench's devices; ``kw``: :class:`AcquisitionSettings` fields (a short grab timeout, the
    line at 100 Hz unless given) and :class:`Acquisition` keywords."""
    cfg = bench.bench_config(acquisition={"line_rate_hz": 100.0})
    fields = {f.name for f in dataclasses.fields(AcquisitionSettings)}
    settings = AcquisitionSettings(
        **{"grab_timeout_s": 0.3, "grab_retries": 1, "line_rate_hz": 100.0, **{k: kw.pop(k) for k in fields & set(kw)}}
    )
    opts = dict(operator=open_operator(cfg), nominal=NOMINAL, limits=cfg.calib_limits(), settings=settings)
    opts.update(kw)
    return Acquisition(plan, open_actuators(cfg), open_camera(cfg), out, **opts)


async def close(acq):
    for d in (acq.actuators, acq.camera, acq.operator):
        await d.close()


async def test_full_plan_on_the_sim_bench(bench, tmp_path):
    plan = make_plan("full", NOMINAL)
    seen = []
    cfg = bench.bench_config(acquisition={"line_rate_hz": 100.0})
    res = await acquire(plan, cfg, tmp_path / "ds", progress=lambda p: seen.append(p))
    n = len(plan_units(plan))
    assert res.frames == n == 121
    ds = Dataset.open(tmp_path / "ds")
    assert [f.phase for f in ds.frames] == [u.phase for u in plan_units(plan)]
    assert ds.document.camera.width == 32 and ds.load_image(n - 1).shape == (24, 32)
    for f in ds.frames:  # encoders are what the true mechanism did, frames show the true mechanism
        truth = f.model_extra["truth"]
        assert f.model_extra.get("q_spread_m", 0.0) > 1e-5 or np.allclose(f.q, truth["q"], atol=3e-6)
    line = [f for f in ds.frames if f.phase == "line"]
    assert len(line) == 51
    # the operator moved the TRUE mechanism along a truly straight segment
    poses = np.array([f.model_extra["truth"]["pose"] for f in line])
    d = poses[-1, :3] - poses[0, :3]
    off = poses[:, :3] - poses[0, :3] - np.outer((poses[:, :3] - poses[0, :3]) @ d / (d @ d), d)
    assert np.abs(off).max() < 1e-9
    assert sorted({f.model_extra["line_sample"] for f in line}) == list(range(51))
    assert sum(f.model_extra["q_spread_m"] > 1e-5 for f in line) <= 2  # frames match encoders
    # ... which the nominal model would not call straight
    nom = dkm(NOMINAL, np.array([f.q for f in line]))
    dn = nom[-1, :3] - nom[0, :3]
    offn = nom[:, :3] - nom[0, :3] - np.outer((nom[:, :3] - nom[0, :3]) @ dn / (dn @ dn), dn)
    assert np.abs(offn).max() > 1e-5
    assert seen[-1].state == "done" and seen[-1].done == n
    assert any(p.eta_s is not None for p in seen)


async def test_alarm_mid_run_then_resume(bench, tmp_path):
    plan = small_plan()
    out = tmp_path / "ds"
    acq = make_acq(bench, plan, out)
    bench.mechanism.axes[1].pending_alarm = None
    orig_move = acq.actuators.move
    calls = {"n": 0}

    async def move(q, *a, **k):
        calls["n"] += 1
        if calls["n"] == 5:  # the 5th pose: axis 2 faults half-way
            bench.mechanism.inject_alarm(1, ALARM_DRIVE_FAULT, 0.5)
        return await orig_move(q, *a, **k)

    acq.actuators.move = move
    with pytest.raises(
        AcquisitionError,
        match=r"pose 5/18 \(plan step 4, phase 'poses'.*axis 2 in alarm, "
        r"code 0x10.*motion stopped; 4 frames kept",
    ) as ei:
        await acq.run()
    await close(acq)
    assert ei.value.pose == 4 and ei.value.frames_kept == 4
    assert not any(a.moving for a in bench.mechanism.axes)
    ds = Dataset.open(out)
    assert len(ds.frames) == 4 and ds.document.model_extra["acquisition"]["state"] == "failed"
    assert all(ds.load_image(i) is not None for i in range(4))
    # the operator clears the fault; the run resumes from pose 5
    bench.mechanism.axes[1].alarm_code = 0
    acq2 = make_acq(bench, plan, out, resume=True)
    res = await acq2.run()
    await close(acq2)
    assert res.frames == 18 and res.recorded_now == 14
    ds = Dataset.open(out)
    assert [f.phase for f in ds.frames] == [u.phase for u in plan_units(plan)]
    assert ds.document.model_extra["acquisition"]["state"] == "done"


async def test_camera_stops_delivering(bench, tmp_path):
    plan = small_plan()
    out = tmp_path / "ds"
    acq = make_acq(bench, plan, out)
    n = {"k": 0}
    orig = acq.camera.grab

    async def grab(t):
        n["k"] += 1
        if n["k"] == 4:
            bench.frames.faults.timeouts = 5  # the camera goes silent
        return await orig(t)

    acq.camera.grab = grab
    with pytest.raises(AcquisitionError, match=r"pose 3/18.*no reply from the simulated bench.*2 frames kept"):
        await acq.run()
    await close(acq)
    assert not any(a.moving for a in bench.mechanism.axes)
    assert len(Dataset.open(out).frames) == 2
    bench.frames.faults.timeouts = 0
    acq2 = make_acq(bench, plan, out, resume=True)
    assert (await acq2.run()).frames == 18
    await close(acq2)


async def test_corrupt_frame_is_retried(bench, tmp_path):
    bench.frames.faults.corrupt = 1
    acq = make_acq(bench, small_plan(), tmp_path / "ds")
    res = await acq.run()
    await close(acq)
    assert res.frames == 18 and bench.frames.faults.corrupt == 0


async def test_plan_outside_limits_moves_nothing(bench, tmp_path):
    plan = Plan(
        name="bad", steps=[Step(phase="poses", q=[0.3, 0.3, 0.3, 0.3]), Step(phase="poses", q=[0.3, 0.95, 0.3, 0.3])]
    )
    acq = make_acq(bench, plan, tmp_path / "ds")
    q0 = bench.mechanism.q_true()
    with pytest.raises(InputError, match="q2 = 950.000 mm is outside the soft limits"):
        await acq.run()
    await close(acq)
    assert np.array_equal(bench.mechanism.q_true(), q0)
    assert bench.controller.requests == 0


async def test_controller_in_alarm_at_start(bench, tmp_path):
    bench.mechanism.axes[3].alarm_code = 0x40
    acq = make_acq(bench, small_plan(), tmp_path / "ds")
    with pytest.raises(Exception, match="axis 4 in alarm, code 0x40 \\(overload\\)"):
        await acq.run()
    await close(acq)


async def test_pause_resume_abort(bench, tmp_path):
    plan = small_plan()
    states = []
    acq = make_acq(bench, plan, tmp_path / "ds", progress=lambda p: states.append((p.state, p.done, p.message)))
    task = asyncio.create_task(acq.run())
    while not any(s == "running" and d >= 2 for s, d, _ in states):
        await asyncio.sleep(0.002)
    acq.pause()

    # the pose in progress is finished first (however long a loaded machine takes), then the run holds
    async def held() -> None:
        while not any(m.startswith("held before pose") for _, _, m in states):
            await asyncio.sleep(0.002)

    await asyncio.wait_for(held(), timeout=30.0)  # generous: only a run that never holds reaches it
    n_paused = len(Dataset.open(tmp_path / "ds").frames)
    await asyncio.sleep(0.1)
    assert len(Dataset.open(tmp_path / "ds").frames) == n_paused  # nothing happens while paused
    assert not any(a.moving for a in bench.mechanism.axes)
    acq.resume()
    while not any(s == "running" and d >= n_paused + 2 for s, d, _ in states):
        await asyncio.sleep(0.001)
    acq.abort()
    with pytest.raises(AbortedError, match="motion stopped"):
        await task
    await close(acq)
    assert not any(a.moving for a in bench.mechanism.axes)
    ds = Dataset.open(tmp_path / "ds")
    assert n_paused + 2 <= len(ds.frames) < 18
    assert ds.document.model_extra["acquisition"]["state"] == "aborted"


async def test_abort_waits_for_the_frame_being_written(bench, tmp_path, monkeypatch):
    """An abort that arrives while the run waits for a frame's write (frames are written behind the next move) ends
    the run only after that write, and keeps the frame grabbed meanwhile: the state record counts every frame kept and
    nothing is written once the run has ended. Before, the abort lost the write in flight: the run ended with it still
    running, its record a frame short, the grabbed frame dropped, and the two writers of dataset.json shared one
    temporary file (the state record could be lost)."""
    import threading

    from calib.formats.dataset import DatasetWriter

    release, in_flight = threading.Event(), threading.Event()
    original = DatasetWriter.add_frame

    def add_frame(self, *args, **kwargs):
        if len(self) >= 2:  # the third frame's write (and any after) waits until the test releases it
            in_flight.set()
            release.wait(10.0)
        try:
            return original(self, *args, **kwargs)
        finally:
            in_flight.clear()

    monkeypatch.setattr(DatasetWriter, "add_frame", add_frame)
    acq = make_acq(bench, small_plan(), tmp_path / "ds")
    task = asyncio.create_task(acq.run())
    while not in_flight.is_set():
        await asyncio.sleep(0.002)
    # the next pose's move runs while the frame is written; once it is over and its frame grabbed, the run waits
    # for the write (a loaded machine only makes the wait start later: the write is held until released)
    while not any(a.moving for a in bench.mechanism.axes):
        await asyncio.sleep(0.002)
    while any(a.moving for a in bench.mechanism.axes):
        await asyncio.sleep(0.002)
    await asyncio.sleep(0.2)
    acq.abort()
    asyncio.get_running_loop().call_later(0.3, release.set)
    with pytest.raises(AbortedError, match="motion stopped"):
        await task
    assert not in_flight.is_set(), "the run ended while a frame was still being written"
    await close(acq)
    ds = Dataset.open(tmp_path / "ds")
    record = ds.document.model_extra["acquisition"]
    assert record["state"] == "aborted"
    assert record["frames"] == len(ds.frames) == 4  # the three before the abort and the one grabbed while waiting
    await asyncio.sleep(0.2)
    assert len(Dataset.open(tmp_path / "ds").frames) == 4


async def test_existing_dataset_needs_resume(bench, tmp_path):
    out = tmp_path / "ds"
    acq = make_acq(bench, small_plan(), out)
    await acq.run()
    await close(acq)
    acq = make_acq(bench, small_plan(), out)
    with pytest.raises(InputError, match="already exists"):
        await acq.run()
    await close(acq)


async def test_bench_file_lens_model_reaches_the_dataset(bench, tmp_path):
    """A bench file's ``[camera] lens_model`` is written into the dataset's camera, which extraction follows."""
    from drivers.acquisition.acquire import acquisition_from_config, close_devices

    cfg = bench.bench_config(acquisition={"line_rate_hz": 100.0}, camera={"lens_model": "rational"})
    plan = Plan(name="one", steps=[s for s in make_plan("full", NOMINAL).steps if s.phase == "poses"][:1])
    acq = acquisition_from_config(plan, cfg, tmp_path / "ds")
    try:
        await acq.run()
    finally:
        await close_devices(acq)
    assert Dataset.open(tmp_path / "ds").document.camera.model_extra["lens_model"] == "rational"


async def test_a_late_line_sample_does_not_read_the_encoders_back_to_back(bench, tmp_path):
    """A line sample that comes late (a slow grab: a loaded machine) is not followed by samples read back to back:
    the operator moves the ruler on as soon as a sample's encoders were read, so two reads a millisecond apart saw
    the axes jump by a mark (60 mm here) and the axes' plausibility check stopped the run (seen once in CI). At
    least half a line period now separates a sample's last encoder read from the next sample's first."""
    rate = 20.0
    plan = Plan(name="line", steps=make_plan("line", NOMINAL, line_samples=9).steps)
    acq = make_acq(bench, plan, tmp_path / "ds", line_rate_hz=rate)
    reads: list[tuple[str, float]] = []
    in_line = {"on": False}
    status, read_encoders, grab = acq.actuators.status, acq.actuators.read_encoders, acq._grab
    begin, end = acq.operator.begin_line, acq.operator.end_line
    n = {"grabs": 0}

    async def begin_line(*a, **k):
        in_line["on"] = True
        return await begin(*a, **k)

    async def end_line():
        in_line["on"] = False
        return await end()

    async def logged_status():
        if in_line["on"]:
            reads.append(("status", time.monotonic()))
        return await status()

    async def logged_read():
        r = await read_encoders()
        if in_line["on"]:
            reads.append(("encoders", time.monotonic()))
        return r

    async def slow_grab():
        n["grabs"] += 1
        if n["grabs"] == 3:
            await asyncio.sleep(0.4)  # eight periods late
        return await grab()

    acq.actuators.status, acq.actuators.read_encoders, acq._grab = logged_status, logged_read, slow_grab
    acq.operator.begin_line, acq.operator.end_line = begin_line, end_line
    res = await acq.run()
    await close(acq)
    assert res.frames == 9
    gaps = [b[1] - a[1] for a, b in itertools.pairwise(reads) if a[0] == "encoders" and b[0] == "status"]
    assert len(gaps) == 8
    assert min(gaps) >= 0.5 / rate - 0.002, gaps  # before: 0.1 ms after the late sample
