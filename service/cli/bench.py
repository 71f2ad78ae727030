"""``i4cal bench BENCHMARK``: the benchmarks of :mod:`service.benchmarks` (``speed``; more as they come).

Each module of :mod:`service.benchmarks` that defines ``register(subparsers)`` adds its sub-command
(the same discovery as :mod:`service.cli`), so a new benchmark is a new module there.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil


def register(subparsers: argparse._SubParsersAction) -> None:
    from service import benchmarks

    p = subparsers.add_parser(
        "bench",
        help="benchmarks of this machine and of the methods (never timed tests)",
        description="Benchmarks: " + ", ".join(f"`i4cal bench {m.name}`" for m in _modules(benchmarks.__path__)) + ".",
    )
    sub = p.add_subparsers(dest="benchmark", metavar="BENCHMARK")
    for info in _modules(benchmarks.__path__):
        module = importlib.import_module(f"{benchmarks.__name__}.{info.name}")
        reg = getattr(module, "register", None)
        if reg is not None:
            reg(sub)

    def usage(args: argparse.Namespace) -> int:
        p.print_help()
        return 1

    p.set_defaults(handler=usage)


def _modules(path: list[str]) -> list[pkgutil.ModuleInfo]:
    return sorted((m for m in pkgutil.iter_modules(path) if not m.name.startswith("_")), key=lambda m: m.name)
