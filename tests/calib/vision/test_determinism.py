"""Bit-reproducibility: the same rendered dataset gives the same images, and ``i4cal extract`` the same
observations bytes, whatever the worker count and from one process to the next.

Each extraction runs in its own ``i4cal extract`` process: OpenCV's multi-threaded ``calibrateCameraRO`` gave an
fx differing in the last digits from one process to the next (never twice in one process), and the rods'
refinement of the camera and its second pass turned that into different rods (measured before the fix: 3 runs
of this extraction, 3 different files).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from calib.formats.plan import Plan, make_plan
from drivers.sim.rendered_dataset import simulate_dataset
from drivers.sim.twin import BenchGeometry
from service.cli import main


def _files(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``root``."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _extract(dataset: Path, out: Path, workers: int) -> bytes:
    env = {**os.environ, "PYTHONHASHSEED": str(workers)}  # a different hash seed per run: no set-order dependence
    res = subprocess.run(
        # every phase's rods: the more frames measured twice, the more chances for a difference to show
        [
            sys.executable,
            *("-m", "i4cal", "extract", str(dataset), "-o", str(out), "--workers", str(workers), "--quiet"),
            *("--rod-phases", "all"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    return out.read_bytes()


@pytest.fixture(scope="module")
def calibrated_dataset(tmp_path_factory) -> Path:
    """8 camera views (the intrinsics are calibrated) + 4 rotation, 3 translation, 3 fit frames: enough for the
    rods to refine the camera and for the second pass to run."""
    g = BenchGeometry()
    steps = (
        make_plan("rotation-sweep", g.nominal, n_base=4).steps
        + make_plan("equal-translation", g.nominal, n_base=3).steps
        + make_plan("pose-set", g.nominal, n_fit=3, seed=3).steps
    )
    root = tmp_path_factory.mktemp("det") / "ds"
    return simulate_dataset(root, seed=3, plan=Plan(name="small", steps=steps), n_camera_views=8)


def test_extract_gives_the_same_bytes_with_one_and_two_workers(calibrated_dataset, tmp_path):
    one = _extract(calibrated_dataset, tmp_path / "w1.json", 1)
    two = _extract(calibrated_dataset, tmp_path / "w2.json", 2)
    doc = json.loads(one)
    summary = doc["extraction"]["summary"]
    # the paths that carried the non-determinism ran: intrinsics calibrated (calibrateCameraRO), camera refined by
    # the rods, frames measured a second time
    assert summary["camera"]["n_views"] >= 5
    assert summary["camera"]["refined_by_rods"]["applied"], summary["camera"]["refined_by_rods"]
    assert sum(r is not None for f in doc["frames"] for leg in f["legs"].values() for r in leg) >= 60
    assert hashlib.sha256(two).hexdigest() == hashlib.sha256(one).hexdigest()
    # no wall-clock value in the observations: nothing named like a time or a date anywhere in the document (the
    # dataset frames' ``t`` is not copied; a board's ``t`` is its translation)
    keys: set[str] = set()

    def walk(x):
        if isinstance(x, dict):
            keys.update(x)
            for v in x.values():
                walk(v)
        elif isinstance(x, list):
            for v in x:
                walk(v)

    walk(doc)
    assert not {k for k in keys if k in {"time", "time_s", "timestamp", "date", "created", "elapsed_s"}}


def test_simulate_images_is_reproducible_at_a_seed(tmp_path):
    """``i4cal simulate --images --seed N`` twice: the same dataset.json and image bytes (the frames' ``t`` is the
    simulated clock, not the wall clock: no field is excluded)."""
    args = ["simulate", "--images", "--seed", "4", "--plan", "validation", "--camera-views", "2", "--out"]
    assert main([*args, str(tmp_path / "a")]) == 0
    assert main([*args, str(tmp_path / "b")]) == 0
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert len([k for k in a if k.endswith(".png")]) == 12
    assert a == b
