"""The ranges a design's notes quote about the legs prediction are the ones ``i4cal bench design`` measured.

``calib.design.optimize`` tells the user, when a legs prediction leans on its model of the rods' shading, how far
the legs prediction may fall from the RMS error from one plan to another. The stored design benches
(``benchmarks/results``: five seeds of the paper's and designed plans, ``design-seed*.json``; five of plans
designed for the combined and legs methods, ``design-legs-seed*.json``) measure it; when a bench is run again the
constants must follow, or the design prints a stale claim.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from calib.design.optimize import LEGS_DESIGNED_PREDICTION_RATIO_RANGE, LEGS_PREDICTION_RATIO_RANGE

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def _legs_ratio_range(docs: list[dict]) -> tuple[float, float]:
    """Min and max over the benches' plans and combinations of the legs prediction over its RMS error on the trials
    whose data pinned the estimate (the bench's ``predicted_images_over_rms_data_pinned``: a trial where the method
    fell back to its prior says so to the user, and its error is the prior's, which no prediction is about)."""
    ratios = [
        float(r)
        for doc in docs
        for plan in doc["checks"]["predicted_images_over_rms_data_pinned"].values()
        for r in plan["legs"].values()
    ]
    return min(ratios), max(ratios)


@pytest.mark.parametrize(
    ("pattern", "n_plans", "stated"),
    [
        ("design-seed[0-9].json", 10, LEGS_PREDICTION_RATIO_RANGE),
        ("design-legs-seed[0-9].json", 5, LEGS_DESIGNED_PREDICTION_RATIO_RANGE),
    ],
)
def test_the_quoted_legs_ratio_range_is_the_stored_benches_range(pattern, n_plans, stated):
    files = sorted(RESULTS.glob(pattern))
    assert len(files) == 5, files
    docs = [json.loads(f.read_text()) for f in files]
    assert sum(len(doc["plans"]) for doc in docs) == n_plans
    lo, hi = _legs_ratio_range(docs)
    assert (round(lo, 2), round(hi, 2)) == stated
