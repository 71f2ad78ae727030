"""``i4cal sim-bench``: run the simulated bench (Modbus controller + camera frame server) as a process."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys


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
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    if args.watchdog_s < 0:
        print("i4cal sim-bench: --watchdog-s must be >= 0 (0 = off)", file=sys.stderr)
        return 2
    from calib.jsonio import write_json_atomic
    from drivers.sim.bench import serve_forever

    from .calibrate import check_output_file

    if args.truth_out is not None:
        check_output_file(args.truth_out, "--truth-out")

    def out(line: str) -> None:
        print(line, flush=True)

    def write_truth(bench) -> None:
        if args.truth_out is not None:
            write_json_atomic(args.truth_out, true_parameters(bench))

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(
            serve_forever(args.port, seed=args.seed, watchdog_s=args.watchdog_s, print_fn=out, on_start=write_truth)
        )
    return 0


def true_parameters(bench) -> dict[str, float]:
    """The simulated robot's true seven parameters (metres), keyed H, q02, q03, q04, S, D, L."""
    truth = bench.geometry.truth
    return {k: float(getattr(truth, k)) for k in ("H", "q02", "q03", "q04", "S", "D", "L")}
