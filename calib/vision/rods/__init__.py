"""Rod (leg) observation: predicted image, limb lines with sub-pixel edges, axis from interpretation planes.

Geometry (the paper's eqs. 6-7). A rod is a cylinder of radius r, axis through P with unit
direction u (camera frame). Its two silhouette (limb) lines are the images of the two planes
through the camera centre tangent to the cylinder; their unit normals h1, h2 ("interpretation
planes") satisfy ``h_j . u = 0`` and ``h_j . X = r`` for every axis point X (signs chosen so that
the axis is on the positive side). Hence ``u = normalize(h1 x h2)`` and the axis point closest to
the camera centre solves ``[h1; h2; u] X = [r, r, 0]``.

Extraction, per rod and per frame (see docs/vision.md):

1. Prediction: the nominal model at the encoder values and a coarse ``camera_from_base`` give the
   rod's axis segment in the camera frame, hence its two limb lines in ideal (undistorted) pixels.
2. Profiles: along the predicted axis, every ``step_px``, a profile perpendicular to it is sampled
   in ideal-pixel coordinates (each sample mapped to the distorted image with the camera model and
   read by bilinear interpolation); samples hidden by the board or outside the image are dropped.
3. Edges: the derivative-of-Gaussian of each profile, its local maxima of |gradient|, parabolic
   interpolation to sub-pixel; per profile the pair of edges of opposite polarity whose spacing
   matches the predicted width and whose centre is nearest the prediction (inside the band).
4. Lines: per limb, RANSAC (2-point) then iteratively reweighted total least squares with a
   3-sigma rejection; quality figures: residual RMS (px), number of edge points, and the angle
   between the two interpretation planes; the two rods of a leg are compared (parallelism).
"""

from __future__ import annotations

from .covariance import _direction_covariance  # noqa: F401  (calib.design predicts with the extraction's own covariance)
from .cylinder import ROD_KEYS, axis_from_planes, limb_planes, rod_name
from .linefit import robust_line
from .measure import image_ideal_bbox, leg_parallelism, measure_rod, measure_rods
from .types import RodMeasurement, RodPrediction, RodSettings, predict_rods

__all__ = [
    "ROD_KEYS",
    "RodMeasurement",
    "RodPrediction",
    "RodSettings",
    "axis_from_planes",
    "image_ideal_bbox",
    "leg_parallelism",
    "limb_planes",
    "measure_rod",
    "measure_rods",
    "predict_rods",
    "robust_line",
    "rod_name",
]
