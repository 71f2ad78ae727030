"""The calibration document (i4cal.calibration/1, calib.identify.export): built from a result of the three methods on
the
geometric twin, its seven parameters reproduce each method's combinations, its statuses follow the completion rule,
it survives JSON, and the parity check passes for the result's own model and fails for any other."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from calib.errors import InputError
from calib.formats.plan import make_plan
from calib.identify.export import (
    COMPLETION_RULES,
    REPRODUCE_TOL_M,
    CalibrationDocument,
    ExportContext,
    build_calibration,
    check_parity,
    load_calibration,
    method_parameters,
    plan_joints,
    recommended_method,
)
from calib.identify.pipeline import calibrate, to_jsonable
from calib.model.kinematics import dkm
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES, I4Parameters

CTX = ExportContext(software_version="test", bench="bench-x", run="0" * 32, date="2026-01-01T00:00:00Z")


@pytest.fixture(scope="module")
def result(noisy_obs) -> dict:
    return to_jsonable(calibrate(noisy_obs[0]))


@pytest.fixture(scope="module")
def full_q(result) -> np.ndarray:
    nominal = I4Parameters.from_mapping(result["nominal"])
    return plan_joints(make_plan("full", nominal), nominal)


def _roundtrip(doc: CalibrationDocument) -> CalibrationDocument:
    return load_calibration(json.loads(doc.model_dump_json()))


@pytest.mark.parametrize("method", ["combined", "end-effector", "legs"])
def test_seven_reproduce_the_combinations_and_the_check_passes(result, full_q, method):
    entry = result["methods"][method]
    assert entry["converged"]
    doc = _roundtrip(build_calibration(result, CTX, method))
    assert doc.format == "i4cal.calibration/1" and doc.method == method and doc.method_choice == f"asked for: {method}"
    assert (doc.bench, doc.run, doc.date, doc.software_version) == ("bench-x", "0" * 32, "2026-01-01T00:00:00Z", "test")
    assert doc.units.length == "m" and doc.units.covariance == "m^2" and doc.units.T_per_rad == "m/rad"
    got = doc.to_parameters().combinations()
    for k in COMBINATION_NAMES:
        assert abs(got[k] - entry["combinations"][k]) <= REPRODUCE_TOL_M, k
        assert doc.combinations[k] == entry["combinations"][k]
        assert doc.combinations_std[k] == entry["combinations_std"][k]
    assert doc.covariance == entry["covariance"] and doc.covariance_order == list(COMBINATION_NAMES)
    # the model the result validated with: its seven, bit for bit
    assert doc.seven == entry["parameters_seven_completed"]
    assert doc.nominal == result["nominal"] and doc.T_per_rad == result["nominal"]["T_per_rad"]
    assert set(doc.identified) | set(doc.fixed_at_nominal) == set(PARAMETER_NAMES)
    assert doc.completion.text == COMPLETION_RULES[doc.completion.rule]
    assert doc.validation is not None and doc.validation.poses == "validation"
    assert doc.validation.gap_rms_m == pytest.approx(result["validation"][method]["gaps_validation"]["rms_mm"] * 1e-3)
    rep = check_parity(doc, method_parameters(result, method), entry["combinations"], full_q)
    assert rep.passed and rep.n_poses == len(full_q) == 121
    assert rep.dkm_max_m <= REPRODUCE_TOL_M and rep.ikm_max_m <= REPRODUCE_TOL_M and rep.unreachable == 0


def test_completed_methods_fix_H_S_q03_at_nominal_and_derive_the_std(result):
    nominal = result["nominal"]
    for method in ("combined", "end-effector"):
        entry = result["methods"][method]
        doc = build_calibration(result, CTX, method)
        assert doc.completion.rule == "combinations+nominal"
        assert doc.fixed_at_nominal == ["H", "S", "q03"] and doc.identified == ["q02", "q04", "D", "L"]
        assert all(doc.seven[k] == nominal[k] for k in ("H", "S", "q03"))
        assert all(doc.seven_std[k] is None for k in ("H", "S", "q03"))
        cov = np.asarray(entry["covariance"])
        # L = L, D = H - (H-D), q02 = 2 S - 2 (S-q02/2), q04 = q03 + 2 S - 2 (S-(q04-q03)/2)
        assert doc.seven_std["L"] == pytest.approx(np.sqrt(cov[0, 0]), rel=1e-12)
        assert doc.seven_std["D"] == pytest.approx(np.sqrt(cov[1, 1]), rel=1e-12)
        assert doc.seven_std["q02"] == pytest.approx(2 * np.sqrt(cov[2, 2]), rel=1e-12)
        assert doc.seven_std["q04"] == pytest.approx(2 * np.sqrt(cov[3, 3]), rel=1e-12)


def test_legs_identifies_the_seven_or_says_which_fell_back_to_nominal(result):
    entry = result["methods"]["legs"]
    doc = build_calibration(result, CTX, "legs")
    assert doc.completion.rule == "identified" and doc.identified == list(PARAMETER_NAMES) and not doc.fixed_at_nominal
    assert doc.seven == entry["seven"] and doc.seven_std == entry["seven_std"]
    for fallback, rule, fixed in (
        ("L, S, D", "a-priori L, S, D", ["S", "D", "L"]),
        ("all seven", "a-priori all", list(PARAMETER_NAMES)),
    ):
        r = copy.deepcopy(result)
        r["methods"]["legs"]["diagnostics"]["identifiability"]["a_priori_fallback"] = fallback
        d = build_calibration(r, CTX, "legs")
        assert d.completion.rule == rule and d.fixed_at_nominal == fixed
        assert d.identified == [n for n in PARAMETER_NAMES if n not in fixed]
        assert all(d.seven_std[n] is None for n in fixed)
        assert d.completion.text.startswith("the method") and "nominal" in d.completion.text


def test_recommended_method_rule(result):
    """The export's default method is the verdict's (calib.identify.verdict), the rule every front end states."""
    from calib.identify.verdict import verdict

    assert recommended_method(result)[0] == verdict(result).method == "combined"
    assert build_calibration(result, CTX).method == "combined"
    assert build_calibration(result, CTX).method_choice.startswith("recommended: load combined")
    r = copy.deepcopy(result)
    r["methods"]["combined"] = {"converged": False, "error": "boom", "parameters": None, "combinations": None}
    name, why = recommended_method(r)
    assert name == verdict(r).method and name in ("end-effector", "legs") and "validation gap" in why
    # no gap at all to judge by: nothing recommended, the user names the method
    for m in ("end-effector", "legs"):
        del r["validation"][m]
    with pytest.raises(InputError, match="--method"):
        recommended_method(r)
    for m in r["methods"]:
        r["methods"][m]["converged"] = False
    with pytest.raises(InputError, match="no fit converged"):
        recommended_method(r)
    with pytest.raises(InputError, match="'combined' did not converge in this result: boom") as e:
        build_calibration(
            r | {"methods": {**r["methods"], "combined": {"converged": False, "error": "boom"}}}, CTX, "combined"
        )
    assert e.value.field == "method"
    with pytest.raises(InputError, match="no method 'nope'"):
        build_calibration(result, CTX, "nope")


def test_the_check_fails_for_a_changed_parameter_or_another_methods_model(result, full_q):
    entry = result["methods"]["legs"]
    ref = method_parameters(result, "legs")
    doc = build_calibration(result, CTX, "legs")
    # one micrometre on L: the DKM moves by about that, beyond the 1 nm tolerance
    bad = doc.model_copy(update={"seven": {**doc.seven, "L": doc.seven["L"] + 1e-6}})
    rep = check_parity(bad, ref, entry["combinations"], full_q)
    expected = np.max(np.abs(dkm(bad.to_parameters(), full_q) - dkm(ref, full_q)))
    assert not rep.passed and rep.dkm_max_m == pytest.approx(expected) and 1e-7 < rep.dkm_max_m < 1e-5
    assert rep.combinations_max_m == pytest.approx(1e-6, rel=1e-6) and rep.ikm_max_m > 1e-7
    # H moves the constant offsets the combinations do not see (H - D kept): the combinations agree, the DKM not
    shifted = doc.model_copy(update={"seven": {**doc.seven, "H": doc.seven["H"] + 1e-3, "D": doc.seven["D"] + 1e-3}})
    rep = check_parity(shifted, ref, entry["combinations"], full_q)
    assert rep.combinations_max_m < 1e-12 and not rep.passed and rep.dkm_max_m == pytest.approx(1e-3, rel=1e-6)
    # the combined method's document against the legs result: millimetres apart
    other = build_calibration(result, CTX, "combined")
    rep = check_parity(other, ref, entry["combinations"], full_q)
    assert not rep.passed and rep.dkm_max_m > 1e-4
    # a changed T_per_rad fails even where the poses agree
    rep = check_parity(doc.model_copy(update={"T_per_rad": 0.021}), ref, entry["combinations"], full_q)
    assert not rep.passed and rep.T_per_rad_diff == pytest.approx(0.001)


def test_bad_documents_and_results_are_named():
    with pytest.raises(InputError, match="field 'format'.*not an i4cal.calibration/1 document"):
        load_calibration({"format": "i4cal.result/1"}, source="x.json")
    with pytest.raises(InputError, match="x.json, field 'seven'.*missing parameter.*q04"):
        load_calibration({**_minimal(), "seven": {k: 0.1 for k in PARAMETER_NAMES if k != "q04"}}, source="x.json")
    with pytest.raises(InputError, match="field 'T_per_rad'"):
        load_calibration({**_minimal(), "T_per_rad": -1}, source="x.json")
    with pytest.raises(InputError, match="field 'format'.*not an i4cal.result/1"):
        build_calibration({"format": "something"}, CTX)


def test_an_inconsistent_result_is_refused(result):
    r = copy.deepcopy(result)
    r["methods"]["combined"]["parameters_seven_completed"]["L"] += 1e-6
    with pytest.raises(InputError, match=r"field 'methods.combined.parameters_seven_completed'.*L = .*inconsistent"):
        build_calibration(r, CTX, "combined")


def test_without_stored_seven_the_combinations_are_completed_with_nominal(result):
    """A result written before parameters_seven_completed existed: the same completion rule, the same document."""
    r = copy.deepcopy(result)
    del r["methods"]["combined"]["parameters_seven_completed"]
    old, new = build_calibration(result, CTX, "combined"), build_calibration(r, CTX, "combined")
    for k in PARAMETER_NAMES:
        assert new.seven[k] == pytest.approx(old.seven[k], abs=1e-15)


def _minimal() -> dict:
    from calib.model.parameters import NOMINAL

    return {
        "format": "i4cal.calibration/1",
        "method": "combined",
        "method_choice": "x",
        "software_version": "x",
        "seven": NOMINAL.seven(),
        "seven_std": dict.fromkeys(PARAMETER_NAMES),
        "identified": [],
        "fixed_at_nominal": list(PARAMETER_NAMES),
        "completion": {"rule": "a-priori all", "text": COMPLETION_RULES["a-priori all"]},
        "T_per_rad": 0.02,
        "combinations": NOMINAL.combinations(),
        "combinations_std": dict.fromkeys(COMBINATION_NAMES),
        "nominal": NOMINAL.as_dict(),
        "nominal_combinations": NOMINAL.combinations(),
    }


def test_a_minimal_document_loads():
    doc = load_calibration(_minimal())
    assert doc.to_parameters() == I4Parameters.from_mapping({**_minimal()["seven"], "T_per_rad": 0.02})
    assert doc.covariance is None and doc.units.length == "m"


@pytest.mark.parametrize("name", PARAMETER_NAMES)
def test_each_of_the_seven_parameters_changed_by_a_micrometre_fails_the_check(result, full_q, name):
    """H, S and q03, which the combinations do not see, are checked through the base-frame point and T."""
    doc = build_calibration(result, CTX, "legs")
    bad = doc.model_copy(update={"seven": {**doc.seven, name: doc.seven[name] + 1e-6}})
    rep = check_parity(bad, method_parameters(result, "legs"), result["methods"]["legs"]["combinations"], full_q)
    assert not rep.passed and max(rep.dkm_max_m, rep.ikm_max_m) > 1e-7, rep
