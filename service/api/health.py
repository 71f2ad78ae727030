"""Liveness and readiness (outside the versioned API, no token)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from pydantic import BaseModel
from sqlalchemy import text

router = APIRouter(tags=["health"])


class Health(BaseModel):
    status: str
    version: str
    bench: str | None = None
    active_runs: int = 0
    bench_held_by: str | None = None


@router.get("/healthz", response_model=Health)
async def healthz(request: Request) -> Health:
    from service import __version__

    m = request.app.state.manager
    return Health(
        status="ok", version=__version__, bench=m.name, active_runs=len(m.active), bench_held_by=m.bench_holder
    )


@router.get("/readyz", response_model=Health, responses={503: {"model": Health}})
async def readyz(request: Request, response: Response) -> Health:
    """Ready when the database answers."""
    from service import __version__

    try:
        with request.app.state.db.engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
        return Health(status="database unavailable", version=__version__)
    return Health(status="ready", version=__version__)
