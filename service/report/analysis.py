"""Figures the report derives from its inputs: hashes, per-pose and per-leg residuals, worst poses, conditions,
and what is missing. Metres and radians inside; the report converts to mm and degrees for display."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calib.errors import I4calError
from calib.formats.resultdoc import Diagnostics, ResultDocument
from calib.identify.registry import method_names
from calib.identify.registry import methods as registered_methods
from calib.model.kinematics import dkm, leg_directions
from calib.model.parameters import PARAMETER_NAMES, I4Parameters

#: Phases whose poses get per-pose residuals (the fit set, then the separate validation poses).
RESIDUAL_PHASES = ("poses", "validation")


def method_order(present: Any = ()) -> list[str]:
    """The registered methods (:mod:`calib.identify.registry`, in its order), then any other name in ``present`` (a
    result document's methods made with a method this process does not know), in its order."""
    names = list(method_names())
    return names + [m for m in present if m not in names]


def sha256_file(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def dataset_sha256(dataset_dir: Path) -> tuple[str, int, list[str]]:
    """SHA-256 of a dataset: of its ``sha256sum``-style manifest over ``dataset.json`` and the frame images.

    The manifest has one line ``"<sha256 hex>  <path relative to the dataset>\\n"`` per file: ``dataset.json``
    first, then every frame's image in frame order (each once). ``sha256sum dataset.json frames/*.png | sha256sum``
    gives the same digest when the frames are numbered in order.

    Returns
    -------
    digest : str
    n_files : int
        Files hashed.
    missing : list of str
        Frame images named in ``dataset.json`` but absent (left out of the manifest).
    """
    root = Path(dataset_dir)
    doc = json.loads((root / "dataset.json").read_text(encoding="utf-8"))
    names = ["dataset.json"]
    for f in doc.get("frames", []):
        img = f.get("image")
        if img and img not in names:
            names.append(img)
    lines, missing = [], []
    for n in names:
        p = root / n
        if p.is_file():
            lines.append(f"{sha256_file(p)}  {n}\n")
        else:
            missing.append(n)
    return hashlib.sha256("".join(lines).encode()).hexdigest(), len(lines), missing


def json_sha256(doc: Any) -> str:
    """SHA-256 of a JSON document in canonical form (sorted keys, no spaces, UTF-8)."""
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def method_parameters(result: ResultDocument | dict[str, Any], method: str) -> I4Parameters | None:
    """The seven parameters a converged method stands for (identified, or completed with the a priori ones)."""
    return ResultDocument.of(result).method_parameters(method)


@dataclass
class LegResiduals:
    """Angle between each observed leg and the leg the identified geometry predicts, per pose and leg.

    Attributes
    ----------
    frames : list of int
        Observation-frame indices of the poses (fit poses first, then validation poses).
    phases : list of str
    angle_rad : ndarray, shape (N, 4)
        Mean over the leg's observed rods of the angle between rod axis (in the base frame) and model leg
        direction, radians; NaN where no rod of the leg was seen or the pose is out of the model's reach.
    """

    frames: list[int]
    phases: list[str]
    angle_rad: np.ndarray

    def per_pose_rms(self) -> np.ndarray:
        """RMS over the seen legs of each pose, radians, shape (N,) (NaN when none was seen)."""
        a = self.angle_rad
        n = np.sum(np.isfinite(a), axis=1)
        s = np.nansum(a**2, axis=1)
        return np.where(n > 0, np.sqrt(s / np.maximum(n, 1)), np.nan)

    def per_leg_rms(self, phase: str | None = None) -> np.ndarray:
        """RMS over the poses of each leg, radians, shape (4,)."""
        a = self.angle_rad if phase is None else self.angle_rad[np.array(self.phases) == phase]
        with np.errstate(invalid="ignore"):
            return np.sqrt(np.nanmean(a**2, axis=0)) if len(a) else np.full(4, np.nan)


def leg_residuals(obs: Any, result: ResultDocument | dict[str, Any], method: str) -> LegResiduals | None:
    """Per-pose, per-leg residual angles of ``method``'s geometry on the fit and validation poses.

    The rods' axes are turned into the base frame with the rotation estimated from the ``rotation`` and
    ``translation`` phases (``result.base_frame``); the model's leg directions come from the encoder values
    through the identified geometry (DKM then IKM). None when the method has no result or no base frame.

    Parameters
    ----------
    obs : calib.formats.observations.Observations
    result : ResultDocument
        The result document of :func:`calib.identify.pipeline.calibrate_document`.
    """
    doc = ResultDocument.of(result)
    params = doc.method_parameters(method)
    R = doc.base_frame.rotation() if doc.base_frame is not None else None
    if params is None or R is None:
        return None
    frames: list[int] = []
    phases: list[str] = []
    rows = []
    for ph in RESIDUAL_PHASES:
        d = obs.arrays(ph)
        for k in range(len(d)):
            ang = np.full(4, np.nan)
            try:
                m = leg_directions(params, dkm(params, d.q[k]))
            except (I4calError, ValueError):
                m = None
            if m is not None:
                for leg in range(4):
                    us = [d.rod_u[k, leg, j] @ R for j in range(2) if d.has_rod[k, leg, j]]
                    if us:
                        c = [abs(float(u @ m[leg]) / float(np.linalg.norm(u))) for u in us]
                        ang[leg] = float(np.mean(np.arccos(np.clip(c, -1.0, 1.0))))
            frames.append(int(d.index[k]))
            phases.append(ph)
            rows.append(ang)
    return LegResiduals(frames, phases, np.array(rows).reshape(-1, 4))


def reference_method(result: ResultDocument | dict[str, Any], methods: list[str] | None = None) -> str | None:
    """The method whose residuals pick the worst poses: the paper's combined one when it converged, else the
    first converged one."""
    ms = ResultDocument.of(result).methods
    names = [m for m in method_order(ms) if m in ms and (methods is None or m in methods)]
    return next((m for m in names if ms[m].converged and ms[m].parameters), None)


def worst_poses(res: LegResiduals, n: int = 3) -> list[tuple[int, str, float]]:
    """The ``n`` poses with the largest RMS leg residual: (observation frame, phase, RMS angle in radians)."""
    rms = res.per_pose_rms()
    order = [i for i in np.argsort(-np.nan_to_num(rms, nan=-1.0)) if np.isfinite(rms[i])][:n]
    return [(res.frames[i], res.phases[i], float(rms[i])) for i in order]


@dataclass
class Missing:
    """What the report could not show, and why (one sentence each)."""

    items: list[str] = field(default_factory=list)

    def add(self, text: str) -> None:
        if text not in self.items:
            self.items.append(text)


def missing_items(
    result: ResultDocument | dict[str, Any],
    obs_doc: dict[str, Any] | None,
    dataset_dir: Path | None,
    methods: list[str],
    missing_files: list[str],
) -> Missing:
    """Everything absent from the inputs that a reader of the report would expect."""
    m = Missing()
    result = ResultDocument.of(result)
    for text in (
        *_missing_inputs(obs_doc, dataset_dir, missing_files),
        *_missing_extraction(obs_doc),
        *_missing_methods(result, methods),
        *_missing_in_result(result),
    ):
        m.add(text)
    return m


def _missing_inputs(obs_doc: dict[str, Any] | None, dataset_dir: Path | None, missing_files: list[str]) -> list[str]:
    """What the report lacks for want of observations, a dataset or its frame images."""
    out = []
    if obs_doc is None:
        out.append("no observations: residuals per pose and leg, camera calibration and frames are not shown")
    if dataset_dir is None:
        out.append("no dataset: no dataset hash and no frames")
    elif missing_files:
        out.append(
            f"{len(missing_files)} frame image(s) named in dataset.json are missing: "
            + ", ".join(missing_files[:5])
            + (" ..." if len(missing_files) > 5 else "")
        )
    return out


def _missing_extraction(obs_doc: dict[str, Any] | None) -> list[str]:
    """What the observations' extraction record says was not measured (or that there is no record)."""
    ext = (obs_doc or {}).get("extraction")
    if obs_doc is not None and not ext:
        return [
            "no extraction record: the observations were not produced from images by i4cal extract "
            "(camera calibration quality unknown)"
        ]
    if not ext:
        return []
    out = []
    src = ((ext.get("summary") or {}).get("camera") or {}).get("source")
    if src in ("given", "dataset"):
        out.append(
            f"no camera phase: intrinsics {'given' if src == 'given' else 'taken from the dataset'} "
            "(no reprojection errors, no intrinsic standard deviations)"
        )
    miss: dict[str, int] = {}  # frames missing, per reason
    for c in ((ext.get("summary") or {}).get("phases") or {}).values():
        for k, v in (c.get("missing") or {}).items():
            miss[k] = miss.get(k, 0) + v
    if miss:
        out.append("not measured in some frames: " + "; ".join(f"{k} x{v}" for k, v in sorted(miss.items())))
    return out


def _missing_methods(result: ResultDocument, methods: list[str]) -> list[str]:
    """The methods asked for that were not run, failed or did not converge, and the bounds not computed."""
    out = []
    for name in method_order(methods):
        if name not in methods:
            continue
        e = result.methods.get(name)
        if e is None:
            out.append(f"method {name} was not run")
        elif not e.parameters:
            out.append(f"method {name} failed: {e.error if e.error is not None else 'no parameters'}")
        elif not e.converged:
            out.append(f"method {name} did not converge: {e.message or ''}")
    comb = result.methods.get("combined")
    if comb is not None and comb.parameters and not comb.bound_std:
        note = comb.bound.note if comb.bound is not None and comb.bound.note is not None else "no base frame"
        out.append(f"no Cramer-Rao bound for the combined method ({note})")
    with_bound = [s.name for s in registered_methods() if s.bound]
    if any(n not in with_bound for n in result.methods):
        out.append(f"Cramer-Rao bound computed for the {', '.join(with_bound)} method only")
    return out


def _missing_in_result(result: ResultDocument) -> list[str]:
    """What the result's base frame, phases and truth leave out."""
    out = []
    bf = result.base_frame
    if bf is not None and bf.error is not None:
        out.append(f"no base frame: {bf.error}")
    if not result.phases.get("validation"):
        out.append("no validation poses: Table II on the fit poses only")
    if not result.phases.get("line"):
        out.append("no line phase: straightness (Table III) not measured")
    if result.truth_errors is None:
        out.append("no truth (not a simulated data set): errors against the true geometry cannot be given")
    return out


def conditions(
    result: ResultDocument | dict[str, Any], obs_doc: dict[str, Any] | None, dataset_doc: dict[str, Any] | None
) -> list[tuple[str, str]]:
    """Measurement conditions as (item, value) rows, for display (mm, deg, px)."""
    result = ResultDocument.of(result)
    rows: list[tuple[str, str]] = []
    rows.append(("poses per phase", ", ".join(f"{k} {v}" for k, v in result.phases.items()) or "-"))
    if dataset_doc:
        rows += _dataset_conditions(dataset_doc)
    elif obs_doc is not None and isinstance(obs_doc.get("noise"), dict):
        rows.append(("data source", "simulated observations (geometric twin, no images)"))
    return rows + _fit_conditions(result)


def _dataset_conditions(dataset_doc: dict[str, Any]) -> list[tuple[str, str]]:
    """The camera, board, rods, data source and acquisition a dataset records."""
    rows: list[tuple[str, str]] = []
    cam = dataset_doc.get("camera") or {}
    rows.append(("image size", f"{cam.get('width')} x {cam.get('height')} px"))
    b = dataset_doc.get("board") or {}
    rows.append(
        (
            "ChArUco board",
            f"{b.get('squares_x')} x {b.get('squares_y')} squares of "
            f"{b.get('square_length_m', 0) * 1e3:.1f} mm, {b.get('dictionary')}",
        )
    )
    legs = dataset_doc.get("legs") or {}
    if legs.get("rod_radius_m"):
        rows.append(("rods", f"{legs.get('rods_per_leg', 2)} per leg, radius {legs['rod_radius_m'] * 1e3:.2f} mm"))
    gen = dataset_doc.get("generator")
    if isinstance(gen, dict):
        rows.append(("data source", f"simulated: {gen.get('name')} (seed {gen.get('seed')}, plan {gen.get('plan')})"))
    acq = dataset_doc.get("acquisition")
    if isinstance(acq, dict):
        rows.append(
            (
                "acquisition",
                f"{acq.get('state')}: {acq.get('frames')}/{acq.get('total')} frames {acq.get('reason') or ''}".strip(),
            )
        )
    return rows


def _fit_conditions(result: ResultDocument) -> list[tuple[str, str]]:
    """The base frame's quality and the noise levels the fits measured."""
    rows: list[tuple[str, str]] = []
    bf = result.base_frame
    if bf is not None and bf.z_std_deg is not None:
        rows.append(
            (
                "base frame",
                f"z_B std {bf.z_std_deg:.4f} deg, x_B std {bf.x_std_deg:.4f} deg, board "
                f"rotation residual RMS {bf.rotation_residual_rms_deg:.4f} deg, translation "
                f"residual RMS {bf.translation_residual_rms_mm:.3f} mm",
            )
        )
    rows += _combined_conditions(_diagnostics(result, "combined"))
    rows += _legs_conditions(_diagnostics(result, "legs"))
    ee = _diagnostics(result, "end-effector")
    if isinstance(ee.board_noise_std, dict):
        rows.append(
            (
                "board pose noise (end-effector fit)",
                ", ".join(_fmt_noise(k, v) for k, v in ee.board_noise_std.items()),
            )
        )
    comb = result.methods.get("combined")
    noise = comb.bound.noise if comb is not None and comb.bound is not None else None
    if noise is not None:
        rows.append(
            (
                "noise levels of the Cramer-Rao bound",
                f"rod direction {np.degrees(noise.rod_direction_rad or 0):.4f} deg, board rotation "
                f"{np.degrees(noise.board_rotation_rad or 0):.4f} deg, board translation "
                f"{np.mean(noise.board_translation_m or [0]) * 1e3:.3f} mm",
            )
        )
    return rows


def _diagnostics(result: ResultDocument, method: str) -> Diagnostics:
    """A method's diagnostics (empty when it has none)."""
    e = result.methods.get(method)
    return (e.diagnostics if e is not None else None) or Diagnostics()


def _combined_conditions(c: Diagnostics) -> list[tuple[str, str]]:
    """The combined fit's rod noise and the correlations of the rods' errors."""
    rows: list[tuple[str, str]] = []
    if c.direction_noise_scale is not None:
        if c.weighting == "gls":  # a scale on the extraction's per-rod covariances, not an angle
            rows.append(("rod direction noise (combined fit)", f"{c.direction_noise_scale:.2f} x the rods' cov_u"))
        else:
            rows.append(("rod direction noise (combined fit)", f"{np.degrees(c.direction_noise_scale):.4f} deg"))
    shared = c.rod_errors
    if shared is not None and shared.model_fields_set:
        own = shared.own_scale if shared.own_scale is not None else float("nan")
        text = f"own scale {own:.2f}; a leg's two rods {shared.pair_correlation:.2f}"
        if shared.distance_correlation is not None:
            text += (
                f"; rods nearby in the image {shared.distance_correlation:.2f} "
                f"x exp(-d / {shared.distance_length_px:.0f} px)"
            )
        rows.append(("rods' shared errors (combined fit, correlation)", text))
    return rows


def _legs_conditions(lg: Diagnostics) -> list[tuple[str, str]]:
    """The legs fit's rod noise (an angle, or the chi-square of the rods' measured covariances)."""
    line = lg.line_residual_rms_mm if lg.line_residual_rms_mm is not None else 0
    if lg.rod_direction_noise_rad is not None:
        return [
            (
                "rod direction noise (legs fit)",
                f"{np.degrees(lg.rod_direction_noise_rad):.4f} deg; line residual RMS {line:.3f} mm",
            )
        ]
    if lg.steps34_chi2_per_dof is not None:
        step1 = lg.step1_chi2_per_dof if lg.step1_chi2_per_dof is not None else float("nan")
        return [
            (
                "rod noise (legs fit, measured rod covariances)",
                f"chi-square per degree of freedom: step 1 {step1:.2f}, "
                f"steps 3-4 {lg.steps34_chi2_per_dof:.2f}; line residual RMS {line:.3f} mm",
            )
        ]
    return []


def _fmt_noise(key: str, v: Any) -> str:
    """A noise figure named ``*_deg``, ``*_rad``, ``*_mm`` or ``*_m`` in deg or mm."""
    try:
        x = np.atleast_1d(np.asarray(v, float))
    except (TypeError, ValueError):
        return str(v)
    name, _, unit = key.rpartition("_")
    scale, shown = {"deg": (1.0, "deg"), "rad": (180.0 / np.pi, "deg"), "mm": (1.0, "mm"), "m": (1e3, "mm")}.get(
        unit, (1.0, unit)
    )
    digits = 4 if shown == "deg" else 3
    return (name or key) + " " + " / ".join(f"{a * scale:.{digits}f}" for a in x) + f" {shown}"


__all__ = [
    "PARAMETER_NAMES",
    "LegResiduals",
    "Missing",
    "conditions",
    "dataset_sha256",
    "json_sha256",
    "leg_residuals",
    "method_parameters",
    "missing_items",
    "reference_method",
    "sha256_file",
    "worst_poses",
]
