"""The calibration document a robot controller loads: ``i4cal.calibration/1`` (docs/export.md).

One document per calibration: where it comes from (bench, run, method, date, software version, dataset hash), the
seven parameters of the I4 model (docs/model.md) in metres, which of them were identified and which were fixed at
their nominal values (and the rule that completed them), the four identifiable combinations with their standard
deviations and covariance, the nominal geometry it was made against, and the units, stated in the document.

Built from a result document (``i4cal.result/1``, :mod:`calib.formats.resultdoc`) by :func:`build_calibration`; checked
against the result's own model by :func:`check_parity` (the largest DKM and IKM difference over a plan's poses).
Pure: no file or network access (the command line and the service read and write the text, JSON or YAML).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from calib.errors import InputError, UnreachableError
from calib.formats.plan import Plan, line_poses
from calib.formats.resultdoc import Combinations, MethodEntry, ResultDocument, ValidationEntry
from calib.identify.verdict import verdict
from calib.model.kinematics import dkm, ikm
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters

CALIBRATION_FORMAT: Final = "i4cal.calibration/1"

#: How close the seven parameters must reproduce the four combinations, and the default tolerance of the parity
#: check (:func:`check_parity`), metres. The document carries the values the result computed, bit for bit (JSON and
#: YAML both write a float's shortest round-trip form), so any difference is a transcription error.
REPRODUCE_TOL_M = 1e-9

#: The parameters the four combinations leave free: no Jacobian- or IKM-based method sees them (constant offsets of
#: X, T and the mid-line), completed at their nominal values
#: (:meth:`calib.model.parameters.I4Parameters.from_combinations`).
FREE_PARAMETERS: tuple[str, ...] = ("H", "S", "q03")

#: Completion rules, by name: how the seven parameters were made from what the method identified.
COMPLETION_RULES: dict[str, str] = {
    "identified": "the method identified all seven parameters",
    "combinations+nominal": "the four combinations completed with the nominal H, S, q03: q02 = 2 (S - (S-q02/2)), "
    "q04 = q03 + 2 (S - (S-(q04-q03)/2)), D = H - (H-D), L = L (calib.model.parameters.I4Parameters.from_combinations)",
    "a-priori L, S, D": "the method identified H, q02, q03, q04 (lock phases); its data contradicted the a priori "
    "tolerance on L, S, D, which are the nominal values",
    "a-priori all": "the method's data contradicted the a priori tolerance: all seven are the nominal values",
}


class Units(BaseModel):
    """The units of every number of the document."""

    model_config = ConfigDict(extra="allow")
    length: Literal["m"] = Field("m", description="the seven parameters, the combinations, their std")
    covariance: Literal["m^2"] = Field("m^2", description="the combinations' covariance")
    T_per_rad: Literal["m/rad"] = Field("m/rad", description="metres of T per radian of end-effector rotation")
    date: Literal["ISO 8601 UTC"] = "ISO 8601 UTC"


class Completion(BaseModel):
    """How the seven parameters were completed from what the method identified."""

    rule: str = Field(description="one of: " + ", ".join(COMPLETION_RULES))
    text: str = Field(description="the rule in words")


class Validation(BaseModel):
    """The calibration's displacement gap against vision on poses it was not fitted to (Table II), m."""

    model_config = ConfigDict(extra="allow")
    poses: Literal["validation", "fit"] = Field(description="which poses' gaps (validation when the plan has them)")
    gap_rms_m: float | None = Field(description="RMS gap with these parameters, m")
    a_priori_gap_rms_m: float | None = Field(description="RMS gap with the nominal parameters, m")


class Source(BaseModel):
    """What the document was made from."""

    model_config = ConfigDict(extra="allow")
    result_sha256: str | None = Field(
        None, description="SHA-256 of the result document (canonical JSON: sorted keys, no spaces, UTF-8)"
    )
    result_file: str | None = Field(None, description="the result file it was exported from, when one")


class CalibrationDocument(BaseModel):
    """``i4cal.calibration/1``: the calibration a controller loads (docs/export.md). Metres throughout."""

    model_config = ConfigDict(extra="allow", title="i4cal calibration v1")

    format: Literal["i4cal.calibration/1"] = CALIBRATION_FORMAT
    units: Units = Field(default_factory=Units)
    bench: str | None = Field(None, description="the bench the calibration is of")
    run: str | None = Field(None, description="the service run that produced the result (null: a result file)")
    method: str = Field(description="the identification method (GET /api/v1/methods names)")
    method_choice: str = Field(description="why this method: asked for, or the recommendation rule")
    date: str | None = Field(
        None, description="when the result was made (the run's end; a result file's modification time), ISO 8601 UTC"
    )
    exported_at: str | None = Field(None, description="when this document was written, ISO 8601 UTC")
    software_version: str = Field(description="the i4cal version that wrote this document")
    dataset_hash: str | None = Field(
        None,
        description="SHA-256 of the dataset (manifest of dataset.json and its frames; the report's 'dataset "
        "SHA-256'), null when not known",
    )
    seven: dict[str, float] = Field(description="the seven parameters H, q02, q03, q04, S, D, L, m")
    seven_std: dict[str, float | None] = Field(
        description="their standard deviations, m (null for a parameter fixed at its nominal value)"
    )
    identified: list[str] = Field(description="the parameters the data determined (directly or via a combination)")
    fixed_at_nominal: list[str] = Field(description="the parameters set to their nominal value")
    completion: Completion
    T_per_rad: float = Field(gt=0, description="model constant: metres of T per radian of end-effector rotation")
    combinations: dict[str, float] = Field(description="L, H-D, S-q02/2, S-(q04-q03)/2 identified, m")
    combinations_std: dict[str, float | None] = Field(description="their standard deviations, m")
    covariance: list[list[float]] | None = Field(
        None, description="4x4 covariance of the combinations in covariance_order, m^2 (null: no longer stored)"
    )
    covariance_order: list[str] = Field(default_factory=lambda: list(COMBINATION_NAMES))
    nominal: dict[str, float] = Field(description="the a priori geometry it was made against: seven and T_per_rad")
    nominal_combinations: dict[str, float] = Field(description="the a priori combinations, m")
    validation: Validation | None = None
    warnings: list[str] = Field(default_factory=list, description="what the method said the user must know")
    source: Source = Field(default_factory=Source)

    def to_parameters(self) -> I4Parameters:
        """The model the document stands for (the seven parameters and ``T_per_rad``)."""
        return I4Parameters.from_mapping({**self.seven, "T_per_rad": self.T_per_rad})


@dataclass(frozen=True)
class ExportContext:
    """Provenance written into the document (what the result file itself does not hold).

    Attributes
    ----------
    software_version : str
    bench, run, date, exported_at : str or None
        ``date``/``exported_at``: ISO 8601 UTC.
    dataset_hash : str or None
        SHA-256 hex of the dataset manifest.
    result_sha256, result_file : str or None
    """

    software_version: str
    bench: str | None = None
    run: str | None = None
    date: str | None = None
    exported_at: str | None = None
    dataset_hash: str | None = None
    result_sha256: str | None = None
    result_file: str | None = None


# -- which method ---------------------------------------------------------------------------------------------
def _gap_rms_m(validation: ValidationEntry | None) -> tuple[float | None, Literal["validation", "fit"]]:
    """The RMS displacement gap of one parameter set's validation entry, m, and which poses it is over."""
    if validation is not None:
        for gaps, poses in ((validation.gaps_validation, "validation"), (validation.gaps_poses, "fit")):
            rms = gaps.rms_finite_mm() if gaps is not None else None
            if rms is not None:
                # poses: one of the two literals of the loop's tuples
                return rms * 1e-3, poses  # type: ignore[return-value]
    return None, "validation"


def recommended_method(result: ResultDocument | dict[str, Any]) -> tuple[str, str]:
    """The method to export when none is asked for, and why: the verdict's (:func:`calib.identify.verdict.verdict`, the
    rule the demo, ``calibrate``, the report and the dashboard state).

    Parameters
    ----------
    result : ResultDocument or dict
        The calibration result.

    Returns
    -------
    method : str
        The method's name.
    reason : str
        Why, as shown to the user (``"recommended: ..."``).

    Raises
    ------
    InputError
        No method of the result converged, or none improves the a priori geometry's validation gap
        (``field="methods"``; the message gives the verdict's reason).
    """
    v = verdict(result)
    if v.method is None:
        raise InputError(f"{v.reason}; nothing recommended to export (name one with --method)", field="methods")
    return v.method, f"recommended: {v.reason}"


# -- the document -----------------------------------------------------------------------------------------------
def _four(mapping: Combinations | None, what: str) -> dict[str, float]:
    if mapping is None:
        raise InputError(f"the result has no {what}", field=what)
    out = {}
    for k in COMBINATION_NAMES:
        v = mapping.get(k)
        if v is None or not math.isfinite(v):
            raise InputError(f"{k} is missing or not a finite number", field=f"{what}.{k}")
        out[k] = float(v)
    return out


def _nominal(result: ResultDocument) -> I4Parameters:
    try:
        return I4Parameters.from_mapping(result.nominal)
    except (ValueError, TypeError) as exc:
        raise InputError(f"the result's nominal geometry: {exc}", field="nominal") from None


def _status(entry: MethodEntry) -> tuple[str, list[str], list[str]]:
    """Completion rule, identified parameters, parameters fixed at nominal."""
    if not entry.seven:
        fixed = list(FREE_PARAMETERS)
        return "combinations+nominal", [n for n in PARAMETER_NAMES if n not in fixed], fixed
    fallback = entry.diagnostics.a_priori_fallback() if entry.diagnostics is not None else None
    if fallback == "all seven":
        return "a-priori all", [], list(PARAMETER_NAMES)
    if fallback == "L, S, D":
        fixed = ["S", "D", "L"]
        return "a-priori L, S, D", [n for n in PARAMETER_NAMES if n not in fixed], fixed
    return "identified", list(PARAMETER_NAMES), []


def _entry(result: ResultDocument, method: str) -> MethodEntry:
    """Method ``method``'s entry of ``result``, converged.

    Raises
    ------
    InputError
        No such method, or it did not converge (``field="method"``).
    """
    entry = result.methods.get(method)
    if entry is None:
        have = ", ".join(result.methods) or "none"
        raise InputError(f"the result has no method {method!r} (it has: {have})", field="method")
    if not entry.ok:
        why = f": {entry.error}" if entry.error else ""
        raise InputError(f"method {method!r} did not converge in this result{why}; nothing to export", field="method")
    return entry


def method_parameters(result: ResultDocument | dict[str, Any], method: str) -> I4Parameters:
    """The seven parameters method ``method`` of ``result`` stands for (what its own validation used):
    ``parameters_seven_completed``, else ``seven``, else its combinations completed with the nominal H, S, q03.

    Parameters
    ----------
    result : ResultDocument or dict
        The calibration result.
    method : str
        The method's name.

    Returns
    -------
    I4Parameters
        The seven parameters, m (``T_per_rad`` m/rad).

    Raises
    ------
    InputError
        Not a result document, no such method, or it did not converge (``field="method"``).
    """
    doc = ResultDocument.from_dict(result)
    entry = _entry(doc, method)
    nominal = _nominal(doc)
    seven = entry.seven_or_completed
    if seven:
        try:
            return I4Parameters.from_mapping({**seven, "T_per_rad": nominal.T_per_rad})
        except (ValueError, TypeError) as exc:
            raise InputError(f"{exc}", field=f"methods.{method}.parameters_seven_completed") from None
    return I4Parameters.from_combinations(_four(entry.values, f"methods.{method}.combinations"), nominal)


def _seven_std(
    entry: MethodEntry, fixed: list[str], cov: np.ndarray | None, std4: dict[str, float | None]
) -> dict[str, float | None]:
    """Standard deviations of the seven: the method's, or those of the combinations through the completion."""
    if entry.seven_std:
        return {n: (None if n in fixed else _finite_or_none(entry.seven_std.get(n))) for n in PARAMETER_NAMES}
    # completed: L = c1, D = H - c2, q02 = 2 S - 2 c3, q04 = q03 + 2 S - 2 c4 (H, S, q03 fixed)
    s = dict(std4)
    if cov is not None:
        s = {k: float(math.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(COMBINATION_NAMES)}

    def times(k: str, f: float) -> float | None:
        v = s.get(k)
        return None if v is None else f * v

    derived = {
        "L": times("L", 1.0),
        "D": times("H-D", 1.0),
        "q02": times("S-q02/2", 2.0),
        "q04": times("S-(q04-q03)/2", 2.0),
    }
    return {n: (None if n in fixed else derived.get(n)) for n in PARAMETER_NAMES}


def _finite_or_none(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def _covariance(entry: MethodEntry, where: str) -> np.ndarray | None:
    if entry.covariance is None:
        return None
    try:
        a = np.asarray(entry.covariance, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("not a 4x4 matrix of numbers", field=where) from None
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise InputError(f"must be a finite 4x4 matrix, got shape {a.shape}", field=where)
    return a


def build_calibration(
    result: ResultDocument | dict[str, Any], context: ExportContext, method: str | None = None
) -> CalibrationDocument:
    """The ``i4cal.calibration/1`` document of one method of a result.

    Parameters
    ----------
    result : ResultDocument or dict
        An ``i4cal.result/1`` document (``i4cal calibrate -o``, ``GET /api/v1/runs/{id}/result``).
    context : ExportContext
        Provenance the result does not hold.
    method : str, optional
        The method to export (default: :func:`recommended_method`).

    Returns
    -------
    CalibrationDocument
        Its seven parameters reproduce the method's four combinations within :data:`REPRODUCE_TOL_M`.

    Raises
    ------
    InputError
        Not a result document, no such method, not converged, or values that do not agree (names the field).
    """
    doc = ResultDocument.from_dict(result)
    choice = f"asked for: {method}"
    if method is None:
        method, choice = recommended_method(doc)
    params = method_parameters(doc, method)
    entry = _entry(doc, method)
    combos = _four(entry.values, f"methods.{method}.combinations")
    got = params.combinations()
    worst = max(COMBINATION_NAMES, key=lambda k: abs(got[k] - combos[k]))
    if abs(got[worst] - combos[worst]) > REPRODUCE_TOL_M:
        raise InputError(
            f"the seven parameters give {worst} = {got[worst]!r} m, the method reports {combos[worst]!r} m "
            f"({abs(got[worst] - combos[worst]) * 1e3:.3g} mm apart): the result is inconsistent",
            field=f"methods.{method}.parameters_seven_completed",
        )
    rule, identified, fixed = _status(entry)
    cov = _covariance(entry, f"methods.{method}.covariance")
    std4_raw = entry.values_std or {}
    std4 = {k: _finite_or_none(std4_raw.get(k)) for k in COMBINATION_NAMES}
    nominal = _nominal(doc)
    gap, poses = _gap_rms_m(doc.validation.get(method))
    gap0, _ = _gap_rms_m(doc.validation.get("a priori"))
    return CalibrationDocument(
        bench=context.bench,
        run=context.run,
        method=method,
        method_choice=choice,
        date=context.date,
        exported_at=context.exported_at,
        software_version=context.software_version,
        dataset_hash=context.dataset_hash,
        seven=params.seven(),
        seven_std=_seven_std(entry, fixed, cov, std4),
        identified=identified,
        fixed_at_nominal=fixed,
        completion=Completion(rule=rule, text=COMPLETION_RULES[rule]),
        T_per_rad=params.T_per_rad,
        combinations=combos,
        combinations_std=std4,
        covariance=None if cov is None else cov.tolist(),
        nominal=nominal.as_dict(),
        nominal_combinations=nominal.combinations(),
        validation=None
        if gap is None and gap0 is None
        else Validation(poses=poses, gap_rms_m=gap, a_priori_gap_rms_m=gap0),
        warnings=[str(w) for w in entry.warnings or []],
        source=Source(result_sha256=context.result_sha256, result_file=context.result_file),
    )


def load_calibration(data: Any, source: str | None = None) -> CalibrationDocument:
    """Validate a parsed ``i4cal.calibration/1`` document (JSON or YAML already read into a mapping).

    Parameters
    ----------
    data : Any
        The parsed document.
    source : str, optional
        The file it was read from, for the error messages.

    Returns
    -------
    CalibrationDocument
        The validated document.

    Raises
    ------
    InputError
        Not that format, or a field missing or wrong (named, with ``source`` as the file).
    """
    if not isinstance(data, dict):
        raise InputError(f"not an {CALIBRATION_FORMAT} document (a {type(data).__name__})", file=source)
    if data.get("format") != CALIBRATION_FORMAT:
        raise InputError(
            f"not an {CALIBRATION_FORMAT} document (format {data.get('format')!r})", file=source, field="format"
        )
    try:
        doc = CalibrationDocument.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(err["msg"], file=source, field=".".join(str(p) for p in err["loc"])) from None
    missing = [n for n in PARAMETER_NAMES if n not in doc.seven]
    if missing:
        raise InputError(f"missing parameter(s) {', '.join(missing)}", file=source, field="seven")
    try:
        doc.to_parameters()
    except ValueError as exc:
        raise InputError(str(exc), file=source, field="seven") from None
    return doc


# -- the parity check ----------------------------------------------------------------------------------------------
def plan_joints(plan: Plan, nominal: I4Parameters) -> np.ndarray:
    """The joint vectors a plan commands, shape (N, 4), m: every step's ``q``, a guided line's samples through the
    nominal IKM (as the acquisition commands them).

    Parameters
    ----------
    plan : Plan
        The acquisition plan.
    nominal : I4Parameters
        The a priori geometry the acquisition's IKM uses.

    Returns
    -------
    ndarray, shape (N, 4)
        The joint vectors, m.
    """
    rows = []
    for step in plan.steps:
        if step.line is not None:
            rows.append(ikm(nominal, line_poses(step.line)).reshape(-1, 4))
        elif step.q is not None:
            rows.append(np.asarray(step.q, dtype=np.float64).reshape(1, 4))
    if not rows:
        raise InputError("the plan commands no joint vector", field="steps")
    return np.concatenate(rows)


def _rows(fn: Any, params: I4Parameters, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``fn(params, X)`` row by row where the whole batch fails: the values (NaN where unreachable) and a mask."""
    try:
        return fn(params, X), np.ones(len(X), dtype=bool)
    except UnreachableError:
        out = np.full((len(X), 4), np.nan)
        ok = np.zeros(len(X), dtype=bool)
        for i, x in enumerate(X):
            try:
                out[i] = fn(params, x)
                ok[i] = True
            except UnreachableError:
                pass
        return out, ok


def _base_frame(params: I4Parameters, P: np.ndarray) -> np.ndarray:
    """Poses (X, Y, Z, T) as (E_x, E_y, E_z, T) with E in the base frame (E_y = H + Y), shape (N, 4), m."""
    out = np.array(P, dtype=np.float64, copy=True)
    out[:, 1] += params.H
    return out


def _pose(params: I4Parameters, E: np.ndarray) -> np.ndarray:
    """The inverse of :func:`_base_frame` for ``params``."""
    out = np.array(E, dtype=np.float64, copy=True)
    out[:, 1] -= params.H
    return out


@dataclass(frozen=True)
class ParityReport:
    """How far the model rebuilt from a document's seven parameters is from the result's own model.

    Attributes
    ----------
    n_poses : int
        Joint vectors compared (the plan's).
    dkm_max_m : float
        Largest |difference| of the DKM's end-effector point in the base frame ``E = (X, H + Y, Z)`` and of ``T``
        over them, m (T is a length; Y counts from the mid-line y = H, so H is compared through E).
    ikm_max_m : float
        Largest |difference| of the IKM's (q1..q4) at the result model's end-effector points and T, m.
    combinations_max_m : float
        Largest |difference| between the document's seven parameters' combinations and the result's, m.
    T_per_rad_diff : float
        Document minus result, m/rad.
    unreachable : int
        Joint vectors one model reaches and the other does not (each a failure).
    unreachable_both : int
        Joint vectors neither model reaches (left out).
    tolerance_m : float
    """

    n_poses: int
    dkm_max_m: float
    ikm_max_m: float
    combinations_max_m: float
    T_per_rad_diff: float
    unreachable: int
    unreachable_both: int
    tolerance_m: float

    @property
    def passed(self) -> bool:
        return (
            self.unreachable == 0
            and self.n_poses > self.unreachable_both
            and max(self.dkm_max_m, self.ikm_max_m, self.combinations_max_m) <= self.tolerance_m
            and self.T_per_rad_diff == 0.0
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_poses": self.n_poses,
            "dkm_max_m": self.dkm_max_m,
            "ikm_max_m": self.ikm_max_m,
            "combinations_max_m": self.combinations_max_m,
            "T_per_rad_diff": self.T_per_rad_diff,
            "unreachable": self.unreachable,
            "unreachable_both": self.unreachable_both,
            "tolerance_m": self.tolerance_m,
            "passed": self.passed,
        }


def check_parity(
    doc: CalibrationDocument,
    reference: I4Parameters,
    reference_combinations: dict[str, float],
    q: np.ndarray,
    tolerance_m: float = REPRODUCE_TOL_M,
) -> ParityReport:
    """Compare the model of ``doc`` with ``reference`` (the result's own model) over joint vectors ``q``.

    The DKM of both models at ``q``, as base-frame points ``E = (X, H + Y, Z)`` and ``T``; the IKM of both at the
    reference's points (each model's ``Y = E_y - H``). Every one of the seven parameters moves one of them: H, S and
    q03, which the combinations do not see, move E and T by constant offsets.

    Parameters
    ----------
    doc : CalibrationDocument
    reference : I4Parameters
        The seven parameters the result's method stands for (:func:`method_parameters`).
    reference_combinations : dict
        The four combinations the result's method reports, m.
    q : ndarray, shape (N, 4)
        Joint vectors, m (:func:`plan_joints`).
    tolerance_m : float
        The largest difference that passes, m.

    Returns
    -------
    ParityReport
        The largest differences of the DKM, the IKM and the combinations between the two models over ``q`` (m), and
        the joint vectors one model reaches and the other does not, against ``tolerance_m``.
    """
    model = doc.to_parameters()
    Q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    P_ref, ok_ref = _rows(dkm, reference, Q)
    P_doc, ok_doc = _rows(dkm, model, Q)
    both = ok_ref & ok_doc
    E_ref, E_doc = _base_frame(reference, P_ref[both]), _base_frame(model, P_doc[both])
    dkm_max = float(np.max(np.abs(E_doc - E_ref))) if both.any() else 0.0
    none = (np.zeros((0, 4)), np.zeros(0, dtype=bool))
    Q_ref, ok_i_ref = _rows(ikm, reference, _pose(reference, E_ref)) if len(E_ref) else none
    Q_doc, ok_i_doc = _rows(ikm, model, _pose(model, E_ref)) if len(E_ref) else none
    ib = ok_i_ref & ok_i_doc
    ikm_max = float(np.max(np.abs(Q_doc[ib] - Q_ref[ib]))) if ib.any() else 0.0
    got = model.combinations()
    comb_max = max(abs(got[k] - float(reference_combinations[k])) for k in COMBINATION_NAMES)
    return ParityReport(
        n_poses=len(Q),
        dkm_max_m=dkm_max,
        ikm_max_m=ikm_max,
        combinations_max_m=float(comb_max),
        T_per_rad_diff=float(model.T_per_rad - reference.T_per_rad),
        unreachable=int(np.sum(ok_ref ^ ok_doc) + np.sum(ok_i_ref ^ ok_i_doc)),
        unreachable_both=int(np.sum(~ok_ref & ~ok_doc)),
        tolerance_m=float(tolerance_m),
    )


__all__ = [
    "CALIBRATION_FORMAT",
    "COMPLETION_RULES",
    "REPRODUCE_TOL_M",
    "CalibrationDocument",
    "ExportContext",
    "ParityReport",
    "build_calibration",
    "check_parity",
    "load_calibration",
    "method_parameters",
    "plan_joints",
    "recommended_method",
]
