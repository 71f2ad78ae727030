"""``i4cal report RUN|DATASET -o report.html``: the calibration report as one self-contained HTML file."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING

from calib.errors import I4calError, InputError
from calib.identify.registry import method_names

if TYPE_CHECKING:
    from service.cli._output import LongStep


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="write the calibration report (HTML, opens offline) of a run or a dataset",
        description=(
            "Build one self-contained HTML report: parameters with standard and expanded uncertainties, "
            "the Cramer-Rao bound, validation (Tables II, III), residuals per pose and leg, "
            "identifiability, camera calibration, the frames of the worst poses, hashes. TARGET is a "
            "dataset directory (extracted and calibrated), an observations v1 file (calibrated), a result "
            "file (i4cal calibrate -o), or the id (or a unique prefix) of a run of the service."
        ),
    )
    p.add_argument("target", metavar="RUN|DATASET", help="run id, dataset directory, observations or result file")
    p.add_argument("-o", "--output", required=True, metavar="HTML", help="report file to write")
    p.add_argument(
        "--methods",
        nargs="+",
        default=["all"],
        choices=[*method_names(), "all"],
        metavar="METHOD",
        help=f"methods to calibrate with / to show: {', '.join(method_names())} or all (default)",
    )
    p.add_argument("--config", metavar="TOML", help="service configuration (for RUN: where the data directory is)")
    p.add_argument("--server", metavar="URL", help="fetch the report of RUN from a running service")
    p.add_argument(
        "--token", default=os.environ.get("I4CAL_TOKEN"), help="bearer token for --server (default: $I4CAL_TOKEN)"
    )
    p.add_argument("--observations", metavar="OBS", help="observations v1 to show with a result file")
    p.add_argument(
        "--dataset", metavar="DIR", help="dataset directory whose frames to show with a result or observations file"
    )
    p.add_argument("--workers", type=int, default=None, metavar="N", help="extraction processes (default: all cores)")
    p.add_argument("--frames", type=int, default=3, metavar="N", help="worst poses to show as frames (default 3)")
    p.add_argument(
        "--extract",
        action="store_true",
        help="for a DATASET: extract its images again even when its observations.json (inside or beside it, written "
        "after the dataset) already exists",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=handler)


def handler(args: argparse.Namespace) -> int:
    from rich.console import Console

    methods = list(method_names()) if "all" in args.methods else list(dict.fromkeys(args.methods))
    out = Path(args.output)
    if not out.parent.is_dir():
        raise InputError("output directory does not exist", file=str(out.parent))
    err = Console(stderr=True)
    with _StageProgress(err, args.quiet) as progress:
        if args.server:
            progress("fetching", 0, 0)
            html = fetch_report(args.server, args.target, args.token, None if "all" in args.methods else methods)
        else:
            from service.report import build_report

            inputs = resolve_inputs(args, methods, progress)
            html = build_report(
                inputs, progress=lambda d, t, _label: progress("report", d, t), max_frames=max(0, args.frames)
            )
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(html, encoding="utf-8")
    tmp.replace(out)
    err.print(f"wrote {out} ({len(html.encode()) / 1024:.0f} kB)", soft_wrap=True)
    return 0


class _StageProgress:
    """The report's stages (extract, calibrate, report; fetching): rich bars on a terminal, plain periodic lines
    otherwise (``_output.LongStep``), nothing with ``--quiet``. Called as ``progress(stage, done, total)``."""

    def __init__(self, console, quiet: bool) -> None:
        self.console, self.quiet = console, quiet
        self.step: LongStep | None = None

    def __enter__(self):
        return self

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.quiet:
            return
        if self.step is None:  # started by the first stage, so that a mistake in the inputs stays one line
            from service.cli._output import LongStep

            self.step = LongStep(self.console, "report").__enter__()
        self.step.update(stage, done=done, total=total or None)

    def __exit__(self, *exc) -> None:
        if self.step is not None:
            self.step.__exit__(*exc)


def resolve_inputs(args: argparse.Namespace, methods: list[str], progress):
    """ReportInputs for TARGET: a path on disk, else a run of the service's data directory."""
    from rich.console import Console

    from service.report import find_run, inputs_from_path, inputs_from_run
    from service.report.sources import RUN_ID, existing_observations, read_json

    target = Path(args.target)
    if target.exists():
        ds = target if target.is_dir() else target.parent if target.name == "dataset.json" else None
        reuse = not getattr(args, "extract", False)
        found = existing_observations(ds.resolve()) if ds is not None and reuse else None
        if found is not None:
            Console(stderr=True).print(
                f"using the observations already extracted: {found} (--extract to extract again)", highlight=False
            )
        inputs = inputs_from_path(
            target.resolve(),
            methods,
            workers=args.workers,
            progress=lambda s, d, t: progress(s, d, t),
            reuse_observations=reuse,
        )
    elif RUN_ID.match(args.target):
        from service.settings import load_settings

        settings = load_settings(args.config)
        run = find_run(settings, args.target)
        inputs = inputs_from_run(settings.data_dir, run, None if "all" in args.methods else methods)
    else:
        raise InputError("no such dataset, observations or result file, and not a run id", file=args.target)
    if args.observations:
        inputs.observations = read_json(Path(args.observations))
    if args.dataset:
        d = Path(args.dataset).resolve()
        if not (d / "dataset.json").is_file():
            raise InputError("not a dataset directory (no dataset.json)", file=str(d))
        inputs.dataset_dir = d
    return inputs


def fetch_report(server: str, ident: str, token: str | None, methods: list[str] | None) -> str:
    """The report of run ``ident`` (full id or unique prefix) from a running service."""
    import httpx

    from service.report import RunNotFoundError

    base = server.rstrip("/") + "/api/v1"
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        with httpx.Client(timeout=300.0, headers=headers) as c:
            run_id = ident
            if len(ident) != 32:
                runs = _check(c.get(f"{base}/runs", params={"limit": 1000}), server, ident).json()
                found = [r["id"] for r in runs if r["id"].startswith(ident)]
                if len(found) != 1:
                    raise RunNotFoundError(
                        f"no run {ident} on {server}"
                        if not found
                        else f"run id prefix {ident!r} is ambiguous on {server}; give more digits"
                    )
                run_id = found[0]
            r = _check(
                c.get(f"{base}/runs/{run_id}/report", params=[("methods", m) for m in methods or []]), server, ident
            )
    except httpx.HTTPError as exc:
        raise I4calError(f"cannot reach the service at {server}: {exc}") from None
    return r.text


def _check(r, server: str, ident: str):
    from service.report import RunNotFoundError

    if r.status_code == 200:
        return r
    try:
        detail = r.json().get("detail")
    except ValueError:
        detail = r.text[:200]
    if r.status_code in (404, 422):
        raise RunNotFoundError(f"no run {ident} on {server}")
    if r.status_code == 409:
        raise I4calError(f"run {ident}: {detail}")
    if r.status_code == 401:
        raise I4calError(f"{server} wants a bearer token: give --token or set I4CAL_TOKEN")
    raise I4calError(f"{server} answered {r.status_code}: {detail}")
