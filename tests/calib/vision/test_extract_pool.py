"""extract_dataset's worker processes: same observations as in one process, whatever the image cache holds."""

from __future__ import annotations

import itertools

import pytest

import calib.vision.extract as extract
import calib.vision.pool as pool_module
from calib.vision.extract import extract_dataset
from tests.calib.vision.test_determinism import calibrated_dataset  # noqa: F401  (with camera views)
from tests.calib.vision.test_extract import small_dataset  # noqa: F401  (the rendered, partly damaged dataset)


@pytest.mark.parametrize("cache_bytes", [pool_module.IMAGE_CACHE_BYTES, 2 * 1024 * 768])
def test_workers_give_the_observations_of_one_process(small_dataset, monkeypatch, cache_bytes):  # noqa: F811
    # the dataset's intrinsics are given: nothing but the scheduling differs between the two runs
    root, _, _ = small_dataset
    one = extract_dataset(root, workers=1).observations
    # a cache of 2 frames in all: most frames are decoded again in the rods stage (or by a worker that stole them)
    monkeypatch.setattr(pool_module, "IMAGE_CACHE_BYTES", cache_bytes)
    done: list[tuple[int, int]] = []
    two = extract_dataset(root, workers=2, progress=lambda d, t: done.append((d, t))).observations
    assert two["frames"] == one["frames"]
    assert two["extraction"] == one["extraction"]
    assert all(b[0] > a[0] for a, b in itertools.pairwise(done)) and done[-1][0] == done[-1][1]
    # the damaged frames keep their reasons (missing file, truncated file)
    by = {f["dataset_frame"]: f for f in two["frames"]}
    assert "image" in by[8]["missing"] and "image" in by[9]["missing"]


def test_a_worker_error_is_raised_and_the_workers_end(small_dataset):  # noqa: F811
    root, _, _ = small_dataset
    with pytest.raises(AttributeError), extract._Pool(2) as pool:  # no camera: the board stage cannot pose
        pool.run(extract._task_board, [0, 1, 2, 3, 4], (str(root), None, None, 6, None), None, 0, 5)
    assert pool.procs == [] and pool.conns == []


def test_a_second_pass_reuses_the_first_pass_corners_and_images(small_dataset):  # noqa: F811
    """The second pass (the camera refined by the rods) poses the corners the first found and measures the rods
    in the images the workers kept: the same observations as a fresh extraction with that camera."""
    import numpy as np

    from calib.formats.camera import CameraModel
    from calib.formats.dataset import Dataset
    from calib.identify.intrinsics import perturbed_camera

    root, _, _ = small_dataset
    ds = Dataset.open(root)
    c = ds.document.camera
    cam = CameraModel(np.asarray(c.K), np.asarray(c.dist), c.width, c.height)
    other = perturbed_camera(cam, np.array([2.0, 2.0, -3.0, 2.0, 1e-3, -2e-3, 1e-4, -1e-4]))
    opts = extract.ExtractOptions(refine_camera=False)
    fresh = extract_dataset(root, camera=other, workers=2, options=opts).observations
    with extract._Pool(2) as pool:
        corners: dict = {}
        first = extract._extract(pool, ds, cam, None, opts, None, keep_images=True, corners=corners)
        assert sum(len(v[0]) > 0 for v in corners.values()) > len(corners) // 2
        again = extract._extract(pool, ds, other, None, opts, None, corners=corners)
    assert again.observations["frames"] == fresh["frames"]
    assert again.observations["frames"] != first.observations["frames"]


def _thread_counts(_item: int) -> tuple[list[int], int]:
    """In a pool worker: the BLAS/OpenMP libraries' thread counts and OpenCV's."""
    import cv2
    from threadpoolctl import threadpool_info

    return [lib["num_threads"] for lib in threadpool_info()], cv2.getNumThreads()


#: A process that has used OpenCV's and OpenBLAS's own threads (as ``i4cal demo`` has, rendering, when it extracts)
#: forks a pool of two workers and asks each for its thread counts; prints them and its own OpenCV count after.
_FORK_AFTER_THREADS = """
import json, sys
import cv2
import numpy as np
from threadpoolctl import threadpool_limits
from calib.vision import extract
from tests.calib.vision.test_extract_pool import _thread_counts

cv2.setNumThreads(2)
img = np.random.default_rng(0).integers(0, 255, (1500, 1500), dtype=np.uint8)
for _ in range(10):
    cv2.GaussianBlur(img, (31, 31), 5)
with threadpool_limits(limits=2):
    np.linalg.svd(np.random.default_rng(0).normal(size=(300, 300)))
    with extract._Pool(2) as pool:
        out = pool.run(_thread_counts, [0, 1, 2, 3], (sys.argv[1], None, None, 6, None), None, 0, 4)
print(json.dumps({"workers": out, "parent_cv_threads": cv2.getNumThreads()}))
"""


def test_pool_workers_run_one_numerics_thread_each(small_dataset):  # noqa: F811
    """Two workers forked by a process that used two OpenCV and two BLAS threads: each worker runs one of each, and
    the parent keeps its own. (In a separate process with a timeout: a forked worker that reconfigures OpenCV's
    thread pool hangs for ever; ``i4cal demo`` did.)"""
    import json
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    root, _, _ = small_dataset
    proc = subprocess.Popen(
        [sys.executable, "-c", _FORK_AFTER_THREADS, str(root)],
        cwd=Path(__file__).resolve().parents[3],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its workers too are killed if it hangs
    )
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise AssertionError("the pool's workers hung (120 s)") from None
    assert proc.returncode == 0, err[-2000:]
    got = json.loads(out.strip().splitlines()[-1])
    for blas, cv in got["workers"]:
        assert blas and all(n == 1 for n in blas) and cv == 1, (blas, cv)
    assert got["parent_cv_threads"] == 2


def test_the_workers_detect_the_boards_while_the_camera_is_calibrated(
    calibrated_dataset,  # noqa: F811
    monkeypatch,
    tmp_path,
):
    """With 2 workers the robot frames' boards are detected while the intrinsics are fitted, not after the fit: the
    fit (wherever it runs: a worker, forked after the patches, or this process) starts only once a robot frame has
    been decoded, which a file every process writes to shows; the code that detected the boards after the fit never
    gets there (30 s, then the fit reports it). That the observations do not change is test_determinism's one- and
    two-worker bytes."""
    import time

    from calib.formats.dataset import Dataset

    decoded, seen = tmp_path / "decoded", tmp_path / "seen"
    decoded.touch()
    load_image = Dataset.load_image

    def logged_load(self, index):
        with open(decoded, "a") as f:
            f.write(f"{index}\n")
        return load_image(self, index)

    monkeypatch.setattr(Dataset, "load_image", logged_load)
    robot = {i for i, f in enumerate(Dataset.open(calibrated_dataset).frames) if f.phase != "camera"}
    fit = extract.calibrate_intrinsics

    def waiting_fit(*args, **kwargs):
        deadline = time.monotonic() + 30.0
        got: set[int] = set()
        while not got and time.monotonic() < deadline:
            got = {int(x) for x in decoded.read_text().split()} & robot
            time.sleep(0.01)
        seen.write_text(" ".join(map(str, sorted(got))))
        return fit(*args, **kwargs)

    monkeypatch.setattr(extract, "calibrate_intrinsics", waiting_fit)
    res = extract_dataset(calibrated_dataset, workers=2, options=extract.ExtractOptions(refine_camera=False))
    assert seen.exists() and seen.read_text().split(), "no robot frame decoded while the camera was calibrated"
    assert res.summary["camera"]["n_views"] >= 5
    assert sum(f["board"] is not None for f in res.observations["frames"]) == len(robot)


def _refuse(_arg):
    from calib.errors import InputError

    raise InputError("too few views", field="camera")


def test_a_calibration_that_fails_beside_the_boards_is_raised_and_the_pool_goes_on(small_dataset):  # noqa: F811
    """The side task's error reaches the caller once the frames in flight are answered; the pool's next stage then
    gets its own answers (none of the dropped ones)."""
    from calib.errors import InputError

    root, _, _ = small_dataset
    init = (str(root), None, None, 6, None)
    with extract._Pool(2) as pool:
        with pytest.raises(InputError, match="too few views"):
            pool.run_beside(_refuse, None, pool_module._task_corners, [0, 1, 2, 3, 4, 5, 6], init)
        got = pool.run(pool_module._task_detect, [0, 1, 2, 3, 4], init, None, 0, 5)
    assert [i for i, _ in got] == [0, 1, 2, 3, 4]
    assert all(isinstance(r, tuple) and len(r) == 2 for _, r in got)
