"""``i4cal calibrate``: identify the parameters from observations (or a dataset) and print Tables I-III."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from calib.errors import InputError
from calib.formats.observations import Observations
from calib.identify.pipeline import calibrate, to_jsonable
from calib.identify.registry import method_names


def load_observations(path: str, console=None, camera: str | None = None) -> Observations:
    """An observations file, or a dataset directory (extracted on the fly; ``camera``: an i4cal.camera/1 file for a
    dataset that records no intrinsics)."""
    p = Path(path)
    if p.is_dir() or p.name == "dataset.json":
        try:
            from calib.formats.camera import CameraModel
            from calib.vision.extract import extract_dataset
        except ImportError as exc:  # pragma: no cover
            raise InputError(f"cannot extract a dataset here: {exc}", file=str(p)) from None
        cam = CameraModel.load(camera) if camera else None
        return Observations.from_dict(extract_dataset(p, camera=cam).observations, source=str(p))
    if camera:
        raise InputError("--camera applies to a dataset (observations already carry their camera)", file=str(p))
    return Observations.load(p)


def check_output_file(path: str, option: str) -> None:
    """Refuse, before any work, an output file whose directory is missing or that is a directory."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{option}: is a directory; give a file name", file=str(p))
    if not p.parent.is_dir():
        raise InputError(f"{option}: directory {p.parent} does not exist", file=str(p))


def handler(args: argparse.Namespace) -> int:
    from rich.console import Console

    from service.cli._output import make_console, print_result

    methods = list(method_names()) if args.method == "all" else [args.method]
    if args.output:
        check_output_file(args.output, "-o/--output")
    err = Console(stderr=True)
    obs = load_observations(args.observations, camera=args.camera)
    with err.status("calibrating...", spinner="dots") if not args.json else _Null():
        doc = calibrate(obs, methods, strict=args.method != "all")
    doc = to_jsonable(doc)
    if args.output:
        Path(args.output).write_text(json.dumps(doc, indent=1), encoding="utf-8")
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
    else:
        print_result(doc, make_console(), result=args.output)
    if args.output:
        err.print(f"wrote {args.output} (the result: i4cal report, i4cal export)", highlight=False, soft_wrap=True)
    failed = [m for m, e in doc["methods"].items() if not e.get("converged")]
    return 1 if failed and len(failed) == len(methods) else 0


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="identify the kinematic parameters from observations or a dataset",
        description="Identify the I4 parameters with one or all methods and print the paper's "
        "Tables I-III (a priori vs each method, displacement gaps, straightness).",
    )
    p.add_argument("observations", metavar="OBS", help="observations v1 JSON file, or a dataset v1 directory")
    p.add_argument(
        "--method",
        "-m",
        default="all",
        choices=[*method_names(), "all"],
        help="identification method (calib.identify.registry) or all (default)",
    )
    p.add_argument(
        "--camera",
        metavar="JSON",
        default=None,
        help="with a dataset: its camera's intrinsics (i4cal.camera/1, `i4cal camera calibrate`) when the dataset "
        "records none; default: the dataset's, else calibrated from its 'camera' phase",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object to stdout")
    p.add_argument("-o", "--output", help="also write the result JSON to this file")
    p.set_defaults(handler=handler)
