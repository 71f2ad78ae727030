"""The camera a bench's design places by: the bench file's ``[camera.mounting]`` (the camera's pose in the robot's base
frame) and camera file, the simulated bench's only for a simulated bench or, on another, with a warning naming what
is missing and what was used (``i4cal plan design`` / ``plan predict``, ``service.design.bench_scene``)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from calib.design import phase_q, visibility
from calib.formats.plan import Plan
from calib.numerics.transforms import Rigid, matrix_to_rotvec
from drivers.acquisition.config import load_bench
from drivers.sim.twin import default_base_from_camera
from service.cli import main
from service.design import bench_scene, twin_scene

BENCH_SIM = Path(__file__).resolve().parents[2] / "deploy" / "bench-sim.toml"
SMALL = ["--n-fit", "4", "--no-line", "--candidates", "60"]
#: the bench's camera 100 mm from the simulated bench's along -x of the base frame and 50 mm along +y: from there the
#: camera does not see every fit pose designed for the simulated bench's mounting (checked below)
SHIFT_M = (-0.10, 0.05, 0.0)


def _mounting() -> Rigid:
    """base_from_camera of the bench file below: the simulated bench's camera moved by :data:`SHIFT_M`."""
    g = default_base_from_camera()
    return Rigid(g.R, g.t + np.array(SHIFT_M))


def _bench(tmp: Path, name: str, mounting: Rigid | None, uri: str = "sim://127.0.0.1:5022") -> Path:
    """The simulated bench's file with another camera URI and, when given, a ``[camera.mounting]``."""
    text = BENCH_SIM.read_text().replace('uri = "sim://127.0.0.1:5022"\n# intrinsics', f'uri = "{uri}"\n# intrinsics')
    if mounting is not None:
        pos, rot = mounting.t.tolist(), matrix_to_rotvec(mounting.R).tolist()
        text = text.replace(
            "\n[operator]", f"\n[camera.mounting]\nposition_m = {pos}\nrotation_rad = {rot}\n\n[operator]"
        )
    path = tmp / name
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    """The plan designed on the simulated bench and on a bench file whose camera sits elsewhere (same seed)."""
    tmp = tmp_path_factory.mktemp("mounting")
    mounted = _bench(tmp, "mounted.toml", _mounting())
    plans = {}
    for name, bench in (("sim", BENCH_SIM), ("mounted", mounted)):
        out = tmp / f"{name}.plan.json"
        assert main(["plan", "design", "--bench", str(bench), *SMALL, "-o", str(out)]) == 0
        plans[name] = Plan.load(out)
    return mounted, plans


def test_the_bench_files_mounting_places_the_camera(designs):
    mounted, _ = designs
    scene = bench_scene(load_bench(mounted)).scene
    want = _mounting().inverse()
    assert np.allclose(scene.camera_from_base.R, want.R, atol=1e-12)
    assert np.allclose(scene.camera_from_base.t, want.t, atol=1e-12)
    assert not np.allclose(scene.camera_from_base.t, twin_scene().camera_from_base.t, atol=1e-3)


def test_a_design_sees_its_fit_poses_from_the_bench_files_mounting(designs, capsys):
    """Every fit pose designed for the bench file's mounting is in view from there, where a pose designed for the
    simulated bench's is not; ``plan predict`` on that bench lists it among the steps the camera will not see."""
    mounted, plans = designs
    cfg = load_bench(mounted)
    seen_from_bench = dataclasses.replace(twin_scene(), camera_from_base=_mounting().inverse())
    nominal = cfg.nominal_parameters()
    assert visibility(seen_from_bench, nominal, phase_q(plans["mounted"], "poses"))["ok"].all()
    sim_fit = visibility(seen_from_bench, nominal, phase_q(plans["sim"], "poses"))["ok"]
    assert not sim_fit.all()
    # a sim:// bench with its own mounting: no warning
    assert "warning" not in capsys.readouterr().err
    sim_plan = mounted.parent / "sim.plan.json"
    assert main(["plan", "predict", str(sim_plan), "--bench", str(mounted), "--methods", "combined", "--json"]) == 0
    unseen = json.loads(capsys.readouterr().out)["unseen"]
    fit_steps = [i for i, s in enumerate(plans["sim"].steps) if s.phase == "poses"]
    assert {u["step"] for u in unseen if u["phase"] == "poses"} == {
        i for i, ok in zip(fit_steps, sim_fit, strict=True) if not ok
    }


def test_a_real_bench_without_a_mounting_says_what_it_used(tmp_path, capsys):
    """A bench whose camera is not the simulated one, without ``[camera.mounting]`` nor a camera file: the design says
    (stderr, and the plan's notes) that the simulated bench's mounting and camera were used."""
    bench = _bench(tmp_path, "real.toml", None, uri="v4l2:///dev/video0")
    out = tmp_path / "plan.json"
    assert main(["plan", "design", "--bench", str(bench), *SMALL, "--json", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "[camera.mounting]" in err and "simulated bench's camera is used" in err, err
    notes = Plan.load(out).model_extra["design"]["notes"]
    assert any("[camera.mounting]" in n and "(950, 400, 30) mm" in n for n in notes), notes
    # plan predict: the same, in the check's notes
    assert main(["plan", "predict", str(out), "--bench", str(bench), "--methods", "combined", "--json"]) == 0
    captured = capsys.readouterr()
    assert "[camera.mounting]" in captured.err
    assert any("[camera.mounting]" in n for n in json.loads(captured.out)["notes"])
    # the same bench with a mounting: only the camera file is missing
    bench = _bench(tmp_path, "real-mounted.toml", _mounting(), uri="v4l2:///dev/video0")
    assert [w for w in bench_scene(load_bench(bench)).warnings if "[camera.mounting]" in w] == []


def test_a_mounting_that_is_not_a_pose_is_refused(tmp_path, capsys):
    bench = tmp_path / "bad.toml"
    bench.write_text(
        BENCH_SIM.read_text().replace(
            "\n[operator]", "\n[camera.mounting]\nposition_m = [0.9, 0.4]\nrotation_rad = [3.1, 0, 0]\n\n[operator]"
        )
    )
    assert main(["plan", "design", "--bench", str(bench), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "camera.mounting.position_m" in err and str(bench) in err, err


def test_a_cached_check_plan_is_not_reused_for_another_mounting(tmp_path):
    """The check plan's cache key (what its design depends on) follows the bench file's camera mounting."""
    from calib.design.drift_check import CheckPlanRequest
    from service.checks.plan import _design_key

    request = CheckPlanRequest()
    plain = load_bench(_bench(tmp_path, "plain.toml", None))
    key = _design_key(plain, request)
    assert _design_key(load_bench(_bench(tmp_path, "same.toml", None)), request) == key
    assert _design_key(load_bench(_bench(tmp_path, "mounted.toml", _mounting())), request) != key
