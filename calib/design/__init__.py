"""Experiment design before motion: predicted accuracy of every method for a plan, optimal pose sets, motion time.

* :mod:`.scene`: the camera, its mounting, the board and rods, and what is in view;
* :mod:`.predict`: the predicted covariance of each method's estimate (combined, end-effector, legs), for
  measurements of known noise (:class:`DesignNoise`) or, through :mod:`.predict_images` and :mod:`.imaging`, on
  images (:class:`ImageNoise`: what the extraction measures and the methods' image-level uncertainty);
* :mod:`.motion`: trapezoidal motion time and a tour of the poses;
* :mod:`.optimize`: greedy + exchange selection of the fit poses and the sweeps' extents; :func:`design_plan`;
* :mod:`.check`: a plan the user already has: its prediction, motion time and the steps not in view
  (:func:`check_plan`);
* :mod:`.tradeoff`: one design per fit-pose count, accuracy against motion time (:func:`design_tradeoff`).

See docs/design.md.
"""

from .check import PlanCheck, check_plan, targets_from_plan
from .imaging import calibration_covariance, synthetic_rods
from .motion import MotionSpec, move_time, order_tour, plan_motion_time
from .optimize import DesignRequest, DesignResult, design_plan, design_score, log_det_information, select_poses
from .predict import (
    METHODS,
    DesignNoise,
    Prediction,
    phase_q,
    predict_combined,
    predict_end_effector,
    predict_legs,
    predict_plan,
)
from .predict_images import ImageNoise
from .scene import Scene, VisibilityLimits, visibility
from .tradeoff import (
    TradeoffRow,
    design_tradeoff,
    parse_counts,
    recommendation_reason,
    recommended_count,
    recommended_design,
    tradeoff_trend,
)

__all__ = [
    "METHODS",
    "DesignNoise",
    "DesignRequest",
    "DesignResult",
    "ImageNoise",
    "MotionSpec",
    "PlanCheck",
    "Prediction",
    "Scene",
    "TradeoffRow",
    "VisibilityLimits",
    "calibration_covariance",
    "check_plan",
    "design_plan",
    "design_score",
    "design_tradeoff",
    "log_det_information",
    "move_time",
    "order_tour",
    "parse_counts",
    "phase_q",
    "plan_motion_time",
    "predict_combined",
    "predict_end_effector",
    "predict_legs",
    "predict_plan",
    "recommendation_reason",
    "recommended_count",
    "recommended_design",
    "select_poses",
    "synthetic_rods",
    "targets_from_plan",
    "tradeoff_trend",
    "visibility",
]
