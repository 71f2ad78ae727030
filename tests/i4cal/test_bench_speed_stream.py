"""``i4cal bench speed``: the extraction's per-frame cost beside OpenCV's own detectBoard on the same frames, and the
result-after-motion section's settings (the real bench example's speeds); the run itself takes minutes (the
simulated bench at real speeds): docs/benchmarks.md."""

from __future__ import annotations

import json
import subprocess
import sys

from i4cal.benchmarks.speed import REAL_BENCH_EXAMPLE, parse_sections, real_bench_speeds

I4CAL = [sys.executable, "-m", "i4cal"]


def test_extraction_section_reports_opencv_detect_board_on_the_same_frames(tmp_path):
    out = tmp_path / "speed.json"
    r = subprocess.run(
        [*I4CAL, "bench", "speed", "--only", "extraction", "--frames", "3", "--quiet", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    ours, floor = doc["details"]["extraction"]["frame_ms"], doc["details"]["extraction"]["opencv_detect_board_ms"]
    assert len(ours) == len(floor) == 3  # the same frames, one by one
    f = doc["figures"]["extraction_opencv_detect_board_median_ms"]
    assert f["unit"] == "ms" and f["value"] > 0 and "detectBoard" in f["label"]
    # the library's board detection alone is a floor: the whole frame (board, pose, eight rods) costs more
    assert f["value"] < doc["figures"]["extraction_frame_median_ms"]["value"]
    assert "detectBoard" in r.stdout


def test_result_after_motion_runs_at_the_real_bench_example_speeds():
    assert parse_sections("stream") == ["result-after-motion"]
    sp = real_bench_speeds()
    text = REAL_BENCH_EXAMPLE.read_text()
    assert f"speed_m_s = {sp['speed_m_s']}" in text and f"accel_m_s2 = {sp['accel_m_s2']}" in text
    assert sp["settle_s"] > 0 and sp["speed_m_s"] < 1.0  # a real bench's pace, not the simulated one's


def test_stream_runs_option_is_checked():
    assert main_bench(["bench", "speed", "--only", "stream", "--stream-runs", "sometimes"]) == 2


def main_bench(argv):
    from i4cal.cli import main as i4cal_main

    return i4cal_main(argv)
