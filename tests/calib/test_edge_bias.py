"""The combined method's limb-edge bias against rods rendered with a known edge offset.

The renderer widens every rod's silhouette by ``RenderSettings.rod_edge_offset_px`` on each side; the same dataset
(seed, truth, camera phase) rendered at -0.1 and +0.1 px must move the combined method's estimate of the limbs' bias
(outward positive) by +0.2 px, within its reported std, and leave the combinations where they were, within theirs.
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_edge_bias_estimate_follows_a_known_edge_offset(tmp_path):
    from calib.methods.combined import calibrate_combined
    from calib.observations import Observations
    from calib.parameters import COMBINATION_NAMES, NOMINAL
    from calib.plan import Plan, make_plan
    from calib.vision.extract import extract_dataset
    from drivers.sim.imaging import simulate_dataset
    from drivers.sim.render import RenderSettings

    full = make_plan("full", NOMINAL, seed=0, n_base=6, n_fit=12, n_lock=2, n_validation=2)
    plan = Plan.model_validate(
        {
            "name": "edge",
            "steps": [s.model_dump() for s in full.steps if s.phase in ("rotation", "translation", "poses")],
        }
    )
    results = {}
    for off in (-0.1, 0.1):
        ds = simulate_dataset(
            tmp_path / f"ds{off}", seed=2, render=RenderSettings(rod_edge_offset_px=off), plan=plan, n_camera_views=15
        )
        obs = Observations.from_dict(extract_dataset(ds, workers=2).observations)
        results[off] = calibrate_combined(obs)
    lo, hi = results[-0.1], results[0.1]
    e_lo, e_hi = (np.asarray(r.diagnostics["limb_edge_bias"]["estimate_px"]) for r in (lo, hi))
    s_lo, s_hi = (np.asarray(r.diagnostics["limb_edge_bias"]["std_px"]) for r in (lo, hi))
    shift = e_hi - e_lo  # per limb, px
    print("edge estimate shift per limb (px):", shift, "std", np.hypot(s_lo, s_hi))
    assert np.all(np.abs(shift - 0.2) < 3 * np.hypot(s_lo, s_hi)), (shift, s_lo, s_hi)
    for k in COMBINATION_NAMES:
        d = hi.combinations[k] - lo.combinations[k]
        assert abs(d) < 3 * np.hypot(lo.combinations_std[k], hi.combinations_std[k]), (k, d)
