"""``i4cal bench check --speeds BENCH_FILE``: the check plan designed at the real-bench example's speeds, settle
times and soft limits moves for at most the 60 s budget (the figure docs/check.md gives), and the simulated axes are
driven at those speeds (the measured motion: docs/check.md's table, a run of minutes, not repeated here)."""

from __future__ import annotations

import argparse
from pathlib import Path

from i4cal.benchmarks.check import _context, motion_overrides

REAL = Path(__file__).resolve().parents[2] / "deploy" / "bench-real.example.toml"


def test_speeds_of_the_real_bench_example_design_a_check_within_the_budget():
    over = motion_overrides(str(REAL))
    assert over["actuators"]["speed_m_s"] == 0.05 and over["actuators"]["settle_s"] == 0.3
    assert over["actuators"]["limits"]["q_min"] == [0.0] * 4
    ctx = _context(argparse.Namespace(speeds=str(REAL), max_seconds=60.0, seed=0))
    assert ctx["overrides"] == over
    assert ctx["n_fit"] >= 4 and 30.0 < ctx["motion_s"] <= 60.0  # the simulated bench's speeds: under 1 s
    assert motion_overrides(None) == {}
