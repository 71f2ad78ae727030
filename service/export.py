"""The calibration document (``i4cal.calibration/1``, :mod:`calib.identify.export`) of a run or a result file, as JSON
or
YAML text: what ``i4cal export`` writes and ``GET /api/v1/runs/{id}/export`` and ``GET /api/v1/calibration/current``
serve (docs/export.md)."""

from __future__ import annotations

import json
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from calib.errors import InputError
from calib.formats.plan import Plan
from calib.formats.resultdoc import RESULT_FORMAT, MethodEntry, ResultDocument
from calib.identify.export import CalibrationDocument, ExportContext, build_calibration, load_calibration
from service.timefmt import iso_utc

Format = Literal["json", "yaml"]
FORMATS: tuple[str, ...] = ("json", "yaml")
MEDIA_TYPES = {"json": "application/json", "yaml": "application/yaml"}


def dumps(doc: CalibrationDocument, fmt: str = "json") -> str:
    """The document as JSON (indented) or YAML (block style, keys in the document's order). Both write each float's
    shortest round-trip form: the numbers read back are the numbers written."""
    data = doc.model_dump(mode="json")
    if fmt == "yaml":
        import yaml

        return yaml.safe_dump(data, sort_keys=False, allow_unicode=True, default_flow_style=False, width=120)
    if fmt != "json":
        raise InputError(f"unknown format {fmt!r}; formats are {', '.join(FORMATS)}", field="format")
    return json.dumps(data, indent=1, ensure_ascii=False) + "\n"


def loads(text: str, source: str | None = None) -> CalibrationDocument:
    """An ``i4cal.calibration/1`` document from JSON or YAML text (YAML is a superset of JSON: one parser reads both,
    JSON first for its clearer errors).

    Raises
    ------
    InputError
        Not parseable, or not a valid document (names the file and the field).
    """
    try:
        data = json.loads(text)
    except ValueError:
        import yaml

        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise InputError(f"neither JSON nor YAML: {exc}", file=source) from None
    return load_calibration(data, source=source)


def _iso(dt: datetime | None) -> str | None:
    return None if dt is None else iso_utc(dt)


# -- the dataset's hash, once per dataset --------------------------------------------------------------------------
_hash_lock = threading.Lock()
_hash_cache: dict[tuple[str, int, int], str] = {}


def dataset_hash(dataset_dir: Path | None) -> str | None:
    """SHA-256 of a dataset (``service.report.analysis.dataset_sha256``: its manifest of dataset.json and frames);
    None without a dataset. Kept per dataset (path, dataset.json's size and modification time): a controller polling
    the current calibration does not hash every frame again."""
    if dataset_dir is None:
        return None
    meta = Path(dataset_dir) / "dataset.json"
    try:
        st = meta.stat()
    except OSError:
        return None
    key = (str(Path(dataset_dir).resolve()), st.st_size, st.st_mtime_ns)
    with _hash_lock:
        if key in _hash_cache:
            return _hash_cache[key]
    from service.report.analysis import dataset_sha256

    digest = dataset_sha256(Path(dataset_dir))[0]
    with _hash_lock:
        _hash_cache[key] = digest
    return digest


def result_sha256(result: ResultDocument | dict[str, Any]) -> str:
    """SHA-256 of a result document's JSON in canonical form (``service.report.analysis.json_sha256``)."""
    from service.report.analysis import json_sha256

    return json_sha256(result.to_dict() if isinstance(result, ResultDocument) else result)


# -- from a run -------------------------------------------------------------------------------------------------------
def run_dataset_dir(data_dir: Path, run: Any) -> Path | None:
    """The run's dataset directory inside the data directory, None when it is not there."""
    root = Path(data_dir).resolve()
    ds = (root / run.dataset_dir).resolve()
    return ds if root in ds.parents and (ds / "dataset.json").is_file() else None


def run_context(data_dir: Path, run: Any, software_version: str | None = None) -> ExportContext:
    """The provenance of a run's result: its bench, id, end time and dataset hash."""
    from service import __version__

    return ExportContext(
        software_version=software_version or __version__,
        bench=run.bench,
        run=run.id,
        date=_iso(run.finished_at),
        exported_at=iso_utc(datetime.now(UTC)),
        dataset_hash=dataset_hash(run_dataset_dir(data_dir, run)),
        result_sha256=result_sha256(run.result),
    )


def run_document(data_dir: Path, run: Any, method: str | None = None, **context: Any) -> CalibrationDocument:
    """The calibration document of ``method`` (default: the recommended one) of a finished run's result.

    Raises
    ------
    InputError
        The run has no result, or no converged result for the method (``field="method"``).
    """
    if run.result is None:
        raise InputError(f"run {run.id} is {run.state} and has no result yet; nothing to export", field="run")
    ctx = run_context(data_dir, run)
    if context:
        from dataclasses import replace

        ctx = replace(ctx, **context)
    return build_calibration(run.result, ctx, method)


def run_plan(data_dir: Path, run: Any) -> Plan | None:
    """The plan a run executed; an offline run: the plan its dataset records, else its frames' joint vectors
    (:func:`dataset_plan`); None when there is neither."""
    if run.plan:
        try:
            return Plan.from_dict(run.plan, source=f"run {run.id}")
        except InputError:
            pass
    ds = run_dataset_dir(data_dir, run)
    return None if ds is None else dataset_plan(ds)


def dataset_plan(dataset_dir: Path) -> Plan | None:
    """The plan a dataset records (``plan``), else one step per frame with its joint values (what was executed);
    None when the dataset holds neither."""
    try:
        doc = json.loads((Path(dataset_dir) / "dataset.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if isinstance(doc, dict) and doc.get("plan"):
        try:
            return Plan.from_dict(doc["plan"], source=str(dataset_dir))
        except InputError:
            pass
    frames = doc.get("frames") if isinstance(doc, dict) else None
    steps = [{"phase": f["phase"], "q": f["q"]} for f in frames or [] if isinstance(f, dict) and "q" in f]
    if not steps:
        return None
    try:
        return Plan.from_dict({"name": f"the frames of {Path(dataset_dir).name}", "steps": steps}, str(dataset_dir))
    except InputError:
        return None


# -- from a file ------------------------------------------------------------------------------------------------------
def file_context(path: Path, result: Any, dataset_dir: Path | None = None) -> ExportContext:
    """The provenance of a result file: its modification time as the date, the dataset's hash when given."""
    from service import __version__

    mtime = datetime.fromtimestamp(Path(path).stat().st_mtime, UTC)
    return ExportContext(
        software_version=__version__,
        date=iso_utc(mtime),
        exported_at=iso_utc(datetime.now(UTC)),
        dataset_hash=dataset_hash(dataset_dir),
        result_sha256=result_sha256(result),
        result_file=str(Path(path).resolve()),
    )


def payload_result(payload: dict[str, Any]) -> ResultDocument:
    """A result document holding the one method an applied calibration's record keeps (``calibrations.payload``):
    for a calibration whose run's result is no longer stored (no covariance then)."""
    entry: dict[str, Any] = {
        "converged": True,
        "combinations": payload.get("combinations"),
        "combinations_std": payload.get("combinations_std"),
    }
    if payload.get("parameters"):
        entry["seven"] = payload["parameters"]
        entry["seven_std"] = payload.get("parameters_std")
    return ResultDocument.from_dict(
        {
            "format": RESULT_FORMAT,
            "nominal": payload.get("nominal") or {},
            "methods": {payload.get("method") or "unknown": MethodEntry.model_validate(entry)},
        }
    )


__all__ = [
    "FORMATS",
    "MEDIA_TYPES",
    "dataset_hash",
    "dataset_plan",
    "dumps",
    "file_context",
    "loads",
    "payload_result",
    "run_context",
    "run_document",
    "run_plan",
]
