"""Checked option values of the command line: a value out of range is a user mistake, refused by argparse in one
line naming the option (exit 2), never a traceback later.

:func:`check_ranges` applies the rules below to every sub-command's options by their destination name, so that a
command written later (or a benchmark's) gets them too: seeds are non-negative integers, worker counts positive,
noise levels non-negative and finite, ports 0-65535.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
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


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, ``i4cal COMMAND: error: ...`` (exit 2)."""

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def load_plan(spec: str, cfg, seed: int):
    """A ``--plan`` / ``PLAN``: a plan name (its poses drawn within the bench configuration's soft limits) or a plan
    file."""
    from calib.plan import PLAN_NAMES, Plan, make_plan

    if spec in PLAN_NAMES:
        return make_plan(spec, cfg.nominal_parameters(), seed=seed, limits=cfg.calib_limits())
    return Plan.load(spec)
