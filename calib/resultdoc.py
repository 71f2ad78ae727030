"""The result document of :func:`calib.pipeline.calibrate` (``i4cal calibrate --json``,
``GET /api/v1/runs/{id}/result``) as pydantic models: the keys every consumer may rely on, named and described;
further keys are allowed (the document only grows: keys are added, never renamed or removed).

Names: the four identifiable combinations (``L``, ``H-D``, ``S-q02/2``, ``S-(q04-q03)/2``) of a method are
``combinations`` and ``combinations_std``; ``parameters`` and ``std`` carry the same values under the format's first
names. The seven parameters (``H``, ``q02``, ``q03``, ``q04``, ``S``, ``D``, ``L``), when a method identifies them,
are ``seven`` and ``seven_std``. Metres throughout.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

#: Values by name, m (null where a value is not finite: the service writes JSON without NaN).
Combinations = dict[str, float | None]


class MethodEntry(BaseModel):
    """One method's outcome in ``methods[name]``."""

    model_config = ConfigDict(extra="allow")

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
    time_s: float | None = Field(None, description="wall time of the fit, s")
    identifiability: dict[str, Any] | None = None
    bound: dict[str, Any] | None = Field(None, description="Cramer-Rao bound (methods that support it)")


class ResultDocument(BaseModel):
    """The whole result document (format ``i4cal.result/1``)."""

    model_config = ConfigDict(extra="allow")

    format: str = Field(description="i4cal.result/1")
    nominal: Combinations = Field(description="a priori parameters (seven and T_per_rad), m")
    nominal_combinations: Combinations = Field(description="a priori combinations, m")
    methods: dict[str, MethodEntry] = Field(description="per method (GET /api/v1/methods names)")
    validation: dict[str, Any] = Field(
        description="per parameter set ('a priori', each method, 'truth' on simulated data): displacement gaps and "
        "straightness, mm"
    )
    phases: dict[str, int] = Field(description="frames per phase")
    base_frame: dict[str, Any] | None = None
    truth_errors: dict[str, Any] | None = Field(None, description="method - truth, simulated data only, m")


__all__ = ["MethodEntry", "ResultDocument"]
