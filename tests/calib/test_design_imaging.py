"""The vectorised ``synthetic_rods`` (every rod of every frame at once) and the batched direction covariance give the
per-rod implementation's results to rounding, on the simulated bench's scene, in a fraction of its time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib.design.imaging import RodSet, synthetic_rods
from calib.design.scene import Scene, rod_segments, visibility
from calib.errors import InputError
from calib.formats.plan import make_plan
from calib.model.kinematics import dkm
from calib.model.parameters import NOMINAL, I4Parameters
from calib.vision.rods import _direction_covariance, limb_planes
from calib.vision.rods.covariance import _direction_covariances
from service.design import twin_scene

#: where along a limb's span the extraction reports its line: the means of five equal-count bins of evenly spread
#: edge points (calib.vision.rods.measure._limb_samples; as in calib.design.imaging)
_BIN_MEANS = np.array([0.1, 0.3, 0.5, 0.7, 0.9])

#: the direction covariance is a central difference with steps of 1e-6 rad and 1e-3 px: a rounding of its inputs
#: (~1e-16 relative) moves it by ~1e-16 / 1e-6 = 1e-10 of its size; ``test_direction_covariances_...`` measures that
#: floor on the per-rod function itself. The other fields are rounding-exact up to a few ulps.
RTOL = 1e-12


def _synthetic_rods_reference(
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
    """The per-rod ``synthetic_rods`` (one rod at a time, the vectorised one's reference), with ``cov_u_own`` (the
    allowance averaged over ``edge_bias_length_px``) added: the reference."""
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
    fields: dict[str, list] = {
        f: []
        for f in ("k", "leg", "rod", "u", "point", "h", "cov_u", "cov_u_own", "limbs_px", "n_points", "visible_px")
    }
    for k, i, j in zip(*np.nonzero(v["rod_px"] >= min_length_px), strict=True):
        vis = v["rod_visible"][k, i, j]
        X = top[k, i, j] + s[vis, None] * (bot[k, i, j] - top[k, i, j])
        u = bot[k, i, j] - top[k, i, j]
        u /= np.linalg.norm(u)
        P = X[len(X) // 2]
        try:
            h = np.array(limb_planes(P, u, scene.rod_radius_m))
        except ValueError:
            continue
        xi = X @ K.T
        xi = xi[:, :2] / xi[:, 2:]
        fits = []
        limbs = []
        npts = []
        for hq in h:
            line = Kinv.T @ hq
            line = line / np.linalg.norm(line[:2])
            n = line[:2]
            td = np.array([n[1], -n[0]])
            foot = xi - (xi @ n + line[2])[:, None] * n
            t = foot @ td
            t0, t1 = float(t.min()), float(t.max())
            m = max(int(np.floor((t1 - t0) / step_px)) + 1, 3)
            tt = np.linspace(t0, t1, m)
            base = foot[0] - (foot[0] @ td) * td
            pts = base + tt[:, None] * td
            fits.append((pts.mean(axis=0), td, edge_px**2, pts))
            q5 = base + (t0 + _BIN_MEANS * (t1 - t0))[:, None] * td
            limbs.append(cam.distort_normalized(np.c_[q5, np.ones(5)] @ Kinv.T[:, :2]))
            npts.append(m)
        cmid = 0.5 * (fits[0][0] + fits[1][0])
        inner = Kinv @ np.append(cmid, 1.0)
        # the point is the axis point seen at the limbs' image middle, as the extraction reports it
        ray = inner / np.linalg.norm(inner)
        w = u - (u @ ray) * ray
        P = P - ((P @ w) / float(w @ w)) * u
        fields["k"].append(k)
        fields["leg"].append(i)
        fields["rod"].append(j)
        fields["u"].append(u)
        fields["point"].append(P)
        fields["h"].append(h)
        fields["cov_u"].append(_direction_covariance(K, fits, inner, edge_bias_px))
        fields["cov_u_own"].append(_direction_covariance(K, fits, inner, edge_bias_px, edge_bias_length_px))
        fields["limbs_px"].append(np.stack(limbs))
        fields["n_points"].append(npts)
        fields["visible_px"].append(v["rod_px"][k, i, j])
    shapes = {
        "u": (0, 3),
        "point": (0, 3),
        "h": (0, 2, 3),
        "cov_u": (0, 3, 3),
        "cov_u_own": (0, 3, 3),
        "limbs_px": (0, 2, 5, 2),
    }
    out = {
        f: (np.asarray(val) if val else np.zeros(shapes.get(f, (0,)) if f != "n_points" else (0, 2)))
        for f, val in fields.items()
    }
    for f in ("k", "leg", "rod", "n_points"):
        out[f] = out[f].astype(int)
    return RodSet(**out)


def _assert_same_rods(new: RodSet, ref: RodSet, cov_rtol: float) -> None:
    """Same rods in the same (frame, leg, rod) order, same counts; the float fields equal to ``RTOL`` of their scale
    (a rod's vector, covariance or image size: components near zero carry the rounding of the others)."""
    assert len(ref) > 0
    for f in RodSet.__dataclass_fields__:
        a, b = getattr(new, f), getattr(ref, f)
        assert a.shape == b.shape, (f, a.shape, b.shape)
        assert a.dtype.kind == b.dtype.kind, (f, a.dtype, b.dtype)
    for f in ("k", "leg", "rod", "n_points"):
        np.testing.assert_array_equal(getattr(new, f), getattr(ref, f), err_msg=f)
    for f, scale in (("u", 1.0), ("point", np.abs(ref.point).max()), ("h", 1.0), ("visible_px", ref.visible_px.max())):
        np.testing.assert_allclose(getattr(new, f), getattr(ref, f), rtol=RTOL, atol=RTOL * scale, err_msg=f)
    size = float(np.abs(ref.limbs_px).max())
    np.testing.assert_allclose(new.limbs_px, ref.limbs_px, rtol=RTOL, atol=RTOL * size, err_msg="limbs_px")
    for f in ("cov_u", "cov_u_own"):
        a, b = getattr(new, f), getattr(ref, f)
        cov_scale = np.abs(b).max(axis=(1, 2), keepdims=True)  # per rod
        assert np.all(np.abs(a - b) <= cov_rtol * cov_scale), (f, np.max(np.abs(a - b) / cov_scale))


@pytest.fixture(scope="module")
def scene() -> Scene:
    return twin_scene()


@pytest.fixture(scope="module")
def poses() -> np.ndarray:
    """The joint values of a full paper plan with 200 fit poses: 250 frames (sweeps, fit, lock, validation poses),
    rods whole, cut by the image border and hidden by the board or each other."""
    plan = make_plan("full", NOMINAL, seed=0, n_fit=200)
    return np.array([s.q for s in plan.steps if s.q is not None])


def _fits(rng: np.random.Generator, M: int) -> tuple[list, np.ndarray, np.ndarray]:
    """M random rods' limb fits (c, td, s2, pts) as the extraction makes them (scattered edge points along a line
    across a 1280 x 1024 image), the camera matrix and each rod's ``inner`` direction."""
    K = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 512.0], [0.0, 0.0, 1.0]])
    fits, inner = [], []
    for _ in range(M):
        centre = rng.uniform([200, 150], [1080, 870])
        ang = rng.uniform(0, np.pi)
        rod = []
        for side in (-1.0, 1.0):
            td = np.array([np.cos(ang + side * 0.01), np.sin(ang + side * 0.01)])
            n = np.array([td[1], -td[0]])
            t = np.sort(rng.uniform(-300, 300, rng.integers(3, 200)))
            pts = centre + side * 12.0 * n + t[:, None] * td + rng.normal(0, 0.3, (len(t), 1)) * n
            rod.append((pts.mean(axis=0), td, float(rng.uniform(0.05, 0.2)), pts))
        fits.append(rod)
        inner.append(np.linalg.solve(K, np.append(centre, 1.0)))
    return fits, K, np.array(inner)


def test_direction_covariances_equal_the_per_rod_function():
    """The batched covariance of 200 random rods equals the per-rod function's, within its own rounding floor: the
    largest change of a per-rod covariance when its centroids move by one ulp (the central differences amplify
    rounding ~1e6 times), times 10."""
    rng = np.random.default_rng(11)
    fits, K, inner = _fits(rng, 200)
    ref = np.stack([_direction_covariance(K, f, inner[a], 0.05) for a, f in enumerate(fits)])
    nudged = np.stack(
        [
            _direction_covariance(K, [(np.nextafter(c, np.inf), td, s2, p) for c, td, s2, p in f], inner[a], 0.05)
            for a, f in enumerate(fits)
        ]
    )
    scale = np.abs(ref).max(axis=(1, 2), keepdims=True)
    floor = float(np.max(np.abs(nudged - ref) / scale))
    assert 0 < floor < 1e-8, floor
    t = [[(p - c) @ td for c, td, _s2, p in f] for f in fits]
    new = _direction_covariances(
        K,
        np.array([[c for c, *_ in f] for f in fits]),
        np.array([[td for _c, td, *_ in f] for f in fits]),
        np.array([[s2 for _c, _td, s2, _p in f] for f in fits]),
        np.array([[len(p) for *_, p in f] for f in fits]),
        np.array([[tj @ tj for tj in ti] for ti in t]),
        np.array([[np.ptp(tj) for tj in ti] for ti in t]),
        inner,
        0.05,
    )
    assert new.shape == (200, 3, 3)
    dev = float(np.max(np.abs(new - ref) / scale))
    print(f"batched vs per-rod: {dev:.2e} of the covariance; the per-rod function's one-ulp floor {floor:.2e}")
    assert dev <= 10 * floor, (dev, floor)


def test_synthetic_rods_equal_the_per_rod_reference(scene, poses):
    """On the simulated bench's scene, 250 frames of a full plan: the same rods in the same order with the same
    edge-point counts, their directions, points, planes, limb samples and visible lengths to 1e-12, their direction
    covariances to the central difference's rounding floor (1e-8 of their size: the per-rod one's is ~1e-10). (Its
    speed, ~7x less CPU than the per-rod loop, is a benchmark's figure, not asserted here: the machines are shared.)"""
    ref = _synthetic_rods_reference(scene, NOMINAL, poses, 0.3)
    new = synthetic_rods(scene, NOMINAL, poses, 0.3)
    assert len(ref) > 1500  # most of the 250 x 8 rods are measured
    assert len(set(ref.k.tolist())) == len(poses)
    _assert_same_rods(new, ref, cov_rtol=1e-8)
    # other options: finer edge points, no edge bias, a longer minimum length (some rods dropped)
    kw = {"step_px": 1.5, "edge_bias_px": 0.0, "min_length_px": 400.0}
    ref2 = _synthetic_rods_reference(scene, NOMINAL, poses[:60], 0.2, **kw)
    assert 0 < len(ref2) < 60 * 8
    _assert_same_rods(synthetic_rods(scene, NOMINAL, poses[:60], 0.2, **kw), ref2, cov_rtol=1e-8)


def test_synthetic_rods_drop_the_rods_around_the_camera_like_the_per_rod_one(scene, poses):
    """Rods so thick that the camera centre lies inside some of them (``limb_planes`` raises ValueError): those are
    left out, the others kept, as the per-rod loop did; none measured: empty fields of the documented shapes."""
    thick = dataclasses.replace(scene, rod_radius_m=0.5)
    ref = _synthetic_rods_reference(thick, NOMINAL, poses[:40], 0.3)
    v = visibility(thick, NOMINAL, poses[:40])
    assert 0 < len(ref) < np.count_nonzero(v["rod_px"] >= 40.0)  # some rods dropped by the planes, not visibility
    _assert_same_rods(synthetic_rods(thick, NOMINAL, poses[:40], 0.3), ref, cov_rtol=1e-8)
    empty = synthetic_rods(scene, NOMINAL, poses[:5], 0.3, min_length_px=1e9)
    old_empty = _synthetic_rods_reference(scene, NOMINAL, poses[:5], 0.3, min_length_px=1e9)
    assert len(empty) == 0
    for f in RodSet.__dataclass_fields__:
        assert getattr(empty, f).shape == getattr(old_empty, f).shape, f


def test_synthetic_rods_report_the_point_seen_at_the_limbs_middle(scene, poses):
    """Each rod's ``point`` is the axis point seen at the middle of its visible limbs, where the extraction reports
    it (``calib.vision.rods.measure``): the legs method pivots each limb line's noise about that point's foot
    (``limb_line_noise``). The 3-D middle of the visible axis samples would not do: perspective puts it off the
    image middle (on the simulated bench's lock phases by about 12% of the span, where extracted rods are within
    2%), and the prediction would weigh the lock planes 1.6-1.9x the method's."""
    rods = synthetic_rods(scene, NOMINAL, poses[:40], 0.08)
    K = scene.camera.K
    x = rods.point @ K.T
    seen = x[:, :2] / x[:, 2:]
    xn = scene.camera.undistort_points(rods.limbs_px.reshape(-1, 2)).reshape(rods.limbs_px.shape)
    ideal = xn @ K[:2, :2].T + K[:2, 2]  # (M, 2, 5, 2): the five limb samples at 0.1 .. 0.9 of each limb's span
    middle = ideal.mean(axis=(1, 2))
    span = np.linalg.norm(ideal[:, :, -1] - ideal[:, :, 0], axis=-1).mean(axis=1) / 0.8
    off = np.linalg.norm(seen - middle, axis=1) / span
    assert len(rods) > 200
    assert off.max() < 0.01, off.max()
    # and it is on the axis: its distance to the rod's axis line is zero
    top, _bot = rod_segments(scene, NOMINAL, poses[:40], dkm(NOMINAL, poses[:40]))
    a = top[rods.k, rods.leg, rods.rod]
    d = rods.point - a
    along = np.einsum("mi,mi->m", d, rods.u)[:, None] * rods.u
    assert np.abs(d - along).max() < 1e-12
