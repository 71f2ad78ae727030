"""Predicted covariance of each method on rendered (or real) images: the methods' own uncertainty models.

On images the methods weigh what the extraction measures by what it reports (rods: ``cov_u`` from the limb edges'
scatter; boards: the PnP covariance) and carry the camera's intrinsics and a limb-edge bias common to every rod as
nuisances (:mod:`calib.identify.combined`, :mod:`calib.identify.end_effector`, :mod:`calib.identify.legs`). The
prediction rebuilds those measurements for the plan at the nominal geometry (:mod:`.imaging`) and computes the
covariance each method reports, with the noise levels of :class:`ImageNoise` (the image-level twin's by default,
or taken from a run):

* **combined**: GLS information of every rod's two Jacobian entries over (four combinations, base-frame rotation w,
  the intrinsics' principal directions z, the two limb-edge biases), each rod weighted by ``rod_scale^2`` times its
  ``cov_u`` mapped to the entries (the method's noise shape times its measured scale), the base frame's rotation
  from the rotation and translation phases' board poses (PnP covariances; its change with the intrinsics, G, from
  their ``d_intrinsics``) as w's prior, N(0, I) priors on z and the edge biases (``edge_bias_prior_px``): the
  inverse of the information, which is the method's covariance (its sandwich collapses when the weights are the
  noise's). Also the intrinsics' posterior (what the rods teach about the camera), which the two other methods use.
* **end-effector**: the method's IKM residual model (:func:`.information.end_effector_problem`) weighted by each
  pose's PnP covariance (corner noise ``corner_px``) and the encoders: ``(sum J^T C^-1 J)^-1``, plus the intrinsics'
  posterior propagated through the fit's gain (the method's ``_intrinsics_part``).
* **legs**: step 1's joints from the lock phases' plane equations weighted by their limb lines' variances
  (:func:`calib.identify.legs.limb_line_noise`, the method's own weighting), propagated through steps 2-4; the GLS
  covariance of (L, S, D) from the fit poses' leg directions (two rods' ``cov_u`` combined); the intrinsics'
  posterior and the edge biases redone through the whole estimate (the method's ``IntrinsicsEffect``); then the
  a priori tolerance (``legs_prior_std_m``, the method's ``with_prior``), and the a priori values with that
  tolerance along the three directions the four combinations do not see (the method's ``null_space_to_prior``:
  the seven's std, not the four's). The method scales its parts by their
  residual chi-square per degree of freedom, never below 1: the prediction uses 1.

Units: metres, radians; ``_px`` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.camera.intrinsics import INTRINSICS_NAMES
from calib.design.imaging import BoardPoses, RodSet, board_poses, design_camera, synthetic_rods
from calib.design.information import board_pose_sensitivity, end_effector_problem, invert_information
from calib.design.scene import Scene
from calib.errors import IdentifiabilityError, InputError
from calib.identify.legs.constants import JOINT_DEPTH_SYS_LEG_SHARE, JOINT_DEPTH_SYS_M
from calib.model.parameters import COMBINATION_NAMES, SEVEN_TO_FOUR, I4Parameters
from calib.numerics.numdiff import central_jacobian
from calib.numerics.transforms import matrix_to_rotvec, rotvec_to_matrix

__all__ = [
    "DEFAULT_INTRINSICS_NAMES",
    "ImageNoise",
    "LegsFitDirections",
    "LegsLock",
    "base_frame_images",
    "combined_images_pose_information",
    "combined_images_prior",
    "end_effector_images_pose_information",
    "legs_fit_directions",
    "legs_lock_joints",
    "predict_combined_images",
    "predict_end_effector_images",
    "predict_legs_images",
]

#: the image-level twin's lens model (chosen by BIC on its board views: k1, k2, p1, p2 and k3)
DEFAULT_INTRINSICS_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class ImageNoise:
    """Noise levels of an image extraction and the camera's calibration (defaults: the image-level twin's).

    Attributes
    ----------
    edge_px : float
        Std of a limb edge point about its line (px): the extraction's edge residual RMS (``rms_px``; the benches'
        ``edge_noise_px_median``). The rods' ``cov_u`` adds the edge-bias allowance (``edge_bias_px``), which
        dominates it; the legs method's lock phases leave that allowance out and weigh their frames by this scatter
        (:func:`calib.identify.legs.limb_line_noise`), so a larger value standing in for the bias would weigh them
        as noisier than they are.
    rod_scale : float
        The rods' scatter over the prediction's synthetic ``cov_u_own`` (what the combined method weighs by): the
        method's own scale over the extracted ``cov_u_own`` (``diagnostics.rod_errors.own_scale``, about 0.9 on
        rendered images) times the extracted over the synthetic covariance's principal std (about 1.1): 1.0 by
        default (docs/design.md).
    rod_pair_correlation, rod_distance_correlation : float
        The rods' error correlations as the combined method estimates them (``diagnostics.rod_errors``: a leg's
        two rods in one frame; rods seen at nearby places, times exp(-distance / 100 px)); the defaults, 0.15 and
        0.18, are typical of rendered images of designed and paper plans (docs/design.md). The prediction's
        covariance is the method's sandwich with them; the design's exchange leaves them out (per-pose
        information).
    corner_px : float
        Effective std of a board corner (px) for the board poses' PnP covariance (times the end-effector
        method's measured factor), in a view whose squares are oblique to the pixel axes.
    corner_axis_ratio, corner_axis_width_deg : float
        How much noisier the corners of a view whose squares' edges run along the pixel axes are, and how fast that
        fades with the angle (:func:`calib.design.imaging.corner_noise_factor`; ratio 1: every view alike).
    edge_bias_px, step_px : float
        The extraction's edge-bias allowance in ``cov_u`` and its profile spacing (``RodSettings``).
    edge_bias_length_px : float
        The allowance's correlation length along a limb (``RodSettings.edge_bias_length_px``).
    edge_bias_prior_px : float
        Prior std of the limb-edge bias common to every rod (``calib.identify.combined.EDGE_BIAS_STD_PX``).
    legs_lock_chi2, legs_directions_chi2 : float
        The legs method's residual chi-square per degree of freedom in its lock phases (step 1, the joints' planes)
        and in its fit poses (steps 3-4, the leg directions): the method scales its joints' and its leg directions'
        covariance by them, since the rods' errors exceed their edge scatter (frame to frame, a rod keeps part of its
        error). The defaults, 1.5 and 1.3, are their typical values on rendered images of the image-level twin
        (docs/design.md). 1: the covariances as the noise model gives them.
    legs_rod_cov_ratio : float
        The extracted fit-pose rods' own covariances over the synthetic ones, as the legs method's steps 3-4 weigh
        them (variance ratio of their leg-directions part before its chi-square level): 1.26 by default, the
        synthetic ``cov_u``'s principal std being about 1.1x smaller than the extracted on rendered images
        (docs/design.md). The combined prediction has it in ``rod_scale``.
    legs_joint_depth_sys_m, legs_joint_depth_sys_leg_share : float
        The lock phases' joints' systematic error along their line of sight (m, RMS per joint) and the share of
        its variance common to a leg's two joints: the legs method's (``calib.identify.legs.constants``,
        ``joint_depth_systematic``; the rods' shading, the same in every frame of a lock phase). 0: left out.
    legs_prior_std_m : float or None
        The legs method's a priori tolerance per parameter (``calib.identify.legs.PRIOR_STD_M``).
    intrinsics_names : tuple of str
        The lens model's parameters.
    intrinsics_cov : tuple of tuples, or None
        The camera calibration's covariance over ``intrinsics_names`` (px for fx, fy, cx, cy); None: the camera
        is taken as known.
    encoder_m : float
        Encoders (m).
    """

    edge_px: float = 0.08
    rod_scale: float = 1.0
    corner_px: float = 0.025
    corner_axis_ratio: float = 3.3
    corner_axis_width_deg: float = 5.5
    edge_bias_px: float = 0.05
    edge_bias_length_px: float = 100.0
    rod_pair_correlation: float = 0.15
    rod_distance_correlation: float = 0.18
    step_px: float = 3.0
    edge_bias_prior_px: float = 0.1
    legs_lock_chi2: float = 1.5
    legs_directions_chi2: float = 1.3
    legs_rod_cov_ratio: float = 1.26
    legs_joint_depth_sys_m: float = JOINT_DEPTH_SYS_M
    legs_joint_depth_sys_leg_share: float = JOINT_DEPTH_SYS_LEG_SHARE
    legs_prior_std_m: float | None = 0.01
    intrinsics_names: tuple[str, ...] = DEFAULT_INTRINSICS_NAMES
    intrinsics_cov: tuple[tuple[float, ...], ...] | None = None
    encoder_m: float = 1e-6

    def __post_init__(self) -> None:
        for k in (
            "edge_px",
            "rod_scale",
            "corner_px",
            "step_px",
            "corner_axis_width_deg",
            "legs_lock_chi2",
            "legs_directions_chi2",
            "legs_rod_cov_ratio",
        ):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"image noise: {k} must be finite and > 0, got {v}", field=k)
        for k in (
            "edge_bias_px",
            "edge_bias_length_px",
            "edge_bias_prior_px",
            "encoder_m",
            "rod_pair_correlation",
            "rod_distance_correlation",
            "legs_joint_depth_sys_m",
        ):
            v = getattr(self, k)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"image noise: {k} must be finite and >= 0, got {v}", field=k)
        if not (np.isfinite(self.legs_joint_depth_sys_leg_share) and 0 <= self.legs_joint_depth_sys_leg_share <= 1):
            raise InputError(
                "image noise: legs_joint_depth_sys_leg_share must be within [0, 1], got "
                f"{self.legs_joint_depth_sys_leg_share}",
                field="legs_joint_depth_sys_leg_share",
            )
        for k in ("rod_pair_correlation", "rod_distance_correlation"):
            v = getattr(self, k)
            if not v < 1:
                raise InputError(f"image noise: {k} must be < 1, got {v}", field=k)
        if not (np.isfinite(self.corner_axis_ratio) and self.corner_axis_ratio >= 1):
            raise InputError(
                f"image noise: corner_axis_ratio must be finite and >= 1, got {self.corner_axis_ratio}",
                field="corner_axis_ratio",
            )
        bad = [n for n in self.intrinsics_names if n not in (*INTRINSICS_NAMES, "k3", "k4", "k5", "k6")]
        if bad:
            raise InputError(f"image noise: unknown intrinsics {', '.join(bad)}", field="intrinsics_names")
        if self.intrinsics_cov is not None:
            C = np.asarray(self.intrinsics_cov, dtype=np.float64)
            n = len(self.intrinsics_names)
            if C.shape != (n, n) or not np.all(np.isfinite(C)) or np.linalg.eigvalsh(0.5 * (C + C.T))[0] < -1e-12:
                raise InputError(
                    f"image noise: intrinsics_cov must be a finite positive semi-definite {n}x{n} matrix",
                    field="intrinsics_cov",
                )

    def board_poses(self, scene: Scene, nominal: I4Parameters, q: np.ndarray) -> BoardPoses:
        """:func:`calib.design.imaging.board_poses` of frames ``q`` (N, 4) at these corner noise levels.

        Parameters
        ----------
        scene : Scene
            The camera, its mounting and the board (metres).
        nominal : I4Parameters
            The geometry the frames are seen with (metres).
        q : ndarray, shape (N, 4)
            Encoder values of the frames, metres.

        Returns
        -------
        BoardPoses
            Poses (metres), their (N, 6, 6) PnP covariance (rad^2, m^2) and ``d_intrinsics``.
        """
        return board_poses(
            scene,
            nominal,
            q,
            self.corner_px,
            self.intrinsics_names,
            self.corner_axis_ratio,
            self.corner_axis_width_deg,
        )

    def covariance(self) -> np.ndarray | None:
        return None if self.intrinsics_cov is None else np.asarray(self.intrinsics_cov, dtype=np.float64)

    def with_intrinsics(self, cov: np.ndarray, names: tuple[str, ...] | None = None) -> ImageNoise:
        """The same levels with the camera's covariance ``cov`` (over ``names``, default the current ones).

        Parameters
        ----------
        cov : ndarray, shape (n, n)
            Covariance of the intrinsics (px^2 for fx, fy, cx, cy; dimensionless for distortion), symmetrised here.
        names : tuple of str, optional
            The intrinsics it is over (default: ``intrinsics_names``).

        Returns
        -------
        ImageNoise
            A copy carrying ``cov``.
        """
        from dataclasses import replace

        c = np.asarray(cov, dtype=np.float64)
        c = 0.5 * (c + c.T)
        return replace(
            self,
            intrinsics_names=tuple(names or self.intrinsics_names),
            intrinsics_cov=tuple(tuple(float(x) for x in row) for row in c),
        )

    def to_dict(self) -> dict[str, Any]:
        cov = self.covariance()
        return {
            "model": "images",
            "edge_px": self.edge_px,
            "rod_scale": self.rod_scale,
            "corner_px": self.corner_px,
            "corner_axis_ratio": self.corner_axis_ratio,
            "corner_axis_width_deg": self.corner_axis_width_deg,
            "edge_bias_px": self.edge_bias_px,
            "edge_bias_length_px": self.edge_bias_length_px,
            "rod_pair_correlation": self.rod_pair_correlation,
            "rod_distance_correlation": self.rod_distance_correlation,
            "step_px": self.step_px,
            "edge_bias_prior_px": self.edge_bias_prior_px,
            "legs_lock_chi2": self.legs_lock_chi2,
            "legs_directions_chi2": self.legs_directions_chi2,
            "legs_rod_cov_ratio": self.legs_rod_cov_ratio,
            "legs_joint_depth_sys_m": self.legs_joint_depth_sys_m,
            "legs_joint_depth_sys_leg_share": self.legs_joint_depth_sys_leg_share,
            "legs_prior_std_m": self.legs_prior_std_m,
            "intrinsics_names": list(self.intrinsics_names),
            "intrinsics_std": None
            if cov is None
            else dict(zip(self.intrinsics_names, np.sqrt(np.maximum(np.diag(cov), 0)).tolist(), strict=True)),
            "encoder_m": self.encoder_m,
        }


def _steps(cov: np.ndarray | None, n: int) -> np.ndarray:
    from calib.identify.intrinsics import principal_steps

    return np.zeros((0, n)) if cov is None else principal_steps(cov)


def _rods(scene: Scene, nominal: I4Parameters, q: np.ndarray, noise: ImageNoise) -> RodSet:
    return synthetic_rods(
        scene,
        nominal,
        q,
        noise.edge_px,
        step_px=noise.step_px,
        edge_bias_px=noise.edge_bias_px,
        edge_bias_length_px=noise.edge_bias_length_px,
    )


# -- base frame ------------------------------------------------------------------------------------------------
def base_frame_images(
    nominal: I4Parameters,
    q_rot: np.ndarray,
    q_tra: np.ndarray,
    scene: Scene,
    noise: ImageNoise,
    steps: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Information (3, 3) on the base frame's rotation ``w`` from the board poses of the rotation and translation
    phases (their PnP covariances), and its change G (3, n_steps) per intrinsics step (rows of ``steps``).

    The rotation phase's board orientations turn about z_B (reference orientation and angles unknown), the
    translation phase's positions move along x_B (start unknown); the estimate's gain maps the board poses'
    change with the intrinsics (``d_intrinsics``) to w.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the frames are seen with (metres).
    q_rot, q_tra : ndarray, shape (N, 4)
        Joint values of the rotation and translation phases, metres (at least 2 each).
    scene : Scene
        The camera, its mounting and the board.
    noise : ImageNoise
        Corner noise (px) and the intrinsics' names.
    steps : ndarray, shape (n_steps, n), optional
        Intrinsics steps (rows, in the units of each intrinsic); none by default.

    Returns
    -------
    info : ndarray, shape (3, 3)
        Information on ``w``, rad^-2.
    G : ndarray, shape (3, n_steps)
        Change of ``w`` per intrinsics step, radians.

    Raises
    ------
    IdentifiabilityError
        Fewer than 2 frames in a phase.
    """
    q_rot = np.asarray(q_rot, dtype=np.float64).reshape(-1, 4)
    q_tra = np.asarray(q_tra, dtype=np.float64).reshape(-1, 4)
    if len(q_rot) < 2 or len(q_tra) < 2:
        raise IdentifiabilityError("the base frame needs at least 2 rotation and 2 translation frames")
    br = noise.board_poses(scene, nominal, q_rot)
    bt = noise.board_poses(scene, nominal, q_tra)
    R_cb = scene.camera_from_base.R
    n_r = len(q_rot)
    T_rot = (q_rot[:, 0] + q_rot[:, 1] - q_rot[:, 2] - q_rot[:, 3]) / 4.0
    th0 = (T_rot - T_rot[0]) / nominal.T_per_rad
    s = q_tra.mean(axis=1)
    zB = R_cb[:, 2]
    Rref = rotvec_to_matrix(-zB * th0[0]) @ br.R[0]
    Rm, tm = br.R, bt.t

    def model(x: np.ndarray, Rmeas: np.ndarray = Rm, tmeas: np.ndarray = tm) -> np.ndarray:
        w, rho, th, t0 = x[:3], x[3:6], x[6 : 6 + n_r], x[6 + n_r :]
        R = rotvec_to_matrix(w) @ R_cb
        Rk = rotvec_to_matrix(R[:, 2][None, :] * (th + th0[0])[:, None]) @ rotvec_to_matrix(rho) @ Rref
        rot = matrix_to_rotvec(Rk @ np.swapaxes(Rmeas, 1, 2))
        tra = t0[None, :] + (s - s[0])[:, None] * R[:, 0][None, :] - tmeas
        return np.concatenate([rot.ravel(), tra.ravel()])

    x0 = np.concatenate([np.zeros(6), th0 - th0[0], bt.t[0]])
    r0 = model(x0)
    if np.max(np.abs(r0)) > 1e-9:
        raise RuntimeError(f"base-frame design model does not close at nominal ({np.max(np.abs(r0)):.2e})")
    J = central_jacobian(model, x0, 1e-7)
    # whitening: per frame, the rotation (rotation phase) or the position (translation phase) covariance
    W = np.zeros((3 * (n_r + len(q_tra)),) * 2)
    for k in range(n_r):
        W[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = np.linalg.inv(br.cov[k, :3, :3])
    for k in range(len(q_tra)):
        a = 3 * (n_r + k)
        W[a : a + 3, a : a + 3] = np.linalg.inv(bt.cov[k, 3:, 3:])
    H = J.T @ W @ J
    Hi = np.linalg.pinv(H, rcond=1e-13, hermitian=True)
    F = np.linalg.inv(Hi[:3, :3])
    n_st = 0 if steps is None else steps.shape[0]
    G = np.zeros((3, n_st))
    for j in range(n_st):
        assert steps is not None
        dr = np.einsum("nij,j->ni", br.d_intrinsics, steps[j])
        dt = np.einsum("nij,j->ni", bt.d_intrinsics, steps[j])
        # the measured poses moved: rotation exp(d[:3]) R, position t + d[3:]
        Rp = np.einsum("nij,njk->nik", rotvec_to_matrix(dr[:, :3]), Rm)
        dm = model(x0, Rp, tm + dt[:, 3:]) - r0
        G[:, j] = -(Hi @ J.T @ W @ dm)[:3]
    return F, G


# -- combined --------------------------------------------------------------------------------------------------
def _combined_terms(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    scene: Scene,
    noise: ImageNoise,
    steps: np.ndarray,
    G: np.ndarray,
    drop: set[tuple[int, int, int]] | None = None,
    correlated: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Per rod: Jacobian (M, 2, p) of the raw residuals over (combinations, w, z, edge biases), their noise
    covariance (M, 2, 2) and the pose index (M,). ``drop``: rods left out, (fit pose index, leg 0-3, rod 0-1).
    ``correlated``: also the rods' whole error covariance (2M, 2M) with the method's correlations between rods
    (:func:`_rod_error_covariance`), else None."""
    from calib.identify.combined import RodIntrinsicsModel, model_ratios, ratio_gradient

    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    R0 = scene.camera_from_base.R
    rods = _rods(scene, nominal, q_fit, noise)
    keep = np.abs((rods.u @ R0)[:, 0]) >= 0.05  # the method's own cut (near-vertical rods in the base frame)
    if drop:
        keep &= np.array(
            [(int(k), int(i), int(j)) not in drop for k, i, j in zip(rods.k, rods.leg, rods.rod, strict=True)]
        )
    rods = rods.subset(keep)
    if len(rods) == 0:
        return np.zeros((0, 2, 9 + steps.shape[0])), np.zeros((0, 2, 2)), np.zeros(0, dtype=int), None
    cam = design_camera(scene.camera, noise.intrinsics_names)
    im = RodIntrinsicsModel(cam, steps, rods.limbs_px, rods.h, G, None, noise.edge_bias_prior_px)
    nz = steps.shape[0] + im.n_edge
    xi0 = np.array([nominal.combinations()[k] for k in COMBINATION_NAMES])

    def raw(v: np.ndarray) -> np.ndarray:
        z = v[7:]
        u = im.directions(z, rods.u)
        R = im.rotation(z) @ rotvec_to_matrix(v[4:7]) @ R0
        uB = u @ R
        return (model_ratios(v[:4], q_fit)[rods.k, rods.leg] - uB[:, 1:] / uB[:, :1]).ravel()

    x0 = np.concatenate([xi0, np.zeros(3 + nz)])
    J = central_jacobian(raw, x0, 1e-7).reshape(len(rods), 2, -1)
    uB = rods.u @ R0
    Gr = ratio_gradient(uB)
    P = np.einsum("ji,mjk,kl->mil", R0, rods.cov_u_own, R0)  # as the method weighs its rods
    shape = np.einsum("mij,mjk,mlk->mil", Gr, P, Gr)
    S = noise.rod_scale**2 * shape
    Sig = _rod_error_covariance(rods, shape, Gr, R0, cam.K, noise) if correlated else None
    return J, S, rods.k, Sig


def _rod_error_covariance(
    rods: RodSet, shape: np.ndarray, ratio_grad: np.ndarray, R_cb: np.ndarray, K: np.ndarray, noise: ImageNoise
) -> np.ndarray:
    """The rods' error covariance (2M, 2M) in the combined method's raw residuals, as the method models it
    (:mod:`calib.identify.rod_correlation`): each rod's own ``shape`` (M, 2, 2), the whitened errors of a leg's two
    rods in one frame correlated at ``noise.rod_pair_correlation``, the in-image errors of rods seen at nearby places
    at ``noise.rod_distance_correlation`` (times exp(-distance / 100 px)), all times ``noise.rod_scale^2``."""
    from calib.identify import rod_correlation as rc

    m = len(rods)
    pairs = rc.rod_pairs(rods.k, rods.leg)
    own = rc.block_diagonal(shape)
    shapes, rho = [], []
    if noise.rod_pair_correlation > 0 and len(pairs) >= rc.MIN_PAIRS:
        shapes.append(rc.pair_shape(pairs, np.linalg.inv(rc.whitening(shape)), m))
        rho.append(noise.rod_pair_correlation)
    if noise.rod_distance_correlation > 0:
        rays = rods.point / np.linalg.norm(rods.point, axis=1, keepdims=True)
        g = rc.in_image_sensitivity(rods.u, rays, R_cb, ratio_grad, shape)
        shapes.append(rc.distance_shape(rays, float(np.sqrt(K[0, 0] * K[1, 1])), g, pairs))
        rho.append(noise.rod_distance_correlation)
    if shapes:
        r = rc.positive_definite(own, shapes, np.asarray(rho))
        own = own + sum(rj * Sj for rj, Sj in zip(r, shapes, strict=True))
    return noise.rod_scale**2 * own


def combined_images_pose_information(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    scene: Scene,
    noise: ImageNoise,
    steps: np.ndarray,
    G: np.ndarray,
    drop: set[tuple[int, int, int]] | None = None,
) -> np.ndarray:
    """GLS information (N, p, p) of each fit pose's rods over (combinations, w, z, edge biases).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the rods are seen with (metres).
    q_fit : ndarray, shape (N, 4)
        Joint values of the fit poses, metres.
    scene : Scene
        The camera, its mounting and the rods.
    noise : ImageNoise
        The extraction's noise levels (px).
    steps : ndarray, shape (n_z, n)
        The intrinsics' principal steps (:func:`combined_images_prior`).
    G : ndarray, shape (3, n_z)
        The base frame's rotation change per step, radians.
    drop : set of (int, int, int), optional
        Rods left out: (fit pose index, leg 0-3, rod 0-1).

    Returns
    -------
    ndarray, shape (N, p, p)
        Per pose, information on the combinations (m^-2), ``w`` (rad^-2) and the nuisances ``z`` and edge biases
        (dimensionless, in units of their prior std).
    """
    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    J, S, k, _ = _combined_terms(nominal, q_fit, scene, noise, steps, G, drop)
    Si = np.linalg.inv(S + 1e-30 * np.eye(2))
    Fm = np.einsum("mai,mab,mbj->mij", J, Si, J)
    out = np.zeros((len(q_fit), J.shape[2], J.shape[2]))
    np.add.at(out, k, Fm)
    return out


def combined_images_prior(
    nominal: I4Parameters, q_rot: np.ndarray, q_tra: np.ndarray, scene: Scene, noise: ImageNoise
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The combined method's prior information (p, p) over (combinations, w, z, edge biases), the intrinsics'
    principal steps (n_z, n) and the base frame's change with them G (3, n_z).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the frames are seen with (metres).
    q_rot, q_tra : ndarray, shape (N, 4)
        Joint values of the rotation and translation phases, metres.
    scene : Scene
        The camera, its mounting and the board.
    noise : ImageNoise
        Corner noise (px), the camera's covariance and the edge-bias prior (px).

    Returns
    -------
    P : ndarray, shape (p, p)
        Prior information: ``w`` (rad^-2) from the base-frame phases, unit on ``z`` and the edge biases.
    steps : ndarray, shape (n_z, n)
        The intrinsics' principal steps (in the units of each intrinsic; none without a camera covariance).
    G : ndarray, shape (3, n_z)
        The base frame's rotation change per step, radians.
    """
    steps = _steps(noise.covariance(), len(noise.intrinsics_names))
    Fw, G = base_frame_images(nominal, q_rot, q_tra, scene, noise, steps)
    n_edge = 2 if noise.edge_bias_prior_px > 0 else 0
    p = 7 + steps.shape[0] + n_edge
    P = np.zeros((p, p))
    P[4:7, 4:7] = Fw
    P[7:, 7:] = np.eye(p - 7)
    return P, steps, G


def predict_combined_images(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    q_rot: np.ndarray,
    q_tra: np.ndarray,
    scene: Scene,
    noise: ImageNoise,
    drop: set[tuple[int, int, int]] | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Predicted covariance (4, 4) of the combined method's combinations on images (m^2), and the intrinsics'
    posterior covariance (n, n) after the rods (None without a camera covariance). ``drop``: rods left out (fit
    pose index, leg 0-3, rod 0-1), e.g. those a run's fit rejected.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit, q_rot, q_tra : ndarray, shape (N, 4)
        Joint values of the fit poses and of the rotation and translation phases, metres.
    scene : Scene
        The camera, its mounting, the board and the rods.
    noise : ImageNoise
        The extraction's and the camera's noise levels.
    drop : set of (int, int, int), optional
        Rods left out.

    Returns
    -------
    cov4 : ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.
    posterior : ndarray, shape (n, n) or None
        The intrinsics' posterior covariance (px^2 for fx, fy, cx, cy), None without a camera covariance.

    Raises
    ------
    IdentifiabilityError
        The plan does not determine the four combinations.
    """
    C4, post, _edge = predict_combined_images_posteriors(nominal, q_fit, q_rot, q_tra, scene, noise, drop)
    return C4, post


def predict_combined_images_posteriors(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    q_rot: np.ndarray,
    q_tra: np.ndarray,
    scene: Scene,
    noise: ImageNoise,
    drop: set[tuple[int, int, int]] | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`predict_combined_images` and the limb-edge bias's posterior covariance (2, 2), px^2 (None without the
    edge-bias nuisances): what the legs method takes from the combined fit (``calib.identify.edge_bias``).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit, q_rot, q_tra : ndarray, shape (N, 4)
        Joint values of the fit poses and of the rotation and translation phases, metres.
    scene : Scene
        The camera, its mounting, the board and the rods.
    noise : ImageNoise
        The extraction's and the camera's noise levels.
    drop : set of (int, int, int), optional
        Rods left out: (fit pose index, leg 0-3, rod 0-1).

    Returns
    -------
    cov4 : ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.
    posterior : ndarray, shape (n, n) or None
        The intrinsics' posterior covariance, None without a camera covariance.
    edge : ndarray, shape (2, 2) or None
        The limb-edge biases' posterior covariance, px^2, None without edge-bias nuisances.

    Raises
    ------
    IdentifiabilityError
        The plan does not determine the four combinations.
    """
    P, steps, G = combined_images_prior(nominal, q_rot, q_tra, scene, noise)
    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    J, S, _k, Sig = _combined_terms(nominal, q_fit, scene, noise, steps, G, drop, correlated=True)
    Si = np.linalg.inv(S + 1e-30 * np.eye(2))
    F = np.einsum("mai,mab,mbj->ij", J, Si, J) + P
    C = invert_information(F, "combined")
    if Sig is not None and len(J):  # the rods' correlated errors: the method's sandwich (its GLS weights kept)
        Jw = np.einsum("mab,mbj->maj", Si, J).reshape(-1, J.shape[2]).T  # J^T W, (p, 2M)
        C = C @ (Jw @ Sig @ Jw.T + P) @ C
    post = None
    ni = steps.shape[0]
    if ni:
        post = steps.T @ C[7 : 7 + ni, 7 : 7 + ni] @ steps
    edge = None
    if C.shape[0] == 7 + ni + 2:
        edge = C[7 + ni :, 7 + ni :] * noise.edge_bias_prior_px**2
    return C[:4, :4], post, edge


# -- end-effector ----------------------------------------------------------------------------------------------
def _ee_terms(nominal: I4Parameters, q_fit: np.ndarray, scene: Scene, noise: ImageNoise):
    """The end-effector problem's residual Jacobian (N, 6, p), their sensitivity to the board pose (N, 6, 6), the
    board poses (PnP covariance, d_intrinsics) and the residuals' covariance (N, 6, 6)."""
    model, x0, R, t = end_effector_problem(nominal, q_fit, scene)
    n = len(R)
    J = central_jacobian(lambda x: model.residuals(x).ravel(), x0, 1e-7).reshape(n, 6, -1)
    A = board_pose_sensitivity(model, x0, R, t)
    bp = noise.board_poses(scene, nominal, q_fit)
    C = np.einsum("nij,njk,nlk->nil", A, bp.cov, A)
    C[:, :4, :4] += noise.encoder_m**2 * np.eye(4)
    return J, A, bp, C + 1e-30 * np.eye(6)


def end_effector_images_pose_information(
    nominal: I4Parameters, q_fit: np.ndarray, scene: Scene, noise: ImageNoise
) -> np.ndarray:
    """GLS information (N, 16, 16) of each fit pose's board pose (PnP covariance) and encoders on the end-effector
    method's unknowns (the combinations first).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit : ndarray, shape (N, 4)
        Joint values of the fit poses, metres.
    scene : Scene
        The camera, its mounting and the board.
    noise : ImageNoise
        Corner noise (px) and encoder noise (metres).

    Returns
    -------
    ndarray, shape (N, 16, 16)
        Per pose, information on the unknowns (inverse squared metres and radians).
    """
    J, _A, _bp, C = _ee_terms(nominal, np.asarray(q_fit, dtype=np.float64).reshape(-1, 4), scene, noise)
    return np.einsum("nai,nab,nbj->nij", J, np.linalg.inv(C), J)


def predict_end_effector_images(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    scene: Scene,
    noise: ImageNoise,
    intrinsics_cov: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Predicted covariance (4, 4) of the end-effector method on images (m^2) and its parts
    (``board_poses_and_encoders``, ``intrinsics``). ``intrinsics_cov``: the camera's covariance the method uses
    (the rods' posterior, as the extraction records it; default: the calibration's).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit : ndarray, shape (N, 4)
        Joint values of the fit poses, metres.
    scene : Scene
        The camera, its mounting and the board.
    noise : ImageNoise
        Corner noise (px), encoder noise (metres) and the camera's covariance.
    intrinsics_cov : ndarray, shape (n, n), optional
        The camera's covariance the method uses (px^2 for fx, fy, cx, cy).

    Returns
    -------
    cov4 : ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.
    parts : dict of str to ndarray, shape (4, 4)
        Its parts (m^2), adding up to ``cov4``.

    Raises
    ------
    IdentifiabilityError
        The plan does not determine the four combinations.
    """
    J, A, bp, C = _ee_terms(nominal, np.asarray(q_fit, dtype=np.float64).reshape(-1, 4), scene, noise)
    Ci = np.linalg.inv(C)
    F = np.einsum("nai,nab,nbj->ij", J, Ci, J)
    Fi = invert_information(F, "end-effector")
    parts = {"board_poses_and_encoders": Fi[:4, :4], "intrinsics": np.zeros((4, 4))}
    cov_i = noise.covariance() if intrinsics_cov is None else intrinsics_cov
    if cov_i is not None:
        steps = _steps(cov_i, len(noise.intrinsics_names))
        D = np.einsum("nij,njk,sk->nis", A, bp.d_intrinsics, steps)  # (n, 6, S) residual change per step
        dx = Fi @ np.einsum("nai,nab,nbs->is", J, Ci, D)
        parts["intrinsics"] = (dx @ dx.T)[:4, :4]
    return parts["board_poses_and_encoders"] + parts["intrinsics"], parts


# -- legs ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LegsLock:
    """The legs method's step 1 on a plan's lock phases, as the prediction rebuilds it at the nominal geometry.

    Attributes
    ----------
    q_locked : ndarray, shape (4,)
        Each locked actuator's value (mean over its phase), metres.
    planes : list
        Per leg and rod, the :class:`calib.identify.legs.PlaneObservation` of each lock frame.
    lock_fields : list
        Per leg and rod, the limb samples (distorted pixels) and interpretation planes, for redoing the planes
        with other intrinsics.
    P : ndarray, shape (4, 2, 3)
        The joints (leg, rod), camera frame, metres.
    covP : ndarray, shape (24, 24)
        Their covariance from the lock frames' limb lines (before the lock phases' chi-square level), m^2.
    """

    q_locked: np.ndarray
    planes: list[Any]
    lock_fields: list[Any]
    P: np.ndarray
    covP: np.ndarray


def legs_lock_joints(nominal: I4Parameters, q_lock: list[np.ndarray], scene: Scene, noise: ImageNoise) -> LegsLock:
    """Step 1 of the legs method on the lock phases ``q_lock`` (four arrays (n_i, 4) of actuator values, metres):
    the joints and their covariance (:class:`LegsLock`).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the frames are seen with (metres).
    q_lock : list of 4 ndarrays, shape (n_i, 4)
        Actuator values of the ``lock-1`` .. ``lock-4`` phases, metres.
    scene : Scene
        The camera, its mounting and the rods.
    noise : ImageNoise
        The extraction's noise levels (px).

    Returns
    -------
    LegsLock
        The joints (metres) and their covariance (m^2).

    Raises
    ------
    IdentifiabilityError
        A phase with fewer than 2 frames, or a rod in view in fewer than 2 of its lock frames (names the phase and
        the rod).
    """
    from calib.identify.legs import PlaneObservation, joint_from_planes, limb_line_noise

    if len(q_lock) != 4 or any(len(np.atleast_2d(q)) < 2 for q in q_lock):
        raise IdentifiabilityError("the legs method needs at least 2 frames in each of lock-1 .. lock-4")
    K = scene.camera.K
    q_locked = np.zeros(4)
    planes: list[list[list[PlaneObservation]]] = []
    lock_fields = []
    for i in range(4):
        q = np.atleast_2d(np.asarray(q_lock[i], dtype=np.float64))
        q_locked[i] = float(np.mean(q[:, i]))
        rods = _rods(scene, nominal, q, noise)
        row, frow = [], []
        for j in range(2):
            sel = (rods.leg == i) & (rods.rod == j)
            if sel.sum() < 2:
                raise IdentifiabilityError(
                    f"lock-{i + 1}: rod {j} of leg {i + 1} is in view in {int(sel.sum())} frame(s); at least 2 needed"
                )
            obs = []
            for m in np.nonzero(sel)[0]:
                dh, var = limb_line_noise(
                    K,
                    rods.h[m],
                    rods.point[m],
                    np.array([noise.edge_px] * 2),
                    rods.n_points[m],
                    rods.cov_u[m],
                    noise.step_px,
                    noise.edge_bias_px,
                    frame_bias=False,  # as the method weighs its lock phases
                )
                obs.append(PlaneObservation(rods.h[m], scene.rod_radius_m, dh, var))
            row.append(obs)
            frow.append((rods.limbs_px[sel], rods.h[sel]))
        planes.append(row)
        lock_fields.append(frow)
    P = np.array([[joint_from_planes(planes[i][j])[0] for j in range(2)] for i in range(4)])
    covP = np.zeros((24, 24))
    for i in range(4):
        for j in range(2):
            k = (2 * i + j) * 3
            covP[k : k + 3, k : k + 3] = np.linalg.inv(joint_from_planes(planes[i][j])[1])
    return LegsLock(q_locked, planes, lock_fields, P, covP)


@dataclass(frozen=True)
class LegsFitDirections:
    """The fit poses' rods and leg directions as the legs method combines them (NaN where a rod is not seen).

    Attributes: ``rods`` (the synthetic :class:`.imaging.RodSet`), ``u`` (N, 4, 2, 3) rod directions, ``cov_u`` and
    ``cov_u_own`` (N, 4, 2, 3, 3) their covariances, ``has`` (N, 4, 2), ``U`` (N, 4, 3) and ``CU`` (N, 4, 3, 3) the
    legs' directions (the two rods' covariance-weighted mean) and covariances, ``has_leg`` (N, 4), ``pts`` (N, 4, 3) a
    point on each leg's rods (camera frame, metres)."""

    rods: RodSet
    u: np.ndarray
    cov_u: np.ndarray
    cov_u_own: np.ndarray
    has: np.ndarray
    U: np.ndarray
    CU: np.ndarray
    has_leg: np.ndarray
    pts: np.ndarray


def legs_fit_directions(nominal: I4Parameters, q_fit: np.ndarray, scene: Scene, noise: ImageNoise) -> LegsFitDirections:
    """The leg directions of the fit poses ``q_fit`` (N, 4) (actuator values, metres), :class:`LegsFitDirections`.

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the frames are seen with (metres).
    q_fit : ndarray, shape (N, 4)
        Actuator values of the fit poses, metres.
    scene : Scene
        The camera, its mounting and the rods.
    noise : ImageNoise
        The extraction's noise levels (px).

    Returns
    -------
    LegsFitDirections
        Rod and leg directions (dimensionless) and their covariances (rad^2), NaN where not seen.
    """
    from calib.identify.legs import pair_means

    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    N = len(q_fit)
    fr = _rods(scene, nominal, q_fit, noise)
    u = np.full((N, 4, 2, 3), np.nan)
    Cr = np.full((N, 4, 2, 3, 3), np.nan)
    Co = np.full((N, 4, 2, 3, 3), np.nan)
    has = np.zeros((N, 4, 2), dtype=bool)
    pts = np.full((N, 4, 3), np.nan)
    u[fr.k, fr.leg, fr.rod] = fr.u
    Cr[fr.k, fr.leg, fr.rod] = fr.cov_u
    Co[fr.k, fr.leg, fr.rod] = fr.cov_u_own
    has[fr.k, fr.leg, fr.rod] = True
    U, CU, _ = pair_means(u, has, Cr)
    has_leg = np.asarray(has.any(axis=2))
    for k, i, j in zip(fr.k, fr.leg, fr.rod, strict=True):
        if np.isnan(pts[k, i, 0]):
            pts[k, i] = fr.point[(fr.k == k) & (fr.leg == i) & (fr.rod == j)][0]
    return LegsFitDirections(fr, u, Cr, Co, has, U, CU, has_leg, pts)


def predict_legs_images(
    nominal: I4Parameters,
    q_fit: np.ndarray,
    q_lock: list[np.ndarray],
    scene: Scene,
    noise: ImageNoise,
    intrinsics_cov: np.ndarray | None = None,
    edge_cov_px2: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Predicted covariances of the legs method on images: seven parameters (7, 7), four combinations (4, 4), and
    the seven's parts (``joint_centres``, ``joint_depth_systematic``, ``leg_directions``, ``intrinsics``,
    ``limb_edge_bias``, ``a_priori``).
    ``edge_cov_px2`` (2, 2): the limb-edge bias's covariance the method uses, the combined fit's measurement of it
    (:func:`predict_combined_images_posteriors`; the method's default); None: the allowance
    (``edge_bias_prior_px`` per limb).

    Parameters
    ----------
    nominal : I4Parameters
        The geometry the model is linearised at (metres).
    q_fit : ndarray, shape (N, 4)
        Actuator values of the fit poses, metres.
    q_lock : list of 4 ndarrays, shape (n_i, 4)
        Actuator values of the ``lock-1`` .. ``lock-4`` phases, metres.
    scene : Scene
        The camera, its mounting and the rods.
    noise : ImageNoise
        The extraction's and the camera's noise levels.
    intrinsics_cov : ndarray, shape (n, n), optional
        The camera's covariance the method uses (default: ``noise``'s).
    edge_cov_px2 : ndarray, shape (2, 2), optional
        The limb-edge biases' covariance, px^2.

    Returns
    -------
    cov7 : ndarray, shape (7, 7)
        Covariance of the seven parameters, m^2.
    cov4 : ndarray, shape (4, 4)
        Covariance of the four combinations, m^2.
    parts : dict of str to ndarray, shape (7, 7)
        The seven's parts (m^2), adding up to ``cov7``.

    Raises
    ------
    IdentifiabilityError
        The lock phases or the fit poses do not determine the parameters.
    """
    from calib.identify.legs import (
        IntrinsicsEffect,
        LegsModel,
        joint_depth_systematic,
        joint_from_planes,
        null_space_to_prior,
        pair_means,
        pair_own_covariances,
        steps34_sandwich,
        with_prior,
    )

    lk = legs_lock_joints(nominal, q_lock, scene, noise)
    q_locked, planes, lock_fields, P, covP = lk.q_locked, lk.planes, lk.lock_fields, lk.P, lk.covP
    q_fit = np.asarray(q_fit, dtype=np.float64).reshape(-1, 4)
    fd = legs_fit_directions(nominal, q_fit, scene, noise)
    fr, u, Cr, Co, has, U, CU, has_leg, pts = (
        fd.rods,
        fd.u,
        fd.cov_u,
        fd.cov_u_own,
        fd.has,
        fd.U,
        fd.CU,
        fd.has_leg,
        fd.pts,
    )
    pipe = LegsModel(q_locked, q_fit, pts, has_leg, CU, nominal)
    Uf = np.where(has_leg[..., None], U, 0.0)
    seven = pipe.run(P, Uf)
    x2 = np.array([*seven[1:4].tolist(), seven[0]])
    GP = central_jacobian(lambda p: pipe.run(p.reshape(4, 2, 3), Uf, x2), P.ravel(), 1e-7)  # (7, 24)
    covJ = noise.legs_lock_chi2 * covP
    CU_own = np.nan_to_num(pair_own_covariances(u, has, Cr, Co))
    c34, _chi, _expected = steps34_sandwich(pipe, P, Uf, seven, CU_own, covJ)
    # the method scales both by its residuals' chi-square level; the prediction by their levels on the twin
    parts = {"joint_centres": GP @ covJ @ GP.T, "leg_directions": np.zeros((7, 7))}
    if noise.legs_joint_depth_sys_m > 0:
        sys_cov = joint_depth_systematic(P, noise.legs_joint_depth_sys_m, noise.legs_joint_depth_sys_leg_share)
        parts["joint_depth_systematic"] = GP @ sys_cov @ GP.T
    idx = np.array([6, 4, 5])
    # the extracted rods' covariances are larger than the synthetic ones (``legs_rod_cov_ratio``)
    parts["leg_directions"][np.ix_(idx, idx)] = noise.legs_directions_chi2 * noise.legs_rod_cov_ratio * c34
    parts["intrinsics"] = np.zeros((7, 7))
    parts["limb_edge_bias"] = np.zeros((7, 7))
    cov_i = noise.covariance() if intrinsics_cov is None else intrinsics_cov
    steps = _steps(cov_i, len(noise.intrinsics_names))
    if steps.shape[0] or noise.edge_bias_prior_px > 0:
        cam = design_camera(scene.camera, noise.intrinsics_names)
        idx_fit = (fr.k, fr.leg, fr.rod)
        eff = IntrinsicsEffect(cam, steps, lock_fields, idx_fit, fr.limbs_px, fr.h)
        rod_u = u  # NaN where a rod is not measured, as the method passes them (a zero would flip its pair)

        def seven_for(z: np.ndarray) -> np.ndarray:
            pz = eff.lock_planes(z, planes)
            Pz = np.array([[joint_from_planes(pz[i][j])[0] for j in range(2)] for i in range(4)])
            Uz = pair_means(eff.rod_u(z, rod_u), has, Cr)[0]
            return pipe.run(Pz, np.where(pipe.has_leg[..., None], Uz, 0.0), x2)

        nz = steps.shape[0]
        E = np.zeros((nz + 2, nz + 2))
        E[:nz, :nz] = np.eye(nz)
        E[nz:, nz:] = noise.edge_bias_prior_px * np.eye(2)
        Jz = np.stack([(seven_for(e) - seven_for(-e)) / 2.0 for e in E], axis=1)
        parts["intrinsics"] = Jz[:, :nz] @ Jz[:, :nz].T
        if edge_cov_px2 is not None and noise.edge_bias_prior_px > 0:
            J_px = Jz[:, nz:] / noise.edge_bias_prior_px
            parts["limb_edge_bias"] = J_px @ np.asarray(edge_cov_px2, dtype=np.float64) @ J_px.T
        else:
            parts["limb_edge_bias"] = Jz[:, nz:] @ Jz[:, nz:].T
    cov7 = np.sum(np.stack(list(parts.values())), axis=0)
    if noise.legs_prior_std_m:
        _s, cov7, parts = with_prior(seven, cov7, parts, nominal, noise.legs_prior_std_m)
        # as the method: the directions the four combinations do not see are the a priori values on images
        _s, cov7, parts, _dirs = null_space_to_prior(_s, parts, nominal, noise.legs_prior_std_m)
    return cov7, SEVEN_TO_FOUR @ cov7 @ SEVEN_TO_FOUR.T, parts
