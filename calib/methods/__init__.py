"""The three calibration methods: combined (legs + end-effector), end-effector only, legs only."""

from .combined import calibrate_combined
from .end_effector import calibrate_end_effector
from .legs import calibrate_legs
from .result import MethodResult

METHODS = {
    "combined": calibrate_combined,
    "end-effector": calibrate_end_effector,
    "legs": calibrate_legs,
}

__all__ = ["METHODS", "MethodResult", "calibrate_combined", "calibrate_end_effector", "calibrate_legs"]
