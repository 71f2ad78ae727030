"""``i4cal bench design``'s summary of the trials whose estimate came from the data.

The legs method returns its a priori values (with their tolerance as std and a warning) when its data contradict
them; a plan's predicted std is for runs whose data pin the estimate. Averaged into the RMS error the prediction is
compared with, one such trial in 50 (error 2.9 mm, std 4.7 mm) moves a legs combination's RMS by a third; it is
left out of ``data_pinned`` and counted.
"""

import numpy as np
import pytest

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
                "diagnostics": {
                    "step1_residual_chi2_per_dof": 1.4,
                    "steps34_residual_chi2_per_dof": 0.8,
                    "steps34_chi2_per_dof": 1.0,
                },
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
    assert rec["methods"]["legs"]["noise_levels"] == {"lock_chi2": 1.4, "directions_chi2": 0.8, "directions_level": 1.0}
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


def test_ratio_interval_holds_the_true_ratio_about_as_often_as_it_says():
    """An RMS error over 50 trials is itself uncertain; the bench gives each prediction / RMS ratio a 90% bootstrap
    interval. Over 300 seeded sets of 50 normal errors of std 1, a prediction of 1 is inside it 87% of the time (a
    BCa interval is a little short at n = 50): between 0.83 and 0.94, the binomial scatter (std 0.019) about 0.885
    at three std. The interval's mean ends are those of the RMS's chi-square interval (50 / chi2(50) at 5% and 95%:
    0.86, 1.19) within 0.03."""
    from i4cal.benchmarks.design import ratio_interval

    rng = np.random.default_rng(11)
    inside, ends = 0, []
    for i in range(300):
        lo, hi = ratio_interval(1.0, rng.normal(size=50), resamples=1000, seed=i)
        inside += lo <= 1.0 <= hi
        ends.append((lo, hi))
    assert 0.83 <= inside / 300 <= 0.94
    from scipy.stats import chi2

    expected = np.sqrt(chi2.ppf([0.05, 0.95], 50) / 50)
    assert np.allclose(np.mean(ends, axis=0), expected, atol=0.03)


def test_ratio_interval_rejects_what_it_cannot_use():
    from i4cal.benchmarks.design import ratio_interval

    for bad in ([1.0], [0.0, 0.0], [1.0, np.nan]):
        with pytest.raises(ValueError):
            ratio_interval(1.0, np.array(bad))


def _plan_with(errors_mm: np.ndarray, predicted_mm: float) -> dict:
    trials = [_trial([e] * 4, [predicted_mm] * 4) for e in errors_mm]
    rms = np.sqrt(np.mean(np.square(errors_mm))) * 1e-3
    methods = {
        m: {"rms_error_m": dict.fromkeys(C), "mean_std_m": dict.fromkeys(C)} for m in ("combined", "end-effector")
    }
    methods["legs"] = {"rms_error_m": dict.fromkeys(C, rms), "mean_std_m": dict.fromkeys(C, predicted_mm * 1e-3)}
    return {
        "trials": trials,
        "summary": {"methods": methods},
        "data_pinned": _data_pinned(trials),
        "predicted_images_std_m": {"legs": dict.fromkeys(C, predicted_mm * 1e-3)},
    }


def test_checks_count_the_predictions_within_30_percent_and_list_the_others_with_intervals():
    """A prediction 2x the RMS error of 50 trials is listed outside, its interval entirely beyond 1.3; one equal to
    the RMS error is within, its interval about 1."""
    rng = np.random.default_rng(3)
    e = rng.normal(size=50) * 0.2
    rms_mm = float(np.sqrt(np.mean(e**2)))
    plans = {"designed-12": _plan_with(e, 2.0 * rms_mm), "paper-20": _plan_with(e, rms_mm)}
    checks = _checks(plans)
    within = checks["prediction_within_30pct"]
    assert within["n"] == 8 and within["within"] == 4
    assert {(o["plan"], o["combination"]) for o in within["outside"]} == {("designed-12", c) for c in C}
    for o in within["outside"]:
        assert np.isclose(o["ratio"], 2.0)
        assert o["interval90"][0] > 1.3 and not o["interval_reaches_within"]
    lo, hi = checks["predicted_images_over_rms_interval90"]["paper-20"]["legs"]["L"]
    assert lo < 1.0 < hi and lo > 0.75 and hi < 1.35
    assert checks["predicted_images_over_rms_interval90"]["paper-20"]["combined"]["L"] is None


def test_checks_give_each_methods_prediction_scale_over_its_four_combinations():
    """Per plan and method, the geometric mean over the four combinations of predicted / RMS error, with its 90%
    bootstrap interval: a prediction 2x too large everywhere is outside (interval above 1.3); one 2x too large on a
    single combination (a bias of the plan's poses there) is within per method, 2^(1/4), and listed outside per
    combination."""
    rng = np.random.default_rng(5)
    e = rng.normal(size=50) * 0.2
    rms_mm = float(np.sqrt(np.mean(e**2)))
    one_off = _plan_with(e, rms_mm)
    one_off["predicted_images_std_m"]["legs"]["L"] *= 2.0
    plans = {"designed-12": _plan_with(e, 2.0 * rms_mm), "paper-20": one_off}
    checks = _checks(plans)
    per = checks["prediction_within_30pct_per_method"]
    assert per["n"] == 2 and per["within"] == 1, per
    (o,) = per["outside"]
    assert (o["plan"], o["method"]) == ("designed-12", "legs") and np.isclose(o["ratio"], 2.0)
    assert o["interval90"][0] > 1.3
    r = per["ratios"]["paper-20"]["legs"]
    assert np.isclose(r["ratio"], 2.0**0.25) and r["interval90"][0] < 2.0**0.25 < r["interval90"][1]
    assert per["ratios"]["paper-20"]["combined"] is None  # no prediction, no trials: not counted
    assert [(x["plan"], x["combination"]) for x in checks["prediction_within_30pct"]["outside"]].count(
        ("paper-20", "L")
    ) == 1


def test_checks_list_the_reported_std_that_does_not_cover_the_error_with_the_bias():
    """The methods' own std is checked against the RMS error too (is the method honest on this plan?). A method that
    reports the spread of its errors but not their common offset (a bias of the plan's poses: the legs method's L on
    the seed-2 paper plan, -0.82 +/- 0.13 mm, std 0.72x its RMS error) is listed with its trials' mean error."""
    rng = np.random.default_rng(4)
    spread, bias = 0.2, 0.3
    e = bias + rng.normal(size=50) * spread
    plan = _plan_with(e, spread)  # the mean reported std is the spread alone
    checks = _checks({"paper-20": plan})
    honest = checks["reported_std_within_30pct"]
    assert honest["n"] == 4 and honest["within"] == 0
    for o in honest["outside"]:
        assert o["method"] == "legs" and o["ratio"] < 1 / 1.3
        se = o["mean_error_se_m"]
        assert abs(o["mean_error_m"] - bias * 1e-3) < 3 * se and np.isclose(se, spread * 1e-3 / np.sqrt(50), rtol=0.3)
    # a std equal to the RMS error is within
    plan_ok = _plan_with(e, float(np.sqrt(np.mean(e**2))))
    assert _checks({"paper-20": plan_ok})["reported_std_within_30pct"]["within"] == 4
    # against the trials' spread about their mean, the same std is within: what it misses is the bias alone
    of_spread = checks["reported_std_within_30pct_of_spread"]
    assert of_spread["reference"] == "spread" and of_spread["n"] == 4 and of_spread["within"] == 4, of_spread
    lo, hi = checks["reported_std_over_spread_interval90"]["paper-20"]["legs"]["L"]
    assert lo < 1.0 < hi, (lo, hi)
    # a std twice the spread is outside it, its interval above 1.3
    wide = _checks({"paper-20": _plan_with(e, 2.0 * float(np.std(e, ddof=1)))})["reported_std_within_30pct_of_spread"]
    assert wide["within"] == 0 and all(o["interval90"][0] > 1.3 for o in wide["outside"]), wide


def test_report_reprints_a_saved_bench_and_refuses_other_files(tmp_path, capsys):
    """``i4cal bench design --report FILE`` prints the table and the checks of a saved run, recomputed, without
    running a trial; another file is refused with its name."""
    import argparse
    import json

    from calib.errors import InputError
    from i4cal.benchmarks.design import FORMAT, run

    rng = np.random.default_rng(5)
    e = rng.normal(size=20) * 0.1
    plan = _plan_with(e, 0.25) | {"motion_s": 200.0, "predicted_std_m": {}}
    for m in ("combined", "end-effector", "legs"):
        plan["summary"]["methods"][m].setdefault("n_ok", 20)
    doc = {"format": FORMAT, "plans": {"designed-12": plan}, "checks": {}, "elapsed_s": 1.0, "date": "today"}
    path = tmp_path / "bench.json"
    path.write_text(json.dumps(doc))
    args = argparse.Namespace(report=str(path), trials=5, counts=[12])
    assert run(args) == 0
    out = capsys.readouterr().out
    assert "image predictions within 30% of the RMS error: 0 of 4" in out
    assert "designed-12 legs L: " in out
    assert "the methods' mean reported std within 30% of the RMS error: 0 of 4" in out
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(InputError, match="other.json"):
        run(argparse.Namespace(report=str(other), trials=5, counts=[12]))


def _bench_doc(indices: range, rng: np.random.Generator, steps: list | None = None, name: str = "paper-20") -> dict:
    """A design bench of one plan (``name``) whose trials ``indices`` carry full records of the three methods."""
    from i4cal.benchmarks.design import FORMAT, _checks, _summarize_plans

    def record(k: int) -> dict:
        e = rng.normal(size=(3, 4)) * 0.2e-3
        return {
            "index": k,
            "methods": {
                m: {
                    "ok": True,
                    "errors": dict(zip(C, e[i].tolist(), strict=True)),
                    "std": dict.fromkeys(C, 0.2e-3),
                    "gap_validation_rms_mm": 0.1,
                }
                for i, m in enumerate(("combined", "end-effector", "legs"))
            },
        }

    pred = {m: dict.fromkeys(C, 0.2e-3) for m in ("combined", "end-effector", "legs")}
    plan = {
        "steps": steps or [{"phase": "poses", "q": [0.1, 0.1, 0.1, 0.1]}],
        "motion_s": 100.0,
        "predicted_std_m": pred,
        "predicted_images_std_m": pred,
        "records": [record(k) for k in indices],
    }
    plans = {name: plan}
    _summarize_plans(plans)
    return {
        "format": FORMAT,
        "options": {"seed": 0},
        "plans": plans,
        "checks": _checks(plans),
        "elapsed_s": 5.0,
        "date": "today",
    }


def test_runs_of_disjoint_trial_ranges_merge_into_one_bench(tmp_path, capsys):
    """``--first-trial`` runs a range of trials; ``--report A.json B.json`` merges runs of disjoint ranges of the
    same plans into one (summaries and checks over every trial, written with --json). Overlapping trials or other
    poses are refused, naming the file."""
    import argparse
    import json

    from calib.errors import InputError
    from i4cal.benchmarks.design import merge_benches, run

    rng = np.random.default_rng(6)
    a, b = _bench_doc(range(0, 10), rng), _bench_doc(range(10, 30), rng)
    merged = merge_benches([a, b], ["a.json", "b.json"])
    p = merged["plans"]["paper-20"]
    assert [t["index"] for t in p["trials"]] == list(range(30))
    errs = np.array([r["methods"]["legs"]["errors"]["L"] for d in (a, b) for r in d["plans"]["paper-20"]["records"]])
    assert np.isclose(p["summary"]["methods"]["legs"]["rms_error_m"]["L"], np.sqrt(np.mean(errs**2)))
    assert merged["checks"]["prediction_within_30pct"]["n"] == 12 and merged["elapsed_s"] == 10.0
    with pytest.raises(InputError, match="trial 5 of paper-20 is in a.json"):
        merge_benches([a, _bench_doc(range(5, 8), rng)], ["a.json", "c.json"])
    with pytest.raises(InputError, match="d.json: plan paper-20's poses differ"):
        other = _bench_doc(range(40, 42), rng, steps=[{"phase": "poses", "q": [0.2, 0.1, 0.1, 0.1]}])
        merge_benches([a, other], ["a.json", "d.json"])
    # a run written before the full records were kept merges from its per-trial errors and std
    old = _bench_doc(range(30, 40), rng)
    del old["plans"]["paper-20"]["records"]
    with_old = merge_benches([a, old], ["a.json", "old.json"])
    assert with_old["records_reduced"] == ["old.json"] and len(with_old["plans"]["paper-20"]["trials"]) == 20
    assert with_old["plans"]["paper-20"]["summary"]["methods"]["legs"]["n_ok"] == 20
    # plans run apart (--plans designed-12, then paper-20) merge into one bench with the designed-vs-paper check
    both = merge_benches([_bench_doc(range(30), rng, name="designed-12"), a], ["d.json", "a.json"])
    assert set(both["plans"]) == {"designed-12", "paper-20"} and both["plans"]["designed-12"]["sources"] == ["d.json"]
    assert set(both["checks"]["designed12_combined_not_worse_than_paper20"]) == set(C)
    # a plan designed for the legs method too (--design-methods combined,legs) is checked on both against paper-20
    legs_doc = _bench_doc(range(30), rng, name="designed-legs-12")
    legs_doc["plans"]["designed-legs-12"].update(n_fit=12, design_methods=["combined", "legs"])
    with_legs = merge_benches([legs_doc, a, b], ["l.json", "a.json", "b.json"])
    check = with_legs["checks"]["designed-legs-12_not_worse_than_paper20"]
    assert set(check) == {"combined", "legs"} and set(check["legs"]) == set(C)
    rms = {
        n: with_legs["plans"][n]["summary"]["methods"]["legs"]["rms_error_m"] for n in ("designed-legs-12", "paper-20")
    }
    assert check["legs"] == {c: rms["designed-legs-12"][c] <= rms["paper-20"][c] for c in C}
    # through the command: the merged table and checks printed, and written
    for name, doc in (("a.json", a), ("b.json", b)):
        for m in ("combined", "end-effector", "legs"):
            doc["plans"]["paper-20"]["summary"]["methods"][m].setdefault("n_ok", 0)
        (tmp_path / name).write_text(json.dumps(doc))
    out_path = tmp_path / "merged.json"
    args = argparse.Namespace(report=[str(tmp_path / "a.json"), str(tmp_path / "b.json")], json=str(out_path))
    assert run(args) == 0
    assert "(30 ok)" in capsys.readouterr().out
    back = json.loads(out_path.read_text())
    assert len(back["plans"]["paper-20"]["trials"]) == 30 and back["merged_from"][1].endswith("b.json")


def test_repredict_recomputes_a_saved_benchs_predictions_and_keeps_its_trials(tmp_path, capsys):
    """``--report FILE --repredict --json OUT``: every plan's predictions recomputed from its steps by the current
    code (the bench's seed, the twin's image noise), the checks redone against the same trials, the old
    predictions kept under ``repredicted``; the trials untouched."""
    import argparse
    import json

    from calib.design import predict_plan
    from calib.formats.plan import Plan, make_plan
    from calib.model.parameters import NOMINAL
    from i4cal.benchmarks.design import run
    from service.design import twin_image_noise, twin_scene

    plan = make_plan("full", NOMINAL, seed=0, n_fit=8)
    steps = [s.model_dump(exclude_none=True) for s in plan.steps if s.phase != "line"]
    doc = _bench_doc(range(20), np.random.default_rng(6), steps=steps, name="paper-8")
    path, out_path = tmp_path / "bench.json", tmp_path / "repredicted.json"
    path.write_text(json.dumps(doc))
    assert run(argparse.Namespace(report=[str(path)], repredict=True, json=str(out_path))) == 0
    assert "image predictions within 30%" in capsys.readouterr().out
    new = json.loads(out_path.read_text())
    p = new["plans"]["paper-8"]
    want = predict_plan(Plan(name="paper-8", steps=steps), NOMINAL, twin_scene(), twin_image_noise(seed=0)).std
    for m in ("combined", "end-effector", "legs"):
        for c in C:
            assert p["predicted_images_std_m"][m][c] == pytest.approx(want[m][c], rel=1e-9)
            assert new["repredicted"]["predicted_images_std_m_before"]["paper-8"][m][c] == 0.2e-3
    assert p["records"] == doc["plans"]["paper-8"]["records"]
    # the checks are those of the new predictions against the same RMS errors
    rms = p["summary"]["methods"]["legs"]["rms_error_m"]["L"]
    ratio = new["checks"]["predicted_images_over_rms"]["paper-8"]["legs"]["L"]
    assert ratio == pytest.approx(want["legs"]["L"] / rms, rel=1e-9)
    # without --json nothing is written; without --repredict the saved predictions are used
    assert run(argparse.Namespace(report=[str(path)], repredict=False, json=None)) == 0
    assert json.loads(path.read_text()) == doc
