"""The methods fit with one BLAS thread whatever the caller's settings: their matrices are small, and on a 2-core
machine a second BLAS thread only spins (0.4-3 s more CPU for ``i4cal calibrate --method all``, same result)."""

from __future__ import annotations

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from calib.formats.observations import Observations
from calib.formats.plan import make_plan
from calib.identify.pipeline import calibrate
from drivers.sim.twin import GeometricTwin, NoiseSpec


def _blas_threads() -> list[int]:
    return [int(p["num_threads"]) for p in threadpool_info() if p.get("user_api") == "blas"]


def test_the_fits_run_with_one_blas_thread():
    twin = GeometricTwin(noise=NoiseSpec())
    sim_obs = Observations.from_dict(twin.observations(plan=make_plan("full", twin.geometry.nominal), seed=1))
    seen: list[list[int]] = []
    with threadpool_limits(limits=2):  # a caller that allows two (OpenBLAS's default on 2 cores)
        before = _blas_threads()
        if not before or max(before) < 2:
            pytest.skip(f"BLAS allows one thread on this machine ({before})")
        calibrate(sim_obs, ["combined"], progress=lambda name, state: seen.append(_blas_threads()))
        after = _blas_threads()
    assert seen and all(n == [1] * len(n) for n in seen), seen
    assert after == before  # the caller's settings are given back
