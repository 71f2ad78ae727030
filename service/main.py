"""Assemble the service: ``create_app(settings)``.

The lifespan opens the database (Alembic migrations to head), marks runs left active by a crash as
interrupted, creates the bench (a configured one, or an in-process simulated bench) and the run manager;
the routers in :mod:`service.api` read them from ``app.state``.
"""

from __future__ import annotations

import gc
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles

from service import __version__
from service.api import api_router
from service.api.health import router as health_router
from service.api.plans import router as plans_router
from service.auth import Reader
from service.db import Database
from service.hardening import install as install_hardening
from service.metrics import CONTENT_TYPE, make_registry, render
from service.runs import Bench, RunManager
from service.settings import Settings

STATIC = Path(__file__).resolve().parent / "static"
log = logging.getLogger("i4cal.service")


def _check_scheduler(app: FastAPI, settings: Settings, manager: RunManager):
    """The scheduled checks (``settings.check_schedule``) started on the bench, None without a schedule or bench."""
    if settings.check_schedule is None or manager.bench is None:
        return None
    from service.api.calibration import current_document
    from service.checks.manager import CheckManager
    from service.checks.schedule import CheckScheduler

    cm = app.state.checks = CheckManager(manager)

    def in_force():
        cal = manager.current_calibration()
        return None if cal is None else (current_document(manager, cal), cal.id, cal.run_id)

    scheduler = app.state.check_scheduler = CheckScheduler(cm, settings.check_schedule, in_force)
    scheduler.start()
    return scheduler


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        for sub in ("runs", "datasets", "tmp"):
            (settings.data_dir / sub).mkdir(exist_ok=True)
        import asyncio

        from service.jobs import warm_up

        # the forkserver of the extraction and fit processes imports the heavy modules now, not during a run
        warm = asyncio.get_running_loop().run_in_executor(None, warm_up)
        db = Database(settings.db_url)
        db.upgrade()
        bench = await Bench.from_settings(settings)
        if bench is not None:
            await asyncio.to_thread(bench.preload)
        manager = RunManager(settings, db, bench)
        interrupted = manager.recover()
        # the objects of start-up (modules, the app, the bench) live as long as the service: out of the collector's
        # sight, a full collection during a run scans only what the run allocates (50-70 ms otherwise)
        gc.collect()
        gc.freeze()
        if interrupted:
            log.warning("runs interrupted by the last stop (resume them): %s", ", ".join(interrupted))
        app.state.settings, app.state.db, app.state.manager = settings, db, manager
        scheduler = _check_scheduler(app, settings, manager)
        try:
            yield
        finally:
            warm.cancel()
            if scheduler is not None:
                await scheduler.stop()
            await manager.shutdown()
            if bench is not None:
                await bench.close()
            db.dispose()

    app = FastAPI(
        title="i4cal service",
        version=__version__,
        lifespan=lifespan,
        description="Acquisition and kinematic calibration of I4 parallel robots: runs on the bench, "
        "live progress, results, the current calibration. State-changing requests need a "
        "bearer token (`i4cal token create`).",
        openapi_url="/api/v1/openapi.json",
        docs_url=None,  # served below with the Swagger UI assets of service/static/docs (no CDN: works offline)
        redoc_url=None,
    )
    app.state.settings = settings
    install_hardening(app, settings)
    app.include_router(api_router)
    app.include_router(health_router)
    app.include_router(plans_router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/api/v1/docs", include_in_schema=False)
    async def api_docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url="/api/v1/openapi.json",
            title=f"{app.title} - API docs",
            swagger_js_url="/static/docs/swagger-ui-bundle.js",
            swagger_css_url="/static/docs/swagger-ui.css",
            swagger_favicon_url="/static/docs/favicon-32x32.png",
            swagger_ui_parameters={"validatorUrl": None},  # no badge fetched from the validator's site
        )

    metrics_registry = make_registry(lambda: getattr(app.state, "manager", None))

    @app.get("/metrics", include_in_schema=False)
    async def metrics(_: Reader) -> Response:
        """Prometheus text format (service/metrics.py): runs by state, run and stage durations, frames extracted,
        the drivers' Modbus counters."""
        import asyncio

        body = await asyncio.to_thread(render, metrics_registry)
        return Response(body, media_type=CONTENT_TYPE)

    @app.get("/", include_in_schema=False)
    async def index() -> RedirectResponse:
        return RedirectResponse("/dashboard")

    @app.get("/dashboard", include_in_schema=False)
    async def dashboard() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})

    return app
