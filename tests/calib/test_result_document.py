"""The result document's contract (calib/formats/resultdoc.py): the combinations under clear names beside the format's
first
ones, the document validates against its models, and the API publishes them as the result's response schema."""

from __future__ import annotations

import json

from calib.formats.resultdoc import ResultDocument
from calib.identify.pipeline import calibrate, to_jsonable
from calib.model.parameters import COMBINATION_NAMES, PARAMETER_NAMES


def test_combinations_named_beside_the_first_names(noisy_obs):
    obs, _ = noisy_obs
    doc = json.loads(json.dumps(to_jsonable(calibrate(obs))))
    model = ResultDocument.model_validate(doc)
    assert list(model.methods) == ["combined", "end-effector", "legs"]
    for name, e in doc["methods"].items():
        assert e["converged"], name
        assert set(e["combinations"]) == set(COMBINATION_NAMES)
        assert e["combinations"] == e["parameters"] and e["combinations_std"] == e["std"]
        assert model.methods[name].combinations == e["parameters"]
    assert set(doc["methods"]["legs"]["seven"]) == set(PARAMETER_NAMES)
    # further keys are kept: the format grows
    assert model.model_dump(exclude_unset=True)["methods"]["combined"]["bound"] == doc["methods"]["combined"]["bound"]


def test_a_failed_method_has_null_values_under_both_names(noisy_obs):
    from calib.formats.observations import Observations

    obs, _ = noisy_obs
    d = obs.document.model_dump(mode="json")
    d["frames"] = [f for f in d["frames"] if not f["phase"].startswith("lock")]
    e = calibrate(Observations.from_dict(d), ["legs"])["methods"]["legs"]
    assert not e["converged"] and "lock-1" in e["error"]
    assert e["parameters"] is None and e["combinations"] is None and e["combinations_std"] is None
    ResultDocument.model_validate(to_jsonable(calibrate(Observations.from_dict(d), ["legs"])))


def test_api_publishes_the_result_schema():
    from service.main import create_app

    spec = create_app().openapi()
    ok = spec["paths"]["/api/v1/runs/{run_id}/result"]["get"]["responses"]["200"]["content"]["application/json"]
    assert ok["schema"]["$ref"].endswith("/ResultDocument")
    entry = spec["components"]["schemas"]["MethodEntry"]["properties"]
    assert {"combinations", "combinations_std", "parameters", "std", "seven"} <= set(entry)
