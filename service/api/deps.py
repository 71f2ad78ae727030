"""Dependencies shared by the routers (the app state is built in the lifespan of service.main)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, HTTPException, Path, Request, status
from pydantic import BaseModel, ConfigDict

from calib.errors import InputError
from service.runs import Bench, RunManager, RunNotFoundError
from service.settings import Settings

ID_PATTERN = r"^[0-9a-f]{32}$"


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_manager(request: Request) -> RunManager:
    return request.app.state.manager


def get_bench(request: Request) -> Bench | None:
    return request.app.state.manager.bench


class RequestBody(BaseModel):
    """Base of every JSON request body: no unknown field, and strict types: a number must be a JSON number (an
    integer is a valid float; a boolean or a numeric string is refused, 422 naming the field), a boolean a JSON
    boolean. Lax coercion would turn ``false`` or ``"0.3"`` into numbers and execute them."""

    model_config = ConfigDict(extra="forbid", strict=True)


SettingsDep = Annotated[Settings, Depends(get_settings)]
Manager = Annotated[RunManager, Depends(get_manager)]
BenchDep = Annotated[Bench | None, Depends(get_bench)]
RunId = Annotated[str, Path(pattern=ID_PATTERN, description="run id (32 hex digits)")]
DatasetId = Annotated[str, Path(pattern=ID_PATTERN, description="dataset id (32 hex digits)")]


def not_found(what: str) -> HTTPException:
    return HTTPException(status.HTTP_404_NOT_FOUND, detail=f"{what} not found")


def conflict(msg: str) -> HTTPException:
    return HTTPException(status.HTTP_409_CONFLICT, detail=msg)


def unprocessable(exc: InputError, prefix: tuple[Any, ...] = ("body",)) -> HTTPException:
    """422 naming the field, as FastAPI reports validation errors."""
    loc: list[Any] = list(prefix)
    if exc.frame is not None:
        loc += ["steps", exc.frame]
    if exc.field:
        loc += [p for p in exc.field.split(".") if p]
    return HTTPException(
        status.HTTP_422_UNPROCESSABLE_CONTENT if hasattr(status, "HTTP_422_UNPROCESSABLE_CONTENT") else 422,
        detail=[{"loc": loc, "msg": exc.reason, "type": "value_error"}],
    )


def get_run(manager: RunManager, run_id: str):
    try:
        return manager.get(run_id)
    except RunNotFoundError:
        raise not_found("run") from None
