"""Terminal rendering of calibration results (the paper's Tables I, II and III) and the verdict.

Every table fits the console's width (80 columns on a plain terminal): the methods are columns, and when they do not
fit the table is split into several, each repeating the row names; names are never cut. Uncertainties are
± 1 standard deviation everywhere (:data:`calib.identify.verdict.UNCERTAINTY`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rich import box
from rich.console import Console
from rich.table import Table

from calib.formats.resultdoc import ResultDocument
from calib.identify.validation import vision_scale_ppm
from calib.identify.verdict import UNCERTAINTY, Verdict, verdict
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES

#: width of a console that is not a terminal (a file, a pipe): wide enough for every table, no squeezing
FILE_WIDTH = 150


def _mm(v: float | None, digits: int = 3) -> str:
    return "-" if v is None else f"{v * 1e3:.{digits}f}"


def make_console(stderr: bool = False) -> Console:
    """A console that does not squeeze tables when the output is a file or a pipe."""
    con = Console(stderr=stderr)
    if not con.is_terminal:
        con = Console(stderr=stderr, width=FILE_WIDTH)
    return con


def _fitting_tables(
    title: str, rows: Sequence[str], columns: Sequence[tuple[str, Sequence[str]]], width: int
) -> list[Table]:
    """``columns`` (header, one cell per row) as tables no wider than ``width``: split into several tables, each with
    the row names first, when they do not fit in one."""
    name_w = max(len(r) for r in rows) + 2
    chunks: list[list[tuple[str, Sequence[str]]]] = [[]]
    used = name_w
    for head, cells in columns:
        w = max(len(head), *(len(c) for c in cells)) + 3
        if chunks[-1] and used + w > width:
            chunks.append([])
            used = name_w
        chunks[-1].append((head, cells))
        used += w
    out = []
    for i, chunk in enumerate(chunks):
        head = title + (f" ({i + 1}/{len(chunks)})" if len(chunks) > 1 else "")
        t = Table(
            title=head, title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, min_width=min(len(head), width)
        )
        t.add_column("", no_wrap=True)
        for head, _ in chunk:
            t.add_column(head, justify="right", no_wrap=True)
        for j, r in enumerate(rows):
            t.add_row(r, *(cells[j] for _, cells in chunk))
        out.append(t)
    return out


def _table1(doc: ResultDocument, width: int) -> tuple[list[Table], list[str]]:
    """Table I (a priori and each method's four combinations ± 1 std) and the failed fits' reasons (one line each)."""
    nom = doc.nominal_combinations
    cols: list[tuple[str, Sequence[str]]] = [("a priori", [_mm(nom[k], 2) for k in COMBINATION_NAMES])]
    failed = []
    for name, e in doc.methods.items():
        if not e.parameters or not e.std:
            failed.append(f"{name}: fit failed: {e.error or e.message or 'no parameters'}")
            continue
        head = name if e.converged else f"{name} (not converged)"
        val, std = e.parameters, e.std
        cols.append((head, [f"{_mm(val[k], 2)} ± {_mm(std[k], 2)}" for k in COMBINATION_NAMES]))
    tables = _fitting_tables(f"Table I - the four combinations (mm, {UNCERTAINTY})", COMBINATION_NAMES, cols, width)
    truth = doc.truth_errors
    if truth:
        tcols = [(name, [f"{te[k] * 1e3:+.3f}" for k in COMBINATION_NAMES]) for name, te in truth.items()]
        tables += _fitting_tables("errors against the simulator's truth (mm)", COMBINATION_NAMES, tcols, width)
    return tables, failed


def _seven(doc: ResultDocument, width: int) -> list[Table]:
    """The seven parameters of the methods that identify them (the legs method), ± 1 std."""
    cols: list[tuple[str, Sequence[str]]] = [("a priori", [_mm(doc.nominal[k], 2) for k in PARAMETER_NAMES])]
    for name, e in doc.methods.items():
        seven, seven_std = e.seven, e.seven_std
        if seven and seven_std:
            cols.append((name, [f"{_mm(seven[k], 2)} ± {_mm(seven_std[k], 2)}" for k in PARAMETER_NAMES]))
    if len(cols) == 1:
        return []
    return _fitting_tables(f"the seven parameters (mm, {UNCERTAINTY})", PARAMETER_NAMES, cols, width)


def _table2(doc: ResultDocument) -> Table:
    """Table II (displacement gaps, vision vs model) and Table III (straightness), one row per parameter set."""
    t = Table(
        title="Table II - displacement gaps (mm) / Table III - straightness (mm)",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
    )
    t.add_column("parameter set", no_wrap=True)
    for head in ("fit poses\nmean", "fit poses\nRMS", "validation\nmean", "validation\nRMS", "straight-\nness RMS"):
        t.add_column(head, justify="right", no_wrap=True)

    def f(x: Any, fmt: str = ".3f") -> str:
        return "-" if x is None else format(x, fmt)

    for name, v in doc.validation.items():
        gp, gv, st = v.gaps_poses, v.gaps_validation, v.straightness
        t.add_row(
            name if name != "truth" else "true geometry",
            f(gp and gp.mean_mm, "+.4f"),
            f(gp and gp.rms_mm),
            f(gv and gv.mean_mm, "+.4f"),
            f(gv and gv.rms_mm),
            f(st and st.rms_mm),
        )
    return t


#: a camera length scale this far from 1 (relative) is more than a camera calibration or a board's print explains
SCALE_CHECK_ABOVE = 0.005


def scale_line(doc: ResultDocument | dict[str, Any]) -> str | None:
    """The camera's length scale against the encoders, explained in one line (None: not measured)."""
    sc = ResultDocument.of(doc).vision_scale()
    if sc is None or sc.std is None:
        return None
    far = abs(float(1.0 if sc.scale is None else sc.scale) - 1.0) > SCALE_CHECK_ABOVE
    return (
        f"camera length scale vs encoders (translation phase, {sc.n_poses} poses): "
        f"{vision_scale_ppm(sc.model_dump())}; "
        "Table II's gaps are divided by it"
        + (" (beyond 0.5%: check the board's square length in the bench file)" if far else "")
    )


def print_result(
    result_doc: ResultDocument | dict[str, Any], console: Console | None = None, result: str | None = None
) -> Verdict:
    """Print Table I (a priori vs each method, ± 1 std), the seven parameters where identified, Table II (gaps) and
    Table III (straightness), then the verdict (which result to load and why, the next command); returns the
    verdict.

    ``result``: how the verdict's next command names the result (a result file); None: ``RESULT``.
    """
    doc = ResultDocument.of(result_doc)
    con = console or make_console()
    width = con.width
    tables, failed = _table1(doc, width)
    for t in tables:
        con.print(t)
    line: str | None  # a failed row's message, then the scale line (or None)
    for line in failed:
        con.print(f"[red]{line}[/red]")
    for t in _seven(doc, width):
        con.print(t)
    con.print(_table2(doc))
    line = scale_line(doc)
    if line:
        con.print(line)
        sc = doc.vision_scale()
        if sc is not None and sc.warning:
            con.print(f"[yellow]warning:[/yellow] {sc.warning}")
    v = verdict(doc, result or "RESULT")
    style = "bold green" if v.method else "bold red"
    lines = v.lines()
    con.print(f"[{style}]{lines[0]}[/{style}]", soft_wrap=False)
    for extra in lines[1:]:
        con.print(extra, highlight=False)
    if v.next_command and result is None:
        con.print("(RESULT: the result file, e.g. of i4cal calibrate OBS -o result.json)", highlight=False)
    return v


# -- long steps: rich on a terminal, plain periodic lines otherwise (a script, CI, a log file) ---------------------

#: seconds between two plain progress lines when the output is not a terminal (``I4CAL_PROGRESS_EVERY_S`` overrides)
PLAIN_EVERY_S = 10.0


def _plain_every_s() -> float:
    import os

    try:
        return max(0.05, float(os.environ.get("I4CAL_PROGRESS_EVERY_S", PLAIN_EVERY_S)))
    except ValueError:
        return PLAIN_EVERY_S


class LongStep:
    """A long step's progress on ``console``: a rich spinner and bar on a terminal; elsewhere a first line at once,
    then one plain line every :data:`PLAIN_EVERY_S` seconds (what it is doing, done/total, elapsed), and a last line
    when it ends.

    Use as a context manager; :meth:`update` with a status text and/or ``done``/``total``.
    """

    def __init__(self, console: Console, label: str, total: int | None = None) -> None:
        import threading
        import time

        self.console, self.label, self.total = console, label, total
        self.done: int | None = None
        self.text = ""
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bar: Any = None
        self._task: Any = None

    def __enter__(self) -> LongStep:
        import threading

        if self.console.is_terminal:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                SpinnerColumn,
                TextColumn,
                TimeElapsedColumn,
            )

            self._bar = Progress(
                SpinnerColumn(),
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                console=self.console,
                transient=True,
            )
            self._bar.__enter__()
            self._task = self._bar.add_task(self.label, total=self.total)
        else:
            self.console.print(f"{self.label} ...", highlight=False)
            self._thread = threading.Thread(target=self._ticker, name="i4cal-progress", daemon=True)
            self._thread.start()
        return self

    def _line(self) -> str:
        import time

        count = f" {self.done}/{self.total}" if self.done is not None and self.total else ""
        text = f": {self.text}" if self.text else ""
        return f"{self.label}{count}{text} ({time.monotonic() - self._t0:.0f} s)"

    def _ticker(self) -> None:
        every = _plain_every_s()
        while not self._stop.wait(every):
            self.console.print(self._line(), highlight=False)

    def update(self, text: str | None = None, done: int | None = None, total: int | None = None) -> None:
        if text is not None:
            self.text = text
        if total is not None:
            self.total = total
        if done is not None:
            self.done = done
        if self._bar is not None:
            desc = self.label + (f": {self.text}" if self.text else "")
            self._bar.update(self._task, description=desc, completed=self.done or 0, total=self.total)

    def __exit__(self, *exc: Any) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc)
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if exc[0] is None:
            self.console.print(self._line().replace(f"{self.label}", f"{self.label} done", 1), highlight=False)
