"""Identification methods: the registry (:mod:`calib.identify.registry`) as the dashboard and clients read it.

:data:`MethodName` is the type of a method name in request bodies and queries: any method registered when the
request arrives (validated then, so a method registered after the app was built is accepted); the OpenAPI schema
lists the registered names as an enum.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter
from pydantic import BaseModel, Field, GetCoreSchemaHandler, GetJsonSchemaHandler
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import core_schema

from calib.identify.registry import get_method, method_names, methods
from service.auth import Reader

router = APIRouter(prefix="/methods", tags=["methods"])


class _Registered:
    """Pydantic annotation: a string naming a registered method (checked at validation time)."""

    @classmethod
    def __get_pydantic_core_schema__(cls, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        return core_schema.no_info_after_validator_function(cls._check, core_schema.str_schema(max_length=32))

    @classmethod
    def __get_pydantic_json_schema__(
        cls, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        return {"type": "string", "enum": list(method_names())}

    @staticmethod
    def _check(name: str) -> str:
        get_method(name)  # InputError (a ValueError): "unknown method 'x'; methods are ..."
        return name


MethodName = Annotated[str, _Registered]


class MethodOut(BaseModel):
    name: str = Field(description="key in results, requests and `i4cal calibrate --method`")
    label: str
    colour: str = Field(description="#rrggbb of its plots")
    description: str
    required_phases: list[str] = Field(description="observation phases the method needs")
    identifiability: bool = Field(description="the result carries an identifiability report")
    bound: bool = Field(description="the result carries the Cramer-Rao bound")


@router.get("", response_model=list[MethodOut], responses={401: {"description": "reads are closed and no token"}})
async def list_methods(_: Reader) -> list[MethodOut]:
    """The registered identification methods, in the order of result documents."""
    return [MethodOut(**spec.summary()) for spec in methods()]


__all__ = ["MethodName", "MethodOut", "router"]
