"""The combined method's limb-edge bias against rods rendered with a known edge offset.

The renderer widens every rod's silhouette by ``RenderSettings.rod_edge_offset_px`` on each side; the same dataset
(seed, truth, camera phase) rendered at -0.1 and +0.1 px must move the combined method's estimate of the limbs' bias
(outward positive) by +0.2 px, within its reported std, and leave the combinations where they were, within theirs.
Measured: 0.19 and 0.26 px. While the renderer applied the offset in ideal (undistorted) pixels, 0.31 and 0.33
(tests/drivers/sim/test_render.py).
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_edge_bias_estimate_follows_a_known_edge_offset(tmp_path):
    from calib.formats.observations import Observations
    from calib.formats.plan import Plan, make_plan
    from calib.identify.combined import calibrate_combined
    from calib.model.parameters import COMBINATION_NAMES, NOMINAL
    from calib.vision.extract import extract_dataset
    from drivers.sim.render import RenderSettings
    from drivers.sim.rendered_dataset import simulate_dataset

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


def _limbs_moved_outward(doc: dict, delta_px: tuple[float, float]) -> dict:
    """A copy of observations v1 with every rod's limb samples moved outward by ``delta_px`` (limb 0, limb 1) image
    pixels, along the normal of each limb's line through its samples (away from the rod's other limb)."""
    import copy

    out = copy.deepcopy(doc)
    for fr in out["frames"]:
        for rods in (fr.get("legs") or {}).values():
            for rod in rods:
                if rod is None:
                    continue
                L = np.asarray(rod["limbs_px"], dtype=np.float64)
                c = L.mean(axis=1)
                for j in range(2):
                    t = np.linalg.svd(L[j] - c[j])[2][0]
                    n = np.array([-t[1], t[0]])
                    n = -n if n @ (c[1 - j] - c[j]) > 0 else n
                    L[j] += delta_px[j] * n
                rod["limbs_px"] = L.tolist()
    return out


@pytest.mark.slow
def test_edge_bias_is_modelled_in_image_pixels(tmp_path):
    """An edge detector's bias is a number of image pixels wherever the rod is; the undistortion magnifies a pixel
    with the radius (k1 = -0.3 here). The same extracted dataset with its limb samples moved outward by a known
    number of pixels moves the estimate by that number. When the bias was a constant in normalized coordinates
    the estimate followed two thirds of it and the combinations moved by up to 0.8 of their std."""
    from calib.formats.observations import Observations
    from calib.formats.plan import Plan, make_plan
    from calib.identify.combined import calibrate_combined
    from calib.model.parameters import NOMINAL
    from calib.vision.extract import extract_dataset
    from drivers.sim.rendered_dataset import simulate_dataset

    full = make_plan("full", NOMINAL, seed=0, n_base=6, n_fit=12, n_lock=2, n_validation=2)
    plan = Plan.model_validate(
        {
            "name": "edge",
            "steps": [s.model_dump() for s in full.steps if s.phase in ("rotation", "translation", "poses")],
        }
    )
    doc = extract_dataset(
        simulate_dataset(tmp_path / "ds", seed=2, plan=plan, n_camera_views=15), workers=2
    ).observations
    base = calibrate_combined(Observations.from_dict(doc))
    e0 = np.asarray(base.diagnostics["limb_edge_bias"]["estimate_px"])
    for delta in ((0.2, 0.2), (0.0, 0.2)):
        r = calibrate_combined(Observations.from_dict(_limbs_moved_outward(doc, delta)))
        shift = np.asarray(r.diagnostics["limb_edge_bias"]["estimate_px"]) - e0
        print(delta, "estimate moved by", shift)
        # the same data moved by a known amount: the noise is common to both fits, what is left is the model's
        # first-order error and the estimate's pull towards its prior (0.1 px std against a 0.03 px posterior).
        # Measured: 0.192, 0.201 px for 0.2, 0.2 and the combinations moved by at most 0.30 std (0.134, 0.131 px and
        # 0.80 std, H-D, with the bias constant in normalized coordinates)
        assert np.all(np.abs(shift - np.asarray(delta)) < 0.03), (delta, shift)
        for k, v in r.combinations.items():
            print(k, (v - base.combinations[k]) / base.combinations_std[k])
            assert abs(v - base.combinations[k]) < 0.5 * base.combinations_std[k], (k, v, base.combinations[k])
