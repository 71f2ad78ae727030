"""Legs observation only (the paper's reference [9], section IV.A.2), in four steps.

1. ``lock-i`` phases: with actuator i locked, each rod of leg i turns about its fixed upper spherical
   joint, so its axis passes through that joint in every frame: the joint is the point that best
   satisfies every frame's axis constraint; the two joints' midpoint is A_i at the locked encoder value.
   x_B is the direction A1 -> A2 (and A3 -> A4); ``A_i(q_i = 0) = A_i - q_i x_B``.
2. (q02, q03, q04, H) from the scalar products of ``V = (OA2, OA3, OA4)|q=0`` (eq. 9, 10), O = A1(q1 = 0).
3. L from the invariance of |B1 B2| and |B3 B4| over the fit poses (eq. 11), with
   ``B_i = A_i(q_i) + L u_i``.
4. S from |B1 B2| = |B3 B4| = 2S; D from the distance 2D between B1 and B3 (and B2, B4) along y_B.

All seven parameters are identified.

Weighting. When the rods carry what the image extraction measures (extra fields ``h``, the two
interpretation-plane normals, and ``cov_u``, the direction's covariance; observations v1), the
method uses the measurement's real noise, which is far from isotropic: a rod's image position is
precise, its depth (from its apparent width) tens of times less so.

* Step 1 solves the two plane equations ``h_q . X = r`` of every frame (r the rod radius, read as
  ``h . point``) for the joint X by weighted least squares, each equation weighed by the variance of
  its limb line (angle and offset, from the limb's edge scatter ``rms_px`` over ``n_points``, the
  extraction's edge-bias allowance, scaled per rod so that it reproduces the rod's ``cov_u``),
  propagated to the distance of X from the plane. Frames whose two equations are beyond the
  chi-square(2) 99.9% quantile of a robust scale are dropped. Without ``h``: the least-squares
  intersection of the axis lines (direction and point), all lines weighing the same.
* Steps 3 and 4 are solved together (poses judged for the gating below by a robust fit from the a
  priori values, a Cauchy loss on each pose's whitened equations, then the least-squares fit of the
  poses kept): per fit pose, ``|B1 B2| - 2S``, ``|B3 B4| - 2S``,
  ``(B3 - B1) . y_B - 2D`` and ``(B4 - B2) . y_B - 2D`` vanish (eq. 11 and step 4 with the constant
  made explicit); (L, S, D) minimise these residuals whitened by their covariance from the leg
  directions' covariance (generalised least squares). A leg's direction is the covariance-weighted
  mean of its two rods (``cov_u``; isotropic without it); a pair of rods that disagree beyond the
  chi-square(2) 99.9% quantile, or a pose whose whitened residuals are beyond their chi-square
  99.9% quantile, is dropped.

One wrong joint (the rod-pair check, :func:`.uncertainty._pair_consistency`, flags exactly one leg): repaired from
its partner and the other legs' rod spacing when the fit poses single it out (:mod:`.repair`).

Standard deviations: the joints' covariance (from the weighted fit, scaled by its residual
chi-square per degree of freedom) propagated linearly through steps 2-4 (numerical derivatives),
plus the GLS covariance of (L, S, D), scaled by its residual chi-square per degree of freedom.
The two parts come from different frames (``lock-i`` and fit phases) and are independent.
"""

from __future__ import annotations

from .constants import PRIOR_STD_M
from .joints import (
    PlaneObservation,
    Step1Planes,
    intersect_lines,
    joint_from_planes,
    limb_line_noise,
    planes_direction_covariance,
    step1_planes,
)
from .method import LegsSettings, calibrate_legs
from .steps import (
    LegsModel,
    fit_step2,
    leg_directions,
    pair_means,
    pair_own_covariances,
    pose_set_model,
    steps34_covariance,
    steps34_sandwich,
)
from .uncertainty import (
    IntrinsicsEffect,
    combinations_null_space,
    joint_depth_systematic,
    null_space_to_prior,
    with_prior,
)

__all__ = [
    "PRIOR_STD_M",
    "IntrinsicsEffect",
    "LegsModel",
    "LegsSettings",
    "PlaneObservation",
    "Step1Planes",
    "calibrate_legs",
    "combinations_null_space",
    "fit_step2",
    "intersect_lines",
    "joint_depth_systematic",
    "joint_from_planes",
    "leg_directions",
    "limb_line_noise",
    "null_space_to_prior",
    "pair_means",
    "pair_own_covariances",
    "planes_direction_covariance",
    "pose_set_model",
    "step1_planes",
    "steps34_covariance",
    "steps34_sandwich",
    "with_prior",
]
