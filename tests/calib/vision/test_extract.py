"""Extraction from a small rendered dataset: found/missing per frame with reasons, damaged frames."""

from __future__ import annotations

import itertools
import json

import cv2
import numpy as np
import pytest

from calib.formats.camera import CameraModel
from calib.formats.dataset import CameraSpec, Dataset, DatasetWriter, LegsSpec
from calib.formats.observations import Observations
from calib.formats.plan import Plan, make_plan
from calib.vision.extract import RODS_NOT_READ, ExtractOptions, extract_dataset
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """5 rotation + 3 translation + 4 poses frames, true intrinsics known; frames 8-11 damaged on purpose."""
    g = BenchGeometry()
    rs = RenderSettings()
    r = BenchRenderer(g, rs, seed=4)
    steps = (
        make_plan("rotation-sweep", g.nominal, n_base=5).steps
        + make_plan("equal-translation", g.nominal, n_base=3).steps
        + make_plan("pose-set", g.nominal, n_fit=4).steps
    )
    tp = GeometricTwin(g).true_poses(Plan(name="small", steps=steps))
    root = tmp_path_factory.mktemp("ds")
    cam = r.camera
    board = rs.board.model_copy(update={"height_above_ee_m": 0.035})
    w = DatasetWriter(
        root,
        camera=CameraSpec(width=1024, height=768, K=cam.K.tolist(), dist=cam.dist.tolist()),
        board=board,
        legs=LegsSpec(rod_radius_m=g.rod_radius_m, rod_spacing_m=g.rod_spacing_m),
        nominal=g.nominal.as_dict(),
    )
    rng = np.random.default_rng(0)
    for k, (ph, q, pose) in enumerate(tp):
        img = r.render(q, pose, rng, board_visible=(k != 10))  # frame 10: board hidden
        if k == 11:  # frame 11: leg 1's rods painted out
            top, bot = g.rod_segments_base(q, pose)
            img = img.copy()
            for rod in range(2):
                seg = np.linspace(0.2, 1.0, 40)[:, None] * (bot[0, rod] - top[0, rod]) + top[0, rod]
                px = np.clip(cam.project(g.camera_from_base.apply(seg)), -4000, 4000).astype(int)
                for a, b in itertools.pairwise(px):
                    cv2.line(img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 50, thickness=40)
        w.add_frame(ph, q, img, truth={"q": q.tolist(), "pose": pose.tolist()})
    w.close()
    (root / "frames/000008.png").unlink()  # missing file
    data = (root / "frames/000009.png").read_bytes()
    (root / "frames/000009.png").write_bytes(data[: len(data) // 3])  # truncated
    return root, g, cam


def test_extract_reports_per_frame_reasons_and_processes_the_rest(small_dataset):
    root, _, _ = small_dataset
    calls = []
    res = extract_dataset(root, workers=1, progress=lambda d, t: calls.append((d, t)))
    assert calls and calls[-1][0] == calls[-1][1]
    obs = Observations.from_dict(res.observations)  # valid observations v1
    fr = res.observations["frames"]
    assert len(fr) == 12
    assert res.summary["placement"]["ok"]
    assert "corrupt or truncated" in fr[9]["missing"]["image"]
    assert "missing" in fr[8]["missing"]["image"]
    assert fr[9]["board"] is None and fr[8]["board"] is None
    assert "board not found" in fr[10]["missing"]["board"]
    # the board-less frame still gets its rods (predicted from the model)
    assert sum(r is not None for leg in fr[10]["legs"].values() for r in leg) >= 6
    assert fr[11]["legs"]["1"] == [None, None]
    assert "leg1.rod0" in fr[11]["missing"] and "leg1.rod1" in fr[11]["missing"]
    # every other frame (rotation, translation): its board; its rods are not read (ExtractOptions.rod_phases) ...
    for i in range(8):
        assert fr[i]["board"] is not None
        assert all(r is None for leg in fr[i]["legs"].values() for r in leg)
        assert fr[i]["missing"] == {"rods": RODS_NOT_READ}
    # ... unless asked: then most of them
    every = extract_dataset(root, workers=1, options=ExtractOptions(rod_phases=None)).observations["frames"]
    for i in range(8):
        assert sum(r is not None for leg in every[i]["legs"].values() for r in leg) >= 6
    s = res.summary
    assert s["phases"]["rotation"]["frames"] == 5 and s["phases"]["poses"]["frames"] == 4
    assert s["phases"]["poses"]["missing"]["image: image file missing"] == 1
    assert s["phases"]["poses"]["missing"]["board: board not found"] == 1
    assert "9" in s["frames"] and "8" in s["frames"] and "10" in s["frames"]
    assert obs.arrays("rotation").has_board.sum() == 5


def test_rod_outside_the_image_has_a_reason(small_dataset):
    from calib.vision.rods import RodPrediction, measure_rod

    _, _, cam = small_dataset
    img = np.full((768, 1024), 50, np.float32)
    pred = RodPrediction(0, 0, np.array([3.0, 0.0, 1.0]), np.array([3.0, 0.5, 1.2]))
    m = measure_rod(img, cam, pred, 0.008)
    assert not m.ok and "outside the image" in m.reason
    pred = RodPrediction(0, 0, np.array([0.0, 0.0, 0.7]), np.array([0.1, 0.1, 0.7]))
    m = measure_rod(img, cam, pred, 0.008)
    assert not m.ok and "too few limb edge points" in m.reason


def test_cli_extract(small_dataset, tmp_path):
    from service.cli import main

    root, _, _ = small_dataset
    out = tmp_path / "obs.json"
    assert main(["extract", str(root), "-o", str(out), "--workers", "1", "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "i4cal.observations/1" and len(doc["frames"]) == 12
    assert main(["extract", str(tmp_path / "nowhere"), "-o", str(out), "--quiet"]) == 2


def test_dataset_writer_is_crash_safe(tmp_path):
    """A run cut off leaves a valid dataset of the frames written so far; stray temporaries are harmless."""
    g = BenchGeometry()
    w = DatasetWriter(
        tmp_path,
        camera=CameraSpec(width=8, height=6),
        board=RenderSettings().board,
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=g.nominal.as_dict(),
    )
    img = np.zeros((6, 8), np.uint8)
    w.add_frame("poses", [0.1, 0.2, 0.3, 0.4], img)
    w.add_frame("poses", [0.1, 0.2, 0.3, 0.5], img)
    # a crash while writing the third frame: its temporaries exist, dataset.json is the old one
    (tmp_path / "frames/.000002.png.tmp").write_bytes(b"\x89PNG partial")
    (tmp_path / ".dataset.json.tmp").write_text('{"format": "i4cal.dataset/1", "frames": [')
    ds = Dataset.open(tmp_path)
    assert len(ds.frames) == 2 and ds.load_image(1).shape == (6, 8)
    # resuming appends after the last complete frame
    w2 = DatasetWriter(
        tmp_path,
        camera=CameraSpec(width=8, height=6),
        board=RenderSettings().board,
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=g.nominal.as_dict(),
        resume=True,
    )
    assert w2.add_frame("poses", [0, 0, 0, 0], img) == 2
    assert len(Dataset.open(tmp_path).frames) == 3


def test_dataset_validation_names_frame_and_field(tmp_path):
    from calib.errors import InputError

    g = BenchGeometry()
    w = DatasetWriter(
        tmp_path,
        camera=CameraSpec(width=8, height=6),
        board=RenderSettings().board,
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=g.nominal.as_dict(),
    )
    w.add_frame("poses", [0.1, 0.2, 0.3, 0.4], None)
    doc = json.loads((tmp_path / "dataset.json").read_text())
    doc["frames"][0]["q"] = [1, 2]
    (tmp_path / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as e:
        Dataset.open(tmp_path)
    assert e.value.frame == 0 and e.value.field == "q"


def test_camera_model_from_dataset_spec_matches(small_dataset):
    root, _, cam = small_dataset
    d = Dataset.open(root).document.camera
    assert np.allclose(CameraModel(np.asarray(d.K), np.asarray(d.dist), d.width, d.height).K, cam.K)


def test_shipped_dataset_schema_matches_the_models():
    from pathlib import Path

    from calib.formats.dataset import dataset_json_schema

    shipped = Path(__file__).resolve().parents[3] / "calib/formats/schemas/dataset-v1.schema.json"
    assert json.loads(shipped.read_text()) == dataset_json_schema()


def test_cli_extract_says_the_camera_views_were_weighted(tmp_path, capsys):
    """A dataset with a camera phase: the printout gives the views' corner-noise range the calibration weighted by."""
    from calib.formats.plan import make_plan
    from drivers.sim.rendered_dataset import simulate_dataset
    from service.cli import main

    plan = make_plan("rotation-sweep", BenchGeometry().nominal, n_base=2)
    root = simulate_dataset(tmp_path / "ds", seed=5, plan=plan, n_camera_views=10)
    assert main(["extract", str(root), "-o", str(tmp_path / "obs.json"), "--workers", "1"]) == 0
    cap = capsys.readouterr()
    out = cap.out + cap.err
    assert "views weighted by their corner noise (" in out, out
    cam = json.loads((tmp_path / "obs.json").read_text())["extraction"]["camera"]["calibration"]
    assert "weighted" in cam["method"] and len(cam["view_sigma_px"]) == cam["n_views"]


def _pose_set_with_true_camera(tmp_path, n_fit: int, seed: int):
    """A rendered pose set (no camera phase) whose dataset carries the renderer's true intrinsics."""
    from drivers.sim.rendered_dataset import simulate_dataset

    g = BenchGeometry()
    root = simulate_dataset(
        tmp_path / "ds", seed=seed, plan=make_plan("pose-set", g.nominal, n_fit=n_fit, seed=seed), n_camera_views=0
    )
    spec = json.loads((root / "dataset.json").read_text())
    cam = RenderSettings().camera()
    spec["camera"].update(K=cam.K.tolist(), dist=cam.dist.tolist())
    (root / "dataset.json").write_text(json.dumps(spec))
    return root


def test_cli_extract_counts_the_corners_left_out(tmp_path, capsys):
    """Rendered poses where the legs cross the board: corners next to a rod are left out of the board pose
    (calib.vision.board.reject_corners), counted per frame and per phase, and the printout says so."""
    from service.cli import main

    root = _pose_set_with_true_camera(tmp_path, n_fit=12, seed=0)
    out = tmp_path / "obs.json"
    assert main(["extract", str(root), "-o", str(out), "--workers", "1"]) == 0
    printed = capsys.readouterr()
    doc = json.loads(out.read_text())
    per_frame = [f["board"]["corners_rejected"] for f in doc["frames"] if f["board"]]
    n = doc["extraction"]["summary"]["phases"]["poses"]["corners_rejected"]
    assert n == sum(per_frame) and n > 0  # this seed's poses have rods across the board
    said = " ".join((printed.out + printed.err).split())
    line = "board corners left out of the poses, their residual beyond the others' scatter (next to an occluding rod"
    assert f"{line}, a glint): {n} (poses {n})" in said, said
    # the poses that lost corners are as clean as the others (a pulled corner left in gave 0.3-1.7 px)
    assert max(f["board"]["rms_px"] for f in doc["frames"] if f["board"]) < 0.2


def test_cli_extract_reports_the_refitted_prediction_and_can_skip_it(tmp_path, capsys):
    """By default the rods' prediction is refitted to the first pass (calib.vision.repredict) and the printout says
    how far the measured rods were from the nominal prediction and from the refitted one; ``--no-repredict`` keeps
    one pass on the nominal prediction."""
    from service.cli import main

    root = _pose_set_with_true_camera(tmp_path, n_fit=6, seed=1)
    out = tmp_path / "obs.json"
    assert main(["extract", str(root), "-o", str(out), "--workers", "1"]) == 0
    said = " ".join((lambda c: c.out + c.err)(capsys.readouterr()).split())
    summary = json.loads(out.read_text())["extraction"]["summary"]
    rp = summary["repredicted"]
    assert rp["median_px_after"] < rp["median_px_before"], rp
    assert "recovered" not in summary and "search bands" not in said  # the refit found the rods: no second look
    assert f"rods' prediction refitted to the first pass ({rp['rods']} rods, {rp['boards']} boards)" in said, said
    assert main(["extract", str(root), "-o", str(out), "--workers", "1", "--no-repredict"]) == 0
    said = " ".join((lambda c: c.out + c.err)(capsys.readouterr()).split())
    assert json.loads(out.read_text())["extraction"]["summary"]["repredicted"] is None
    assert "refitted" not in said, said
