"""Bearer tokens: stored hashed (sha256), configured in the settings or created with ``i4cal token create``.

Every request that moves hardware or changes state depends on :func:`require_token`; reads depend on
:func:`read_access`, which asks for a token only when ``open_reads`` is false.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import select

from .db import Database, Token

bearer = HTTPBearer(auto_error=False, description="a token from `i4cal token create`")


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def new_token() -> str:
    return "i4c_" + secrets.token_urlsafe(32)


def create_token(db: Database, name: str = "") -> str:
    """Store a new token's hash and return the token (shown once)."""
    token = new_token()
    with db.session() as s:
        s.add(Token(name=name, sha256=hash_token(token)))
    return token


def token_valid(request: Request, token: str) -> bool:
    digest = hash_token(token)
    ok = False
    for h in request.app.state.settings.token_hashes:
        ok |= hmac.compare_digest(h.lower(), digest)
    if ok:
        return True
    db: Database = request.app.state.db
    with db.session() as s:
        return s.scalar(select(Token.id).where(Token.sha256 == digest)) is not None


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(status.HTTP_401_UNAUTHORIZED, detail=detail, headers={"WWW-Authenticate": "Bearer"})


def require_token(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> str:
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise _unauthorized("a bearer token is required")
    if len(creds.credentials) > 512 or not token_valid(request, creds.credentials):
        raise _unauthorized("invalid token")
    return creds.credentials


def read_access(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    if request.app.state.settings.open_reads:
        return
    require_token(request, creds)


Writer = Annotated[str, Depends(require_token)]
Reader = Annotated[None, Depends(read_access)]
