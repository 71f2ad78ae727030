"""Bearer tokens: stored hashed (sha256), configured in the settings or created with ``i4cal token create``.

Every request that moves hardware or changes state depends on :func:`require_token`; reads depend on
:func:`read_access`, which asks for a token only when ``open_reads`` is false. A token created with an expiry
(``--expires-in``, ``--expires-at``) or revoked (``i4cal token revoke ID``) is refused (401); ``token_hashes`` of the
settings never expire (remove them from the configuration to revoke them).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import select, update

from service.db import Database, Token

bearer = HTTPBearer(auto_error=False, description="a token from `i4cal token create`")


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def new_token() -> str:
    return "i4c_" + secrets.token_urlsafe(32)


#: characters of a token kept in clear to recognise it ("i4c_" and 4 of the 43 random ones: 24 bits of 256)
PREFIX_CHARS = 8
#: the last use of a token is written at most this often (one write per token and minute, not per request)
LAST_USED_EVERY = timedelta(seconds=60)


def create_token_record(
    db: Database, name: str = "", expires_at: datetime | None = None, expires_in: timedelta | None = None
) -> tuple[str, int]:
    """Store a new token's hash (and its first characters); the token (shown once) and the stored row's id.

    ``expires_at``: refused from then on (aware, or naive UTC); None: no expiry. ``expires_in``: the token lives
    this long from its issuance (the time stored as its creation, taken as it is stored: not before the database
    was opened)."""
    token = new_token()
    issued = datetime.now(UTC)
    if expires_in is not None:
        expires_at = issued + expires_in
    row = Token(
        name=name, sha256=hash_token(token), prefix=token[:PREFIX_CHARS], created_at=issued, expires_at=expires_at
    )
    with db.session() as s:
        s.add(row)
        s.flush()
        rid = row.id
    return token, rid


@dataclass(frozen=True)
class TokenCheck:
    ok: bool
    reason: str = "invalid token"


def check_token(request: Request, token: str) -> TokenCheck:
    """Whether ``token`` is accepted: one of ``token_hashes``, or a stored token neither expired nor revoked."""
    digest = hash_token(token)
    ok = False
    for h in request.app.state.settings.token_hashes:
        ok |= hmac.compare_digest(h.lower(), digest)
    if ok:
        return TokenCheck(True)
    db: Database = request.app.state.db
    now = datetime.now(UTC)
    with db.session() as s:
        row = s.execute(
            select(Token.id, Token.expires_at, Token.revoked_at, Token.last_used_at).where(Token.sha256 == digest)
        ).one_or_none()
        if row is None:
            return TokenCheck(False)
        if row.revoked_at is not None and row.revoked_at <= now:
            return TokenCheck(False, "token revoked")
        if row.expires_at is not None and row.expires_at <= now:
            return TokenCheck(False, "token expired")
        if row.last_used_at is None or now - row.last_used_at >= LAST_USED_EVERY:
            s.execute(update(Token).where(Token.id == row.id).values(last_used_at=now))
    return TokenCheck(True)


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(status.HTTP_401_UNAUTHORIZED, detail=detail, headers={"WWW-Authenticate": "Bearer"})


def require_token(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> str:
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise _unauthorized("a bearer token is required")
    if len(creds.credentials) > 512:
        raise _unauthorized("invalid token")
    check = check_token(request, creds.credentials)
    if not check.ok:
        raise _unauthorized(check.reason)
    return creds.credentials


def read_access(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    if request.app.state.settings.open_reads:
        return
    require_token(request, creds)


Writer = Annotated[str, Depends(require_token)]
Reader = Annotated[None, Depends(read_access)]
