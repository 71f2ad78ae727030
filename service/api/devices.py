"""Devices of the bench: connection state and last error."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter
from pydantic import BaseModel

from ..auth import Reader
from .deps import Manager

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


@router.get("", response_model=DevicesOut, responses={401: {"description": "reads are closed and no token"}})
async def list_devices(manager: Manager, _: Reader, probe: bool = False) -> DevicesOut:
    """Each device's connection state and last error. ``probe=true`` connects to them briefly (only while no run
    holds the bench)."""
    bench = manager.bench
    if bench is None:
        return DevicesOut(bench=None, simulated=False, held_by=None, devices=[])
    if probe and manager.bench_holder is None:
        await bench.probe()
    return DevicesOut(
        bench=bench.name,
        simulated=bench.sim is not None,
        held_by=manager.bench_holder,
        devices=[
            DeviceOut(name=d.name, uri=d.uri, state=d.state, last_error=d.last_error, last_seen=d.last_seen)
            for d in bench.devices.values()
        ],
    )
