"""Camera calibrations the service runs on its bench (``POST /api/v1/camera/calibrations``, docs/camera.md): the
guided board session of ``i4cal camera calibrate`` as a background job that holds the bench (no run starts meanwhile);
the camera file (``i4cal.camera/1``) kept in the data directory under ``cameras/ID.json``.

The bench's operator must be able to hold the board without a terminal: the simulated bench's (``sim://``); a person
at a real bench (``console``) runs ``i4cal camera calibrate`` there. Jobs live in memory; their files stay on disk.
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from service.runs.lifecycle import RunConflictError
from service.timefmt import now_utc

log = logging.getLogger(__name__)


@dataclass
class CameraCalibrationJob:
    """One camera calibration: its state (``running``, ``done``, ``failed``), what was said, the views' counts and
    what is still missing, the result (summary) and the camera file once done, the error once failed."""

    id: str
    views: int
    lens_model: str
    max_grabs: int
    created: datetime
    state: str = "running"
    grabs: int = 0
    kept: int = 0
    missing: list[str] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    result: dict[str, Any] | None = None
    file: Path | None = None
    error: str | None = None
    task: asyncio.Task | None = field(default=None, repr=False)


class CameraCalibrations:
    """The camera calibrations of one service (see the module's docstring)."""

    def __init__(self, manager: Any) -> None:
        self.manager = manager
        self.jobs: dict[str, CameraCalibrationJob] = {}

    def start(
        self, views: int = 15, lens_model: str | None = None, max_grabs: int | None = None
    ) -> CameraCalibrationJob:
        """Start a session on the bench.

        Raises
        ------
        RunConflictError
            No bench, the bench held (a run, another camera calibration), or an operator that needs a terminal.
        InputError
            An unknown lens model.
        """
        from service.camera_session import check_lens_model

        bench = self.manager.bench
        if bench is None:
            raise RunConflictError("this service has no bench")
        if self.manager.bench_holder is not None:
            raise RunConflictError(f"{self.manager.bench_holder} holds the bench")
        if bench.config.operator.uri == "console":
            raise RunConflictError(
                "the bench's operator is 'console', a person at the bench's terminal: run `i4cal camera calibrate "
                "--bench BENCH.toml -o camera.json` there (docs/camera.md)"
            )
        lens = check_lens_model(lens_model or bench.config.camera.lens_model or "auto")
        job = CameraCalibrationJob(uuid.uuid4().hex, views, lens, max_grabs or 3 * views + 20, now_utc())
        self.jobs[job.id] = job
        self.manager.bench_holder = f"camera calibration {job.id}"
        job.task = asyncio.get_running_loop().create_task(self._run(job))
        return job

    async def _run(self, job: CameraCalibrationJob) -> None:
        from rich.text import Text

        from service.camera_session import calibrate_views, collect_views

        holder = f"camera calibration {job.id}"
        cfg = self.manager.bench.config

        def say(text: str) -> None:
            job.messages.append(Text.from_markup(text).plain)

        def on_view(guide: Any, _verdict: Any) -> None:
            job.grabs = len(guide.kept) + len(guide.rejected)
            job.kept = len(guide.kept)
            job.missing = guide.missing()

        try:
            session = await collect_views(cfg, job.views, job.max_grabs, say, on_view)
            job.grabs = session.grabs
            res, camera = await asyncio.to_thread(calibrate_views, session, cfg, job.lens_model, cfg.source)
            path = Path(self.manager.settings.data_dir) / "cameras" / f"{job.id}.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            await asyncio.to_thread(camera.save, path)
            cal = camera.extra.get("calibration") or {}
            job.result = {
                "width": camera.width,
                "height": camera.height,
                "K": camera.K.tolist(),
                "dist": camera.dist.tolist(),
                "std": {k: v for k, v in res.std.items() if k in (cal.get("covariance_params") or [])},
                "rms_px": res.rms_px,
                "n_views": len(res.per_view_rms_px),
                "lens_model": (res.lens_model or {}).get("chosen"),
                "field_coverage": (res.lens_model or {}).get("field_coverage"),
                "warnings": (res.lens_model or {}).get("warnings") or [],
            }
            job.file = path
            job.state = "done"
            say(f"wrote {path}")
        except Exception as exc:  # a device fault, views not covered, a failed calibration: said, not raised
            log.warning("camera calibration %s failed: %s", job.id, exc)
            job.error = str(exc) or type(exc).__name__
            job.state = "failed"
        finally:
            if self.manager.bench_holder == holder:
                self.manager.bench_holder = None

    def get(self, job_id: str) -> CameraCalibrationJob | None:
        return self.jobs.get(job_id)

    async def wait(self, job_id: str) -> None:
        job = self.jobs.get(job_id)
        if job is not None and job.task is not None:
            await asyncio.shield(job.task)
