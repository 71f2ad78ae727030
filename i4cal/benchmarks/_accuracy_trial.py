"""Worker side of ``i4cal bench accuracy``: one camera calibration or one Monte-Carlo trial on the image-level twin.

Both run in a worker of the study's Dask cluster (or in the calling process with one worker: :mod:`service.fanout`)
and return plain JSON-able dicts; every length in metres, except the displacement gaps (mm, as the result document
gives them) and the edge noise (px). Each works in its own temporary directory, deleted afterwards.
"""

from __future__ import annotations

import math
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from calib.identify.registry import method_names
from calib.vision.extract import RODS_NOT_READ

#: Methods of :func:`calib.identify.pipeline.calibrate`, in the order of its result document (the registered methods).
METHODS: tuple[str, ...] = method_names()


class CameraTask(BaseModel):
    """The study's camera phase: ``views`` board views (+ ``steps``, a few bench poses) rendered and calibrated."""

    noise_sigma: float = Field(ge=0, description="renderer sensor noise, grey levels (std)")
    seed: int
    views: int = Field(ge=5)
    steps: list[dict[str, Any]] = Field(description="plan steps rendered after the views (a few rotation poses)")


class TrialTask(BaseModel):
    """One trial: a true geometry, the plan it runs, the renderer's noise and the study's calibrated camera."""

    key: str = Field(description="identifies the trial across study and sweep points: 'noise=..,fit=..,k=..'")
    index: int = Field(ge=0)
    seed: int = Field(description="seed of the rendered dataset (background, board error, sensor noise)")
    truth: list[float] = Field(min_length=7, max_length=7, description="the seven true parameters, metres")
    noise_sigma: float = Field(ge=0)
    steps: list[dict[str, Any]]
    camera: dict[str, Any] | None = Field(
        description="CameraModel.to_dict() of the study's camera; None: calibrated from the trial's own camera phase"
    )
    camera_views: int = Field(0, ge=0, description="board views rendered with the trial (its own camera phase)")
    dist: list[float] | None = Field(None, description="the rendered lens's distortion (None: the renderer's default)")
    lens: str | None = Field(None, description="the lens's name in the lens sweep")


def _finite(x: Any) -> float | None:
    """``x`` as a float, None when missing or not finite (JSON has no NaN)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _plan(steps: list[dict[str, Any]], name: str) -> Any:
    from calib.formats.plan import Plan

    return Plan.model_validate({"name": name, "steps": steps})


def calibrate_camera(task: CameraTask) -> dict[str, Any]:
    """Render the camera phase and calibrate the intrinsics from it (what the lab does once).

    Returns
    -------
    dict
        ``camera`` (``CameraModel.to_dict()``), ``intrinsics`` (reprojection RMS px, views used, rejected),
        ``true_camera`` (the renderer's), ``render_s``, ``extract_s``, ``cpu_s``, ``noise_sigma``, ``source``.
    """
    from calib.vision.extract import extract_dataset
    from drivers.sim.render import RenderSettings
    from drivers.sim.rendered_dataset import simulate_dataset
    from drivers.sim.twin import BenchGeometry

    rs = RenderSettings(noise_sigma=task.noise_sigma)
    cpu0 = time.process_time()
    with tempfile.TemporaryDirectory(prefix="i4cal-acc-camera-") as tmp:
        t0 = time.perf_counter()
        path = simulate_dataset(
            Path(tmp) / "ds",
            seed=task.seed,
            geometry=BenchGeometry(),
            render=rs,
            plan=_plan(task.steps, "camera phase"),
            n_camera_views=task.views,
        )
        t1 = time.perf_counter()
        res = extract_dataset(path, workers=1)
        t2 = time.perf_counter()
    if res.intrinsics is None:  # pragma: no cover - the dataset has no K: extraction calibrates or raises
        raise RuntimeError("the camera phase gave no intrinsics")
    return {
        "noise_sigma": task.noise_sigma,
        "source": "calibrated",
        **_camera_record(res, rs),
        "render_s": t1 - t0,
        "extract_s": t2 - t1,
        "cpu_s": time.process_time() - cpu0,
    }


def error_against_covariance(error: Any, covariance: Any) -> dict[str, Any] | None:
    """How an estimate's error compares with the covariance it reports: ``mahalanobis`` (e^T C^-1 e), ``dof`` and
    ``principal_z2``, the squared error along each principal direction of C over its variance, smallest variance
    first (each is chi-square(1) when C is right: mean 1). None when C is not positive definite.

    The rods' refinement of the camera (``calibration.covariance_refined``) is right on average over its principal
    directions but one on the image-level twin: along the lens's radial distortion, which the rods pin 30-60 times
    better than the board views, the mean is 2.5-3.0 (docs/design.md); the design bench records it per trial.
    """
    import numpy as np

    e = np.asarray(error, dtype=np.float64).reshape(-1)
    C = np.asarray(covariance, dtype=np.float64)
    if C.shape != (e.size, e.size) or not np.all(np.isfinite(C)) or not np.all(np.isfinite(e)):
        return None
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    if w[0] <= 0:
        return None
    z2 = (V.T @ e) ** 2 / w
    return {"mahalanobis": float(z2.sum()), "dof": int(e.size), "principal_z2": z2.tolist()}


def _refined_honesty(res: Any, true: Any) -> dict[str, Any] | None:
    """The extraction's camera (refined by the rods) against the renderer's, in its ``covariance_refined``
    (:func:`error_against_covariance`); None when the rods did not refine it."""
    from calib.camera.intrinsics import intrinsics_names, intrinsics_vector

    calib = res.camera.extra.get("calibration") or {}
    cov = calib.get("covariance_refined")
    if cov is None:
        return None
    names = list(calib.get("covariance_params") or intrinsics_names(res.camera))
    return error_against_covariance(intrinsics_vector(res.camera, names) - intrinsics_vector(true, names), cov)


def _camera_record(res: Any, rs: Any) -> dict[str, Any]:
    """The calibrated camera of an extraction against the renderer's: ``camera`` (the extraction's, refined by the
    rods when they moved it), ``true_camera``, ``intrinsics`` (reprojection RMS px, views, rejected, ``error_vs_true``
    of the calibration, ``refined_error_vs_true`` of the extraction's camera, the calibration's ``std`` of fx,
    fy, cx, cy [px], k1, k2, p1, p2, and ``refined_against_covariance``: the extraction's camera's error in its
    ``covariance_refined``, :func:`error_against_covariance`), ``lens_model`` (the lens model the calibration chose
    and its evidence)."""
    from calib.camera.intrinsics import INTRINSICS_NAMES, intrinsics_vector

    s = res.intrinsics.summary()
    cam, true = res.intrinsics.camera, rs.camera()  # the calibration's (the extraction's may be refined by the rods)

    def vec(c: Any) -> Any:
        return intrinsics_vector(c, INTRINSICS_NAMES)

    calib = cam.extra.get("calibration") or {}
    cov, names = calib.get("covariance"), list(calib.get("covariance_params") or INTRINSICS_NAMES)
    std = [
        math.sqrt(max(cov[names.index(k)][names.index(k)], 0.0)) if cov and k in names else None
        for k in INTRINSICS_NAMES
    ]
    return {
        "camera": cam.to_dict(),
        "true_camera": true.to_dict(),
        "intrinsics": {
            "rms_px": _finite(s.get("rms_px")),
            "n_views": s.get("n_views"),
            "rejected": {str(k): str(v) for k, v in (s.get("rejected") or {}).items()},
            "error_vs_true": {k: float(a - b) for k, a, b in zip(INTRINSICS_NAMES, vec(cam), vec(true), strict=True)},
            "refined_error_vs_true": {
                k: float(a - b) for k, a, b in zip(INTRINSICS_NAMES, vec(res.camera), vec(true), strict=True)
            },
            "std": dict(zip(INTRINSICS_NAMES, std, strict=True)),
            "refined_against_covariance": _refined_honesty(res, true),
        },
        "lens_model": (cam.extra.get("calibration") or {}).get("lens_model"),
    }


def _render_settings(task: TrialTask) -> Any:
    """The renderer's settings of a trial: its sensor noise and, in the lens sweep, its lens."""
    from drivers.sim.render import RenderSettings

    if task.dist is None:
        return RenderSettings(noise_sigma=task.noise_sigma)
    return RenderSettings(noise_sigma=task.noise_sigma, dist=tuple(task.dist))


def edge_noise_px(observations: dict[str, Any]) -> float | None:
    """Median over every measured rod of the fit phases of its limb edges' residual RMS (``rms_px``), pixels."""
    vals = []
    for fr in observations.get("frames", []):
        for rods in (fr.get("legs") or {}).values():
            for rod in rods or []:
                if rod:
                    vals += [v for v in (_finite(x) for x in rod.get("rms_px") or []) if v is not None]
    if not vals:
        return None
    vals.sort()
    n = len(vals)
    return vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])


def _gap(validation: dict[str, Any], name: str) -> float | None:
    v = validation.get(name) or {}
    return _finite((v.get("gaps_validation") or {}).get("rms_mm"))


#: per method, the noise levels its fit measured (diagnostics, dimensionless), which the design's image-level
#: prediction takes at their twin values (``calib.design.ImageNoise``: ``rod_scale``, ``legs_lock_chi2``,
#: ``legs_directions_chi2``): the bench records them per trial to check those values
NOISE_LEVELS: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "combined": (
        ("direction_noise_scale", ("direction_noise_scale",)),
        ("rod_own_scale", ("rod_errors", "own_scale")),
        ("rod_pair_correlation", ("rod_errors", "pair_correlation")),
        ("rod_distance_correlation", ("rod_errors", "distance_correlation")),
    ),
    "legs": (
        ("lock_chi2", ("step1_residual_chi2_per_dof",)),
        ("directions_chi2", ("steps34_residual_chi2_per_dof",)),
        # the level its leg directions' own part is scaled by (the chi-square over its expectation, floored at 1):
        # what ``legs_directions_chi2`` stands for
        ("directions_level", ("steps34_chi2_per_dof",)),
    ),
}


def noise_levels(method: str, diagnostics: dict[str, Any]) -> dict[str, float | None]:
    """The noise levels (:data:`NOISE_LEVELS`) a method's diagnostics carry; None where one is missing."""
    out: dict[str, float | None] = {}
    for name, path in NOISE_LEVELS.get(method, ()):
        v: Any = diagnostics
        for k in path:
            v = v.get(k) if isinstance(v, dict) else None
        out[name] = _finite(v)
    return out


def trial_record(doc: dict[str, Any], observations: dict[str, Any]) -> dict[str, Any]:
    """The numbers of one trial from its result document (:func:`calib.identify.pipeline.calibrate`) and observations.

    Returns
    -------
    dict
        ``methods``: per method ``ok``, ``error``, ``converged``, ``errors`` and ``std`` (metres, per
        combination), ``gap_validation_rms_mm``, ``a_priori_fallback`` (None, or which parameters the method
        returned as their a priori values because its data contradicted them), ``unpinned_directions`` (how many
        directions of the seven its data left to the a priori tolerance), ``noise_levels`` (:func:`noise_levels`);
        ``bound_std`` (the combined method's
        Cramer-Rao bound, metres, None when the result has none); ``gap_a_priori_rms_mm``,
        ``gap_truth_rms_mm``; ``edge_noise_px``; ``rods_found`` and ``rods_total`` (the rods looked for: those of
        the frames whose rods are read), ``boards_found`` and ``frames``;
        ``extraction_recovered`` (:func:`calib.vision.extract.extract_dataset`'s ``summary["recovered"]``, or None).
    """
    from calib.model.parameters import COMBINATION_NAMES

    truth_errors = doc.get("truth_errors") or {}
    validation = doc.get("validation") or {}
    methods: dict[str, Any] = {}
    for name in METHODS:
        entry = (doc.get("methods") or {}).get(name)
        if entry is not None:
            methods[name] = method_record(name, entry, truth_errors.get(name), validation)
    bound = ((doc.get("methods") or {}).get("combined") or {}).get("bound") or {}
    bstd = bound.get("std")
    frames = observations.get("frames", [])
    return {
        "methods": methods,
        "bound_std": {k: _finite(bstd.get(k)) for k in COMBINATION_NAMES} if isinstance(bstd, dict) else None,
        "bound_note": bound.get("note"),
        "gap_a_priori_rms_mm": _gap(validation, "a priori"),
        "gap_truth_rms_mm": _gap(validation, "truth"),
        "edge_noise_px": edge_noise_px(observations),
        "frames": len(frames),
        "boards_found": sum(1 for fr in frames if fr.get("board")),
        "rods_found": _rods_found(frames),
        "rods_total": 8 * sum(1 for fr in frames if (fr.get("missing") or {}).get("rods") != RODS_NOT_READ),
        # the extraction's second look when too many rods were lost in their search bands (calib.vision.recover):
        # None when it was not needed
        "extraction_recovered": _recovered(observations),
    }


def method_record(
    name: str, entry: dict[str, Any], err: dict[str, Any] | None, validation: dict[str, Any]
) -> dict[str, Any]:
    """One method's numbers in a trial (the ``methods`` entries of :func:`trial_record`).

    ``entry`` is the method's entry of the result document, ``err`` its errors against the truth (metres, per
    combination and ``seven``; None when the result has none), ``validation`` the result's validation section.
    """
    from calib.model.parameters import COMBINATION_NAMES

    std = entry.get("std") or {}
    errors = {k: _finite(err.get(k)) for k in COMBINATION_NAMES} if err else None
    stds = {k: _finite(std.get(k)) for k in COMBINATION_NAMES} if std else None
    problem = entry.get("error")
    if not problem and not errors:
        problem = "no parameters"
    elif errors and None in errors.values():
        problem = "non-finite parameters"
    ident = (entry.get("diagnostics") or {}).get("identifiability") or {}
    rec: dict[str, Any] = {
        "ok": not problem,
        "error": problem or None,
        "converged": bool(entry.get("converged")),
        "errors": errors,
        "std": stds,
        "gap_validation_rms_mm": _gap(validation, name),
        # what the method returned when its data could not pin the estimate (the legs method's a priori values,
        # with their tolerance as std and a warning): None when the estimate is the data's
        "a_priori_fallback": ident.get("a_priori_fallback"),
        # directions of the seven the data knew less well than the a priori tolerance (the legs method says so in
        # a warning; the estimate there is the tolerance's): 0 when the data pinned every one
        "unpinned_directions": len(ident.get("unpinned") or []),
        "noise_levels": noise_levels(name, entry.get("diagnostics") or {}),
    }
    if err and "seven" in err:
        rec["seven_errors"] = {k: _finite(v) for k, v in err["seven"].items()}
    return rec


def _rods_found(frames: list[dict[str, Any]]) -> int:
    """Rods measured over the frames (at most eight a frame: two per leg)."""
    return sum(1 for fr in frames for rs in (fr.get("legs") or {}).values() for r in rs or [] if r)


def _recovered(observations: dict[str, Any]) -> dict[str, Any] | None:
    rec = ((observations.get("extraction") or {}).get("summary") or {}).get("recovered")
    if not rec:
        return None
    return {k: rec.get(k) for k in ("applied", "lost_before", "lost_after", "looked_for_before", "reason")}


def run_trial(task: TrialTask) -> dict[str, Any]:
    """Render the trial's dataset for its true geometry, extract it with the study's camera, calibrate (all methods).

    Never raises for what goes wrong inside the trial: the record then has ``error`` (and no methods).

    Returns
    -------
    dict
        ``key``, ``index``, ``seed``, ``truth`` (seven, metres), ``truth_combinations`` (metres), ``render_s``,
        ``extract_s``, ``calibrate_s`` (wall), ``cpu_s`` (CPU time of the whole trial: its cost on an idle core),
        ``error`` (None) and the fields of :func:`trial_record`.
    """
    from calib.formats.camera import CameraModel
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate
    from calib.model.parameters import NOMINAL, I4Parameters
    from calib.vision.extract import extract_dataset
    from drivers.sim.rendered_dataset import simulate_dataset
    from drivers.sim.twin import BenchGeometry

    truth = I4Parameters.from_vector(task.truth, T_per_rad=NOMINAL.T_per_rad)
    out: dict[str, Any] = {
        "key": task.key,
        "index": task.index,
        "seed": task.seed,
        "noise_sigma": task.noise_sigma,
        "truth": truth.seven(),
        "truth_combinations": truth.combinations(),
        "error": None,
        "render_s": None,
        "extract_s": None,
        "calibrate_s": None,
        "cpu_s": None,
    }
    cpu0 = time.process_time()
    try:
        with tempfile.TemporaryDirectory(prefix="i4cal-acc-trial-") as tmp:
            t0 = time.perf_counter()
            path = simulate_dataset(
                Path(tmp) / "ds",
                seed=task.seed,
                geometry=BenchGeometry(truth=truth),
                render=_render_settings(task),
                plan=_plan(task.steps, "trial"),
                n_camera_views=task.camera_views if task.camera is None else 0,
            )
            out["render_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            cam = None if task.camera is None else CameraModel.from_dict(task.camera)
            res = extract_dataset(path, camera=cam, workers=1)
            out["extract_s"] = time.perf_counter() - t0
        if task.camera is None and res.intrinsics is not None:
            out["camera"] = _camera_record(res, _render_settings(task))
        t0 = time.perf_counter()
        doc = calibrate(Observations.from_dict(res.observations))
        out["calibrate_s"] = time.perf_counter() - t0
        out.update(trial_record(doc, res.observations))
        out["cpu_s"] = time.process_time() - cpu0
    except Exception as exc:  # a failed trial is counted, never the end of the study
        out["error"] = f"{type(exc).__name__}: {exc}"
        out["traceback"] = traceback.format_exc(limit=6)
        out["methods"] = {}
    return out
