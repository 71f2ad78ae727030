"""The calibration report: a run's or a dataset's result as one self-contained HTML file (``i4cal report``,
``GET /api/v1/runs/{id}/report``). See docs/report.md."""

from .builder import ReportInputs, build_report
from .sources import RunNotFoundError, find_run, inputs_from_path, inputs_from_run

__all__ = ["ReportInputs", "RunNotFoundError", "build_report", "find_run", "inputs_from_path", "inputs_from_run"]
