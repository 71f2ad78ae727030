"""What the combined fit measures that the legs method carries: the limb-edge bias and the re-estimated intrinsics.

The combined fit (:func:`calib.identify.combined.calibrate_combined`) has the limb-edge bias common to every rod and
the camera's intrinsics as nuisance unknowns and measures both from every rod; the legs method cannot tell them apart
from its joints and rod radius and corrects its rods by these measurements instead. The pipeline
(:func:`calib.identify.pipeline.calibrate`) runs the combined fit first and passes its :class:`CombinedMeasurements`
forward
(:attr:`calib.identify.registry.MethodContext.combined`); a legs fit run alone measures them once, before its stages,
with :func:`measure_with_combined`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from calib.errors import I4calError
from calib.formats.observations import Observations
from calib.identify.edge_bias import MeasuredEdgeBias
from calib.identify.measured_intrinsics import MeasuredIntrinsics
from calib.identify.result import MethodResult


@dataclass(frozen=True)
class CombinedMeasurements:
    """The combined fit's measurements of the limb-edge bias and the intrinsics on a run's rods.

    Attributes
    ----------
    edge_bias : MeasuredEdgeBias or None
        Per limb, outward px, and its covariance (px^2); None: the fit did not measure it (no limb samples, or it
        failed).
    intrinsics : MeasuredIntrinsics or None
        The intrinsics' shift from the extraction's camera (px for fx, fy, cx, cy) and their posterior covariance;
        None: not re-estimated.
    """

    edge_bias: MeasuredEdgeBias | None = None
    intrinsics: MeasuredIntrinsics | None = None

    @classmethod
    def from_result(cls, result: MethodResult | dict[str, Any] | None) -> CombinedMeasurements:
        """From a combined result (or its dict); a failed fit (None) measured nothing.

        Parameters
        ----------
        result : MethodResult or dict or None
            The combined method's result.

        Returns
        -------
        CombinedMeasurements
            The limb-edge bias and intrinsics it measured (each None when not measured).
        """
        if result is None:
            return cls()
        return cls(MeasuredEdgeBias.from_result(result), MeasuredIntrinsics.from_result(result))


def measure_with_combined(obs: Observations) -> CombinedMeasurements:
    """Run the combined fit on ``obs`` for its measurements (nothing measured when it fails on the data).

    Parameters
    ----------
    obs : Observations
        The run's observations (the combined fit needs the rotation, translation and poses phases).

    Returns
    -------
    CombinedMeasurements
    """
    from calib.identify.combined import calibrate_combined

    try:
        return CombinedMeasurements.from_result(calibrate_combined(obs))
    except I4calError:
        return CombinedMeasurements()


__all__ = ["CombinedMeasurements", "measure_with_combined"]
