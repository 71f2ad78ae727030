"""The rods' prediction refitted to what the first pass measured (a bench whose geometry is far from nominal).

The rods are looked for near their prediction: the *nominal* model at the encoder values and the coarse
``camera_from_base`` (:mod:`.placement`). On a bench whose geometry is some 15 mm off nominal, that prediction is
20-30 px off, beyond the search band: rods are lost, or another edge pair (the other rod of the leg, the gap) is
taken for them. The first pass still measures most rods, and every board pose. This module fits the seven
parameters, ``camera_from_base`` and ``ee_from_board`` to them (robust least squares, a weak prior towards the
nominal model), so that a second pass can look where the rods are.

The refit only decides where to look: the rods are then measured from the image edges as in the first pass, and
the calibration uses those measurements only. Its units: pixels (the camera's focal length times the angles).

When the first prediction is off by about half the rods' image spacing, most of what the first pass measured is not
the rod it was looking for: the leg's other rod, or the gap between the leg's two rods (a dark band as wide as a rod,
taken for a rod of the other polarity, then the frame's polarity voted wrong). A fit that takes every line for its own
rod then settles on a wrong geometry, tens of millimetres off, that explains those lines.
:func:`refit_prediction` with ``mixture=True`` lets each line be any of the three (:data:`HYPOTHESES`: whichever the
geometry explains best), and with ``starts`` tries that many more starting points drawn around the nominal model:
the true geometry explains every line, a wrong one does not, and the lowest cost wins.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calib.errors import I4calError
from calib.model.kinematics import base_from_ee
from calib.model.parameters import PARAMETER_NAMES, I4Parameters
from calib.numerics.transforms import Rigid, matrix_to_rotvec, rotvec_to_matrix
from calib.vision.rods.types import rod_ends_camera

Array = NDArray[np.float64]

#: the board's rotation residual is weighed as the displacement of a point this far from its centre (metres)
BOARD_ARM_M = 0.05
#: residuals beyond this (px) count less and less (soft-L1): rods the first pass took for another edge pair
ROBUST_SCALE_PX = 2.0
#: what a line measured for a rod may be, with ``mixture=True``: that rod, its leg's other rod, the gap between them
HYPOTHESES = ("own", "other_rod", "gap")
#: the extra starting points of ``refit_prediction(starts=...)``: the nominal parameters plus a normal draw of this std
#: (metres; a bench's geometry is within a few centimetres of its drawings)
START_SPREAD_M = 0.012


@dataclass
class MeasuredRod:
    """One rod measured in the first pass: frame index into the refit's arrays, leg, rod, its axis (camera frame)."""

    frame: int
    leg: int
    rod: int
    point: Array
    u: Array


@dataclass
class Repredicted:
    """The refitted prediction and its evidence.

    Attributes
    ----------
    parameters : I4Parameters
        The seven parameters that predict the rods (metres).
    camera_from_base, ee_from_board : Rigid
    median_px_before, median_px_after : float
        Median distance (px) of the measured rods' axes from the prediction's rod ends, with the first prediction
        and with the refitted one.
    rods, boards : int
        Measurements used.
    """

    parameters: I4Parameters
    camera_from_base: Rigid
    ee_from_board: Rigid
    median_px_before: float
    median_px_after: float
    rods: int
    boards: int
    shift_m: dict[str, float] = field(default_factory=dict)
    #: with ``mixture``: how many measured lines the refit explains as each of :data:`HYPOTHESES`
    hypotheses: dict[str, int] | None = None
    #: starting points tried (1 without ``starts``)
    starts: int = 1

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "rods": self.rods,
            "boards": self.boards,
            "median_px_before": self.median_px_before,
            "median_px_after": self.median_px_after,
            "parameters_shift_mm": {k: v * 1e3 for k, v in self.shift_m.items()},
        }
        if self.hypotheses is not None:
            out["lines_explained_as"] = self.hypotheses
            out["starts"] = self.starts
        return out


def _vector(params: I4Parameters, C: Rigid, E: Rigid) -> Array:
    return np.concatenate([params.vector(), matrix_to_rotvec(C.R), C.t, matrix_to_rotvec(E.R), E.t[:2]]).astype(
        np.float64
    )


def _unpack(x: Array, T_per_rad: float, board_height_m: float) -> tuple[I4Parameters, Rigid, Rigid]:
    p = I4Parameters.from_vector(x[:7], T_per_rad=T_per_rad)
    C = Rigid(rotvec_to_matrix(x[7:10]), np.asarray(x[10:13], dtype=np.float64))
    E = Rigid(rotvec_to_matrix(x[13:16]), np.array([x[16], x[17], board_height_m]))
    return p, C, E


def _residuals(
    x: Array,
    q: Array,
    rods: tuple[Array, Array, Array, Array],
    boards: tuple[Array, Array, Array],
    f_px: float,
    nominal: I4Parameters,
    prior_m: float,
    rod_spacing_m: float,
    board_height_m: float,
    mixture: bool = False,
) -> Array:
    """Residuals (px): two per rod, six per board, seven for the prior. ``rods``: frame, leg, rod indices (M,) and
    the unit normals (M, 3) of the planes through the camera centre and the measured axes; ``boards``: frame
    indices (B,), measured rotations (B, 3, 3) and translations (B, 3). ``mixture``: each rod's pair is that of the
    hypothesis (:data:`HYPOTHESES`) the parameters explain best."""
    k = rods[0]
    bk, bR, bt = boards
    n_out = 2 * len(k) + 6 * len(bk) + 7
    try:
        params, C, E = _unpack(x, nominal.T_per_rad, board_height_m)
        top, bottom, pose = rod_ends_camera(params, q, C, rod_spacing_m)
    except (I4calError, ValueError):  # a geometry that cannot close, or a negative length
        return np.full(n_out, 1e3)
    out = np.empty(n_out)
    pairs = _rod_pairs(top, bottom, rods, f_px, mixture)
    out[: 2 * len(k)] = pairs[np.arange(len(k)), _best_hypothesis(pairs)].reshape(-1) if mixture else pairs.reshape(-1)
    o = 2 * len(k)
    RB, tB = base_from_ee(params, pose[bk])  # (B, 3, 3), (B, 3)
    Rp = np.einsum("ij,bjk,kl->bil", C.R, RB, E.R)
    tp = (np.einsum("bij,j->bi", RB, E.t) + tB) @ C.R.T + C.t
    scale = f_px / np.maximum(bt[:, 2], 0.05)
    res = np.empty((len(bk), 6))
    res[:, :3] = scale[:, None] * (tp - bt)
    res[:, 3:] = (scale * BOARD_ARM_M)[:, None] * matrix_to_rotvec(Rp @ np.transpose(bR, (0, 2, 1)))
    out[o : o + 6 * len(bk)] = res.reshape(-1)
    out[o + 6 * len(bk) :] = (np.asarray(params.vector()) - np.asarray(nominal.vector())) / prior_m
    return out


def _rod_pairs(top: Array, bottom: Array, rods: tuple[Array, Array, Array, Array], f_px: float, mixture: bool) -> Array:
    """Each measured rod's two residuals (px): the angles of the predicted ends from the plane through the camera
    centre and the measured axis. Shape (M, 2) for its own rod; (M, 3, 2) over :data:`HYPOTHESES` with
    ``mixture``."""
    k, i, j, n = rods

    def pair(T: Array, B: Array) -> Array:
        return np.stack([f_px * np.einsum("md,md->m", n, X) / np.linalg.norm(X, axis=1) for X in (T, B)], axis=-1)

    own = pair(top[k, i, j], bottom[k, i, j])
    if not mixture:
        return own
    other = pair(top[k, i, 1 - j], bottom[k, i, 1 - j])
    gap = pair(0.5 * (top[k, i, 0] + top[k, i, 1]), 0.5 * (bottom[k, i, 0] + bottom[k, i, 1]))
    return np.stack([own, other, gap], axis=1)


def _best_hypothesis(pairs: Array) -> NDArray[np.int_]:
    """Per rod, the index into :data:`HYPOTHESES` of the pair (M, 3, 2) with the smallest largest residual."""
    return np.argmin(np.abs(pairs).max(axis=2), axis=1)


def refit_prediction(
    nominal: I4Parameters,
    q: Array,
    rods: list[MeasuredRod],
    boards: dict[int, Rigid],
    camera_from_base: Rigid,
    ee_from_board: Rigid,
    f_px: float,
    rod_spacing_m: float,
    board_height_m: float = 0.0,
    prior_m: float = 0.02,
    start: I4Parameters | None = None,
    mixture: bool = False,
    starts: int = 0,
    seed: int = 0,
) -> Repredicted | None:
    """Fit the seven parameters, ``camera_from_base`` and ``ee_from_board`` to the first pass's measurements.

    Parameters
    ----------
    nominal : I4Parameters
        The model the first pass predicted with; the prior's centre.
    q : ndarray, shape (N, 4)
        Encoder values (metres) of the frames the measurements index.
    rods : list of MeasuredRod
        Rod axes measured by the first pass (camera frame, metres), indexed into ``q``.
    boards : dict
        Frame index -> measured ``camera_from_board``.
    camera_from_base, ee_from_board : Rigid
        The coarse placement (:func:`.placement.fit_placement`): the starting point.
    f_px : float
        Focal length (px): angles to pixels.
    rod_spacing_m : float
        Distance between the axes of a leg's two rods (metres).
    board_height_m : float
        Height of the board's origin above E (fixed, as in the coarse placement).
    prior_m : float
        Each parameter's prior std around nominal (metres): a soft pull in directions the measurements leave free.
    start : I4Parameters, optional
        The seven parameters the first pass predicted with, when not ``nominal`` (with ``camera_from_base`` and
        ``ee_from_board``: the starting point and the "before" of the figures).
    mixture : bool
        Let each measured line be its own rod, its leg's other rod or the gap between them (:data:`HYPOTHESES`,
        whichever the geometry explains best) instead of its own rod only.
    starts : int
        Further starting points: the nominal parameters plus a normal draw of std :data:`START_SPREAD_M` (seeded
        by ``seed``), each with ``camera_from_base`` and ``ee_from_board``; the fit of lowest cost is kept.
    seed : int
        Seed of the draw of the further starting points.

    Returns
    -------
    Repredicted or None
        None when there is too little to fit (fewer than 8 rods) or the fit does not bring the rods closer to
        the prediction.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    if len(rods) < 8:
        return None
    normals = np.cross([m.point for m in rods], [m.u for m in rods])
    packed = (
        np.array([m.frame for m in rods]),
        np.array([m.leg for m in rods]),
        np.array([m.rod for m in rods]),
        normals / np.linalg.norm(normals, axis=1, keepdims=True),
    )
    bk = np.array(sorted(boards), dtype=int)
    pb = (bk, np.array([boards[b].R for b in bk]).reshape(-1, 3, 3), np.array([boards[b].t for b in bk]).reshape(-1, 3))
    args = (q, packed, pb, float(f_px), nominal, prior_m, rod_spacing_m, board_height_m, mixture)
    x0 = _vector(start or nominal, camera_from_base, ee_from_board)
    r0 = _residuals(x0, *args)
    rng = np.random.default_rng(seed)
    firsts = [x0]
    for _ in range(starts):
        x = x0.copy()
        x[:7] = np.asarray(nominal.vector()) + rng.normal(0.0, START_SPREAD_M, 7)
        firsts.append(x)
    sol = None
    for x in firsts:
        s = least_squares(
            _residuals, x, args=args, loss="soft_l1", f_scale=ROBUST_SCALE_PX, x_scale="jac", method="trf", max_nfev=200
        )
        if np.all(np.isfinite(s.x)) and (sol is None or s.cost < sol.cost):
            sol = s
    n_rod = 2 * len(rods)

    def per_rod(r: Array) -> Array:
        return np.abs(r[:n_rod]).reshape(-1, 2).max(axis=1)

    before = float(np.median(per_rod(r0)))
    after = float(np.median(per_rod(sol.fun))) if sol is not None else np.inf
    if sol is None or after >= before:
        return None
    params, C, E = _unpack(sol.x, nominal.T_per_rad, board_height_m)
    shift = {n: float(a - b) for n, a, b in zip(PARAMETER_NAMES, params.vector(), nominal.vector(), strict=True)}
    out = Repredicted(params, C, E, before, after, len(rods), len(boards), shift)
    if mixture:
        top, bottom, _ = rod_ends_camera(params, q, C, rod_spacing_m)
        best = _best_hypothesis(_rod_pairs(top, bottom, packed, float(f_px), True))
        out.hypotheses = {h: int(np.count_nonzero(best == e)) for e, h in enumerate(HYPOTHESES)}
        out.starts = len(firsts)
    return out


def prediction_shift_px(
    K: Array, size: tuple[int, int], first: tuple[Array, Array], second: tuple[Array, Array], near_m: float = 0.05
) -> Array:
    """Per frame, how far (ideal px) a second prediction of the rods moves them where they are seen.

    Per rod, the median over 41 points along it (those in front of the camera that both predictions put inside
    the image) of the distance between their two images: the rods reach close to the camera, where a millimetre
    moves the image by tens of pixels over a short stretch, so the median, not the maximum.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix (px).
    size : (width, height)
        The image (px).
    first, second : tuple of ndarray, shape (N, 4, 2, 3) each
        ``(top, bottom)`` rod ends in the camera frame (metres; :func:`rod_ends_camera`).
    near_m : float
        Points of a rod closer to the camera than this depth (metres) are left out.

    Returns
    -------
    ndarray, shape (N,)
        The largest of the frame's rods' medians; 0 where no rod is seen.
    """
    w, h = size
    s = np.linspace(0.0, 1.0, 41)[:, None, None, None, None]
    a = first[0][None] + s * (first[1] - first[0])[None]  # (41, N, 4, 2, 3)
    b = second[0][None] + s * (second[1] - second[0])[None]
    ok = (a[..., 2] > near_m) & (b[..., 2] > near_m)
    pa = (a @ K.T)[..., :2] / np.where(ok, a[..., 2], 1.0)[..., None]
    pb = (b @ K.T)[..., :2] / np.where(ok, b[..., 2], 1.0)[..., None]
    for p in (pa, pb):
        ok &= (p[..., 0] >= 0) & (p[..., 0] <= w) & (p[..., 1] >= 0) & (p[..., 1] <= h)
    d = np.where(ok, np.linalg.norm(pa - pb, axis=-1), np.nan)
    seen = ok.any(axis=0)
    med = np.zeros(seen.shape)
    med[seen] = np.nanmedian(d[:, seen], axis=0)
    return med.reshape(len(med), -1).max(axis=1)
