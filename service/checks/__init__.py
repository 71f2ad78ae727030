"""Checks: does the calibration in force still hold? A short plan acquired on the bench, fitted, and tested against
the calibration (``calib.check.drift``); the proposed update where it drifted (docs/check.md)."""

from .plan import check_plan_for_bench
from .run import CheckOutcome, CheckSettings, evaluate_check, run_check

__all__ = ["CheckOutcome", "CheckSettings", "check_plan_for_bench", "evaluate_check", "run_check"]
