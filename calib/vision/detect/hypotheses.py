"""Rod detection's settings and data types: lines, rod and leg candidates, placement hypotheses, the detection."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from calib.numerics.transforms import Rigid
from calib.vision.rods import RodPrediction

Array = NDArray[np.float64]


@dataclass
class DetectSettings:
    """Tuning of :func:`detect_rods` (pixels are ideal, undistorted pixels of the camera model)."""

    min_segment_px: float = 15.0  #: LSD segments shorter than this are dropped
    min_contrast: float = 12.0  #: grey levels between the two sides of a segment
    merge_angle_rad: float = 0.025  #: collinear merge: angle between segments
    merge_dist_px: float = 2.0  #: collinear merge: end point distance to the other line
    merge_gap_px: float = 450.0  #: collinear merge: largest gap along the line
    refine_step_px: float = 6.0  #: edge refinement: profile spacing along a line
    refine_band_px: float = 4.0  #: edge refinement: half-length of each profile
    limb_angle_rad: float = 0.08  #: angle between the two limbs of a rod (perspective)
    depth_range_m: tuple[float, float] = (0.15, 3.0)  #: rods nearer / farther are not searched
    min_rod_px: float = 60.0  #: overlap of the two limbs of a rod candidate
    polarity: Literal["bright", "dark", "auto"] = "auto"  #: rods brighter/darker than their background
    leg_angle_rad: float = 0.1  #: angle between the two rods of a leg in the image
    leg_width_ratio: float = 1.6  #: largest width ratio of the two rods of a leg
    spacing_ratio_range: tuple[float, float] = (0.15, 1.3)  #: image separation / nominal (spacing / width)
    min_legs: int = 3  #: legs needed to solve the placement
    centre_plane_sigma_rad: float = 1.5e-3  #: error of a rod's axis plane (sets a leg direction's error)
    model_direction_rad: float = 0.03  #: nominal-model error of a leg direction
    pair_angle_tol_rad: float = 0.1  #: pairwise leg-angle mismatch (plus 3 sigma of both directions)
    kabsch_tol: float = 3.0  #: weighted RMS direction misfit (sigmas) of an assignment's rotation
    max_hypotheses: int = 6  #: per leg count, refined by Levenberg-Marquardt (best first)
    max_rms_px: float = 12.0  #: placement fit RMS above this: hypothesis rejected
    ambiguity_ratio: float = 1.5  #: a rival within ratio x RMS + ambiguity_px is a tie
    ambiguity_px: float = 1.0
    prior_tol_rad: float = 0.5  #: hypotheses rotated farther from the prior are dropped
    depth_tolerance: float = 0.12  #: a prior's depth / model's off the frame's median by more: moved


@dataclass
class Line2:
    """A merged straight edge in ideal pixels: ``n . x + c = 0``, ``n`` towards the brighter side."""

    n: Array
    c: float
    t: Array  # unit direction, n rotated by -90 deg
    s0: float  # extent along t (s = t . x)
    s1: float
    contrast: float  # grey levels across it

    def point(self, s: float) -> Array:
        """The point of the line at abscissa ``s`` along ``t``.

        Parameters
        ----------
        s : float
            Position along the line's direction ``t`` (ideal px, ``s = t . x``).

        Returns
        -------
        ndarray, shape (2,)
            The point (ideal px).
        """
        return -self.c * self.n + s * self.t


@dataclass
class RodCandidate:
    """Two limb lines facing each other: a rod seen in the image."""

    limbs: tuple[Line2, Line2]
    s0: float  # overlap extent along ``t``
    s1: float
    t: Array
    width_px: tuple[float, float]  # at s0 and s1
    centre: tuple[Array, Array]  # centre-line points at s0 and s1 (ideal px)
    bright: bool
    h: tuple[Array, Array]  # limb planes (camera), unit normals, the axis on their positive side
    m: Array  # the axis plane: through the camera centre and the axis (bisects h)

    @property
    def length(self) -> float:
        return self.s1 - self.s0


@dataclass
class LegCandidate:
    """Two rod candidates side by side at the rod spacing: a leg seen in the image."""

    rods: tuple[int, int]  # indices into the rod candidates
    d: Array  # 3-D direction (camera), sign arbitrary
    sigma: float  # its expected error, rad (centre-plane error / angle between the planes)


@dataclass
class Hypothesis:
    """An association of leg candidates to legs with its fitted placement."""

    legs: dict[int, tuple[int, int]]  # leg (0-based) -> (rod candidate of rod0, of rod1)
    camera_from_base: Rigid
    rms_px: float
    kabsch_misfit: float

    def labels(self) -> dict[int, tuple[int, int]]:
        """Rod candidate -> (leg, rod)."""
        return {c: (leg, r) for leg, pair in self.legs.items() for r, c in enumerate(pair)}


@dataclass
class RodDetection:
    """What :func:`detect_rods` found in one frame.

    Attributes
    ----------
    predictions : list of RodPrediction or None, length 8 (``ROD_KEYS`` order)
        Priors for :func:`calib.vision.rods.measure_rod`; None where the rod was not associated.
    reasons : dict
        ``rod_name -> reason`` for every None prediction.
    camera_from_base : Rigid or None
        The coarse placement fitted to this frame's rods (None when not solved).
    rms_px : float
        Residual RMS of the limb end points to the predicted limb lines (ideal px).
    ambiguous : bool
        Another labelling of the legs fits as well: every rod is None (see ``reason``).
    hypotheses : list of Hypothesis
        Every accepted hypothesis, best first (diagnostics).
    directions : list of ndarray (3,) or None, length 8
        Each associated rod's detected direction in the camera frame, oriented from the actuator to
        the plate: its leg's direction from the two rods' axis planes, weighted with the nominal
        model's at the fitted placement where those planes nearly coincide.
    rods : list of RodCandidate
    leg_candidates : list of LegCandidate
    counts : dict
        Numbers of segments, lines, rod and leg candidates.
    reason : str or None
        Why nothing was associated (no legs, no fit, ambiguous).
    """

    predictions: list[RodPrediction | None]
    reasons: dict[str, str]
    camera_from_base: Rigid | None = None
    rms_px: float = float("nan")
    ambiguous: bool = False
    hypotheses: list[Hypothesis] = field(default_factory=list)
    directions: list[Array | None] = field(default_factory=lambda: [None] * 8)
    rods: list[RodCandidate] = field(default_factory=list)
    leg_candidates: list[LegCandidate] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.camera_from_base is not None
