"""A bench whose geometry is far from nominal: the rods' prediction refitted to the first pass (calib.vision.repredict).

The geometry is the design benchmark's trial 47 (seed 0): D 15 mm below nominal, the other six a few mm off. Its
nominal prediction of the rods is 15-30 px off, beyond the 18 px search band: on the code before the refit, the
extraction lost 56 of the 496 rods of that trial and took others for the wrong edge pair (up to 76 px from the true
rod), and the legs method's estimate and std were 4-7 mm.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib.model.parameters import NOMINAL, I4Parameters
from calib.numerics.transforms import Rigid
from calib.vision.extract import ROD_PHASES, ExtractOptions, _first_sample, extract_dataset
from calib.vision.handeye import fit_placement
from calib.vision.repredict import MeasuredRod, prediction_shift_px, refit_prediction, rod_ends_camera
from drivers.sim.rendered_dataset import simulate_dataset
from drivers.sim.twin import BenchGeometry
from tests.calib.vision._far_bench import exact_boards, far_plan, lost_and_far

#: the design benchmark's trial 47 (i4cal.benchmarks.accuracy.draw_truth(0, 47, default spread)), metres
TRUTH = I4Parameters.from_vector(
    [0.40385660714828314, 1.386133281760735, 0.0010519741715442228, 1.3874446821661581, 0.061482799100059084,
     0.03856379125348636, 0.9997719015038695],
    T_per_rad=NOMINAL.T_per_rad,
)  # fmt: skip
K = np.array([[774.0, 0.0, 512.0], [0.0, 774.0, 384.0], [0.0, 0.0, 1.0]])


def test_refit_brings_the_prediction_onto_the_rods():
    """Exact measurements of a far-from-nominal bench: the nominal model with its coarse placement predicts the rods
    more than 10 px off (median); refitted, within 0.1 px, and the frames it moved are those above the threshold."""
    g = BenchGeometry(truth=TRUTH)
    q = np.array([s.q for s in far_plan().steps if s.phase in ("rotation", "poses")])
    boards = exact_boards(g, q)
    top, bottom, _ = rod_ends_camera(TRUTH, q, g.camera_from_base, g.rod_spacing_m)
    u = (bottom - top) / np.linalg.norm(bottom - top, axis=-1, keepdims=True)
    rods = [MeasuredRod(k, i, j, top[k, i, j], u[k, i, j]) for k in range(len(q)) for i in range(4) for j in range(2)]
    bR = np.array([b.R for b in boards.values()])
    bt = np.array([b.t for b in boards.values()])
    C, E, _ = fit_placement(q, bR, bt, NOMINAL, float(g.ee_from_board.t[2]))
    fit = refit_prediction(NOMINAL, q, rods, boards, C, E, 774.0, g.rod_spacing_m, float(g.ee_from_board.t[2]))
    assert fit is not None
    assert fit.median_px_before > 10.0, fit.summary()
    assert fit.median_px_after < 0.1, fit.summary()
    first = rod_ends_camera(NOMINAL, q, C, g.rod_spacing_m)[:2]
    second = rod_ends_camera(fit.parameters, q, fit.camera_from_base, g.rod_spacing_m)[:2]
    true = (top, bottom)
    assert np.median(prediction_shift_px(K, (1024, 768), first, true)) > 10.0
    assert np.max(prediction_shift_px(K, (1024, 768), second, true)) < 1.0


def test_refit_declines_without_enough_rods():
    fit = refit_prediction(NOMINAL, np.zeros((0, 4)), [], {}, Rigid.identity(), Rigid.identity(), 774.0, 0.06)
    assert fit is None


@pytest.mark.slow
def test_far_bench_keeps_its_rods(tmp_path):
    """Rendered images of the far bench: with one pass on the nominal prediction rods are lost or taken for another
    edge pair (measured: 45 lost, 3 beyond their bound, of 248); with the refit every rod is found and lies within its
    own covariance's 99.9% bound of the truth."""
    g = BenchGeometry(truth=TRUTH)
    root = simulate_dataset(tmp_path / "ds", seed=3, geometry=g, plan=far_plan(), n_camera_views=0)
    doc = json.loads((root / "dataset.json").read_text())
    doc["camera"]["K"], doc["camera"]["dist"] = doc["truth"]["K"], doc["truth"]["dist"]
    (root / "dataset.json").write_text(json.dumps(doc))

    def outcome(opts: ExtractOptions) -> tuple[int, int, dict]:
        res = extract_dataset(root, workers=1, options=opts)
        return (*lost_and_far(res.observations, TRUTH, g), res.summary.get("repredicted") or {})

    lost_old, far_old, _ = outcome(ExtractOptions(repredict_px=None, recover_lost_share=None))
    assert lost_old + far_old >= 20, (lost_old, far_old)  # the trap is real: one pass on the nominal prediction fails
    lost, far, info = outcome(ExtractOptions())
    assert info["applied"] and info["median_px_before"] > 10.0, info
    assert lost == 0 and far == 0, (lost, far, info)


@pytest.mark.slow
def test_a_first_pass_on_a_sample_of_frames_keeps_every_rod(tmp_path, monkeypatch):
    """The far bench's first pass on the nominal prediction measures every third frame; the refit from that sample
    brings the prediction onto every rod: each frame's rods are measured once on it (the sampled ones again), fewer
    measurements than a full first pass and every rod found within its own covariance's 99.9% bound of the truth."""
    from tests.calib.vision.test_refine import _count_rods_tasks

    g = BenchGeometry(truth=TRUTH)
    root = simulate_dataset(tmp_path / "ds", seed=3, geometry=g, plan=far_plan(), n_camera_views=0)
    doc = json.loads((root / "dataset.json").read_text())
    doc["camera"]["K"], doc["camera"]["dist"] = doc["truth"]["K"], doc["truth"]["dist"]
    (root / "dataset.json").write_text(json.dumps(doc))
    measured = _count_rods_tasks(monkeypatch)
    opts = ExtractOptions(first_pass_every=3, first_pass_min_frames=8, recover_lost_share=None)
    res = extract_dataset(root, workers=1, options=opts)
    lost, far = lost_and_far(res.observations, TRUTH, g)
    info = res.summary["repredicted"]
    frames = len(res.observations["frames"])
    sample = {it[0] for it in _first_sample([(k,) for k in range(frames)], opts)}  # one in 3, spread evenly
    read = {k for k, f in enumerate(res.observations["frames"]) if f["phase"] in ROD_PHASES}
    assert info["first_sample_frames"] == len(sample), info
    # measured on the refit only: the frames out of the sample whose rods go into the observations
    assert info["median_px_before"] > 10.0 and info["frames_measured_on_the_refit_only"] == len(read - sample), info
    assert len(measured) < 2 * frames  # a full first pass on the nominal prediction, then again on the refit: 2x
    assert lost == 0 and far == 0, (lost, far, info)
