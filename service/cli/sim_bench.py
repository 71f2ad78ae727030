"""``i4cal sim-bench``: run the simulated bench (Modbus controller + camera frame server) as a process."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import re
import sys

#: units a ``--drift`` change may carry, in metres
_DRIFT_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
_DRIFT_ITEM = re.compile(r"\s*([A-Za-z0-9]+)\s*=\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµ]*)\s*")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim-bench",
        help="run the simulated bench on 127.0.0.1 and print its device URIs",
        description=(
            "Starts a simulated four-axis Modbus controller (default register map, see docs/drivers.md) "
            "on 127.0.0.1: Modbus TCP on PORT, Modbus RTU framing over TCP on PORT+1, and the simulated "
            "camera/operator endpoint on PORT+2. Runs until interrupted."
        ),
    )
    p.add_argument("--port", type=int, default=5020, help="Modbus TCP port (default 5020)")
    p.add_argument("--seed", type=int, default=0, help="seed of encoder and image noise")
    p.add_argument(
        "--watchdog-s",
        type=float,
        default=0.5,
        metavar="S",
        help=(
            "communication watchdog: a move with no Modbus request for S seconds is stopped and the axis goes "
            "into alarm 0x50 (default 0.5; 0 = off)"
        ),
    )
    p.add_argument(
        "--truth-out",
        metavar="FILE",
        default=None,
        help="write the simulated robot's true seven parameters (metres: a JSON object keyed H, q02, q03, q04, S, D, "
        "L) to FILE once the bench serves, to compare a calibration with the truth",
    )
    p.add_argument(
        "--drift",
        metavar="P=CHANGE,...",
        type=parse_drift,
        default=None,
        help="move the simulated robot's true geometry, e.g. L=+0.3mm,q03=-0.5mm (any of H, q02, q03, q04, S, D, L; "
        "units mm, um or m): what a check (i4cal check) must catch; --truth-out writes the moved truth",
    )
    p.set_defaults(handler=_run)


def parse_drift(text: str) -> dict[str, float]:
    """``--drift``: ``NAME=CHANGE[,NAME=CHANGE...]``, each change a signed length with its unit (mm, um or m), to
    metres keyed by parameter name; a usage error naming the item otherwise."""
    from drivers.sim.bench import DRIFT_PARAMETERS

    out: dict[str, float] = {}
    items = text.split(",")
    for item in items:
        m = _DRIFT_ITEM.fullmatch(item)
        if not m:
            raise argparse.ArgumentTypeError(
                f"{item.strip()!r} is not NAME=CHANGE with a unit (e.g. L=+0.3mm,q03=-0.5mm)"
            )
        name, number, unit = m.groups()
        if name not in DRIFT_PARAMETERS:
            raise argparse.ArgumentTypeError(f"{name!r} is not a parameter: one of {', '.join(DRIFT_PARAMETERS)}")
        if unit not in _DRIFT_UNITS:
            raise argparse.ArgumentTypeError(
                f"{item.strip()!r}: " + ("give a unit" if not unit else f"unknown unit {unit!r}") + " (mm, um or m)"
            )
        if name in out:
            raise argparse.ArgumentTypeError(f"{name} is given twice")
        value = float(number) * _DRIFT_UNITS[unit]
        if not math.isfinite(value) or abs(value) >= 0.05:
            raise argparse.ArgumentTypeError(f"{item.strip()!r}: a drift must be finite and under 50 mm")
        out[name] = value
    return out


def _run(args: argparse.Namespace) -> int:
    if args.watchdog_s < 0:
        print("i4cal sim-bench: --watchdog-s must be >= 0 (0 = off)", file=sys.stderr)
        return 2
    from calib.numerics.jsonio import write_json_atomic
    from drivers.sim.bench import serve_forever
    from service.cli.calibrate import check_output_file

    if args.truth_out is not None:
        check_output_file(args.truth_out, "--truth-out")

    def out(line: str) -> None:
        print(line, flush=True)

    def write_truth(bench) -> None:
        if args.truth_out is not None:
            write_json_atomic(args.truth_out, true_parameters(bench))

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(
            serve_forever(
                args.port,
                seed=args.seed,
                watchdog_s=args.watchdog_s,
                print_fn=out,
                on_start=write_truth,
                drift_m=args.drift,
            )
        )
    return 0


def true_parameters(bench) -> dict[str, float]:
    """The simulated robot's true seven parameters (metres), keyed H, q02, q03, q04, S, D, L."""
    truth = bench.geometry.truth
    return {k: float(getattr(truth, k)) for k in ("H", "q02", "q03", "q04", "S", "D", "L")}
