"""The method registry: every identification method, described once, read by every consumer.

A method is a :class:`MethodSpec`: its name (the key in result documents, ``--method`` and the API), a label and a
colour for the report and the dashboard, a one-sentence description, the observation phases it needs, its public
measurement model at a pose set (``model(params, q) -> PoseSetModel``: predictions, residuals, Jacobian, covariance;
:mod:`calib.identify.pose_set_model`, :func:`method_model`), whether the pipeline computes a Cramer-Rao bound for it,
and a
uniform ``fit(observations, context) -> MethodResult``. The pipeline (:mod:`calib.identify.pipeline`), the
identifiability
report, the command line, the REST service (``GET /api/v1/methods``), the report and the dashboard list the methods
from here, in registration order.

Adding a method: write its module (a ``fit`` function and a ``MethodSpec``) and register it, either with one line in
:func:`_builtin_specs` (a method of this package) or, outside the package, with :func:`register_method` in a module
that is named in the ``I4CAL_METHODS`` environment variable (comma-separated module names) or in the
``i4cal.methods`` entry-point group; those modules are imported on the first use of the registry, in every process
(the service's fit processes too).
"""

from __future__ import annotations

import importlib
import os
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.errors import I4calError, InputError
from calib.formats.observations import Observations
from calib.identify.baseframe import BaseFrameResult
from calib.identify.combined_measurements import CombinedMeasurements
from calib.identify.identifiability import analyse
from calib.identify.iterations import IterationCallback
from calib.identify.pose_set_model import ModelFactory, PoseSetModel
from calib.identify.result import MethodResult
from calib.model.parameters import I4Parameters, identifiable_parameters

#: Name of a method: lower case, digits and dashes (it is a URL, CLI and JSON key).
NAME_PATTERN = r"^[a-z][a-z0-9-]{0,31}$"
#: Environment variable naming modules (comma-separated) that register methods when imported.
ENV_VAR = "I4CAL_METHODS"
#: Entry-point group of the same (``module`` or ``module:attr``; importing the module registers).
ENTRY_POINT_GROUP = "i4cal.methods"


@dataclass(frozen=True)
class MethodContext:
    """What the pipeline hands a method besides the observations.

    Attributes
    ----------
    base_frame : BaseFrameResult or None
        The base frame found from the rotation and translation phases (None when it could not be found).
    on_iteration : callable or None
        Receives ``{"stage", "iteration", "cost"}`` after each iteration of the method's fits
        (:mod:`calib.identify.iterations`).
    combined : CombinedMeasurements or None
        What a combined fit of the same run measured (the limb-edge bias and the intrinsics; empty when it failed);
        None: no combined fit ran before (a method that needs its measurements runs it once itself).
    """

    base_frame: BaseFrameResult | None = None
    on_iteration: IterationCallback | None = None
    combined: CombinedMeasurements | None = None


#: ``fit(observations, context) -> MethodResult``.
FitFunction = Callable[[Observations, MethodContext], MethodResult]
#: ``model(params, q) -> (f, n_nuisance)``: the method's measurement model as a function of the seven parameters
#: followed by ``n_nuisance`` nuisance parameters (:func:`calib.identify.identifiability.analyse`); ``q`` (N, 4)
#: encoders, m.
#: The same as a :data:`calib.identify.pose_set_model.ModelFactory`, in the tuple form.
IdentifiabilityModel = Callable[[I4Parameters, np.ndarray], tuple[Callable[[np.ndarray], np.ndarray], int]]


@dataclass(frozen=True)
class MethodSpec:
    """One identification method.

    Attributes
    ----------
    name : str
        Key in result documents, ``i4cal calibrate --method`` and the API (:data:`NAME_PATTERN`).
    label : str
        Short human name (report headings, dashboard).
    colour : str
        ``#rrggbb`` of its plots and dashboard marks.
    description : str
        One sentence: what it observes and fits.
    fit : callable
        ``fit(observations, context) -> MethodResult`` (:data:`FitFunction`); raises
        :class:`calib.errors.I4calError` subclasses for data it cannot use.
    required_phases : tuple of str
        Observation phases it needs (observations v1 phase names).
    identifiability : callable or None
        Its measurement model for the identifiability report, in the tuple form (:data:`IdentifiabilityModel`);
        derived from ``model`` when not given. None (and no ``model``): no report.
    bound : bool
        The pipeline computes the Cramer-Rao bound of its estimate (the combined method's bound).
    apply_rank : int
        Preference when a run's result is applied without naming a method: the converged method of lowest rank.
    model : callable or None
        Its public measurement model at a pose set, ``model(params, q) -> PoseSetModel`` (residuals, Jacobian,
        covariance: :mod:`calib.identify.pose_set_model`; :func:`method_model`); derived from ``identifiability`` when
        not
        given. None: the method has none.
    """

    name: str
    label: str
    colour: str
    description: str
    fit: FitFunction
    required_phases: tuple[str, ...] = ("poses",)
    identifiability: IdentifiabilityModel | None = None
    bound: bool = False
    apply_rank: int = 100
    model: ModelFactory | None = None

    def __post_init__(self) -> None:
        if not re.match(NAME_PATTERN, self.name) or self.name == "all":
            raise InputError(f"method name {self.name!r} must match {NAME_PATTERN} and not be 'all'", field="name")
        if not re.match(r"^#[0-9a-fA-F]{6}$", self.colour):
            raise InputError(f"method {self.name}: colour {self.colour!r} is not #rrggbb", field="colour")
        if not callable(self.fit):
            raise InputError(f"method {self.name}: fit is not callable", field="fit")
        # one model, two forms: the PoseSetModel factory and the identifiability report's (f, n_nuisance)
        if self.model is None and self.identifiability is not None:
            object.__setattr__(self, "model", _model_from_tuple(self.identifiability))
        elif self.model is not None and self.identifiability is None:
            object.__setattr__(self, "identifiability", _tuple_from_model(self.model))

    def summary(self) -> dict[str, Any]:
        """JSON-able description (``GET /api/v1/methods``)."""
        return {
            "name": self.name,
            "label": self.label,
            "colour": self.colour,
            "description": self.description,
            "required_phases": list(self.required_phases),
            "identifiability": self.identifiability is not None,
            "bound": self.bound,
        }


def _model_from_tuple(identifiability: IdentifiabilityModel) -> ModelFactory:
    def model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
        f, k = identifiability(params, q)
        return PoseSetModel(f, params, k)

    return model


def _tuple_from_model(model: ModelFactory) -> IdentifiabilityModel:
    def identifiability(params: I4Parameters, q: np.ndarray) -> tuple[Callable[[np.ndarray], np.ndarray], int]:
        m = model(params, q)
        return m.fun, m.n_nuisance

    return identifiability


_lock = threading.RLock()
_registry: dict[str, MethodSpec] = {}
_builtin_names: tuple[str, ...] = ()
_plugins_loaded = False
_plugin_modules: list[str] = []


def register_method(spec: MethodSpec, *, replace: bool = False) -> MethodSpec:
    """Register ``spec`` (after the methods already registered); return it.

    Parameters
    ----------
    spec : MethodSpec
        The method: its name, fit function, model and options.
    replace : bool
        Replace a method of the same name instead of raising.

    Returns
    -------
    MethodSpec
        ``spec``.

    Raises
    ------
    InputError
        A method of that name exists and ``replace`` is False.
    """
    with _lock:
        _ensure_builtins()
        if spec.name in _registry and not replace:
            raise InputError(f"a method named {spec.name!r} is already registered", field="name")
        _registry[spec.name] = spec
        module = getattr(spec.fit, "__module__", None)
        if spec.name not in _builtin_names and module and module != "__main__" and module not in _plugin_modules:
            _plugin_modules.append(module)
    return spec


def unregister_method(name: str) -> None:
    """Remove a method registered by :func:`register_method` (built-in methods stay).

    Parameters
    ----------
    name : str
        The method's name; an unknown name is ignored.

    Raises
    ------
    InputError
        ``name`` is a built-in method.
    """
    with _lock:
        if name in _builtin_names:
            raise InputError(f"{name!r} is a built-in method", field="name")
        spec = _registry.pop(name, None)
        module = getattr(spec.fit, "__module__", None) if spec else None
        if module in _plugin_modules and all(getattr(s.fit, "__module__", None) != module for s in _registry.values()):
            _plugin_modules.remove(module)


def methods() -> tuple[MethodSpec, ...]:
    """Every registered method, in registration order (the built-in three first).

    Returns
    -------
    tuple of MethodSpec
        The registered methods.
    """
    _ensure_loaded()
    with _lock:
        return tuple(_registry.values())


def method_names() -> tuple[str, ...]:
    """Names of the registered methods, in registration order.

    Returns
    -------
    tuple of str
        The registered methods' names.
    """
    return tuple(s.name for s in methods())


def get_method(name: str) -> MethodSpec:
    """The spec of method ``name``.

    Parameters
    ----------
    name : str
        The method's name.

    Returns
    -------
    MethodSpec
        Its spec.

    Raises
    ------
    InputError
        No such method (the message lists the registered ones).
    """
    _ensure_loaded()
    spec = _registry.get(name)
    if spec is None:
        raise InputError(f"unknown method {name!r}; methods are {', '.join(_registry)} or all", field="method")
    return spec


def apply_order() -> tuple[str, ...]:
    """Method names by preference for applying a result (``apply_rank``, then registration order).

    Returns
    -------
    tuple of str
        The registered methods' names, the preferred first.
    """
    specs = methods()
    order = sorted(range(len(specs)), key=lambda i: (specs[i].apply_rank, i))
    return tuple(specs[i].name for i in order)


def plugin_modules() -> tuple[str, ...]:
    """Modules that registered methods beyond the built-in ones (import them in another process to have them).

    Returns
    -------
    tuple of str
        Dotted module names, in registration order.
    """
    _ensure_loaded()
    with _lock:
        return tuple(_plugin_modules)


def load_modules(names: list[str] | tuple[str, ...]) -> None:
    """Import the modules ``names`` (each registers its methods when imported); already imported ones are skipped.

    Parameters
    ----------
    names : list of str or tuple of str
        Dotted module names (blank entries are skipped).

    Raises
    ------
    I4calError
        A module cannot be imported (named with the reason).
    """
    _ensure_builtins()
    for name in names:
        name = name.strip()
        if not name:
            continue
        try:
            importlib.import_module(name.split(":", 1)[0])
        except ImportError as exc:
            raise I4calError(f"cannot import method module {name!r} ({ENV_VAR} or plugins): {exc}") from None


def _ensure_loaded() -> None:
    global _plugins_loaded
    _ensure_builtins()
    if _plugins_loaded:
        return
    with _lock:
        if _plugins_loaded:
            return
        _plugins_loaded = True
        from importlib.metadata import entry_points

        names = [ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)]
        names += os.environ.get(ENV_VAR, "").split(",")
        load_modules(names)


def _ensure_builtins() -> None:
    global _builtin_names
    if _builtin_names:
        return
    with _lock:
        if _builtin_names:
            return
        specs = _builtin_specs()
        for s in specs:
            _registry.setdefault(s.name, s)
        _builtin_names = tuple(s.name for s in specs)


# -- the built-in methods ---------------------------------------------------------------------------------------
def _fit_combined(obs: Observations, ctx: MethodContext) -> MethodResult:
    from calib.identify.combined import calibrate_combined

    return calibrate_combined(obs, base_frame=ctx.base_frame, on_iteration=ctx.on_iteration)


def _fit_end_effector(obs: Observations, ctx: MethodContext) -> MethodResult:
    from calib.identify.end_effector import calibrate_end_effector

    return calibrate_end_effector(obs, on_iteration=ctx.on_iteration)


def _fit_legs(obs: Observations, ctx: MethodContext) -> MethodResult:
    from calib.identify.legs import calibrate_legs

    # the combined fit's measurements of the limb-edge bias and the intrinsics when the run already made them; None:
    # calibrate_legs runs the combined fit once itself when its data need them
    return calibrate_legs(obs, on_iteration=ctx.on_iteration, combined=ctx.combined)


def _combined_model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    from calib.identify.combined import pose_set_model

    return pose_set_model(params, q)


def _end_effector_model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    from calib.identify.end_effector import pose_set_model

    return pose_set_model(params, q)


def _legs_model(params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    from calib.identify.legs import pose_set_model

    return pose_set_model(params, q)


def method_model(method: str, params: I4Parameters, q: np.ndarray) -> PoseSetModel:
    """The measurement model of a registered method at a pose set (:attr:`MethodSpec.model`).

    Parameters
    ----------
    method : str
        A registered method's name.
    params : I4Parameters
        The linearisation point.
    q : ndarray, shape (N, 4)
        Encoder values of the poses, m.

    Returns
    -------
    PoseSetModel
        Its predictions, residuals, Jacobian (in the seven parameters, m, then its nuisance unknowns) and the
        covariance of the four combinations for a given measurement noise.

    Raises
    ------
    ValueError
        The method is not registered, or has no model.
    """
    q = np.asarray(q, dtype=np.float64)
    try:
        spec = get_method(method)
    except InputError as exc:
        raise ValueError(str(exc)) from None
    if spec.model is None:
        raise ValueError(f"method {method!r} has no identifiability model")
    return spec.model(params, q)


def method_identifiability(method: str, params: I4Parameters, q: np.ndarray) -> dict:
    """Identifiability report of a registered method at a pose set (encoders q, (N, 4), m): its
    :attr:`MethodSpec.model` analysed by :func:`calib.identify.identifiability.analyse`.

    Parameters
    ----------
    method : str
        A registered method's name.
    params : I4Parameters
        The geometry at which the model is linearised.
    q : array_like, shape (N, 4)
        Encoder values of the poses, m.

    Returns
    -------
    dict
        :func:`calib.identify.identifiability.analyse`'s report, plus ``method``, ``n_poses`` and ``combination_values``
        (the identifiable combinations at ``params``, m).

    Raises
    ------
    ValueError
        The method is not registered, or has no identifiability model.
    """
    q = np.asarray(q, dtype=np.float64)
    model = method_model(method, params, q)
    out = analyse(model.fun, params, model.n_nuisance)
    out["method"] = method
    out["n_poses"] = int(q.shape[0])
    out["combination_values"] = identifiable_parameters(params)
    return out


def _builtin_specs() -> list[MethodSpec]:
    """The methods of this package, one line each (the order of result documents and menus)."""
    return [
        MethodSpec(
            name="combined",
            label="combined",
            colour="#1f77b4",
            description="legs + end-effector (the paper's eq. 8): the Jacobian entries observed on the legs, in the "
            "base frame found from the board's rotation and translation phases, fitted to the model's",
            fit=_fit_combined,
            required_phases=("rotation", "translation", "poses"),
            model=_combined_model,
            bound=True,
            apply_rank=0,
        ),
        MethodSpec(
            name="end-effector",
            label="end-effector",
            colour="#ff7f0e",
            description="end-effector only: the board poses fitted through the direct kinematic model, camera and "
            "board placements as nuisance parameters",
            fit=_fit_end_effector,
            required_phases=("poses",),
            model=_end_effector_model,
            apply_rank=2,
        ),
        MethodSpec(
            name="legs",
            label="legs",
            colour="#2ca02c",
            description="legs only: joint centres from the lock-actuator phases, then all seven parameters from the "
            "leg axes",
            fit=_fit_legs,
            required_phases=("lock-1", "lock-2", "lock-3", "lock-4", "poses"),
            model=_legs_model,
            apply_rank=1,
        ),
    ]


__all__ = [
    "ENTRY_POINT_GROUP",
    "ENV_VAR",
    "FitFunction",
    "IdentifiabilityModel",
    "MethodContext",
    "MethodSpec",
    "apply_order",
    "get_method",
    "load_modules",
    "method_identifiability",
    "method_model",
    "method_names",
    "methods",
    "plugin_modules",
    "register_method",
    "unregister_method",
]
