"""Experiment design (calib.design): predictions against a seeded Monte-Carlo on the geometric twin, the pose-set
optimiser against the paper's pose sets, visibility, motion time, plans that validate."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from calib.design import (
    DesignNoise,
    DesignRequest,
    MotionSpec,
    Scene,
    design_plan,
    log_det_information,
    move_time,
    order_tour,
    phase_q,
    plan_motion_time,
    predict_plan,
    visibility,
)
from calib.formats.observations import Observations
from calib.formats.plan import Plan, make_plan, validate_plan
from calib.identify import calibrate_combined, calibrate_end_effector, calibrate_legs
from calib.identify.legs import joint_from_planes
from calib.model.parameters import COMBINATION_NAMES, NOMINAL
from drivers.sim.render import RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin, NoiseSpec

#: the comparison's tolerance (the issue's): predicted std within 30% of the empirical spread
TOL = 0.30


def twin_scene(**camera) -> Scene:
    """The camera, mounting, board and rods the geometric and image-level twins use."""
    g = BenchGeometry()
    rs = RenderSettings(**camera)
    return Scene(
        rs.camera(),
        g.camera_from_base,
        g.ee_from_board,
        rs.board.size_m,
        rs.board_margin_m,
        g.rod_radius_m,
        g.rod_spacing_m,
    )


@pytest.fixture(scope="module")
def scene() -> Scene:
    return twin_scene()


@pytest.fixture(scope="module")
def designed(scene):
    """A designed plan of 12 fit poses (small lock phases, no line, no validation: what the fits use)."""
    req = DesignRequest(n_fit=12, n_lock=4, n_validation=0, with_line=False, n_candidates=150, seed=3)
    return design_plan(NOMINAL, scene, req)


#: Monte-Carlo draws per method. The sample std's relative standard error is 1/sqrt(2(n-1)); the comparison's
#: tolerance is 2.5 of them (a right prediction fails about 1% of the time per combination): 30 draws -> 0.33
N_TRIALS = 30
TOL_MC = 2.5 / np.sqrt(2 * (N_TRIALS - 1))
FITS = {
    ("combined", "frobenius"): calibrate_combined,  # the method's own choice for rods without a covariance
    ("combined", "gls"): lambda o: calibrate_combined(o, weighting="gls"),
    ("end-effector", "gls"): calibrate_end_effector,
    ("legs", "gls"): calibrate_legs,
}


@pytest.fixture(scope="module")
def paper12() -> Plan:
    """The paper's plan generator with 12 fit poses (small lock phases, no line, no validation)."""
    plan = make_plan("full", NOMINAL, seed=0, n_fit=12, n_lock=4, n_validation=2)
    return Plan(name="paper-12", steps=[s for s in plan.steps if s.phase not in ("line", "validation")])


@pytest.fixture(scope="module")
def monte_carlo(designed, paper12) -> dict[tuple[str, str], tuple[Plan, np.ndarray]]:
    """Errors of every method on N_TRIALS seeded noisy data sets: the combined and end-effector methods on the
    designed plan, the legs method on the paper's 12-pose plan (on the designed plan its L spread is heavy-tailed:
    docs/design.md)."""
    twin = GeometricTwin(noise=NoiseSpec())
    t4 = twin.geometry.truth.combinations()
    truth = np.array([t4[k] for k in COMBINATION_NAMES])
    plans = {k: (paper12 if k[0] == "legs" else designed.plan) for k in FITS}
    out: dict[tuple[str, str], list[np.ndarray]] = {k: [] for k in FITS}
    for s in range(N_TRIALS):
        docs = {}
        for key, fit in FITS.items():
            plan = plans[key]
            if plan.name not in docs:
                docs[plan.name] = Observations.from_dict(twin.observations(plan=plan, seed=2000 + s))
            out[key].append(fit(docs[plan.name]).vector() - truth)
    return {k: (plans[k], np.asarray(v)) for k, v in out.items()}


def test_enough_trials_for_the_comparison():
    # the Monte-Carlo tolerance is derived from the draws (2.5 standard errors of the sample std) and stays within
    # a third of the predicted std: a prediction off by 40% or more would fail
    assert TOL_MC <= 1.0 / 3.0


@pytest.mark.slow
@pytest.mark.parametrize(("method", "weighting"), list(FITS))
def test_prediction_matches_monte_carlo(designed, scene, monte_carlo, method, weighting):
    """Predicted std of each combination within TOL_MC (2.5 standard errors of the sample std of N_TRIALS draws) of
    the spread of the method's estimates over seeded noisy data sets of the geometric twin (default noise), 12 fit
    poses."""
    plan, errors = monte_carlo[(method, weighting)]
    pred = predict_plan(plan, NOMINAL, scene, DesignNoise(), methods=(method,), weighting=weighting)
    assert not pred.errors
    predicted = np.array([pred.std[method][k] for k in COMBINATION_NAMES])
    ratio = errors.std(axis=0, ddof=1) / predicted
    print(method, weighting, "empirical / predicted std:", np.round(ratio, 3))
    assert np.all(np.abs(ratio - 1.0) < TOL_MC), (method, weighting, np.round(ratio, 3))


def test_prediction_scales_with_the_noise(designed, scene):
    base = predict_plan(designed.plan, NOMINAL, scene, DesignNoise())
    twice = predict_plan(designed.plan, NOMINAL, scene, DesignNoise(1e-3, 1e-3, 6e-4, (2e-4, 2e-4, 6e-4), 2e-6))
    for m in ("combined", "end-effector", "legs"):
        for k in COMBINATION_NAMES:
            assert twice.std[m][k] == pytest.approx(2 * base.std[m][k], rel=1e-3), (m, k)


def test_designed_plan_validates_and_round_trips(designed, tmp_path):
    plan = designed.plan
    validate_plan(plan, NOMINAL)
    path = tmp_path / "plan.json"
    plan.save(path)
    back = Plan.load(path)
    validate_plan(back, NOMINAL)
    assert back.count()["poses"] == 12 and back.count()["lock-1"] == 4
    assert back.model_extra["design"]["prediction"]["std_m"]["combined"]["L"] > 0


def test_every_chosen_pose_keeps_the_board_and_the_rods_in_view(designed, scene):
    plan = designed.plan
    q = phase_q(plan, "poses")
    v = visibility(scene, NOMINAL, q)
    assert v["ok"].all()
    # independently: every board outline corner projects inside the image, every rod spans >= min_rod_px
    from calib.design.scene import board_outline

    for cb in scene.camera_from_board(NOMINAL, np.array([s for s in _poses(q)])):
        px = scene.camera.project(cb.apply(board_outline(scene)))
        assert np.all((px >= 0) & (px < [scene.camera.width, scene.camera.height]))
    assert np.all(v["rod_px"] >= scene.limits.min_rod_px)


def _poses(q: np.ndarray) -> np.ndarray:
    from calib.model.kinematics import dkm

    return dkm(NOMINAL, q)


def test_visibility_binds_with_a_narrow_camera():
    """A camera with 1.4 times the focal length sees half the field: candidates are rejected, and the
    designed poses are all in view of that camera."""
    narrow = twin_scene(fx=1.4 * RenderSettings().fx, fy=1.4 * RenderSettings().fy)
    res = design_plan(
        NOMINAL, narrow, DesignRequest(n_fit=8, n_lock=2, n_validation=0, with_line=False, n_candidates=200)
    )
    assert res.candidates["visible"] < 0.8 * res.candidates["drawn"], res.candidates
    assert visibility(narrow, NOMINAL, phase_q(res.plan, "poses"))["ok"].all()
    assert visibility(twin_scene(), NOMINAL, phase_q(res.plan, "poses"))["ok"].all()


def test_d_criterion_beats_the_paper_plan_and_grows_with_the_count(scene):
    """At equal fit-pose counts the designed plan's D-criterion (log det of the combined method's information
    on the four combinations) is at least the paper's plan's, and it grows with the count."""
    got = []
    for n in (8, 12, 20, 30):
        res = design_plan(
            NOMINAL, scene, DesignRequest(n_fit=n, n_lock=2, n_validation=0, with_line=False, n_candidates=120)
        )
        d = log_det_information(res.plan, NOMINAL, scene)["combined"]
        paper = log_det_information(make_plan("full", NOMINAL, seed=0, n_fit=n), NOMINAL, scene)["combined"]
        assert d >= paper, (n, d, paper)
        got.append(d)
    assert all(b > a for a, b in itertools.pairwise(got)), got


def test_target_and_time_pick_the_smallest_plan(scene):
    """With a target and no count the design returns the smallest count whose prediction meets it."""
    req = DesignRequest(target_std_m=3e-4, n_lock=2, n_validation=0, with_line=False, n_candidates=120)
    res = design_plan(NOMINAL, scene, req)
    assert res.target_met
    assert max(res.prediction.std["combined"].values()) <= 3e-4
    fewer = design_plan(NOMINAL, scene, DesignRequest(**{**req.__dict__, "n_fit": res.n_fit - 1, "target_std_m": None}))
    assert max(fewer.prediction.std["combined"].values()) > 3e-4 * 0.98  # one pose less does not (or barely) meet it


def test_trapezoidal_move_times():
    spec = MotionSpec(speed_m_s=0.1, accel_m_s2=1.0)
    # long move: cruise; short move: triangle; the slowest axis sets the time
    assert move_time(np.zeros(4), np.array([0.5, 0, 0, 0]), spec) == pytest.approx(0.5 / 0.1 + 0.1 / 1.0)
    assert move_time(np.zeros(4), np.array([0.004, 0.001, 0, 0]), spec) == pytest.approx(2 * np.sqrt(0.004))
    rng = np.random.default_rng(0)
    q = rng.uniform(0, 0.7, (15, 4))
    order = order_tour(q, spec)
    assert sorted(order.tolist()) == list(range(15))
    t_tour = move_time(q[order][:-1], q[order][1:], spec).sum()
    t_given = move_time(q[:-1], q[1:], spec).sum()
    assert t_tour < t_given


def test_plan_motion_time_counts_every_move():
    plan = make_plan("full", NOMINAL, seed=0)
    spec = MotionSpec(speed_m_s=0.05, accel_m_s2=0.5, settle_s=0.1)
    mt = plan_motion_time(plan, spec, NOMINAL)
    assert mt["total_s"] == pytest.approx(sum(mt["per_phase_s"].values()))
    frames = sum(1 for s in plan.steps if s.q is not None)
    slower = plan_motion_time(plan, MotionSpec(speed_m_s=0.025, accel_m_s2=0.5, settle_s=0.1), NOMINAL)
    assert slower["total_s"] > mt["total_s"] > frames * 0.1


def test_tighter_soft_limits_shorten_the_line_and_the_plan_validates(scene):
    """With a real bench's limits (0-750 mm) the paper's 500 mm line leaves them: the design shortens it, and every
    step of the plan (line samples included) passes validate_plan for those limits."""
    from calib.formats.plan import SoftLimits

    limits = SoftLimits(q_min=[0.0] * 4, q_max=[0.75] * 4)
    with pytest.raises(Exception, match="outside the soft limits"):
        validate_plan(make_plan("line", NOMINAL), NOMINAL, limits)
    res = design_plan(NOMINAL, scene, DesignRequest(n_fit=6, n_lock=2, n_validation=2, n_candidates=80), limits=limits)
    validate_plan(res.plan, NOMINAL, limits)
    assert res.plan.count().get("line", 0) > 0 and any("shortened" in n for n in res.notes)


# -- on rendered images ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rendered(scene, tmp_path_factory):
    """A designed plan of 12 fit poses rendered by the image-level twin with its own camera phase (20 board views),
    extracted (camera calibrated from those views, rods, boards), as the accuracy benchmark does per trial."""
    import cv2

    from calib.vision.extract import extract_dataset
    from drivers.sim.rendered_dataset import simulate_dataset

    cv2.setNumThreads(1)
    req = DesignRequest(n_fit=12, n_base=8, n_lock=4, n_validation=0, with_line=False, n_candidates=150, seed=0)
    plan = design_plan(NOMINAL, scene, req).plan
    ds = simulate_dataset(tmp_path_factory.mktemp("design-rendered") / "ds", seed=5, plan=plan, n_camera_views=20)
    res = extract_dataset(ds, workers=1)
    return plan, Observations.from_dict(res.observations), res.observations


def _image_noise(doc: dict):
    from calib.design import ImageNoise

    cal = doc["extraction"]["camera"]["calibration"]
    return ImageNoise().with_intrinsics(np.asarray(cal["covariance"]), tuple(cal["covariance_params"]))


def _rod_sets(plan, doc, scene, edge_px):
    """The synthetic rods of the fit poses and the set (pose, leg 0-3, rod) the extraction measured."""
    from calib.design import synthetic_rods

    frames = [f for f in doc["frames"] if f["phase"] == "poses"]
    rods = synthetic_rods(scene, NOMINAL, phase_q(plan, "poses"), edge_px)
    measured = {
        (k, int(leg) - 1, j)
        for k, f in enumerate(frames)
        for leg, rr in f["legs"].items()
        for j, r in enumerate(rr)
        if r
    }
    return frames, rods, measured


def test_synthetic_rods_are_the_extracted_ones(rendered, scene):
    """The rods the prediction builds for the fit poses are those the extraction measures (all of them; it misses a
    few: limb edges too scattered, a neighbour's image taken), with the direction covariance it reports (median
    ratio of the principal std within 30%: the edge noise level is the rendered one, ImageNoise.edge_px)."""
    plan, _obs, doc = rendered
    frames, rods, measured = _rod_sets(plan, doc, scene, _image_noise(doc).edge_px)
    synthetic = set(zip(rods.k.tolist(), rods.leg.tolist(), rods.rod.tolist(), strict=True))
    assert measured <= synthetic
    assert len(measured) >= 0.9 * len(synthetic), (len(measured), len(synthetic))
    for field in ("cov_u", "cov_u_own"):
        ratio = []
        for a in range(len(rods)):
            r = frames[rods.k[a]]["legs"][str(rods.leg[a] + 1)][rods.rod[a]]
            if r:
                ratio.append(
                    np.sqrt(
                        np.linalg.eigvalsh(np.asarray(r[field]))[1:] / np.linalg.eigvalsh(getattr(rods, field)[a])[1:]
                    )
                )
        med = np.median(ratio, axis=0)
        print(f"extracted / synthetic {field} principal std, median:", np.round(med, 3))
        assert np.all(np.abs(med - 1.0) < TOL), (field, med)
    # the five limb samples sit where the extraction puts them (the means of five equal-count bins of edge points,
    # 0.1 .. 0.9 of the span): the span from the first to the last, median over the rods, 0.93 here (the visible
    # parts are a little shorter than predicted); 0.74 when the prediction put them at the span's ends
    ends = []
    for a in range(len(rods)):
        r = frames[rods.k[a]]["legs"][str(rods.leg[a] + 1)][rods.rod[a]]
        if r:
            lm, lp = np.asarray(r["limbs_px"]), rods.limbs_px[a]
            span_m = np.linalg.norm(lm[:, 4] - lm[:, 0], axis=-1)
            span_p = np.linalg.norm(lp[:, 4] - lp[:, 0], axis=-1)
            ends.append(span_m / span_p)
    span_ratio = float(np.median(ends))
    print("extracted / synthetic span of the limb samples, median:", round(span_ratio, 3))
    assert abs(span_ratio - 1.0) < 0.12, span_ratio
    # the legs method's limb-line noise (how it weighs its lock phases' planes, pivoted about the rod's point) is the
    # same for the synthetic rods as for the extracted ones. Before the synthetic point was put where the extraction
    # reports it (the limbs' image middle, not the 3-D middle of the visible axis) the synthetic offsets' variance
    # was 1.3x the extracted here (median ratio 0.755), 1.6-1.9x on the paper plan's lock phases; now 1.08. The
    # angles' ratio, 1.25 now, follows the extracted limbs' shorter spans (0.92 of the synthetic: 0.92^-3 = 1.28)
    from calib.identify.legs import limb_line_noise

    K = scene.camera.K
    Kx = np.asarray(doc["extraction"]["camera"]["K"], dtype=np.float64)
    edge_px = _image_noise(doc).edge_px
    lines = []
    for a in range(len(rods)):
        r = frames[rods.k[a]]["legs"][str(rods.leg[a] + 1)][rods.rod[a]]
        if r:
            _, vm = limb_line_noise(
                Kx,
                np.asarray(r["h"]),
                np.asarray(r["point"]),
                np.asarray(r["rms_px"]),
                np.asarray(r["n_points"]),
                np.asarray(r["cov_u"]),
                frame_bias=False,
            )
            _, vp = limb_line_noise(
                K, rods.h[a], rods.point[a], np.full(2, edge_px), rods.n_points[a], rods.cov_u[a], frame_bias=False
            )
            lines.append(vm.sum(axis=0) / vp.sum(axis=0))
    line_ratio = np.median(lines, axis=0)
    print("extracted / synthetic limb-line variance (angle, offset), median:", np.round(line_ratio, 3))
    assert abs(line_ratio[0] - 1.0) < TOL and abs(line_ratio[1] - 1.0) < 0.15, line_ratio


def test_image_prediction_is_the_combined_methods_uncertainty(rendered, scene):
    """On a rendered dataset the image-level prediction for the rods the run used (the extraction's, less those the
    method rejected) equals the std the combined method reports, within 30%: it models the method's weighting (rods'
    cov_u times its measured scale), its intrinsics and limb-edge nuisances and its base-frame prior. The old
    prediction (geometric twin's noise, no nuisances) was 1.4-2.6x off on such data."""
    from calib.design.predict_images import predict_combined_images

    plan, obs, doc = rendered
    noise = _image_noise(doc)
    _frames, rods, measured = _rod_sets(plan, doc, scene, noise.edge_px)
    r = calibrate_combined(obs)
    fit_idx = [i for i, f in enumerate(doc["frames"]) if f["phase"] == "poses"]
    rejected = {(fit_idx.index(x["frame"]), x["leg"] - 1, x["rod"]) for x in r.diagnostics["rods_rejected"]}
    synthetic = set(zip(rods.k.tolist(), rods.leg.tolist(), rods.rod.tolist(), strict=True))
    cov, _post = predict_combined_images(
        NOMINAL,
        phase_q(plan, "poses"),
        phase_q(plan, "rotation"),
        phase_q(plan, "translation"),
        scene,
        noise,
        drop=(synthetic - measured) | rejected,
    )
    ratio = np.sqrt(np.diag(cov)) / r.std_vector()
    print("combined, predicted / reported std:", np.round(ratio, 3), "rods rejected by the fit:", len(rejected))
    assert np.all(np.abs(ratio - 1.0) < TOL), ratio
    old = predict_plan(plan, NOMINAL, scene, DesignNoise(), methods=("combined",))
    old_ratio = np.array([old.std["combined"][k] for k in COMBINATION_NAMES]) / r.std_vector()
    assert np.any(np.abs(old_ratio - 1.0) > TOL), old_ratio  # the check can tell a wrong model


def test_image_prediction_scales_with_the_image_noise(designed, scene):
    """Without a camera covariance, edge biases or the joints' systematic depth, every image-level std is
    proportional to the edge and corner noise together (rods' cov_u and boards' PnP covariance both scale with their
    square)."""
    from calib.design import ImageNoise

    kw = {
        "edge_bias_px": 0.0,
        "edge_bias_prior_px": 0.0,
        "legs_prior_std_m": None,
        "encoder_m": 0.0,
        "legs_joint_depth_sys_m": 0.0,
    }
    base = predict_plan(designed.plan, NOMINAL, scene, ImageNoise(edge_px=0.1, corner_px=0.05, **kw))
    twice = predict_plan(designed.plan, NOMINAL, scene, ImageNoise(edge_px=0.2, corner_px=0.1, **kw))
    assert not base.errors and base.noise["model"] == "images"
    for m in ("combined", "end-effector", "legs"):
        for k in COMBINATION_NAMES:
            assert twice.std[m][k] == pytest.approx(2 * base.std[m][k], rel=1e-3), (m, k)


def test_image_prediction_parts_add_up_to_the_std(designed, scene):
    """The parts each source of error contributes (what ``i4cal plan design --breakdown`` prints) are independent:
    their variances add up to the predicted variance, per method and combination; the legs' include the lock
    phases' systematic depth error, and that part scales with its level."""
    from calib.design import ImageNoise

    pred = predict_plan(designed.plan, NOMINAL, scene, ImageNoise())
    assert set(pred.parts) == {"end-effector", "legs"}
    assert {"joint_centres", "joint_depth_systematic", "leg_directions", "intrinsics"} <= set(pred.parts["legs"])
    for m, parts in pred.parts.items():
        for k in COMBINATION_NAMES:
            total = sum(p[k] ** 2 for p in parts.values())
            assert total == pytest.approx(pred.std[m][k] ** 2, rel=1e-9), (m, k)
    assert pred.to_dict()["parts_std_m"] == pred.parts
    sys_m = ImageNoise().legs_joint_depth_sys_m
    half = predict_plan(designed.plan, NOMINAL, scene, ImageNoise(legs_joint_depth_sys_m=sys_m / 2))
    for k in COMBINATION_NAMES:
        assert pred.parts["legs"]["joint_depth_systematic"][k] > 0
        assert half.parts["legs"]["joint_depth_systematic"][k] == pytest.approx(
            pred.parts["legs"]["joint_depth_systematic"][k] / 2, rel=1e-6
        )


def test_image_noise_rejects_bad_levels():
    from calib.design import ImageNoise
    from calib.errors import InputError

    with pytest.raises(InputError, match="edge_px"):
        ImageNoise(edge_px=0.0)
    with pytest.raises(InputError, match="intrinsics_cov"):
        ImageNoise(intrinsics_names=("fx", "fy"), intrinsics_cov=((1.0, 0.0), (0.0, -1.0)))
    with pytest.raises(InputError, match="rod_distance_correlation"):
        ImageNoise(rod_distance_correlation=1.0)
    with pytest.raises(InputError, match="rod_pair_correlation"):
        ImageNoise(rod_pair_correlation=-0.1)
    with pytest.raises(InputError, match="edge_bias_length_px"):
        ImageNoise(edge_bias_length_px=float("nan"))


def test_designed_12_beats_the_paper_20_on_images(scene):
    """The design's target, as predicted on images (the image-level twin's camera, its calibration from 30 views): the
    plan designed with 12 fit poses gives the combined method a std no larger than the paper's 20-pose plan for
    each of the four combinations, and takes less motion time."""
    from service.design import twin_image_noise

    noise = twin_image_noise()
    res = design_plan(NOMINAL, scene, DesignRequest(n_fit=12, with_line=False, seed=0), noise=noise)
    paper = make_plan("full", NOMINAL, seed=0, n_fit=20)
    paper = Plan(name="paper-20", steps=[s for s in paper.steps if s.phase != "line"])
    a = res.prediction.std["combined"]
    b = predict_plan(paper, NOMINAL, scene, noise, methods=("combined",)).std["combined"]
    print({k: (round(a[k] * 1e3, 3), round(b[k] * 1e3, 3)) for k in COMBINATION_NAMES})
    assert all(a[k] <= b[k] for k in COMBINATION_NAMES), (a, b)
    assert res.motion["total_s"] < plan_motion_time(paper, MotionSpec(), NOMINAL)["total_s"]


def test_target_met_is_judged_on_the_plans_prediction(scene):
    """``target_met`` says what the plan's prediction says. The exchange ranks poses by their information without the
    rods' correlations; on images the plan's prediction (the method's own uncertainty) is larger, so a target judged on
    the exchange's information alone would be "met" by a plan whose prediction misses it. The count is chosen again, the
    exchange's targets tightened by the prediction's miss, until the prediction meets the target or the count reaches
    its maximum (and beyond it as far as the trend of the prediction over the count says:
    ``tests/calib/test_count_trend.py``)."""
    from service.design import twin_image_noise

    noise = twin_image_noise()
    base = DesignRequest(n_lock=2, n_validation=0, with_line=False, n_candidates=300)
    target = 6.5e-5  # one the count search meets (past its most: tests/calib/test_count_trend.py)
    res = design_plan(NOMINAL, scene, replace(base, target_std_m=target), noise=noise)
    got = res.prediction.std["combined"]
    print(target, res.n_fit, {k: round(v * 1e3, 4) for k, v in got.items()}, res.notes)
    assert res.target_met is (max(got.values()) <= target * (1 + 1e-9)), (target, res.target_met, got)
    assert res.target_met, (res.n_fit, got, res.notes)
    # the smallest count that meets it, give or take the exchange: a few poses fewer miss it
    fewer = design_plan(NOMINAL, scene, replace(base, n_fit=res.n_fit - 3), noise=noise)
    assert max(fewer.prediction.std["combined"].values()) > target, fewer.prediction.std["combined"]


def test_lock_phase_frames_are_weighed_by_their_own_noise(rendered):
    """The legs method weighs each lock frame's planes by the edge scatter alone: the extraction's edge-bias allowance
    does not vary between the frames of a lock phase (the rod barely moves against its background), so counted per
    frame it claimed noise the residuals do not show (chi-square per dof 0.30, median of 17 rendered trials of a
    designed plan; 1.5 without it) and overstated the joints' std along the rods 2-2.7-fold. Median over the eight
    rods (a rod taken for another edge in some frames is far off either way)."""
    from calib.identify.legs.joints import _plane_observations

    _plan, obs, _doc = rendered
    per_rod = []
    for i in range(4):
        d = obs.arrays(f"lock-{i + 1}")
        for j in range(2):
            planes = _plane_observations(obs, d, i, j)
            assert planes is not None and all(p.var is not None for p in planes)
            per_rod.append(float(np.sum(joint_from_planes(planes)[2])) / (2 * len(planes) - 3))
    assert 0.7 < float(np.median(per_rod)) < 3.0, np.round(per_rod, 2)


def test_legs_prediction_carries_the_methods_chi_square_levels(rendered, scene):
    """The legs method scales its joints' covariance by its lock phases' chi-square per dof and its leg directions'
    by its fit poses' chi-square over what their own errors and the joints' make it expect (never below 1); the
    prediction by their levels on the twin (``ImageNoise.legs_lock_chi2``, ``legs_directions_chi2``). Without them
    (both 1, the old prediction) its std was 0.69-0.82x the legs method's RMS error on a designed plan of `i4cal bench
    design` (50 trials). Here: the rendered dataset's lock chi-square is at the default level (its spread over 64
    rendered trials: 1.16-1.73, sd 0.15), and the prediction's joints' and leg directions' parts are those of the noise
    model times the levels."""
    from calib.design import ImageNoise
    from calib.design.predict_images import predict_combined_images_posteriors, predict_legs_images

    plan, obs, doc = rendered
    r = calibrate_legs(obs)
    level = ImageNoise().legs_lock_chi2
    assert abs(r.diagnostics["step1_chi2_per_dof"] - level) < 4 * 0.15, (r.diagnostics["step1_chi2_per_dof"], level)
    # the fit poses' chi-square is reported before its floor at 1 too, with its expectation (the bench averages it)
    raw, expected = r.diagnostics["steps34_residual_chi2_per_dof"], r.diagnostics["steps34_expected_chi2_per_dof"]
    assert expected is not None and expected > 0
    assert r.diagnostics["steps34_chi2_per_dof"] == pytest.approx(max(raw / expected, 1.0), rel=1e-12), (raw, expected)
    q_fit = phase_q(plan, "poses")
    locks = [phase_q(plan, f"lock-{i}") for i in range(1, 5)]
    parts = {}
    for a, b in ((1.0, 1.0), (1.5, 2.0)):
        noise = _image_noise(doc)
        noise = replace(noise, legs_lock_chi2=a, legs_directions_chi2=b, legs_prior_std_m=None)
        _c, post, edge = predict_combined_images_posteriors(
            NOMINAL, q_fit, phase_q(plan, "rotation"), phase_q(plan, "translation"), scene, noise
        )
        parts[a] = predict_legs_images(NOMINAL, q_fit, locks, scene, noise, post, edge)[2]
    np.testing.assert_allclose(parts[1.5]["joint_centres"], 1.5 * parts[1.0]["joint_centres"], rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(parts[1.5]["leg_directions"], 2.0 * parts[1.0]["leg_directions"], rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(parts[1.5]["intrinsics"], parts[1.0]["intrinsics"], rtol=1e-9, atol=1e-18)
    # with the levels, the prediction is the method's reported std on this dataset within TOL
    _c, post, edge = predict_combined_images_posteriors(
        NOMINAL, q_fit, phase_q(plan, "rotation"), phase_q(plan, "translation"), scene, _image_noise(doc)
    )
    c4 = predict_legs_images(NOMINAL, q_fit, locks, scene, _image_noise(doc), post, edge)[1]
    ratio = np.sqrt(np.diag(c4)) / r.std_vector()
    print("legs, predicted / reported std:", np.round(ratio, 3))
    assert np.all(np.abs(ratio - 1.0) < TOL), ratio


def test_image_prediction_of_a_plan_with_a_leg_seen_through_its_second_rod_only(scene):
    """A fit pose where one leg's first rod is out of the measured set (too short in the image) and its second is
    measured: the legs method uses the one rod (``pair_means``), and so must its prediction: a missing rod filled with
    a zero direction would zero the measured one in the intrinsics' effect and the prediction would raise on
    non-finite residuals."""
    from calib.design import ImageNoise, synthetic_rods

    q_odd = np.array([-0.1105, 0.2272, -0.0996, 0.2438])  # leg 1: rod 1 measured, rod 0 not
    noise = ImageNoise()
    rods = synthetic_rods(scene, NOMINAL, q_odd[None], noise.edge_px)
    seen = set(zip(rods.leg.tolist(), rods.rod.tolist(), strict=True))
    assert (0, 1) in seen and (0, 0) not in seen, seen
    paper = make_plan("full", NOMINAL, seed=0, n_fit=12)
    steps = [s for s in paper.steps if s.phase != "line"]
    k = next(i for i, s in enumerate(steps) if s.phase == "poses")
    steps[k] = steps[k].model_copy(update={"q": q_odd.tolist()})
    plan = Plan(name="odd", steps=steps)
    pred = predict_plan(plan, NOMINAL, scene, noise)
    assert not pred.errors, pred.errors
    std = np.array([pred.std["legs"][c] for c in COMBINATION_NAMES])
    assert np.all(np.isfinite(std)) and np.all(std > 0), std
    ref = predict_plan(Plan(name="paper", steps=[s for s in paper.steps if s.phase != "line"]), NOMINAL, scene, noise)
    # one pose of twelve changed: the same order of magnitude as the paper's plan
    assert np.all(np.abs(np.log(std / np.array([ref.std["legs"][c] for c in COMBINATION_NAMES]))) < np.log(3)), std


def test_best_of_several_candidate_draws(scene):
    """``draws``: each draw of the candidates designed in full, the best kept by the criterion on its prediction.
    The best of three is at least as good as each draw alone (here strictly better than the seed's own draw, whose
    exchange stops at a local optimum), draw 0 is the one-draw design, and the plan says which draw it is."""
    from dataclasses import replace

    from calib.design import design_score
    from calib.errors import InputError

    target = (1.0e-4, 0.4e-4, 1.0e-4, 1.0e-4)
    req = DesignRequest(
        n_fit=8,
        n_lock=2,
        n_validation=0,
        with_line=False,
        n_candidates=120,
        seed=4,
        criterion="target",
        target_std_m=target,
    )
    singles = [design_plan(NOMINAL, scene, replace(req, candidate_draw=k)) for k in range(3)]
    best = design_plan(NOMINAL, scene, replace(req, draws=3))
    scores = [design_score(r, req)[2] for r in singles]
    assert design_score(best, req)[2] == pytest.approx(min(scores), rel=1e-12), scores
    assert scores[0] > min(scores), scores  # another draw holds a better design than the seed's own
    # draw 0 is the seed's own: the design without draws
    plain = design_plan(NOMINAL, scene, req)
    assert phase_q(plain.plan, "poses").tolist() == phase_q(singles[0].plan, "poses").tolist()
    k = int(np.argmin(scores))
    assert best.plan.model_extra["design"]["request"]["candidate_draw"] == k
    assert any("best of 3 draws" in n for n in best.notes), best.notes
    with pytest.raises(InputError, match="draws"):
        replace(req, draws=0)


def test_joint_depth_systematic_is_along_the_lines_of_sight_shared_within_a_leg(designed, scene, rendered):
    """The lock phases' joints' systematic depth error (the rods' shading, the same in every frame of a lock phase):
    per joint ``JOINT_DEPTH_SYS_M`` along its line of sight, ``JOINT_DEPTH_SYS_LEG_SHARE`` of its variance common to
    a leg's two joints, none between legs. The legs method carries it as a part of its std (estimates unchanged) and
    so does its prediction; the other methods' predictions are unchanged."""
    from calib.design import ImageNoise
    from calib.identify.legs import joint_depth_systematic
    from calib.identify.legs.constants import JOINT_DEPTH_SYS_LEG_SHARE, JOINT_DEPTH_SYS_M

    rng = np.random.default_rng(11)
    P = rng.normal(size=(4, 2, 3)) * 0.1 + np.array([0.0, 0.0, 0.7])
    C = joint_depth_systematic(P, 0.8e-3, 0.5)
    assert C.shape == (24, 24) and np.allclose(C, C.T) and np.linalg.eigvalsh(C)[0] > -1e-18
    los = (P / np.linalg.norm(P, axis=-1, keepdims=True)).reshape(8, 3)
    for a in range(8):
        for b in range(8):
            block = C[3 * a : 3 * a + 3, 3 * b : 3 * b + 3]
            want = 0.0 if a // 2 != b // 2 else (1.0 if a == b else 0.5)
            assert np.allclose(block, want * 0.8e-3**2 * np.outer(los[a], los[b]), atol=1e-20), (a, b)
    with pytest.raises(ValueError, match="shape"):
        joint_depth_systematic(P[:3], 0.8e-3, 0.5)
    with pytest.raises(ValueError, match="leg_share"):
        joint_depth_systematic(P, 0.8e-3, 1.5)
    noise = ImageNoise()
    assert (noise.legs_joint_depth_sys_m, noise.legs_joint_depth_sys_leg_share) == (
        JOINT_DEPTH_SYS_M,
        JOINT_DEPTH_SYS_LEG_SHARE,
    )
    with_sys = predict_plan(designed.plan, NOMINAL, scene, noise)
    without = predict_plan(designed.plan, NOMINAL, scene, ImageNoise(legs_joint_depth_sys_m=0.0))
    for k in COMBINATION_NAMES:
        assert with_sys.std["legs"][k] > without.std["legs"][k]
        assert with_sys.std["combined"][k] == without.std["combined"][k]
    # the method: the same estimate, a larger std by its own part
    _plan, obs, _doc = rendered
    r = calibrate_legs(obs)
    r0 = calibrate_legs(obs, joint_depth_sys_m=0.0)
    for k in COMBINATION_NAMES:  # the same up to rounding (the a priori blend's eigen-decomposition)
        assert r.combinations[k] == pytest.approx(r0.combinations[k], rel=1e-12, abs=1e-15)
    assert max(r.std_breakdown["joint_depth_systematic"].values()) > 0
    assert max(r0.std_breakdown["joint_depth_systematic"].values()) == 0
    for k in COMBINATION_NAMES:
        assert r.combinations_std[k] > r0.combinations_std[k]


def test_a_design_says_when_the_legs_prediction_leans_on_its_shading_model(scene):
    """The legs prediction's shading part (the lock phases' systematic depth error) is right on average over plans,
    not plan by plan: a design whose legs prediction leans on it says so, with the share of the variance it is; without
    that part in the model, no such note."""
    from calib.design import ImageNoise

    req = DesignRequest(n_fit=8, n_lock=3, n_validation=0, with_line=False, n_candidates=60)
    res = design_plan(NOMINAL, scene, req, noise=ImageNoise())
    parts, std = res.prediction.parts["legs"]["joint_depth_systematic"], res.prediction.std["legs"]
    share = max((parts[k] / std[k]) ** 2 for k in COMBINATION_NAMES)
    notes = [n for n in res.notes if "lock phases' shading" in n]
    assert share > 0.1 and len(notes) == 1, res.notes
    assert f"up to {share:.0%} of a combination's predicted variance" in notes[0]
    plain = design_plan(NOMINAL, scene, req, noise=ImageNoise(legs_joint_depth_sys_m=0.0))
    assert not any("shading" in n for n in plain.notes), plain.notes


def test_an_absurdly_small_target_is_not_met_without_overflow_warnings(scene):
    """A target of 5e-324 m (the API accepts any positive target): not met, the worst ratio said in a readable form,
    and no overflow warning on the way (the API fuzz found three)."""
    import warnings

    req = DesignRequest(
        target_std_m=5e-324, criterion="target", n_max=6, n_lock=2, n_validation=0, with_line=False, n_candidates=40
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        res = design_plan(NOMINAL, scene, req)
    assert res.target_met is False
    note = next(n for n in res.notes if "target is not met" in n)
    assert "predicted for 4.94e-321 mm (no finite ratio)" in note, note
    # and with several candidate draws, each judged by that criterion
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        drawn = design_plan(NOMINAL, scene, replace(req, draws=2))
    assert drawn.target_met is False


def test_draws_of_a_plan_a_method_cannot_determine_are_ranked_not_a_crash(scene):
    """Two fit poses leave the end-effector method undetermined: each draw's prediction has no std for it, which
    ranks it last (infinite in every part of the score). The score was a 1-tuple then and the draws' note read its
    third entry: the API fuzz's 500 on ``{"n_fit": 2, "methods": ["end-effector"], "draws": 2}``."""
    from calib.design import design_score

    req = DesignRequest(
        n_fit=2, n_lock=2, n_validation=0, with_line=False, n_candidates=60, seed=1, methods=("end-effector",), draws=2
    )
    res = design_plan(NOMINAL, scene, req)
    assert "end-effector" not in res.prediction.std
    assert design_score(res, req) == (np.inf, np.inf, np.inf, np.inf)
    assert any("best of 2 draws" in n and "inf" in n for n in res.notes), res.notes
