"""What the camera sees: the bench's camera, its mounting, the board and the rods, and visibility tests.

A :class:`Scene` holds the camera model (pinhole + distortion, image size), the camera's placement in the
base frame, the board's placement on the end-effector and the rods' geometry. ``calib`` never imports the
simulated bench: the caller builds the scene (``service`` builds it from the twin's mounting, which the
simulated bench and the image-level twin use).

Visibility of a pose (nominal geometry, joint values ``q``):

* board: every point of its outline (pattern plus white margin) in front of the camera and projected
  inside the image with ``margin_px`` to spare, and the board facing the camera;
* rods: each of the eight rods keeps at least ``min_rod_px`` of visible length, a sample along its axis
  being visible when it is in front of the camera, inside the image (``margin_px``), not behind the
  board (inside the board's image and farther than the board along that ray) and not behind another
  rod (within the sum of the two rods' image radii of a nearer rod's axis).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.formats.camera import CameraModel
from calib.model.kinematics import base_from_ee, dkm
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import Rigid
from calib.vision.rods.types import rod_ends_camera

__all__ = ["Scene", "VisibilityLimits", "board_outline", "rod_segments", "visibility"]


@dataclass(frozen=True)
class VisibilityLimits:
    """What counts as "in view" (pixels)."""

    margin_px: float = 10.0  #: distance kept from the image border
    min_rod_px: float = 80.0  #: visible length each rod keeps (the extraction needs 40 px: twice that)
    samples_per_rod: int = 64


@dataclass(frozen=True)
class Scene:
    """The camera, its mounting and the observed parts, all in metres.

    Attributes
    ----------
    camera : CameraModel
        Intrinsics and image size.
    camera_from_base : Rigid
        Base frame to camera frame.
    ee_from_board : Rigid
        Board frame (OpenCV's: origin at a corner, z into the board) to end-effector frame.
    board_size_m : tuple of float
        Printed pattern's width and height.
    board_margin_m : float
        White margin around the pattern (part of the outline that must be in view).
    board_square_m : float
        The chessboard's square: its inner corners are what the board poses are measured from.
    rod_radius_m, rod_spacing_m : float
        Radius of a rod; the two rods of a leg sit at -/+ half the spacing along x_B from the leg.
    limits : VisibilityLimits
    """

    camera: CameraModel
    camera_from_base: Rigid
    ee_from_board: Rigid
    board_size_m: tuple[float, float] = (0.24, 0.16)
    board_margin_m: float = 0.012
    rod_radius_m: float = 0.008
    rod_spacing_m: float = 0.06
    limits: VisibilityLimits = field(default_factory=VisibilityLimits)
    board_square_m: float = 0.04

    def camera_from_board(self, params: I4Parameters, pose: np.ndarray) -> list[Rigid]:
        """Board poses in the camera frame.

        Parameters
        ----------
        params : I4Parameters
            The geometry (m, rad).
        pose : ndarray, shape (N, 4) or (4,)
            End-effector poses (X, Y, Z in m, the rotation in rad).

        Returns
        -------
        list of Rigid
            ``camera_from_board`` per pose (m).
        """
        Rs, ts = base_from_ee(params, np.atleast_2d(pose))
        return [self.camera_from_base @ Rigid(R, t) @ self.ee_from_board for R, t in zip(Rs, ts, strict=True)]


def board_outline(scene: Scene, per_edge: int = 8) -> np.ndarray:
    """Points along the board's outline (pattern plus margin).

    Parameters
    ----------
    scene : Scene
        The board's size and margin (m).
    per_edge : int
        Points per edge.

    Returns
    -------
    ndarray, shape (4 * per_edge, 3)
        The points in the board frame, m.
    """
    W, H = scene.board_size_m
    m = scene.board_margin_m
    c = np.array([[-m, -m, 0.0], [W + m, -m, 0.0], [W + m, H + m, 0.0], [-m, H + m, 0.0]])
    s = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None]
    return np.concatenate([c[i] + s * (c[(i + 1) % 4] - c[i]) for i in range(4)])


def rod_segments(scene: Scene, params: I4Parameters, q: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rod end points in the camera frame: upper (actuator) and lower (plate).

    Parameters
    ----------
    scene : Scene
        The camera's mounting and the rods' spacing (m).
    params : I4Parameters
        The geometry (m, rad).
    q : ndarray, shape (N, 4)
        Joint values, m.
    pose : ndarray, shape (N, 4)
        The end-effector poses at ``q`` (m, rad).

    Returns
    -------
    top, bottom : ndarray, shape (N, 4, 2, 3)
        Per pose, leg and rod, the upper and lower end points, m.
    """
    top, bot, _ = rod_ends_camera(params, q, scene.camera_from_base, scene.rod_spacing_m, pose)
    return top, bot


def _inside(px: np.ndarray, cam: CameraModel, margin: float) -> np.ndarray:
    return (
        (px[..., 0] >= margin)
        & (px[..., 1] >= margin)
        & (px[..., 0] <= cam.width - 1 - margin)
        & (px[..., 1] <= cam.height - 1 - margin)
    )


def _point_in_polygon(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd test of points (M, 2) against a polygon (V, 2)."""
    x, y = p[:, 0][:, None], p[:, 1][:, None]
    x0, y0 = poly[:, 0][None], poly[:, 1][None]
    x1, y1 = np.roll(poly[:, 0], -1)[None], np.roll(poly[:, 1], -1)[None]
    cross = ((y0 > y) != (y1 > y)) & (x < (x1 - x0) * (y - y0) / np.where(y1 == y0, 1e-300, y1 - y0) + x0)
    return (np.sum(cross, axis=1) % 2) == 1


def visibility(scene: Scene, params: I4Parameters, q: np.ndarray, samples: bool = False) -> dict[str, np.ndarray]:
    """Visibility of the board and of every rod at joint values ``q``.

    Parameters
    ----------
    scene : Scene
    params : I4Parameters
        Geometry used to place the parts (the nominal one before motion).
    q : ndarray, shape (N, 4)
        Joint values, metres.
    samples : bool
        Also return ``rod_visible`` (N, 4, 2, S): which of the ``samples_per_rod`` samples along each rod's axis
        (at ``(i + 0.5) / S`` from its top) are visible.

    Returns
    -------
    dict
        ``board`` (N,) bool: the whole outline in view and facing the camera; ``rod_px`` (N, 4, 2): visible
        length of each rod, pixels; ``rods`` (N,) bool: every rod keeps ``min_rod_px``; ``ok`` (N,) bool: both.
    """
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    lim = scene.limits
    cam = scene.camera
    n = len(q)
    pose = dkm(params, q)
    outline = board_outline(scene)
    board_ok = np.zeros(n, dtype=bool)
    polys: list[np.ndarray | None] = []
    planes: list[tuple[np.ndarray, float] | None] = []
    for k, cb in enumerate(scene.camera_from_board(params, pose)):
        pc = cb.apply(outline)
        if np.any(pc[:, 2] <= 0.05):
            polys.append(None)
            planes.append(None)
            continue
        px = cam.project(pc)
        normal = cb.R[:, 2]  # into the board: away from the camera when it faces it
        facing = float(normal @ cb.t) > 0.0
        board_ok[k] = bool(np.all(_inside(px, cam, lim.margin_px)) and facing)
        polys.append(px)
        planes.append((normal, float(normal @ cb.t)))
    top, bot = rod_segments(scene, params, q, pose)
    s = (np.arange(lim.samples_per_rod) + 0.5) / lim.samples_per_rod
    pts = top[..., None, :] + s[:, None] * (bot - top)[..., None, :]  # (N, 4, 2, S, 3)
    f = cam.focal_px
    r = scene.rod_radius_m
    P = pts.reshape(n, 8, -1, 3)
    front = P[..., 2] > 0.05
    z = np.where(front, P[..., 2], 1.0)
    safe = np.where(front[..., None], P, np.array([0.0, 0.0, 1.0]))
    px = cam.project(safe.reshape(-1, 3)).reshape(n, 8, -1, 2)
    vis = front & _inside(px, cam, lim.margin_px)
    for k in range(n):
        poly, plane = polys[k], planes[k]
        if poly is not None and plane is not None:  # both None together (the board behind the camera)
            normal, d = plane
            inside = _point_in_polygon(px[k].reshape(-1, 2), poly).reshape(8, -1)
            behind = (P[k] @ normal) > d  # the board's plane lies between the camera and the sample
            vis[k] &= ~(inside & behind)
    # rod a's samples against rod b's image segment (every pair at once): hidden when within the two image
    # radii of b's axis and b is nearer there
    rad_px = f * r / z  # (n, 8, S)
    p0, p1 = px[:, :, 0], px[:, :, -1]  # (n, 8, 2)
    seg = p1 - p0
    L2 = np.einsum("nbi,nbi->nb", seg, seg) + 1e-12
    rel = px[:, :, None, :, :] - p0[:, None, :, None, :]  # (n, a, b, S, 2)
    tpar = np.clip(np.einsum("nabsi,nbi->nabs", rel, seg) / L2[:, None, :, None], 0.0, 1.0)
    near = p0[:, None, :, None, :] + tpar[..., None] * seg[:, None, :, None, :]
    dist = np.linalg.norm(px[:, :, None] - near, axis=-1)
    zb = z[:, None, :, 0][..., None] + tpar * (z[:, None, :, -1] - z[:, None, :, 0])[..., None]
    hidden = (dist < rad_px[:, :, None, :] + f * r / zb) & (zb < z[:, :, None, :]) & front.all(axis=2)[:, None, :, None]
    hidden[:, np.arange(8), np.arange(8)] = False
    vis &= ~hidden.any(axis=2)
    step = np.linalg.norm(np.diff(px, axis=2), axis=3)  # (n, 8, S-1)
    seglen = np.concatenate([step[:, :, :1], step], axis=2)
    rod_px = np.sum(np.where(vis, seglen, 0.0), axis=2).reshape(n, 4, 2)
    rods_ok = np.all(rod_px >= lim.min_rod_px, axis=(1, 2))
    out = {"board": board_ok, "rod_px": rod_px, "rods": rods_ok, "ok": board_ok & rods_ok}
    if samples:
        out["rod_visible"] = vis.reshape(n, 4, 2, -1)
    return out
