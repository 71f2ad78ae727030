"""Rendered datasets: the image-level twin writes a dataset v1 with the truth alongside."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from calib.formats.dataset import CameraSpec, DatasetWriter, LegsSpec
from calib.formats.plan import Plan, make_plan
from drivers.sim.render import BenchRenderer, RenderSettings
from drivers.sim.twin import BenchGeometry, GeometricTwin


def simulate_dataset(
    out_dir: str | Path,
    *,
    seed: int = 0,
    geometry: BenchGeometry | None = None,
    render: RenderSettings | None = None,
    plan: Plan | None = None,
    n_camera_views: int = 15,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a plan into a dataset v1 directory (``camera`` phase first), with the truth alongside.

    Parameters
    ----------
    out_dir : path
        Created if needed; an existing dataset there is overwritten.
    seed : int
        Seeds the plan (when not given), the renderer (background, board error, noise) and the
        camera-phase views.
    geometry : BenchGeometry, optional
        The true bench (default: the twin's default).
    render : RenderSettings, optional
    plan : Plan, optional
        Default: ``make_plan('full', geometry.nominal, seed)``.
    n_camera_views : int
        Board views for intrinsic calibration (every corner visible), 0 for none.
    progress : callable(done, total), optional

    Returns
    -------
    Path
        The dataset directory. ``dataset.json`` holds a top-level ``truth``: the true parameters,
        ``camera_from_base``, ``ee_from_board``, true ``K``/``dist``, the true board corners; and
        each frame a ``truth`` with the true ``q`` and ``pose`` (and ``camera_from_board`` for the
        camera phase). The dataset's ``camera`` has no K/dist: they are to be calibrated.
    """
    g = geometry or BenchGeometry()
    rs = render or RenderSettings()
    plan = plan or make_plan("full", g.nominal, seed=seed)
    renderer = BenchRenderer(g, rs, seed=seed)
    twin = GeometricTwin(g)
    steps = twin.true_poses(plan)
    rng = np.random.default_rng([seed, 7])
    views = renderer.random_board_views(n_camera_views, rng) if n_camera_views else []
    cam = renderer.camera
    truth = twin.truth_dict()
    truth.update(
        {
            "K": cam.K.tolist(),
            "dist": cam.dist.tolist(),
            "board_points_true": renderer.board_points_true.tolist(),
            "board_points_nominal": renderer.board_points_nominal.tolist(),
            "render": {k: (v.model_dump() if hasattr(v, "model_dump") else v) for k, v in rs.__dict__.items()},
        }
    )
    # what a ruler says: the board origin's height above the end-effector point, to 5 mm
    board_spec = rs.board.model_copy(update={"height_above_ee_m": round(float(g.ee_from_board.t[2]) / 0.005) * 0.005})
    out = Path(out_dir)
    w = DatasetWriter(
        out,
        camera=CameraSpec(width=rs.width, height=rs.height, pixel_size_m=4.65e-6),
        board=board_spec,
        legs=LegsSpec(rod_radius_m=g.rod_radius_m, rods_per_leg=2, rod_spacing_m=g.rod_spacing_m),
        nominal=g.nominal.as_dict(),
        extra={"truth": truth, "generator": {"name": "i4cal image twin", "seed": seed, "plan": plan.name}},
    )
    total = len(views) + len(steps)
    noise_rng = np.random.default_rng([seed, 11])
    t = 0.0
    k = 0
    for v in views:
        img = renderer.render_board_view(v, noise_rng)
        w.add_frame("camera", np.zeros(4), img, t=t, truth={"camera_from_board": v.to_dict()})
        t += 0.5
        k += 1
        if progress:
            progress(k, total)
    for phase, q, pose in steps:
        img = renderer.render(q, pose, noise_rng)
        w.add_frame(phase, q, img, t=t, truth={"q": q.tolist(), "pose": pose.tolist()})
        t += 1.0
        k += 1
        if progress:
            progress(k, total)
    w.close()
    return out
