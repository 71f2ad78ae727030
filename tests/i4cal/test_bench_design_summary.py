"""``i4cal bench design``'s summary of the trials whose estimate came from the data.

The legs method returns its a priori values (with their tolerance as std and a warning) when its data contradict
them; a plan's predicted std is for runs whose data pin the estimate. Such a trial used to be averaged into the RMS
error the prediction is compared with: one of 50 (error 2.9 mm, std 4.7 mm) moved the designed plan's legs
S-(q04-q03)/2 RMS from 0.49 to 0.64 mm. It is now left out of ``data_pinned`` and counted.
"""

import numpy as np

from i4cal.benchmarks._accuracy_trial import trial_record
from i4cal.benchmarks.design import _checks, _data_pinned

C = ["L", "H-D", "S-q02/2", "S-(q04-q03)/2"]


def _trial(errors_mm, std_mm, fallback=None, unpinned=0):
    return {
        "methods": {
            "legs": {
                "ok": True,
                "errors": {c: e * 1e-3 for c, e in zip(C, errors_mm, strict=True)},
                "std": {c: s * 1e-3 for c, s in zip(C, std_mm, strict=True)},
                "a_priori_fallback": fallback,
                "unpinned_directions": unpinned,
            }
        }
    }


def test_a_priori_fallback_trials_are_counted_and_left_out():
    trials = [_trial([0.3, -0.1, 0.4, -0.2], [0.4] * 4), _trial([-0.5, 0.1, 0.0, 0.2], [0.5] * 4)]
    trials.append(_trial([5.0, 2.0, 3.0, -2.9], [6.4, 2.1, 4.2, 4.7], fallback="all seven"))
    trials.append(_trial([4.3, 1.5, -2.1, -4.7], [6.3, 2.1, 4.2, 4.7], unpinned=2))
    dp = _data_pinned(trials)["legs"]
    assert dp["n_trials"] == 2 and dp["n_a_priori_fallback"] == 1 and dp["n_unpinned"] == 1
    assert np.isclose(dp["rms_error_m"]["L"], np.sqrt((0.3**2 + 0.5**2) / 2) * 1e-3)
    assert np.isclose(dp["mean_std_m"]["S-q02/2"], 0.45e-3)
    plans = {
        "designed-12": {"data_pinned": _data_pinned(trials), "predicted_images_std_m": {"legs": dict.fromkeys(C, 4e-4)}}
    }
    plans["designed-12"]["summary"] = {
        "methods": {m: {"rms_error_m": {}, "mean_std_m": {}} for m in ("combined", "end-effector", "legs")}
    }
    ratio = _checks(plans)["predicted_images_over_rms_data_pinned"]["designed-12"]["legs"]["L"]
    assert np.isclose(ratio, 0.4 / np.sqrt((0.3**2 + 0.5**2) / 2))


def test_trial_record_carries_the_methods_fallback():
    doc = {
        "methods": {
            "legs": {
                "std": dict.fromkeys(C, 1e-3),
                "diagnostics": {"identifiability": {"a_priori_fallback": "L, S, D", "unpinned": [{}, {}]}},
                "converged": True,
            },
            "combined": {"std": dict.fromkeys(C, 1e-4), "diagnostics": {}, "converged": True},
        },
        "truth_errors": {"legs": dict.fromkeys(C, 1e-3), "combined": dict.fromkeys(C, 1e-4)},
    }
    rec = trial_record(doc, {"frames": []})
    assert rec["methods"]["legs"]["a_priori_fallback"] == "L, S, D"
    assert rec["methods"]["legs"]["unpinned_directions"] == 2
    assert rec["methods"]["combined"]["a_priori_fallback"] is None


def test_the_methods_measured_noise_levels_are_recorded_and_averaged():
    """The design's image-level prediction takes the combined method's rod scale and the legs method's chi-square
    levels at their twin values (``ImageNoise``); each trial records what its fits measured, and the plan's summary
    their means over the trials whose estimate came from the data, so that a run of the bench checks those values."""
    doc = {
        "methods": {
            "legs": {
                "std": dict.fromkeys(C, 1e-3),
                "diagnostics": {"step1_residual_chi2_per_dof": 1.4, "steps34_residual_chi2_per_dof": 0.8},
                "converged": True,
            },
            "combined": {
                "std": dict.fromkeys(C, 1e-4),
                "diagnostics": {
                    "direction_noise_scale": 0.55,
                    "rod_errors": {"own_scale": 0.6, "pair_correlation": 0.2, "distance_correlation": None},
                },
                "converged": True,
            },
        },
        "truth_errors": {"legs": dict.fromkeys(C, 1e-3), "combined": dict.fromkeys(C, 1e-4)},
    }
    rec = trial_record(doc, {"frames": []})
    assert rec["methods"]["legs"]["noise_levels"] == {"lock_chi2": 1.4, "directions_chi2": 0.8}
    assert rec["methods"]["combined"]["noise_levels"] == {
        "direction_noise_scale": 0.55,
        "rod_own_scale": 0.6,
        "rod_pair_correlation": 0.2,
        "rod_distance_correlation": None,
    }
    a = _trial([0.3, -0.1, 0.4, -0.2], [0.4] * 4)
    b = _trial([-0.5, 0.1, 0.0, 0.2], [0.5] * 4)
    c = _trial([5.0, 2.0, 3.0, -2.9], [6.4, 2.1, 4.2, 4.7], fallback="all seven")
    for t, lock in ((a, 1.2), (b, 1.8), (c, 9.0)):
        t["methods"]["legs"]["noise_levels"] = {"lock_chi2": lock, "directions_chi2": None}
    means = _data_pinned([a, b, c])["legs"]["noise_levels_mean"]
    assert np.isclose(means["lock_chi2"], 1.5) and means["directions_chi2"] is None  # the fallback trial left out
