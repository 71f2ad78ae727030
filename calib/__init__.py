"""i4cal's numerical core: the I4 model, observations, and the calibration methods.

Pure computation over numpy arrays: this package imports neither ``drivers`` nor ``service``.
"""

from .errors import ConvergenceError, I4calError, IdentifiabilityError, InputError, UnreachableError
from .model.kinematics import dkm, ikm, jacobian, jacobian_ratios, joint_points, leg_directions
from .model.parameters import COMBINATION_NAMES, NOMINAL, PARAMETER_NAMES, I4Parameters, identifiable_parameters

__all__ = [
    "COMBINATION_NAMES",
    "NOMINAL",
    "PARAMETER_NAMES",
    "ConvergenceError",
    "I4Parameters",
    "I4calError",
    "IdentifiabilityError",
    "InputError",
    "UnreachableError",
    "dkm",
    "identifiable_parameters",
    "ikm",
    "jacobian",
    "jacobian_ratios",
    "joint_points",
    "leg_directions",
]
