"""The legs method's seven parameters against the truth on rendered trials (not a timed test): docs/benchmarks.md.

Run:  python benchmarks/bench_legs_seven.py --obs-dir DIR [--seed 3] [--trials 20] [--json PATH]

Trial ``k`` is the accuracy study's (``i4cal bench accuracy --seed SEED``): its plan (the full plan without the line),
its true geometry and render seed, its own 30-view camera phase; rendered and extracted as the study does (about a
minute per trial on one core) and its observations kept in ``DIR/seed{SEED}-trial{k:02d}.json``, so that later runs
(another version of the method) only calibrate. Per trial the legs method's seven parameters: error over the std it
serves (``seven``, ``seven_std``), and the data's own estimate (``diagnostics.identifiability.data_estimate``) along
the three directions of the seven that the four combinations do not see
(:func:`calib.identify.legs.combinations_null_space`), with the data std there when the method reports it
(``not_identified``). Lengths in metres in the JSON, mm in the table.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from calib.formats.observations import Observations
from calib.identify.legs import calibrate_legs, combinations_null_space
from calib.model.parameters import NOMINAL, PARAMETER_NAMES, I4Parameters


def observations(seed: int, k: int, obs_dir: Path) -> dict[str, Any]:
    """Trial ``k`` of the accuracy study at ``seed``: its observations (rendered and extracted once, then kept)."""
    path = obs_dir / f"seed{seed}-trial{k:02d}.json"
    if path.exists():
        return json.loads(path.read_text())
    from calib.vision.extract import extract_dataset
    from drivers.sim.render import RenderSettings
    from drivers.sim.rendered_dataset import simulate_dataset
    from drivers.sim.twin import BenchGeometry
    from i4cal.benchmarks._accuracy_trial import _plan
    from i4cal.benchmarks.accuracy import AccuracyOptions, default_spread_m, draw_truth, plan_steps, trial_seed

    opts = AccuracyOptions(seed=seed)
    truth = I4Parameters.from_vector(draw_truth(seed, k, default_spread_m()), T_per_rad=NOMINAL.T_per_rad)
    with tempfile.TemporaryDirectory(prefix="i4cal-legs-seven-") as tmp:
        ds = simulate_dataset(
            Path(tmp) / "ds",
            seed=trial_seed(seed, k),
            geometry=BenchGeometry(truth=truth),
            render=RenderSettings(),
            plan=_plan(plan_steps(opts, opts.n_fit), "trial"),
            n_camera_views=opts.camera_views,
        )
        doc = extract_dataset(ds, workers=1).observations
    path.write_text(json.dumps(doc))
    return doc


def trial(doc: dict[str, Any]) -> dict[str, Any]:
    """The legs method on one trial's observations: the seven's errors, std and the null-space figures (m)."""
    truth = np.array([doc["truth"]["parameters"][k] for k in PARAMETER_NAMES])
    res = calibrate_legs(Observations.from_dict(doc))
    assert res.parameters is not None and res.parameters_std is not None
    seven = np.array([res.parameters[k] for k in PARAMETER_NAMES])
    std = np.array([res.parameters_std[k] for k in PARAMETER_NAMES])
    ident = res.diagnostics["identifiability"]
    data = np.array([ident["data_estimate"][k] for k in PARAMETER_NAMES])
    N = combinations_null_space()
    dirs = ident.get("not_identified") or []
    return {
        "error_m": dict(zip(PARAMETER_NAMES, (seven - truth).tolist(), strict=True)),
        "std_m": dict(zip(PARAMETER_NAMES, std.tolist(), strict=True)),
        "null_data_error_m": (N.T @ (data - truth)).tolist(),
        "null_data_std_m": [d.get("data_std_m") for d in dirs] if dirs else None,
        "not_identified": [d["label"] for d in dirs],
    }


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    z = np.array([[r["error_m"][k] / r["std_m"][k] for k in PARAMETER_NAMES] for r in rows])
    null = np.array([r["null_data_error_m"] for r in rows])
    nstd = [r["null_data_std_m"] for r in rows if r["null_data_std_m"]]
    return {
        "trials": len(rows),
        "z_rms": dict(zip(PARAMETER_NAMES, np.sqrt(np.mean(z**2, axis=0)).tolist(), strict=True)),
        "z_max": dict(zip(PARAMETER_NAMES, np.abs(z).max(axis=0).tolist(), strict=True)),
        "within_3_std": dict(zip(PARAMETER_NAMES, np.mean(np.abs(z) < 3.0, axis=0).tolist(), strict=True)),
        "error_rms_m": dict(
            zip(
                PARAMETER_NAMES,
                np.sqrt(np.mean(np.array([list(r["error_m"].values()) for r in rows]) ** 2, axis=0)).tolist(),
                strict=True,
            )
        ),
        "std_mean_m": dict(
            zip(PARAMETER_NAMES, np.mean([list(r["std_m"].values()) for r in rows], axis=0).tolist(), strict=True)
        ),
        "null_data_error_mean_m": null.mean(axis=0).tolist(),
        "null_data_error_sd_m": null.std(axis=0, ddof=1).tolist() if len(rows) > 1 else None,
        "null_data_std_mean_m": np.mean(nstd, axis=0).tolist() if nstd else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--obs-dir", required=True, help="where the trials' observations are kept (created)")
    ap.add_argument("--seed", type=int, default=3, help="the accuracy study's seed (default 3)")
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--json", help="write every trial and the summary here")
    args = ap.parse_args()
    obs_dir = Path(args.obs_dir)
    obs_dir.mkdir(parents=True, exist_ok=True)
    rows = [trial(observations(args.seed, k, obs_dir)) for k in range(args.trials)]
    s = summary(rows)
    print(f"legs method, seven parameters, {s['trials']} trials (seed {args.seed})")
    print("param   error RMS mm   mean std mm   |error|/std RMS   max   within 3 std")
    for k in PARAMETER_NAMES:
        print(
            f"{k:5s} {s['error_rms_m'][k] * 1e3:12.2f} {s['std_mean_m'][k] * 1e3:13.2f} {s['z_rms'][k]:17.2f}"
            f" {s['z_max'][k]:6.1f} {s['within_3_std'][k] * 100:10.0f}%"
        )
    mean, sd = s["null_data_error_mean_m"], s["null_data_error_sd_m"] or [float("nan")] * 3
    print("data's estimate along the directions the combinations do not see (H+D, q03+q04, q02/S/q04-q03), mm:")
    print("  error mean " + ", ".join(f"{m * 1e3:+.1f} (sd {d * 1e3:.1f})" for m, d in zip(mean, sd, strict=True)))
    if s["null_data_std_mean_m"]:
        print("  data std (mean) " + ", ".join(f"{v * 1e3:.2f}" for v in s["null_data_std_mean_m"]))
    if args.json:
        Path(args.json).write_text(json.dumps({"seed": args.seed, "trials": rows, "summary": s}, indent=1))


if __name__ == "__main__":
    main()
