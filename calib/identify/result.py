"""The result object every calibration method returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters


@dataclass
class MethodResult:
    """Identified parameters with standard deviations and fit diagnostics.

    Attributes
    ----------
    method : str
        ``"combined"``, ``"end-effector"`` or ``"legs"``.
    combinations : dict
        The four identifiable combinations (metres).
    combinations_std : dict
        Their standard deviations (metres), accounting for every noisy input the estimate
        depends on (for ``combined``: leg directions, encoders and the base frame).
    covariance : ndarray, shape (4, 4)
        Covariance of the combinations in :data:`COMBINATION_NAMES` order (m^2).
    parameters : dict or None
        The seven parameters when the method identifies them (``legs``), else None.
    parameters_std : dict or None
    residual_rms : float
        RMS of the (unweighted) fit residuals, in ``residual_unit``.
    """

    method: str
    combinations: dict[str, float]
    combinations_std: dict[str, float]
    covariance: np.ndarray
    residual_rms: float
    residual_unit: str
    n_observations: int
    n_poses: int
    iterations: int
    converged: bool
    message: str = ""
    parameters: dict[str, float] | None = None
    parameters_std: dict[str, float] | None = None
    std_breakdown: dict[str, dict[str, float]] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    residuals: np.ndarray | None = field(default=None, repr=False)
    #: what the user must know about this result (a parameter the data cannot pin, a check that failed)
    warnings: list[str] = field(default_factory=list)

    def vector(self) -> np.ndarray:
        return np.array([self.combinations[k] for k in COMBINATION_NAMES])

    def std_vector(self) -> np.ndarray:
        return np.array([self.combinations_std[k] for k in COMBINATION_NAMES])

    def full_parameters(self, reference: I4Parameters) -> I4Parameters:
        """Seven parameters: the identified ones, or the combinations completed with ``reference``.

        Parameters
        ----------
        reference : I4Parameters
            The a priori geometry (``T_per_rad``, and H, S, q03 when only the combinations were identified).

        Returns
        -------
        I4Parameters
            The seven parameters, m.
        """
        if self.parameters is not None:
            return I4Parameters.from_mapping({**self.parameters, "T_per_rad": reference.T_per_rad})
        return I4Parameters.from_combinations(self.combinations, reference)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            # "parameters"/"std" (the four combinations, the first names of the format) and "combinations"/
            # "combinations_std" (the same values under clear names) are both kept: the format only grows
            "parameters": dict(self.combinations),
            "std": dict(self.combinations_std),
            "combinations": dict(self.combinations),
            "combinations_std": dict(self.combinations_std),
            "converged": self.converged,
            "residual_rms": self.residual_rms,
            "residual_unit": self.residual_unit,
            "n_observations": self.n_observations,
            "n_poses": self.n_poses,
            "iterations": self.iterations,
            "message": self.message,
            "covariance": np.asarray(self.covariance).tolist(),
            "std_breakdown": self.std_breakdown,
            "diagnostics": self.diagnostics,
            "warnings": list(self.warnings),
        }
        if self.parameters is not None:
            out["seven"] = {k: self.parameters[k] for k in PARAMETER_NAMES}
            out["seven_std"] = {k: (self.parameters_std or {}).get(k) for k in PARAMETER_NAMES}
        return out


def combos_dict(v: np.ndarray) -> dict[str, float]:
    """The four combinations by name (:data:`calib.model.parameters.COMBINATION_NAMES`).

    Parameters
    ----------
    v : ndarray, shape (4,)
        The combinations, m.

    Returns
    -------
    dict of str to float
        Name to value, m.
    """
    return {k: float(x) for k, x in zip(COMBINATION_NAMES, v, strict=True)}


def std_dict(cov: np.ndarray) -> dict[str, float]:
    """The four combinations' standard deviations by name, from their covariance.

    Parameters
    ----------
    cov : ndarray, shape (4, 4)
        The combinations' covariance, m^2.

    Returns
    -------
    dict of str to float
        Name to standard deviation, m (negative variances read as zero).
    """
    return {k: float(np.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(COMBINATION_NAMES)}


def check_excitation(J: np.ndarray, names: tuple[str, ...], rel_tol: float = 1e-9) -> None:
    """Raise IdentifiabilityError naming the parameter a Jacobian does not excite.

    Parameters
    ----------
    J : ndarray, shape (M, P)
        A Jacobian, one column per unknown.
    names : tuple of str
        The unknowns' names, (P,).
    rel_tol : float
        Tolerance on the column-scaled Jacobian's smallest singular value relative to its largest (dimensionless).

    Raises
    ------
    IdentifiabilityError
        A column of ``J`` is zero, or the column-scaled ``J`` is (nearly) rank-deficient (the parameter named is the
        one the weakest direction moves most).
    """
    from calib.errors import IdentifiabilityError

    scale = np.linalg.norm(J, axis=0)
    if np.any(scale == 0):
        k = int(np.flatnonzero(scale == 0)[0])
        raise IdentifiabilityError(f"the pose set does not excite parameter {names[k]}", parameter=names[k])
    Js = J / scale
    _, s, Vt = np.linalg.svd(Js, full_matrices=False)
    if s[-1] < rel_tol**0.5 * s[0] * 1e-2 or s[-1] / s[0] < 1e-7:
        k = int(np.argmax(np.abs(Vt[-1])))
        raise IdentifiabilityError(
            f"the pose set does not excite parameter {names[k]} (condition number {s[0] / s[-1]:.3g}); "
            "use poses spread over the workspace",
            parameter=names[k],
        )
