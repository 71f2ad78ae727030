"""Frames measured one by one during an acquisition (calib.vision.stream) and taken by the extraction at the end.

A small rendered dataset (image-level twin, known intrinsics) is measured frame by frame as a worker beside the
acquisition does it, handed over as JSON (as the worker writes it), and extracted with and without it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib.formats.observations import Observations
from calib.formats.plan import Plan, make_plan
from calib.vision.extract import extract_dataset
from calib.vision.stream import FrameStreamer, StreamedFrames
from drivers.acquisition.streaming import _finite
from drivers.sim.rendered_dataset import simulate_dataset
from drivers.sim.twin import BenchGeometry


def _bytes(res) -> str:
    return json.dumps(_finite(res.observations), sort_keys=True)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """4 rotation, 3 translation and 6 fit frames, the true intrinsics recorded (as a bench file's camera file)."""
    g = BenchGeometry()
    steps = (
        make_plan("rotation-sweep", g.nominal, n_base=4).steps
        + make_plan("equal-translation", g.nominal, n_base=3).steps
        + make_plan("pose-set", g.nominal, n_fit=6, seed=3).steps
    )
    root = simulate_dataset(
        tmp_path_factory.mktemp("stream") / "ds", seed=3, plan=Plan(name="small", steps=steps), n_camera_views=0
    )
    doc = json.loads((root / "dataset.json").read_text())
    doc["camera"]["K"], doc["camera"]["dist"] = doc["truth"]["K"], doc["truth"]["dist"]
    (root / "dataset.json").write_text(json.dumps(doc))
    return root


@pytest.fixture(scope="module")
def streamed(dataset) -> dict:
    """Every frame measured in order, as the worker does (with a few frames measured again on the latest prediction
    between two frames), and written as it writes it (JSON)."""
    fs = FrameStreamer(str(dataset))
    n = len(json.loads((dataset / "dataset.json").read_text())["frames"])
    infos = []
    for i in range(n):
        infos.append(fs.add(i))
        for _ in range(3):
            if not fs.idle_step():
                break
    assert fs.frames is not None
    return {"doc": json.loads(json.dumps(fs.frames.to_dict(), default=lambda o: o.tolist())), "infos": infos}


@pytest.fixture(scope="module")
def plain(dataset):
    return extract_dataset(dataset, workers=1)


def test_streamed_boards_give_the_extraction_its_own_bytes(dataset, streamed, plain):
    # reuse_px 0: the boards are taken from the stream, every rod measured again on the final prediction
    frames = StreamedFrames.from_dict({**streamed["doc"], "reuse_px": 0.0})
    res = extract_dataset(dataset, workers=1, streamed=frames)
    assert frames.used["boards"] == len(plain.observations["frames"])  # every board came from the stream
    assert _bytes(res) == _bytes(plain)


def test_streamed_rods_within_reuse_give_the_same_observations_and_fit(dataset, streamed, plain):
    frames = StreamedFrames.from_dict(streamed["doc"])
    res = extract_dataset(dataset, workers=1, streamed=frames)
    # rods measured during the acquisition were taken: the frames after the provisional placement settled
    assert frames.used["rods"] >= 4, frames.used
    a, b = plain.observations["frames"], res.observations["frames"]
    assert [f["board"] for f in a] == [f["board"] for f in b]  # the boards, to the bit
    assert [sorted(f["missing"]) for f in a] == [sorted(f["missing"]) for f in b]  # the same rods found
    # the combined fit of both agrees within its own standard deviation: the rods measured on a prediction within
    # reuse_px differ from those measured on the final one by about their own noise (profiles placed elsewhere)
    from calib.identify.pipeline import calibrate

    fa = calibrate(Observations.from_dict(plain.observations), ["combined"])["methods"]["combined"]
    fb = calibrate(Observations.from_dict(res.observations), ["combined"])["methods"]["combined"]
    keys = sorted(fa["std"])
    pa, pb = np.array([fa["parameters"][k] for k in keys]), np.array([fb["parameters"][k] for k in keys])
    std = np.array([fa["std"][k] for k in keys])
    assert np.all(np.abs(pa - pb) <= 2 * std), (pa - pb) / std


def test_each_frame_reports_its_board_and_rods_as_it_is_measured(streamed, plain):
    infos = streamed["infos"]
    assert [i["frame"] for i in infos] == list(range(len(infos)))
    assert all(i["board"] for i in infos)  # every rendered frame shows the board
    # rods from the frame at which enough board poses place the camera (3), 8 per frame looked for
    assert [i["rods"] is None for i in infos[:2]] == [True, True]
    assert all(i["rods"] is not None for i in infos[2:])
    # once the rotation and translation frames place the camera, the fit frames' rods are found
    assert all(i["rods"] >= 6 for i in infos[7:]), [i["rods"] for i in infos]


def test_a_frame_missing_from_the_stream_is_measured_at_the_end(dataset, streamed, plain):
    doc = json.loads(json.dumps(streamed["doc"]))
    gone = 7
    del doc["boards"][str(gone)]
    doc["rods"].pop(str(gone), None)
    doc["failed"] = {str(gone): "RuntimeError: the worker failed"}
    frames = StreamedFrames.from_dict({**doc, "reuse_px": 0.0})
    res = extract_dataset(dataset, workers=1, streamed=frames)
    assert frames.used["boards"] == len(plain.observations["frames"]) - 1
    assert _bytes(res) == _bytes(plain)


def test_with_a_camera_the_rods_refine_the_stream_is_reexpressed_not_measured_again(dataset, tmp_path, monkeypatch):
    """A camera file with its calibration's covariance: the rods refine the camera at the end, and the frames the
    stream measured are re-expressed for it from their edge points (calib.vision.rods.reexpress) instead of measured
    again; the result agrees with the extraction without streaming within the fit's standard deviation."""
    import shutil

    import calib.vision.pool as pool
    from calib.camera.intrinsics import INTRINSICS_NAMES

    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    doc = json.loads((root / "dataset.json").read_text())
    K = np.asarray(doc["camera"]["K"]) + np.array([[1.5, 0, -1.5], [0, 1.5, 1.5], [0, 0, 0]])  # a few std off
    std = np.array([0.5, 0.5, 0.5, 0.5, 1e-3, 1e-3, 1e-4, 1e-4])
    doc["camera"]["K"] = K.tolist()
    doc["camera"]["intrinsics"] = {
        "calibration": {"covariance_params": list(INTRINSICS_NAMES), "covariance": np.diag(std**2).tolist()}
    }
    (root / "dataset.json").write_text(json.dumps(doc))
    fs = FrameStreamer(str(root))
    for i in range(len(doc["frames"])):
        fs.add(i)
        while fs.idle_step():
            pass
    assert fs.frames is not None
    frames = StreamedFrames.from_dict(json.loads(json.dumps(fs.frames.to_dict(), default=lambda o: o.tolist())))
    measured: list[int] = []
    measure_rods = pool.measure_rods

    def counted(img, camera, preds, *a, **k):
        measured.append(1)
        return measure_rods(img, camera, preds, *a, **k)

    monkeypatch.setattr(pool, "measure_rods", counted)
    res = extract_dataset(root, workers=1, streamed=frames)
    at_end = len(measured)
    monkeypatch.undo()
    assert res.camera_refinement is not None and res.camera_refinement.applied
    n = len(res.observations["frames"])
    # the frames before the stream's placement (2), and a few whose prediction the refined camera moved
    assert at_end <= 4, (at_end, n, frames.used)
    plain = extract_dataset(root, workers=1)
    a, b = plain.observations["frames"], res.observations["frames"]
    assert [sorted(f["missing"]) for f in a] == [sorted(f["missing"]) for f in b]
    from calib.identify.pipeline import calibrate

    fa = calibrate(Observations.from_dict(plain.observations), ["combined"])["methods"]["combined"]
    fb = calibrate(Observations.from_dict(res.observations), ["combined"])["methods"]["combined"]
    keys = sorted(fa["std"])
    pa, pb = np.array([fa["parameters"][k] for k in keys]), np.array([fb["parameters"][k] for k in keys])
    sd = np.array([fa["std"][k] for k in keys])
    assert np.all(np.abs(pa - pb) <= 2 * sd), (pa - pb) / sd


def test_a_streamed_extraction_refits_to_every_frame_and_takes_every_rod(dataset):
    """With the frames streamed (the worker idle long enough to measure each frame on its latest refit), the first
    pass takes every frame's rods on the nominal prediction (they cost nothing) and refits to all of them, as the
    stream did: its refit is then the stream's, and every rod measured on the stream's refit is taken. A sample (
    2 frames here) would refit elsewhere, and frames would be measured again at the end."""
    from calib.vision.extract import ExtractOptions

    fs = FrameStreamer(str(dataset))
    for i in range(len(json.loads((dataset / "dataset.json").read_text())["frames"])):
        fs.add(i)
        while fs.idle_step():
            pass
    assert fs.frames is not None
    frames = StreamedFrames.from_dict(json.loads(json.dumps(fs.frames.to_dict(), default=lambda o: o.tolist())))
    opts = ExtractOptions(first_pass_every=13, first_pass_min_frames=2)
    res = extract_dataset(dataset, workers=1, streamed=frames, options=opts)
    assert frames.used["rods_measured_again"] == 0, frames.used
    n = len(res.observations["frames"])
    assert frames.used["rods"] >= n - 2, frames.used  # all but the frames before the stream's placement
