"""The lens-model candidates fitted from one shared start (the outlier test's ``k1k2k3`` fit).

On the camera views of a rendered dataset (15 views, 1024x768, as ``i4cal simulate --images`` makes them): each
candidate fitted from the shared start lands where OpenCV's own guess leads (to a small fraction of its standard
deviation), in fewer iterations, and a candidate that a start leads to another minimum is fitted again from OpenCV's
guess. The calibration with the shared start (the default) chooses the same lens model as with every candidate from
OpenCV's own guess, here and on the lens-model tests' views.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

import calib.camera.intrinsics as cc
from tests.calib.test_lens_model import IDS, K3, PLAIN, PTS, _views

#: agreement asked of two fits that reach the same minimum: this fraction of the parameter's standard deviation
#: (OpenCV stops when a step moves the unknowns by less than 1e-12 of themselves; measured: below 3e-6)
SAME_MINIMUM_STD_FRACTION = 0.01


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The full-board views of a rendered dataset's camera phase and the outlier test's ``k1k2k3`` fit."""
    from calib.formats.dataset import Dataset
    from calib.formats.plan import Plan, make_plan
    from calib.model.parameters import NOMINAL
    from calib.vision.board import BoardDetector
    from drivers.sim.rendered_dataset import simulate_dataset

    one_step = Plan.model_validate(
        {"name": "camera", "steps": [make_plan("full", NOMINAL, seed=0).steps[0].model_dump()]}
    )
    ds = Dataset.open(simulate_dataset(tmp_path_factory.mktemp("shared-start") / "ds", seed=0, plan=one_step))
    det = BoardDetector(ds.document.board)
    views = {}
    for i, f in enumerate(ds.frames):
        if f.phase == "camera":
            d = det.detect(ds.load_image(i))
            views[i] = (np.asarray(d.ids, dtype=int), np.asarray(d.pixels).reshape(-1, 2), None)
    size = (ds.document.camera.width, ds.document.camera.height)
    board = cc.select_board_views(views, det.ids_all, det.points_nominal, size)
    board, first = cc.reject_outlier_views(board, "k1k2k3", cc.IntrinsicsSettings())
    assert len(board.keys) == 15, board.rejected
    return views, size, (det.ids_all, det.points_nominal), board, first


def _intrinsics(fit: cc.LensFit) -> np.ndarray:
    """fx, fy, cx, cy (px) and k1..k6, the order of OpenCV's standard deviations."""
    d = np.concatenate([fit.dist, np.zeros(8)])[:8]
    return np.array([fit.K[0, 0], fit.K[1, 1], fit.K[0, 2], fit.K[1, 2], *d])


def _in_std(fit: cc.LensFit, ref: cc.LensFit) -> float:
    """The largest difference of ``fit``'s estimated intrinsics from ``ref``'s, in ``ref``'s standard deviations."""
    idx = [
        ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"].index(n)
        for n in cc.lens_model_params(ref.model)
    ]
    std = ref.std_intrinsics[idx]
    assert np.all(std > 0), (ref.model, std)
    return float(np.max(np.abs(_intrinsics(fit)[idx] - _intrinsics(ref)[idx]) / std))


def test_each_candidate_from_the_shared_start_lands_at_its_own_guess_s_minimum(rendered):
    _, _, _, board, first = rendered
    assert set(cc.SHARED_START_MODELS) == {"k1k2", "k1k2k3", "k1k2-radial", "k1k2k3-radial"}
    fits = cc.fit_lens_candidates(board, list(cc.LENS_MODELS), {"k1k2k3": first}, start=first)
    for model in cc.LENS_MODELS:
        own = cc.fit_lens_model(board, model)
        from_start = cc.fit_lens_model(board, model, start=first)
        assert _in_std(from_start, own) < SAME_MINIMUM_STD_FRACTION, model
        # the shared-start models kept as fitted from the start (not fitted again), the rational ones from OpenCV's
        kept = first if model == "k1k2k3" else from_start if model in cc.SHARED_START_MODELS else own
        assert np.array_equal(fits[model].K, kept.K) and np.array_equal(fits[model].dist, kept.dist), model
        assert _in_std(fits[model], own) < SAME_MINIMUM_STD_FRACTION, model
        assert abs(fits[model].rms_px - own.rms_px) < 1e-9 * own.rms_px, model
        assert np.allclose(fits[model].std_intrinsics, own.std_intrinsics, rtol=1e-3, atol=0), model


@pytest.mark.parametrize("model", ["k1k2", "k1k2-radial", "k1k2k3-radial", "k1k2k3"])
def test_from_the_shared_start_a_candidate_needs_fewer_iterations(rendered, model):
    """Six Levenberg-Marquardt iterations bring a fit from the shared start to the minimum, not one from OpenCV's own
    guess (which needs 12-15 here)."""
    _, _, _, board, first = rendered
    converged = cc.fit_lens_model(board, model)
    from_start = cc.fit_lens_model(board, model, start=first, max_iterations=6)
    from_guess = cc.fit_lens_model(board, model, max_iterations=6)
    assert _in_std(from_start, converged) < SAME_MINIMUM_STD_FRACTION
    assert _in_std(from_guess, converged) > 1.0


def test_a_candidate_a_start_leads_to_another_minimum_is_fitted_from_opencvs_guess(rendered):
    """From a start with k1 = +0.5 (the lens is barrel, k1 = -0.3) the models without tangential terms stop at
    another minimum (RMS 0.55 px instead of 0.10 px); they are fitted again from OpenCV's guess, the others (the
    rational models aside, never fitted from the start) kept."""
    _, _, _, board, first = rendered
    wrong = replace(first, dist=np.array([0.5, 0.0, 0.0, 0.0, 0.0]))
    fits = cc.fit_lens_candidates(board, list(cc.LENS_MODELS), {"k1k2k3": first}, start=wrong)
    for model in cc.LENS_MODELS:
        own = cc.fit_lens_model(board, model)
        from_wrong = cc.fit_lens_model(board, model, start=wrong)
        if model.endswith("-radial"):
            assert from_wrong.rms_px > 2 * own.rms_px, (model, from_wrong.rms_px, own.rms_px)
            assert not cc.at_the_start_s_minimum(from_wrong, wrong, {"k1k2k3": first}, board)
            kept = own
        else:
            assert cc.at_the_start_s_minimum(from_wrong, wrong, {"k1k2k3": first}, board)
            kept = first if model == "k1k2k3" else from_wrong if model in cc.SHARED_START_MODELS else own
        assert np.array_equal(fits[model].K, kept.K) and np.array_equal(fits[model].dist, kept.dist), model
        assert _in_std(fits[model], own) < SAME_MINIMUM_STD_FRACTION, model


def test_a_start_opencv_refuses_leaves_every_candidate_to_opencvs_guess(rendered):
    """A principal point outside the image: OpenCV raises for the start; the candidates are fitted from its guess."""
    _, _, _, board, first = rendered
    K = first.K.copy()
    K[0, 2] = -50.0
    outside = replace(first, K=K)
    with pytest.raises(cv2.error, match="Principal point"):
        cc.fit_lens_model(board, "k1k2", start=outside)
    fits = cc.fit_lens_candidates(board, list(cc.LENS_MODELS), {"k1k2k3": first}, start=outside)
    for model in cc.LENS_MODELS:
        own = first if model == "k1k2k3" else cc.fit_lens_model(board, model)
        assert np.array_equal(fits[model].K, own.K) and np.array_equal(fits[model].dist, own.dist), model


def test_the_calibration_from_the_shared_start_chooses_the_same_lens_model(rendered):
    """The same model chosen and the same candidates' evidence, on the rendered views and on the lens-model tests' (a
    plain lens, a k3 lens, a k3 lens seen only near the centre)."""
    views, size, (ids, pts), _, _ = rendered
    cases = [(views, size, ids, pts)] + [
        (_views(dist, seed, **kw), (1024, 768), IDS, PTS)
        for dist, seed, kw in ((PLAIN, 0, {}), (K3, 1, {}), (K3, 3, {"spread": 0.3, "corners": False}))
    ]
    for v, sz, i, p in cases:
        own = cc.calibrate_intrinsics(v, sz, i, p, lens_model="auto", shared_start=False)
        shared = cc.calibrate_intrinsics(v, sz, i, p, lens_model="auto")
        assert shared.lens_model["chosen"] == own.lens_model["chosen"]
        assert shared.lens_model["lowest_bic"] == own.lens_model["lowest_bic"]
        for a, b in zip(own.lens_model["candidates"], shared.lens_model["candidates"], strict=True):
            assert a["model"] == b["model"] and abs(b["rss_px2"] - a["rss_px2"]) < 1e-9 * a["rss_px2"], (a, b)
        k_std = np.array([own.std[n] for n in ("fx", "fy", "cx", "cy")])
        k_own = own.camera.K[[0, 1, 0, 1], [0, 1, 2, 2]]
        k_shared = shared.camera.K[[0, 1, 0, 1], [0, 1, 2, 2]]
        assert np.all(np.abs(k_shared - k_own) < SAME_MINIMUM_STD_FRACTION * k_std)
        assert all(abs(shared.std[n] - own.std[n]) <= 1e-3 * own.std[n] for n in own.std)
