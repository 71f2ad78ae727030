"""The result document (format ``i4cal.result/1``): what :func:`calib.identify.pipeline.calibrate_document` builds, the
service stores, ``GET /api/v1/runs/{id}/result`` serves, and the report, the verdict and the export read.

Names: the four identifiable combinations (``L``, ``H-D``, ``S-q02/2``, ``S-(q04-q03)/2``) of a method are
``combinations`` and ``combinations_std``; ``parameters`` and ``std`` carry the same values under the format's first
names. The seven parameters (``H``, ``q02``, ``q03``, ``q04``, ``S``, ``D``, ``L``), when a method identifies them,
are ``seven`` and ``seven_std``. Metres throughout, except where a key ends in ``_mm`` or ``_deg``.

The JSON of a document is a contract read by tools outside the project: keys are added, never renamed or removed.
Every model here keeps the keys it was given, in their order, and no others (:class:`Record`): a stored document
loaded with :meth:`ResultDocument.from_dict` and written with :meth:`ResultDocument.to_dict` gives the same JSON,
keys the models do not name included. Read the document through the attributes; the keys a model does not name
(method-specific diagnostics) are in ``model_extra``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any, Self

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    SerializerFunctionWrapHandler,
    ValidationError,
    ValidatorFunctionWrapHandler,
    model_serializer,
    model_validator,
)

from calib.errors import InputError
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters

#: The format name of a result document.
RESULT_FORMAT = "i4cal.result/1"

#: Values by name, m (null where a value is not finite: the service writes JSON without NaN).
Combinations = dict[str, float | None]


class Record(BaseModel):
    """A part of the result document: its JSON holds the keys it was given, in their order (keys a subclass does
    not name included, in ``model_extra``), and the fields set since; never a default it was not given."""

    model_config = ConfigDict(extra="allow")

    _keys: tuple[str, ...] = PrivateAttr(default=())

    @model_validator(mode="wrap")
    @classmethod
    def _remember_keys(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        model = handler(data)
        if isinstance(data, Mapping) and isinstance(model, Record) and not model._keys:
            model._keys = tuple(str(k) for k in data)
        return model

    @model_serializer(mode="wrap")
    def _in_given_order(self, handler: SerializerFunctionWrapHandler):
        # no return annotation: with one, pydantic would publish the annotation as the schema, not the fields
        out = handler(self)
        if not isinstance(out, dict):  # pragma: no cover - a model always serialises to a mapping
            return out
        keys = [k for k in self._keys if k in out] + [k for k in out if k not in self._keys]
        return {k: out[k] for k in keys}


# -- validation ----------------------------------------------------------------------------------------------------
class Gaps(Record):
    """Displacement gaps between consecutive poses (:func:`calib.identify.validation.displacement_gaps`), mm."""

    error: str | None = Field(None, description="why the gaps could not be computed")
    mean_mm: float | None = None
    rms_mm: float | None = None
    max_abs_mm: float | None = None
    n_pairs: int | None = Field(None, description="pose pairs")
    gaps_mm: list[float | None] | None = Field(None, description="one gap per consecutive pose pair, mm")

    def rms_finite_mm(self) -> float | None:
        """The RMS gap when it is a finite number, mm."""
        return self.rms_mm if self.rms_mm is not None and math.isfinite(self.rms_mm) else None

    def count(self) -> int:
        """Pose pairs behind the RMS."""
        return int(self.n_pairs or len(self.gaps_mm or ()))


class Straightness(Record):
    """Straightness of the guided line (:func:`calib.identify.validation.straightness`)."""

    error: str | None = None
    rms_mm: float | None = Field(None, description="RMS distance of the model positions to their line, mm")
    n: int | None = Field(None, description="points")
    length_mm: float | None = None


class VisionScale(Record):
    """Vision's displacement per encoder metre (:func:`calib.identify.validation.vision_scale`)."""

    scale: float | None = None
    std: float | None = None
    n_poses: int | None = None
    source: str | None = None
    warning: str | None = None


class ValidationEntry(Record):
    """The validation of one parameter set (``validation[name]``: ``a priori``, a method, ``truth``)."""

    error: str | None = None
    vision_scale: VisionScale | None = None
    gaps_poses: Gaps | None = Field(None, description="on the fit poses")
    gaps_validation: Gaps | None = Field(None, description="on the separate validation poses")
    straightness: Straightness | None = None

    def gaps(self, part: str) -> Gaps | None:
        """``gaps_poses`` (``part="poses"``) or ``gaps_validation`` (``part="validation"``).

        Parameters
        ----------
        part : str
            ``"poses"`` or ``"validation"``.

        Returns
        -------
        Gaps or None
            The gaps of that part (m), None when not computed.
        """
        return self.gaps_validation if part == "validation" else self.gaps_poses


# -- one method ----------------------------------------------------------------------------------------------------
class Identifiability(Record):
    """A method's numerical identifiability at the identified geometry
    (:func:`calib.identify.identifiability.analyse`)."""

    error: str | None = None
    rank: int | None = None
    condition_number: float | None = None
    singular_values: list[float] | None = None
    n_poses: int | None = None
    finds_paper_four: bool | None = None
    identifiable_combinations: list[str] | None = None


class BoundNoise(Record):
    """The noise levels a Cramer-Rao bound was computed at."""

    rod_direction_rad: float | None = None
    board_rotation_rad: float | None = None
    board_translation_m: list[float] | None = None


class Bound(Record):
    """The Cramer-Rao bound of a method for the run's poses at the noise levels the run measured."""

    std: Combinations | None = Field(None, description="the bound's standard deviations of the combinations, m")
    note: str | None = None
    noise: BoundNoise | None = None
    covariance: list[list[float]] | None = None
    includes_intrinsics: bool | None = None
    efficiency_std_ratio: Combinations | None = None


class RodErrors(Record):
    """The correlations of the rods' errors the combined fit measured."""

    own_scale: float | None = None
    pair_correlation: float | None = None
    distance_correlation: float | None = None
    distance_length_px: float | None = None


class Diagnostics(Record):
    """A method's fit diagnostics: the figures the report and the export read are named; the others (method
    specific) are in ``model_extra``."""

    weighting: str | None = Field(None, description="'gls' when the rods' measured covariances weigh the fit")
    direction_noise_scale: float | None = Field(
        None, description="combined: the rods' direction noise, rad (or a scale on their covariances with 'gls')"
    )
    rod_errors: RodErrors | None = None
    rod_direction_noise_rad: float | None = None
    line_residual_rms_mm: float | None = None
    step1_chi2_per_dof: float | None = None
    steps34_chi2_per_dof: float | None = None
    board_noise_std: dict[str, Any] | None = Field(None, description="end-effector: board pose noise by name")
    identifiability: dict[str, Any] | None = None

    def a_priori_fallback(self) -> str | None:
        """Which parameters a fit fixed at their a priori values (``all seven``, ``L, S, D``), or None."""
        ident = self.identifiability or {}
        fallback = ident.get("a_priori_fallback") if isinstance(ident, dict) else None
        return None if fallback is None else str(fallback)


class MethodEntry(Record):
    """One method's outcome in ``methods[name]``."""

    converged: bool
    error: str | None = Field(None, description="why the method gave no result (then the values are null)")
    combinations: Combinations | None = Field(
        None, description="the four identifiable combinations, m (absent in documents written before they were added)"
    )
    combinations_std: Combinations | None = Field(None, description="their standard deviations, m")
    parameters: Combinations | None = Field(None, description="the four combinations, m (the format's first name)")
    std: Combinations | None = Field(None, description="their standard deviations, m (the format's first name)")
    seven: Combinations | None = Field(None, description="the seven parameters, when the method identifies them, m")
    seven_std: Combinations | None = None
    parameters_seven_completed: Combinations | None = Field(
        None, description="the seven parameters it stands for: identified, or the combinations completed a priori, m"
    )
    covariance: list[list[float | None]] | None = Field(None, description="4x4 covariance of the combinations, m^2")
    residual_rms: float | None = None
    residual_unit: str | None = None
    n_observations: int | None = None
    n_poses: int | None = None
    iterations: int | None = None
    message: str | None = None
    std_breakdown: dict[str, Any] | None = Field(None, description="the std's contributions by source, m")
    diagnostics: Diagnostics | None = None
    warnings: list[str] | None = None
    time_s: float | None = Field(None, description="wall time of the fit, s")
    identifiability: Identifiability | None = None
    bound: Bound | None = Field(None, description="Cramer-Rao bound (methods that support it)")

    @property
    def values(self) -> Combinations | None:
        """The four combinations, m (``combinations``, else the format's first name ``parameters``)."""
        return self.combinations or self.parameters

    @property
    def values_std(self) -> Combinations | None:
        """Their standard deviations, m."""
        return self.combinations_std or self.std

    @property
    def ok(self) -> bool:
        """Converged with the four combinations."""
        return self.converged and bool(self.values)

    @property
    def seven_or_completed(self) -> Combinations | None:
        """The seven parameters the method stands for (``parameters_seven_completed``, else ``seven``), m."""
        return self.parameters_seven_completed or self.seven

    @property
    def bound_std(self) -> Combinations:
        """The Cramer-Rao bound's standard deviations ({} without a bound), m."""
        return (self.bound.std if self.bound is not None else None) or {}

    @property
    def failure(self) -> str | None:
        """Why the method gave no usable result (None when it did)."""
        if self.converged and self.parameters:
            return None
        return str(self.error or self.message or "did not converge")


# -- the document --------------------------------------------------------------------------------------------------
class BaseFrameSummary(Record):
    """The base frame found from the board's rotation and translation phases (:mod:`calib.identify.baseframe`)."""

    error: str | None = Field(None, description="why no base frame could be fitted")
    camera_from_base_R: list[list[float]] | None = None
    z_std_deg: float | None = None
    x_std_deg: float | None = None
    orthogonality_error_deg: float | None = None
    rotation_residual_rms_deg: float | None = None
    translation_residual_rms_mm: float | None = None
    translation_scale: float | None = None
    translation_scale_std: float | None = None
    n_rotation: int | None = None
    n_translation: int | None = None

    def rotation(self) -> np.ndarray | None:
        """``camera_from_base_R``, (3, 3), or None."""
        return None if self.camera_from_base_R is None else np.asarray(self.camera_from_base_R, float)


class ResultDocument(Record):
    """The whole result document (format ``i4cal.result/1``)."""

    format: str = Field(description="i4cal.result/1")
    nominal: Combinations = Field(default_factory=dict, description="a priori parameters (seven and T_per_rad), m")
    nominal_combinations: Combinations = Field(default_factory=dict, description="a priori combinations, m")
    methods: dict[str, MethodEntry] = Field(default_factory=dict, description="per method (GET /api/v1/methods names)")
    validation: dict[str, ValidationEntry] = Field(
        default_factory=dict,
        description="per parameter set ('a priori', each method, 'truth' on simulated data): displacement gaps and "
        "straightness, mm",
    )
    phases: dict[str, int] = Field(default_factory=dict, description="frames per phase")
    base_frame: BaseFrameSummary | None = None
    truth_errors: dict[str, dict[str, Any]] | None = Field(
        None, description="method - truth per combination, and 'seven' when identified; simulated data only, m"
    )

    # -- reading and writing ----------------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> Self:
        """A parsed result document (a stored one of any age: keys it lacks are None or empty).

        Parameters
        ----------
        data : Any
            The parsed JSON (a mapping), or a :class:`ResultDocument` returned as is.
        source : str, optional
            The file it was read from, for the error messages.

        Returns
        -------
        ResultDocument
            The document.

        Raises
        ------
        InputError
            Not an ``i4cal.result/1`` document, or a field of the wrong type (named, with ``source`` as the file).
        """
        if isinstance(data, cls):
            return data
        if not isinstance(data, Mapping) or data.get("format") != RESULT_FORMAT:
            got = data.get("format") if isinstance(data, Mapping) else type(data).__name__
            raise InputError(f"not an {RESULT_FORMAT} document (format {got!r})", file=source, field="format")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            raise InputError(err["msg"], file=source, field=".".join(str(p) for p in err["loc"])) from None

    @classmethod
    def of(cls, doc: ResultDocument | Mapping[str, Any]) -> ResultDocument:
        """``doc`` as a document to read: a :class:`ResultDocument` as is; a mapping may be a part of one (the keys a
        reader needs, such as ``methods`` and ``validation``): a missing ``format`` is this format's, a method entry
        without ``converged`` did not converge. For reading only (:meth:`from_dict` loads a whole document).

        Parameters
        ----------
        doc : ResultDocument or mapping
            A document, or a mapping of (some of) its keys.

        Returns
        -------
        ResultDocument
            The document to read.

        Raises
        ------
        pydantic.ValidationError
            A value of the wrong type.
        """
        if isinstance(doc, ResultDocument):
            return doc
        data = {"format": RESULT_FORMAT, **doc}
        methods = data.get("methods")
        if isinstance(methods, Mapping):
            data["methods"] = {
                m: e if not isinstance(e, Mapping) or "converged" in e else {**e, "converged": False}
                for m, e in methods.items()
            }
        return cls.model_validate(data)

    def to_dict(self) -> dict[str, Any]:
        """The document as JSON values (what is stored and printed): the keys it was built or loaded with."""
        return to_jsonable(self.model_dump(exclude_unset=True))

    def merge(self, part: ResultDocument, method: str) -> Self:
        """This document with ``method``'s entry, validation and truth errors from ``part`` (a document of the same
        observations in which ``method`` ran), in place; returns ``self``.

        Parameters
        ----------
        part : ResultDocument
            A document of the same observations in which ``method`` ran.
        method : str
            The method whose entry is taken.

        Returns
        -------
        ResultDocument
            ``self``.
        """
        self.methods[method] = part.methods[method]
        if method in part.validation:
            self.validation[method] = part.validation[method]
        if part.truth_errors:
            if self.truth_errors is None:
                self.truth_errors = {}
            self.truth_errors.update(part.truth_errors)
        return self

    # -- what the readers ask ---------------------------------------------------------------------------------------
    def entry(self, method: str) -> MethodEntry | None:
        """The entry of ``method``, or None when it did not run.

        Parameters
        ----------
        method : str
            The method's name.

        Returns
        -------
        MethodEntry or None
            Its entry.
        """
        return self.methods.get(method)

    def converged(self) -> Iterator[tuple[str, MethodEntry]]:
        """The methods with a usable result (converged, with the four combinations), in the document's order."""
        return ((m, e) for m, e in self.methods.items() if e.ok)

    def method_parameters(self, method: str) -> I4Parameters | None:
        """The seven parameters a converged method stands for (identified, or completed with the a priori ones) with
        the a priori ``T_per_rad``; None when the method has no result or its values are incomplete.

        Parameters
        ----------
        method : str
            The method's name.

        Returns
        -------
        I4Parameters or None
            The parameters (m; ``T_per_rad`` m/rad).
        """
        e = self.methods.get(method)
        seven = e.seven_or_completed if e is not None else None
        if e is None or not e.parameters or not seven:
            return None
        try:
            return I4Parameters.from_mapping({**seven, "T_per_rad": self.nominal.get("T_per_rad")})
        except (ValueError, KeyError, TypeError):
            return None

    def truth_error(self, method: str) -> dict[str, Any] | None:
        """Method minus truth per combination (and ``seven`` per parameter when identified), m; simulated only.

        Parameters
        ----------
        method : str
            The method's name.

        Returns
        -------
        dict or None
            The errors, m; None when the run was not simulated or the method did not run.
        """
        return (self.truth_errors or {}).get(method)

    def truth_combinations(self) -> dict[str, float] | None:
        """The true combinations a simulated run recorded (a converged method's value minus its error), m."""
        for m, te in (self.truth_errors or {}).items():
            e = self.methods.get(m)
            if e is not None and e.parameters:
                return {k: _num(e.parameters[k]) - te[k] for k in COMBINATION_NAMES}
        return None

    def vision_scale(self) -> VisionScale | None:
        """The vision scale the validation recorded (every entry holds the same), or None."""
        return next((v.vision_scale for v in self.validation.values() if v.vision_scale), None)


def to_jsonable(x: Any) -> Any:
    """``x`` with numpy arrays and scalars turned into lists and Python numbers, tuples into lists, a model into its
    JSON mapping (the rest unchanged: NaN stays NaN).

    Parameters
    ----------
    x : Any
        A value of a result (numpy arrays and scalars, mappings, sequences, pydantic models).

    Returns
    -------
    Any
        The same value in JSON-ready Python types.
    """
    if isinstance(x, BaseModel):
        return to_jsonable(x.model_dump(exclude_unset=True))
    if isinstance(x, dict):
        return {k: to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _num(v: float | None) -> float:
    return math.nan if v is None else float(v)


__all__ = [
    "PARAMETER_NAMES",
    "RESULT_FORMAT",
    "BaseFrameSummary",
    "Bound",
    "BoundNoise",
    "Combinations",
    "Diagnostics",
    "Gaps",
    "Identifiability",
    "MethodEntry",
    "Record",
    "ResultDocument",
    "RodErrors",
    "Straightness",
    "ValidationEntry",
    "VisionScale",
    "to_jsonable",
]
