"""The bench file's `[camera] intrinsics`: read relative to the bench file and checked before anything moves; every
acquisition records the camera file (K, dist, SHA-256, calibration) in its dataset, which extraction then uses; a
camera of another image size, or a resume with another camera file, is refused. The console operator's board
prompts. In-process simulated bench (real loopback sockets, tiny fake renderer: 32 x 24 images)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from calib.camera.views import ViewGuide
from calib.errors import InputError
from calib.formats.camera import CameraModel
from calib.formats.dataset import Dataset
from calib.formats.plan import Plan, make_plan
from calib.model.parameters import NOMINAL
from drivers.acquisition.acquire import acquire
from drivers.acquisition.config import load_bench
from drivers.acquisition.operators import ConsoleOperator
from drivers.errors import AbortedError

CALIBRATION = {"rms_px": 0.1, "covariance_params": ["fx", "fy"], "covariance": [[1.0, 0.9], [0.9, 1.0]]}


def _camera_file(path: Path, width: int = 32, height: int = 24) -> Path:
    K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])
    path.parent.mkdir(parents=True, exist_ok=True)
    CameraModel(K, np.array([-0.1, 0.01, 0.0, 0.0, 0.0]), width, height, {"calibration": CALIBRATION}).save(path)
    return path


def _bench_toml(path: Path, intrinsics: str) -> Path:
    path.write_text(
        '[actuators]\nuri = "modbus+tcp://127.0.0.1:1"\n[camera]\nuri = "sim://127.0.0.1:2"\n'
        f'intrinsics = "{intrinsics}"\n',
        encoding="utf-8",
    )
    return path


def _plan() -> Plan:
    full = make_plan("full", NOMINAL)
    return Plan(name="few", steps=[s for s in full.steps if s.phase == "poses"][:3])


def test_the_camera_file_is_read_relative_to_the_bench_file(tmp_path):
    cam = _camera_file(tmp_path / "cams" / "camera.json")
    cfg = load_bench(_bench_toml(tmp_path / "bench.toml", "cams/camera.json"))
    known = cfg.camera_intrinsics()
    assert known is not None and known.path == tmp_path / "cams" / "camera.json"
    assert known.sha256 == hashlib.sha256(cam.read_bytes()).hexdigest()
    assert known.camera.size == (32, 24) and known.camera.extra["calibration"] == CALIBRATION


def test_a_missing_or_wrong_camera_file_says_which_and_what_to_run(tmp_path):
    bench = _bench_toml(tmp_path / "bench.toml", "camera.json")
    with pytest.raises(InputError) as e:
        load_bench(bench).camera_intrinsics()
    msg = str(e.value)
    assert "camera file not found" in msg and str(bench) in msg and "camera.intrinsics" in msg
    assert f"i4cal camera calibrate --bench {bench} -o camera.json" in msg
    (tmp_path / "camera.json").write_text(json.dumps({"format": "i4cal.result/1"}), encoding="utf-8")
    with pytest.raises(InputError, match="not a camera file .* expected 'i4cal.camera/1'"):
        load_bench(bench).camera_intrinsics()


async def test_acquire_records_the_camera_file_and_extraction_uses_its_calibration(bench, tmp_path):
    cam_file = _camera_file(tmp_path / "camera.json")
    cfg = bench.bench_config(camera={"intrinsics": str(cam_file)})
    await acquire(_plan(), cfg, tmp_path / "ds")
    ds = Dataset.open(tmp_path / "ds")
    cam = ds.document.camera
    saved = json.loads(cam_file.read_text())
    assert saved["K"] == cam.K and cam.dist == saved["dist"]
    known = cam.model_extra["intrinsics"]
    assert known["sha256"] == hashlib.sha256(cam_file.read_bytes()).hexdigest() and known["file"] == str(cam_file)
    model = cam.camera_model()  # what extraction builds: the calibration (covariance, board points) comes along
    assert model is not None and model.extra["calibration"] == CALIBRATION
    assert np.array_equal(model.K, np.asarray(saved["K"]))
    # a resume with another camera file would mix two cameras in one dataset
    other = _camera_file(tmp_path / "other.json")
    other.write_text(other.read_text().replace("30.0", "31.0"), encoding="utf-8")
    cfg2 = bench.bench_config(camera={"intrinsics": str(other)})
    with pytest.raises(InputError, match="other intrinsics than the bench file's camera file"):
        await acquire(_plan(), cfg2, tmp_path / "ds", resume=True)


async def test_a_camera_file_of_another_image_size_is_refused_before_the_plan_moves(bench, tmp_path):
    cam_file = _camera_file(tmp_path / "camera.json", 1024, 768)
    cfg = bench.bench_config(camera={"intrinsics": str(cam_file)})
    with pytest.raises(InputError, match="calibrated on 1024x768 images, the camera delivers 32x24"):
        await acquire(_plan(), cfg, tmp_path / "ds")
    assert not (tmp_path / "ds" / "dataset.json").exists()
    first_pose = np.asarray(_plan().steps[0].q)
    assert np.abs(bench.mechanism.q_true() - first_pose).max() > 1e-2  # homed only: the plan's first pose not reached


async def test_the_console_operator_grabs_on_enter_and_stops_on_q():
    answers = iter(["", "q"])
    op = ConsoleOperator(read=lambda: next(answers))
    placement = ViewGuide.first_placement()
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        await op.present_board(placement)  # Enter: grab
        with pytest.raises(AbortedError, match="stopped by the operator"):
            await op.present_board(placement)
    printed = buf.getvalue().splitlines()
    assert printed == ["Press Enter to grab (q then Enter to stop)."] * 2  # the session said where, in words
    eof = ConsoleOperator(read=lambda: (_ for _ in ()).throw(EOFError()))
    with contextlib.redirect_stdout(io.StringIO()), pytest.raises(AbortedError, match="input ended"):
        await eof.present_board(placement)
