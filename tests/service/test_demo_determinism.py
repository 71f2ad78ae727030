"""``i4cal demo`` is reproducible at a seed: the same dataset (encoders, images), observations and
tables on two runs.

The full path runs for real: a Modbus server on loopback driven by the Modbus driver, the simulated operator
guiding the line, the rendered camera, extraction on two workers, the three methods. Its hidden ``--small``
option runs a reduced paper plan (22 frames, a 4-sample line) to keep the test affordable. Before the fix, the
encoders' noise depended on how often they were polled while the axes moved, and the operator's line on the
wall clock (line encoders up to 11.7 mm apart between runs; images differed with them).

Wall-clock fields of the dataset, which differ between runs by design: each frame's ``t`` (seconds since the
acquisition started) and the line frames' ``line_rate_hz`` (the sampling rate the acquisition could sustain on
this machine). Nothing downstream reads them: the observations are byte-identical.
"""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

#: dataset v1 frame fields that carry the wall clock (documented in the module docstring)
WALL_CLOCK_FIELDS = {"t", "line_rate_hz"}


def _demo(*args: str) -> str:
    res = subprocess.run([sys.executable, "-m", "i4cal", "demo", *args], capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    return res.stdout


def _tables(stdout: str) -> str:
    """The printed Tables I-III (from Table I's title to the end, without the final timing line)."""
    start = stdout.index("Table I")
    return re.sub(r"done in [0-9.]+ s\s*$", "", stdout[start:]).rstrip()


def _dataset(root: Path) -> tuple[dict, dict[str, str]]:
    doc = json.loads((root / "dataset.json").read_text())
    for f in doc["frames"]:
        for k in WALL_CLOCK_FIELDS:
            f.pop(k, None)
    images = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((root / "frames").iterdir())}
    return doc, images


def test_quick_demo_prints_the_same_tables_twice():
    a, b = _demo("--quick"), _demo("--quick")
    assert "Table I" in a
    assert _tables(a) == _tables(b)


@pytest.mark.slow
def test_demo_is_reproducible_at_its_seed(tmp_path):
    out_a, out_b = tmp_path / "a", tmp_path / "b"
    a = _demo("--small", "--out", str(out_a))
    b = _demo("--small", "--out", str(out_b))
    doc_a, img_a = _dataset(out_a / "dataset")
    doc_b, img_b = _dataset(out_b / "dataset")
    line = [f for f in doc_a["frames"] if f["phase"] == "line"]
    assert len(line) == 4 and [f["line_sample"] for f in line] == [0, 1, 2, 3]
    assert len(img_a) == len(doc_a["frames"]) == 22
    # every frame's encoders, truth and image, the line's included
    assert doc_a["frames"] == doc_b["frames"]
    assert img_a == img_b
    assert doc_a == doc_b
    # observations bytes, then the tables
    assert (out_a / "observations.json").read_bytes() == (out_b / "observations.json").read_bytes()
    # the tables, the verdict and its next command (which names each run's own directory)
    assert _tables(a).replace(str(out_a), "OUT") == _tables(b).replace(str(out_b), "OUT")
    assert "combined" in _tables(a)
