"""The report's first screen says which result to load and why (calib.identify.verdict), in the uncertainty convention
of
the command line and the dashboard (± 1 std, U (k = 2) beside it), with the combinations spelled as everywhere."""

from __future__ import annotations

import re

import pytest


@pytest.fixture(scope="module")
def result() -> dict:
    from calib.formats.observations import Observations
    from calib.identify.pipeline import calibrate, to_jsonable
    from drivers.sim.twin import GeometricTwin

    return to_jsonable(calibrate(Observations.from_dict(GeometricTwin().observations(seed=1))))


def test_the_first_screen_gives_the_verdict_and_the_next_command(result):
    from calib.identify.verdict import verdict
    from service.report import build_report
    from service.report.builder import ReportInputs

    html = build_report(ReportInputs(result=result, source="result.json"), max_frames=0)
    v = verdict(result, "result.json")
    head = html[: html.index('id="contents"')] if 'id="contents"' in html else html[:20000]
    assert 'id="verdict"' in head and f"verdict: load {v.method}:" in head, head[-3000:]
    assert f"i4cal export result.json -o calibration.json --method {v.method}" in head
    # Table I: value ± 1 std (the convention of the CLI and the dashboard), U (k = 2) said to be beside it
    t1 = re.search(r"<caption>Table I[^<]*</caption>", html).group(0)
    assert "± 1 std" in t1 and "U (k = 2)" in t1, t1
    e = result["methods"][v.method]
    assert f"{e['parameters']['L'] * 1e3:.3f} ± {e['std']['L'] * 1e3:.3f}" in html


def test_the_identifiability_table_spells_the_combinations_as_everywhere(result):
    from service.report import build_report
    from service.report.builder import ReportInputs

    html = build_report(ReportInputs(result=result, source="result.json"), max_frames=0)
    assert "L, H-D, S-q02/2, S-(q04-q03)/2 (row-reduced:" in html
