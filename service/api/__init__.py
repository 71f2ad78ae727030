"""HTTP API, versioned under ``/api/v1``: one router per resource."""

from fastapi import APIRouter

from service.api import calibration, cameras, checks, datasets, devices, methods, runs

api_router = APIRouter(prefix="/api/v1")
api_router.include_router(runs.router)
api_router.include_router(datasets.router)
api_router.include_router(calibration.router)
api_router.include_router(devices.router)
api_router.include_router(methods.router)
api_router.include_router(cameras.router)
api_router.include_router(checks.router)

__all__ = ["api_router"]
