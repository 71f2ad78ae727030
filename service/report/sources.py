"""Where a report's inputs come from: a run of the service (its data directory), or files on disk (a dataset
directory, an observations file, a result file)."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from calib.errors import I4calError, InputError
from calib.formats.resultdoc import ResultDocument
from service.report.builder import ReportInputs

RUN_ID = re.compile(r"^[0-9a-f]{6,32}$")


class RunNotFoundError(I4calError):
    """No run with this id (or id prefix) in the service's data."""


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("file not found", file=str(path)) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON: {exc}", file=str(path)) from None


def run_metadata(run: Any) -> dict[str, Any]:
    """The title-block fields of a service run (``service.db.models.Run``)."""

    def iso(t: Any) -> str | None:
        return None if t is None else t.strftime("%Y-%m-%d %H:%M:%S %Z").strip()

    return {
        "id": run.id,
        "bench": run.bench,
        "state": run.state,
        "plan": run.plan_name or (f"dataset {run.source_dataset}" if run.source_dataset else None),
        "note": run.note,
        "created_at": iso(run.created_at),
        "finished_at": iso(run.finished_at),
    }


def inputs_from_run(data_dir: str | Path, run: Any, methods: list[str] | None = None) -> ReportInputs:
    """A run's result, observations (``runs/<id>/observations.json``) and dataset, from the data directory.

    Raises
    ------
    I4calError
        The run has no result.
    """
    if run.result is None:
        raise I4calError(f"run {run.id} is {run.state} and has no result yet; nothing to report")
    data_dir = Path(data_dir).resolve()
    obs_path = data_dir / "runs" / run.id / "observations.json"
    obs = read_json(obs_path) if obs_path.is_file() else None
    ds = (data_dir / run.dataset_dir).resolve()
    ds_dir = ds if data_dir in ds.parents and (ds / "dataset.json").is_file() else None
    return ReportInputs(
        result=ResultDocument.from_dict(run.result, f"run {run.id}"),
        observations=obs,
        dataset_dir=ds_dir,
        run=run_metadata(run),
        source=f"run {run.id}",
        methods=methods,
        prediction=run.prediction,
    )


def find_run(settings: Any, ident: str) -> Any:
    """The run with this id, or the one run whose id starts with it, in the service's database.

    Raises
    ------
    RunNotFoundError
    """
    from sqlalchemy import select

    from service.db import Database
    from service.db.models import Run

    url = settings.db_url
    if url.startswith("sqlite:///"):
        db_file = Path(url[len("sqlite:///") :])
        if not db_file.is_file():
            raise RunNotFoundError(
                f"no run {ident}: no service database at {db_file} (give --config or I4CAL_DATA_DIR)"
            )
    db = Database(url)
    try:
        with db.session() as s:
            run = s.get(Run, ident)
            if run is None:
                found = list(s.scalars(select(Run).where(Run.id.startswith(ident)).limit(2)))
                if len(found) > 1:
                    raise RunNotFoundError(f"run id prefix {ident!r} is ambiguous; give more digits")
                run = found[0] if found else None
    finally:
        db.dispose()
    if run is None:
        raise RunNotFoundError(f"no run {ident} in {settings.data_dir}")
    return run


Progress = Callable[[str, int, int], None]


def existing_observations(ds_dir: Path) -> Path | None:
    """The observations already extracted from the dataset ``ds_dir``, or None.

    Looked for as ``observations.json`` inside the dataset directory, then beside it (where ``i4cal demo --out`` and
    the service keep them); kept only when written after the dataset's ``dataset.json``, produced by an extraction
    (an ``extraction`` section) and every frame's ``dataset_frame`` one of the dataset's frames.
    """
    ds_json = ds_dir / "dataset.json"
    try:
        written = ds_json.stat().st_mtime
        n_frames = len(json.loads(ds_json.read_text(encoding="utf-8")).get("frames") or [])
    except (OSError, ValueError, AttributeError):
        return None
    for cand in (ds_dir / "observations.json", ds_dir.parent / "observations.json"):
        try:
            if not cand.is_file() or cand.stat().st_mtime < written:
                continue
            doc = json.loads(cand.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        frames = doc.get("frames") if isinstance(doc, dict) else None
        if not frames or "extraction" not in doc:
            continue
        if all(isinstance(f.get("dataset_frame"), int) and 0 <= f["dataset_frame"] < n_frames for f in frames):
            return cand
    return None


def inputs_from_path(
    path: Path,
    methods: list[str],
    *,
    workers: int | None = None,
    progress: Progress | None = None,
    reuse_observations: bool = True,
) -> ReportInputs:
    """Inputs from a dataset directory (extracted, then calibrated), an observations v1 file (calibrated), or a
    result file (``i4cal calibrate -o``; shown as is).

    Parameters
    ----------
    progress : callable(stage, done, total), optional
        Stages ``"extract"`` (frames) and ``"calibrate"`` (methods).
    reuse_observations : bool
        For a dataset: use the observations already extracted from it (:func:`existing_observations`) instead of
        extracting again.
    """
    from calib.formats.observations import Observations
    from calib.identify.pipeline import RESULT_FORMAT, calibrate_document, to_jsonable

    p = Path(path)
    ds_dir = None
    if p.is_dir() or p.name == "dataset.json":
        from calib.vision.extract import extract_dataset

        ds_dir = p if p.is_dir() else p.parent
        if not (ds_dir / "dataset.json").is_file():
            raise InputError("not a dataset directory (no dataset.json)", file=str(ds_dir))
        found = existing_observations(ds_dir) if reuse_observations else None
        if found is not None:
            obs_doc = read_json(found)
        else:
            cb = (lambda d, t: progress("extract", d, t)) if progress else None
            obs_doc = to_jsonable(extract_dataset(ds_dir, workers=workers, progress=cb).observations)
    else:
        doc = read_json(p)
        fmt = doc.get("format") if isinstance(doc, dict) else None
        if fmt == RESULT_FORMAT:
            return ReportInputs(result=ResultDocument.from_dict(doc, str(p)), source=str(p), methods=methods)
        obs_doc = doc
    obs = Observations.from_dict(obs_doc, source=str(p))
    done = [0]

    def on_method(name: str, state: str) -> None:
        if state != "start":
            done[0] += 1
        if progress:
            progress("calibrate", done[0], len(methods))

    result = calibrate_document(obs, methods, progress=on_method)
    return ReportInputs(result=result, observations=obs_doc, dataset_dir=ds_dir, source=str(p), methods=methods)
