"""``i4cal extract DATASET -o OBS``: dataset v1 (images) -> observations v1."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.console import Console

    from calib.formats.camera import CameraModel
    from calib.vision.extract import ExtractionResult, ExtractOptions


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "extract",
        help="extract board poses and rod axes from a recorded dataset (images) into observations v1",
        description=(
            "Reads a dataset v1 directory, calibrates the intrinsics from its 'camera' phase (unless "
            "given), measures the ChArUco board pose and the eight rods in every frame, writes "
            "observations v1 and prints what was found and missing per phase."
        ),
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset directory (or its dataset.json)")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="observations v1 JSON to write")
    p.add_argument("--workers", type=int, default=None, metavar="N", help="processes (default: all cores)")
    p.add_argument(
        "--camera",
        metavar="JSON",
        default=None,
        help="known intrinsics (i4cal.camera/1 JSON); default: the dataset's, else calibrated",
    )
    p.add_argument("--camera-out", metavar="JSON", default=None, help="also save the intrinsics used")
    p.add_argument("--min-corners", type=int, default=6, help="fewer ChArUco corners: board missing (default 6)")
    p.add_argument(
        "--no-refine-camera",
        dest="refine_camera",
        action="store_false",
        help="do not let the rods refine the camera and measure the frames again with it (faster: one "
        "pass; less accurate when the camera calibration is off)",
    )
    p.add_argument(
        "--no-repredict",
        dest="repredict",
        action="store_false",
        help="look for the rods near the nominal model's prediction only (one pass over the rods); by default the "
        "prediction is refitted to what that pass measured and the frames it moves by more than 3 px are measured "
        "again (a bench far from its nominal geometry keeps its rods)",
    )
    p.add_argument(
        "--no-recover",
        dest="recover",
        action="store_false",
        help="keep the extraction even when more than 5%% of the rods looked for are lost in their search bands; by "
        "default the prediction is then refitted robustly (each measured line its rod, its leg's other rod or the "
        "gap between them) and every frame measured again, kept when it loses fewer rods",
    )
    p.add_argument(
        "--lens-model",
        default=None,
        metavar="MODEL",
        help="lens model of the camera calibration: auto (chosen from the camera phase's board views by BIC), "
        "k1k2, k1k2k3, rational, or one of them with -radial (no tangential terms); default: the dataset's "
        "(the bench file's camera.lens_model), else auto",
    )
    p.add_argument(
        "--rod-phases",
        default=None,
        metavar="PHASES",
        help="the phases whose rods the observations carry: comma-separated phase names, or all; default: those a "
        "method or the report reads (poses, lock-1..lock-4, validation); the others' frames keep their boards",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from calib.formats.camera import CameraModel
    from calib.formats.observations import Observations
    from calib.numerics.jsonio import dumps_readable

    console = Console(stderr=True)
    opts = _options(args)
    cam = CameraModel.load(args.camera) if args.camera else None
    res = _extract(args, cam, opts, console)
    obs = Observations.from_dict(res.observations, source=str(args.output))
    out = Path(args.output)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(dumps_readable(obs.to_dict()), encoding="utf-8")  # the C encoder: indent=1 is pure Python
    tmp.replace(out)
    if args.camera_out:
        res.camera.save(args.camera_out)
    if res.intrinsics is not None:
        _print_intrinsics(console, res, args.camera_out)
    s = res.summary
    _print_camera_refinement(console, s)
    _print_repredicted(console, s)
    _print_recovered(console, s)
    _print_phases(console, s)
    console.print(f"wrote {out} ({len(obs.frames)} frames)")
    return 0


def _options(args: argparse.Namespace) -> ExtractOptions:
    """The extraction's settings from the command line (the lens model checked)."""
    from calib.camera.intrinsics import LENS_MODEL_CHOICES
    from calib.errors import InputError
    from calib.vision.extract import ExtractOptions

    if args.lens_model is not None and args.lens_model not in LENS_MODEL_CHOICES:
        raise InputError(
            f"unknown lens model {args.lens_model!r}; lens models are {', '.join(LENS_MODEL_CHOICES)}",
            field="--lens-model",
        )
    return ExtractOptions(
        rod_phases=_rod_phases(args.rod_phases),
        min_corners=args.min_corners,
        refine_camera=args.refine_camera,
        lens_model=args.lens_model,
        repredict_px=ExtractOptions.repredict_px if args.repredict else None,
        recover_lost_share=ExtractOptions.recover_lost_share if args.recover else None,
    )


def _rod_phases(value: str | None) -> tuple[str, ...] | None:
    """``--rod-phases``: None (all), the default phases, or those named (each checked)."""
    from calib.errors import InputError
    from calib.formats.observations import PHASES
    from calib.vision.extract import ROD_PHASES

    if value is None:
        return ROD_PHASES
    if value.strip() == "all":
        return None
    names = tuple(n.strip() for n in value.split(",") if n.strip())
    unknown = [n for n in names if n not in PHASES]
    if unknown or not names:
        raise InputError(
            f"unknown phase {', '.join(unknown) or repr(value)}; phases are {', '.join(PHASES)}, or all",
            field="--rod-phases",
        )
    return names


def _extract(
    args: argparse.Namespace, cam: CameraModel | None, opts: ExtractOptions, console: Console
) -> ExtractionResult:
    """The extraction, with a progress bar unless ``--quiet``."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from calib.vision.extract import extract_dataset

    if args.quiet:
        return extract_dataset(args.dataset, camera=cam, workers=args.workers, options=opts)
    with Progress(
        TextColumn("extract"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("extract", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        return extract_dataset(args.dataset, camera=cam, workers=args.workers, progress=progress, options=opts)


def _print_intrinsics(console: Console, res: ExtractionResult, camera_out: str | None) -> None:
    """The camera calibrated from the ``camera`` phase: its fit and lens model."""
    i = res.intrinsics
    assert i is not None
    sig = (i.camera.extra.get("calibration") or {}).get("view_sigma_px")
    console.print(
        f"intrinsics: calibrated from {len(i.per_view_rms_px)} views, RMS {i.rms_px:.3f} px, "
        f"fx {res.camera.fx:.2f} +/- {i.std.get('fx', float('nan')):.2f} px, "
        f"{len(i.rejected)} views rejected"
        + (f"; views weighted by their corner noise ({min(sig):.3f}-{max(sig):.3f} px)" if sig else "")
    )
    lm = i.lens_model or {}
    if not lm:
        return
    prof = lm.get("residual_profile") or {}
    where = f"evidence in {camera_out} (calibration.lens_model)" if camera_out else "evidence: --camera-out FILE"
    how = "chosen by BIC" if lm.get("requested") == "auto" else "given"
    console.print(
        f"lens model: {lm['chosen']} ({how} among {len(lm.get('candidates', []))}; radial model error up to "
        f"{prof.get('max_systematic_px', 0.0):.3f} px); {where}",
        highlight=False,
        soft_wrap=True,  # a path is never cut across lines
    )
    for w in lm.get("warnings") or []:
        console.print(f"warning: {w}")


def _print_camera_refinement(console: Console, s: dict[str, Any]) -> None:
    ref = (s.get("camera") or {}).get("refined_by_rods") or {}
    if ref.get("applied"):
        sh = ref["shift"]
        n = s.get("rods_frames") or {}
        again = f"rods of {n['reexpressed']} frames re-expressed for it, {n['measured']} frames measured" if n else ""
        console.print(
            f"camera refined by the rods ({ref['mahalanobis']:.1f} std: fx {sh['fx']:+.2f}, "
            f"cx {sh['cx']:+.2f}, cy {sh['cy']:+.2f} px, k1 {sh['k1']:+.4f}); {again}"
        )
    elif ref:
        console.print(f"camera not refined: {ref.get('reason')}")


def _print_repredicted(console: Console, s: dict[str, Any]) -> None:
    rp = s.get("repredicted") or {}
    rp0 = rp.get("first_camera_pass") or rp
    if rp0.get("median_px_before") is not None:
        console.print(
            f"rods' prediction refitted to the first pass ({rp0['rods']} rods, {rp0['boards']} boards): measured rods "
            f"{rp0['median_px_before']:.1f} px from the nominal prediction (median), {rp0['median_px_after']:.2f} px "
            f"from the refitted one; {rp0['frames_measured_again']} frames measured again"
        )
    elif rp0.get("reason"):
        console.print(f"rods' prediction not refitted: {rp0['reason']}")


def _print_recovered(console: Console, s: dict[str, Any]) -> None:
    rec = s.get("recovered")
    if not rec:
        return
    kinds = ", ".join(f"{k} {v}" for k, v in ((rec.get("refit") or {}).get("lines_explained_as") or {}).items())
    console.print(
        f"rods lost in their search bands: {rec['lost_before']} of {rec['looked_for_before']} looked for (more "
        f"than {rec['share']:.0%}): "
        + (
            f"prediction refitted robustly (lines explained as {kinds}"
            f"; {rec['refit']['starts']} starts), every frame measured again: {rec['lost_after']} lost"
            + ("" if rec["applied"] else f"; not kept: {rec['reason']}")
            if rec.get("refit")
            else f"not recovered: {rec['reason']}"
        )
    )


def _print_phases(console: Console, s: dict[str, Any]) -> None:
    """The coarse placement, the table of what was found per phase and the corners left out."""
    from rich.console import Console
    from rich.table import Table

    pl = s["placement"]
    console.print(
        "coarse camera placement: "
        + (f"ok (board residual RMS {pl['rms_m'] * 1e3:.2f} mm)" if pl["ok"] else str(pl["reason"]))
    )
    t = Table(title="found per phase")
    for col in ("phase", "frames", "board", "rods", "missing (count)"):
        t.add_column(col)
    for ph, c in s["phases"].items():
        miss = "; ".join(f"{k} x{v}" for k, v in sorted(c["missing"].items(), key=lambda kv: -kv[1]))
        rods = f"{c['rods']}/{c['rods_total']}" if c["rods_total"] or not c.get("rods_not_read") else "not read"
        t.add_row(ph, str(c["frames"]), f"{c['board']}/{c['frames']}", rods, miss or "-")
    Console().print(t)
    out_corners = {ph: c["corners_rejected"] for ph, c in s["phases"].items() if c.get("corners_rejected")}
    if out_corners:
        console.print(
            f"board corners left out of the poses, their residual beyond the others' scatter (next to an occluding "
            f"rod, a glint): {sum(out_corners.values())} ("
            + ", ".join(f"{ph} {n}" for ph, n in out_corners.items())
            + ")"
        )
