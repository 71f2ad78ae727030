"""``i4cal acquire``: run a motion plan on a bench and record a dataset, with a progress bar."""

from __future__ import annotations

import argparse
import asyncio
import signal
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "acquire",
        help="run a motion plan on a bench and record a dataset",
        description=(
            "Validates the plan against the bench's soft limits and nominal model, then for every pose "
            "moves, waits in position, reads the encoders, grabs and writes a frame. A fault stops the "
            "motion, keeps the frames written and names the pose; --resume continues from there."
        ),
    )
    p.add_argument("--bench", required=True, help="bench configuration file (TOML), e.g. deploy/bench-sim.toml")
    p.add_argument(
        "--plan",
        default="full",
        help="a plan name (full, rotation-sweep, equal-translation, pose-set, lock-actuator, line, "
        "validation) or a plan JSON file",
    )
    p.add_argument("--out", required=True, help="dataset directory to write")
    p.add_argument("--resume", action="store_true", help="continue a partial dataset from its first missing pose")
    p.add_argument("--seed", type=int, default=0, help="seed of a generated plan")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from drivers.acquisition import AcquisitionError, acquisition_from_config, close_devices
    from drivers.config import load_bench

    from ._args import load_plan

    cfg = load_bench(args.bench)
    plan = load_plan(args.plan, cfg, args.seed)
    console = Console(stderr=True)
    bar = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[phase]}"),
        TimeRemainingColumn(),
        console=console,
        disable=args.no_progress,
    )
    task = bar.add_task("acquire", total=None, phase="")

    def on_progress(p) -> None:
        bar.update(task, total=p.total, completed=p.done, phase=p.phase or p.state)
        if p.state in ("paused", "suspended", "failed", "aborted") and p.message:
            console.print(f"[yellow]{p.state}[/]: {p.message}")
        elif p.message.startswith("suspension cleared"):  # drivers.suspenders: going on by itself
            console.print(p.message)

    async def main() -> int:
        acq = acquisition_from_config(plan, cfg, Path(args.out), resume=args.resume, progress=on_progress)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, acq.abort)  # abort stops the actuators, keeps the frames
        try:
            with bar:
                res = await acq.run()
        finally:
            await close_devices(acq)
        console.print(f"{res.frames}/{res.total} frames in {res.path} ({res.elapsed_s:.1f} s)")
        return 0

    try:
        return asyncio.run(main())
    except AcquisitionError:
        raise  # one clear line from the CLI (an I4calError)
