"""A rod's prediction (nominal model at the encoder values, coarse camera placement), the measurement's settings and
its result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.model.kinematics import dkm, joint_points
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import Rigid

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
@dataclass
class RodPrediction:
    """A rod's predicted axis segment in the camera frame (metres): from ``top`` (actuator) to ``bottom``."""

    leg: int
    rod: int
    top: Array
    bottom: Array

    @property
    def u(self) -> Array:
        d = self.bottom - self.top
        return d / np.linalg.norm(d)


def predict_rods(
    nominal: I4Parameters, q: ArrayLike, camera_from_base: Rigid, rod_spacing_m: float
) -> list[RodPrediction]:
    """Predicted rod segments (8, in ``ROD_KEYS`` order) from the nominal model and encoder values.

    Parameters
    ----------
    nominal : I4Parameters
        The model predicted with (metres, radians).
    q : array_like, shape (4,)
        Encoder values of the frame (metres).
    camera_from_base : Rigid
        The camera's placement (metres, radians).
    rod_spacing_m : float
        Distance between the axes of a leg's two rods (metres).

    Returns
    -------
    list of RodPrediction
        Eight predictions, ends in the camera frame (metres).

    Raises
    ------
    UnreachableError
        The nominal model cannot close at ``q``.
    """
    top, bottom, _ = rod_ends_camera(
        nominal, np.asarray(q, dtype=np.float64).reshape(1, 4), camera_from_base, rod_spacing_m
    )
    return [RodPrediction(leg, rod, top[0, leg, rod], bottom[0, leg, rod]) for leg in range(4) for rod in range(2)]


def rod_ends_camera(
    params: I4Parameters, q: Array, camera_from_base: Rigid, rod_spacing_m: float, pose: Array | None = None
) -> tuple[Array, Array, Array]:
    """Rod ends in the camera frame (metres) and the end-effector poses: every rod of every frame at once.

    Parameters
    ----------
    params : I4Parameters
        The model (metres, radians).
    q : ndarray, shape (N, 4)
        Encoder values (metres), one row per frame.
    camera_from_base : Rigid
        The camera's placement (metres, radians).
    rod_spacing_m : float
        Distance between the axes of a leg's two rods (metres).
    pose : ndarray, shape (N, 4), optional
        The end-effector poses at ``q``, when already known (default: ``dkm(params, q)``).

    Returns
    -------
    top, bottom : ndarray, shape (N, 4, 2, 3)
        Actuator-side and plate-side ends of every rod (rod 0 on the -x_B side).
    pose : ndarray, shape (N, 4)
        ``(X, Y, Z, T)``.

    Raises
    ------
    UnreachableError
        ``params`` cannot close at some ``q``.
    """
    pose = dkm(params, q) if pose is None else pose
    A, B = joint_points(params, q, pose)
    off = np.array([-0.5, 0.5])[:, None] * rod_spacing_m * np.array([1.0, 0.0, 0.0])  # (2, 3)
    top = A[:, :, None, :] + off[None, None]
    bottom = B[:, :, None, :] + off[None, None]
    R, t = camera_from_base.R, camera_from_base.t
    return top @ R.T + t, bottom @ R.T + t, pose


#: the board hides the rods' profiles within this of the pattern's outline (the board's margin plus ~15 mm, so
#: that its edges stay out of the profiles), metres
ROD_BOARD_OCCLUDER_M = 0.028
#: a profile is left out when any point within the rod's half width plus this (px) of its centre is on the board
ROD_OCCLUDER_CLEARANCE_PX = 4.0


@dataclass
class RodSettings:
    """Tuning of the rod extraction (pixels are ideal, undistorted pixels)."""

    band_px: float = 18.0  #: search half-band around each predicted limb line
    step_px: float = 3.0  #: spacing of the profiles along the axis
    sigma_px: float = 1.0  #: derivative-of-Gaussian scale on the profiles
    sample_px: float = 0.5  #: sample spacing along each profile
    min_contrast: float = 6.0  #: minimum |gradient| (grey levels per px) of an edge
    width_tolerance: float = 0.15  #: accepted relative deviation of the limb spacing from the prediction
    ransac_iters: int = 150
    inlier_px: float = 1.0  #: RANSAC inlier threshold
    min_points: int = 20  #: per limb, after outlier rejection
    min_length_px: float = 40.0  #: visible length needed
    max_rms_px: float = 0.8  #: residual RMS above this: rod rejected
    min_plane_angle_rad: float = 2e-3
    border_px: float = 3.0  #: samples closer to the image border are dropped
    near_m: float = 0.05  #: the segment is clipped to z >= near_m
    edge_bias_px: float = 0.05  #: slowly varying edge bias allowed for in ``cov_u`` (end-to-end, px)
    #: its correlation length along a limb (px) in ``cov_u_own``, where it averages over longer spans
    #: (``covariance.edge_bias_factor``); ``cov_u`` keeps the allowance whole (it also covers the bias every rod shares)
    edge_bias_length_px: float = 100.0
    neighbour_px: float = 4.0  #: limb points closer than this to another rod's predicted silhouette: dropped
    #: the rods' brightness against their surroundings: +1 brighter, -1 darker, 0 decided per frame by most rods
    polarity: int = 0


@dataclass
class RodMeasurement:
    """One rod measured in one image (or the reason why not: ``reason`` set, ``u`` None)."""

    leg: int
    rod: int
    u: Array | None = None
    point: Array | None = None
    h: tuple[Array, Array] | None = None
    rms_px: tuple[float, float] = (np.nan, np.nan)
    n_points: tuple[int, int] = (0, 0)
    plane_angle_rad: float = np.nan
    reason: str | None = None
    lines_px: list[Array] = field(default_factory=list)  # per limb (a, b, c) in ideal pixels, a^2+b^2=1
    cov_u: Array | None = None  #: (3, 3) covariance of u (camera frame) from the limb edges' scatter
    #: (3, 3) the same without the edge bias every rod shares: the allowance averaged along the limb
    #: (``RodSettings.edge_bias_length_px``), what a fit that measures the shared bias weighs the rod by
    cov_u_own: Array | None = None
    #: (2, 5, 2) per limb, five points of its fitted line spread over the measured edge points
    #: (quantiles 0, 1/4, 1/2, 3/4, 1 along it), in distorted pixels: the raw measurement, from which
    #: the limb planes can be recomputed for other intrinsics (uncertainty propagation)
    limbs_px: Array | None = None
    #: the two limbs' inlier edge points (N_i, 2) and the middle of the visible part (2,), distorted image pixels:
    #: they do not depend on the camera, so the rod can be re-expressed for other intrinsics
    #: (:func:`calib.vision.rods.reexpress.reexpress_rod`) without measuring the image again; not serialized
    edges_px: tuple[Array, Array] | None = None
    middle_px: Array | None = None
    #: +1 when the rod was measured as brighter than its surroundings, -1 darker, 0 not decided
    polarity: int = 0
    #: edge pairs found across the profiles (bright rod, dark rod), before one polarity is kept
    pairs_by_polarity: tuple[int, int] = (0, 0)

    @property
    def ok(self) -> bool:
        return self.u is not None

    def to_dict(self) -> dict | None:
        if self.u is None:
            return None
        d = {
            "u": self.u.tolist(),
            "rms_px": [float(x) for x in self.rms_px],
            "n_points": [int(x) for x in self.n_points],
            "plane_angle_rad": float(self.plane_angle_rad),
        }
        if self.point is not None:
            d["point"] = self.point.tolist()
        if self.cov_u is not None:
            d["cov_u"] = self.cov_u.tolist()
        if self.cov_u_own is not None:
            d["cov_u_own"] = self.cov_u_own.tolist()
        if self.h is not None:
            d["h"] = [self.h[0].tolist(), self.h[1].tolist()]  # interpretation-plane normals (camera frame)
        if self.limbs_px is not None:
            d["limbs_px"] = self.limbs_px.tolist()
        return d
