"""The camera's intrinsics as the combined fit re-estimates them from the rods, for the methods that only carry them.

The extraction refines the camera by the rods once (:func:`calib.vision.refine.refine_camera_by_rods`): one step of the
combined fit linearized at the calibration's camera, with that fit's posterior as ``calibration.covariance_refined``.
Where the calibration was far off (the lens's radial terms, which a camera phase that does not reach the image's
corners leaves to the rods), one step is not the estimate: the refined camera's error along the radial direction
can be well above its reported std, and the legs method's L errs with it. The
combined fit of the same observations, linearized at the refined camera, re-estimates the intrinsics (with the
calibration as prior, not the refinement: ``calib.identify.intrinsics.calibration_offset``); the legs method re-measures
its rods through them and takes their posterior as its intrinsics' uncertainty (``calibrate_legs(intrinsics=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.identify.result import MethodResult

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MeasuredIntrinsics:
    """The intrinsics ``names`` moved by ``shift`` from the extraction's camera (px for fx, fy, cx, cy), and their
    posterior covariance (n, n) after the rods."""

    names: tuple[str, ...]
    shift: Array
    covariance: Array
    source: str = "combined fit"

    def __post_init__(self) -> None:
        n = len(self.names)
        s = np.asarray(self.shift, dtype=np.float64)
        c = np.asarray(self.covariance, dtype=np.float64)
        if s.shape != (n,) or not np.all(np.isfinite(s)):
            raise ValueError(f"intrinsics shift must be {n} finite values (one per name), got shape {s.shape}")
        if c.shape != (n, n) or not np.all(np.isfinite(c)):
            raise ValueError(f"intrinsics covariance must be a finite {n}x{n} matrix, got shape {c.shape}")
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "shift", s)
        object.__setattr__(self, "covariance", 0.5 * (c + c.T))

    @classmethod
    def from_result(cls, result: MethodResult | dict[str, Any]) -> MeasuredIntrinsics | None:
        """From a combined result (or its dict): its ``intrinsics_refinement`` and ``intrinsics_posterior_covariance``
        (in the calibration's parameter order); None when it did not estimate the intrinsics.

        Parameters
        ----------
        result : MethodResult or dict
            The combined method's result.

        Returns
        -------
        MeasuredIntrinsics or None
            The intrinsics' shift (px for fx, fy, cx, cy; dimensionless after) and its covariance.
        """
        diag = (result.get("diagnostics") if isinstance(result, dict) else result.diagnostics) or {}
        shift, cov = diag.get("intrinsics_refinement"), diag.get("intrinsics_posterior_covariance")
        if not shift or cov is None:
            return None
        names = tuple(shift)
        return cls(names, np.array([shift[k] for k in names]), np.asarray(cov))

    def along(self, names: tuple[str, ...] | list[str]) -> tuple[Array, Array] | None:
        """The shift and covariance in the order ``names``; None when they are not this measurement's.

        Parameters
        ----------
        names : tuple of str or list of str
            Intrinsics' names in the wanted order.

        Returns
        -------
        tuple of (ndarray of shape (n,), ndarray of shape (n, n)) or None
            The shift and its covariance, reordered.
        """
        if tuple(names) != self.names:
            if sorted(names) != sorted(self.names):
                return None
            idx = [self.names.index(k) for k in names]
            return self.shift[idx], self.covariance[np.ix_(idx, idx)]
        return self.shift, self.covariance

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "shift": dict(zip(self.names, self.shift.tolist(), strict=True)),
            "covariance": self.covariance.tolist(),
        }
