"""The limb line fit's RANSAC: the adaptive stop of the candidates' scoring (``calib.vision.rods.linefit``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.vision.rods import linefit
from calib.vision.rods.linefit import (
    _MIN_SCORED,
    RANSAC_CONFIDENCE,
    candidates_needed,
    ransac_start,
    robust_line,
)

SIGMA_PX = 0.1  # edge noise of the synthetic limbs (px)
LENGTH_PX = 300.0


def _limb(rng: np.random.Generator, n: int, share: float, box_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points: ``share`` of them on the line y = 0.2 x + 10 (x in [0, LENGTH_PX], noise SIGMA_PX normal to
    it), the others uniform in a band of ``box_px`` across it, shuffled; the points, the line's unit normal and c."""
    k = round(share * n)
    nrm = np.array([-0.2, 1.0]) / math.hypot(0.2, 1.0)
    x = rng.uniform(0.0, LENGTH_PX, n)
    pts = np.column_stack([x, 0.2 * x + 10.0])
    pts[:k] += rng.normal(0.0, SIGMA_PX, k)[:, None] * nrm
    pts[k:] += rng.uniform(-box_px / 2, box_px / 2, n - k)[:, None] * nrm
    rng.shuffle(pts)
    return pts, nrm, np.array(-10.0 / math.hypot(0.2, 1.0))


def _twin(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    return np.random.default_rng(seed), np.random.default_rng(seed)


def test_candidates_needed_is_the_standard_termination_rule():
    assert candidates_needed(0.8, 0.999) == pytest.approx(math.log(0.001) / math.log(1 - 0.64))
    assert candidates_needed(1.0, 0.999) == 0.0
    assert candidates_needed(0.0, 0.999) == math.inf
    assert candidates_needed(0.9, 1.0) == math.inf


@pytest.mark.parametrize("seed", range(12))
def test_adaptive_stop_gives_the_line_of_the_full_scoring_with_fewer_candidates(seed):
    """A limb of 85% inliers (outliers within +/-20 px of it): the adaptive scoring stops at its minimum number of
    candidates, and the refined line and inliers are those of scoring all 150 drawn candidates."""
    pts, _, _ = _limb(np.random.default_rng(100 + seed), 200, 0.85, 40.0)
    ra, rf = _twin(seed)
    line, inl = robust_line(pts, ra, 150, 1.0)
    line_full, inl_full = robust_line(pts, rf, 150, 1.0, confidence=1.0)
    assert np.allclose(line, line_full, rtol=0.0, atol=1e-9)
    assert np.array_equal(inl, inl_full)
    ra, rf = _twin(seed)
    start, full = ransac_start(pts, ra, 150, 1.0), ransac_start(pts, rf, 150, 1.0, confidence=1.0)
    assert full.scored == full.drawn > 140  # (pairs of one point twice dropped)
    assert start.scored == _MIN_SCORED < full.scored
    assert start.n_inliers >= 0.85 * 200 - 5


def test_low_inlier_share_scores_many_candidates_and_finds_the_line():
    """30% inliers, the outliers spread over a 400 px band: the rule asks for ~70 candidates or more, and the line
    is found within its noise (5 std of its angle and of its offset at the points' centre) on every seed."""
    n, share = 200, 0.3
    k = round(n * share)
    sd_angle = SIGMA_PX / math.sqrt(k * LENGTH_PX**2 / 12)  # (rad) TLS angle std, points uniform along the limb
    sd_offset = SIGMA_PX / math.sqrt(k)  # (px) at the points' centre
    scored = []
    for seed in range(40):
        pts, nrm, c = _limb(np.random.default_rng(seed), n, share, 400.0)
        start = ransac_start(pts, np.random.default_rng(seed), 150, 1.0)
        assert start.scored >= min(candidates_needed(start.n_inliers / n, RANSAC_CONFIDENCE), start.drawn)
        scored.append(start.scored)
        line, inl = robust_line(pts, np.random.default_rng(seed), 150, 1.0)
        if line[:2] @ nrm < 0:
            line = -line
        centre = pts[inl].mean(0)
        assert math.acos(min(1.0, float(line[:2] @ nrm))) < 5 * sd_angle, seed
        assert abs(float(centre @ line[:2] + line[2])) < 1e-9  # (the TLS line passes through its points' centre)
        assert abs(float(centre @ nrm + c)) < 5 * sd_offset + 1e-9, seed
        assert k - 3 <= np.count_nonzero(inl) <= k + 10
    assert min(scored) > _MIN_SCORED and np.median(scored) >= 64


def test_robust_line_scores_fewer_candidates_than_it_draws(monkeypatch):
    """The candidates handed to the inlier counting: the first block only on a limb of 85% inliers (the rule asks
    for 7), against every one of the 150 drawn when scoring all."""
    scored = []

    def counting(pts, nx, ny, c, inlier_px):
        scored.append(c.size)
        return inlier_counts(pts, nx, ny, c, inlier_px)

    inlier_counts = linefit._inlier_counts
    monkeypatch.setattr(linefit, "_inlier_counts", counting)
    pts, _, _ = _limb(np.random.default_rng(3), 200, 0.85, 40.0)
    robust_line(pts, np.random.default_rng(4), 150, 1.0)
    assert sum(scored) == _MIN_SCORED
    scored.clear()
    robust_line(pts, np.random.default_rng(4), 150, 1.0, confidence=1.0)
    assert sum(scored) > 140


@pytest.mark.parametrize("confidence", [RANSAC_CONFIDENCE, 1.0])
def test_the_generator_draws_the_same_whenever_the_scoring_stops(confidence):
    """All the pairs are drawn up front: the generator is left as one that drew ``iters`` pairs, so the next
    limbs' and rods' draws of a frame do not depend on where a fit stopped scoring."""
    pts, _, _ = _limb(np.random.default_rng(5), 180, 0.9, 40.0)
    rng, ref = _twin(11)
    robust_line(pts, rng, 150, 1.0, confidence=confidence)
    ref.integers(0, len(pts), size=(150, 2))
    assert rng.bit_generator.state == ref.bit_generator.state
    # a single point draws nothing
    robust_line(pts[:1], rng, 150, 1.0, confidence=confidence)
    assert rng.bit_generator.state == ref.bit_generator.state
