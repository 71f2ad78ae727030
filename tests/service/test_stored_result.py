"""A stored result document (``i4cal calibrate -o`` of an earlier version, committed as test data) loads into the
typed ResultDocument, writes back byte-identical, reads through attributes, and renders the report, the verdict and
the export. The data: ``i4cal simulate -o obs.json --seed 1`` calibrated with every method
(``result_twin_seed1.json``), and the same observations without their lock and validation phases, where the legs
method fails (``result_legs_failed.json``)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from calib.formats.resultdoc import ResultDocument
from calib.identify.export import ExportContext, build_calibration
from calib.identify.verdict import verdict
from calib.model.parameters import COMBINATION_NAMES

DATA = Path(__file__).parent / "data"
FILES = ("result_twin_seed1.json", "result_legs_failed.json")


def _keys_in_order(x: Any) -> Any:
    """Every mapping's keys, in their order, nested (what a byte comparison of the JSON sees besides the values)."""
    if isinstance(x, dict):
        return [(k, _keys_in_order(v)) for k, v in x.items()]
    if isinstance(x, list):
        return [_keys_in_order(v) for v in x]
    return None


@pytest.mark.parametrize("name", FILES)
def test_a_stored_result_loads_and_writes_back_byte_identical(name):
    text = (DATA / name).read_text(encoding="utf-8")
    doc = ResultDocument.from_dict(json.loads(text), source=name)
    assert json.dumps(doc.to_dict(), indent=1) == text
    # what the API serves (response_model=ResultDocument, exclude_unset): the stored keys, in the stored order
    served = doc.model_dump(mode="json", exclude_unset=True)
    assert _keys_in_order(served) == _keys_in_order(json.loads(text))


def test_a_stored_result_reads_through_attributes():
    raw = json.loads((DATA / "result_legs_failed.json").read_text(encoding="utf-8"))
    doc = ResultDocument.from_dict(raw)
    legs = doc.methods["legs"]
    assert not legs.ok and legs.failure == raw["methods"]["legs"]["error"] and "lock-1" in legs.failure
    comb = doc.methods["combined"]
    assert comb.ok and comb.values == raw["methods"]["combined"]["combinations"]
    assert comb.bound is not None and comb.bound.std == raw["methods"]["combined"]["bound"]["std"]
    assert comb.identifiability is not None and comb.identifiability.rank == 4
    gaps = doc.validation["combined"].gaps_poses
    assert gaps is not None and gaps.rms_mm == raw["validation"]["combined"]["gaps_poses"]["rms_mm"]
    assert doc.base_frame is not None and doc.base_frame.rotation().shape == (3, 3)
    # keys the models do not name are kept, and reachable
    assert comb.diagnostics is not None and comb.diagnostics.model_extra
    truth = doc.truth_combinations()
    assert truth is not None
    for k in COMBINATION_NAMES:
        assert truth[k] == pytest.approx(comb.values[k] - raw["truth_errors"]["combined"][k], abs=0)


def test_a_document_that_is_not_a_result_is_named():
    from calib.errors import InputError

    with pytest.raises(InputError, match="field 'format'.*not an i4cal.result/1"):
        ResultDocument.from_dict({"format": "i4cal.plan/1"}, source="x.json")
    raw = json.loads((DATA / "result_twin_seed1.json").read_text(encoding="utf-8"))
    raw["methods"]["legs"]["iterations"] = "many"
    with pytest.raises(InputError, match=r"x.json, field 'methods.legs.iterations'"):
        ResultDocument.from_dict(raw, source="x.json")


@pytest.mark.parametrize("name", FILES)
def test_a_stored_result_renders_the_report_the_verdict_and_the_export(name):
    from service.report import build_report
    from service.report.analysis import json_sha256
    from service.report.builder import ReportInputs

    raw = json.loads((DATA / name).read_text(encoding="utf-8"))
    doc = ResultDocument.from_dict(raw)
    html = build_report(ReportInputs(result=doc, source=name), max_frames=0)
    assert html == build_report(ReportInputs(result=raw, source=name), max_frames=0) or _same_but_dates(
        html, build_report(ReportInputs(result=raw, source=name), max_frames=0)
    )
    v = verdict(doc, name)
    assert v.method is not None and v.method in raw["methods"] and v.lines()[0] in html.replace("&#x27;", "'")
    assert json_sha256(raw) in html  # the result's hash is the stored JSON's
    for m, e in raw["methods"].items():
        assert f"Method: {m}" in html
        if e["converged"]:
            assert f"{e['combinations']['L'] * 1e3:.4f}" in html  # the identified L in mm, from the document
        else:
            assert "failed" in html and e["error"].split(" (")[0] in html
    cal = build_calibration(doc, ExportContext(software_version="test"))
    assert cal.method == v.method and cal.combinations == raw["methods"][v.method]["combinations"]


def _same_but_dates(a: str, b: str) -> bool:
    date = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC")
    return date.sub("DATE", a) == date.sub("DATE", b)


def test_merging_one_method_at_a_time_gives_each_methods_entry_validation_and_truth_error():
    """The service fits one method at a time and merges the parts (service.jobs.fit_job)."""
    raw = json.loads((DATA / "result_twin_seed1.json").read_text(encoding="utf-8"))

    def part(method: str) -> ResultDocument:
        d = json.loads(json.dumps(raw))
        d["methods"] = {method: d["methods"][method]}
        d["validation"] = {k: v for k, v in d["validation"].items() if k in ("a priori", method, "truth")}
        d["truth_errors"] = {method: d["truth_errors"][method]}
        return ResultDocument.from_dict(d)

    doc = part("combined").merge(part("legs"), "legs")
    out = doc.to_dict()
    assert list(out["methods"]) == ["combined", "legs"]
    assert out["methods"]["legs"] == raw["methods"]["legs"]
    assert list(out["validation"]) == ["a priori", "combined", "truth", "legs"]
    assert out["validation"]["legs"] == raw["validation"]["legs"]
    assert out["truth_errors"] == {m: raw["truth_errors"][m] for m in ("combined", "legs")}
    assert doc.truth_error("legs") == raw["truth_errors"]["legs"]
