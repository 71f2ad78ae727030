"""``i4cal acquire``: run a motion plan on a bench and record a dataset, with a progress bar."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
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
    p.add_argument(
        "--extract",
        action="store_true",
        help="measure each frame's board and rods while the bench moves to the next pose (a worker process beside "
        "the acquisition), then extract the observations seconds after the last frame (as i4cal extract does)",
    )
    p.add_argument(
        "--observations",
        metavar="OBS",
        default=None,
        help="with --extract: the observations v1 JSON to write (default: OUT/observations.json)",
    )
    p.add_argument(
        "--workers", type=int, default=None, metavar="N", help="with --extract: extraction processes at the end"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from calib.errors import InputError
    from drivers.acquisition.acquire import AcquisitionError, acquisition_from_config, close_devices
    from drivers.acquisition.config import load_bench
    from service.cli._args import load_plan

    if not args.extract and (args.observations is not None or args.workers is not None):
        raise InputError("--observations and --workers go with --extract", field="--extract")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"must be at least 1, got {args.workers}", field="--workers")
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
    measured = bar.add_task("measured", total=None, phase="", visible=bool(args.extract))
    out = Path(args.out)
    stream = None
    if args.extract:
        from drivers.acquisition.streaming import FrameStream

        def on_stream(kind: str, data: dict) -> None:
            if kind == "frame":
                bar.update(measured, completed=data["measured"], phase=f"frame {data['frame']}")
            elif kind == "failed":
                console.print(
                    f"[yellow]frame {data['frame']}[/]: not measured during the acquisition ({data['reason']})"
                )
            elif kind == "off":
                console.print(f"[yellow]no measuring during the acquisition[/]: {data['reason']}")

        out.mkdir(parents=True, exist_ok=True)
        stream = FrameStream(out, out / ".streamed.json", on_event=on_stream).start()
        if args.resume:
            stream.submit_recorded()

    def on_progress(p) -> None:
        bar.update(task, total=p.total, completed=p.done, phase=p.phase or p.state)
        if p.state in ("paused", "suspended", "failed", "aborted") and p.message:
            console.print(f"[yellow]{p.state}[/]: {p.message}")
        elif p.message.startswith("suspension cleared"):  # drivers.acquisition.suspenders: going on by itself
            console.print(p.message)

    async def main() -> int:
        acq = acquisition_from_config(
            plan,
            cfg,
            out,
            resume=args.resume,
            progress=on_progress,
            on_frame=None if stream is None else stream.submit,
        )
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
        code = asyncio.run(main())
    except BaseException as exc:
        if stream is not None:  # no extraction of a run that did not end: its worker stops
            stream.close()
        if isinstance(exc, AcquisitionError):
            raise  # one clear line from the CLI (an I4calError)
        raise
    if stream is not None:
        _extract_after(args, out, stream, console)
    return code


def _extract_after(args: argparse.Namespace, out: Path, stream, console) -> None:
    """The extraction at the end, taking what the stream worker measured during the acquisition."""
    import time

    from calib.formats.observations import Observations
    from calib.numerics.jsonio import write_json_atomic
    from calib.vision.extract import extract_dataset
    from drivers.acquisition.streaming import load_streamed
    from service.jobs import clean_json

    t0 = time.monotonic()
    summary = stream.finish(60.0)
    frames = load_streamed((summary or {}).get("file"))
    res = extract_dataset(out, workers=args.workers, streamed=frames)
    doc = clean_json(res.observations)
    Observations.from_dict(doc, str(out))
    target = Path(args.observations) if args.observations else out / "observations.json"
    write_json_atomic(target, doc, indent=None)
    with contextlib.suppress(OSError):
        (out / ".streamed.json").unlink()
    took = time.monotonic() - t0
    if frames is None:
        console.print(f"observations in {target} ({took:.1f} s after the last frame; nothing measured during it)")
    else:
        u = frames.used
        console.print(
            f"observations in {target} ({took:.1f} s after the last frame; measured during the acquisition: "
            f"{u['boards']} boards, {u['rods']} frames' rods taken, {u['rods_measured_again']} measured again, "
            f"{len(frames.failed)} failed)"
        )
