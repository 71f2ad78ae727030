"""Terminal rendering of calibration results (the paper's Tables I, II and III)."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

from calib.parameters import COMBINATION_NAMES, PARAMETER_NAMES
from calib.validation import recorded_vision_scale, vision_scale_ppm


def _mm(v: float | None, digits: int = 3) -> str:
    return "-" if v is None else f"{v * 1e3:.{digits}f}"


def make_console(stderr: bool = False) -> Console:
    """A console that does not squeeze tables when the output is a file or a pipe."""
    con = Console(stderr=stderr)
    if not con.is_terminal:
        con = Console(stderr=stderr, width=150)
    return con


def print_result(doc: dict[str, Any], console: Console | None = None) -> None:
    """Print Table I (a priori vs each method, with std), Table II (gaps) and Table III (straightness)."""
    con = console or make_console()
    t1 = Table(title="Table I - identifiable parameters (mm; ± one standard deviation)", title_justify="left")
    t1.add_column("parameter set")
    for k in COMBINATION_NAMES:
        t1.add_column(k, justify="right")
    t1.add_column("converged", justify="center")
    nom = doc["nominal_combinations"]
    t1.add_row("a priori", *[_mm(nom[k], 2) for k in COMBINATION_NAMES], "")
    for name, e in doc["methods"].items():
        if not e.get("parameters"):
            t1.add_row(name, *(["-"] * 4), f"[red]no: {e.get('error', '')}[/red]")
            continue
        t1.add_row(
            name,
            *[f"{e['parameters'][k] * 1e3:.2f} ± {e['std'][k] * 1e3:.2f}" for k in COMBINATION_NAMES],
            "yes" if e.get("converged") else "[red]no[/red]",
        )
    truth = doc.get("truth_errors")
    if truth:
        for name, te in truth.items():
            t1.add_row(f"[dim]{name} - truth[/dim]", *[f"[dim]{te[k] * 1e3:+.3f}[/dim]" for k in COMBINATION_NAMES], "")
    con.print(t1)
    legs = doc["methods"].get("legs")
    if legs and legs.get("seven"):
        t7 = Table(title="Legs method - all seven parameters (mm)", title_justify="left")
        t7.add_column("")
        for k in PARAMETER_NAMES:
            t7.add_column(k, justify="right")
        t7.add_row("a priori", *[_mm(doc["nominal"][k], 2) for k in PARAMETER_NAMES])
        t7.add_row(
            "legs", *[f"{legs['seven'][k] * 1e3:.2f} ± {legs['seven_std'][k] * 1e3:.2f}" for k in PARAMETER_NAMES]
        )
        con.print(t7)
    t2 = Table(
        title="Table II - displacement gaps, vision vs model (mm)  /  Table III - straightness (mm)",
        title_justify="left",
    )
    for c in (
        "parameter set",
        "fit poses mean",
        "fit poses RMS",
        "validation mean",
        "validation RMS",
        "straightness RMS",
    ):
        t2.add_column(c, justify="right" if c != "parameter set" else "left")
    for name, v in doc["validation"].items():
        gp, gv, st = v.get("gaps_poses", {}), v.get("gaps_validation", {}), v.get("straightness", {})

        def f(x: Any, fmt: str = ".3f") -> str:
            return "-" if x is None else format(x, fmt)

        t2.add_row(
            name if name != "truth" else "[dim]true geometry[/dim]",
            f(gp.get("mean_mm"), "+.4f"),
            f(gp.get("rms_mm")),
            f(gv.get("mean_mm"), "+.4f"),
            f(gv.get("rms_mm")),
            f(st.get("rms_mm")),
        )
    con.print(t2)
    sc = recorded_vision_scale(doc["validation"])
    if sc and sc.get("std") is not None:
        con.print(
            f"vision's displacements divided by its scale on the translation phase: "
            f"{vision_scale_ppm(sc)} ({sc['n_poses']} poses)"
        )
        if sc.get("warning"):
            con.print(f"[yellow]warning:[/yellow] {sc['warning']}")
