"""Benchmarks behind ``i4cal bench`` (speed and accuracy figures of this machine; never timed tests).

Each module of this package that defines ``register(subparsers)`` adds one ``i4cal bench`` sub-command
(discovered by :mod:`service.cli.bench`), so a new benchmark is a new module. Modules import their heavy
dependencies inside functions: the whole command line imports them to build its parser.
"""
