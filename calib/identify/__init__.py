"""The three calibration methods: combined (legs + end-effector), end-effector only, legs only; by name through
:mod:`calib.identify.registry`."""

from .combined import calibrate_combined
from .end_effector import calibrate_end_effector
from .legs import calibrate_legs
from .result import MethodResult

__all__ = ["MethodResult", "calibrate_combined", "calibrate_end_effector", "calibrate_legs"]
