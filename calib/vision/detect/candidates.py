"""Detection steps 3-4: rod candidates (pairs of facing limb lines) and leg candidates (pairs of parallel rods)."""

from __future__ import annotations

import itertools
from typing import cast

import numpy as np
from numpy.typing import NDArray

from calib.formats.camera import CameraModel
from calib.numerics.transforms import cross
from calib.vision.detect.hypotheses import DetectSettings, LegCandidate, Line2, RodCandidate
from calib.vision.detect.rays import _line_point, _plane, _ray, _sample, _to_canvas

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
# 3. rods


def _inside_fraction(
    canvas: np.ndarray, scale: float, origin: Array, pa: list[Array], pb: list[Array], bright: bool, need: float
) -> float:
    """Fraction of 9 profiles across the span between two lines where the inside is brighter (darker)
    than both outsides by ``need`` grey levels: its darkest (brightest) of 5 samples against the
    brighter (darker) of the samples 3 px beyond each line (near enough to stay in a narrow gap
    between the two rods of a leg). ``pa``, ``pb``: each line's points at the span's ends (ideal px).
    """
    fr = np.linspace(0.05, 0.95, 9)
    A = pa[0][None] + fr[:, None] * (pa[1] - pa[0])[None]
    B = pb[0][None] + fr[:, None] * (pb[1] - pb[0])[None]
    across = B - A
    u = across / np.linalg.norm(across, axis=1)[:, None]
    inner = A[:, None] + np.linspace(0.2, 0.8, 5)[None, :, None] * across[:, None]
    Ii = _sample(canvas, _to_canvas(inner, scale, origin))
    Ia = _sample(canvas, _to_canvas(A - 3.0 * u, scale, origin))
    Ib = _sample(canvas, _to_canvas(B + 3.0 * u, scale, origin))
    if bright:
        margin = Ii.min(axis=1) - np.maximum(Ia, Ib)
    else:
        margin = np.minimum(Ia, Ib) - Ii.max(axis=1)
    return float(np.mean(margin > need))


def find_rods(
    lines: list[Line2],
    canvas: np.ndarray,
    scale: float,
    origin: Array,
    camera: CameraModel,
    radius: float,
    settings: DetectSettings,
) -> list[RodCandidate]:
    """Pairs of lines that bound a rod (see the module docstring, step 3).

    Parameters
    ----------
    lines : list of Line2
        Refined, merged edges (ideal px).
    canvas : ndarray, shape (h, w), float32
        The undistorted image (:func:`calib.vision.detect.segments.undistorted_canvas`).
    scale : float
        Canvas pixels per ideal pixel.
    origin : ndarray, shape (2,)
        Ideal pixel of canvas (0, 0) (px).
    camera : CameraModel
        Its focal length (px) turns the rod's diameter into image widths over ``settings.depth_range_m``.
    radius : float
        Rod radius (metres).
    settings : DetectSettings
        Thresholds of the detection.

    Returns
    -------
    list of RodCandidate
        Best score first; each line bounds at most one rod of each polarity.
    """
    f = camera.focal_px
    wmin = 2 * radius * f / settings.depth_range_m[1]
    wmax = 2 * radius * f / settings.depth_range_m[0]
    cands: list[tuple[float, int, int, RodCandidate]] = []
    K = camera.K
    K_inv = cast("Array", np.linalg.inv(K))  # float64 (numpy's stubs: any floating)
    if len(lines) < 2:
        return []
    T = np.array([ln.t for ln in lines])
    par = np.abs(T @ T.T) >= np.cos(settings.limb_angle_rad)
    for i, j in zip(*np.nonzero(np.triu(par, 1)), strict=True):
        i, j = int(i), int(j)
        a, b = lines[i], lines[j]
        # common direction (a's), extents of both on it
        t = a.t
        # 1-D @ 1-D: numpy float64 scalars (numpy's stubs type the product as an array)
        ea = cast("list[float]", sorted((a.point(a.s0) @ t, a.point(a.s1) @ t)))
        eb = cast("list[float]", sorted((b.point(b.s0) @ t, b.point(b.s1) @ t)))
        s0, s1 = max(ea[0], eb[0]), min(ea[1], eb[1])
        if s1 - s0 < settings.min_rod_px:
            continue
        pa = [_line_point(a, s0, t), _line_point(a, s1, t)]
        pb = [_line_point(b, s0, t), _line_point(b, s1, t)]
        wd = (float(np.linalg.norm(pb[0] - pa[0])), float(np.linalg.norm(pb[1] - pa[1])))
        if min(wd) < wmin or max(wd) > wmax:
            continue
        # facing: a's bright side towards b and b's towards a (bright rod), or both away (dark rod)
        mid_a, mid_b = 0.5 * (pa[0] + pa[1]), 0.5 * (pb[0] + pb[1])
        fa = a.n @ (mid_b - mid_a) > 0
        fb = b.n @ (mid_a - mid_b) > 0
        if fa != fb:
            continue
        bright = bool(fa)
        if (settings.polarity == "bright" and not bright) or (settings.polarity == "dark" and bright):
            continue
        inside = _inside_fraction(canvas, scale, origin, pa, pb, bright, 0.3 * min(a.contrast, b.contrast))
        if inside < 0.7:
            continue
        # limb lines as (a, b, c) with the axis on the positive side of their planes
        centre = (0.5 * (pa[0] + pb[0]), 0.5 * (pa[1] + pb[1]))
        cm = 0.5 * (centre[0] + centre[1])
        hs = []
        for ln in (a, b):
            h = _plane(K, np.array([ln.n[0], ln.n[1], ln.c]))
            if h @ _ray(K_inv, cm) < 0:
                h = -h
            hs.append(h)
        # the plane through the camera centre and the axis bisects the two limb planes
        m = hs[0] - hs[1]
        m = m / np.linalg.norm(m)
        rc = RodCandidate((a, b), s0, s1, t, wd, centre, bright, (hs[0], hs[1]), m)
        score = (s1 - s0) * inside * np.sqrt(np.mean(wd))
        cands.append((score, i, j, rc))
    # each line bounds at most one rod of each polarity (the inner limb of a bright rod also bounds
    # the dark gap between the two rods of its leg): best score first
    cands.sort(key=lambda x: -x[0])
    used: set[tuple[int, bool]] = set()
    out = []
    for _, i, j, rc in cands:
        if (i, rc.bright) in used or (j, rc.bright) in used:
            continue
        used.update(((i, rc.bright), (j, rc.bright)))
        out.append(rc)
    return out


# ---------------------------------------------------------------------------------------------
# 4. legs
def find_legs(rods: list[RodCandidate], radius: float, spacing: float, settings: DetectSettings) -> list[LegCandidate]:
    """Pairs of parallel rod candidates at the rod spacing (see the module docstring, step 4).

    Parameters
    ----------
    rods : list of RodCandidate
        From :func:`find_rods`.
    radius : float
        Rod radius (metres).
    spacing : float
        Distance between the axes of a leg's two rods (metres); only its ratio to the diameter is used.
    settings : DetectSettings
        Thresholds of the detection.

    Returns
    -------
    list of LegCandidate
    """
    out = []
    nominal_ratio = spacing / (2 * radius)
    lo, hi = settings.spacing_ratio_range
    for i, j in itertools.combinations(range(len(rods)), 2):
        a, b = rods[i], rods[j]
        if a.bright != b.bright or abs(a.t @ b.t) < np.cos(settings.leg_angle_rad):
            continue
        t = a.t
        # 1-D @ 1-D: numpy float64 scalars (numpy's stubs type the product as an array)
        ea = cast("list[float]", sorted((a.centre[0] @ t, a.centre[1] @ t)))
        eb = cast("list[float]", sorted((b.centre[0] @ t, b.centre[1] @ t)))
        s0, s1 = max(ea[0], eb[0]), min(ea[1], eb[1])
        if s1 - s0 < 0.3 * min(a.length, b.length):
            continue
        sm = 0.5 * (s0 + s1)
        nrm = np.array([-t[1], t[0]])

        def at(rc: RodCandidate, s: float, nrm=nrm, t=t) -> tuple[float, float]:
            c0, c1 = rc.centre
            s_0, s_1 = c0 @ t, c1 @ t
            f = (s - s_0) / (s_1 - s_0) if abs(s_1 - s_0) > 1e-9 else 0.5
            p = c0 + f * (c1 - c0)
            w = rc.width_px[0] + f * (rc.width_px[1] - rc.width_px[0])
            return float(p @ nrm), float(w)

        ka, wa = at(a, sm)
        kb, wb = at(b, sm)
        if max(wa, wb) > settings.leg_width_ratio * min(wa, wb) or min(wa, wb) <= 0:
            continue
        ratio = abs(ka - kb) / (0.5 * (wa + wb))
        if not lo * nominal_ratio <= ratio <= hi * nominal_ratio:
            continue
        d = cross(a.m, b.m)
        sn = float(np.linalg.norm(d))
        if sn < 1e-4:
            continue
        out.append(LegCandidate((i, j), d / sn, settings.centre_plane_sigma_rad / sn))
    return out
