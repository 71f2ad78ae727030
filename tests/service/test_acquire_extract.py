"""`i4cal acquire --extract`: each frame measured while the simulated bench (`i4cal sim-bench`, its own process)
moves to the next pose, the observations written after the last frame, as `i4cal extract` writes them."""

from __future__ import annotations

import json

from calib.formats.plan import Plan, pose_set
from calib.model.parameters import NOMINAL
from drivers.sim.render import BenchRenderer
from drivers.sim.twin import BenchGeometry
from tests.service.test_camera_path import _bench_file, _i4cal, sim_bench  # noqa: F401 (the fixture)


def test_acquire_extract_writes_the_observations_measured_during_the_motion(sim_bench, tmp_path):  # noqa: F811
    port, _truth = sim_bench
    BenchRenderer(BenchGeometry()).camera.save(tmp_path / "camera.json")  # the simulated lens, as a camera file
    bench = _bench_file(tmp_path / "bench.toml", port, extra_camera='intrinsics = "camera.json"')
    plan = tmp_path / "plan.json"
    plan.write_text(Plan(name="pose-set", steps=pose_set(NOMINAL, 8, seed=5)).model_dump_json(exclude_none=True))
    ds = tmp_path / "ds"
    out = _i4cal("acquire", "--bench", str(bench), "--plan", str(plan), "--out", str(ds), "--extract", "--no-progress")
    said = " ".join(out.stderr.split())  # the console wraps long lines (a long temporary path)
    assert "observations in" in said and "after the last frame" in said, out.stderr
    # 8 boards measured during the motion and taken by the extraction
    assert "measured during the acquisition: 8 boards" in said, out.stderr
    doc = json.loads((ds / "observations.json").read_text())
    _i4cal("extract", str(ds), "-o", str(tmp_path / "o.json"), "--quiet")
    plain = json.loads((tmp_path / "o.json").read_text())
    # the same frames, boards to the bit (rods: measured on a prediction within the reuse tolerance, calib tests)
    assert [f["board"] for f in doc["frames"]] == [f["board"] for f in plain["frames"]]
    assert (
        doc["format"] == plain["format"]
        and len(doc["frames"]) == 8
        and all(f["board"] is not None for f in doc["frames"])
    )


def test_observations_without_extract_is_refused_before_anything_moves(tmp_path, capsys):
    from service.cli import main

    rc = main(["acquire", "--bench", str(tmp_path / "none.toml"), "--out", str(tmp_path / "ds"), "--observations", "o"])
    assert rc == 2
    assert "--extract" in capsys.readouterr().err
    assert not (tmp_path / "ds").exists()
