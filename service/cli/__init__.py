"""The ``i4cal`` command line.

Each module of this package that defines ``register(subparsers)`` adds its sub-command(s);
modules are discovered automatically, so a new command is a new module. A command's handler
receives the parsed ``argparse.Namespace`` and returns an exit code. Errors derived from
:class:`calib.errors.I4calError` print one clear line and exit with status 2; no traceback for
user mistakes (``I4CAL_DEBUG=1`` shows it).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from collections.abc import Sequence

from calib.errors import I4calError


def build_parser() -> argparse.ArgumentParser:
    from service import __version__

    parser = argparse.ArgumentParser(
        prog="i4cal",
        description=(
            "Acquisition and kinematic calibration of I4 parallel robots by leg and end-effector observation."
        ),
    )
    parser.add_argument("--version", action="version", version=f"i4cal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 1
    try:
        return int(args.handler(args) or 0)
    except I4calError as exc:
        if os.environ.get("I4CAL_DEBUG"):
            raise
        print(f"i4cal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"i4cal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
