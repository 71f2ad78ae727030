"""Benchmarks behind ``i4cal bench`` (speed and accuracy figures of this machine; never timed tests).

A layer above the service (they use its console and design helpers), so they live in :mod:`i4cal`, not in
:mod:`service`. Each module of this package that defines ``register(subparsers)`` adds one ``i4cal bench``
sub-command (discovered by :mod:`i4cal.bench_cli`), so a new benchmark is a new module. Modules import their heavy
dependencies inside functions: the whole command line imports them to build its parser.
"""
