"""A dataset's known camera: the intrinsics an acquisition recorded (K, dist and the camera file's calibration) are
what extraction uses; a dataset with neither intrinsics nor a 'camera' phase says what to run."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.dataset import BoardSpec, CameraSpec, DatasetWriter, LegsSpec
from calib.model.parameters import NOMINAL
from calib.vision.extract import extract_dataset


def test_a_dataset_with_no_intrinsics_says_what_to_run(tmp_path):
    w = DatasetWriter(
        tmp_path / "ds",
        camera=CameraSpec(width=32, height=24),
        board=BoardSpec(),
        legs=LegsSpec(rod_radius_m=0.008),
        nominal=NOMINAL.as_dict(),
    )
    w.add_frame("poses", np.zeros(4), np.zeros((24, 32), np.uint8))
    w.close()
    with pytest.raises(InputError) as e:
        extract_dataset(tmp_path / "ds", workers=1)
    msg = str(e.value)
    assert "field 'camera': no intrinsics" in msg
    assert "i4cal camera calibrate --bench BENCH.toml -o camera.json" in msg
    assert '[camera] intrinsics = "camera.json"' in msg and "--camera camera.json" in msg


def test_the_known_camera_carries_the_camera_files_calibration():
    K = [[700.0, 0.0, 15.5], [0.0, 700.0, 11.5], [0.0, 0.0, 1.0]]
    cal = {"covariance_params": ["fx"], "covariance": [[2.0]], "board_points": {"ids": [0], "points_m": [[0, 0, 0]]}}
    spec = CameraSpec(width=32, height=24, K=K, dist=[-0.1, 0.0, 0.0, 0.0, 0.0], intrinsics={"calibration": cal})
    cam = spec.camera_model()
    assert cam is not None and np.array_equal(cam.K, np.asarray(K)) and cam.extra == {"calibration": cal}
    plain = CameraSpec(width=32, height=24, K=K, dist=[0.0, 0.0, 0.0, 0.0]).camera_model()
    assert plain is not None and plain.extra == {}  # K/dist alone (a service camera_file): no calibration
    assert CameraSpec(width=32, height=24).camera_model() is None  # to be calibrated from the 'camera' phase
