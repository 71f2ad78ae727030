"""First-frame rod detection: no prior pose, only the image, the encoder values and the nominal model.

Without a coarse camera placement (``camera_from_base``) no rod can be predicted, so
:func:`calib.vision.rods.measure_rod` has no search band. This module finds the rods from scratch,
associates them to the legs, and gives back what :func:`calib.vision.rods.predict_rods` gives (one
axis segment per rod, camera frame) plus a coarse ``camera_from_base`` (see docs/vision.md):

1. **Segments**: the image is resampled to ideal (undistorted) pixels on a canvas of the original
   area (straight rods stay straight), then ``cv2.createLineSegmentDetector``. Each segment gets its
   polarity (which side is brighter) and contrast from samples on either side.
2. **Lines**: collinear segments of the same polarity are merged (union-find on angle, distance and
   gap, so a limb cut by the board or by another rod is one line), re-measured with sub-pixel edges
   on profiles across them (LSD's lines sit ~2 px inside a shaded rod's limbs) and merged again.
3. **Rods**: pairs of lines that are nearly parallel, overlap, face each other (a bright rod: each
   limb's bright side towards the other; ``polarity``), are as far apart as a rod of the known
   radius between ``depth_range_m``, and whose inside is brighter (darker) than their outside along
   the overlap. Each gives its two limb planes h1, h2 (camera frame, paper eq. 6).
4. **Legs**: pairs of rod candidates that are nearly parallel in the image, of similar width, whose
   separation over width matches ``rod_spacing / (2 rod_radius)`` (foreshortened). The two rods are
   parallel in space, so the leg's 3-D direction is the intersection of their axis planes
   (``h1 - h2`` bisects the limb planes and contains the axis).
5. **Association and placement**: the nominal model at the encoder values gives the legs'
   directions in the base frame. Assignments of leg candidates to legs 1..4 (at least ``min_legs``)
   whose pairwise angles match are enumerated with the directions' signs; the rotation is a weighted
   Kabsch fit, the rod order in each leg follows from the side of x_B, the translation is linear
   (every limb plane satisfies ``h . X = r`` on the axis), then Levenberg-Marquardt on the limb
   lines' end points (ideal px) refines ``camera_from_base``. The best hypothesis (most legs, then
   lowest RMS) wins unless a *rival* that labels the rods differently fits about as well: then the
   frame is ambiguous and its rods are reported missing (only the leg concerned when the rival just
   swaps the two rods of one leg).

The I4 is symmetric under a half-turn about the vertical through the end-effector when ``Y = 0``
(legs 1<->4, 2<->3; the nominal model is centimetres off, so in practice up to ``|Y|`` ~ 0.1 m):
rods alone cannot tell those labellings apart. A ``prior`` (a coarse ``camera_from_base``: the
bench's camera mounting, or the placement other frames agreed on, :func:`resolve_frames`) drops
the hypotheses rotated more than ``prior_tol_rad`` from it.

The priors handed to ``measure_rod`` are the detected rods themselves (their limb planes and the
radius), along the detected leg direction, over the nominal model's extent: the nominal model's
rods are 1-2 cm (10-25 px) off even at the fitted placement, the detected lines are not.
"""

from __future__ import annotations

from .association import associate
from .candidates import find_legs, find_rods
from .frames import consensus_placement, detect_rods, measure_detected, resolve, resolve_frames
from .hypotheses import DetectSettings, Hypothesis, LegCandidate, Line2, RodCandidate, RodDetection
from .segments import detect_segments, merge_lines, merge_segments, refine_lines, undistorted_canvas

__all__ = [
    "DetectSettings",
    "Hypothesis",
    "LegCandidate",
    "Line2",
    "RodCandidate",
    "RodDetection",
    "associate",
    "consensus_placement",
    "detect_rods",
    "detect_segments",
    "find_legs",
    "find_rods",
    "measure_detected",
    "merge_lines",
    "merge_segments",
    "refine_lines",
    "resolve",
    "resolve_frames",
    "undistorted_canvas",
]
