"""The camera refined by the rods: a stage of its own between the first pass and the frames measured again."""

from __future__ import annotations

import numpy as np

from calib.camera.intrinsics import INTRINSICS_NAMES
from calib.formats.camera import CameraModel
from calib.vision.extract import ROD_PHASES, ExtractOptions, extract_dataset
from calib.vision.refine import refine_camera_by_rods
from tests.calib.vision.test_extract import small_dataset  # noqa: F401  (the rendered, partly damaged dataset)


def _with_covariance(cam: CameraModel) -> CameraModel:
    """The true camera, a little off, carrying a calibration covariance (0.5 px on fx..cy, 1e-3 on the rest)."""
    std = np.array([0.5, 0.5, 0.5, 0.5, 1e-3, 1e-3, 1e-4, 1e-4])
    K = cam.K + np.array([[1.0, 0, -1.0], [0, 1.0, 1.0], [0, 0, 0]])
    cal = {"covariance_params": list(INTRINSICS_NAMES), "covariance": np.diag(std**2).tolist()}
    return CameraModel(K, cam.dist, cam.width, cam.height, {"calibration": cal})


def _count_rods_tasks(monkeypatch) -> list[int]:
    """The frames whose rods the extraction measures in their images, in order (each ``_task_rods`` call)."""
    import calib.vision.extract as extract

    measured: list[int] = []
    task_rods = extract._task_rods

    def counted(args: tuple) -> tuple:
        measured.append(int(args[0]))
        return task_rods(args)

    monkeypatch.setattr(extract, "_task_rods", counted)
    return measured


def test_the_refinement_is_the_stage_run_on_the_first_pass(small_dataset):  # noqa: F811
    root, _, cam = small_dataset
    camera = _with_covariance(cam)
    res = extract_dataset(root, camera=camera, workers=1)
    ref = res.camera_refinement
    assert ref is not None and ref.fit is not None  # the combined fit ran, once, and is passed forward
    assert ref.info == res.summary["camera"]["refined_by_rods"]
    # the stage alone, on the first pass's observations, finds the same refinement
    one_pass = ExtractOptions(refine_camera=False, recover_lost_share=None)
    first = extract_dataset(root, camera=camera, workers=1, options=one_pass)
    again = refine_camera_by_rods(first.observations, first.camera)
    assert again.info == ref.info
    assert again.applied == ref.applied
    if ref.applied:  # the frames were measured again with the refined camera
        assert ref.camera is not None
        np.testing.assert_array_equal(res.camera.K, ref.camera.K)
        assert res.observations["frames"] != first.observations["frames"]


def test_a_camera_without_covariance_is_not_refined(small_dataset):  # noqa: F811
    root, _, cam = small_dataset
    res = extract_dataset(root, camera=cam, workers=1, options=ExtractOptions(recover_lost_share=None))
    assert res.camera_refinement is not None and not res.camera_refinement.applied
    assert res.camera_refinement.fit is None  # no fit run for nothing
    assert "no calibration covariance" in res.summary["camera"]["refined_by_rods"]["reason"]


def test_frames_the_refinement_does_not_use_are_measured_once(small_dataset, monkeypatch):  # noqa: F811
    """With a camera the rods can refine, the first pass measures on the refitted prediction only the frames the
    refinement uses (the poses); the others are measured once, by the pass with the refined camera (those of a phase
    whose rods are not read, not at all). The refinement is the one a first pass measuring every frame finds."""
    root, _, cam = small_dataset
    camera = _with_covariance(cam)
    sample = {"first_pass_every": 3, "first_pass_min_frames": 4, "recover_lost_share": None}
    measured = _count_rods_tasks(monkeypatch)
    res = extract_dataset(root, camera=camera, workers=1, options=ExtractOptions(**sample))
    monkeypatch.undo()
    ref = res.camera_refinement
    assert ref is not None and ref.applied
    phase = {f["dataset_frame"]: f["phase"] for f in res.observations["frames"]}
    first_sample = [i for i in sorted(phase) if i not in (8, 9)][::3]  # 8, 9: no image, no rods looked for
    for i, ph in phase.items():  # the others once; those of a phase whose rods are not read, never
        if ph != "poses" and i not in first_sample and i not in (8, 9):
            assert measured.count(i) == (1 if ph in ROD_PHASES else 0), (i, ph, measured)
    full = extract_dataset(root, camera=camera, workers=1, options=ExtractOptions(refine_camera=False, **sample))
    assert refine_camera_by_rods(full.observations, full.camera).info == ref.info


def test_the_first_sample_is_spread_evenly_with_its_minimum():
    """One frame in ``first_pass_every``, at least ``first_pass_min_frames`` spread over the frames, all of them only
    when there are no more (a 60-frame dataset sampled 24 frames, not all 60)."""
    from calib.vision.extract import _first_sample

    items = [(i,) for i in range(60)]
    picked = [it[0] for it in _first_sample(items, ExtractOptions(first_pass_every=5, first_pass_min_frames=24))]
    assert len(picked) == 24 and picked[0] == 0 and picked[-1] == 59
    gaps = np.diff(picked)
    assert gaps.min() >= 2 and gaps.max() <= 3  # evenly spread
    paper = [it[0] for it in _first_sample([(i,) for i in range(121)], ExtractOptions())]
    assert paper == list(range(0, 121, 5))  # 25 frames, one in 5
    assert len(_first_sample(items[:20], ExtractOptions())) == 20  # no more frames than the minimum: all
