"""The registry of mechanisms: :func:`get_mechanism` by name, :func:`mechanisms`, :func:`mechanism_names`;
:func:`register_mechanism` adds one. The implementations of :class:`calib.mechanism.Mechanism` live beside it: the
I4 (adapter, :mod:`calib.mechanisms.i4`) and a linear Delta (:mod:`calib.mechanisms.linear_delta`); a new one is a
module here plus one line in :func:`_builtin_factories` (docs/mechanisms.md)."""

from __future__ import annotations

import re
import threading
from collections.abc import Callable

from ..errors import InputError
from ..mechanism import NAME_PATTERN, Mechanism

_lock = threading.RLock()
_registry: dict[str, Mechanism] = {}
_builtins_loaded = False


def register_mechanism(mechanism: Mechanism, *, replace: bool = False) -> Mechanism:
    """Register ``mechanism`` under its name; return it.

    Raises
    ------
    InputError
        A bad name, or a mechanism of that name exists and ``replace`` is False.
    """
    if not re.match(NAME_PATTERN, str(getattr(mechanism, "name", ""))):
        raise InputError(f"mechanism name {getattr(mechanism, 'name', None)!r} must match {NAME_PATTERN}", field="name")
    if not isinstance(mechanism, Mechanism):
        raise InputError(f"{mechanism.name!r} does not implement calib.mechanism.Mechanism", field="mechanism")
    with _lock:
        _ensure_builtins()
        if mechanism.name in _registry and not replace:
            raise InputError(f"a mechanism named {mechanism.name!r} is already registered", field="name")
        _registry[mechanism.name] = mechanism
    return mechanism


def mechanisms() -> tuple[Mechanism, ...]:
    """Every registered mechanism, in registration order (the built-in ones first)."""
    _ensure_builtins()
    with _lock:
        return tuple(_registry.values())


def mechanism_names() -> tuple[str, ...]:
    """Names of the registered mechanisms."""
    return tuple(m.name for m in mechanisms())


def get_mechanism(name: str) -> Mechanism:
    """The mechanism ``name``.

    Raises
    ------
    InputError
        No such mechanism (the message lists the registered ones).
    """
    _ensure_builtins()
    mech = _registry.get(name)
    if mech is None:
        raise InputError(f"unknown mechanism {name!r}; mechanisms are {', '.join(_registry)}", field="mechanism")
    return mech


def _ensure_builtins() -> None:
    global _builtins_loaded
    if _builtins_loaded:
        return
    with _lock:
        if _builtins_loaded:
            return
        for factory in _builtin_factories():
            m = factory()
            _registry.setdefault(m.name, m)
        _builtins_loaded = True


def _i4() -> Mechanism:
    from .i4 import I4Mechanism

    return I4Mechanism()


def _linear_delta() -> Mechanism:
    from .linear_delta import LinearDelta

    return LinearDelta()


def _builtin_factories() -> list[Callable[[], Mechanism]]:
    """The mechanisms of this package, one line each."""
    return [_i4, _linear_delta]


__all__ = ["get_mechanism", "mechanism_names", "mechanisms", "register_mechanism"]
