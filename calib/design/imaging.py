"""What the image extraction would measure for a plan, before any image: rods, board poses, the camera's uncertainty.

The image-level predictions (:mod:`.predict`, ``ImageNoise``) need, per frame, what the extraction reports and the
methods weigh by:

* per rod (:func:`synthetic_rods`): the two limb lines of its visible part in ideal pixels, as TLS lines through
  edge points ``step_px`` apart with the residual ``edge_px`` (the extraction's ``_line_cov``), hence its
  interpretation planes ``h``, its direction ``u`` and the direction's covariance ``cov_u`` computed by the
  extraction's own model (:func:`calib.vision.rods.covariance._direction_covariances`, the batched form of its
  ``_direction_covariance``, with its edge-bias allowance), and
  the five limb samples per limb in distorted pixels (``limbs_px``) from which the methods recompute the planes for
  other intrinsics;
* per board pose (:func:`board_poses`): the PnP covariance of its pose (left rotation, t) for corner noise
  ``corner_px`` and its first-order change with the intrinsics (``d_intrinsics``);
* the camera's calibration covariance when none is given (:func:`calibration_covariance`): the inverse
  information of the board views of the camera phase (corner noise ``corner_px``, each view's pose and the released
  board points marginalised: what :func:`calib.camera.intrinsics.calibrate_intrinsics` reports).

Everything at the nominal geometry, metres and radians; pixels where named ``_px``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.camera.bundle import MIN_VIEW_DOF, Bundle, bundle_covariance, view_dof
from calib.camera.intrinsics import moved_camera
from calib.design.scene import Scene, rod_segments, visibility
from calib.errors import InputError
from calib.formats.camera import CameraModel
from calib.model.kinematics import dkm
from calib.model.parameters import I4Parameters
from calib.numerics.transforms import Rigid, matrix_to_rotvec, rotvec_to_matrix

__all__ = [
    "BoardPoses",
    "RodSet",
    "board_axis_angle_deg",
    "board_corners",
    "board_poses",
    "calibration_covariance",
    "corner_noise_factor",
    "design_camera",
    "synthetic_rods",
]

#: where along a limb's visible span the extraction's five ``limbs_px`` lie: the means of its edge points in five
#: bins of equal count (``calib.vision.rods.measure._limb_samples``), for points spread evenly over the span
_BIN_MEANS = np.array([0.1, 0.3, 0.5, 0.7, 0.9])


def design_camera(camera: CameraModel, names: tuple[str, ...]) -> CameraModel:
    """``camera`` carrying the lens model's parameter names (what
    :func:`calib.camera.intrinsics.intrinsics_names` reads).

    Parameters
    ----------
    camera : CameraModel
        The camera (K in px).
    names : tuple of str
        The intrinsics calibrated (``fx``, ``fy``, ``cx``, ``cy``, ``k1`` ...).

    Returns
    -------
    CameraModel
        A copy whose ``extra["calibration"]["covariance_params"]`` is ``names``, its distortion padded with zeros to
        the coefficients they name.
    """
    extra = dict(camera.extra or {})
    extra["calibration"] = {**(extra.get("calibration") or {}), "covariance_params": list(names)}
    need = max([5 if "k3" in names else 4, camera.dist.size])
    dist = np.concatenate([camera.dist, np.zeros(max(need - camera.dist.size, 0))])
    return CameraModel(camera.K, dist, camera.width, camera.height, extra)


@dataclass
class RodSet:
    """The rods the extraction would measure in a set of frames (M of them), camera frame.

    Attributes
    ----------
    k, leg, rod : ndarray of int, shape (M,)
        Frame index, leg (0-3), rod of the leg (0-1).
    u : ndarray, shape (M, 3)
        Axis direction (top to bottom).
    point : ndarray, shape (M, 3)
        Axis point seen at the middle of the visible limbs (as the extraction reports it), metres.
    h : ndarray, shape (M, 2, 3)
        Interpretation-plane normals, ``h . X = radius`` on the axis.
    cov_u : ndarray, shape (M, 3, 3)
        The extraction's direction covariance (edge scatter plus its edge-bias allowance).
    cov_u_own : ndarray, shape (M, 3, 3)
        The same with the allowance averaged along the limb (``edge_bias_length_px``): what the fits weigh by.
    limbs_px : ndarray, shape (M, 2, 5, 2)
        Five points per limb line, distorted pixels.
    n_points : ndarray of int, shape (M, 2)
        Edge points per limb.
    visible_px : ndarray, shape (M,)
        Visible length, pixels.
    """

    k: np.ndarray
    leg: np.ndarray
    rod: np.ndarray
    u: np.ndarray
    point: np.ndarray
    h: np.ndarray
    cov_u: np.ndarray
    cov_u_own: np.ndarray
    limbs_px: np.ndarray
    n_points: np.ndarray
    visible_px: np.ndarray

    def __len__(self) -> int:
        return len(self.k)

    def subset(self, keep: np.ndarray) -> RodSet:
        """The rods selected by ``keep``, every array alike.

        Parameters
        ----------
        keep : ndarray of bool, shape (M,), or of int
            The rods kept (a boolean mask or indices).

        Returns
        -------
        RodSet
            The selected rods.
        """
        return RodSet(**{f: getattr(self, f)[keep] for f in self.__dataclass_fields__})


def synthetic_rods(
    scene: Scene,
    params: I4Parameters,
    q: np.ndarray,
    edge_px: float,
    *,
    step_px: float = 3.0,
    edge_bias_px: float = 0.05,
    min_length_px: float = 40.0,
    edge_bias_length_px: float = 100.0,
) -> RodSet:
    """The rods of frames ``q`` (N, 4) as the extraction would measure them (see :class:`RodSet`).

    A rod is measured when its visible part (:func:`.scene.visibility`'s samples) spans ``min_length_px`` (the
    extraction's ``min_length_px``). Its limb lines are those of the cylinder's silhouette over that part; each is
    a TLS line through edge points ``step_px`` apart with residual std ``edge_px`` (the extraction's effective
    residual, including the correlation of neighbouring edges). A rod around the camera centre (no limb planes) is
    left out. Every rod of every frame is computed at once (array operations, no loop over rods).

    Parameters
    ----------
    scene : Scene
        The camera, its mounting and the rods' radius (metres).
    params : I4Parameters
        The geometry the frames are seen with (metres).
    q : ndarray, shape (N, 4)
        Encoder values of the frames, metres.
    edge_px : float
        Residual std of an edge point about its limb line, px (> 0).
    step_px : float, optional
        Spacing of the edge points along a limb, px.
    edge_bias_px : float, optional
        The extraction's allowance for a systematic edge offset, px.
    min_length_px : float, optional
        Shortest visible rod measured, px.
    edge_bias_length_px : float, optional
        Limb length over which the edge-bias allowance is averaged in ``cov_u_own``, px.

    Returns
    -------
    RodSet
        The M rods measured, in (frame, leg, rod) order.

    Raises
    ------
    InputError
        If ``edge_px`` is not finite and > 0.
    """
    from calib.vision.rods.covariance import _direction_covariances_set
    from calib.vision.rods.cylinder import axis_point_seen_along

    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if not (np.isfinite(edge_px) and edge_px > 0):
        raise InputError(f"edge_px must be finite and > 0, got {edge_px}", field="edge_px")
    cam = scene.camera
    K = cam.K
    Kinv = np.linalg.inv(K)
    v = visibility(scene, params, q, samples=True)
    pose = dkm(params, q)
    top, bot = rod_segments(scene, params, q, pose)
    S = scene.limits.samples_per_rod
    s = (np.arange(S) + 0.5) / S
    # every measured rod of every frame at once, in (frame, leg, rod) order: M rods, their S axis samples
    kk, ii, jj = np.nonzero(v["rod_px"] >= min_length_px)
    vis = v["rod_visible"][kk, ii, jj]  # (M, S)
    nv = vis.sum(axis=1)
    keep = nv > 0
    kk, ii, jj, vis, nv = kk[keep], ii[keep], jj[keep], vis[keep], nv[keep]
    t0p, b0p = top[kk, ii, jj], bot[kk, ii, jj]  # (M, 3)
    d = b0p - t0p
    X = t0p[:, None] + s[None, :, None] * d[:, None]  # (M, S, 3), the visible ones where vis
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    mid = np.argmax(np.cumsum(vis, axis=1) > (nv // 2)[:, None], axis=1)  # the middle visible sample
    P = X[np.arange(len(X)), mid]
    # the interpretation planes (limb_planes, every rod at once); the camera centre inside a cylinder: not measured
    uu = u / np.linalg.norm(u, axis=1, keepdims=True)
    p = P - np.einsum("mi,mi->m", P, uu)[:, None] * uu
    dist = np.linalg.norm(p, axis=1)
    ok = dist > scene.rod_radius_m
    kk, ii, jj, vis, X, u, P, uu, p, dist = (a[ok] for a in (kk, ii, jj, vis, X, u, P, uu, p, dist))
    M = len(kk)
    e1 = p / dist[:, None]
    e2 = np.stack(
        [
            uu[:, 1] * e1[:, 2] - uu[:, 2] * e1[:, 1],
            uu[:, 2] * e1[:, 0] - uu[:, 0] * e1[:, 2],
            uu[:, 0] * e1[:, 1] - uu[:, 1] * e1[:, 0],
        ],
        axis=1,
    )
    c = scene.rod_radius_m / dist
    sn = np.sqrt(1.0 - c * c)
    h = np.stack([c[:, None] * e1 + sn[:, None] * e2, c[:, None] * e1 - sn[:, None] * e2], axis=1)  # (M, 2, 3)
    # the limb lines in ideal pixels, unit normal n (M, 2, 2), direction td, offset
    line = h @ Kinv  # rows: (Kinv^T h)^T
    line = line / np.linalg.norm(line[..., :2], axis=-1, keepdims=True)
    n = line[..., :2]
    td = np.stack([n[..., 1], -n[..., 0]], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = X @ K.T
        xi = xi[..., :2] / xi[..., 2:]  # (M, S, 2), meaningful where vis
    xi = np.where(vis[..., None], xi, 0.0)
    # the samples' feet on each limb line and their positions t along it (M, 2, S)
    foot = xi[:, None] - (np.einsum("msi,mqi->mqs", xi, n) + line[..., 2, None])[..., None] * n[:, :, None]
    t = np.einsum("mqsi,mqi->mqs", foot, td)
    t0 = np.where(vis[:, None], t, np.inf).min(axis=-1)
    t1 = np.where(vis[:, None], t, -np.inf).max(axis=-1)
    length = t1 - t0
    m = np.maximum(np.floor(length / step_px).astype(int) + 1, 3)  # edge points per limb, ``step_px`` apart
    f0 = foot[np.arange(M), :, np.argmax(vis, axis=1)]  # (M, 2, 2), the first visible sample's foot
    base = f0 - np.einsum("mqi,mqi->mq", f0, td)[..., None] * td
    # edge points at linspace(t0, t1, m): centroid at the mid-span, spread sum(t^2) = span^2 m (m + 1) / (12 (m - 1))
    centroid = base + (0.5 * (t0 + t1))[..., None] * td
    t_sumsq = length**2 * m * (m + 1) / (12.0 * (m - 1))
    q5 = base[..., None, :] + (t0[..., None] + _BIN_MEANS * length[..., None])[..., None] * td[..., None, :]
    xn = q5.reshape(-1, 2) @ Kinv[:2, :2].T + Kinv[:2, 2]
    limbs_px = cam.distort_normalized(xn).reshape(M, 2, 5, 2)
    cmid = 0.5 * (centroid[:, 0] + centroid[:, 1])
    inner = np.c_[cmid, np.ones(M)] @ Kinv.T
    # the axis point seen at the middle of the visible limbs, as the extraction reports it: the legs method pivots
    # each limb line's noise about its foot, and the 3-D middle sample (above) projects off the image middle by
    # perspective (about 12% of the span on lock phases), which would weigh the prediction's lock planes unlike the
    # method's
    P = axis_point_seen_along(P, uu, inner)
    cov_u, cov_u_own = _direction_covariances_set(
        K,
        centroid,
        td,
        np.full((M, 2), edge_px**2),
        m,
        t_sumsq,
        length,
        inner,
        edge_bias_px,
        (0.0, edge_bias_length_px),
    )
    return RodSet(
        k=kk.astype(int),
        leg=ii.astype(int),
        rod=jj.astype(int),
        u=u,
        point=P,
        h=h,
        cov_u=cov_u,
        cov_u_own=cov_u_own,
        limbs_px=limbs_px,
        n_points=m.astype(int),
        visible_px=v["rod_px"][kk, ii, jj],
    )


def board_corners(scene: Scene) -> np.ndarray:
    """The board's inner chessboard corners (board frame, z = 0), shape (C, 3), metres.

    Parameters
    ----------
    scene : Scene
        The board's size and square (metres).

    Returns
    -------
    ndarray, shape (C, 3)
        The corners, row by row, metres.
    """
    W, H = scene.board_size_m
    a = scene.board_square_m
    nx, ny = round(W / a), round(H / a)
    gx, gy = np.meshgrid(np.arange(1, nx) * a, np.arange(1, ny) * a)
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])


def _corner_jacobians(
    camera: CameraModel, names: tuple[str, ...], R: np.ndarray, t: np.ndarray, pts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For poses R (N, 3, 3), t (N, 3): d(projected corners, 2C) / d(left rotation, t), (N, 2C, 6), and
    / d(intrinsics ``names``), (N, 2C, n); central differences, every pose at once."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    n, c = len(R), len(pts)

    def proj(cam: CameraModel, Rm: np.ndarray, tm: np.ndarray) -> np.ndarray:
        # Rm (..., 3, 3), tm (..., 3) -> (..., 2C)
        X = np.einsum("...ij,cj->...ci", Rm, pts) + tm[..., None, :]
        return cam.project(X.reshape(-1, 3)).reshape(*X.shape[:-2], 2 * c)

    h = 1e-7
    E = np.concatenate([np.eye(6), -np.eye(6)]) * h  # (12, 6)
    Rp = np.einsum("kij,njl->knil", rotvec_to_matrix(E[:, :3]), R)  # (12, N, 3, 3)
    tp = t[None] + E[:, None, 3:]
    P = proj(camera, Rp, tp)  # (12, N, 2C)
    Jp = np.moveaxis((P[:6] - P[6:]) / (2 * h), 0, -1)  # (N, 2C, 6)
    Ji = np.zeros((n, 2 * c, len(names)))
    for a, name in enumerate(names):
        hs = 1e-4 if name in ("fx", "fy", "cx", "cy") else 1e-7
        e = np.zeros(len(names))
        e[a] = hs
        Ji[:, :, a] = (proj(moved_camera(camera, e, names), R, t) - proj(moved_camera(camera, -e, names), R, t)) / (
            2 * hs
        )
    return Jp, Ji


@dataclass
class BoardPoses:
    """Board poses of N frames as PnP would give them: pose (camera frame), covariance, intrinsics' effect.

    Attributes
    ----------
    R : ndarray, shape (N, 3, 3)
    t : ndarray, shape (N, 3)
    cov : ndarray, shape (N, 6, 6)
        Covariance of (left rotation [rad], t [m]) for the corner noise.
    d_intrinsics : ndarray, shape (N, 6, n)
        The pose's change per unit change of the intrinsics (fixed corner pixels).
    """

    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    d_intrinsics: np.ndarray


def board_axis_angle_deg(scene: Scene, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """How far the board's squares' edges lie from the pixel axes in the image, per pose, degrees in [0, 45].

    The angle of the board's x axis at its centre as the camera sees it, folded onto the nearest pixel axis
    (the squares' other edges are at 90 degrees to it).

    Parameters
    ----------
    scene : Scene
        The camera and the board (metres).
    R : ndarray, shape (N, 3, 3)
        ``camera_from_board`` rotations.
    t : ndarray, shape (N, 3)
        ``camera_from_board`` translations, metres.

    Returns
    -------
    ndarray, shape (N,)
        The angle per pose, degrees in [0, 45].
    """
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    if len(R) == 0:
        return np.zeros(0)
    W, H = scene.board_size_m
    c = np.einsum("nij,j->ni", R, np.array([W / 2, H / 2, 0.0])) + t
    step = 0.25 * scene.board_square_m * R[:, :, 0]
    d = scene.camera.project(c + step) - scene.camera.project(c)
    a = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 90.0
    return np.minimum(a, 90.0 - a)


def corner_noise_factor(angle_deg: np.ndarray, axis_ratio: float, axis_width_deg: float) -> np.ndarray:
    """Corner noise of a view over that of a view whose edges are oblique to the pixel axes (>= 1).

    ``sqrt(1 + (axis_ratio^2 - 1) / (1 + (angle / axis_width)^2))``: squares whose edges run along the pixel rows
    and columns give sub-pixel corners ``axis_ratio`` times noisier (the edge's pixel phase is the same along it:
    pixel locking). On rendered views at 0.55-0.75 m, corners within 4 degrees of the axes are about three times
    noisier than beyond 20 degrees (docs/design.md).

    Parameters
    ----------
    angle_deg : ndarray, shape (N,)
        :func:`board_axis_angle_deg` of each view, degrees.
    axis_ratio : float
        Noise of a view along the axes over an oblique one's (dimensionless, >= 1; 1: no effect).
    axis_width_deg : float
        Angle at which the excess noise has halved in variance, degrees.

    Returns
    -------
    ndarray, shape (N,)
        The factor per view (dimensionless, >= 1).
    """
    a = np.asarray(angle_deg, dtype=np.float64)
    return np.sqrt(1.0 + (axis_ratio**2 - 1.0) / (1.0 + (a / axis_width_deg) ** 2))


def board_poses(
    scene: Scene,
    params: I4Parameters,
    q: np.ndarray,
    corner_px: float,
    names: tuple[str, ...],
    axis_ratio: float = 1.0,
    axis_width_deg: float = 5.5,
) -> BoardPoses:
    """Board poses of frames ``q`` (N, 4) with their PnP covariance and ``d_intrinsics`` (intrinsics ``names``).

    Corner noise ``corner_px`` (px) for a view whose squares are oblique in the image, times
    :func:`corner_noise_factor` (``axis_ratio``, ``axis_width_deg``) by how close their edges run to the pixel
    axes; ``axis_ratio`` 1: the same noise in every view.

    Parameters
    ----------
    scene : Scene
        The camera, its mounting and the board (metres).
    params : I4Parameters
        The geometry the frames are seen with (metres).
    q : ndarray, shape (N, 4)
        Encoder values of the frames, metres.
    corner_px : float
        Corner noise of an oblique view, px.
    names : tuple of str
        The intrinsics whose effect ``d_intrinsics`` gives.
    axis_ratio : float, optional
        See :func:`corner_noise_factor` (dimensionless).
    axis_width_deg : float, optional
        See :func:`corner_noise_factor`, degrees.

    Returns
    -------
    BoardPoses
        Poses (metres), their (N, 6, 6) covariance (rad^2, m^2) and (N, 6, n) ``d_intrinsics``.
    """
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    pts = board_corners(scene)
    cbs = scene.camera_from_board(params, dkm(params, q))
    R = np.stack([c.R for c in cbs]) if cbs else np.zeros((0, 3, 3))
    t = np.stack([c.t for c in cbs]) if cbs else np.zeros((0, 3))
    Jp, Ji = _corner_jacobians(scene.camera, names, R, t, pts)
    Hi = np.linalg.inv(np.einsum("nai,naj->nij", Jp, Jp))
    f = corner_noise_factor(board_axis_angle_deg(scene, R, t), axis_ratio, axis_width_deg)
    cov = (corner_px * f)[:, None, None] ** 2 * Hi
    dint = -np.einsum("nij,naj,nak->nik", Hi, Jp, Ji)
    return BoardPoses(R, t, cov, dint)


def calibration_covariance(scene: Scene, views: list[Rigid], corner_px: float, names: tuple[str, ...]) -> np.ndarray:
    """Covariance (n, n) of the intrinsics ``names`` calibrated from board ``views`` (camera_from_board poses).

    What :func:`calib.camera.intrinsics.calibrate_intrinsics` reports for these views: the bundle's information
    (every view's
    pose and the released board points marginalised, OpenCV's gauge) with corner noise ``corner_px`` in every view,
    times the factor for weights estimated from the views' residuals when it weights them
    (:mod:`calib.camera.bundle`).
    With views of unequal noise the weighted fit's information is that of ``corner_px`` = the views' variances'
    harmonic mean, square-rooted.

    Parameters
    ----------
    scene : Scene
        The camera and the board (metres).
    views : list of Rigid
        ``camera_from_board`` poses of the calibration views (metres), at least 3.
    corner_px : float
        Corner noise, px.
    names : tuple of str
        The intrinsics calibrated.

    Returns
    -------
    ndarray, shape (n, n)
        Their covariance, in the squared units of each (px^2 for ``fx`` .. ``cy``, dimensionless for distortion).

    Raises
    ------
    InputError
        Fewer than 3 views (``field="views"``).
    """
    if len(views) < 3:
        raise InputError("a camera calibration needs at least 3 board views", field="views")
    pts = board_corners(scene)
    cam = scene.camera
    ncols = int(np.sum(np.isclose(pts[:, 1], pts[0, 1])))
    bundle = Bundle.of(
        cam.K,
        cam.dist,
        pts,
        [cam.project(v.apply(pts)) for v in views],
        [matrix_to_rotvec(v.R) for v in views],
        [v.t for v in views],
        ncols - 1,
        names,
    )
    weighted = view_dof(bundle) > MIN_VIEW_DOF
    cov, _ = bundle_covariance(bundle, np.full(len(views), float(corner_px) ** 2), estimated=weighted)
    return cov
