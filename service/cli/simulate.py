"""``i4cal simulate``: observations (or, with --images, a rendered dataset) from the simulated bench."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def noise_from_args(args: argparse.Namespace):
    from drivers.sim.twin import NoiseSpec

    base = NoiseSpec().scaled(args.noise)
    kw: dict[str, Any] = {  # NoiseSpec's fields
        "rod_direction_rad": base.rod_direction_rad
        if args.rod_direction_mrad is None
        else args.rod_direction_mrad * 1e-3,
        "rod_point_m": base.rod_point_m if args.rod_point_mm is None else args.rod_point_mm * 1e-3,
        "board_rotation_rad": base.board_rotation_rad
        if args.board_rotation_mrad is None
        else args.board_rotation_mrad * 1e-3,
        "board_translation_m": base.board_translation_m
        if args.board_translation_mm is None
        else tuple(v * 1e-3 for v in args.board_translation_mm),
        "encoder_m": base.encoder_m if args.encoder_um is None else args.encoder_um * 1e-6,
    }
    return NoiseSpec(**kw)


def handler(args: argparse.Namespace) -> int:
    from rich.console import Console

    from calib.formats.observations import Observations
    from calib.formats.plan import make_plan
    from calib.numerics.jsonio import dumps_readable
    from drivers.sim.twin import GeometricTwin

    con = Console(stderr=True)
    out = Path(args.out)
    plan_name = getattr(args, "plan", "full")
    if args.images:
        from drivers.sim.rendered_dataset import simulate_dataset
        from drivers.sim.twin import BenchGeometry
        from service.cli._output import LongStep, make_console

        plan = make_plan(plan_name, BenchGeometry().nominal, seed=args.seed) if plan_name != "full" else None
        with LongStep(make_console(stderr=True), "rendering frames") as bar:
            path = simulate_dataset(
                out,
                seed=args.seed,
                plan=plan,
                n_camera_views=getattr(args, "camera_views", 15),
                progress=lambda done, total: bar.update(done=done, total=total),
            )
        con.print(f"wrote dataset [bold]{path}[/bold]")
        return 0
    if out.is_dir():
        from calib.errors import InputError

        raise InputError("--out: is a directory; give an observations file (or --images for a dataset)", file=str(out))
    twin = GeometricTwin(noise=noise_from_args(args))
    plan = make_plan(plan_name, twin.geometry.nominal, seed=args.seed) if plan_name != "full" else None
    doc = twin.observations(plan=plan, seed=args.seed)
    Observations.from_dict(doc)  # validate what we write
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(dumps_readable(doc), encoding="utf-8")
    counts: dict[str, int] = {}  # frames per phase
    for f in doc["frames"]:
        counts[f["phase"]] = counts.get(f["phase"], 0) + 1
    con.print(
        f"wrote [bold]{out}[/bold]: {len(doc['frames'])} frames "
        f"({', '.join(f'{k} {v}' for k, v in counts.items())}), truth included"
    )
    return 0


def add_noise_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("noise (geometric twin)")
    g.add_argument("--noise", type=float, default=1.0, help="scale of the default noise levels (0 = noise-free)")
    g.add_argument("--rod-direction-mrad", type=float, help="rod direction noise per axis, mrad (default 0.5)")
    g.add_argument("--rod-point-mm", type=float, help="rod axis point noise, mm (default 0.5)")
    g.add_argument("--board-rotation-mrad", type=float, help="board rotation noise, mrad (default 0.3)")
    g.add_argument(
        "--board-translation-mm",
        type=float,
        nargs=3,
        metavar=("X", "Y", "DEPTH"),
        help="board translation noise along camera x, y and depth, mm (default 0.1 0.1 0.3)",
    )
    g.add_argument("--encoder-um", type=float, help="encoder noise, um (default 1)")


def register(sub: argparse._SubParsersAction) -> None:
    from calib.formats.plan import PLAN_NAMES
    from service.cli._args import non_negative_int

    p = sub.add_parser(
        "simulate",
        help="simulate the paper's acquisition on the digital twin",
        description="Run the paper's full plan on the twin's true geometry and write observations "
        "v1 (or, with --images, a rendered dataset v1), with the truth alongside.",
    )
    p.add_argument("--out", "-o", required=True, help="output observations file (or dataset directory with --images)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--images", action="store_true", help="render camera images and write a dataset directory")
    p.add_argument(
        "--plan",
        choices=PLAN_NAMES,
        default="full",
        help="the plan to simulate (default: full, the paper's; the others are its phases)",
    )
    p.add_argument(
        "--camera-views",
        type=non_negative_int,
        default=15,
        metavar="N",
        help="with --images: board views of the 'camera' phase, for the intrinsic calibration (default 15; 0: none)",
    )
    add_noise_args(p)
    p.set_defaults(handler=handler)
