"""The report's plots: matplotlib figures (Agg canvas, no pyplot state, safe in worker threads) rendered as PNG
``data:`` URIs. Inputs in metres/radians; axes in mm, degrees or pixels."""

from __future__ import annotations

import base64
import io
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from calib.formats.resultdoc import Identifiability, ResultDocument
from calib.model.parameters import COMBINATION_NAMES
from service.report.analysis import LegResiduals

#: Colours of the rows that are not methods (a method's colour is its registry entry's).
COLOURS = {
    "a priori": "#7f7f7f",
    "truth": "#000000",
    "true geometry": "#000000",
}


def colour(name: str) -> str | None:
    """Plot colour of ``name``: a registered method's (:mod:`calib.identify.registry`), or of a reference row."""
    from calib.identify.registry import methods

    for spec in methods():
        if spec.name == name:
            return spec.colour
    return COLOURS.get(name)


LEG_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd")
DPI = 100


def _figure(width_in: float, height_in: float, nrows: int = 1, ncols: int = 1, **kw: Any):
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def _f(v: float | None) -> float:
    """A value of the document as a float (NaN for null)."""
    return float("nan") if v is None else float(v)


def to_data_uri(fig: Figure) -> str:
    """The figure as a PNG ``data:`` URI (no software metadata in the file)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None}, facecolor="white")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def parameter_plot(result: ResultDocument, methods: Sequence[str], truth: dict[str, float] | None) -> str | None:
    """Each combination's deviation from the a priori value (mm) per method, error bars ± 1 std."""
    names = [m for m in methods if (e := result.methods.get(m)) is not None and e.parameters]
    if not names:
        return None
    nom = result.nominal_combinations
    fig, axes = _figure(10.0, 3.0, 1, 4)
    for ax, key in zip(axes[0], COMBINATION_NAMES, strict=True):
        for i, m in enumerate(names):
            value, std = (result.methods[m].parameters or {})[key], (result.methods[m].std or {})[key]
            ax.errorbar(
                [i],
                [(_f(value) - _f(nom[key])) * 1e3],
                yerr=[_f(std) * 1e3],
                fmt="o",
                color=colour(m),
                capsize=4,
                label=m,
            )
        ax.axhline(0.0, color=COLOURS["a priori"], lw=1, ls="--", label="a priori")
        if truth:
            ax.axhline((truth[key] - _f(nom[key])) * 1e3, color="black", lw=1, ls=":", label="truth")
        ax.set_title(key, fontsize=10)
        ax.set_xticks(range(len(names)), names, rotation=20, fontsize=8)
        ax.set_xlim(-0.6, len(names) - 0.4)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("identified - a priori (mm)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    return to_data_uri(fig)


def gaps_plot(result: ResultDocument) -> str | None:
    """Displacement gaps (vision - model, mm) per consecutive pose pair, fit poses and validation poses."""
    fig, axes = _figure(10.0, 3.2, 1, 2)
    drawn = False
    for ax, key, title in (
        (axes[0][0], "poses", "fit poses"),
        (axes[0][1], "validation", "validation poses"),
    ):
        for name, v in result.validation.items():
            gaps = v.gaps(key)
            g = (gaps.gaps_mm if gaps is not None else None) or []
            if g:
                ax.plot(
                    np.arange(1, len(g) + 1),
                    g,
                    marker="o",
                    ms=3,
                    lw=1,
                    color=colour(name),
                    label=name,
                    ls=":" if name == "truth" else "-",
                )
                drawn = True
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_title(f"displacement gaps, {title}", fontsize=10)
        ax.set_xlabel("pose pair")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel("gap (mm)")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no poses", transform=ax.transAxes, ha="center", va="center", color="0.4")
    return to_data_uri(fig) if drawn else None


def leg_residual_plot(residuals: dict[str, LegResiduals]) -> str | None:
    """Per method, the residual angle (deg) of each leg at each fit and validation pose."""
    items = [(m, r) for m, r in residuals.items() if r is not None and np.isfinite(r.angle_rad).any()]
    if not items:
        return None
    fig, axes = _figure(10.0, 1.0 + 2.2 * len(items), len(items), 1, sharex=True)
    for ax, (m, r) in zip(axes[:, 0], items, strict=True):
        x = np.arange(len(r.frames))
        deg = np.degrees(r.angle_rad)
        for leg in range(4):
            ax.plot(
                x + (leg - 1.5) * 0.12,
                deg[:, leg],
                ls="none",
                marker="o",
                ms=4,
                color=LEG_COLOURS[leg],
                label=f"leg {leg + 1}",
            )
        nfit = sum(p == "poses" for p in r.phases)
        if 0 < nfit < len(r.frames):
            ax.axvline(nfit - 0.5, color="0.4", ls="--", lw=1)
            ax.text(nfit - 0.4, 0.95, "validation poses", transform=ax.get_xaxis_transform(), fontsize=8, va="top")
        ax.set_ylabel(f"{m}\nangle (deg)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0][0].legend(ncol=4, fontsize=8, loc="upper left")
    axes[-1][0].set_xlabel("pose (fit poses, then validation poses)")
    axes[-1][0].xaxis.set_major_locator(MaxNLocator(integer=True))
    return to_data_uri(fig)


def singular_value_plot(result: ResultDocument, methods: Sequence[str]) -> str | None:
    """Singular values of each method's identification Jacobian over the seven parameters, relative to the
    largest, with the rank threshold."""
    fig, axes = _figure(7.0, 3.4)
    ax = axes[0][0]
    drawn = False
    for m in methods:
        e = result.methods.get(m)
        ident = (e.identifiability if e is not None else None) or Identifiability()
        s = np.asarray(ident.singular_values or [], float)
        if s.size and s[0] > 0:
            ax.semilogy(
                np.arange(1, s.size + 1),
                np.maximum(s / s[0], 1e-18),
                marker="o",
                color=colour(m),
                label=f"{m} (rank {ident.rank})",
            )
            drawn = True
    if not drawn:
        return None
    ax.axhline(1e-7, color="0.4", ls="--", lw=1, label="rank threshold (1e-7)")
    ax.set_xlabel("singular value index")
    ax.set_ylabel("relative singular value")
    ax.set_title("identification Jacobian over (H, q02, q03, q04, S, D, L)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return to_data_uri(fig)


def camera_view_plot(camera_summary: dict[str, Any]) -> str | None:
    """RMS reprojection error (px) of each kept calibration view, with the overall RMS."""
    per = camera_summary.get("per_view_rms_px") or {}
    if not per:
        return None
    keys = sorted(per, key=lambda k: int(k) if str(k).isdigit() else str(k))
    vals = [per[k] for k in keys]
    fig, axes = _figure(8.0, 3.0)
    ax = axes[0][0]
    ax.bar(range(len(keys)), vals, color="#1f77b4")
    ax.axhline(
        camera_summary.get("rms_px", float(np.sqrt(np.mean(np.square(vals))))),
        color="#d62728",
        ls="--",
        lw=1,
        label=f"overall RMS {camera_summary.get('rms_px', 0):.3f} px",
    )
    ax.set_xticks(range(len(keys)), [str(k) for k in keys], fontsize=8)
    ax.set_xlabel("dataset frame of the view")
    ax.set_ylabel("RMS reprojection error (px)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8)
    return to_data_uri(fig)
