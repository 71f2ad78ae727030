"""Experiment design for a bench: the scene and motion figures of a bench file, length units, one entry point.

The scene (:func:`bench_scene`): the camera's intrinsics are the bench's own camera (a camera file, given by the
caller), its mounting the bench file's ``[camera.mounting]`` (the camera's pose in the robot's base frame); what the
bench file does not give is the simulated bench's (:class:`drivers.sim.twin.BenchGeometry`,
:class:`drivers.sim.render.RenderSettings`: its camera, mounting, board and rods), said in a warning unless the bench
is the simulated one. With the bench's nominal geometry, soft limits, speeds, accelerations and settle times. Shared by
``i4cal plan design`` / ``plan predict``, ``POST /api/v1/plans/design`` / ``/plans/predict`` and the runs (a run's
prediction).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
from typing import Any
from urllib.parse import urlsplit

from calib.errors import InputError

_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6}


def parse_length(text: str | float, field: str = "target-std") -> float:
    """Metres from ``0.05mm``, ``50um``, ``5e-5`` (plain metres) or ``5e-5m``."""
    if isinstance(text, int | float):
        value = float(text)
    else:
        m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµμ]*)\s*", str(text))
        if not m or m.group(2) not in ("", *_UNITS):
            raise InputError(f"{text!r} is not a length (e.g. 0.05mm, 50um, or metres: 5e-5)", field=field)
        value = float(m.group(1)) * _UNITS.get(m.group(2) or "m", 1.0)
    if not (value > 0 and value < 1.0):
        raise InputError(f"{text!r}: a length in (0, 1) m is expected", field=field)
    return value


def twin_scene(camera=None):
    """The camera, its mounting, the board and the rods of the simulated bench (calib.design.Scene).

    ``camera``: a ``calib.formats.camera.CameraModel`` (the bench's own: intrinsics, lens, image size, e.g. a
    camera file of
    ``i4cal extract``) in place of the twin's, at the twin's mounting (a bench file's own mounting:
    :func:`bench_scene`).
    """
    from calib.design import Scene
    from drivers.sim.render import RenderSettings
    from drivers.sim.twin import BenchGeometry

    g = BenchGeometry()
    rs = RenderSettings()
    return Scene(
        camera=camera if camera is not None else rs.camera(),
        camera_from_base=g.camera_from_base,
        ee_from_board=g.ee_from_board,
        board_size_m=rs.board.size_m,
        board_margin_m=rs.board_margin_m,
        rod_radius_m=g.rod_radius_m,
        rod_spacing_m=g.rod_spacing_m,
    )


@dataclasses.dataclass(frozen=True)
class BenchScene:
    """The scene a bench's design places the camera by (:func:`bench_scene`).

    Attributes
    ----------
    scene : calib.design.Scene
        The camera (intrinsics, image size), its mounting (``camera_from_base``, m), the board and the rods.
    warnings : tuple of str
        On a bench that is not the simulated one, each part of the camera taken from the simulated bench for want of
        the bench's own: what is missing, where to give it and what was used instead.
    """

    scene: Any
    warnings: tuple[str, ...] = ()


def is_simulated(cfg) -> bool:
    """Whether a bench configuration's camera is the simulated bench's (a ``sim://`` URI)."""
    return urlsplit(cfg.camera.uri).scheme == "sim"


def bench_scene(cfg, camera=None) -> BenchScene:
    """The scene of a bench configuration: ``camera`` (the bench's own: a
    ``calib.formats.camera.CameraModel``, e.g. its
    camera file) at the bench file's ``[camera.mounting]``; what is not given is the simulated bench's
    (:func:`twin_scene`), with a warning unless the bench's camera is the simulated one.

    Parameters
    ----------
    cfg : drivers.acquisition.config.BenchConfig
        The bench file (``camera.mounting``: position in m, rotation vector in rad, of the camera in the base frame).
    camera : calib.formats.camera.CameraModel, optional
        The bench's camera (intrinsics, lens, image size); None: the simulated bench's.

    Returns
    -------
    BenchScene
    """
    from calib.numerics.transforms import Rigid

    scene = twin_scene(camera)
    sim = is_simulated(cfg)
    where = cfg.source or "the bench file"
    warnings = []
    mount = cfg.camera.mounting
    if mount is not None:
        base_from_camera = Rigid.from_rotvec(mount.rotation_rad, mount.position_m)
        scene = dataclasses.replace(scene, camera_from_base=base_from_camera.inverse())
    elif not sim:
        at = ", ".join(f"{v * 1e3:.0f}" for v in scene.camera_from_base.inverse().t)
        warnings.append(
            f"{where} gives no camera mounting ([camera.mounting] position_m, rotation_rad: the camera's pose in the "
            f"robot's base frame): the simulated bench's is used (the camera at ({at}) mm in the base frame), which "
            "misplaces what is in view when this bench's camera sits elsewhere"
        )
    if camera is None and not sim:
        named = cfg.intrinsics_path()
        missing = (
            f"{where} names no camera file ([camera] intrinsics; or --camera FILE)"
            if named is None
            else f"the camera file {named} ({where}, [camera] intrinsics) was not read"
        )
        warnings.append(
            f"{missing}: the simulated bench's camera is used ({scene.camera.width} x {scene.camera.height} px)"
        )
    return BenchScene(scene, tuple(warnings))


#: corner noise (px) of the camera phase's board views in :func:`twin_image_noise`: what the weighted calibration
#: (views weighted by their noise, calib.camera.bundle) reports on the image-level twin's 30 rendered views is
#: the bundle's
#: covariance at 0.037 (cx) to 0.056 (fx) px, 0.05 over the nine intrinsics (40 camera phases; the views' corner
#: RMS is 0.10 px, but the weighted fit's information is that of its best views, 0.02-0.2 px)
CALIBRATION_CORNER_PX = 0.05


def twin_image_noise(views: int = 30, seed: int = 0, camera=None, **levels: Any):
    """The image-level prediction's noise for the simulated bench (``calib.design.ImageNoise``).

    Its levels are :class:`calib.design.ImageNoise`'s defaults (measured on the image-level twin, docs/design.md)
    unless given in ``levels``; the camera's calibration covariance is that of ``views`` board views of the twin's
    camera phase (``BenchRenderer.random_board_views``, the views ``simulate_dataset`` renders for ``seed``) at
    :data:`CALIBRATION_CORNER_PX`, the lens model being the twin's (k1, k2, p1, p2, k3). ``camera``: the bench's own
    camera (:func:`twin_scene`), whose calibration is then predicted from those views.
    """
    from calib.design import ImageNoise

    noise = ImageNoise(**levels)
    camera_json = None if camera is None else json.dumps(camera.to_dict(), sort_keys=True)
    cov = _calibration_covariance(views, seed, camera_json, tuple(noise.intrinsics_names))
    return noise.with_intrinsics(cov.copy())


@functools.lru_cache(maxsize=8)
def _calibration_covariance(views: int, seed: int, camera_json: str | None, names: tuple[str, ...]) -> Any:
    """:func:`twin_image_noise`'s calibration covariance (about 0.5 s of CPU), computed once per views,
    seed, camera and intrinsics: every run's prediction and every design of a service would compute it again."""
    import numpy as np

    from calib.design import calibration_covariance
    from calib.formats.camera import CameraModel
    from drivers.sim.render import BenchRenderer, RenderSettings
    from drivers.sim.twin import BenchGeometry

    camera = None if camera_json is None else CameraModel.from_dict(json.loads(camera_json))
    renderer = BenchRenderer(BenchGeometry(), RenderSettings(), seed=seed)
    v = renderer.random_board_views(views, np.random.default_rng([seed, 7]))
    cov = calibration_covariance(twin_scene(camera), v, CALIBRATION_CORNER_PX, names)
    cov.setflags(write=False)
    return cov


def motion_spec(cfg) -> Any:
    """Speeds, acceleration and settle times of a bench configuration (``drivers.acquisition.config.BenchConfig``)."""
    from calib.design import MotionSpec

    a = cfg.actuators
    return MotionSpec(
        speed_m_s=a.speed_m_s,
        accel_m_s2=a.accel_m_s2,
        settle_s=a.settle_s + cfg.acquisition.settle_s,
        line_rate_hz=cfg.acquisition.line_rate_hz,
    )


def _bench_inputs(cfg, noise=None, camera=None) -> tuple[Any, Any, dict[str, Any]]:
    """A bench configuration's nominal geometry, its scene (:func:`bench_scene`), and ``calib.design.design_plan``'s
    keywords (soft limits, motion, noise; the noise by default the image-level model of the bench's camera)."""
    kw = {
        "limits": cfg.calib_limits(),
        "motion": motion_spec(cfg),
        "noise": noise if noise is not None else twin_image_noise(camera=camera),
    }
    return cfg.nominal_parameters(), bench_scene(cfg, camera).scene, kw


def _with_notes(result, notes: tuple[str, ...]):
    """``result`` (``calib.design.DesignResult``) with ``notes`` first among its notes and its plan's."""
    if not notes:
        return result
    from calib.formats.plan import Plan

    result.notes[:0] = notes
    design = dict((result.plan.model_extra or {}).get("design") or {})
    design["notes"] = result.notes
    result.plan = Plan.model_validate({**result.plan.model_dump(exclude_none=True), "design": design})
    return result


def design_for_bench(cfg, request, noise=None, status=None, camera=None, draws_runner=None):
    """Design a plan for a bench configuration.

    Parameters
    ----------
    cfg : drivers.acquisition.config.BenchConfig
        The bench file: nominal geometry, soft limits (m), speeds (m/s), accelerations (m/s^2), settle times (s), the
        camera's mounting.
    request : calib.design.DesignRequest
        What to design.
    noise : calib.design.DesignNoise or ImageNoise, optional
        Default: the image-level model of the bench's camera (:func:`twin_image_noise`), what the methods'
        uncertainty is on images.
    status : callable, optional
        Called with what the design is doing (``calib.design.design_plan``).
    camera : calib.formats.camera.CameraModel, optional
        The bench's own camera (:func:`bench_scene`).
    draws_runner : callable, optional
        Where the candidate draws are designed (``Fanout.index_runner``, :mod:`service.fanout`).

    Returns
    -------
    calib.design.DesignResult
        The scene's warnings (:func:`bench_scene`) first among its notes.
    """
    from calib.design import design_plan

    nominal, scene, kw = _bench_inputs(cfg, noise, camera)
    res = design_plan(nominal, scene, request, status=status, draws_runner=draws_runner, **kw)
    return _with_notes(res, bench_scene(cfg, camera).warnings)


def tradeoff_for_bench(cfg, request, counts, noise=None, progress=None, camera=None):
    """:func:`calib.design.design_tradeoff` on a bench configuration, the scene and noise of
    :func:`design_for_bench`: ``(rows, results)``, one design per count (each with the scene's warnings in its
    notes)."""
    from calib.design import design_tradeoff

    nominal, scene, kw = _bench_inputs(cfg, noise, camera)
    rows, results = design_tradeoff(nominal, scene, request, counts, progress=progress, **kw)
    warnings = bench_scene(cfg, camera).warnings
    return rows, [_with_notes(r, warnings) for r in results]


def reference_targets(
    cfg, plan, noise=None, methods=("combined",), camera=None
) -> dict[str, tuple[float, float, float, float]]:
    """Per method, the predicted std (m) per combination of a reference plan on this bench (the scene and noise of
    :func:`design_for_bench`): targets for a design at least as accurate on every combination of every method."""
    from calib.design import targets_from_plan

    scene, nz = bench_scene(cfg, camera).scene, noise if noise is not None else twin_image_noise(camera=camera)
    return {m: targets_from_plan(plan, cfg.nominal_parameters(), scene, nz, method=m) for m in methods}


def check_for_bench(cfg, plan, noise=None, methods=None, camera=None):
    """:func:`calib.design.check_plan` on a bench configuration, the scene and noise of :func:`design_for_bench`: a
    plan's predicted std per method and combination, its motion time, the steps the camera will not see.

    Parameters
    ----------
    cfg : drivers.acquisition.config.BenchConfig
        The bench file.
    plan : calib.formats.plan.Plan
        The plan as it will run.
    noise : calib.design.DesignNoise or ImageNoise, optional
        As :func:`design_for_bench`'s.
    methods : tuple of str, optional
        Those of the design's (``calib.design.METHODS``) to predict; default all of them.
    camera : calib.formats.camera.CameraModel, optional
        The bench's own camera (:func:`bench_scene`).

    Returns
    -------
    calib.design.PlanCheck
        Std in m, times in s; the scene's warnings first among its notes.
    """
    from calib.design import METHODS, check_plan

    nominal, scene, kw = _bench_inputs(cfg, noise, camera)
    wanted = tuple(m for m in (methods or METHODS) if m in METHODS)
    check = check_plan(plan, nominal, scene, kw["noise"], kw["motion"], methods=wanted)
    check.notes[:0] = bench_scene(cfg, camera).warnings
    return check


def run_prediction(cfg, plan_doc: dict[str, Any], methods: list[str], camera=None, noise=None) -> dict[str, Any] | None:
    """What a run's plan is predicted to buy, stored with the run (``Run.prediction``, ``GET /api/v1/runs/{id}``):
    per method of the run that the design predicts, the std per combination (m), the methods it cannot predict and
    why, the motion time (s), the steps the camera will not see, the notes. None when no method of the run is
    predicted (e.g. a run that only records)."""
    from calib.design import METHODS
    from calib.formats.plan import Plan

    wanted = tuple(m for m in methods if m in METHODS)
    if not wanted:
        return None
    check = check_for_bench(cfg, Plan.model_validate(plan_doc), noise, wanted, camera)
    pred = check.prediction
    return {
        "predicted_std_m": pred.std,
        "prediction_errors": pred.errors,
        "motion_time_s": check.motion["total_s"],
        "unseen": check.unseen,
        "notes": check.notes,
        "noise": _noise_description(cfg, camera),
    }


def _noise_description(cfg, camera) -> str:
    """Which camera and mounting a run's prediction used (its ``noise``)."""
    if cfg.camera.mounting is not None:
        what = "the simulated bench's camera" if camera is None else f"this service's camera ({camera.width} x"
        what += "" if camera is None else f" {camera.height} px)"
        return f"the image-level model with {what} at the bench file's camera mounting (docs/design.md)"
    if camera is None:
        return "the image-level model of the simulated bench's camera and mounting (docs/design.md)"
    return (
        f"the image-level model with this service's camera ({camera.width} x {camera.height} px) at the "
        "simulated bench's mounting (docs/design.md)"
    )


def better_than_request(targets: dict[str, tuple[float, float, float, float]]) -> dict[str, Any]:
    """``calib.design.DesignRequest``'s target fields for :func:`reference_targets`: ``target_std_m`` the combined
    method's (else the first method's), ``method_targets_m`` every other method's own."""
    first = "combined" if "combined" in targets else next(iter(targets))
    return {
        "target_std_m": targets[first],
        "method_targets_m": tuple((m, t) for m, t in targets.items() if m != first),
    }


def prediction_lines(pred, motion: dict[str, Any], breakdown: bool = False) -> list[str]:
    """The predicted std per method and combination (mm; with ``breakdown`` each source's under its method), the
    methods not predicted and why, and the motion time per phase: the lines a design and a plan's check share."""
    from calib.model.parameters import COMBINATION_NAMES

    out = [f"{'predicted std (mm):':<29}" + " | ".join(f"{k:>13}" for k in COMBINATION_NAMES)]
    for m, std in pred.std.items():
        out.append(f"  {m:<26} " + " | ".join(f"{std[k] * 1e3:13.4f}" for k in COMBINATION_NAMES))
        for part, pstd in (pred.parts.get(m, {}) if breakdown else {}).items():
            if any(v > 1e-9 for v in pstd.values()):  # parts that contribute at least a nanometre
                out.append(f"    {part:<24} " + " | ".join(f"{pstd[k] * 1e3:13.4f}" for k in COMBINATION_NAMES))
    for m, why in pred.errors.items():
        out.append(f"  {m:<16} not predicted: {why}")
    out.append(
        f"motion time {motion['total_s'] / 60:.2f} min ("
        + ", ".join(f"{k} {v:.1f} s" for k, v in motion["per_phase_s"].items())
        + ")"
    )
    return out


def check_lines(check, breakdown: bool = False) -> list[str]:
    """Human-readable check of a plan (``calib.design.PlanCheck``): its counts, the prediction, the motion time, the
    steps the camera will not see, the notes."""
    out = [f"plan {check.plan_name}: " + ", ".join(f"{k} {v}" for k, v in check.counts.items())]
    out += prediction_lines(check.prediction, check.motion, breakdown)
    for u in check.unseen:
        c = u.get("board_corners", 0)
        what = (
            []
            if u["board"]
            else [f"board partly out of view ({c} corners in the image)"]
            if c >= 6
            else [f"board out of view ({c} corners in the image: no board pose)"]
        )
        if u["rods_hidden"]:
            what.append("rods " + ", ".join(u["rods_hidden"]) + " hidden or out of the image")
        out.append(f"  step {u['step']} ({u['phase']}): " + "; ".join(what))
    out += [f"note: {n}" for n in check.notes]
    return out


def summary_lines(result, breakdown: bool = False) -> list[str]:
    """Human-readable lines: counts per phase, predicted std per method (mm), motion time; with ``breakdown``, under
    each method the std that each source of error contributes (``Prediction.parts``)."""
    counts = result.plan.count()
    out = ["plan: " + ", ".join(f"{k} {v}" for k, v in counts.items())]
    sw = result.sweeps
    out.append(
        f"fit poses {result.n_fit}; rotation sweep {sw['rotation_span_deg']:.0f} deg, "
        f"translation {sw['translation_length_m'] * 1e3:.0f} mm"
    )
    out += prediction_lines(result.prediction, result.motion, breakdown)
    if result.target_met is not None:
        out.append(f"target {'met' if result.target_met else 'NOT met'}")
    if result.time_met is not None:
        out.append(f"time limit {'met' if result.time_met else 'NOT met'}")
    out += [f"note: {n}" for n in result.notes]
    return out


def tradeoff_lines(rows, request) -> list[str]:
    """Human-readable trade-off: per method a table of fit poses, motion time and predicted std (mm), optimised methods
    first; then the target, the time limit, the trend past the counts listed and the recommended count.

    Parameters
    ----------
    rows : list of calib.design.TradeoffRow
        One designed plan per count (``n_fit``, ``motion_s`` in s, ``std_m`` per method and combination in m).
    request : calib.design.DesignRequest
        The request the rows were designed for (its methods, targets in m and time limit in s).

    Returns
    -------
    list of str
        The lines to print (lengths in mm, times in minutes).
    """
    out = ["trade-off: the designed plan for each fit-pose count (predicted std in mm, motion time of the whole plan)"]
    out += _tradeoff_tables(rows, request)
    out += _tradeoff_target_lines(rows, request)
    out += _tradeoff_trend_lines(rows, request)
    out += _tradeoff_recommendation_lines(rows, request)
    return out


def _tradeoff_tables(rows, request) -> list[str]:
    """Per method (the optimised ones first), the table of fit poses, motion time (min) and predicted std (mm)."""
    from calib.model.parameters import COMBINATION_NAMES

    methods = list(dict.fromkeys([*request.methods, *(m for r in rows for m in r.std_m)]))
    out = []
    head = f"  {'fit poses':>9} | {'motion min':>10} | " + " | ".join(f"{k:>13}" for k in COMBINATION_NAMES)
    for m in methods:
        out.append(f"{m}{' (optimised)' if m in request.methods else ''}:")
        out.append(head)
        for r in rows:
            std = r.std_m.get(m)
            vals = " | ".join(f"{std[k] * 1e3:13.4f}" if std else f"{'-':>13}" for k in COMBINATION_NAMES)
            out.append(f"  {r.n_fit:9d} | {r.motion_s / 60:10.2f} | {vals}")
    return out


def _tradeoff_target_lines(rows, request) -> list[str]:
    """The target (mm; per method when they differ) with each count's worst ratio to it, and the time limit (min)."""
    from calib.model.parameters import COMBINATION_NAMES

    out = []
    t = request.targets_by_method()
    if t is not None:
        own = len({tuple(v) for v in t.values()}) > 1
        out.append(
            "; ".join(
                ("target " + (f"{m} " if own else ""))
                + ", ".join(f"{k} {v * 1e3:.3f}" for k, v in zip(COMBINATION_NAMES, tm, strict=True))
                + " mm"
                for m, tm in (t.items() if own else list(t.items())[:1])
            )
            + "; worst predicted std over it: "
            + ", ".join(f"{r.n_fit} poses {r.worst_ratio:.2f}x" for r in rows if r.worst_ratio is not None)
        )
    if request.max_time_s is not None:
        out.append(
            f"time limit {request.max_time_s / 60:.2f} min: "
            + ", ".join(f"{r.n_fit} poses {'within' if r.time_met else 'over'}" for r in rows)
        )
    return out


def _tradeoff_trend_lines(rows, request) -> list[str]:
    """The level the predicted std settles to with more fit poses (mm), and the count the target needs by that trend."""
    from calib.design import tradeoff_trend

    trend = tradeoff_trend(rows, request)
    if trend is None:
        return []
    a, b = trend["n_fit"]
    floors = "; ".join(
        f"{m} " + ", ".join(f"{k} {v * 1e3:.3f}" for k, v in fl.items()) for m, fl in trend["floor_std_m"].items()
    )
    need = trend["n_fit_needed"]
    t = request.targets_by_method()
    reach = "" if t is None else f"; the target in about {need} fit poses" if need else "; the target in none"
    return [f"with more fit poses (the trend of the predicted std from {a} to {b}): levels off near {floors} mm{reach}"]


def _tradeoff_recommendation_lines(rows, request) -> list[str]:
    """The recommended count and why, or why none qualifies (when a target or a time limit was given)."""
    from calib.design import recommendation_reason, recommended_count

    recommended, why = recommended_count(rows), recommendation_reason(rows)
    if recommended is not None:
        return [f"recommended: {recommended} fit poses ({why})"]
    if request.targets_by_method() is not None or request.max_time_s is not None:
        return [f"no count listed qualifies ({why})"]
    return []
