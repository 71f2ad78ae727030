"""``i4cal token create``: a bearer token for the service (printed once, stored hashed)."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "token",
        help="manage the service's bearer tokens",
        description="Tokens authorise every request that moves hardware or changes state.",
    )
    sub = p.add_subparsers(dest="token_command", metavar="ACTION", required=True)
    c = sub.add_parser("create", help="create a token: printed once, only its sha256 is stored")
    c.add_argument("--config", "-c", default=None, help="service configuration (TOML): where the database is")
    c.add_argument("--data-dir", default=None, help="data directory (overrides the configuration)")
    c.add_argument("--name", default="", help="who or what the token is for")
    c.add_argument(
        "--hash-only",
        action="store_true",
        help="store nothing; print the token and the sha256 line to put in token_hashes",
    )
    c.set_defaults(handler=_create)


def _create(args: argparse.Namespace) -> int:
    import sys

    from service.auth import create_token, hash_token, new_token
    from service.db import Database
    from service.settings import load_settings

    if args.hash_only:
        token = new_token()
        print(token)
        print(f'token_hashes = ["{hash_token(token)}"]', file=sys.stderr)
        return 0
    over = {"data_dir": args.data_dir} if args.data_dir else {}
    settings = load_settings(args.config, **over)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    db = Database(settings.db_url)
    try:
        db.upgrade()
        token = create_token(db, args.name)
    finally:
        db.dispose()
    print(token)
    print(f"token stored (sha256) in {settings.db_url}; it is shown only now", file=sys.stderr)
    return 0
