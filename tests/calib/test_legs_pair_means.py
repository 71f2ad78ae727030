"""The legs method's per-leg means of its two rods' directions, all pairs at once: each pair's own weighted mean.

:func:`calib.identify.legs.steps.pair_means` weighs every pose's and leg's two rods by their covariances in one
batch; each pair's result must be what the pair alone gives (:func:`calib.identify.legs.steps._gls_pair`), a leg
with one rod its rod, a leg with none NaN.
"""

from __future__ import annotations

import numpy as np

from calib.identify.legs.steps import _gls_pair, pair_means
from calib.numerics.transforms import unit


def test_every_pair_is_its_own_weighted_mean():
    rng = np.random.default_rng(0)
    n = 40
    u = unit(np.array([0.3, 0.2, -0.9]) + 0.02 * rng.normal(size=(n, 4, 2, 3)))
    u[:, :, 1] *= rng.choice([-1.0, 1.0], size=(n, 4))[..., None]  # a rod's sign is arbitrary
    A = rng.normal(size=(n, 4, 2, 3, 3)) * 1e-3
    C = A @ A.transpose(0, 1, 2, 4, 3)
    has = rng.random((n, 4, 2)) > 0.25
    u[~has] = np.nan
    U, CU, d2 = pair_means(u, has, C)
    assert has.all(axis=-1).any() and (has.any(axis=-1) & ~has.all(axis=-1)).any() and (~has.any(axis=-1)).any()
    for k in range(n):
        for leg in range(4):
            pair = u[k, leg].copy()
            if has[k, leg].all():
                pair[1] *= np.sign(pair[0] @ pair[1])
                mean, cov, chi2 = _gls_pair(pair, C[k, leg])
                np.testing.assert_allclose(U[k, leg], mean, rtol=0, atol=1e-15)
                np.testing.assert_allclose(CU[k, leg], cov, rtol=1e-14, atol=0)
                np.testing.assert_allclose(d2[k, leg], chi2, rtol=1e-12)
            elif has[k, leg].any():
                j = int(np.argmax(has[k, leg]))
                np.testing.assert_array_equal(U[k, leg], unit(pair[j]))
                np.testing.assert_array_equal(CU[k, leg], C[k, leg, j])
                assert np.isnan(d2[k, leg])
            else:
                assert np.isnan(U[k, leg]).all() and np.isnan(CU[k, leg]).all() and np.isnan(d2[k, leg])
