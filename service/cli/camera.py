"""``i4cal camera calibrate --bench B -o camera.json``: the camera's intrinsics from hand-held board views.

The first step on a bench (the paper's ref. [19]): the I4 turns its board only about the vertical, which cannot fix
the focal length, so the board is held up by hand. The bench's operator (``[operator] uri``: ``console``, a person
pressing Enter; ``sim://``, the simulated bench's operator) is told where to hold it; each view is grabbed, detected
and checked at once (:class:`calib.camera.views.ViewGuide`), and what is still missing is said in words (image
corners, tilts, distances, count). Then the intrinsics are calibrated with the lens model chosen by the data
(:func:`calib.camera.intrinsics.calibrate_intrinsics`), the result and its evidence printed and written as
``i4cal.camera/1``
(docs/camera.md), which the bench file names (``[camera] intrinsics``) and every acquisition records.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path
from typing import Any


def register(subparsers: argparse._SubParsersAction) -> None:
    from service.cli._args import positive_int

    p = subparsers.add_parser("camera", help="the camera's intrinsics: calibrate them from hand-held board views")
    sub = p.add_subparsers(dest="camera_command", metavar="SUBCOMMAND")
    c = sub.add_parser(
        "calibrate",
        help="guide an operator through hand-held board views and calibrate the camera's intrinsics",
        description=(
            "Asks the bench's operator to hold the ChArUco board (the end-effector's) at a series of placements, "
            "grabs and checks each view at once (whole board found, not a repeat, consistent with the others), says "
            "what is still missing (image corners, tilts about both image axes, near and far views, count), then "
            "calibrates the intrinsics with the lens model chosen by the data (BIC) and writes an i4cal.camera/1 "
            'file. Name it in the bench file ([camera] intrinsics = "camera.json") so that every acquisition '
            "records it (docs/camera.md)."
        ),
    )
    c.add_argument("--bench", required=True, help="bench configuration file (TOML): the camera and the operator")
    c.add_argument("-o", "--output", required=True, metavar="JSON", help="camera file to write (i4cal.camera/1)")
    c.add_argument(
        "--views", type=positive_int, default=15, metavar="N", help="full-board views to keep, at least (default 15)"
    )
    c.add_argument(
        "--max-grabs",
        type=positive_int,
        default=None,
        metavar="N",
        help="give up after this many grabs when the views still miss something (default 3 x views + 20)",
    )
    c.add_argument(
        "--lens-model",
        default=None,
        metavar="MODEL",
        help="auto (chosen by BIC over the views), k1k2, k1k2k3, rational, or one of them with -radial; default: "
        "the bench file's camera.lens_model, else auto",
    )
    c.set_defaults(handler=run)
    p.set_defaults(handler=lambda args: (p.print_help(), 1)[1])


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from drivers.acquisition.config import load_bench
    from service.camera_session import calibrate_views, check_lens_model, collect_views
    from service.cli.calibrate import check_output_file

    check_output_file(args.output, "-o/--output")
    cfg = load_bench(args.bench)
    lens = check_lens_model(args.lens_model or cfg.camera.lens_model or "auto", "--lens-model")
    console = Console(stderr=True, highlight=False)
    max_grabs = args.max_grabs or 3 * args.views + 20
    session = asyncio.run(collect_views(cfg, args.views, max_grabs, console.print))
    console.print(
        f"views cover the image, the tilts and the distances: {len(session.guide.kept)} kept of {session.grabs} grabs"
    )
    res, camera = calibrate_views(session, cfg, lens, str(Path(args.bench).resolve()))
    camera.save(args.output)
    print_evidence(res, console)
    console.print(
        f'wrote {args.output}; name it in the bench file (\\[camera] intrinsics = "{Path(args.output).name}", relative '
        "to the bench file) so that `i4cal acquire` records it in every dataset"
    )
    return 0


def print_evidence(res, console) -> None:
    """The calibration's result and its evidence: intrinsics with std, the lens models compared, residuals."""
    from rich.table import Table

    cam = res.camera
    cal = cam.extra.get("calibration") or {}
    lm = res.lens_model or {}
    std = res.std
    t = Table(title=f"intrinsics ({len(res.per_view_rms_px)} views, 1 std)")
    for col in ("parameter", "value", "std"):
        t.add_column(col, justify="right")
    values = {"fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2]}
    for name, val in values.items():
        t.add_row(f"{name} (px)", f"{val:.2f}", f"{std.get(name, float('nan')):.2f}")
    for name in cal.get("covariance_params") or []:
        if name in values:
            continue
        idx = {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4, "k4": 5, "k5": 6, "k6": 7}.get(name)
        if idx is not None and idx < cam.dist.size:
            t.add_row(name, f"{cam.dist[idx]:+.5f}", f"{std.get(name, float('nan')):.5f}")
    console.print(t)
    lt = Table(
        title=f"lens model: {lm.get('chosen')} ({'chosen by BIC' if lm.get('requested') == 'auto' else 'given'})"
    )
    for col in ("model", "parameters", "RMS (px)", "dBIC", "allowed"):
        lt.add_column(col, justify="right")
    for e in lm.get("candidates") or []:
        d = e.get("delta_bic")
        lt.add_row(
            e["model"],
            str(e["n_params"]),
            f"{e['rms_px']:.3f}",
            "-" if d is None else f"{d:+.1f}",
            "yes" if e.get("allowed", True) else f"no: {_not_allowed(e)}",
        )
    console.print(lt)
    sig = cal.get("view_sigma_px")
    prof = lm.get("residual_profile") or {}
    console.print(
        f"reprojection RMS {res.rms_px:.3f} px"
        + (f"; views weighted by their corner noise ({min(sig):.3f}-{max(sig):.3f} px)" if sig else "")
        + f"; views reach {100 * lm.get('field_coverage', 1.0):.0f}% of the image's corner radius"
        + f"; radial model error up to {prof.get('max_systematic_px', 0.0):.3f} px"
    )
    for k, reason in res.rejected.items():
        console.print(f"view {k} left out: {reason}")
    for w in lm.get("warnings") or []:
        console.print(f"[yellow]warning[/]: {w}")


def _not_allowed(e: dict[str, Any]) -> str:
    if e.get("not_allowed_because"):
        return str(e["not_allowed_because"])
    if e.get("tangential_bound_px") is not None:
        return f"tangential terms may reach {e['tangential_bound_px']:.2f} px at the image's corner"
    return "not allowed"
