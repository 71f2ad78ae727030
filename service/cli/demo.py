"""``i4cal demo``: the main job on the simulated bench, end to end.

Default: the simulated bench (a real Modbus server on loopback and the image-level twin's camera)
runs the paper's full plan through the Modbus driver; the frames are written to a dataset as they
come, extracted (board poses and rods from the images) and calibrated with the three methods. The camera is first
calibrated from board views, as a lab does (:func:`_camera_phase`; written as ``camera.json`` under ``--out``).
``--quick``: the geometric twin only (observations handed over, no images), in about a second.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from pathlib import Path
from typing import Any

#: board views of the demo's camera phase (the accuracy study's count; ``plan predict`` assumes as many)
CAMERA_VIEWS = 30


def _quick(args: argparse.Namespace, con) -> dict:
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate, to_jsonable
    from drivers.sim.twin import GeometricTwin

    con.print(
        "1. acquisition on the geometric twin: the paper's plan (rotation sweep, equal translation, "
        "20 fit poses, 4x5 locked-actuator poses, 500 mm line, validation poses)"
    )
    obs = Observations.from_dict(GeometricTwin().observations(seed=args.seed))
    con.print(f"   {len(obs.frames)} frames: " + ", ".join(f"{k} {v}" for k, v in obs.phases().items()))
    con.print("2. calibration with the three methods")
    return to_jsonable(calibrate(obs))


#: the hidden ``--small`` option's plan sizes (a reduced paper plan for the reproducibility test)
SMALL_PLAN: dict[str, Any] = {"n_base": 3, "n_fit": 5, "n_lock": 1, "n_validation": 3, "line_samples": 4}


def _camera_phase(renderer, seed: int, views: int = CAMERA_VIEWS):
    """The intrinsics as a lab obtains them: ``views`` board views held in front of the simulated camera (the
    views ``simulate_dataset`` renders for ``seed``), calibrated with the board's corners released
    (``calib.camera.intrinsics.calibrate_intrinsics``). The camera carries its covariance and the board's corners
    as the
    calibration refined them: the simulated board is printed off its nominal corners (0.2 mm RMS), and poses of
    the nominal board would be off by it; the renderer's true intrinsics carry neither."""
    import numpy as np

    from calib.camera.intrinsics import calibrate_intrinsics
    from calib.vision.board import BoardDetector

    det = BoardDetector(renderer.settings.board)
    noise = np.random.default_rng([seed, 11])
    found = {}
    for k, view in enumerate(renderer.random_board_views(views, np.random.default_rng([seed, 7]))):
        d = det.detect(renderer.render_board_view(view, noise))
        if d.ids.size:
            found[k] = (d.ids, d.pixels, None)
    size = (renderer.camera.width, renderer.camera.height)
    return calibrate_intrinsics(found, size, det.ids_all, det.points_nominal, lens_model="auto").camera


async def _acquire(out: Path, seed: int, con, small: bool = False, temporary: bool = False):
    from calib.formats.plan import make_plan
    from drivers.acquisition.acquire import acquire
    from drivers.acquisition.settings import DatasetHeader
    from drivers.sim.bench import SimBench
    from drivers.sim.twin import GeometricTwin
    from service.cli._output import LongStep

    async with SimBench(port=0, seed=seed) as bench:
        # the simulated camera renders each frame on request: 0.3 s on an idle core, several seconds on a busy
        # machine; a real camera's 2 s timeout would make the demo fail there
        cfg = bench.bench_config(camera={"timeout_s": 30.0})
        con.print(f"   simulated controller at [bold]{bench.actuators_uri}[/bold], camera at {bench.camera_uri}")
        # the plan `i4cal acquire --plan full` runs and `i4cal plan predict full` predicts (their default seed, 0);
        # the demo's seed is the bench's (truth, noise)
        plan = make_plan("full", cfg.nominal_parameters(), seed=0, **(SMALL_PLAN if small else {}))
        cam = _camera_phase(bench.renderer, seed) if hasattr(bench.renderer, "random_board_views") else None
        spec = {"K": cam.K.tolist(), "dist": list(map(float, cam.dist))} if cam is not None else {}
        truth = GeometricTwin(bench.geometry).truth_dict()
        with LongStep(con, "   acquiring poses", total=len(plan.steps)) as bar:

            def progress(p) -> None:
                bar.update(done=p.done, total=p.total)

            res = await acquire(
                plan, cfg, out, progress=progress, header=DatasetHeader(camera=spec, extra={"truth": truth})
            )
        con.print(f"   {res.frames} frames written" + (" (to a temporary directory)" if temporary else f" to {out}"))
        return cam


def _full(args: argparse.Namespace, con, base: Path) -> dict:
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate, to_jsonable
    from calib.numerics.jsonio import dumps_readable
    from calib.vision.extract import extract_dataset
    from service.cli._output import LongStep

    ds = base / "dataset"
    con.print(
        "1. acquisition on the simulated bench over Modbus TCP (loopback): the paper's full plan, "
        "camera frames rendered by the image-level twin"
    )
    camera = asyncio.run(_acquire(ds, args.seed, con, small=getattr(args, "small", False), temporary=not args.out))
    if camera is not None:
        camera.save(base / "camera.json")
    con.print("2. extraction: ChArUco board poses and the eight rods in every frame (both cores)")
    with LongStep(con, "   extracting frames") as bar:
        res = extract_dataset(ds, camera=camera, progress=lambda d, t: bar.update(done=d, total=t))
    obs_doc = res.observations
    obs = Observations.from_dict(obs_doc)
    (base / "observations.json").write_text(dumps_readable(obs_doc))
    found = sum(1 for f in obs.frames if f.board is not None)
    where = f"; observations in {base / 'observations.json'}" if args.out else ""
    con.print(f"   {len(obs.frames)} frames, {found} board poses{where}")
    con.print("3. calibration with the three methods")
    return to_jsonable(calibrate(obs))


def handler(args: argparse.Namespace) -> int:
    from service.cli._output import make_console, print_result

    con = make_console()
    t0 = time.perf_counter()
    con.rule("[bold]i4cal demo[/bold] - simulated I4 bench")
    if args.quick:
        doc = _quick(args, con)
    elif args.out:
        doc = _full(args, con, Path(args.out))
    else:
        # nothing left behind unless asked (--out): the dataset (about 50 MB of images) lives in a temporary
        # directory removed at the end
        with tempfile.TemporaryDirectory(prefix="i4cal-demo-") as tmp:
            doc = _full(args, con, Path(tmp))
    result = None
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        result = str(Path(args.out) / "result.json")
        Path(result).write_text(json.dumps(doc, indent=1), encoding="utf-8")
    print_result(doc, con, result=result)
    if args.out:
        kept = "result.json" if args.quick else "dataset/, observations.json, result.json"
        con.print(f"kept in {args.out}: {kept}")
    else:
        con.print("nothing kept (the demo's files were temporary): --out DIR keeps the dataset and the result")
    con.print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the simulated bench end to end and calibrate it with all methods",
        description="The main job on the simulated bench: acquire the paper's plan over Modbus, "
        "extract the images, calibrate with the three methods and print the "
        "comparison (the paper's Tables I-III).",
    )
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--quick", action="store_true", help="geometric twin only (no images, about a second)")
    p.add_argument(
        "--out", help="keep the dataset, observations and result in this directory (default: nothing is kept)"
    )
    # a reduced plan (fewer poses, a 9-sample line): tests only
    p.add_argument("--small", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(handler=handler)
