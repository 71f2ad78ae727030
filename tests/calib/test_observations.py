import json
from pathlib import Path

import pytest

from calib.errors import InputError
from calib.formats.observations import FORMAT, Observations, json_schema

SCHEMA = Path(__file__).resolve().parents[2] / "calib" / "formats" / "schemas" / "observations-v1.schema.json"


def test_shipped_schema_is_current():
    assert json.loads(SCHEMA.read_text()) == json_schema()


def test_round_trip_keeps_extra_fields(noisy_obs, tmp_path):
    obs, _ = noisy_obs
    doc = obs.to_dict()
    doc["my_lab"] = {"operator": "ada"}
    doc["frames"][3]["note"] = "kept"
    doc["frames"][3]["legs"]["2"][0]["quality"] = {"rms_px": 0.2}
    p = tmp_path / "o.json"
    Observations.from_dict(doc).save(p)
    back = json.loads(p.read_text())
    assert back["my_lab"] == {"operator": "ada"}
    assert back["frames"][3]["note"] == "kept"
    assert back["frames"][3]["legs"]["2"][0]["quality"] == {"rms_px": 0.2}
    assert back["truth"] == doc["truth"]
    assert len(back["frames"]) == len(doc["frames"])


def _doc(noisy_obs):
    return json.loads(json.dumps(noisy_obs[0].to_dict()))


@pytest.mark.parametrize(
    ("mutate", "frame", "field", "text"),
    [
        (lambda d: d["frames"][5].update(q=[0.1, 0.2, 0.3]), 5, "q", "at least 4"),
        (lambda d: d["frames"][7].update(phase="spin"), 7, "phase", "rotation"),
        (lambda d: d["frames"][2]["board"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), 2, "board.R", "orthonormal"),
        (lambda d: d["frames"][9]["legs"]["3"][1].update(u=[0, 0, 0]), 9, "legs.3.1.u", "non-zero"),
        (lambda d: d["frames"][4]["legs"].update({"5": []}), 4, "legs.5", None),
        (lambda d: d["frames"][1]["board"].update(t=[0, "x", 0]), 1, "board.t.1", None),
    ],
)
def test_first_bad_field_is_reported_with_frame(noisy_obs, mutate, frame, field, text):
    d = _doc(noisy_obs)
    mutate(d)
    with pytest.raises(InputError) as ei:
        Observations.from_dict(d, source="obs.json")
    e = ei.value
    assert e.frame == frame
    assert e.field == field
    assert e.file == "obs.json"
    assert f"frame {frame}" in str(e)
    if text:
        assert text in str(e)


def test_missing_rod_is_null_not_dropped(noisy_obs):
    d = _doc(noisy_obs)
    d["frames"][0]["legs"]["1"][0] = None
    obs = Observations.from_dict(d)
    a = obs.arrays()
    assert not a.has_rod[0, 0, 0] and a.has_rod[0, 0, 1]
    assert obs.to_dict()["frames"][0]["legs"]["1"][0] is None


def test_wrong_format_and_bad_json(tmp_path):
    with pytest.raises(InputError, match="unsupported format"):
        Observations.from_dict({"format": "x", "nominal": {}, "frames": []})
    p = tmp_path / "bad.json"
    p.write_text("{ not json")
    with pytest.raises(InputError, match=r"bad\.json: not valid JSON"):
        Observations.load(p)
    with pytest.raises(InputError, match="file not found"):
        Observations.load(tmp_path / "nope.json")


def test_format_constant():
    assert FORMAT == "i4cal.observations/1"
