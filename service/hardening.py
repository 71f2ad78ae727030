"""Request and response hardening of the service: strict JSON bodies, JSON-safe validation errors, a Host allow-list
and security headers on every response (installed by :func:`install` from ``service.main.create_app``).

* JSON request bodies (``application/json``, ``*+json`` or no content type, as FastAPI parses them) larger than
  ``max_json_body_bytes`` are answered 413, and bodies holding ``NaN``, ``Infinity``, ``-Infinity`` or a number
  beyond the float range (which Python's ``json`` would read as infinite) 422 naming the field, before any route
  sees them. Standard JSON has no such numbers; the service never computes with them. So are strings (and keys)
  holding a lone UTF-16 surrogate (``"\\ud800"``: not Unicode text, which no response could encode) and documents
  nested deeper than :data:`MAX_JSON_DEPTH` (Python's parser fails near 1000 levels with a RecursionError). Large
  bodies are parsed in a worker thread, once (:class:`ParsedJSONRoute`). :func:`json_file_problem` applies the same
  depth and surrogate checks to an uploaded ``dataset.json``.
* Validation errors (422) are serialised with non-finite inputs written as strings and lone surrogates or
  undecodable bytes escaped: a value in a field that fails validation can no longer turn the 422 into a 500.
* ``allowed_hosts``: requests whose ``Host`` header is not listed get 400 (Starlette's ``TrustedHostMiddleware``;
  against DNS rebinding: a web page cannot reach the service under a name of its own).
* Every response carries ``Content-Security-Policy`` (the dashboard needs only its own origin; the interactive API
  docs and the calibration report have their own policies, below), ``X-Content-Type-Options: nosniff``,
  ``X-Frame-Options: DENY`` and ``Referrer-Policy: no-referrer``.
"""

from __future__ import annotations

import asyncio
import json
import math
import re
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi.routing import APIRoute
from starlette.datastructures import Headers
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.settings import Settings

#: The dashboard (``/dashboard``, ``/static``) and the API: scripts, styles, images, EventSource from this origin only.
CSP_DEFAULT = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; "
    "font-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
#: The interactive API docs (Swagger UI, its assets served from ``/static/docs``): the page starts the UI with an
#: inline script, and the UI sets inline styles; nothing comes from elsewhere.
CSP_DOCS = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)
#: The calibration report: one self-contained HTML file (inline styles, images as data: URIs, no script).
CSP_REPORT = (
    "default-src 'none'; style-src 'unsafe-inline'; img-src data:; object-src 'none'; base-uri 'none'; "
    "form-action 'none'; frame-ancestors 'none'"
)
DOCS_PREFIX = "/api/v1/docs"
_REPORT_PATH = re.compile(r"^/api/v1/runs/[0-9a-f]{32}/report$")

SECURITY_HEADERS = {
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "no-referrer",
}

#: JSON bodies up to this size are parsed in the event loop; larger ones in a worker thread.
INLINE_PARSE_BYTES = 64 * 1024
#: where the body parsed by :class:`StrictJSONBodies` is left for the route (:class:`ParsedJSONRoute`)
JSON_SCOPE_KEY = "i4cal.json_body"
_MISSING = object()


def csp_for(path: str) -> str:
    """The Content-Security-Policy of a response to ``path``."""
    if path == DOCS_PREFIX or path.startswith(DOCS_PREFIX + "/"):
        return CSP_DOCS
    if _REPORT_PATH.match(path):
        return CSP_REPORT
    return CSP_DEFAULT


class SecurityHeaders:
    """Pure ASGI middleware (streams, Server-Sent Events included, pass through untouched): adds the security
    headers to every HTTP response that does not set them itself."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = {**SECURITY_HEADERS, "content-security-policy": csp_for(scope.get("path", ""))}

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                have = {k.lower() for k, _ in headers}
                headers += [(k.encode(), v.encode()) for k, v in extra.items() if k.encode() not in have]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def non_finite_path(doc: Any) -> tuple[list[str | int], float] | None:
    """The path (keys and indices) of the first non-finite float in a parsed JSON document, and the value."""
    stack: list[tuple[list[str | int], Any]] = [([], doc)]
    while stack:
        path, v = stack.pop()
        if isinstance(v, float):
            if not math.isfinite(v):
                return path, v
        elif isinstance(v, dict):
            stack.extend(([*path, k], x) for k, x in reversed(list(v.items())))
        elif isinstance(v, list):
            stack.extend(([*path, i], x) for i, x in reversed(list(enumerate(v))))
    return None


#: Deepest nesting of arrays and objects accepted in a JSON document (a request body, an uploaded dataset.json); a
#: plan is 5 levels deep. Python's parser raises RecursionError near 1000 levels, which was a 500.
MAX_JSON_DEPTH = 64
_SURROGATE = re.compile("[\ud800-\udfff]")


def has_surrogate(text: str) -> bool:
    """Whether ``text`` holds a lone UTF-16 surrogate (``"\\ud800"`` in JSON: not a Unicode character; a decoded
    valid pair is one character, so any surrogate left is lone)."""
    return not text.isascii() and _SURROGATE.search(text) is not None


def safe_text(text: str) -> str:
    """``text`` with its lone surrogates written as ``\\udXXX`` escapes (encodable as UTF-8)."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8") if has_surrogate(text) else text


def document_problem(doc: Any) -> tuple[str, list[str | int]] | None:
    """The first structural problem of a parsed JSON document: ``("depth", path)`` when it nests deeper than
    :data:`MAX_JSON_DEPTH` (the path to the first container too deep), ``("surrogate", path)`` for a string (or a key)
    holding a lone surrogate (the key written escaped); None when it is fine. Iterative: no recursion limit."""
    stack: list[tuple[list[str | int], Any]] = [([], doc)]
    while stack:
        path, v = stack.pop()
        if isinstance(v, str):
            if has_surrogate(v):
                return "surrogate", path
        elif isinstance(v, dict | list):
            if len(path) >= MAX_JSON_DEPTH:
                return "depth", path
            if isinstance(v, dict):
                for k in reversed(list(v)):
                    if has_surrogate(k):
                        return "surrogate", [*path, safe_text(k)]
                    stack.append(([*path, k], v[k]))
            else:
                stack.extend(([*path, i], x) for i, x in reversed(list(enumerate(v))))
    return None


def _json_safe(v: Any) -> Any:
    """``v`` with every non-finite float written as a string ("nan", "inf", "-inf") and lone surrogates escaped."""
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if isinstance(v, str):
        return safe_text(v)
    if isinstance(v, bytes | bytearray):  # a body of another content type, as the route received it
        return safe_text(bytes(v).decode("utf-8", "backslashreplace"))
    if isinstance(v, dict):
        return {safe_text(k) if isinstance(k, str) else k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    return v


def _json_response(status: int, content: Any) -> JSONResponse:
    return JSONResponse(status_code=status, content=content)


class _NonFiniteError(ValueError):
    pass


def _reject_constant(name: str) -> float:
    raise _NonFiniteError(name)


def _finite_float(text: str) -> float:
    v = float(text)
    if math.isinf(v):  # a literal beyond the float range
        raise _NonFiniteError(text)
    return v


def strict_json(body: bytes) -> tuple[str, Any]:
    """Parse a JSON body: ``("ok", document)``, ``("non_finite", (path, value))`` naming the first NaN, Infinity or
    out-of-range number, ``("surrogate", path)`` naming the first string holding a lone UTF-16 surrogate,
    ``("depth", path)`` when nested deeper than :data:`MAX_JSON_DEPTH`, or ``("invalid", None)`` (not JSON: left to
    FastAPI's own error)."""
    try:
        doc = json.loads(body, parse_constant=_reject_constant, parse_float=_finite_float)
    except _NonFiniteError:
        try:
            return "non_finite", non_finite_path(json.loads(body))
        except RecursionError:
            return "depth", []
    except RecursionError:
        return "depth", []
    except ValueError:
        return "invalid", None
    problem = document_problem(doc)
    if problem is not None:
        return problem
    return "ok", doc


def json_file_problem(path: Path) -> str | None:
    """Why the JSON file ``path`` (e.g. an uploaded ``dataset.json``) cannot be read safely: nested deeper than
    :data:`MAX_JSON_DEPTH`, or a string with a lone surrogate (the message names the file and where); None when it
    parses and is fine, or is not JSON at all (left to its reader's own error)."""
    name = path.name
    try:
        doc = json.loads(path.read_bytes())
    except RecursionError:
        return f"{name}: JSON nested deeper than {MAX_JSON_DEPTH} levels of arrays and objects"
    except ValueError:
        return None
    problem = document_problem(doc)
    if problem is None:
        return None
    kind, where = problem
    at = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in where).lstrip(".") or "the document"
    if kind == "depth":
        return f"{name}: JSON nested deeper than {MAX_JSON_DEPTH} levels of arrays and objects (at {at})"
    return f"{name}: a string holds a lone UTF-16 surrogate, not Unicode text (at {at})"


def strict_json_error(kind: str, value: Any, prefix: tuple[str | int, ...] = ("body",)) -> dict[str, Any] | None:
    """The 422 error item (FastAPI's format) of a :func:`strict_json` outcome other than ``ok`` and ``invalid``."""
    if kind == "non_finite" and value is not None:
        path, bad = value
        return {
            "type": "finite_number",
            "loc": [*prefix, *path],
            "msg": "Input should be a finite number (NaN and Infinity are not JSON numbers)",
            "input": str(bad),
        }
    if kind == "surrogate":
        return {
            "type": "string_unicode",
            "loc": [*prefix, *value],
            "msg": "a string holds a lone UTF-16 surrogate (\\ud800-\\udfff without its pair): not Unicode text",
        }
    if kind == "depth":
        return {
            "type": "json_depth",
            "loc": list(prefix),
            "msg": f"JSON nested deeper than {MAX_JSON_DEPTH} levels of arrays and objects",
        }
    return None


class StrictJSONBodies:
    """Pure ASGI middleware: JSON request bodies bounded in size (413) and free of non-finite numbers (422 naming the
    field, FastAPI's error format); other bodies (archive uploads) pass through unread. The body is parsed once,
    in a worker thread when larger than :data:`INLINE_PARSE_BYTES`, and the document is left in the request's scope
    for :class:`ParsedJSONRoute` routes (which then do not parse it again in the event loop)."""

    METHODS = ("POST", "PUT", "PATCH", "DELETE")

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    @staticmethod
    def _is_json(scope: Scope) -> bool:
        ctype = Headers(scope=scope).get("content-type")
        if not ctype:
            return True  # FastAPI parses a body without a content type as JSON
        main = ctype.split(";")[0].strip().lower()
        return main == "application/json" or (main.startswith("application/") and main.endswith("+json"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in self.METHODS or not self._is_json(scope):
            await self.app(scope, receive, send)
            return
        too_large = _json_response(
            413,
            {"detail": f"JSON body larger than {self.max_bytes} bytes (max_json_body_bytes)"},
        )
        clen = Headers(scope=scope).get("content-length")
        if clen is not None and clen.isdigit() and int(clen) > self.max_bytes:
            await too_large(scope, receive, send)
            return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                await too_large(scope, receive, send)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body:
            if len(body) > INLINE_PARSE_BYTES:
                kind, value = await asyncio.to_thread(strict_json, body)
            else:
                kind, value = strict_json(body)
            err = strict_json_error(kind, value)
            if err is not None:
                await _json_response(422, {"detail": [err]})(scope, receive, send)
                return
            if kind == "ok":
                scope[JSON_SCOPE_KEY] = value
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class ParsedJSONRoute(APIRoute):
    """An API route that takes the JSON body :class:`StrictJSONBodies` already parsed (off the event loop when large)
    instead of parsing it again (Starlette's ``Request.json()`` caches the document in ``_json``)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def route_handler(request: Request) -> Response:
            doc = request.scope.get(JSON_SCOPE_KEY, _MISSING)
            if doc is not _MISSING:
                request._json = doc
            return await handler(request)

        return route_handler


async def validation_error_handler(request: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422 (``{"detail": [{"loc", "msg", "type", "input", ...}]}``), non-finite inputs as strings, lone
    surrogates and undecodable bytes escaped: the 422 itself can always be written."""
    return _json_response(422, {"detail": _json_safe(jsonable_encoder(_json_safe(exc.errors())))})


def allowed_hosts(settings: Settings) -> list[str]:
    """The Host allow-list: ``allowed_hosts``, plus ``host`` when the service binds one specific address."""
    hosts = list(settings.allowed_hosts)
    h = settings.host.strip().lower()
    if h and h not in ("0.0.0.0", "::", "[::]"):
        h = f"[{h}]" if ":" in h and not h.startswith("[") else h
        if h not in hosts:
            hosts.append(h)
    return hosts


def install(app: FastAPI, settings: Settings) -> None:
    """Add the hardening to ``app``: validation-error handler, strict JSON bodies, Host allow-list, headers (outermost:
    every response, the allow-list's 400 included, carries them)."""
    # Starlette types a handler for any Exception; this one is registered for RequestValidationError only
    app.add_exception_handler(RequestValidationError, validation_error_handler)  # type: ignore[arg-type]
    app.add_middleware(StrictJSONBodies, max_bytes=settings.max_json_body_bytes)
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts(settings), www_redirect=False)
    app.add_middleware(SecurityHeaders)
