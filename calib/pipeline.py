"""Run calibration methods on observations and assemble the result document (``i4cal calibrate --json``)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from .baseframe import BaseFrameResult, base_frame_from_observations
from .errors import I4calError
from .identifiability import identifiability
from .methods import METHODS
from .methods.result import MethodResult
from .observations import Observations
from .parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters
from .validation import validate

METHOD_NAMES = tuple(METHODS)
RESULT_FORMAT = "i4cal.result/1"


def run_method(name: str, obs: Observations, base_frame: BaseFrameResult | None = None) -> MethodResult:
    if name not in METHODS:
        raise I4calError(f"unknown method {name!r}; methods are {', '.join(METHODS)} or all")
    if name == "combined":
        return METHODS[name](obs, base_frame=base_frame)
    return METHODS[name](obs)


def calibrate(obs: Observations, methods: Iterable[str] = METHOD_NAMES, *, strict: bool = False,
              progress: Callable[[str, str], None] | None = None) -> dict[str, Any]:
    """Run the methods, validate each result, and return the result document.

    Parameters
    ----------
    obs : Observations
    methods : iterable of str
        Method names (``combined``, ``end-effector``, ``legs``).
    strict : bool
        Raise the first method error instead of recording it in the document.
    progress : callable, optional
        Called as ``progress(method, state)`` with state ``"start"``/``"done"``/``"failed"``.

    Returns
    -------
    dict
        ``{"format", "methods": {name: {...}}, "validation": {"a priori": ..., name: ...}, "base_frame",
        "nominal", "truth_errors"?}``.
    """
    methods = list(methods)
    nominal = obs.nominal
    out: dict[str, Any] = {"format": RESULT_FORMAT, "nominal": nominal.as_dict(),
                           "nominal_combinations": nominal.combinations(), "methods": {}, "validation": {},
                           "phases": obs.phases()}
    bf = None
    try:
        bf = base_frame_from_observations(obs)
        out["base_frame"] = bf.summary()
    except I4calError as exc:
        out["base_frame"] = {"error": str(exc)}
    out["validation"]["a priori"] = validate(obs, nominal)
    fit = obs.arrays("poses")
    for name in methods:
        if progress:
            progress(name, "start")
        t0 = time.perf_counter()
        try:
            res = run_method(name, obs, bf)
        except I4calError as exc:
            if strict:
                raise
            out["methods"][name] = {"converged": False, "error": str(exc), "parameters": None, "std": None}
            if progress:
                progress(name, "failed")
            continue
        entry = res.to_dict()
        entry["time_s"] = time.perf_counter() - t0
        full = res.full_parameters(nominal)
        entry["parameters_seven_completed"] = full.seven()
        try:
            entry["identifiability"] = identifiability(name, full, fit.q) if len(fit) else None
        except I4calError as exc:
            entry["identifiability"] = {"error": str(exc)}
        out["methods"][name] = entry
        try:
            out["validation"][name] = validate(obs, full)
        except I4calError as exc:
            out["validation"][name] = {"error": str(exc)}
        if progress:
            progress(name, "done")
    truth = obs.document.model_extra.get("truth") if obs.document.model_extra else None
    if isinstance(truth, dict) and "combinations" in truth:
        te: dict[str, Any] = {}
        for name, entry in out["methods"].items():
            if entry.get("parameters"):
                te[name] = {k: entry["parameters"][k] - truth["combinations"][k] for k in COMBINATION_NAMES}
                if "seven" in entry and "parameters" in truth:
                    te[name]["seven"] = {k: entry["seven"][k] - truth["parameters"][k] for k in PARAMETER_NAMES}
        out["truth_errors"] = te
        with contextlib.suppress(I4calError, KeyError, ValueError):
            out["validation"]["truth"] = validate(obs, I4Parameters.from_mapping(truth["parameters"]))
    return out


def to_jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
