"""Devices of the bench: connection state and last error."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.security import HTTPAuthorizationCredentials
from pydantic import BaseModel

from service.api.deps import Manager, conflict
from service.auth import Reader, bearer, require_token
from service.runs import RunConflictError

router = APIRouter(prefix="/devices", tags=["devices"])


class DeviceOut(BaseModel):
    name: str
    uri: str
    state: str
    last_error: str | None
    last_seen: datetime | None


class DevicesOut(BaseModel):
    bench: str | None
    simulated: bool
    held_by: str | None
    devices: list[DeviceOut]


@router.get(
    "",
    response_model=DevicesOut,
    responses={
        401: {"description": "reads are closed and no token; or probe=true without a token"},
        409: {"description": "probe=true while a run holds the bench (or another probe is under way)"},
    },
)
async def list_devices(
    request: Request,
    manager: Manager,
    _: Reader,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    probe: bool = False,
) -> DevicesOut:
    """Each device's connection state and last error. ``probe=true`` connects to them briefly: it needs a token
    (it opens connections to the devices), is refused (409) while a run holds the bench, and no run starts while it
    runs."""
    bench = manager.bench
    if probe:
        require_token(request, creds)
    if bench is None:
        return DevicesOut(bench=None, simulated=False, held_by=None, devices=[])
    if probe:
        try:
            await manager.probe()
        except RunConflictError as exc:
            raise conflict(str(exc)) from None
    return DevicesOut(
        bench=bench.name,
        simulated=bench.sim is not None,
        held_by=manager.bench_holder,
        devices=[
            DeviceOut(name=d.name, uri=d.uri, state=d.state, last_error=d.last_error, last_seen=d.last_seen)
            for d in bench.devices.values()
        ],
    )
