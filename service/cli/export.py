"""``i4cal export``: the calibration a robot controller loads (``i4cal.calibration/1``, docs/export.md), and
``i4cal export --check``: does a document reproduce the result's model."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from calib.errors import I4calError, InputError
from service.cli._args import non_negative_float


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write the calibration a robot controller loads (i4cal.calibration/1, JSON or YAML), or check one",
        description=(
            "Write one method's result as an i4cal.calibration/1 document: provenance (bench, run, method, date, "
            "software version, dataset hash), the seven parameters in metres with which were identified and which "
            "fixed at nominal, the four combinations with std and covariance, the nominal, the units (docs/export.md). "
            "TARGET is a result file (i4cal calibrate -o) or the id (or a unique prefix) of a run of the service "
            "(its data directory, or --server). Default method: the verdict's (the one calibrate, the report and the "
            "dashboard recommend; docs/export.md). With --check F: reload F, rebuild the model from its seven "
            "parameters and compare its DKM and IKM with the result's own model over a plan's poses (exit 0 pass, "
            "1 fail, 2 usage error)."
        ),
    )
    p.add_argument("target", nargs="?", metavar="RESULT|RUN", help="result file, or run id (prefix) of the service")
    p.add_argument("-o", "--output", metavar="F", help="document to write (export)")
    p.add_argument("--method", "-m", metavar="M", help="method to export (default: the recommended one)")
    p.add_argument(
        "--format",
        choices=("json", "yaml"),
        help="document format (default: yaml when F ends in .yaml or .yml, else json)",
    )
    p.add_argument("--dataset", metavar="DIR", help="with a result file: the dataset it was made from (for its hash)")
    p.add_argument("--check", metavar="F", help="check document F against the result's model instead of exporting")
    p.add_argument(
        "--result",
        metavar="RESULT|RUN",
        help="with --check: the result file or run id F was exported from (default: the run F names, or its file)",
    )
    p.add_argument(
        "--plan",
        metavar="PLAN",
        help="with --check: poses to compare over, a plan name (drawn for F's nominal), a plan file or a dataset "
        "directory (its plan, else its frames; default: the run's plan or dataset; else the 'full' plan)",
    )
    p.add_argument(
        "--tolerance-m",
        type=non_negative_float,
        default=None,
        metavar="M",
        help="with --check: largest DKM/IKM difference that passes, metres (default 1e-9)",
    )
    p.add_argument("--json", action="store_true", help="with --check: print the check's figures as one JSON object")
    p.add_argument("--config", metavar="TOML", help="service configuration (for RUN: where the data directory is)")
    p.add_argument("--server", metavar="URL", help="take RUN from a running service")
    p.add_argument(
        "--token", default=os.environ.get("I4CAL_TOKEN"), help="bearer token for --server (default: $I4CAL_TOKEN)"
    )
    p.set_defaults(handler=handler)


def handler(args: argparse.Namespace) -> int:
    if args.check:
        if args.target or args.output or args.format or args.dataset or args.method:
            raise InputError("--check F takes no RESULT|RUN, -o, --format, --dataset or --method; give --result")
        return _run_check(args)
    for opt in ("result", "plan", "tolerance_m"):
        if getattr(args, opt) is not None:
            raise InputError(f"--{opt.replace('_', '-')} goes with --check F")
    if not args.target:
        raise InputError("give RESULT|RUN to export (or --check F)")
    if not args.output:
        raise InputError("give -o F, the document to write")
    return _export(args)


# -- export ------------------------------------------------------------------------------------------------------------
def _format(args: argparse.Namespace) -> str:
    if args.format:
        return args.format
    return "yaml" if Path(args.output).suffix.lower() in (".yaml", ".yml") else "json"


def _export(args: argparse.Namespace) -> int:
    from service.cli.calibrate import check_output_file
    from service.export import dumps

    check_output_file(args.output, "-o/--output")
    fmt = _format(args)
    target = Path(args.target)
    if args.server:
        text = _fetch_export(args, fmt)
    elif target.is_file():
        doc = _file_document(target, args.method, Path(args.dataset) if args.dataset else None)
        text = dumps(doc, fmt)
    else:
        if args.dataset:
            raise InputError("--dataset goes with a result file (a run knows its dataset)")
        run, data_dir = _find_run(args, args.target)
        from service.export import run_document

        text = dumps(run_document(data_dir, run, args.method), fmt)
    out = Path(args.output)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(out)
    from service.export import loads

    doc = loads(text, str(out))
    seven = ", ".join(f"{k} {v * 1e3:.4f}" for k, v in doc.seven.items())
    print(f"wrote {out} ({fmt}): {doc.method} ({doc.method_choice}); seven parameters, mm: {seven}", file=sys.stderr)
    if doc.fixed_at_nominal:
        print(f"  fixed at nominal: {', '.join(doc.fixed_at_nominal)} ({doc.completion.rule})", file=sys.stderr)
    return 0


def _read_result(path: Path) -> dict[str, Any]:
    from service.report.sources import read_json

    result = read_json(path)
    if not isinstance(result, dict) or result.get("format") != "i4cal.result/1":
        got = result.get("format") if isinstance(result, dict) else type(result).__name__
        raise InputError(f"not a result file (format {got!r}; i4cal calibrate -o writes one)", file=str(path))
    return result


def _file_document(path: Path, method: str | None, dataset: Path | None):
    from calib.identify.export import build_calibration
    from service.export import file_context

    if dataset is not None and not (dataset / "dataset.json").is_file():
        raise InputError("--dataset: not a dataset directory (no dataset.json)", file=str(dataset))
    result = _read_result(path)
    try:
        return build_calibration(result, file_context(path, result, dataset), method)
    except InputError as exc:
        raise InputError(exc.reason, file=str(path), field=exc.field) from None


def _find_run(args: argparse.Namespace, ident: str):
    """The run ``ident`` (id or unique prefix) of the service's data directory, and that directory."""
    from service.report import find_run
    from service.report.sources import RUN_ID
    from service.settings import load_settings

    if not RUN_ID.match(ident):
        raise InputError("no such result file, and not a run id", file=ident)
    settings = load_settings(args.config)
    return find_run(settings, ident), settings.data_dir


# -- a running service -------------------------------------------------------------------------------------------------
def _client(args: argparse.Namespace):
    import httpx

    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    return httpx.Client(timeout=120.0, headers=headers)


def _server_get(args: argparse.Namespace, ident: str, what: str, params: dict | None = None):
    """GET ``/runs/{id}{what}`` of ``--server`` for run ``ident`` (full id or unique prefix)."""
    import httpx

    from service.cli.report import _check as http_check  # the same error wording as i4cal report --server

    base = args.server.rstrip("/") + "/api/v1"
    try:
        with _client(args) as c:
            run_id = _server_run_id(c, base, args.server, ident)
            r = c.get(f"{base}/runs/{run_id}{what}", params=params or {})
            if r.status_code == 422 and what.startswith("/export"):
                detail = r.json().get("detail")
                msg = detail[0].get("msg") if isinstance(detail, list) and detail else detail
                raise InputError(f"{args.server}: {msg}", field="method")
            return http_check(r, args.server, ident), run_id
    except httpx.HTTPError as exc:
        raise I4calError(f"cannot reach the service at {args.server}: {exc}") from None


def _server_run_id(c, base: str, server: str, ident: str) -> str:
    from service.cli.report import _check as http_check
    from service.report import RunNotFoundError

    if len(ident) == 32:
        return ident
    runs = http_check(c.get(f"{base}/runs", params={"limit": 1000}), server, ident).json()
    found = [r["id"] for r in runs if r["id"].startswith(ident)]
    if len(found) != 1:
        raise RunNotFoundError(
            f"no run {ident} on {server}" if not found else f"run id prefix {ident!r} is ambiguous on {server}"
        )
    return found[0]


def _fetch_export(args: argparse.Namespace, fmt: str) -> str:
    if args.dataset:
        raise InputError("--dataset goes with a result file (a run knows its dataset)")
    params = {"format": fmt, **({"method": args.method} if args.method else {})}
    r, _ = _server_get(args, args.target, "/export", params)
    return r.text


# -- check -------------------------------------------------------------------------------------------------------------
def _run_check(args: argparse.Namespace) -> int:
    from calib.identify.export import REPRODUCE_TOL_M, check_parity, method_parameters, plan_joints
    from calib.model.parameters import I4Parameters
    from service.export import loads

    path = Path(args.check)
    if not path.is_file():
        raise InputError("no such document", file=str(path))
    doc = loads(path.read_text(encoding="utf-8"), str(path))
    result, recorded_plan, where = _reference(args, doc)
    try:
        reference = method_parameters(result, doc.method)
    except InputError as exc:
        raise InputError(f"{where}: {exc.reason}", field=exc.field) from None
    entry = result["methods"][doc.method]
    combos = entry.get("combinations") or entry.get("parameters")
    plan, plan_from = _plan(args, doc, recorded_plan)
    q = plan_joints(plan, I4Parameters.from_mapping(doc.nominal))  # lines as the acquisition commands them
    tol = REPRODUCE_TOL_M if args.tolerance_m is None else args.tolerance_m
    rep = check_parity(doc, reference, combos, q, tol)
    from service.export import result_sha256

    same = doc.source.result_sha256 in (None, result_sha256(result))
    if args.json:
        out = {
            "document": str(path),
            "result": where,
            "method": doc.method,
            "plan": plan_from,
            "same_result": same,
            **rep.to_dict(),
        }
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
    else:
        _print_check(path, doc.method, where, plan_from, rep, same)
    return 0 if rep.passed else 1


def _print_check(path: Path, method: str, where: str, plan_from: str, rep, same: bool) -> None:
    verdict = "PASS" if rep.passed else "FAIL"
    print(f"{path}: {method} against {where}, over {rep.n_poses} joint vectors of {plan_from}")
    if not same:
        print("  note: the result is not the one the document was exported from (its SHA-256 differs)")
    print(f"  DKM (X, Y, Z, T) largest difference: {rep.dkm_max_m:.3g} m")
    print(f"  IKM (q1..q4) largest difference:     {rep.ikm_max_m:.3g} m")
    print(f"  combinations largest difference:     {rep.combinations_max_m:.3g} m")
    if rep.T_per_rad_diff:
        print(f"  T_per_rad differs by {rep.T_per_rad_diff:.3g} m/rad")
    if rep.unreachable:
        print(f"  {rep.unreachable} joint vector(s) reached by one model and not the other")
    if rep.unreachable_both:
        print(f"  {rep.unreachable_both} joint vector(s) neither model reaches (left out)")
    print(f"{verdict} (tolerance {rep.tolerance_m:.3g} m)")


def _reference(args: argparse.Namespace, doc) -> tuple[dict[str, Any], Any, str]:
    """The result to check against, the plan recorded with it (or None), and what it is (for the output)."""
    ident = args.result or doc.run
    if args.result and Path(args.result).is_file():
        return _read_result(Path(args.result)), None, f"result file {args.result}"
    if ident:
        if args.server:
            r, run_id = _server_get(args, ident, "/result")
            return r.json(), None, f"run {run_id} on {args.server}"
        if args.result or _has_data_dir(args):
            from service.export import run_plan

            run, data_dir = _find_run(args, ident)
            if run.result is None:
                raise I4calError(f"run {run.id} is {run.state} and has no result")
            return run.result, run_plan(data_dir, run), f"run {run.id}"
    if doc.source.result_file and Path(doc.source.result_file).is_file():
        return _read_result(Path(doc.source.result_file)), None, f"result file {doc.source.result_file}"
    raise InputError(
        "give --result RESULT|RUN: the result file or run the document was exported from "
        + (f"(run {doc.run} is not in this data directory)" if doc.run else "(it names neither)"),
        file=str(args.check),
    )


def _has_data_dir(args: argparse.Namespace) -> bool:
    from service.settings import load_settings

    settings = load_settings(args.config)
    url = settings.db_url
    return not url.startswith("sqlite:///") or Path(url[len("sqlite:///") :]).is_file()


def _plan(args: argparse.Namespace, doc, recorded) -> tuple[Any, str]:
    from calib.formats.plan import PLAN_NAMES, Plan, make_plan
    from calib.model.parameters import I4Parameters

    if args.plan:
        if args.plan in PLAN_NAMES:
            return make_plan(args.plan, I4Parameters.from_mapping(doc.nominal)), f"the '{args.plan}' plan"
        if Path(args.plan).is_dir():
            from service.export import dataset_plan

            plan = dataset_plan(Path(args.plan))
            if plan is None:
                raise InputError("not a dataset directory with frames (no readable dataset.json)", file=args.plan)
            return plan, f"dataset {args.plan} ({plan.name})"
        if not Path(args.plan).is_file():
            raise InputError(f"not a plan name ({', '.join(PLAN_NAMES)}), plan file or dataset", file=args.plan)
        return Plan.load(args.plan), f"plan file {args.plan}"
    if recorded is not None:
        named = recorded.name.startswith("the frames of")
        return recorded, f"the run's plan ({recorded.name})" if named else f"the run's plan '{recorded.name}'"
    return make_plan("full", I4Parameters.from_mapping(doc.nominal)), "the 'full' plan (none recorded with the result)"
