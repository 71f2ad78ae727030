"""The ranges a design prints about its legs prediction are the ones the stored design benches measured.

``calib.design.optimize`` tells the user, when a legs prediction leans on its model of the rods' shading, how far
the legs prediction fell from the RMS error from one benched plan to another. Those figures come from
``benchmarks/results``; when a bench is run again the constants must follow, or the design prints a stale claim.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from calib.design.optimize import LEGS_DESIGNED_RATIO_RANGE_TWIN, LEGS_RATIO_RANGE_TWIN
from calib.parameters import COMBINATION_NAMES

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def _legs_ratio_range(files: list[Path]) -> tuple[float, float]:
    """Min and max over the files' plans and combinations of the legs prediction over its RMS error, over the trials
    in which the legs method succeeded without falling back to its prior (a trial that does says so to the user; its
    error is the prior's, which no prediction of the data's accuracy is about)."""
    ratios = []
    for f in files:
        for plan in json.loads(f.read_text())["plans"].values():
            legs = [t["methods"]["legs"] for t in plan["trials"]]
            errors = [r["errors"] for r in legs if r.get("ok") and not r.get("a_priori_fallback")]
            for c in COMBINATION_NAMES:
                rms = math.sqrt(sum(e[c] ** 2 for e in errors) / len(errors))
                ratios.append(plan["predicted_images_std_m"]["legs"][c] / rms)
    return min(ratios), max(ratios)


@pytest.mark.parametrize(
    ("pattern", "n_plans", "stated"),
    [
        ("design-seed[0-9].json", 10, LEGS_RATIO_RANGE_TWIN),
        ("design-legs-seed[0-9].json", 5, LEGS_DESIGNED_RATIO_RANGE_TWIN),
    ],
)
def test_the_stated_legs_ratio_range_is_the_benches_range(pattern, n_plans, stated):
    files = sorted(RESULTS.glob(pattern))
    assert len(files) == 5, files
    n = sum(len(json.loads(f.read_text())["plans"]) for f in files)
    assert n == n_plans
    lo, hi = _legs_ratio_range(files)
    assert (round(lo, 2), round(hi, 2)) == stated
