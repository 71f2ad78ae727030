"""Robust chi-square gating (calib/numerics/robust.py), shared by the end-effector and legs methods."""

from __future__ import annotations

import numpy as np
import pytest

from calib.numerics.robust import chi2_gate, chi2_outliers, robust_chi2_scale


def test_robust_scale_ignores_outliers_and_the_gate_finds_them() -> None:
    rng = np.random.default_rng(0)
    n, dof, scale = 4000, 3, 2.5
    d2 = scale * rng.chisquare(dof, size=n)
    bad = rng.choice(n, size=40, replace=False)
    d2[bad] *= 200.0  # 1% gross outliers
    s = robust_chi2_scale(d2, dof)
    # the sample median of n chi-squares has a relative spread of about 1.2 / sqrt(n) (2% here): 4 sigma
    assert s == pytest.approx(scale, rel=0.08)
    out = chi2_outliers(d2, dof)
    assert out[bad].all()
    good = np.setdiff1d(np.arange(n), bad)
    # good blocks rejected at about 1 - GATE_QUANTILE (0.1%): binomial, 0.1% of 3960 = 4 expected, 12 is > 4 sigma
    assert out[good].sum() <= 12


def test_gate_per_block_degrees_of_freedom() -> None:
    dof = np.array([1, 2, 6])
    np.testing.assert_allclose(chi2_gate(dof), [10.828, 13.816, 22.458], rtol=1e-4)
    assert chi2_outliers([11.0, 11.0, 11.0], dof, scale=1.0).tolist() == [True, False, False]


def test_empty_input_is_named() -> None:
    with pytest.raises(ValueError, match="at least one residual block"):
        robust_chi2_scale([], 2)
