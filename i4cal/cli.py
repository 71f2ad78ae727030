"""The ``i4cal`` command line, assembled above the service: the service's commands (:mod:`service.cli`) and the
benchmarks (``i4cal bench``: :mod:`i4cal.bench_cli`, :mod:`i4cal.benchmarks`).

The ``i4cal`` script and ``python -m i4cal`` run :func:`run_program` (:func:`main`, then exit). ``python -m
service.cli`` has every command except ``bench``: the service never imports :mod:`i4cal` (``lint-imports``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import NoReturn

from i4cal import bench_cli
from service import cli as service_cli

#: The ``register(subparsers)`` functions of the commands this layer adds to the service's.
REGISTRARS: tuple[service_cli.Registrar, ...] = (bench_cli.register,)


def build_parser() -> argparse.ArgumentParser:
    """The whole ``i4cal`` parser: :func:`service.cli.build_parser` with this layer's commands."""
    return service_cli.build_parser(extra_registrars=REGISTRARS)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``i4cal`` on ``argv`` (default ``sys.argv[1:]``); the exit code (:func:`service.cli.main`)."""
    return service_cli.main(argv, extra_registrars=REGISTRARS)


def run_program() -> NoReturn:
    """The ``i4cal`` script and ``python -m i4cal``: :func:`main` on ``sys.argv[1:]``, then exit with its code
    (:func:`service.cli.run_program`)."""
    service_cli.run_program(REGISTRARS)


if __name__ == "__main__":  # pragma: no cover
    run_program()
