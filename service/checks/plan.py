"""A bench's check plan: designed once (``calib.design.drift_check``) and kept in a cache keyed by what the design
depends on (the bench's nominal geometry, soft limits, speeds, camera file and mounting, and the request), or the
user's own."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from calib.errors import InputError

#: bumped when the check plan's design changes (a cached plan of an older design is not used)
DESIGN_VERSION = 1


def default_cache_dir() -> Path:
    """``$I4CAL_CACHE_DIR/check-plans``, else ``$XDG_CACHE_HOME/i4cal/check-plans``, else ``~/.cache/...``."""
    root = os.environ.get("I4CAL_CACHE_DIR")
    if root:
        return Path(root) / "check-plans"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "i4cal" / "check-plans"


def _design_key(cfg, request, camera=None) -> str:
    from service.design import motion_spec

    intr = cfg.camera_intrinsics()
    m = motion_spec(cfg)
    cam = (
        hashlib.sha256(json.dumps(camera.to_dict(), sort_keys=True).encode()).hexdigest()
        if camera is not None
        else (None if intr is None else intr.sha256)
    )
    key: dict[str, Any] = {
        "version": DESIGN_VERSION,
        "nominal": cfg.nominal_parameters().as_dict(),
        "limits": [list(cfg.actuators.limits.q_min), list(cfg.actuators.limits.q_max)],
        "motion": [m.speed_m_s, m.accel_m_s2, m.settle_s, m.line_rate_hz],
        "camera": cam,
        "request": request.key(),
    }
    if cfg.camera.mounting is not None:  # the bench file's camera mounting places what the design sees
        key["mounting"] = cfg.camera.mounting.model_dump()
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=repr).encode()).hexdigest()[:24]


def check_plan_for_bench(cfg, budget_s: float = 60.0, cache_dir: Path | None = None, seed: int = 0, camera=None):
    """The bench's designed check plan and where it came from: ``(plan, n_fit, source)``, ``source`` being
    ``"designed"`` or ``"cached: PATH"``. Designed with ``camera`` (a ``calib.formats.camera.CameraModel``: a
    service's
    camera file), else the bench file's camera file, else the simulated bench's camera, at the bench's speeds,
    within ``budget_s`` seconds of motion."""
    from calib.design.drift_check import CheckPlanRequest, design_check_plan
    from calib.formats.plan import Plan
    from service.design import _bench_inputs

    request = CheckPlanRequest(budget_s=budget_s, seed=seed)
    cache = (cache_dir or default_cache_dir()) / f"{_design_key(cfg, request, camera)}.json"
    if cache.is_file():
        try:
            plan = Plan.load(cache)
            return plan, plan.count().get("poses", 0), f"cached: {cache}"
        except InputError:
            pass  # a damaged cache entry: designed again below
    if camera is None:
        intr = cfg.camera_intrinsics()
        camera = None if intr is None else intr.camera
    nominal, scene, kw = _bench_inputs(cfg, None, camera)
    design = design_check_plan(nominal, scene, request, **kw)
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp")
        design.plan.save(tmp)
        os.replace(tmp, cache)
    except OSError:
        pass  # no cache (read-only home): the next check designs it again
    return design.plan, design.n_fit, "designed"


def require_check_phases(plan, source: str) -> None:
    """Refuse a user's check plan that lacks a phase the check's fit needs (before any motion)."""
    from calib.design.drift_check import missing_phases

    missing = missing_phases(plan)
    if missing:
        raise InputError(
            f"a check plan needs the phases rotation, translation and poses (the combined method's); it has no "
            f"{', '.join(missing)}",
            file=source,
            field="--plan",
        )
