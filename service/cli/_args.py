"""Checked option values of the command line: a value out of range is a user mistake, refused by argparse in one
line naming the option (exit 2), never a traceback later.

:func:`check_ranges` applies the rules below to every sub-command's options by their destination name, so that a
command written later (or a benchmark's) gets them too: seeds are non-negative integers, worker counts positive,
noise levels non-negative and finite, ports 0-65535.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable, Sequence
from typing import Any


def _int_at_least(low: int, what: str) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"{v} is not {what}")
        return v

    parse.__name__ = "int"
    return parse


def _int_range(low: int, high: int) -> Callable[[str], int]:
    base = _int_at_least(low, f"in {low}..{high}")

    def parse(text: str) -> int:
        v = base(text)
        if v > high:
            raise argparse.ArgumentTypeError(f"{v} is not in {low}..{high}")
        return v

    parse.__name__ = "int"
    return parse


def non_negative_float(text: str) -> float:
    """A finite float >= 0 (noise levels, lengths)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"{text} is not a finite number >= 0")
    return v


non_negative_float.__name__ = "float"
non_negative_int = _int_at_least(0, ">= 0")
positive_int = _int_at_least(1, ">= 1")
port_number = _int_range(0, 65535)

#: Option destination -> the type every command gives it (only options that were ``int`` or ``float``).
RULES: dict[str, Callable[[str], Any]] = {
    "seed": non_negative_int,
    "workers": positive_int,
    "port": port_number,
    "noise": non_negative_float,
    "rod_direction_mrad": non_negative_float,
    "rod_point_mm": non_negative_float,
    "board_rotation_mrad": non_negative_float,
    "board_translation_mm": non_negative_float,
    "encoder_um": non_negative_float,
    "spread_mm": non_negative_float,
}


def check_ranges(parser: argparse.ArgumentParser) -> None:
    """Give the options named in :data:`RULES` their checked type, in ``parser`` and all its sub-parsers."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                check_ranges(sub)
        elif action.dest in RULES and action.type in (int, float):
            action.type = RULES[action.dest]


_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


def join_negative_values(argv: Sequence[str]) -> list[str]:
    """``--opt -0.05mm`` as ``--opt=-0.05mm``: a value that starts with a minus sign and a digit is the option's value
    (argparse would read ``-0.05mm`` as an unknown option and say "expected one argument"), so that the option's own
    check refuses it with its reason."""
    out: list[str] = []
    args = list(argv)
    i = 0
    while i < len(args):
        tok = args[i]
        if (
            tok.startswith("--")
            and len(tok) > 2
            and "=" not in tok
            and i + 1 < len(args)
            and _NEGATIVE_VALUE.match(args[i + 1])
        ):
            out.append(f"{tok}={args[i + 1]}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, ``i4cal COMMAND: error: ...`` (exit 2); an option's
    negative value is read as its value (:func:`join_negative_values`)."""

    # the base class takes any Iterable; argparse and the CLI pass a list, which join_negative_values indexes
    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: Any = None
    ) -> Any:
        import sys

        return super().parse_known_args(join_negative_values(sys.argv[1:] if args is None else args), namespace)

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def load_plan(spec: str, cfg, seed: int):
    """A ``--plan`` / ``PLAN``: a plan name (its poses drawn within the bench configuration's soft limits) or a plan
    file."""
    from pathlib import Path

    from calib.errors import InputError
    from calib.formats.plan import PLAN_NAMES, Plan, make_plan

    if spec in PLAN_NAMES:
        return make_plan(spec, cfg.nominal_parameters(), seed=seed, limits=cfg.calib_limits())
    if not Path(spec).exists():
        import difflib

        close = difflib.get_close_matches(spec, PLAN_NAMES, n=1)
        hint = f"did you mean {close[0]}? " if close else ""
        raise InputError(
            f"no such plan file, and not a plan name: {hint}plan names are {', '.join(PLAN_NAMES)}", file=spec
        )
    return Plan.load(spec)
