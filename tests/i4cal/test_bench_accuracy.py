"""``i4cal bench accuracy``: the Monte-Carlo study on the image-level twin, through the command line (real rendering,
extraction and calibration in a process pool), its JSON contract, and how failures are counted. The accuracy
figures themselves are benchmark results, reported in the README; here only what holds by construction is asserted.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from calib.model.parameters import COMBINATION_NAMES, NOMINAL
from i4cal.benchmarks._accuracy_report import summarize
from i4cal.benchmarks._accuracy_trial import METHODS, TrialTask, run_trial
from i4cal.benchmarks.accuracy import (
    AccuracyOptions,
    command_line,
    default_spread_m,
    draw_truth,
    plan_steps,
    trial_seed,
)
from i4cal.cli import main

TOP_KEYS = {
    "format",
    "command",
    "argv",
    "version",
    "machine",
    "options",
    "workers",
    "engine",
    "spread_m",
    "plans",
    "notes",
    "cameras",
    "study",
    "sweeps",
    "elapsed_s",
    "cpu_s",
    "load_average",
}
TRIAL_KEYS = {
    "key",
    "index",
    "seed",
    "noise_sigma",
    "truth",
    "truth_combinations",
    "error",
    "render_s",
    "extract_s",
    "calibrate_s",
    "cpu_s",
    "methods",
    "bound_std",
    "gap_a_priori_rms_mm",
    "gap_truth_rms_mm",
    "edge_noise_px",
    "frames",
    "boards_found",
    "rods_found",
    "rods_total",
}
METHOD_SUMMARY_KEYS = {
    "n_ok",
    "n_failed",
    "failures",
    "rms_error_m",
    "mean_std_m",
    "std_over_error",
    "bound_rms_m",
    "efficiency",
    "gap_validation_rms_mm",
    "gap_below_a_priori",
    "gap_trials",
    "within_2_std",
}


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """One quick study (2 trials, 20 camera views) with a pose sweep whose 10-pose point repeats the study's first
    trial (one trial per sweep point: three trials rendered in all)."""
    out = tmp_path_factory.mktemp("acc") / "out.json"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "i4cal",
            "bench",
            "accuracy",
            "--quick",
            "--trials",
            "2",
            "--sweep-trials",
            "1",
            "--camera-views",
            "20",
            "--sweep",
            "poses",
            "--sweep-poses",
            "8,10",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert r.returncode == 0, r.stderr
    return json.loads(out.read_text()), r.stdout


def _rms4(d: dict[str, float]) -> float:
    return math.sqrt(sum(d[c] ** 2 for c in COMBINATION_NAMES) / len(COMBINATION_NAMES))


def test_quick_study_json_contract(quick):
    doc, _ = quick
    assert set(doc) == TOP_KEYS and doc["format"] == "i4cal.bench-accuracy/1"
    assert doc["command"] == (
        "i4cal bench accuracy --quick --trials 2 --camera-views 20 --sweep-trials 1 --sweep-poses 8,10 --sweep poses"
    )
    assert doc["machine"]["cores"] >= 1 and doc["version"] and doc["elapsed_s"] > 0 and doc["cpu_s"] > 0
    assert math.isclose(doc["spread_m"], default_spread_m()) and 0.003 < doc["spread_m"] < 0.008
    study = doc["study"]
    assert (study["sweep"], study["noise_sigma"], study["n_fit"]) == (None, 2.0, 10)
    assert len(study["trials"]) == 2 and [t["index"] for t in study["trials"]] == [0, 1]
    assert doc["plans"]["10"] == {
        "rotation": 6,
        "translation": 6,
        "poses": 10,
        "lock-1": 3,
        "lock-2": 3,
        "lock-3": 3,
        "lock-4": 3,
        "validation": 8,
    }
    assert any("line" in n for n in doc["notes"]) and any("reduced plan" in n for n in doc["notes"])
    assert doc["options"]["camera"] == "per-trial" and doc["cameras"] == {}  # no study-wide camera by default
    for t in study["trials"]:
        assert set(t) >= TRIAL_KEYS and t["error"] is None, t.get("error")
        # each trial calibrated its camera from its own rendered camera phase; errors and std per intrinsic
        cam = t["camera"]["intrinsics"]
        assert cam["n_views"] >= 15 and cam["rms_px"] < 0.5  # of the 20 views rendered
        assert set(cam["error_vs_true"]) == set(cam["std"]) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"}
        assert all(v > 0 for v in cam["std"].values())
        assert t["frames"] == 42 and t["boards_found"] >= 38 and t["rods_found"] >= 0.9 * t["rods_total"]
        truth = np.array([t["truth"][k] for k in ("H", "q02", "q03", "q04", "S", "D", "L")])
        assert 0 < np.abs(truth - NOMINAL.vector()).max() < 6 * doc["spread_m"]
        assert t["methods"]["combined"]["ok"], t["methods"]["combined"]["error"]
        for m, rec in t["methods"].items():
            if rec["ok"]:
                assert all(
                    math.isfinite(rec["errors"][c]) and math.isfinite(rec["std"][c]) and rec["std"][c] > 0
                    for c in COMBINATION_NAMES
                ), m
                assert rec["gap_validation_rms_mm"] > 0
            else:
                assert rec["error"]
        assert all(t["bound_std"][c] > 0 for c in COMBINATION_NAMES)
        assert 0 < t["edge_noise_px"] < 0.8 and t["gap_a_priori_rms_mm"] > 0 and t["gap_truth_rms_mm"] > 0
    s = study["summary"]
    assert set(s["methods"]) == set(METHODS)
    for m in METHODS:
        assert set(s["methods"][m]) == METHOD_SUMMARY_KEYS
        assert s["methods"][m]["n_ok"] + s["methods"][m]["n_failed"] == 2
    comb = s["methods"]["combined"]
    assert comb["n_ok"] == 2 and all(comb["efficiency"][c] > 0 for c in COMBINATION_NAMES)
    # calibration removes most of the a priori error (the truth is drawn ~5 mm around nominal per parameter)
    assert _rms4(comb["rms_error_m"]) < 0.5 * _rms4(s["a_priori_rms_error_m"])
    assert set(s["targets"]) == {"efficiency_combined", "std_honesty", "gap_below_a_priori"}


def test_sweep_points_share_their_trials(quick):
    doc, _ = quick
    pts = doc["sweeps"]["poses"]
    assert [(p["sweep"], p["value"], p["n_fit"], len(p["trials"])) for p in pts] == [
        ("poses", 8, 8, 1),
        ("poses", 10, 10, 1),
    ]
    # the 10-pose point is the study's set-up: its first trial, run once
    assert pts[1]["trials"] == doc["study"]["trials"][:1]
    # trial k has the same truth and seed at every point (common random numbers), not the same plan
    for a, b in zip(pts[0]["trials"], pts[1]["trials"], strict=True):
        assert a["truth"] == b["truth"] and a["seed"] == b["seed"] and a["frames"] == b["frames"] - 2
    assert doc["plans"]["8"]["poses"] == 8


def test_quick_study_prints_its_tables(quick):
    _, out = quick
    for text in (
        "i4cal bench accuracy - 2 trials",
        "RMS error mm",
        "efficiency",
        "a priori (nominal)",
        "displacement gap on the validation poses",
        "combined efficiency",
        "sweep over fit poses",
        "camera calibrated in every trial",
        "intrinsics error RMS / mean reported std",
    ):
        assert text in out, text


def test_failures_are_counted_not_raised():
    """A trial whose extraction cannot work (two frames: no base frame, no placement) and one whose camera is
    unusable still give records; the summary counts every method as failed with its reason."""
    steps = [s for s in plan_steps(AccuracyOptions(n_base=3), 20) if s["phase"] == "rotation"][:2]
    from drivers.sim.render import RenderSettings

    cam = RenderSettings().camera().to_dict()
    base = {"index": 0, "seed": trial_seed(0, 0), "truth": draw_truth(0, 0, 0.005), "noise_sigma": 2.0, "steps": steps}
    few = run_trial(TrialTask(key="few", camera=cam, **base))
    broken = run_trial(TrialTask(key="broken", camera={"K": "no"}, **base))
    assert few["error"] is None and set(few["methods"]) == set(METHODS)
    assert all(not r["ok"] and r["error"] for r in few["methods"].values())
    assert broken["error"] and "InputError" in broken["error"] and broken["methods"] == {}
    s = summarize([few, broken])
    assert s["trials"] == 2 and s["trials_failed"] == 1
    for m in METHODS:
        ms = s["methods"][m]
        assert ms["n_ok"] == 0 and ms["n_failed"] == 2 and sum(ms["failures"].values()) == 2
        assert ms["rms_error_m"] == dict.fromkeys(COMBINATION_NAMES)
    assert not s["targets"]["efficiency_combined"]["met"]


def test_summary_statistics_from_records():
    """RMS error, mean std, honesty ratio and efficiency computed from the per-trial numbers."""
    rng = np.random.default_rng(3)
    trials = []
    for k in range(6):
        errs = dict(zip(COMBINATION_NAMES, rng.normal(0, 1e-3, 4), strict=True))
        rec = {
            "ok": True,
            "error": None,
            "errors": errs,
            "std": dict.fromkeys(COMBINATION_NAMES, 1e-3),
            "gap_validation_rms_mm": 0.5 + 0.1 * k,
        }
        trials.append(
            {
                "error": None,
                "methods": {"combined": rec},
                "bound_std": dict.fromkeys(COMBINATION_NAMES, 8e-4),
                "gap_a_priori_rms_mm": 0.8,
                "gap_truth_rms_mm": 0.4,
                "edge_noise_px": 0.1 + 0.01 * k,
                "truth_combinations": NOMINAL.combinations(),
                "rods_found": 8,
                "rods_total": 8,
            }
        )
    s = summarize(trials)
    comb = s["methods"]["combined"]
    for c in COMBINATION_NAMES:
        e = np.array([t["methods"]["combined"]["errors"][c] for t in trials])
        rms = float(np.sqrt(np.mean(e**2)))
        assert math.isclose(comb["rms_error_m"][c], rms)
        assert math.isclose(comb["std_over_error"][c], 1e-3 / rms)
        assert math.isclose(comb["efficiency"][c], 8e-4 / rms)
    assert comb["gap_below_a_priori"] == 3  # gaps 0.5, 0.6, 0.7 (< 0.8), 0.8, 0.9, 1.0
    assert math.isclose(s["edge_noise_px_median"], 0.125)
    assert s["a_priori_rms_error_m"] == dict.fromkeys(COMBINATION_NAMES, 0.0)
    assert s["methods"]["legs"]["n_failed"] == 6 and s["methods"]["legs"]["failures"] == {"not run": 6}


def test_options_errors_and_command_line(capsys):
    assert main(["bench", "accuracy", "--sweep", "noise,warp"]) == 2
    err = capsys.readouterr().err
    assert "unknown sweep 'warp'" in err and "--sweep" in err and err.count("\n") == 1
    assert main(["bench", "accuracy", "--sweep-trials", "0"]) == 2
    assert "--sweep-trials" in capsys.readouterr().err
    assert main(["bench", "accuracy", "--sweep-poses", "2,8"]) == 2
    assert "--sweep-poses" in capsys.readouterr().err
    assert main(["bench", "accuracy", "--trials", "0"]) == 2
    assert "nothing to run" in capsys.readouterr().err
    assert main(["bench"]) == 1
    assert "i4cal bench accuracy" in capsys.readouterr().out
    opts = AccuracyOptions(
        trials=20, seed=3, noise_sigma=4.0, sweeps=["poses", "noise"], sweep_noise=[0, 2.5], camera="true"
    )
    assert command_line(opts) == (
        "i4cal bench accuracy --trials 20 --seed 3 --noise 4 --sweep-noise 0,2.5 --camera true --sweep noise,poses"
    )
    assert command_line(AccuracyOptions()) == "i4cal bench accuracy"


def test_lens_sweep_points_and_options(capsys):
    """``--sweep lens``: one point per lens, each trial rendered through its distortion, keyed apart from the others."""
    from i4cal.benchmarks.accuracy import LENSES, lens_dist, study_points

    opts = AccuracyOptions(trials=0, sweeps=["lens"], sweep_trials=2, sweep_lenses=["k3=-0.012", "rational", "k3=0.02"])
    pts = study_points(opts)
    assert [(p.sweep, p.lens) for p in pts] == [("lens", "k3=-0.012"), ("lens", "rational"), ("lens", "k3=0.02")]
    keys = [k for p in pts for k in p.trial_keys()]
    assert len(set(keys)) == 6 and all("lens=" in k for k in keys)
    assert lens_dist("rational") == LENSES["rational"] and len(LENSES["rational"]) == 8
    assert lens_dist("k3=0.02")[4] == 0.02 and lens_dist("k3=0.02")[:4] == LENSES["k3=0"][:4]
    assert command_line(opts).endswith("--sweep-lenses k3=-0.012,rational,k3=0.02 --sweep lens")
    assert main(["bench", "accuracy", "--sweep", "lens", "--sweep-lenses", "fisheye"]) == 2
    assert "unknown lens 'fisheye'" in capsys.readouterr().err
