"""``i4cal bench BENCHMARK`` (alias ``i4cal benchmark``): the benchmarks of :mod:`i4cal.benchmarks` (``accuracy``,
``design``, ``speed``).

Each module of :mod:`i4cal.benchmarks` that defines ``register(subparsers)`` adds its sub-command
(the same discovery as :mod:`service.cli`), so a new benchmark is a new module there. :mod:`i4cal.cli` adds
``bench`` to the service's command line (the service never imports :mod:`i4cal`).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil


def register(subparsers: argparse._SubParsersAction) -> None:
    from i4cal import benchmarks

    p = subparsers.add_parser(
        "bench",
        aliases=["benchmark"],
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
