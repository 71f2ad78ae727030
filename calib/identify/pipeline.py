"""Run calibration methods on observations and assemble the result document (``i4cal calibrate --json``)."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterable
from typing import Any, cast

import numpy as np

from calib.errors import I4calError
from calib.formats.observations import LEG_KEYS, Observations, Rod
from calib.formats.resultdoc import (
    RESULT_FORMAT,
    BaseFrameSummary,
    MethodEntry,
    ResultDocument,
    ValidationEntry,
    to_jsonable,
)
from calib.identify.baseframe import BaseFrameResult, base_frame_from_observations
from calib.identify.combined_measurements import CombinedMeasurements
from calib.identify.iterations import IterationCallback
from calib.identify.registry import MethodContext, MethodSpec, get_method, method_identifiability, method_names
from calib.identify.result import MethodResult
from calib.identify.validation import validate, vision_scale
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters
from calib.numerics.transforms import tangent_basis

__all__ = ["RESULT_FORMAT", "calibrate", "calibrate_document", "run_method", "to_jsonable"]


def __getattr__(name: str) -> Any:
    # ``METHOD_NAMES``: the registered methods now (calib.identify.registry), not a snapshot taken at import
    if name == "METHOD_NAMES":
        return method_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_method(
    name: str,
    obs: Observations,
    base_frame: BaseFrameResult | None = None,
    *,
    on_iteration: IterationCallback | None = None,
    context: MethodContext | None = None,
) -> MethodResult:
    """Fit method ``name`` (:func:`calib.identify.registry.get_method`) to ``obs``; ``context``: what earlier methods
    of the same run measured (its base frame and callback are replaced by these arguments).

    Parameters
    ----------
    name : str
        A registered method's name.
    obs : Observations
        The observations.
    base_frame : BaseFrameResult, optional
        The base frame measured from the boards, when the method uses it.
    on_iteration : IterationCallback, optional
        Called at each iteration of the method's fits.
    context : MethodContext, optional
        What earlier methods of the same run measured.

    Returns
    -------
    MethodResult
        The method's result.

    Raises
    ------
    InputError
        No method ``name`` is registered.
    """
    spec = get_method(name)
    ctx = MethodContext() if context is None else context
    return spec.fit(obs, dataclasses.replace(ctx, base_frame=base_frame, on_iteration=on_iteration))


def calibrate(
    obs: Observations,
    methods: Iterable[str] | None = None,
    *,
    strict: bool = False,
    progress: Callable[[str, str], None] | None = None,
    on_iteration: IterationCallback | None = None,
) -> dict[str, Any]:
    """The result document of :func:`calibrate_document` as a mapping (``i4cal calibrate --json``: what is stored
    and printed; numpy values as the methods gave them, :func:`to_jsonable` makes them JSON).

    Parameters
    ----------
    obs : Observations
        The observations.
    methods : iterable of str, optional
        The methods to run (default: every registered one).
    strict : bool
        Raise the first method error instead of recording it in the document.
    progress : callable, optional
        Called as ``progress(method, state)`` with state ``"start"``/``"done"``/``"failed"``.
    on_iteration : IterationCallback, optional
        Called at each iteration of the methods' fits.

    Returns
    -------
    dict
        The ``i4cal.result/1`` document as a mapping.
    """
    doc = calibrate_document(obs, methods, strict=strict, progress=progress, on_iteration=on_iteration)
    return doc.model_dump(exclude_unset=True)


def calibrate_document(
    obs: Observations,
    methods: Iterable[str] | None = None,
    *,
    strict: bool = False,
    progress: Callable[[str, str], None] | None = None,
    on_iteration: IterationCallback | None = None,
) -> ResultDocument:
    """Run the methods, validate each result, and return the result document.

    Parameters
    ----------
    obs : Observations
    methods : iterable of str, optional
        Method names (:func:`calib.identify.registry.method_names`; default: every registered method).
    strict : bool
        Raise the first method error instead of recording it in the document.
    progress : callable, optional
        Called as ``progress(method, state)`` with state ``"start"``/``"done"``/``"failed"``.
    on_iteration : callable, optional
        Called after each iteration of each method's fits with ``{"method", "stage", "iteration", "cost"}``
        (:mod:`calib.identify.iterations`); it does not change the results.

    Returns
    -------
    ResultDocument
        ``format``, ``nominal``, ``nominal_combinations``, ``methods`` (per method), ``validation`` (``a priori``,
        per method, ``truth`` on simulated data), ``phases``, ``base_frame``, ``truth_errors`` (simulated data).
    """
    from threadpoolctl import threadpool_limits

    # one BLAS thread: the fits' matrices are small, a second thread only spins (0.4-3 s more CPU for the three
    # methods on 2 cores, for the same result)
    with threadpool_limits(limits=1):
        return _calibrate_document(obs, methods, strict, progress, on_iteration)


def _calibrate_document(
    obs: Observations,
    methods: Iterable[str] | None,
    strict: bool,
    progress: Callable[[str, str], None] | None,
    on_iteration: IterationCallback | None,
) -> ResultDocument:
    """:func:`calibrate_document`'s work, in the caller's thread settings."""
    methods = list(method_names() if methods is None else methods)
    specs = {name: get_method(name) for name in methods}  # an unknown name fails before any fit
    nominal = obs.nominal
    entries: dict[str, MethodEntry] = {}
    bf, bf_summary = _base_frame(obs)
    scale = vision_scale(obs, bf)  # the validation's measuring instrument, calibrated once against the encoders
    validation = {"a priori": ValidationEntry.model_validate(validate(obs, nominal, scale))}
    fit = obs.arrays("poses")
    shared = MethodContext()  # what one method measures that a later one uses (the combined fit's edge bias)
    for name in methods:
        if progress:
            progress(name, "start")
        t0 = time.perf_counter()
        try:
            res = run_method(name, obs, bf, on_iteration=_tag(on_iteration, name), context=shared)
        except I4calError as exc:
            if name == "combined":  # tried: the later methods do not run it again
                shared = dataclasses.replace(shared, combined=CombinedMeasurements())
            if strict:
                raise
            entries[name] = _failed_entry(exc)
            if progress:
                progress(name, "failed")
            continue
        if name == "combined":  # its measurements, passed forward to the methods that carry them (legs)
            shared = dataclasses.replace(shared, combined=CombinedMeasurements.from_result(res))
        full = res.full_parameters(nominal)
        entries[name] = _method_entry(obs, res, full, specs[name], bf, fit.q, time.perf_counter() - t0)
        validation[name] = _validation(obs, full, scale)
        if progress:
            progress(name, "done")
    truth = obs.document.model_extra.get("truth") if obs.document.model_extra else None
    parts: dict[str, Any] = {}
    if isinstance(truth, dict) and "combinations" in truth:
        parts["truth_errors"] = _truth_errors(entries, truth)
        with contextlib.suppress(I4calError, KeyError, ValueError):
            validation["truth"] = _validation(obs, I4Parameters.from_mapping(truth["parameters"]), scale)
    return ResultDocument.model_validate(
        {
            "format": RESULT_FORMAT,
            "nominal": nominal.as_dict(),
            "nominal_combinations": nominal.combinations(),
            "methods": entries,
            "validation": validation,
            "phases": obs.phases(),
            "base_frame": bf_summary,
            **parts,
        }
    )


def _base_frame(obs: Observations) -> tuple[BaseFrameResult | None, BaseFrameSummary]:
    """The base frame from the board's rotation and translation phases, and its summary (or why there is none)."""
    try:
        bf = base_frame_from_observations(obs)
    except I4calError as exc:
        return None, BaseFrameSummary(error=str(exc))
    return bf, BaseFrameSummary.model_validate(bf.summary())


def _failed_entry(exc: I4calError) -> MethodEntry:
    """The entry of a method that gave no result: why, and null values under both names."""
    return MethodEntry(
        converged=False,
        error=str(exc),
        parameters=None,
        std=None,
        combinations=None,
        combinations_std=None,
    )


def _method_entry(
    obs: Observations,
    res: MethodResult,
    full: I4Parameters,
    spec: MethodSpec,
    bf: BaseFrameResult | None,
    q_fit: np.ndarray,
    time_s: float,
) -> MethodEntry:
    """A method's entry: its result, its wall time ``time_s`` (s), the seven parameters it stands for (``full``),
    its identifiability at the fit poses ``q_fit`` ((N, 4), m) and, for a method with one, its Cramer-Rao bound."""
    entry = res.to_dict()
    entry["time_s"] = time_s
    entry["parameters_seven_completed"] = full.seven()
    try:
        has_model = spec.identifiability is not None
        entry["identifiability"] = method_identifiability(spec.name, full, q_fit) if len(q_fit) and has_model else None
    except I4calError as exc:
        entry["identifiability"] = {"error": str(exc)}
    if spec.bound and bf is not None:
        entry["bound"] = _bound_for(obs, full, res, bf)
    return MethodEntry.model_validate(entry)


def _validation(obs: Observations, params: I4Parameters, scale: dict) -> ValidationEntry:
    """:func:`calib.identify.validation.validate` of one parameter set, or why it failed."""
    try:
        return ValidationEntry.model_validate(validate(obs, params, scale))
    except I4calError as exc:
        return ValidationEntry(error=str(exc))


def _truth_errors(entries: dict[str, MethodEntry], truth: dict[str, Any]) -> dict[str, Any]:
    """Method minus truth per combination (and per parameter under ``seven`` when the method identifies them), m."""
    te: dict[str, Any] = {}
    for name, entry in entries.items():
        if entry.parameters:
            te[name] = {k: _num(entry.parameters[k]) - truth["combinations"][k] for k in COMBINATION_NAMES}
            if entry.seven is not None and "parameters" in truth:
                te[name]["seven"] = {k: _num(entry.seven[k]) - truth["parameters"][k] for k in PARAMETER_NAMES}
    return te


def _num(v: float | None) -> float:
    return float("nan") if v is None else v


def _tag(on_iteration: IterationCallback | None, method: str) -> IterationCallback | None:
    """``on_iteration`` with the method's name added to each report."""
    if on_iteration is None:
        return None
    return lambda info: on_iteration({"method": method, **info})


def _bound_for(obs: Observations, params: I4Parameters, res: MethodResult, bf: BaseFrameResult) -> dict:
    """The Cramer-Rao bound of the combined method for these poses, at the noise levels this run measured.

    With rods that carry their measured covariance (``cov_u``, image extraction) and the GLS fit, each
    leg's direction noise is the information sum of its rods' covariances scaled by the fit's measured
    noise scale; otherwise an isotropic direction noise of the measured scale (radians).
    """
    from calib.formats.plan import Plan, Step
    from calib.identify.bound import MeasurementNoise, crlb_combined

    steps = [Step(phase=f.phase, q=f.q) for f in obs.frames if f.phase in ("rotation", "translation", "poses")]
    scale = float(res.diagnostics.get("direction_noise_scale", 0.0))
    sig_r = bf.rotation_residual_rms_rad / np.sqrt(2.0)  # two tangent components carry the residual
    sig_t = bf.translation_residual_rms_m / np.sqrt(3.0)
    if min(scale, sig_r, sig_t) <= 0:
        return {"std": None, "note": "noise-free data: the bound is zero"}
    rod_cov = _leg_covariances(obs, scale**2) if res.diagnostics.get("weighting") == "gls" else None
    noise = MeasurementNoise(
        scale if rod_cov is None else 0.0, sig_r, (sig_t, sig_t, sig_t), rods_per_leg=2 if rod_cov is None else 1
    )
    try:
        b = crlb_combined(params, Plan(name="observed", steps=steps), noise, bf.camera_from_base_R, rod_cov)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return {"std": None, "note": str(exc)}
    cov_intr = res.diagnostics.get("intrinsics_covariance")
    if cov_intr is not None:
        # the intrinsics are nuisance parameters known from the camera calibration: their prior adds
        cov = np.asarray(b["covariance"]) + np.asarray(cov_intr)
        b["covariance"] = cov.tolist()
        b["std"] = {k: float(np.sqrt(cov[i, i])) for i, k in enumerate(COMBINATION_NAMES)}
        b["includes_intrinsics"] = True
    b["efficiency_std_ratio"] = {k: res.combinations_std[k] / v for k, v in b["std"].items()}
    b["note"] = (
        "Cramer-Rao bound for these poses at the noise levels measured in this run ("
        + (
            "each rod's measured direction covariance, scaled by the fit's noise scale"
            if rod_cov is not None
            else "isotropic rod-direction noise"
        )
        + "; isotropic board-pose noise)"
    )
    return b


def _leg_covariances(obs: Observations, s2: float) -> np.ndarray | None:
    """Per fit pose and leg, the direction covariance of the leg from its rods' ``cov_u_own`` (else ``cov_u``: what
    the combined fit weighs by), (N, 4, 3, 3).

    Information sum of the leg's rods in the plane normal to their mean direction; a leg without a
    measured rod gets a covariance so large it carries no information. None when a rod lacks ``cov_u``.
    """
    out = []
    for f in obs.frames:
        if f.phase != "poses":
            continue
        legs = []
        for leg in range(4):
            rods = cast(dict[str, list[Rod | None]], f.legs or {}).get(LEG_KEYS[leg]) or []
            info = np.zeros((3, 3))
            for rod in rods:
                if rod is None:
                    continue
                c = rod.cov_u_own if rod.cov_u_own is not None else rod.cov_u
                if c is None:
                    return None
                u = np.asarray(rod.u, dtype=np.float64)
                T = tangent_basis(u)
                C2 = T.T @ (s2 * np.asarray(c, dtype=np.float64)) @ T
                info += T @ np.linalg.inv(C2) @ T.T
            if not info.any():
                legs.append(1e6 * np.eye(3))
                continue
            # pseudo-inverse: nothing along the rods' own direction, which the bound projects out
            # (a large variance there would leak into the model direction's tangent plane)
            w, V = np.linalg.eigh(info)  # rank 2: the smallest eigenvalue is along the rods (zero)
            inv = np.where(w[1:] > 1e-12 * w[-1], 1.0 / np.maximum(w[1:], 1e-300), 0.0)
            legs.append(V[:, 1:] @ np.diag(inv) @ V[:, 1:].T)
        out.append(legs)
    return np.asarray(out) if out else None
