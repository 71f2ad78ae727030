"""``i4cal token create|list|revoke``: the service's bearer tokens (printed once, stored hashed).

``create [--name N] [--expires-in 30d | --expires-at 2027-01-31T00:00Z]`` prints a new token; ``list`` shows every
stored token (id, first characters, name, created, expiry, last use, state; never the token or its hash);
``revoke ID`` refuses a token from now on (401). Tokens in ``token_hashes`` of the configuration are counted by
``list`` and revoked by removing them from it.
"""

from __future__ import annotations

import argparse
import re
from datetime import UTC, datetime, timedelta

from calib.errors import InputError

_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


def parse_duration(text: str) -> timedelta:
    """``30d``, ``12h``, ``90m``, ``3600s``, ``2w`` (or a sum: ``1d12h``) as a positive timedelta.

    Raises
    ------
    InputError
        Not such a duration, or zero.
    """
    t = text.strip().lower()
    parts = re.findall(r"(\d+)\s*([smhdw])", t)
    if not parts or re.sub(r"(\d+)\s*([smhdw])", "", t).strip():
        raise InputError(f"{text!r} is not a duration such as 30d, 12h, 90m, 3600s or 2w", field="--expires-in")
    seconds = sum(int(n) * _UNITS[u] for n, u in parts)
    if seconds <= 0:
        raise InputError("the duration must be positive", field="--expires-in")
    return timedelta(seconds=seconds)


def parse_time(text: str) -> datetime:
    """An ISO 8601 date or time (``2027-01-31``, ``2027-01-31T12:00``, ``...Z``, ``...+01:00``); naive means UTC."""
    try:
        dt = datetime.fromisoformat(text.strip().replace("z", "Z"))
    except ValueError:
        raise InputError(f"{text!r} is not an ISO 8601 date or time", field="--expires-at") from None
    return dt.replace(tzinfo=UTC) if dt.tzinfo is None else dt.astimezone(UTC)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "token",
        help="manage the service's bearer tokens",
        description="Tokens authorise every request that moves hardware or changes state.",
    )
    sub = p.add_subparsers(dest="token_command", metavar="ACTION", required=True)

    def common(q: argparse.ArgumentParser) -> None:
        q.add_argument("--config", "-c", default=None, help="service configuration (TOML): where the database is")
        q.add_argument("--data-dir", default=None, help="data directory (overrides the configuration)")

    c = sub.add_parser("create", help="create a token: printed once, only its sha256 is stored")
    common(c)
    c.add_argument("--name", default="", help="who or what the token is for")
    c.add_argument(
        "--hash-only",
        action="store_true",
        help="store nothing; print the token and the sha256 line to put in token_hashes",
    )
    exp = c.add_mutually_exclusive_group()
    exp.add_argument("--expires-in", metavar="DURATION", help="refused after this long: 30d, 12h, 90m, 3600s, 2w")
    exp.add_argument("--expires-at", metavar="TIME", help="refused from this time on (ISO 8601; without a zone: UTC)")
    c.set_defaults(handler=_create)
    ls = sub.add_parser("list", help="stored tokens: id, first characters, name, created, expiry, last use, state")
    common(ls)
    ls.add_argument("--json", action="store_true", help="one JSON array (times in UTC, ISO 8601 with Z)")
    ls.set_defaults(handler=_list)
    r = sub.add_parser("revoke", help="refuse a stored token from now on (401)")
    common(r)
    r.add_argument("id", type=int, help="the token's id (i4cal token list)")
    r.set_defaults(handler=_revoke)


def _open(args: argparse.Namespace):
    from service.db import Database
    from service.settings import load_settings

    over = {"data_dir": args.data_dir} if args.data_dir else {}
    settings = load_settings(args.config, **over)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    db = Database(settings.db_url)
    try:
        db.upgrade()
    except BaseException:
        db.dispose()
        raise
    return settings, db


def _create(args: argparse.Namespace) -> int:
    import sys

    from service.auth import create_token_record, hash_token, new_token
    from service.timefmt import iso_utc

    now = datetime.now(UTC)
    expires_at = None
    expires_in = None
    if args.expires_in:
        expires_in = parse_duration(args.expires_in)  # counted from the token's issuance, once the database is open
    elif args.expires_at:
        expires_at = parse_time(args.expires_at)
        if expires_at <= now:
            raise InputError(f"{iso_utc(expires_at)} is in the past", field="--expires-at")
    if args.hash_only:
        if expires_at is not None or expires_in is not None:
            raise InputError("token_hashes do not expire: --hash-only takes no expiry", field="--expires-in")
        token = new_token()
        print(token)
        print(f'token_hashes = ["{hash_token(token)}"]', file=sys.stderr)
        return 0
    settings, db = _open(args)
    try:
        token, rid = create_token_record(db, args.name, expires_at, expires_in)
        expires = next(r["expires"] for r in token_rows(db) if r["id"] == rid)  # as stored
    finally:
        db.dispose()
    print(token)
    until = f", expires {expires}" if expires else ""
    print(f"token {rid} stored (sha256) in {settings.db_url}{until}; it is shown only now", file=sys.stderr)
    return 0


def token_rows(db) -> list[dict]:
    """Every stored token, oldest first: id, prefix, name, created, expires, last_used, revoked, state."""
    from sqlalchemy import select

    from service.db import Token
    from service.timefmt import iso_utc

    now = datetime.now(UTC)
    out = []
    with db.session() as s:
        for t in s.scalars(select(Token).order_by(Token.id)):
            state = "active"
            if t.revoked_at is not None:
                state = "revoked"
            elif t.expires_at is not None and t.expires_at <= now:
                state = "expired"
            out.append(
                {
                    "id": t.id,
                    "prefix": (t.prefix + "…") if t.prefix else None,
                    "name": t.name,
                    "created": iso_utc(t.created_at),
                    "expires": iso_utc(t.expires_at) if t.expires_at else None,
                    "last_used": iso_utc(t.last_used_at) if t.last_used_at else None,
                    "revoked": iso_utc(t.revoked_at) if t.revoked_at else None,
                    "state": state,
                }
            )
    return out


def _list(args: argparse.Namespace) -> int:
    import json
    import sys

    settings, db = _open(args)
    try:
        rows = token_rows(db)
    finally:
        db.dispose()
    if args.json:
        print(json.dumps(rows, ensure_ascii=False))
    else:
        cols = ("id", "prefix", "name", "created", "expires", "last_used", "state")
        table = [cols] + [tuple("-" if r[k] in (None, "") else str(r[k]) for k in cols) for r in rows]
        widths = [max(len(row[i]) for row in table) for i in range(len(cols))]
        for row in table:
            print("  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)).rstrip())
    if settings.token_hashes:
        print(f"(and {len(settings.token_hashes)} token(s) in token_hashes of the configuration)", file=sys.stderr)
    return 0


def _revoke(args: argparse.Namespace) -> int:
    import sys

    from service.db import Token
    from service.timefmt import iso_utc

    _, db = _open(args)
    try:
        with db.session() as s:
            t = s.get(Token, args.id)
            if t is None:
                raise InputError(f"no stored token has id {args.id} (i4cal token list)", field="id")
            if t.revoked_at is None:
                t.revoked_at = datetime.now(UTC)
            when = iso_utc(t.revoked_at)
    finally:
        db.dispose()
    print(f"token {args.id} revoked ({when}): refused from now on", file=sys.stderr)
    return 0
