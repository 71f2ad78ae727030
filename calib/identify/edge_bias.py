"""The limb-edge bias the combined fit measures, for the methods that only carry it.

An edge detector's bias on a shaded rod is the same on every rod's limb (per side), so it does not average out over
rods; it tilts each rod's apparent axis in depth. The combined method has it as two nuisance unknowns and measures it
from every rod (``diagnostics.limb_edge_bias``); the legs method cannot tell it apart from its joints and rod radius,
and corrects its rods by this measurement instead (:func:`calib.identify.legs.calibrate_legs`, ``edge_bias``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.identify.result import MethodResult

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MeasuredEdgeBias:
    """Per limb (the extraction's limb 0 and 1), the bias (outward, px) and its covariance (2, 2), px^2."""

    estimate_px: Array
    covariance_px2: Array
    source: str = "combined fit"

    def __post_init__(self) -> None:
        e = np.asarray(self.estimate_px, dtype=np.float64)
        c = np.asarray(self.covariance_px2, dtype=np.float64)
        if e.shape != (2,) or not np.all(np.isfinite(e)):
            raise ValueError(f"edge bias estimate must be 2 finite values (px), got shape {e.shape}")
        if c.shape != (2, 2) or not np.all(np.isfinite(c)):
            raise ValueError(f"edge bias covariance must be a finite 2x2 matrix (px^2), got shape {c.shape}")
        object.__setattr__(self, "estimate_px", e)
        object.__setattr__(self, "covariance_px2", 0.5 * (c + c.T))

    @classmethod
    def from_result(cls, result: MethodResult | dict[str, Any]) -> MeasuredEdgeBias | None:
        """From a combined result (or its dict); None when it did not measure the bias.

        Parameters
        ----------
        result : MethodResult or dict
            The combined method's result.

        Returns
        -------
        MeasuredEdgeBias or None
            The bias per limb (px) and its covariance (px^2).
        """
        diag = result.get("diagnostics") if isinstance(result, dict) else result.diagnostics
        e = (diag or {}).get("limb_edge_bias")
        if not e or e.get("covariance_px2") is None:
            return None
        return cls(np.asarray(e["estimate_px"]), np.asarray(e["covariance_px2"]))

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "estimate_px": self.estimate_px.tolist(),
            "covariance_px2": self.covariance_px2.tolist(),
        }
