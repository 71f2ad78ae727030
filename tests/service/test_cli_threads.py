"""The command line runs one BLAS thread unless the user set otherwise, and an extraction with one worker one OpenCV
thread: the project's matrices are small, its parallelism is in processes, and a second thread on 2 cores only spins
(0.3 s of CPU at numpy's import alone)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = (
    "import json, os, sys; from i4cal import cli; from threadpoolctl import threadpool_info; "
    "print(json.dumps([os.environ.get('OPENBLAS_NUM_THREADS'), "
    "[p['num_threads'] for p in threadpool_info() if p.get('user_api') == 'blas']]))"
)


def _probe(env: dict[str, str]) -> list:
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def test_the_command_line_runs_one_blas_thread_by_default():
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    var, threads = _probe(env)
    assert var == "1" and threads and set(threads) == {1}, (var, threads)


def test_a_users_setting_is_kept():
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}
    var, threads = _probe(env)
    assert var == "2" and max(threads) == 2, (var, threads)


def test_one_worker_extracts_with_one_opencv_thread(tmp_path):
    """``workers=1``: the extraction is this process alone; OpenCV's setting is given back afterwards."""
    import cv2

    from calib.vision.extract import extract_dataset

    seen: list[int] = []
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        root = _tiny_dataset(tmp_path)
        extract_dataset(root, workers=1, on_frame=lambda info: seen.append(cv2.getNumThreads()))
        assert seen and set(seen) == {1}, seen
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)


def _tiny_dataset(tmp_path):
    from calib.formats.plan import Plan, make_plan
    from drivers.sim.rendered_dataset import simulate_dataset
    from drivers.sim.twin import BenchGeometry

    g = BenchGeometry()
    steps = make_plan("rotation-sweep", g.nominal, n_base=4).steps
    root = simulate_dataset(tmp_path / "ds", seed=1, plan=Plan(name="tiny", steps=steps), n_camera_views=0)
    doc = json.loads((root / "dataset.json").read_text())
    doc["camera"]["K"], doc["camera"]["dist"] = doc["truth"]["K"], doc["truth"]["dist"]  # intrinsics known
    (root / "dataset.json").write_text(json.dumps(doc))
    return root
