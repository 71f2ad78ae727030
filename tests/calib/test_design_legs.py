"""Designing for the legs method (calib.design.legs_criterion): its additive criterion is the legs prediction, and a
design for the combined and legs methods aimed at the paper's 20-pose plan beats it on both."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib.design import DesignNoise, DesignRequest, design_plan, phase_q, targets_from_plan
from calib.design.legs_criterion import LegsCriterion
from calib.design.predict_images import predict_legs_images
from calib.errors import InputError
from calib.formats.plan import Plan, make_plan
from calib.model.parameters import COMBINATION_NAMES, NOMINAL


@pytest.fixture(scope="module")
def paper20() -> Plan:
    plan = make_plan("full", NOMINAL, seed=1, n_fit=20, n_lock=5)
    return Plan(name="paper-20", steps=[s for s in plan.steps if s.phase != "line"])


def _lock(plan: Plan) -> list[np.ndarray]:
    return [phase_q(plan, f"lock-{i}") for i in range(1, 5)]


def test_criterion_is_the_legs_prediction_without_the_cameras_parts(scene, noise, paper20):
    """Summed per-pose statistics give the legs prediction itself once the intrinsics and the limb-edge bias, which
    the criterion leaves out, are taken out of the prediction too (no intrinsics, no edge-bias allowance): the
    joints' gain through the fit (-A^-1 B, implicit function) is the prediction's numerical derivative of the whole
    pipeline, the leg directions' sandwich the method's."""
    q_fit = phase_q(paper20, "poses")
    quiet = replace(noise, edge_bias_prior_px=0.0)
    crit = LegsCriterion(NOMINAL, _lock(paper20), scene, quiet)
    stats = crit.pose_statistics(q_fit)
    assert stats.shape == (len(q_fit), 3, 30)
    C4, logdet_info = crit.cov4(stats.sum(axis=0))
    _cov7, C4_pred, parts = predict_legs_images(NOMINAL, q_fit, _lock(paper20), scene, quiet, np.zeros((9, 9)))
    assert not np.any(parts["intrinsics"]) and not np.any(parts["limb_edge_bias"])
    np.testing.assert_allclose(np.sqrt(np.diag(C4)), np.sqrt(np.diag(C4_pred)), rtol=1e-4)
    np.testing.assert_allclose(C4, C4_pred, rtol=1e-3, atol=1e-4 * np.max(np.abs(C4_pred)))
    assert logdet_info == pytest.approx(-np.linalg.slogdet(C4_pred)[1], rel=1e-4)
    # batched: the same for a stack of sums
    both = crit.cov4(np.stack([stats.sum(axis=0), stats[:12].sum(axis=0)]))[0]
    np.testing.assert_allclose(both[0], C4, rtol=1e-12)
    # a pose set that cannot determine (L, S, D): -inf, not an error
    assert crit.cov4(stats[:0].sum(axis=0) + np.zeros((3, 30)))[1] == -np.inf


def test_designed_for_combined_and_legs_beats_the_paper_on_both(scene, noise, paper20):
    """12 fit poses designed for both methods, each aimed at the paper's 20-pose plan's own predicted std: no worse
    than it on every combination of both, in less motion; designed for the combined method alone, the legs method
    is left where the poses put it (worse on a combination than designed for both)."""
    tc = targets_from_plan(paper20, NOMINAL, scene, noise)
    tl = targets_from_plan(paper20, NOMINAL, scene, noise, method="legs")
    base = DesignRequest(n_fit=12, seed=1, n_candidates=600, with_line=False, criterion="target", target_std_m=tc)
    both = design_plan(
        NOMINAL, scene, replace(base, methods=("combined", "legs"), method_targets_m=(("legs", tl),)), noise=noise
    )
    alone = design_plan(NOMINAL, scene, base, noise=noise)

    def ratios(res, m, t):
        return np.array([res.prediction.std[m][c] for c in COMBINATION_NAMES]) / np.asarray(t)

    assert np.all(ratios(both, "combined", tc) <= 1.0), ratios(both, "combined", tc)
    assert np.all(ratios(both, "legs", tl) <= 1.0), ratios(both, "legs", tl)
    assert both.target_met is True
    assert np.max(ratios(alone, "legs", tl)) > np.max(ratios(both, "legs", tl))
    assert both.plan.model_extra["design"]["request"]["method_targets_m"] == {"legs": list(tl)}
    assert "logdet_legs" in both.criterion and np.isfinite(both.criterion["logdet_legs"])
    # the design says how far the legs prediction of plans designed for it went on the twin
    assert any("designed for the legs method" in n and "0.58-1.42x" in n for n in both.notes), both.notes
    assert not any("designed for the legs method" in n for n in alone.notes)


def test_requests_name_what_is_wrong(scene):
    with pytest.raises(InputError) as e:
        DesignRequest(methods=("combined",), target_std_m=1e-4, method_targets_m=(("legs", (1e-4,) * 4),))
    assert e.value.field == "method_targets"
    with pytest.raises(InputError) as e:
        DesignRequest(methods=("combined", "legs"), method_targets_m=(("legs", (1e-4,) * 4),))
    assert e.value.field == "target_std"
    with pytest.raises(InputError) as e:
        DesignRequest(methods=("legs",), target_std_m=1e-4, method_targets_m=(("legs", (1e-4, 0.0, 1e-4, 1e-4)),))
    assert e.value.field == "method_targets"
    # the legs criterion is the image-level model's
    with pytest.raises(InputError) as e:
        design_plan(NOMINAL, scene, DesignRequest(n_fit=8, methods=("legs",), n_candidates=50), noise=DesignNoise())
    assert e.value.field == "methods"
