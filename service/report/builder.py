"""Assemble the calibration report: one self-contained HTML file (inline CSS, plots and frames as ``data:`` URIs)
laid out like a calibration certificate."""

from __future__ import annotations

import base64
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from calib.formats.resultdoc import Gaps, MethodEntry, ResultDocument, Straightness
from calib.identify.combined import EDGE_BIAS_STD_PX
from calib.identify.validation import vision_scale_ppm
from calib.identify.verdict import UNCERTAINTY, verdict
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES
from service.report import plots
from service.report.analysis import (
    LegResiduals,
    conditions,
    dataset_sha256,
    json_sha256,
    leg_residuals,
    method_order,
    missing_items,
    reference_method,
    worst_poses,
)
from service.report.html import Raw, bullet_list, esc, figure, kv_table, mm, num, page, section, table

Progress = Callable[[int, int, str], None]

COMBINATION_MEANING = {
    "L": ("L", "length of the (equivalent) legs"),
    "H-D": ("H - D", "half-distance of the actuator axes minus the half-spacing of the plate joints along y_B"),
    "S-q02/2": ("S - q02/2", "plate half-spacing along x_B against the encoder offset of actuator 2"),
    "S-(q04-q03)/2": ("S - (q04 - q03)/2", "plate half-spacing along x_B against the offsets of actuators 3, 4"),
}
K_COVERAGE = 2.0


@dataclass
class ReportInputs:
    """What a report is made from.

    Attributes
    ----------
    result : ResultDocument or dict
        The result document of :func:`calib.identify.pipeline.calibrate_document` (or its JSON, ``i4cal calibrate
        --json``,
        of any age), metres.
    observations : dict, optional
        The observations v1 document (with its ``extraction`` section when produced from images).
    dataset_dir : Path, optional
        The dataset v1 directory (frames).
    run : dict, optional
        Service run metadata: ``id``, ``bench``, ``state``, ``plan``, ``note``, ``created_at``, ``finished_at``.
    prediction : dict, optional
        The run's prediction before motion (``Run.prediction``: ``predicted_std_m`` per method and combination,
        ``motion_time_s``), set beside what the methods report.
    source : str
        What the report was made from (run id, dataset or file path), for the title block.
    methods : list of str, optional
        Methods to show (default: every method of the result).
    """

    result: ResultDocument | dict[str, Any]
    observations: dict[str, Any] | None = None
    dataset_dir: Path | None = None
    run: dict[str, Any] | None = None
    source: str = ""
    methods: list[str] | None = None
    extra_rows: list[tuple[str, str]] = field(default_factory=list)
    prediction: dict[str, Any] | None = None


def build_report(inputs: ReportInputs, *, progress: Progress | None = None, max_frames: int = 3) -> str:
    """The report as one HTML document (str).

    Parameters
    ----------
    inputs : ReportInputs
    progress : callable(done, total, label), optional
    max_frames : int
        Frames shown (the poses with the largest leg residuals).
    """
    from service import __version__

    res = ResultDocument.from_dict(inputs.result, inputs.source or None)
    ms = res.methods
    methods = [m for m in method_order(ms) if m in ms and (not inputs.methods or m in inputs.methods)]
    obs_doc = inputs.observations
    steps = 9
    done = [0]

    def step(label: str) -> None:
        done[0] += 1
        if progress:
            progress(done[0], steps, label)

    ds_doc = None
    missing_files: list[str]
    ds_hash, n_files, missing_files = None, 0, []
    if inputs.dataset_dir is not None:
        ds_doc = json.loads((inputs.dataset_dir / "dataset.json").read_text(encoding="utf-8"))
        ds_hash, n_files, missing_files = dataset_sha256(inputs.dataset_dir)
    step("hashes")
    obs = None
    residuals: dict[str, LegResiduals | None] = {}
    if obs_doc is not None:
        from calib.formats.observations import Observations

        obs = Observations.from_dict(obs_doc)
        residuals = {m: leg_residuals(obs, res, m) for m in methods}
    step("residuals")
    truth = _truth_combinations(res, obs_doc)
    body: list[str] = [
        _title_block(inputs, res, methods, ds_doc, ds_hash, n_files, __version__),
        _verdict(res, inputs),
        _contents(),
    ]
    body.append(_parameters(res, methods, truth))
    step("parameters")
    body.append(_budget(res, methods))
    body.append(_predicted(inputs.prediction, res, methods))
    body.append(_combinations(res, methods))
    body.append(_validation(res))
    step("validation")
    body.append(_residuals(residuals))
    step("residuals plot")
    body.append(_identifiability(res, methods))
    step("identifiability")
    body.append(_camera(obs_doc))
    step("camera")
    ref = reference_method(res, methods)
    body.append(_frames(inputs.dataset_dir, ds_doc, obs_doc, residuals.get(ref) if ref else None, ref, max_frames))
    step("frames")
    body.append(
        section(
            "conditions",
            "Method and measurement conditions",
            _method_text(res, methods),
            kv_table(conditions(res, obs_doc, ds_doc) + inputs.extra_rows),
        )
    )
    body.append(
        section(
            "missing",
            "What this report does not contain",
            Raw('<div class="missing">'),
            bullet_list(missing_items(res, obs_doc, inputs.dataset_dir, methods, missing_files).items),
            Raw("</div>"),
        )
    )
    body.append(
        Raw(
            f"<footer>i4cal {esc(__version__)} - report generated {esc(_now())}. Lengths in mm, angles in "
            "degrees; values are computed in metres and radians. Uncertainties: u = one standard deviation, "
            f"U = k u with k = {K_COVERAGE:g}.</footer>"
        )
    )
    step("html")
    return page(f"i4cal calibration report - {inputs.source or 'result'}", body)


# -- sections -----------------------------------------------------------------------------------
def _verdict(res: ResultDocument, inputs: ReportInputs) -> Raw:
    """The first screen's answer: which method's result to load and why, and the next command
    (calib.identify.verdict)."""
    run_id = (inputs.run or {}).get("id")
    src = inputs.source or ""
    from_result_file = inputs.observations is None and inputs.dataset_dir is None and src.endswith(".json")
    result = run_id or (src if from_result_file else "RESULT")
    v = verdict(res, result)
    lines = v.lines()
    cls = "verdict" if v.method else "verdict none"
    nxt = f"<p>next: <code>{esc(v.next_command)}</code></p>" if v.next_command else ""
    return Raw(
        f'<section id="verdict" class="{cls}"><h2>Verdict</h2><p>{esc(lines[0])}</p>{nxt}'
        f'<p class="note">Uncertainties are {UNCERTAINTY} throughout; the expanded uncertainty U (k = '
        f"{K_COVERAGE:g}) is given beside them in each method's table.</p></section>"
    )


def _now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _title_block(
    inputs: ReportInputs,
    res: ResultDocument,
    methods: list[str],
    ds_doc: dict | None,
    ds_hash: str | None,
    n_files: int,
    version: str,
) -> Raw:
    run = inputs.run or {}
    rows: list[tuple[str, str]] = [("bench", run.get("bench") or "-")]
    if run.get("id"):
        rows.append(("run", f"{run['id']} ({run.get('state', '')}, plan {run.get('plan') or '-'})"))
        if run.get("note"):
            rows.append(("note", run["note"]))
    rows.append(("made from", inputs.source or "-"))
    if run.get("created_at"):
        rows.append(("measured", f"{run['created_at']} to {run.get('finished_at') or '-'}"))
    elif inputs.dataset_dir is not None:
        t = datetime.fromtimestamp((inputs.dataset_dir / "dataset.json").stat().st_mtime, UTC)
        rows.append(("dataset written", t.strftime("%Y-%m-%d %H:%M:%S UTC")))
    rows.append(("report date", _now()))
    rows.append(("software", f"i4cal {version} (result format {res.format})"))
    rows.append(("dataset SHA-256", f"{ds_hash} ({n_files} files: dataset.json and frames)" if ds_hash else "-"))
    rows.append(
        (
            "observations SHA-256",
            json_sha256(inputs.observations) + " (canonical JSON)" if inputs.observations is not None else "-",
        )
    )
    rows.append(("result SHA-256", json_sha256(res.to_dict()) + " (canonical JSON)"))
    rows.append(("methods", ", ".join(methods) or "-"))
    return Raw(
        '<header class="title"><h1>Kinematic calibration report</h1><p>I4 parallel robot observed by one '
        "camera: identified geometry, uncertainties and validation</p></header>" + kv_table(rows)
    )


def _contents() -> Raw:
    items = [
        ("parameters", "Identified parameters"),
        ("budget", "Uncertainty budget"),
        ("predicted", "Predicted before the run vs obtained"),
        ("combinations", "The four identifiable combinations"),
        ("validation", "Validation: displacement gaps and straightness"),
        ("residuals", "Residuals per pose and per leg"),
        ("identifiability", "Identifiability"),
        ("camera", "Camera calibration"),
        ("frames", "Frames of the worst poses"),
        ("conditions", "Method and measurement conditions"),
        ("missing", "What this report does not contain"),
    ]
    return Raw("<nav><ol>" + "".join(f'<li><a href="#{k}">{esc(t)}</a></li>' for k, t in items) + "</ol></nav>")


def _truth_combinations(res: ResultDocument, obs_doc: dict | None) -> dict[str, float] | None:
    t = (obs_doc or {}).get("truth") or {}
    if isinstance(t.get("combinations"), dict):
        return {k: float(t["combinations"][k]) for k in COMBINATION_NAMES}
    return res.truth_combinations()


def _parameters(res: ResultDocument, methods: list[str], truth: dict[str, float] | None) -> Raw:
    parts: list[Any] = [_table_one(res, methods, truth)]
    for m in methods:
        parts += _method_tables(res, m)
    parts.append(
        figure(
            plots.parameter_plot(res, methods, truth),
            "parameter deviations",
            "Identified minus a priori value of each combination, error bars ± 1 std; dotted: truth",
        )
    )
    note = next((b.note or "" for m in methods if (b := res.methods[m].bound) is not None and b.std), None)
    if note is not None:
        parts.append(Raw('<p class="note">' + esc(note) + ".</p>"))
    return section("parameters", "Identified parameters", *parts)


def _table_one(res: ResultDocument, methods: list[str], truth: dict[str, float] | None) -> Raw:
    """Table I: the four combinations of the a priori geometry, of each method (value ± u) and the truth."""
    nom = res.nominal_combinations
    t1_rows = [["a priori (nominal)", *[mm(nom[k]) for k in COMBINATION_NAMES]]]
    for m in methods:
        e = res.methods[m]
        if e.parameters:
            std = e.std or {}
            t1_rows.append([m, *[f"{mm(e.parameters[k])} ± {mm(std[k])}" for k in COMBINATION_NAMES]])
        else:
            t1_rows.append([m, "fit failed (the reason below)", *([""] * 3)])
    if truth:
        t1_rows.append(["truth (simulation)", *[mm(truth[k]) for k in COMBINATION_NAMES]])
    return table(
        ["parameter set", *[f"{k} (mm)" for k in COMBINATION_NAMES]],
        t1_rows,
        caption=f"Table I - identifiable parameters (the four combinations), value {UNCERTAINTY}; "
        f"U (k = {K_COVERAGE:g}) in each method's table",
    )


def _method_tables(res: ResultDocument, m: str) -> list[Any]:
    """One method's combinations (a priori, identified, u, U, bound, error vs truth) and its seven parameters."""
    e = res.methods[m]
    if not e.parameters:
        return [Raw(f"<h3>Method: {esc(m)}</h3><p>failed: {esc(e.error or '')}</p>")]
    bound = e.bound_std
    te = res.truth_error(m)
    nom = res.nominal_combinations
    hdr = ["combination", "a priori (mm)", "identified (mm)", "identified - a priori (mm)", "u (mm)"]
    hdr += [f"U, k = {K_COVERAGE:g} (mm)"]
    hdr += ["Cramer-Rao bound (mm)", "u / bound"] if bound else []
    hdr += ["error vs truth (mm)", "|error| / u"] if te else []
    rows = []
    std = e.std or {}
    for k in COMBINATION_NAMES:
        v, u = _f(e.parameters[k]), _f(std[k])
        row = [k, mm(nom[k]), mm(v, 4), mm(v - _f(nom[k]), 4, True), mm(u, 4), mm(K_COVERAGE * u, 4)]
        if bound:
            b = bound.get(k)
            row += [mm(b, 4), num(u / b, ".2f") if b else "-"]
        if te:
            row += [mm(te[k], 4, True), num(abs(te[k]) / u, ".2f") if u > 0 else "-"]
        rows.append(row)
    note = (
        f"converged: {'yes' if e.converged else 'NO'}, {e.iterations} iterations, "
        f"{e.n_poses} poses, {e.n_observations} observations, residual RMS "
        f"{num(e.residual_rms, '.4g')} ({e.residual_unit or ''})"
    )
    parts: list[Any] = [Raw(f"<h3>Method: {esc(m)}</h3>"), table(hdr, rows), Raw(f'<p class="note">{esc(note)}</p>')]
    if e.seven:
        parts.append(_seven_table(res, m, e, te))
    return parts


def _seven_table(res: ResultDocument, m: str, e: MethodEntry, te: dict[str, Any] | None) -> Raw:
    """A method's seven parameters: a priori, identified, u, U and the error vs truth."""
    seven, seven_std = e.seven or {}, e.seven_std or {}
    te7 = te.get("seven") if te else None
    srows = [
        [
            k,
            mm(res.nominal[k]),
            mm(seven[k], 4),
            mm(seven_std.get(k), 4),
            mm(K_COVERAGE * (seven_std.get(k) or 0), 4),
        ]
        + ([mm(te7[k], 4, True)] if te7 is not None else [])
        for k in PARAMETER_NAMES
    ]
    return table(
        ["parameter", "a priori (mm)", "identified (mm)", "u (mm)", "U, k = 2 (mm)"]
        + (["error vs truth (mm)"] if te7 is not None else []),
        srows,
        caption=f"{m}: all seven parameters",
    )


def _f(v: float | None) -> float:
    """A value of the document as a float (NaN for null)."""
    return float("nan") if v is None else float(v)


#: what each contribution of a method's ``std_breakdown`` is, for the uncertainty budget
BUDGET_SOURCES = {
    "legs_and_encoders": "rod directions (edge noise, measured scatter) and encoders",
    "board_poses_and_encoders": "board poses (PnP noise, factor from the residuals) and encoders",
    "base_frame": "base frame (rotation and translation phases)",
    "intrinsics": "camera intrinsics (calibration covariance, after the rods' refinement where used)",
    "limb_edge_bias": (
        f"limb-edge bias common to every rod (prior {EDGE_BIAS_STD_PX:g} px per limb; the legs method: the combined "
        "fit's measurement of it, which corrects its rods)"
    ),
    "joint_centres": "joint centres (lock phases)",
    "joint_depth_systematic": (
        "joint centres' systematic depth error (the rods' shading, the same in every frame of a lock phase)"
    ),
    "leg_directions": "leg directions of the fit poses",
    "lens_model": "lens model error (the camera calibration's radial residual beyond its noise)",
    "a_priori": "a priori geometry (manufacturing tolerance) where the data do not pin the parameters",
}


def _budget(res: ResultDocument, methods: list[str]) -> Raw:
    """Per method, the standard deviation each source contributes (the combined u is their root sum of squares)."""
    parts: list[Any] = [
        "Standard uncertainty contributed by each source, in mm; the sources are independent and the "
        "combined standard uncertainty u is their root sum of squares (the methods' propagation, "
        "docs/model.md). A source a method does not have is not listed."
    ]
    shown = 0
    for m in methods:
        e = res.methods.get(m)
        bd = (e.std_breakdown if e is not None else None) or {}
        if e is None or not bd or not e.std:
            continue
        names = list(next(iter(bd.values())).keys())
        rows = [[BUDGET_SOURCES.get(src, src)] + [mm(v.get(k), 4) for k in names] for src, v in bd.items()]
        total = e.seven_std if names != list(COMBINATION_NAMES) and e.seven_std else e.std
        rows.append(["combined u (root sum of squares)"] + [mm((total or {}).get(k), 4) for k in names])
        parts += [
            Raw(f"<h3>Method: {esc(m)}</h3>"),
            table(["source"] + [f"{k} (mm)" for k in names], rows, cls="data wide"),
        ]
        shown += 1
    if not shown:
        parts = ["Not available: the results carry no uncertainty breakdown."]
    return section("budget", "Uncertainty budget", *parts)


def _predicted(prediction: dict[str, Any] | None, res: ResultDocument, methods: list[str]) -> Raw:
    """The run's prediction before motion beside each method's reported std (obtained / predicted)."""
    title = "Predicted before the run vs obtained"
    pred = (prediction or {}).get("predicted_std_m") or {}
    shown = [m for m in methods if m in pred and (e := res.methods.get(m)) is not None and e.std]
    if not shown:
        why = (prediction or {}).get("error") or (
            "the report was not made from a run on the bench (an offline run, files)"
            if prediction is None
            else "none of these methods was predicted for the run's plan"
        )
        return section("predicted", title, f"Not available: {why}.")
    rows = []
    for m in shown:
        got = res.methods[m].std or {}
        cells = []
        for k in COMBINATION_NAMES:
            p, o = pred[m].get(k), got.get(k)
            ratio = f" ({o / p:.2f}x)" if p and o else ""
            cells.append(f"{mm(p, 4)} / {mm(o, 4)}{ratio}")
        rows.append([m, *cells])
    motion = prediction.get("motion_time_s") if prediction else None
    return section(
        "predicted",
        title,
        "What the run's plan was predicted to buy before it moved (docs/design.md: the methods' uncertainty models at "
        "the noise levels measured on the image-level twin), beside the standard deviation each method reports: "
        "predicted / obtained in mm, obtained over predicted in brackets. A ratio far from 1 says the run's data "
        "were noisier (or cleaner) than the model's, or that the plan lost frames."
        + ("" if motion is None else f" Predicted motion time: {motion / 60:.1f} min."),
        table(["method", *(f"{k} (mm)" for k in COMBINATION_NAMES)], rows, cls="data wide"),
    )


def _combinations(res: ResultDocument, methods: list[str]) -> Raw:
    rows = [[k, COMBINATION_MEANING[k][0], COMBINATION_MEANING[k][1]] for k in COMBINATION_NAMES]
    found = []
    for m in methods:
        ident = res.methods[m].identifiability
        if ident is not None and ident.finds_paper_four is not None:
            four = "yes" if ident.finds_paper_four else ("all seven" if ident.rank == 7 else "no")
            # the paper's four are spelled as everywhere else; the row-reduced forms the analysis found beside them
            reduced = "; ".join(ident.identifiable_combinations or [])
            names = ", ".join(COMBINATION_NAMES) + f" (row-reduced: {reduced})" if ident.finds_paper_four else reduced
            found.append([m, str(ident.rank), four, names])
    return section(
        "combinations",
        "The four identifiable combinations",
        "Methods that observe the mechanism through its Jacobian or its inverse kinematics identify only "
        "four combinations of the seven parameters (H, q02, q03, q04, S, D, L); the other three directions "
        "do not change any measurement. The legs method, which also sees the joint centres, identifies "
        "all seven.",
        table(["name", "combination", "meaning"], rows, cls="data wide"),
        table(
            ["method", "rank", "the paper's four?", "identifiable combinations found"],
            found,
            cls="data wide",
            caption="Found by the numerical identifiability analysis",
        ),
    )


def _validation(res: ResultDocument) -> Raw:
    g_rows, s_rows = [], []
    for name, v in res.validation.items():
        label = "true geometry" if name == "truth" else name
        if v.error is not None:
            g_rows.append([label, v.error, "", "", "", "", ""])
            continue
        gp, gv = v.gaps_poses or Gaps(), v.gaps_validation or Gaps()
        g_rows.append(
            [
                label,
                num(gp.mean_mm, "+.4f"),
                num(gp.rms_mm, ".4f"),
                num(gp.max_abs_mm, ".4f"),
                num(gv.mean_mm, "+.4f"),
                num(gv.rms_mm, ".4f"),
                num(gv.max_abs_mm, ".4f"),
            ]
        )
        st = v.straightness or Straightness()
        n = "-" if st.n is None else str(st.n)
        s_rows.append([label, num(st.rms_mm, ".4f"), n, num(st.length_mm, ".1f")])
    hdr = [
        "parameter set",
        "fit: mean",
        "fit: RMS",
        "fit: max |gap|",
        "validation: mean",
        "validation: RMS",
        "validation: max |gap|",
    ]
    return section(
        "validation",
        "Validation: displacement gaps and straightness",
        "Displacement gap: length of the end-effector displacement between consecutive poses measured by "
        "the camera (the board point on the rotation axis) minus the one the geometry predicts from the "
        "encoder values, vision's displacements divided by its scale measured on the translation phase "
        f"({_vision_scale_text(res)}). Straightness: RMS distance of the model positions along the guided line "
        "to their best-fit line.",
        table(hdr, g_rows, caption="Table II - displacement gaps (mm)"),
        table(
            ["parameter set", "RMS (mm)", "points", "length (mm)"],
            s_rows,
            caption="Table III - straightness of the guided line",
        ),
        figure(plots.gaps_plot(res), "displacement gaps", "Displacement gap of each pose pair"),
    )


def _vision_scale_text(res: ResultDocument) -> str:
    """The validation's vision scale (displacement per encoder metre) as a sentence fragment."""
    sc = res.vision_scale()
    if sc is None:
        return "not recorded"
    if sc.std is None:
        return f"taken as 1: {sc.source}"
    text = f"{vision_scale_ppm(sc.model_dump())} from {sc.n_poses} poses"
    return f"{text}; {sc.warning}" if sc.warning else text


def _residuals(residuals: dict[str, LegResiduals | None]) -> Raw:
    if not residuals:
        return section("residuals", "Residuals per pose and per leg", "Not available: no observations.")
    rows = []
    for m, r in residuals.items():
        if r is None:
            continue
        for ph in ("poses", "validation"):
            if ph in r.phases:
                rms = np.degrees(r.per_leg_rms(ph))
                rows.append(
                    [
                        f"{m}, {'fit' if ph == 'poses' else 'validation'} poses",
                        *[num(x, ".4f") if np.isfinite(x) else "-" for x in rms],
                    ]
                )
    return section(
        "residuals",
        "Residuals per pose and per leg",
        "Angle between each leg as observed (mean over its rods, in the base frame found from the board's "
        "rotation and translation phases) and the leg direction the identified geometry predicts from the "
        "encoder values.",
        figure(
            plots.leg_residual_plot({k: v for k, v in residuals.items() if v is not None}),
            "leg residuals",
            "Residual angle of each leg at each pose (deg)",
        ),
        table(["method, poses", "leg 1", "leg 2", "leg 3", "leg 4"], rows, caption="RMS residual angle per leg (deg)"),
    )


def _identifiability(res: ResultDocument, methods: list[str]) -> Raw:
    rows = []
    for m in methods:
        ident = res.methods[m].identifiability
        if ident is None:
            continue
        if ident.rank is not None:
            sv = ident.singular_values or []
            n_poses = "-" if ident.n_poses is None else str(ident.n_poses)
            rows.append(
                [m, str(ident.rank), num(ident.condition_number, ".3g"), " ".join(f"{s:.3g}" for s in sv), n_poses]
            )
        elif ident.error is not None:
            rows.append([m, "-", "-", ident.error, "-"])
    return section(
        "identifiability",
        "Identifiability",
        "Singular values of each method's identification Jacobian over the seven parameters at the "
        "identified geometry and the fit poses (nuisance parameters projected out). The rank is the number "
        "of singular values above 1e-7 of the largest; the condition number is over those.",
        figure(plots.singular_value_plot(res, methods), "singular values", "Relative singular values"),
        table(["method", "rank", "condition number", "singular values", "poses"], rows),
    )


def _camera(obs_doc: dict | None) -> Raw:
    ext = (obs_doc or {}).get("extraction")
    if not ext:
        return section("camera", "Camera calibration", "Not available: the observations have no extraction record.")
    summ = ext.get("summary") or {}
    cs = summ.get("camera") or {}
    cam = ext.get("camera") or {}
    src = cs.get("source") or f"calibrated from {cs.get('n_views', '?')} views of the camera phase"
    parts: list[Any] = [
        f"Intrinsics: {src}; image {cam.get('width')} x {cam.get('height')} px."
        + (f" RMS reprojection error {cs['rms_px']:.3f} px." if "rms_px" in cs else "")
    ]
    parts.append(
        table(
            ["intrinsic", "value", "std"], _intrinsic_rows(cam, cs), caption="Intrinsics (px; distortion dimensionless)"
        )
    )
    lm = cs.get("lens_model") or (cam.get("calibration") or {}).get("lens_model")
    if lm:
        parts.append(_lens_model_text(lm))
    if cs.get("per_view_rms_px"):
        parts.append(figure(plots.camera_view_plot(cs), "reprojection errors", "RMS reprojection error per view"))
    rej = cs.get("rejected") or {}
    parts.append(
        table(
            ["view (dataset frame)", "reason"],
            [[k, v] for k, v in rej.items()] or [["-", "none rejected"]],
            cls="data wide",
            caption="Rejected calibration views",
        )
    )
    pl = summ.get("placement") or {}
    parts.append(
        "Coarse camera placement (predicts the rods): "
        + (f"board residual RMS {pl['rms_m'] * 1e3:.2f} mm." if pl.get("ok") else str(pl.get("reason")))
    )
    parts.append(
        table(
            ["phase", "frames", "board found", "rods found", "not measured"],
            _extraction_rows(summ),
            cls="data wide",
            caption="What extraction found per phase",
        )
    )
    return section("camera", "Camera calibration", *parts)


def _intrinsic_rows(cam: dict, cs: dict) -> list[list[str]]:
    """The camera matrix's focal lengths and principal point, then the distortion coefficients, with their std."""
    K = np.asarray(cam.get("K") or np.eye(3), float)
    std = cs.get("std") or {}
    rows = [
        [k, num(K[i, j], ".2f"), num(std.get(k), ".2f")]
        for k, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2)))
    ]
    for name, v in zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), cam.get("dist") or [], strict=False):
        rows.append([name, num(v, ".5f"), num(std.get(name), ".5f")])
    return rows


def _lens_model_text(lm: dict) -> str:
    """The lens model chosen by the camera calibration, its candidates and its field coverage, as sentences."""
    how = "chosen from the board views" if lm.get("requested") == "auto" else "given"
    err_px = float((lm.get("residual_profile") or {}).get("max_systematic_px", 0.0))
    return (
        f"Lens model {lm.get('chosen')} ({how}; lowest BIC {lm.get('lowest_bic', lm.get('chosen'))}): "
        + ", ".join(
            f"{e['model']} {e['n_params']} parameters, RMS {e['rms_px']:.3f} px"
            + (f", BIC {e['delta_bic']:+.1f}" if e.get("delta_bic") is not None else "")
            for e in lm.get("candidates") or []
        )
        + f". The views reach {100 * float(lm.get('field_coverage', 1.0)):.0f}% of the image's corner radius; "
        f"radial model error up to {err_px:.3f} px." + "".join(f" {w}." for w in lm.get("warnings") or [])
    )


def _extraction_rows(summ: dict) -> list[list[str]]:
    """Per phase: frames, boards and rods found, and what was not measured."""
    rows = []
    for ph, c in (summ.get("phases") or {}).items():
        miss = "; ".join(f"{k} x{v}" for k, v in (c.get("missing") or {}).items())
        rows.append(
            [
                ph,
                str(c.get("frames")),
                f"{c.get('board')}/{c.get('frames')}",
                f"{c.get('rods')}/{c.get('rods_total')}"
                if c.get("rods_total") or not c.get("rods_not_read")
                else "not read",
                miss or "-",
            ]
        )
    return rows


def _frames(
    dataset_dir: Path | None,
    ds_doc: dict | None,
    obs_doc: dict | None,
    res: LegResiduals | None,
    method: str | None,
    n: int,
) -> Raw:
    if dataset_dir is None or ds_doc is None or obs_doc is None or res is None:
        return section(
            "frames",
            "Frames of the worst poses",
            "Not available: needs the dataset, the observations and a converged method.",
        )
    import cv2

    from service.report.draw import annotated_frame, frame_camera

    cam = frame_camera(ds_doc, obs_doc)
    parts: list[Any] = [
        f"The {n} poses with the largest RMS leg residual of the {method} geometry, with the board "
        "outline (green, red/green axes) and the rod axes (blue) as extraction measured them."
    ]
    rms_legs = {f: row for f, row in zip(res.frames, res.angle_rad, strict=True)}
    for rank, (fi, ph, rms) in enumerate(worst_poses(res, n), 1):
        fr = obs_doc["frames"][fi]
        di = fr.get("dataset_frame")
        img = (
            None
            if di is None
            else annotated_frame(dataset_dir, ds_doc, int(di), fr, cam, 800, label=f"#{rank}: frame {di} ({ph})")
        )
        legs = ", ".join(
            f"leg {i + 1} {np.degrees(a):.4f}" if np.isfinite(a) else f"leg {i + 1} -"
            for i, a in enumerate(rms_legs[fi])
        )
        cap = (
            f"#{rank}: dataset frame {di}, {ph} pose; q = ({', '.join(f'{v * 1e3:.2f}' for v in fr['q'])}) mm; "
            f"RMS residual {np.degrees(rms):.4f} deg ({legs} deg)"
        )
        if fr.get("missing"):
            cap += "; not measured: " + "; ".join(f"{k}: {v}" for k, v in fr["missing"].items())
        if img is None:
            parts.append(Raw(f'<p class="note">{esc(cap)} - image not available.</p>'))
            continue
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 88])
        uri = "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii") if ok else None
        parts.append(figure(uri, f"frame {di}", cap))
    return section("frames", "Frames of the worst poses", Raw('<div class="frames">'), *parts, Raw("</div>"))


def _method_line(name: str) -> str:
    """``label: description.`` of a registered method (:mod:`calib.identify.registry`); the bare name otherwise."""
    from calib.errors import InputError
    from calib.identify.registry import get_method

    try:
        spec = get_method(name)
    except InputError:
        return f"{name}: a method this software does not know."
    return f"{spec.label}: {spec.description}."


def _method_text(res: ResultDocument, methods: list[str]) -> Raw:
    items = [_method_line(m) for m in methods]
    items.append(
        "Standard uncertainties u are one standard deviation from each fit's covariance, with the noise "
        "level estimated from its residuals and, for the combined method, the base frame's uncertainty "
        f"propagated; expanded uncertainties U = k u with k = {K_COVERAGE:g} (about 95 % coverage for a "
        "normal distribution). The Cramer-Rao bound is the smallest standard deviation any unbiased "
        "estimator could reach with these poses at the noise levels measured in this run."
    )
    items.append(
        "Validation uses the end-effector displacements between consecutive poses (fit poses and separate "
        "validation poses) and the straightness of a guided line, as in the paper's Tables II and III."
    )
    return bullet_list(items)
