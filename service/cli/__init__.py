"""The ``i4cal`` command line.

Each module of this package that defines ``register(subparsers)`` adds its sub-command(s);
modules are discovered automatically, so a new command is a new module. A layer above the service adds its own
commands through ``extra_registrars`` (:func:`build_parser`, :func:`main`): the ``i4cal`` script
(:func:`i4cal.cli.main`) adds ``bench`` that way, so ``python -m service.cli`` has every command except ``bench``
and the service never imports :mod:`i4cal`.

A command's handler receives the parsed ``argparse.Namespace`` and returns an exit code. Errors derived from
:class:`calib.errors.I4calError`, usage errors (an option's value out of range: :mod:`._args`) and
file-system errors print one clear line and exit with status 2; no traceback for user mistakes
(``I4CAL_DEBUG=1`` shows it).

Logging: ``-v`` (INFO), ``-vv`` (DEBUG) or ``--log-level LEVEL`` configure the root logger (stderr, one line
per record); the default is WARNING.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import pkgutil
import sys
from collections.abc import Callable, Iterable, Sequence
from typing import NoReturn

# One BLAS/OpenMP thread unless the user set otherwise, before numpy loads: the project's matrices are small, and a
# second thread only spins (0.3 s of CPU at import alone on 2 cores); the extraction's and the studies' parallelism
# is in processes (docs/benchmarks.md)
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from calib.errors import I4calError  # noqa: E402  (after the threads' settings)

#: A function that adds sub-commands: ``register(subparsers)`` (``subparsers``: the command line's
#: ``argparse._SubParsersAction``), as each command module of this package defines one.
Registrar = Callable[[argparse._SubParsersAction], None]


def build_parser(extra_registrars: Iterable[Registrar] = ()) -> argparse.ArgumentParser:
    """The ``i4cal`` parser: the commands of this package, then those ``extra_registrars`` add (in their order).

    Parameters
    ----------
    extra_registrars : iterable of callables ``register(subparsers)``
        Commands of a layer above the service (``i4cal bench``: :mod:`i4cal.cli`); the range checks and the logging
        options apply to them as to the service's own commands.
    """
    from service import __version__

    from ._args import OneLineParser, check_ranges

    parser = OneLineParser(
        prog="i4cal",
        description=(
            "Acquisition and kinematic calibration of I4 parallel robots by leg and end-effector observation."
        ),
    )
    parser.add_argument("--version", action="version", version=f"i4cal {__version__}")
    add_logging_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    for register in extra_registrars:
        register(sub)
    check_ranges(parser)
    for cmd in dict.fromkeys(sub.choices.values()):
        add_logging_options(cmd, top=False)
    return parser


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def add_logging_options(p: argparse.ArgumentParser, top: bool) -> None:
    """``-v/--verbose`` and ``--log-level`` (before or after the command; a command's own option of that name wins)."""
    taken = set(p._option_string_actions)
    kw = {} if top else {"default": argparse.SUPPRESS}
    if not {"-v", "--verbose"} & taken:
        p.add_argument(
            "-v",
            "--verbose",
            dest="cli_verbose",
            action="count",
            help="more log output: -v informational, -vv debugging",
            **({"default": 0} if top else kw),
        )
    if "--log-level" not in taken:
        p.add_argument(
            "--log-level",
            dest="cli_log_level",
            type=str.upper,
            choices=LOG_LEVELS,
            help="log level (overrides -v; default WARNING)",
            **({"default": None} if top else kw),
        )


def configure_logging(verbose: int = 0, level: str | None = None) -> None:
    """The root logger at ``level`` (else WARNING, INFO with ``verbose`` 1, DEBUG with 2+), to stderr.

    Without ``-v`` or ``--log-level`` a root logger that already has handlers (an embedding program's) is left alone.
    """
    asked = bool(verbose) or level is not None
    if level is None:
        level = ("WARNING", "INFO", "DEBUG")[min(max(verbose or 0, 0), 2)]
    logging.basicConfig(
        level=getattr(logging, level), format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=asked
    )


def main(
    argv: Sequence[str] | None = None, extra_registrars: Iterable[Registrar] = (), *, program: bool = False
) -> int:
    """Run the command line on ``argv`` (default ``sys.argv[1:]``) with the commands ``extra_registrars`` add
    (:func:`build_parser`); the exit code. ``program``: the process ends with the command (:func:`run_program`)."""
    parser = build_parser(extra_registrars)
    args = parser.parse_args(argv)
    if program:
        # the modules' objects live until the exit: out of the cyclic collector's walks, in this process and in the
        # extraction's forked workers (gc.freeze; docs/benchmarks.md)
        gc.freeze()
    configure_logging(args.cli_verbose, args.cli_log_level)
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
    except OSError as exc:  # a file or directory the user named (missing, a directory, not writable)
        if os.environ.get("I4CAL_DEBUG"):
            raise
        what = f"{exc.strerror}: {exc.filename}" if exc.strerror and exc.filename else str(exc)
        print(f"i4cal {args.command}: error: {what}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"i4cal {args.command}: interrupted", file=sys.stderr)
        return 130


def run_program(extra_registrars: Iterable[Registrar] = ()) -> NoReturn:
    """The command line as a program (``python -m service.cli``, the ``i4cal`` script): :func:`main` on
    ``sys.argv[1:]``, then exit with its code.

    What is alive when the command returns lives until the exit: it is frozen out of the cyclic garbage collector
    (``gc.freeze``), whose walk over every object at the interpreter's shutdown costs 0.1-0.2 s of CPU and wall
    time after each command (docs/benchmarks.md). In-process callers (the tests) call :func:`main`, which leaves
    the collector alone.
    """
    code = main(extra_registrars=extra_registrars, program=True)
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    run_program()
